"""The envelope: one message <-> bytes (encode_message, decode_message; peek_projection_id and
peek_compact_code read a compact payload's header without decoding it).

Envelope (every message), a msgpack array:
    [schema_version, codec_version, type, sender, seq, profile, payload]
The payload of a map or submap is coded by mergesvc.wire.objects, of a compact factor by
mergesvc.wire.factors; other factors carry their JSON document (without `keyframe_a` /
`keyframe_b` when they are absent, so such a factor reads in decoders that predate them),
error messages [code, detail, about_seq].

Decoding never trusts a length: sizes are checked against `CodecLimits` before anything is
allocated, and every failure is a `DecodeError` (bytes) or `SchemaError` (version, content).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import msgpack
from pydantic import BaseModel

from mergesvc.core.model import SCHEMA_VERSION, ErrorMessage, Factor, ObjectMap, Submap
from mergesvc.errors import CodecError, DecodeError, MergeError, SchemaError, one_line
from mergesvc.wire.factors import decode_factor_compact, encode_factor_compact
from mergesvc.wire.fields import check_int, check_list, check_str, validate_model
from mergesvc.wire.objects import decode_objects, encode_objects
from mergesvc.wire.profiles import (
    DEFAULT_LIMITS,
    CodecLimits,
    CodecSettings,
    Envelope,
    MessageType,
    Profile,
)
from mergesvc.wire.projection import CompactCode, Projection

CODEC_VERSION = 1  # layout of envelope and payloads; bump on any incompatible change

# Wire codes: never renumber, only add.
_TYPE_CODE = {
    MessageType.SUBMAP: 1,
    MessageType.MAP: 2,
    MessageType.FACTOR: 3,
    MessageType.ERROR: 4,
    MessageType.RELOCALIZE_REQUEST: 5,
    MessageType.RELOCALIZE_REPLY: 6,
}
_PROFILE_CODE = {Profile.FULL: 0, Profile.F16: 1, Profile.INT8: 2, Profile.COMPACT: 3}
_CODE_TYPE = {v: k for k, v in _TYPE_CODE.items()}
_CODE_PROFILE = {v: k for k, v in _PROFILE_CODE.items()}
_RESERVED = {MessageType.RELOCALIZE_REQUEST, MessageType.RELOCALIZE_REPLY}

AnyMessage = ObjectMap | Factor | ErrorMessage


def parse_profile(profile: Profile | str) -> Profile:
    try:
        return Profile(profile)
    except ValueError:
        names = ", ".join(p.value for p in Profile)
        raise CodecError(f"unknown profile {profile!r}: one of {names}") from None


def message_type_of(model: BaseModel) -> MessageType:
    if isinstance(model, Submap):
        return MessageType.SUBMAP
    if isinstance(model, ObjectMap):
        return MessageType.MAP
    if isinstance(model, Factor):
        return MessageType.FACTOR
    if isinstance(model, ErrorMessage):
        return MessageType.ERROR
    raise CodecError(f"no message type for {type(model).__name__}")


def encode_message(
    model: AnyMessage,
    profile: Profile | str,
    sender: str,
    seq: int,
    *,
    projection: Projection | None = None,
    settings: CodecSettings | None = None,
    limits: CodecLimits = DEFAULT_LIMITS,
) -> bytes:
    """Encode a Submap, ObjectMap, Factor or ErrorMessage as one message.

    Factors are coded `compact` or exactly (any other profile); error messages are always
    exact. `projection` is required for object maps in `compact`.
    """
    profile = parse_profile(profile)
    settings = settings or CodecSettings()
    msg_type = message_type_of(model)
    if type(sender) is not str or not 1 <= len(sender) <= 128:
        raise CodecError("sender must be a robot id of 1..128 characters")
    if type(seq) is not int or not 0 <= seq < 2**63:
        raise CodecError("seq must be an integer in 0..2^63-1")
    if isinstance(model, ObjectMap):
        n, d = len(model.objects), model.dim
        if n > limits.max_objects or n * d > limits.max_values or d > limits.max_dim:
            raise CodecError(
                f"{n} objects x {d} dims exceeds the wire limits; send the map in parts"
            )
        payload: Any = encode_objects(model, profile, sender, seq, settings, projection)
    elif isinstance(model, Factor):
        if (model.keyframe_a is None) != (model.keyframe_b is None):  # model_copy skips checks
            raise CodecError("keyframe_a and keyframe_b go together")
        if profile is Profile.COMPACT:
            payload = encode_factor_compact(model, settings)
        else:
            profile = Profile.FULL
            # a factor without keyframes is the document it was before they existed
            none = {k for k in ("keyframe_a", "keyframe_b") if getattr(model, k) is None}
            payload = model.model_dump(mode="json", exclude=none or None)
    else:
        profile = Profile.FULL
        payload = [model.code, model.detail, model.about_seq]
    try:
        data = msgpack.packb(
            [
                SCHEMA_VERSION,
                CODEC_VERSION,
                _TYPE_CODE[msg_type],
                sender,
                seq,
                _PROFILE_CODE[profile],
                payload,
            ],
            use_bin_type=True,
        )
    except (OverflowError, ValueError) as exc:  # an integer msgpack cannot carry (>= 2^64)
        raise CodecError(f"cannot encode the {msg_type.value} message: {one_line(exc)}") from exc
    if len(data) > limits.max_message_bytes:
        raise CodecError(
            f"message of {len(data)} bytes exceeds the limit {limits.max_message_bytes}"
        )
    return data


def _unpack(data: Any, limits: CodecLimits) -> list:
    if not isinstance(data, bytes | bytearray | memoryview):
        raise DecodeError(f"a message must be bytes, got {type(data).__name__}")
    if len(data) > limits.max_message_bytes:
        raise DecodeError(
            f"message of {len(data)} bytes exceeds the limit {limits.max_message_bytes}"
        )
    if not data:
        raise DecodeError("empty message")
    try:
        obj = msgpack.unpackb(
            bytes(data),
            raw=False,
            strict_map_key=True,
            use_list=True,
            max_str_len=1 << 16,
            max_bin_len=limits.max_message_bytes,
            max_array_len=max(limits.max_objects, limits.max_correspondences, 64),
            max_map_len=64,
            max_ext_len=0,
        )
    except Exception as exc:  # foreign parser: map whatever it raises at the boundary
        raise DecodeError(f"not a valid msgpack message: {one_line(exc)}") from exc
    env = check_list(obj, "envelope", 7)
    version = check_int(env[0], "schema_version", 0, 2**31)
    if version != SCHEMA_VERSION:
        raise SchemaError(f"message schema_version {version}: this build reads {SCHEMA_VERSION}")
    codec = check_int(env[1], "codec_version", 0, 2**31)
    if codec != CODEC_VERSION:
        raise SchemaError(f"message codec_version {codec}: this build reads {CODEC_VERSION}")
    return env


def _compact_header(data: bytes, limits: CodecLimits) -> list | None:
    """The `[projection_id, budget_bits, step16]` header of a compact map/submap message with
    a 4-byte id; None for anything else."""
    env = _unpack(data, limits)
    if env[5] != _PROFILE_CODE[Profile.COMPACT] or env[2] not in (1, 2):
        return None
    try:
        hdr = env[6][12]
    except (TypeError, IndexError, KeyError):
        return None
    if type(hdr) is not list or len(hdr) != 3 or type(hdr[0]) is not bytes or len(hdr[0]) != 4:
        return None
    return hdr


def peek_projection_id(data: bytes, limits: CodecLimits = DEFAULT_LIMITS) -> str | None:
    """The projection id a compact map/submap message needs; None for anything else."""
    hdr = _compact_header(data, limits)
    return None if hdr is None else hdr[0].hex()


def peek_compact_code(data: bytes, limits: CodecLimits = DEFAULT_LIMITS) -> CompactCode | None:
    """How a compact map/submap message coded its embeddings; None for anything else (other
    profiles and types, a header out of range: decode_message says what is wrong)."""
    hdr = _compact_header(data, limits)
    if hdr is None:
        return None
    pid, budget, step16 = hdr
    if type(budget) is not int or type(step16) is not int:
        return None
    if not (0 <= budget <= 65535 and 1 <= step16 <= 240):
        return None
    return CompactCode(pid.hex(), budget, step16)


def peek_submap_header(data: bytes, limits: CodecLimits = DEFAULT_LIMITS
                       ) -> tuple[str, str | None, int | None] | None:
    """(sender, session, seq) a submap message's header names, read without validating its
    objects (a refusal's answer names the submap at fault); None when the bytes are not a
    submap message whose header reads. The seq is the payload's own, else the envelope's."""
    try:
        env = _unpack(data, limits)
        if _CODE_TYPE.get(check_int(env[2], "message type", 0, 255)) is not MessageType.SUBMAP:
            return None
        sender = check_str(env[3], "sender", max_len=128)
        seq: int | None = check_int(env[4], "seq", 0, 2**63 - 1)
        fields = check_list(env[6], "submap payload")
        session = check_str(fields[1], "session_id", max_len=128) if len(fields) > 2 else None
        if len(fields) > 2 and fields[2] is not None:
            own = check_int(fields[2], "seq", -1, 2**63 - 1)
            seq = None if own == -1 else own
    except (MergeError, IndexError, TypeError):
        return None
    return sender, session, seq


def decode_message(
    data: bytes,
    projections: Projection | Sequence[Projection] | Mapping[str, Projection] | None = None,
    limits: CodecLimits = DEFAULT_LIMITS,
) -> tuple[Envelope, AnyMessage]:
    """Decode and validate one message -> (envelope, model).

    Raises DecodeError (malformed bytes, unknown type, size limits, missing projection) or
    SchemaError (version mismatch, content the models reject); nothing else.
    """
    if isinstance(projections, Projection):
        projections = {projections.id: projections}
    elif projections is None:
        projections = {}
    elif not isinstance(projections, Mapping):
        projections = {p.id: p for p in projections}
    env = _unpack(data, limits)
    code = check_int(env[2], "message type", 0, 255)
    if code not in _CODE_TYPE:
        raise DecodeError(f"unknown message type {code}")
    msg_type = _CODE_TYPE[code]
    if msg_type in _RESERVED:
        raise DecodeError(f"message type {msg_type.value} is reserved, not handled by this build")
    sender = check_str(env[3], "sender", max_len=128)
    if not sender:
        raise DecodeError("sender: empty")
    seq = check_int(env[4], "seq", 0, 2**63 - 1)
    pcode = check_int(env[5], "profile", 0, 255)
    if pcode not in _CODE_PROFILE:
        raise DecodeError(f"unknown profile {pcode}")
    envelope = Envelope(SCHEMA_VERSION, msg_type, sender, seq, _CODE_PROFILE[pcode], len(data))
    payload = env[6]
    try:
        if msg_type in (MessageType.MAP, MessageType.SUBMAP):
            model, pid = decode_objects(payload, envelope, projections, limits)
            if pid is not None:
                envelope = dataclasses.replace(envelope, projection_id=pid)
            return envelope, model
        if msg_type is MessageType.FACTOR:
            if envelope.profile is Profile.COMPACT:
                return envelope, decode_factor_compact(payload, limits)
            if envelope.profile is not Profile.FULL:
                raise DecodeError(f"factors are not coded {envelope.profile.value}")
            if type(payload) is not dict:
                raise DecodeError("factor: expected a map")
            corr = payload.get("correspondences")
            if isinstance(corr, list) and len(corr) > limits.max_correspondences:
                raise DecodeError("factor: too many correspondences")
            return envelope, validate_model(Factor, payload, "decoded factor")
        code_, detail, about = check_list(payload, "error", 3)
        return envelope, validate_model(
            ErrorMessage, {"code": code_, "detail": detail, "about_seq": about}, "decoded error"
        )
    except (DecodeError, SchemaError):
        raise
    except (ValueError, TypeError, IndexError, KeyError, OverflowError) as exc:
        # last line of defence: a malformed field that slipped past the checks above
        raise DecodeError(f"malformed {msg_type.value} message: {one_line(exc)}") from exc


__all__ = [
    "CODEC_VERSION",
    "AnyMessage",
    "decode_message",
    "encode_message",
    "message_type_of",
    "parse_profile",
    "peek_compact_code",
    "peek_projection_id",
    "peek_submap_header",
]
