"""How mergesvc talks: bytes <-> models (the codec), Zenoh key expressions.

May import: mergesvc.core, mergesvc.errors. No sockets here beyond building a Zenoh config.
"""

from mergesvc.wire.codec import (
    CODEC_VERSION,
    CodecLimits,
    CodecSettings,
    MessageType,
    Profile,
    Projection,
    decode_file,
    decode_message,
    encode_file,
    encode_message,
)

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
]
