"""Wire codec (the encode / decode stage): models <-> msgpack bytes, with quantisation profiles.

Only this module turns models into bytes. `compact` is for acoustic links: every field is
bounded as in DCCL (a field in [min, max] at `resolution` costs ceil(log2((max - min) /
resolution + 1)) bits), and embeddings are transform-coded on a fleet-shared PCA `Projection`
with bits given to components by greedy reverse water-filling.

Envelope (every message), a msgpack array:
    [schema_version, codec_version, type, sender, seq, profile, payload]
Object map / submap payload, a msgpack array:
    [robot_id | nil (= sender), session_id, seq (nil: = envelope seq, -1: none), stamp, n, d,
     ids, labels, nobs_bits, var_mode, positions, variances, embeddings, blob (, up)]
(up, optional: the declared vertical as three int8 codes, direction only; absent = undeclared.
A decoder that predates it refuses a payload of 15 fields; one without `up` reads everywhere.)
where the small header fields say how to read `blob`, one bit stream (MSB first) holding, in
order: id deltas, label codes, n_obs - 1, isotropic flags, positions, variances, embeddings.
Profiles (what each carries per object; positions in full are float64, otherwise fixed point):

    profile   embedding                        variance                       position
    full      float32                          float32, as given              float64
    f16       float16                          log2, 16 bits, as given        fixed point
    int8      int8 + float32 scale per vector  log2, 8 bits, as given         fixed point
    compact   PCA coefficients, 0-8 bits each  mean only, log2, <= 1.1 %      fixed point

Fixed-point positions: 1 cm by default (CodecSettings), the range per axis taken from the data
and carried. Compact spends `embedding_bits` (400) per object on the coefficients.

Decoding never trusts a length: sizes are checked against `CodecLimits` before anything is
allocated, and every failure is a `DecodeError` (bytes) or `SchemaError` (version, content).
"""

from __future__ import annotations

import dataclasses
import hashlib
import heapq
import json
import logging
import math
import struct
import zipfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from mergesvc.core.model import (
    MAX_EMBEDDING_DIM,
    MAX_FILE_BYTES,
    SCHEMA_VERSION,
    ErrorMessage,
    Factor,
    ObjectArrays,
    ObjectMap,
    Submap,
    _format_validation_error,
)
from mergesvc.errors import CodecError, DecodeError, InputError, SchemaError

log = logging.getLogger(__name__)

CODEC_VERSION = 1  # layout of envelope and payloads; bump on any incompatible change
MAX_FIELD_BITS = 56  # widest bit field (any 56-bit field fits one 8-byte read at any offset)
MAX_ID_INT = 10**16  # `<prefix><integer>` ids are delta-coded below this
MAX_COEF_BITS = 8  # most bits one PCA coefficient can get
COMPACT_MAX_N_OBS = 255  # compact saturates n_obs here (a fusion weight, not an identity)
MAX_PROJECTION_FILE_BYTES = 256 * 2**20
PROJECTION_FILE = "projection-{id}.npz"  # name of a fitted projection saved by encode_file

# Max (1960): step of the MSE-optimal uniform quantiser of a unit Gaussian, by bits.
_MAX_STEP = {1: 1.596, 2: 0.9957, 3: 0.5860, 4: 0.3352, 5: 0.1881, 6: 0.1041, 7: 0.0569, 8: 0.0308}
_LOG_UNITS = 64  # log2 variances are carried in 1/64 octave
_LOG2_MIN, _LOG2_MAX = -126, 127  # variances must lie in [2^-126, 2^127] (float32 normal)
# factor std devs: log2 in [-32, 32) at 1/256 octave (14 bits, <= 0.14 % error)
_SIGMA_BITS, _SIGMA_PER_OCTAVE, _SIGMA_LOG2_MIN = 14, 256, -32
_CPC_BITS, _CPC_ATANH_MAX = 13, 5.0  # factor partial correlations: atanh in (-5, 5)
_QUAT_BITS = 15  # smallest-three quaternion components
_SCORE_BITS = 8
_NAN_OR_INF = "NaN or inf"


class Profile(str, Enum):
    """Quantisation profile of a message (see the module docstring)."""

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
_STATUS_CODE = {None: 0, "accepted": 1, "retracted": 2}
_CODE_STATUS = {v: k for k, v in _STATUS_CODE.items()}


@dataclass(frozen=True)
class CodecLimits:
    """What a decoder accepts. Larger messages are refused before anything is allocated;
    the encoder refuses to produce what a decoder with the default limits would refuse.

    max_values bounds objects x dims (4 M: a 10 000-object map of 384-d embeddings), which
    bounds the memory a small compact message can expand into (decompression bombs).
    """

    max_message_bytes: int = 16 * 2**20
    max_objects: int = 20_000
    max_dim: int = MAX_EMBEDDING_DIM
    max_values: int = 4_000_000
    max_correspondences: int = 10_000


DEFAULT_LIMITS = CodecLimits()


class CodecSettings(BaseModel):
    """Encoder settings; every choice the decoder needs is carried in the message."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    position_resolution_m: float = Field(
        0.01, ge=1e-6, le=1000, description="fixed-point step of object positions"
    )
    embedding_bits: int = Field(
        400, ge=0, le=65535, description="compact: bits per object for the PCA coefficients"
    )
    coef_step_scale: float = Field(
        1.5, gt=0, le=15, description="compact: quantiser step in units of Max's Gaussian step"
    )
    translation_resolution_m: float = Field(
        0.001, ge=1e-6, le=1000, description="compact factors: fixed-point step of T_a_b"
    )


@dataclass(frozen=True)
class Envelope:
    """What the envelope of a decoded message said."""

    schema_version: int
    msg_type: MessageType
    sender: str
    seq: int
    profile: Profile
    n_bytes: int
    projection_id: str | None = None


AnyMessage = ObjectMap | Factor | ErrorMessage


# ------------------------------------------------------------------ bit packing


def bits_for(max_value: int) -> int:
    """Bits of an unsigned field holding 0..max_value (0 bits: the field is constant)."""
    return int(max_value).bit_length()


def bounded_bits(lo: float, hi: float, resolution: float) -> int:
    """DCCL: a field in [lo, hi] at `resolution` costs ceil(log2((hi - lo) / resolution + 1))."""
    return bits_for(math.ceil((hi - lo) / resolution))


def zigzag(v: int) -> int:
    """Signed -> unsigned, small magnitudes stay small: 0, -1, 1, -2 -> 0, 1, 2, 3."""
    return 2 * v if v >= 0 else -2 * v - 1


def unzigzag(u: int) -> int:
    return u // 2 if u % 2 == 0 else -(u + 1) // 2


class BitWriter:
    """MSB-first bit packer: unsigned fields of 0..56 bits, and raw bytes at byte boundaries."""

    def __init__(self) -> None:
        self._done: list[bytes] = []
        self._bits: list[np.ndarray] = []
        self._pending = 0
        self.bit_length = 0

    def write(self, value: int, width: int) -> None:
        """One unsigned field, 0 <= value < 2**width."""
        if not 0 <= width <= MAX_FIELD_BITS or not 0 <= value < (1 << width):
            raise CodecError(f"value {value} does not fit a {width}-bit field")
        self.write_fields(np.array([value], dtype=np.uint64), np.array([width]))

    def write_fields(self, values: Any, widths: Any) -> None:
        """Fields in order; values (m,) unsigned ints, widths (m,) or one width for all."""
        v = np.asarray(values).ravel()
        if v.size == 0:
            return
        if v.dtype.kind not in "ui" or (v.dtype.kind == "i" and v.min() < 0):
            raise CodecError(f"bit fields must be unsigned integers, got {v.dtype}")
        v = v.astype(np.uint64)
        w = np.broadcast_to(np.asarray(widths, dtype=np.int64), v.shape).ravel()
        if w.min() < 0 or w.max() > MAX_FIELD_BITS:
            raise CodecError(f"bit field widths must be 0..{MAX_FIELD_BITS}")
        if np.any(v >> w.astype(np.uint64)):
            raise CodecError("a value does not fit its bit field")
        total = int(w.sum())
        if total == 0:
            return
        start = np.repeat(np.cumsum(w) - w, w)
        shift = np.repeat(w, w) - 1 - (np.arange(total) - start)
        self._bits.append(((np.repeat(v, w) >> shift.astype(np.uint64)) & 1).astype(np.uint8))
        self._pending += total
        self.bit_length += total

    def align(self) -> None:
        """Zero bits up to the next byte boundary."""
        pad = -self._pending % 8
        if pad:
            self._bits.append(np.zeros(pad, dtype=np.uint8))
            self._pending += pad
            self.bit_length += pad

    def write_bytes(self, data: bytes) -> None:
        """Raw bytes, after aligning to a byte boundary."""
        self.align()
        if self._bits:
            self._done.append(np.packbits(np.concatenate(self._bits)).tobytes())
            self._bits, self._pending = [], 0
        self._done.append(bytes(data))
        self.bit_length += 8 * len(data)

    def write_f32(self, x: float) -> None:
        self.write(struct.unpack(">I", struct.pack(">f", x))[0], 32)

    def getvalue(self) -> bytes:
        self.write_bytes(b"")
        return b"".join(self._done)


class BitReader:
    """Reads what BitWriter wrote; every over-read is a DecodeError naming `what`."""

    def __init__(self, data: bytes, what: str = "payload") -> None:
        self._data = bytes(data)
        self._buf = np.frombuffer(self._data + bytes(8), dtype=np.uint8)
        self._pos = 0
        self._what = what

    @property
    def remaining_bits(self) -> int:
        return 8 * len(self._data) - self._pos

    def _need(self, bits: int) -> None:
        if bits > self.remaining_bits:
            raise DecodeError(
                f"{self._what} truncated: needs {bits} more bits, {self.remaining_bits} left"
            )

    def read(self, width: int) -> int:
        return int(self.read_fields(np.array([width]))[0])

    def read_fields(self, widths: Any) -> np.ndarray:
        """Fields of the given widths (m,), in order, as uint64 (m,)."""
        w = np.asarray(widths, dtype=np.int64).ravel()
        if w.size == 0:
            return np.zeros(0, dtype=np.uint64)
        if w.min() < 0 or w.max() > MAX_FIELD_BITS:
            raise DecodeError(f"{self._what}: bit field width outside 0..{MAX_FIELD_BITS}")
        ends = np.cumsum(w)
        self._need(int(ends[-1]))
        offsets = self._pos + ends - w
        self._pos += int(ends[-1])
        # one big-endian 8-byte window per field; a 56-bit field at any bit offset fits in it
        byte = offsets >> 3
        v = np.zeros(w.size, dtype=np.uint64)
        for k in range(8):
            v = (v << np.uint64(8)) | self._buf[byte + k].astype(np.uint64)
        v <<= (offsets & 7).astype(np.uint64)
        shift = np.where(w == 0, 0, 64 - w).astype(np.uint64)
        return np.where(w == 0, np.uint64(0), v >> shift)

    def read_array(self, n: int, width: int) -> np.ndarray:
        """n fields of one width, uint64 (n,)."""
        self._need(n * width)
        return self.read_fields(np.full(n, width, dtype=np.int64))

    def align(self) -> None:
        pad = -self._pos % 8
        if pad and self.read(pad) != 0:
            raise DecodeError(f"{self._what}: padding bits are not zero")

    def read_bytes(self, n: int) -> bytes:
        self.align()
        self._need(8 * n)
        start = self._pos // 8
        self._pos += 8 * n
        return self._data[start : start + n]

    def read_f32(self) -> float:
        return struct.unpack(">f", struct.pack(">I", self.read(32)))[0]

    def finish(self) -> None:
        """Require the stream to end here (after zero padding to a byte)."""
        self.align()
        if self.remaining_bits:
            raise DecodeError(f"{self._what}: {self.remaining_bits // 8} unexpected trailing bytes")


# ------------------------------------------------------------------ projection


@dataclass(frozen=True, eq=False)
class Projection:
    """Fleet-shared PCA of embeddings: mean (d,), orthonormal basis (k, d), and the standard
    deviation of each coefficient over the data it was fitted on (k,), all float32.

    `id` is a short content hash (8 hex digits): a compact message names the projection it
    was coded with, and a decoder refuses a message whose projection it does not have.
    """

    mean_d: np.ndarray
    basis_kd: np.ndarray
    scale_k: np.ndarray
    id: str = field(init=False)

    def __post_init__(self) -> None:
        try:
            mean = np.ascontiguousarray(self.mean_d, dtype="<f4")
            basis = np.ascontiguousarray(self.basis_kd, dtype="<f4")
            scale = np.ascontiguousarray(self.scale_k, dtype="<f4")
        except (ValueError, TypeError) as exc:
            raise SchemaError(f"projection arrays must be numeric: {_one_line(exc)}") from exc
        if mean.ndim != 1 or not 1 <= mean.size <= MAX_EMBEDDING_DIM:
            raise SchemaError(f"projection mean must be (d,), d <= {MAX_EMBEDDING_DIM}")
        d = mean.size
        if basis.ndim != 2 or basis.shape[1] != d or not 1 <= basis.shape[0] <= d:
            raise SchemaError(f"projection basis must be (k, {d}) with 1 <= k <= {d}")
        if scale.shape != (basis.shape[0],):
            raise SchemaError(f"projection scale must be ({basis.shape[0]},)")
        for name, a in (("mean", mean), ("basis", basis), ("scale", scale)):
            if not np.all(np.isfinite(a)):
                raise SchemaError(f"projection {name} has {_NAN_OR_INF}")
        if np.any(scale <= 0):
            raise SchemaError("projection scale must be positive")
        gram = basis.astype(np.float64) @ basis.T.astype(np.float64)
        if np.abs(gram - np.eye(len(basis))).max() > 1e-4:
            raise SchemaError("projection basis rows must be orthonormal")
        for name, a in (("mean_d", mean), ("basis_kd", basis), ("scale_k", scale)):
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        h = hashlib.sha256(b"mergesvc-projection-1")
        h.update(struct.pack("<II", basis.shape[0], d))
        for a in (mean, basis, scale):
            h.update(a.tobytes())
        object.__setattr__(self, "id", h.hexdigest()[:8])
        object.__setattr__(self, "_alloc", {})

    @property
    def k(self) -> int:
        return self.basis_kd.shape[0]

    @property
    def dim(self) -> int:
        return self.mean_d.shape[0]

    @classmethod
    def fit(cls, embeddings_nd: Any, k: int | None = None) -> Projection:
        """PCA of (n, d) embeddings; keeps min(k, n - 1, d) components (fewer if the data
        has lower rank). Fit it on data the fleet already shares, not on what it will code."""
        E = np.asarray(embeddings_nd, dtype=np.float64)
        if E.ndim != 2 or E.shape[0] < 2 or not 1 <= E.shape[1] <= MAX_EMBEDDING_DIM:
            raise CodecError(f"a projection needs (n >= 2, d) embeddings, got {E.shape}")
        if not np.all(np.isfinite(E)):
            raise CodecError(f"embeddings have {_NAN_OR_INF}")
        mean = E.mean(axis=0)
        _, S, Vt = np.linalg.svd(E - mean, full_matrices=False)
        scale = S / math.sqrt(E.shape[0])  # std of each coefficient over the fit data
        rank = int(np.sum(scale > 1e-6 * scale[0])) if scale[0] > 0 else 0
        if rank == 0:
            raise CodecError("cannot fit a projection: all embeddings are identical")
        k = rank if k is None else min(int(k), rank)
        if k < 1:
            raise CodecError("a projection needs k >= 1")
        basis = Vt[:k]
        # a deterministic sign per component: the largest entry is positive
        basis = basis * np.sign(basis[np.arange(k), np.abs(basis).argmax(axis=1)])[:, None]
        return cls(mean, basis, scale[:k])

    def coefficients(self, embeddings_nd: np.ndarray) -> np.ndarray:
        """(n, d) -> (n, k): basis (e - mean)."""
        return (np.asarray(embeddings_nd, np.float64) - self.mean_d) @ self.basis_kd.T.astype(
            np.float64
        )

    def reconstruct(self, coeffs_nk: np.ndarray) -> np.ndarray:
        """(n, k) -> (n, d): mean + basis^T c."""
        return self.mean_d.astype(np.float64) + coeffs_nk @ self.basis_kd.astype(np.float64)

    def bit_allocation(self, budget_bits: int) -> np.ndarray:
        """Bits per component (k,) summing to min(budget, 8 k): greedy reverse water-filling,
        each bit to the component whose quantisation error is largest (std / 2^bits).
        Exact arithmetic on the stored float32 scales, so both ends agree bit for bit."""
        cache: dict[int, np.ndarray] = self._alloc  # type: ignore[attr-defined]
        if budget_bits not in cache:
            if len(cache) >= 8:  # budgets come from messages: keep the cache small
                cache.clear()
            bits = np.zeros(self.k, dtype=np.int64)
            heap = [(-float(s), j) for j, s in enumerate(self.scale_k)]
            heapq.heapify(heap)
            for _ in range(min(budget_bits, MAX_COEF_BITS * self.k)):
                neg, j = heapq.heappop(heap)
                bits[j] += 1
                if bits[j] < MAX_COEF_BITS:
                    heapq.heappush(heap, (neg / 2, j))
            bits.setflags(write=False)
            cache[budget_bits] = bits
        return cache[budget_bits]

    def save(self, path: Path | str) -> Path:
        """Write an .npz (mean, basis, scale, id); returns the path."""
        p = Path(path)
        try:
            with p.open("wb") as f:
                np.savez(
                    f,
                    mean=self.mean_d,
                    basis=self.basis_kd,
                    scale=self.scale_k,
                    id=np.array(self.id),
                    version=np.array(1),
                )
        except OSError as exc:
            raise InputError(f"cannot write {p}: {exc.strerror or exc}") from exc
        return p

    @classmethod
    def load(cls, path: Path | str) -> Projection:
        """Read and validate a projection file; its stored id must match its content."""
        p = Path(path)
        try:
            if p.stat().st_size > MAX_PROJECTION_FILE_BYTES:
                raise SchemaError(f"{p}: larger than {MAX_PROJECTION_FILE_BYTES} bytes")
            with np.load(p, allow_pickle=False) as z:
                arrays = {k: z[k] for k in ("mean", "basis", "scale", "id")}
        except OSError as exc:
            raise DecodeError(f"cannot read projection {p}: {exc.strerror or exc}") from exc
        except (ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
            raise DecodeError(f"{p} is not a projection file: {_one_line(exc)}") from exc
        proj = cls(arrays["mean"], arrays["basis"], arrays["scale"])
        if str(arrays["id"]) != proj.id:
            raise SchemaError(
                f"{p}: stored id {str(arrays['id'])!r} does not match its content ({proj.id})"
            )
        return proj


def _coef_step(bits: np.ndarray, step_scale: float) -> np.ndarray:
    """Quantiser step per component in units of its std (0 where no bits)."""
    return np.array([step_scale * _MAX_STEP[b] if b else 0.0 for b in bits])


def quantize_coefficients(
    coeffs_nk: np.ndarray, proj: Projection, budget_bits: int, step_scale: float
) -> np.ndarray:
    """Midrise uniform codes (n, k) of c_j / sigma_j with the allocated bits per component."""
    bits = proj.bit_allocation(budget_bits)
    step = np.where(bits > 0, _coef_step(bits, step_scale), 1.0)
    half = np.where(bits > 0, 1 << np.maximum(bits - 1, 0), 0)
    q = np.floor(coeffs_nk / proj.scale_k.astype(np.float64) / step) + half
    return np.clip(q, 0, (1 << bits) - 1).astype(np.uint64)


def dequantize_coefficients(
    codes_nk: np.ndarray, proj: Projection, budget_bits: int, step_scale: float
) -> np.ndarray:
    """Inverse of quantize_coefficients: bin centres; components without bits decode to 0."""
    bits = proj.bit_allocation(budget_bits)
    step = _coef_step(bits, step_scale) * proj.scale_k.astype(np.float64)
    half = np.where(bits > 0, 1 << np.maximum(bits - 1, 0), 0)
    return np.where(bits > 0, (codes_nk.astype(np.float64) - half + 0.5) * step, 0.0)


# ------------------------------------------------------------------ small field codecs


def _one_line(exc: BaseException | str) -> str:
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0]


def _int(v: Any, what: str, lo: int, hi: int) -> int:
    if type(v) is not int:
        raise DecodeError(f"{what}: expected an integer, got {type(v).__name__}")
    if not lo <= v <= hi:
        raise DecodeError(f"{what}: {v} outside {lo}..{hi}")
    return v


def _str(v: Any, what: str, optional: bool = False, max_len: int = 1024) -> str | None:
    if v is None and optional:
        return None
    if type(v) is not str:
        raise DecodeError(f"{what}: expected a string, got {type(v).__name__}")
    if len(v) > max_len:
        raise DecodeError(f"{what}: longer than {max_len} characters")
    return v


def _list(v: Any, what: str, length: int | None = None) -> list:
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


def _encode_ids(ids: Sequence[str], w: BitWriter) -> list:
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


def _decode_ids(hdr: Any, n: int, r: BitReader, what: str) -> list[str]:
    hdr = _list(hdr, what)
    kind = _int(hdr[0] if hdr else None, f"{what}.0", 0, 1)
    if kind == 0:
        ids = _list(hdr, what, 2)[1]
        ids = _list(ids, f"{what}.1", n)
        return [_str(s, f"{what}.1", max_len=128) for s in ids]  # type: ignore[misc]
    _, prefix, first, dmin, width = _list(hdr, what, 5)
    prefix = _str(prefix, f"{what}.prefix", max_len=128)
    first = _int(first, f"{what}.first", 0, MAX_ID_INT - 1)
    dmin = _int(dmin, f"{what}.delta_min", -MAX_ID_INT, MAX_ID_INT)
    width = _int(width, f"{what}.width", 0, MAX_FIELD_BITS)
    deltas = r.read_array(n - 1, width).astype(np.int64) + dmin
    ints = first + np.concatenate([[0], np.cumsum(deltas)])
    if ints.min() < 0 or ints.max() >= MAX_ID_INT:
        raise DecodeError(f"{what}: id numbers outside 0..{MAX_ID_INT - 1}")
    return [f"{prefix}{v}" for v in ints.tolist()]


def _log_range(values: np.ndarray) -> tuple[int, int]:
    """[lo, hi] of log2(values) in 1/64 octave, hi >= lo + 1."""
    lv = np.log2(values) * _LOG_UNITS
    lo = math.floor(float(lv.min()))
    return lo, max(math.ceil(float(lv.max())), lo + 1)


def _log_encode(values: np.ndarray, lo: int, hi: int, width: int) -> np.ndarray:
    levels = (1 << width) - 1
    code = np.rint((np.log2(values) * _LOG_UNITS - lo) / (hi - lo) * levels)
    return np.clip(code, 0, levels).astype(np.uint64)


def _log_decode(codes: np.ndarray, lo: int, hi: int, width: int) -> np.ndarray:
    levels = (1 << width) - 1
    return np.exp2((lo + codes.astype(np.float64) * (hi - lo) / levels) / _LOG_UNITS)


def _check_variances(v: np.ndarray) -> None:
    if v.size and (v.min() < 2.0**_LOG2_MIN or v.max() > 2.0**_LOG2_MAX):
        raise CodecError(
            f"variances must lie in [2^{_LOG2_MIN}, 2^{_LOG2_MAX}] to be encoded, "
            f"got {v.min():.3g}..{v.max():.3g}"
        )


def _raw(a: np.ndarray, dtype: str, what: str) -> bytes:
    with np.errstate(over="ignore"):
        out = np.ascontiguousarray(a, dtype=dtype)
    if out.dtype.kind == "f" and not np.all(np.isfinite(out)):
        raise CodecError(f"{what} overflow {np.dtype(dtype).name}: use a wider profile")
    return out.tobytes()


def _from_raw(r: BitReader, n: int, dtype: str, what: str) -> np.ndarray:
    a = np.frombuffer(r.read_bytes(n * np.dtype(dtype).itemsize), dtype=dtype)
    if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
        raise SchemaError(f"{what} has {_NAN_OR_INF}")
    return a.astype(np.float64) if a.dtype.kind == "f" else a


# ------------------------------------------------------------------ object maps


def _encode_objects(
    m: ObjectMap,
    profile: Profile,
    sender: str,
    seq: int,
    settings: CodecSettings,
    projection: Projection | None,
) -> list:
    # not m.arrays(): model_copy(update=...) carries the cached arrays of the original over
    arr = ObjectArrays.from_objects(m.objects)
    n, d = arr.n, arr.dim
    w = BitWriter()
    ids_hdr = _encode_ids(arr.ids, w)

    labels = [o.label for o in m.objects]
    label_hdr = None
    if any(lab is not None for lab in labels):
        table = sorted(set(labels), key=lambda s: (s is not None, s or ""))
        index = {lab: k for k, lab in enumerate(table)}
        w.write_fields(np.array([index[lab] for lab in labels]), bits_for(len(table) - 1))
        label_hdr = table

    n_obs = arr.n_obs.astype(np.int64)
    if profile is Profile.COMPACT:
        n_obs = np.minimum(n_obs, COMPACT_MAX_N_OBS)
    if n_obs.max() > 2**32:
        raise CodecError(f"n_obs {n_obs.max()} is larger than the wire limit 2^32")
    nobs_bits = bits_for(int(n_obs.max()) - 1)
    w.write_fields(n_obs - 1, nobs_bits)

    # variances: isotropic ones are one number, others one per dimension (compact: the mean)
    iso = np.array([not isinstance(o.variance, list) for o in m.objects])
    if profile is Profile.COMPACT:
        iso[:] = True
        var_iso, var_dim = arr.uncertainty_s, np.zeros((0, d))
    else:
        var_iso, var_dim = arr.variances_nd[iso, 0], arr.variances_nd[~iso]
    _check_variances(var_iso)
    _check_variances(var_dim)
    var_mode = 0 if iso.all() else 1 if not iso.any() else 2
    if var_mode == 2:
        w.write_fields(iso.astype(np.uint64), 1)

    pos_hdr = None
    if profile is Profile.FULL:
        w.write_bytes(_raw(arr.position_xyz_m, "<f8", "positions"))
    else:
        res_um = round(settings.position_resolution_m * 1e6)
        q_abs = np.rint(arr.position_xyz_m / (res_um / 1e6))
        if np.abs(q_abs).max() >= 2.0**53:
            raise CodecError("positions too far from the origin for the position resolution")
        origin = q_abs.min(axis=0).astype(np.int64)
        q = q_abs.astype(np.int64) - origin
        widths = [bits_for(int(x)) for x in q.max(axis=0)]
        if max(widths) > 32:
            raise CodecError(
                f"objects span more than 2^32 x {res_um} um: use a coarser position resolution"
            )
        w.write_fields(q.ravel(), np.tile(widths, n))
        pos_hdr = [res_um, *origin.tolist(), *widths]

    var_hdr = None
    if profile is Profile.FULL:
        w.write_bytes(_raw(var_iso, "<f4", "variances"))
        w.write_bytes(_raw(var_dim, "<f4", "variances"))
    else:
        both = np.concatenate([var_iso, var_dim.ravel()])
        lo, hi = _log_range(both)
        width = {Profile.F16: 16, Profile.INT8: 8}.get(profile)
        if width is None:  # compact: a step of at most 1/32 octave (<= 1.1 % error)
            width = max(1, bits_for(math.ceil((hi - lo) / 2)))
        w.write_fields(_log_encode(both, lo, hi, width), width)
        var_hdr = [lo, hi, width]

    emb_hdr = None
    E = arr.embeddings_nd
    if profile is Profile.FULL:
        w.write_bytes(_raw(E, "<f4", "embeddings"))
    elif profile is Profile.F16:
        w.write_bytes(_raw(E, "<f2", "embeddings"))
    elif profile is Profile.INT8:
        peak = np.abs(E).max(axis=1)
        scale = (peak / 127.0).astype("<f4")
        safe = np.where(scale > 0, scale.astype(np.float64), 1.0)[:, None]
        w.write_bytes(_raw(scale, "<f4", "int8 scales"))
        w.write_bytes(np.clip(np.rint(E / safe), -127, 127).astype("i1").tobytes())
    else:
        if projection is None:
            raise CodecError("the compact profile needs a projection (Projection.fit)")
        if projection.dim != d:
            raise CodecError(f"projection {projection.id} is {projection.dim}-d, objects {d}-d")
        budget = settings.embedding_bits
        step16 = max(1, round(settings.coef_step_scale * 16))
        codes = quantize_coefficients(projection.coefficients(E), projection, budget, step16 / 16)
        w.write_fields(codes.ravel(), np.tile(projection.bit_allocation(budget), n))
        emb_hdr = [bytes.fromhex(projection.id), budget, step16]

    seq_field = None  # maps have no seq; a submap's is usually the envelope's
    if isinstance(m, Submap) and m.seq != seq:
        seq_field = -1 if m.seq is None else m.seq
    tail = [] if m.up is None else [encode_up(m.up)]
    return [
        None if m.robot_id == sender else m.robot_id,
        m.session_id,
        seq_field,
        getattr(m, "stamp", None),
        n,
        d,
        ids_hdr,
        label_hdr,
        nobs_bits,
        var_mode,
        pos_hdr,
        var_hdr,
        emb_hdr,
        w.getvalue(),
        *tail,
    ]


def encode_up(up: Sequence[float]) -> list[int]:
    """A declared vertical as three int8 codes: round(127 u / max|u|) (about 0.5 deg)."""
    u = np.asarray(up, dtype=np.float64)
    if u.shape != (3,):
        raise CodecError(f"up must be a 3-vector, got shape {u.shape}")
    peak = float(np.abs(u).max())
    if not (np.isfinite(peak) and peak > 0):
        raise CodecError("up must be a finite non-zero vector")
    return np.rint(127.0 * u / peak).astype(int).tolist()


def decode_up(v: Any) -> tuple[float, float, float]:
    codes = [_int(x, "up", -127, 127) for x in _list(v, "up", 3)]
    norm = math.sqrt(sum(c * c for c in codes))
    if norm == 0:
        raise DecodeError("up: the zero vector has no direction")
    return (codes[0] / norm, codes[1] / norm, codes[2] / norm)


def _find_projection(pid: str, projections: Mapping[str, Projection], what: str) -> Projection:
    if pid not in projections:
        have = ", ".join(sorted(projections)) or "none"
        raise DecodeError(
            f"{what} was coded with projection {pid}, which this decoder does not have "
            f"(have: {have}); pass its projection file"
        )
    return projections[pid]


def _decode_objects(
    payload: Any,
    env: Envelope,
    projections: Mapping[str, Projection],
    limits: CodecLimits,
) -> tuple[ObjectMap, str | None]:
    what = f"{env.msg_type.value} payload"
    fields = _list(payload, what)
    if len(fields) not in (14, 15):  # the 15th, optional: the declared vertical
        raise DecodeError(f"{what}: expected 14 or 15 fields, got {len(fields)}")
    robot, session, seq, stamp, n, d, ids_hdr, label_hdr = fields[:8]
    nobs_bits, var_mode, pos_hdr, var_hdr, emb_hdr, blob = fields[8:14]
    up = decode_up(fields[14]) if len(fields) == 15 else None
    robot = _str(robot, "robot_id", optional=True, max_len=128) or env.sender
    session = _str(session, "session_id", max_len=128)
    if seq is not None:
        seq = _int(seq, "seq", -1, 2**63 - 1)
    if stamp is not None and type(stamp) is not float:
        raise DecodeError(f"stamp: expected a float, got {type(stamp).__name__}")
    n = _int(n, "objects", 1, limits.max_objects)
    d = _int(d, "embedding dimension", 1, limits.max_dim)
    if n * d > limits.max_values:
        raise DecodeError(f"{n} objects x {d} dims exceeds the limit {limits.max_values}")
    if type(blob) is not bytes:
        raise DecodeError(f"{what}: the object stream is not binary")
    profile = env.profile
    lossy = profile is not Profile.FULL
    if (pos_hdr is None) == lossy or (var_hdr is None) == lossy:
        raise DecodeError(f"{what}: header does not match profile {profile.value}")
    if (emb_hdr is None) == (profile is Profile.COMPACT):
        raise DecodeError(f"{what}: header does not match profile {profile.value}")
    r = BitReader(blob, what)

    ids = _decode_ids(ids_hdr, n, r, "ids")
    labels: list[str | None] = [None] * n
    if label_hdr is not None:
        table = _list(label_hdr, "labels")
        if not table or len(table) > n:
            raise DecodeError("labels: table must have 1..n entries")
        table = [_str(s, "labels", optional=True, max_len=128) for s in table]
        codes = r.read_array(n, bits_for(len(table) - 1))
        if codes.max() >= len(table):
            raise DecodeError("labels: code outside the table")
        labels = [table[c] for c in codes.tolist()]
    nobs_bits = _int(nobs_bits, "nobs_bits", 0, 32)
    n_obs = r.read_array(n, nobs_bits).astype(np.int64) + 1
    var_mode = _int(var_mode, "var_mode", 0, 2)
    iso = r.read_array(n, 1).astype(bool) if var_mode == 2 else np.full(n, var_mode == 0)
    if profile is Profile.COMPACT and var_mode != 0:
        raise DecodeError("compact carries one variance per object (var_mode must be 0)")
    n_iso, n_dim = int(iso.sum()), int((~iso).sum())

    if not lossy:
        pos = _from_raw(r, 3 * n, "<f8", "positions").reshape(n, 3)
    else:
        res_um, *origin_widths = _list(pos_hdr, "positions", 7)
        res_um = _int(res_um, "positions.resolution_um", 1, 10**9)
        origin = [_int(x, "positions.origin", -(2**53), 2**53) for x in origin_widths[:3]]
        widths = [_int(x, "positions.width", 0, 32) for x in origin_widths[3:]]
        q = r.read_fields(np.tile(widths, n)).reshape(n, 3).astype(np.int64)
        pos = (q + np.array(origin, dtype=np.int64)).astype(np.float64) * (res_um / 1e6)

    if not lossy:
        var_iso = _from_raw(r, n_iso, "<f4", "variances")
        var_dim = _from_raw(r, n_dim * d, "<f4", "variances").reshape(n_dim, d)
    else:
        lo, hi, width = _list(var_hdr, "variances", 3)
        lo = _int(lo, "variances.lo", _LOG2_MIN * _LOG_UNITS, _LOG2_MAX * _LOG_UNITS)
        hi = _int(hi, "variances.hi", lo + 1, _LOG2_MAX * _LOG_UNITS + 1)
        width = _int(width, "variances.width", 1, 16)
        both = _log_decode(r.read_array(n_iso + n_dim * d, width), lo, hi, width)
        var_iso, var_dim = both[:n_iso], both[n_iso:].reshape(n_dim, d)

    pid = None
    if profile is Profile.FULL:
        E = _from_raw(r, n * d, "<f4", "embeddings").reshape(n, d)
    elif profile is Profile.F16:
        E = _from_raw(r, n * d, "<f2", "embeddings").reshape(n, d)
    elif profile is Profile.INT8:
        scale = _from_raw(r, n, "<f4", "int8 scales")
        if scale.min() < 0:
            raise SchemaError("int8 scales must not be negative")
        E = _from_raw(r, n * d, "i1", "embeddings").reshape(n, d) * scale[:, None]
    else:
        pid_bytes, budget, step16 = _list(emb_hdr, "embeddings", 3)
        if type(pid_bytes) is not bytes or len(pid_bytes) != 4:
            raise DecodeError("embeddings: projection id must be 4 bytes")
        pid = pid_bytes.hex()
        proj = _find_projection(pid, projections, f"{env.msg_type.value} {env.seq}")
        if proj.dim != d:
            raise DecodeError(f"projection {pid} is {proj.dim}-d, the message says {d}")
        budget = _int(budget, "embeddings.bits", 0, 65535)
        step = _int(step16, "embeddings.step", 1, 240) / 16
        bits = proj.bit_allocation(budget)
        codes = r.read_fields(np.tile(bits, n)).reshape(n, proj.k)
        E = proj.reconstruct(dequantize_coefficients(codes, proj, budget, step))
    r.finish()

    objects = []
    k_dim = 0
    for i in range(n):
        if iso[i]:
            variance: float | list[float] = float(var_iso[i - k_dim])
        else:
            variance = var_dim[k_dim].tolist()
            k_dim += 1
        obj = {
            "id": ids[i],
            "position": pos[i].tolist(),
            "embedding": E[i].tolist(),
            "variance": variance,
            "n_obs": int(n_obs[i]),
        }
        if labels[i] is not None:
            obj["label"] = labels[i]
        objects.append(obj)
    doc: dict[str, Any] = {"robot_id": robot, "session_id": session, "objects": objects}
    if up is not None:
        doc["up"] = up
    model: type[ObjectMap] = ObjectMap
    if env.msg_type is MessageType.SUBMAP:
        model = Submap
        doc["seq"] = env.seq if seq is None else None if seq == -1 else seq
        doc["stamp"] = stamp
    elif seq is not None or stamp is not None:
        raise DecodeError("a map carries no seq or stamp")
    return _validate(model, doc, f"decoded {env.msg_type.value}"), pid


def _validate(model: type[BaseModel], doc: Any, what: str) -> Any:
    try:
        return model.model_validate(doc)
    except ValidationError as exc:
        raise SchemaError(_format_validation_error(exc, what)) from exc


# ------------------------------------------------------------------ factors


def quaternion_smallest_three(q_wxyz: Any) -> tuple[int, np.ndarray]:
    """(index of the largest |component|, the other three) with the largest made positive."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    q = q / np.linalg.norm(q)
    i = int(np.abs(q).argmax())
    if q[i] < 0:
        q = -q
    return i, np.delete(q, i)


def _cpc_from_correlation(R: np.ndarray) -> np.ndarray:
    """Canonical partial correlations z_ij (i > j), row-major (15,) for 6x6: any values in
    (-1, 1) map back to a valid correlation matrix (Lewandowski et al. 2009, LKJ)."""
    L = np.linalg.cholesky(R)
    z = []
    for i in range(1, len(R)):
        rem = 1.0
        for j in range(i):
            z.append(L[i, j] / math.sqrt(max(rem, 1e-300)))
            rem -= L[i, j] ** 2
    return np.clip(np.array(z), -1.0, 1.0)


def _correlation_from_cpc(z: np.ndarray, n: int = 6) -> np.ndarray:
    L = np.zeros((n, n))
    L[0, 0] = 1.0
    k = 0
    for i in range(1, n):
        rem = 1.0
        for j in range(i):
            L[i, j] = z[k] * math.sqrt(rem)
            rem -= L[i, j] ** 2
            k += 1
        L[i, i] = math.sqrt(max(rem, 0.0))
    R = L @ L.T
    return (R + R.T) / 2


def _encode_factor_compact(f: Factor, settings: CodecSettings) -> list:
    w = BitWriter()
    w.write(_STATUS_CODE[f.status.value if f.status else None], 2)
    res_um = round(settings.translation_resolution_m * 1e6)
    for x in f.T_a_b.translation:
        u = zigzag(round(x / (res_um / 1e6)))
        width = bits_for(u)
        if width > MAX_FIELD_BITS:
            raise CodecError("translation too large for the translation resolution")
        w.write(width, 6)
        w.write(u, width)
    i, rest = quaternion_smallest_three(f.T_a_b.quaternion_wxyz)
    levels = (1 << _QUAT_BITS) - 1
    w.write(i, 2)
    w.write_fields(
        np.rint((rest + math.sqrt(0.5)) / math.sqrt(2) * levels).clip(0, levels).astype(np.uint64),
        _QUAT_BITS,
    )
    C = np.array(f.covariance, dtype=np.float64)
    sigma = np.sqrt(np.diag(C))
    lsig = np.log2(sigma)
    if lsig.min() < _SIGMA_LOG2_MIN or lsig.max() >= -_SIGMA_LOG2_MIN:
        raise CodecError("covariance standard deviations must lie in [2^-32, 2^32)")
    w.write_fields(
        np.rint((lsig - _SIGMA_LOG2_MIN) * _SIGMA_PER_OCTAVE)
        .clip(0, (1 << _SIGMA_BITS) - 1)
        .astype(np.uint64),
        _SIGMA_BITS,
    )
    try:
        z = _cpc_from_correlation(C / np.outer(sigma, sigma))
    except np.linalg.LinAlgError as exc:
        raise CodecError("covariance is too close to singular to encode") from exc
    a = np.arctanh(np.clip(z, -1 + 1e-15, 1 - 1e-15))
    cells = 1 << _CPC_BITS
    codes = np.floor((a + _CPC_ATANH_MAX) / (2 * _CPC_ATANH_MAX) * cells).clip(0, cells - 1)
    w.write_fields(codes.astype(np.uint64), _CPC_BITS)
    ids = [None, None]
    corr = f.correspondences
    if corr:
        ids = [
            _encode_ids([c.object_a for c in corr], w),
            _encode_ids([c.object_b for c in corr], w),
        ]
        scores = np.array([c.score for c in corr])
        lo, hi = np.float32(scores.min()), np.float32(scores.max())
        if not (np.isfinite(lo) and np.isfinite(hi)):
            raise CodecError("correspondence scores overflow float32")
        w.write_f32(float(lo))
        w.write_f32(float(hi))
        span = float(hi) - float(lo)
        levels = (1 << _SCORE_BITS) - 1
        q = np.rint((scores - float(lo)) / span * levels) if span > 0 else np.zeros(len(corr))
        w.write_fields(q.clip(0, levels).astype(np.uint64), _SCORE_BITS if span > 0 else 0)
    return [
        f.factor_id,
        f.robot_a,
        f.session_a,
        f.robot_b,
        f.session_b,
        res_um,
        len(corr),
        *ids,
        w.getvalue(),
    ]


def _decode_factor_compact(payload: Any, limits: CodecLimits) -> Factor:
    (fid, ra, sa, rb, sb, res_um, n_corr, ids_a, ids_b, blob) = _list(payload, "factor", 10)
    res_um = _int(res_um, "factor.resolution_um", 1, 10**9)
    n_corr = _int(n_corr, "factor.correspondences", 0, limits.max_correspondences)
    if type(blob) is not bytes:
        raise DecodeError("factor: the pose stream is not binary")
    r = BitReader(blob, "factor")
    status = _CODE_STATUS.get(r.read(2), "invalid")
    t = []
    for _ in range(3):
        width = r.read(6)
        if width > MAX_FIELD_BITS:
            raise DecodeError("factor: translation field too wide")
        t.append(unzigzag(r.read(width)) * (res_um / 1e6))
    i = r.read(2)
    levels = (1 << _QUAT_BITS) - 1
    rest = r.read_array(3, _QUAT_BITS).astype(np.float64) / levels * math.sqrt(2) - math.sqrt(0.5)
    q = np.insert(rest, i, math.sqrt(max(0.0, 1.0 - float(rest @ rest))))
    q /= np.linalg.norm(q)
    sigma = np.exp2(
        r.read_array(6, _SIGMA_BITS).astype(np.float64) / _SIGMA_PER_OCTAVE + _SIGMA_LOG2_MIN
    )
    cells = 1 << _CPC_BITS
    a = (r.read_array(15, _CPC_BITS).astype(np.float64) + 0.5) / cells * 2 * _CPC_ATANH_MAX
    R = _correlation_from_cpc(np.tanh(a - _CPC_ATANH_MAX))
    C = R * np.outer(sigma, sigma)
    corr: list[dict[str, Any]] = []
    if n_corr:
        a_ids = _decode_ids(ids_a, n_corr, r, "factor.object_a")
        b_ids = _decode_ids(ids_b, n_corr, r, "factor.object_b")
        lo, hi = r.read_f32(), r.read_f32()
        if not (math.isfinite(lo) and math.isfinite(hi)) or hi < lo:
            raise DecodeError("factor: invalid score range")
        span = hi - lo
        codes = r.read_array(n_corr, _SCORE_BITS if span > 0 else 0).astype(np.float64)
        scores = lo + codes / ((1 << _SCORE_BITS) - 1) * span
        corr = [
            {"object_a": x, "object_b": y, "score": float(s)}
            for x, y, s in zip(a_ids, b_ids, scores)
        ]
    elif ids_a is not None or ids_b is not None:
        raise DecodeError("factor: ids given without correspondences")
    r.finish()
    if status == "invalid":
        raise DecodeError("factor: unknown status code")
    doc = {
        "factor_id": fid,
        "robot_a": ra,
        "session_a": sa,
        "robot_b": rb,
        "session_b": sb,
        "T_a_b": {"translation": t, "quaternion_wxyz": q.tolist()},
        "covariance": ((C + C.T) / 2).tolist(),
        "correspondences": corr,
        "status": status,
    }
    return _validate(Factor, doc, "decoded factor")


# ------------------------------------------------------------------ envelope


def _profile(profile: Profile | str) -> Profile:
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
    profile = _profile(profile)
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
        payload: Any = _encode_objects(model, profile, sender, seq, settings, projection)
    elif isinstance(model, Factor):
        if profile is Profile.COMPACT:
            payload = _encode_factor_compact(model, settings)
        else:
            profile = Profile.FULL
            payload = model.model_dump(mode="json")
    else:
        profile = Profile.FULL
        payload = [model.code, model.detail, model.about_seq]
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
        raise DecodeError(f"not a valid msgpack message: {_one_line(exc)}") from exc
    env = _list(obj, "envelope", 7)
    version = _int(env[0], "schema_version", 0, 2**31)
    if version != SCHEMA_VERSION:
        raise SchemaError(f"message schema_version {version}: this build reads {SCHEMA_VERSION}")
    codec = _int(env[1], "codec_version", 0, 2**31)
    if codec != CODEC_VERSION:
        raise SchemaError(f"message codec_version {codec}: this build reads {CODEC_VERSION}")
    return env


def peek_projection_id(data: bytes, limits: CodecLimits = DEFAULT_LIMITS) -> str | None:
    """The projection id a compact map/submap message needs; None for anything else."""
    env = _unpack(data, limits)
    if env[5] != _PROFILE_CODE[Profile.COMPACT] or env[2] not in (1, 2):
        return None
    try:
        pid = env[6][12][0]
    except (TypeError, IndexError, KeyError):
        return None
    return pid.hex() if type(pid) is bytes and len(pid) == 4 else None


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
    code = _int(env[2], "message type", 0, 255)
    if code not in _CODE_TYPE:
        raise DecodeError(f"unknown message type {code}")
    msg_type = _CODE_TYPE[code]
    if msg_type in _RESERVED:
        raise DecodeError(f"message type {msg_type.value} is reserved, not handled by this build")
    sender = _str(env[3], "sender", max_len=128)
    if not sender:
        raise DecodeError("sender: empty")
    seq = _int(env[4], "seq", 0, 2**63 - 1)
    pcode = _int(env[5], "profile", 0, 255)
    if pcode not in _CODE_PROFILE:
        raise DecodeError(f"unknown profile {pcode}")
    envelope = Envelope(SCHEMA_VERSION, msg_type, sender, seq, _CODE_PROFILE[pcode], len(data))
    payload = env[6]
    try:
        if msg_type in (MessageType.MAP, MessageType.SUBMAP):
            model, pid = _decode_objects(payload, envelope, projections, limits)
            if pid is not None:
                envelope = dataclasses.replace(envelope, projection_id=pid)
            return envelope, model
        if msg_type is MessageType.FACTOR:
            if envelope.profile is Profile.COMPACT:
                return envelope, _decode_factor_compact(payload, limits)
            if envelope.profile is not Profile.FULL:
                raise DecodeError(f"factors are not coded {envelope.profile.value}")
            if type(payload) is not dict:
                raise DecodeError("factor: expected a map")
            corr = payload.get("correspondences")
            if isinstance(corr, list) and len(corr) > limits.max_correspondences:
                raise DecodeError("factor: too many correspondences")
            return envelope, _validate(Factor, payload, "decoded factor")
        code_, detail, about = _list(payload, "error", 3)
        return envelope, _validate(
            ErrorMessage, {"code": code_, "detail": detail, "about_seq": about}, "decoded error"
        )
    except (DecodeError, SchemaError):
        raise
    except (ValueError, TypeError, IndexError, KeyError, OverflowError) as exc:
        # last line of defence: a malformed field that slipped past the checks above
        raise DecodeError(f"malformed {msg_type.value} message: {_one_line(exc)}") from exc


# ------------------------------------------------------------------ files


@dataclass(frozen=True)
class EncodeStats:
    msg_type: MessageType
    profile: Profile
    n_bytes: int
    n_objects: int
    bytes_per_object: float
    projection_id: str | None = None
    projection_path: Path | None = None  # a projection fitted and saved by encode_file


def _read_json_model(path: Path) -> AnyMessage:
    try:
        if path.stat().st_size > MAX_FILE_BYTES:
            raise SchemaError(f"{path}: larger than {MAX_FILE_BYTES} bytes")
        raw = json.loads(path.read_bytes())
    except OSError as exc:
        raise DecodeError(f"cannot read {path}: {exc.strerror or exc}") from exc
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DecodeError(f"{path} is not valid JSON: {_one_line(exc)}") from exc
    if not isinstance(raw, dict):
        raise SchemaError(f"invalid {path}: expected a JSON object")
    if "objects" in raw:
        model: type[BaseModel] = Submap if ("seq" in raw or "stamp" in raw) else ObjectMap
    elif "factor_id" in raw:
        model = Factor
    elif "code" in raw:
        model = ErrorMessage
    else:
        raise SchemaError(f"invalid {path}: not a map, submap, factor or error message")
    return _validate(model, raw, str(path))


def _projection_arg(projection: Projection | Path | str | None) -> Projection | None:
    if projection is None or isinstance(projection, Projection):
        return projection
    return Projection.load(projection)


def encode_file(
    in_json_path: Path | str,
    out_bin_path: Path | str,
    profile: Profile | str,
    projection: Projection | Path | str | None = None,
    *,
    sender: str | None = None,
    seq: int | None = None,
    settings: CodecSettings | None = None,
) -> EncodeStats:
    """Encode a map / submap / factor JSON file into one message file.

    A JSON object with `objects` is a submap if it has `seq` or `stamp`, else a map. sender
    defaults to the robot id (robot_a for factors), seq to the submap's seq (else 0).
    For `compact` maps without a projection, one is fitted on the file's own embeddings and
    saved beside the output as `projection-<id>.npz`, where decode_file finds it.
    """
    out = Path(out_bin_path)
    profile = _profile(profile)
    model = _read_json_model(Path(in_json_path))
    proj = _projection_arg(projection)
    saved = None
    if isinstance(model, ObjectMap) and profile is Profile.COMPACT and proj is None:
        proj = Projection.fit(model.arrays().embeddings_nd)
        saved = proj.save(out.parent / PROJECTION_FILE.format(id=proj.id))
        log.info("fitted projection %s (k=%d) saved to %s", proj.id, proj.k, saved)
    if sender is None:
        sender = model.robot_a if isinstance(model, Factor) else getattr(model, "robot_id", "")
        sender = sender or "unknown"
    if seq is None:
        seq = getattr(model, "seq", None) or 0
    data = encode_message(model, profile, sender, seq, projection=proj, settings=settings)
    try:
        out.write_bytes(data)
    except OSError as exc:
        raise InputError(f"cannot write {out}: {exc.strerror or exc}") from exc
    is_map = isinstance(model, ObjectMap)
    n = len(model.objects) if is_map else 0
    used_proj = proj if is_map and profile is Profile.COMPACT else None
    exact = not is_map and not (isinstance(model, Factor) and profile is Profile.COMPACT)
    return EncodeStats(
        msg_type=message_type_of(model),
        profile=Profile.FULL if exact else profile,
        n_bytes=len(data),
        n_objects=n,
        bytes_per_object=len(data) / n if n else float(len(data)),
        projection_id=used_proj.id if used_proj else None,
        projection_path=saved,
    )


def decode_file(
    in_bin_path: Path | str,
    out_json_path: Path | str,
    projection: Projection | Path | str | None = None,
    *,
    limits: CodecLimits = DEFAULT_LIMITS,
) -> tuple[Envelope, AnyMessage]:
    """Decode one message file and write the model as JSON (loadable with load_model).

    A compact map needs its projection: the one given, else `projection-<id>.npz` beside
    the input."""
    src = Path(in_bin_path)
    try:
        if src.stat().st_size > limits.max_message_bytes:
            raise DecodeError(f"{src}: larger than {limits.max_message_bytes} bytes")
        data = src.read_bytes()
    except OSError as exc:
        raise DecodeError(f"cannot read {src}: {exc.strerror or exc}") from exc
    proj = _projection_arg(projection)
    if proj is None:
        pid = peek_projection_id(data, limits)
        if pid is not None:
            beside = src.parent / PROJECTION_FILE.format(id=pid)
            if not beside.exists():
                raise DecodeError(
                    f"{src} was coded with projection {pid}: {beside} not found; "
                    "pass --projection FILE"
                )
            proj = Projection.load(beside)
    envelope, model = decode_message(data, proj, limits)
    out = Path(out_json_path)
    try:
        out.write_text(model.model_dump_json())
    except OSError as exc:
        raise InputError(f"cannot write {out}: {exc.strerror or exc}") from exc
    return envelope, model


__all__ = [
    "CODEC_VERSION",
    "DEFAULT_LIMITS",
    "PROJECTION_FILE",
    "BitReader",
    "BitWriter",
    "CodecLimits",
    "CodecSettings",
    "EncodeStats",
    "Envelope",
    "MessageType",
    "Profile",
    "Projection",
    "bits_for",
    "bounded_bits",
    "decode_file",
    "decode_message",
    "dequantize_coefficients",
    "encode_file",
    "encode_message",
    "message_type_of",
    "peek_projection_id",
    "quantize_coefficients",
    "quaternion_smallest_three",
    "unzigzag",
    "zigzag",
]
