"""Small field codecs shared by the payload codecs, and the checks a decoder applies.

Delta-coded `<prefix><integer>` ids (strings otherwise), log2-coded variances, raw
little-endian arrays, the type-and-range checks of msgpack fields (`check_int`, `check_str`,
`check_list`: every failure a `DecodeError`), and pydantic validation of a decoded document
(`validate_model`: a `SchemaError`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from pydantic import BaseModel, ValidationError

from mergesvc.core.model import _format_validation_error
from mergesvc.errors import CodecError, DecodeError, SchemaError
from mergesvc.wire.bits import MAX_FIELD_BITS, BitReader, BitWriter, bits_for

MAX_ID_INT = 10**16  # `<prefix><integer>` ids are delta-coded below this
LOG_UNITS = 64  # log2 variances are carried in 1/64 octave
LOG2_MIN, LOG2_MAX = -126, 127  # variances must lie in [2^-126, 2^127] (float32 normal)
NAN_OR_INF = "NaN or inf"


def check_int(v: Any, what: str, lo: int, hi: int) -> int:
    if type(v) is not int:
        raise DecodeError(f"{what}: expected an integer, got {type(v).__name__}")
    if not lo <= v <= hi:
        raise DecodeError(f"{what}: {v} outside {lo}..{hi}")
    return v


def check_str(v: Any, what: str, optional: bool = False, max_len: int = 1024) -> str | None:
    if v is None and optional:
        return None
    if type(v) is not str:
        raise DecodeError(f"{what}: expected a string, got {type(v).__name__}")
    if len(v) > max_len:
        raise DecodeError(f"{what}: longer than {max_len} characters")
    return v


def check_list(v: Any, what: str, length: int | None = None) -> list:
    if type(v) is not list:
        raise DecodeError(f"{what}: expected an array, got {type(v).__name__}")
    if length is not None and len(v) != length:
        raise DecodeError(f"{what}: expected {length} elements, got {len(v)}")
    return v


def _split_ids(ids: Sequence[str]) -> tuple[str, list[int]] | None:
    """`<prefix><integer>` ids sharing one prefix (no leading zeros) -> (prefix, ints)."""
    prefix: str | None = None
    ints = []
    for s in ids:
        stem = s.rstrip("0123456789")
        digits = s[len(stem) :]
        if not digits or (len(digits) > 1 and digits[0] == "0") or len(digits) > 16:
            return None
        if prefix is None:
            prefix = stem
        elif stem != prefix:
            return None
        value = int(digits)
        if value >= MAX_ID_INT:
            return None
        ints.append(value)
    return (prefix or "", ints) if prefix is not None else None


def encode_ids(ids: Sequence[str], w: BitWriter) -> list:
    """Header [1, prefix, first, delta_min, width] + deltas in the stream; else [0, ids]."""
    split = _split_ids(ids)
    if split is None:
        return [0, list(ids)]
    prefix, ints = split
    deltas = np.diff(np.array(ints, dtype=np.int64))
    dmin = int(deltas.min()) if deltas.size else 0
    width = bits_for(int((deltas - dmin).max())) if deltas.size else 0
    w.write_fields(deltas - dmin, width)
    return [1, prefix, ints[0], dmin, width]


def decode_ids(hdr: Any, n: int, r: BitReader, what: str) -> list[str]:
    hdr = check_list(hdr, what)
    kind = check_int(hdr[0] if hdr else None, f"{what}.0", 0, 1)
    if kind == 0:
        ids = check_list(hdr, what, 2)[1]
        ids = check_list(ids, f"{what}.1", n)
        return [check_str(s, f"{what}.1", max_len=128) for s in ids]  # type: ignore[misc]
    _, prefix, first, dmin, width = check_list(hdr, what, 5)
    prefix = check_str(prefix, f"{what}.prefix", max_len=128)
    first = check_int(first, f"{what}.first", 0, MAX_ID_INT - 1)
    dmin = check_int(dmin, f"{what}.delta_min", -MAX_ID_INT, MAX_ID_INT)
    width = check_int(width, f"{what}.width", 0, MAX_FIELD_BITS)
    deltas = r.read_array(n - 1, width).astype(np.int64) + dmin
    ints = first + np.concatenate([[0], np.cumsum(deltas)])
    if ints.min() < 0 or ints.max() >= MAX_ID_INT:
        raise DecodeError(f"{what}: id numbers outside 0..{MAX_ID_INT - 1}")
    return [f"{prefix}{v}" for v in ints.tolist()]


def log_range(values: np.ndarray) -> tuple[int, int]:
    """[lo, hi] of log2(values) in 1/64 octave, hi >= lo + 1."""
    lv = np.log2(values) * LOG_UNITS
    lo = math.floor(float(lv.min()))
    return lo, max(math.ceil(float(lv.max())), lo + 1)


def log_encode(values: np.ndarray, lo: int, hi: int, width: int) -> np.ndarray:
    levels = (1 << width) - 1
    code = np.rint((np.log2(values) * LOG_UNITS - lo) / (hi - lo) * levels)
    return np.clip(code, 0, levels).astype(np.uint64)


def log_decode(codes: np.ndarray, lo: int, hi: int, width: int) -> np.ndarray:
    levels = (1 << width) - 1
    return np.exp2((lo + codes.astype(np.float64) * (hi - lo) / levels) / LOG_UNITS)


def check_variances(v: np.ndarray) -> None:
    """Variances the wire can carry (float32 normal numbers). Outside, the input is at fault
    (a map's variance of 1e300 is valid JSON): SchemaError, as for any other bad value."""
    if v.size and (v.min() < 2.0**LOG2_MIN or v.max() > 2.0**LOG2_MAX):
        raise SchemaError(
            f"variances must lie in [2^{LOG2_MIN}, 2^{LOG2_MAX}] to be encoded, "
            f"got {v.min():.3g}..{v.max():.3g}"
        )


def to_raw(a: np.ndarray, dtype: str, what: str) -> bytes:
    with np.errstate(over="ignore"):
        out = np.ascontiguousarray(a, dtype=dtype)
    if out.dtype.kind == "f" and not np.all(np.isfinite(out)):
        raise CodecError(f"{what} overflow {np.dtype(dtype).name}: use a wider profile")
    return out.tobytes()


def from_raw(r: BitReader, n: int, dtype: str, what: str) -> np.ndarray:
    a = np.frombuffer(r.read_bytes(n * np.dtype(dtype).itemsize), dtype=dtype)
    if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
        raise SchemaError(f"{what} has {NAN_OR_INF}")
    return a.astype(np.float64) if a.dtype.kind == "f" else a


def validate_model(model: type[BaseModel], doc: Any, what: str) -> Any:
    try:
        return model.model_validate(doc)
    except ValidationError as exc:
        raise SchemaError(_format_validation_error(exc, what)) from exc


__all__ = [
    "LOG2_MAX",
    "LOG2_MIN",
    "LOG_UNITS",
    "MAX_ID_INT",
    "NAN_OR_INF",
    "check_int",
    "check_list",
    "check_str",
    "check_variances",
    "decode_ids",
    "encode_ids",
    "from_raw",
    "log_decode",
    "log_encode",
    "log_range",
    "to_raw",
    "validate_model",
]
