"""How mergesvc talks: bytes <-> models (the codec), Zenoh key expressions.

The codec (the encode / decode stage) turns models into msgpack bytes with quantisation
profiles; only this package turns models into bytes. Modules, bottom up: `bits` (the bit
packer), `fields` (small field codecs and decoder checks), `projection` (the fleet-shared PCA
of embeddings), `profiles` (Profile, MessageType, CodecSettings, CodecLimits, Envelope),
`objects` (map / submap payloads), `factors` (the compact factor codec), `envelope`
(encode_message / decode_message), `files` (encode_file / decode_file, load_model for
`match`'s JSON files), `mapfile` (binary map files, memory-mapped), `golden` (the protocol's
golden test vectors, docs/wire.md); `keys`
holds every Zenoh key expression; `session` builds a Zenoh config from the shared flags.

May import: mergesvc.core, mergesvc.errors. No sockets here beyond building a Zenoh config.
"""

import importlib
import typing

# name -> its module, imported on first use (PEP 562): `mergesvc.wire.names` and the command
# line's help need none of the codec
_WHERE = {
    **dict.fromkeys(("CODEC_VERSION", "decode_message", "encode_message"),
                    "mergesvc.wire.envelope"),
    **dict.fromkeys(("decode_file", "encode_file", "load_model"), "mergesvc.wire.files"),
    **dict.fromkeys(("CodecLimits", "CodecSettings"), "mergesvc.wire.profiles"),
    **dict.fromkeys(("MessageType", "Profile"), "mergesvc.wire.names"),
    "Projection": "mergesvc.wire.projection",
    **dict.fromkeys(("load_arrays", "save_arrays"), "mergesvc.wire.mapfile"),
}


def __getattr__(name: str) -> typing.Any:
    where = _WHERE.get(name)
    if where is None:
        raise AttributeError(f"module 'mergesvc.wire' has no attribute {name!r}")
    value = getattr(importlib.import_module(where), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(__all__)


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
    "load_arrays",
    "load_model",
    "save_arrays",
]
