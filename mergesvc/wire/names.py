"""The wire's fixed vocabularies, without the codec: what the command line names."""

from __future__ import annotations

from enum import Enum


class Profile(str, Enum):
    """Quantisation profile of a message (see mergesvc.wire.profiles)."""

    FULL = "full"
    F16 = "f16"
    INT8 = "int8"
    COMPACT = "compact"


class MessageType(str, Enum):
    SUBMAP = "submap"
    MAP = "map"
    FACTOR = "factor"
    ERROR = "error"
    RELOCALIZE_REQUEST = "relocalize_request"  # reserved: no model yet
    RELOCALIZE_REPLY = "relocalize_reply"  # reserved: no model yet


__all__ = ["MessageType", "Profile"]
