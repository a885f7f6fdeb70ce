"""How mergesvc talks: bytes <-> models (the codec), Zenoh key expressions.

The codec (the encode / decode stage) turns models into msgpack bytes with quantisation
profiles; only this package turns models into bytes. Modules, bottom up: `bits` (the bit
packer), `fields` (small field codecs and decoder checks), `projection` (the fleet-shared PCA
of embeddings), `profiles` (Profile, MessageType, CodecSettings, CodecLimits, Envelope),
`objects` (map / submap payloads), `factors` (the compact factor codec), `envelope`
(encode_message / decode_message), `files` (encode_file / decode_file, load_model for
`match`'s JSON files), `golden` (the protocol's golden test vectors, docs/wire.md); `keys`
holds every Zenoh key expression; `session` builds a Zenoh config from the shared flags.

May import: mergesvc.core, mergesvc.errors. No sockets here beyond building a Zenoh config.
"""

from mergesvc.wire.envelope import CODEC_VERSION, decode_message, encode_message
from mergesvc.wire.files import decode_file, encode_file, load_model
from mergesvc.wire.profiles import CodecLimits, CodecSettings, MessageType, Profile
from mergesvc.wire.projection import Projection

__all__ = [
    "CODEC_VERSION",
    "CodecLimits",
    "CodecSettings",
    "MessageType",
    "Profile",
    "Projection",
    "decode_file",
    "decode_message",
    "encode_file",
    "encode_message",
    "load_model",
]
