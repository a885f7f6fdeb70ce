"""The compact factor codec (FACTOR messages in `compact`; other profiles carry the JSON), and
the pose / covariance bit fields it shares with the submap odometry (mergesvc.wire.objects).

Compact factor payload, a msgpack array:
    [factor_id, robot_a, session_a, robot_b, session_b, resolution_um, n_correspondences,
     ids_a, ids_b, blob (, keyframe_a, keyframe_b)]
where `blob` is one bit stream (MSB first) holding, in order: the status code; per translation
axis a 6-bit width and the zigzag fixed-point value; the rotation as smallest three quaternion
components; the covariance as six log2 standard deviations and the 15 canonical partial
correlations of its correlation matrix (any codes decode to a valid covariance); then, with
correspondences, id deltas of both sides and the scores (float32 range, 8 bits each).
keyframe_a, keyframe_b (optional, both or neither: a pose-level factor) are msgpack unsigned
integers; a factor without them is 10 fields, byte-identical to before they existed, and a
decoder that predates them refuses a payload of 12 fields.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from mergesvc.core.model import Factor
from mergesvc.errors import CodecError, DecodeError
from mergesvc.wire.bits import MAX_FIELD_BITS, BitReader, BitWriter, bits_for, unzigzag, zigzag
from mergesvc.wire.fields import check_int, check_list, decode_ids, encode_ids, validate_model
from mergesvc.wire.profiles import CodecLimits, CodecSettings

_CPC_BITS, _CPC_ATANH_MAX = 13, 5.0  # factor partial correlations: atanh in (-5, 5)
QUAT_BITS = 15  # smallest-three quaternion components: rotation error <= 1.5e-4 rad
_SCORE_BITS = 8
MAX_KEYFRAME = 2**63 - 1  # keyframes travel as msgpack integers

# Wire codes: never renumber, only add.
_STATUS_CODE = {None: 0, "accepted": 1, "retracted": 2}
_CODE_STATUS = {v: k for k, v in _STATUS_CODE.items()}


@dataclass(frozen=True)
class SigmaCode:
    """Standard deviations as log2 codes of `bits` bits, `per_octave` steps per octave from
    2^log2_min: the range is [2^log2_min, 2^(log2_min + 2^bits / per_octave)), the relative
    error at most 2^(1 / (2 per_octave)) - 1."""

    bits: int
    per_octave: int
    log2_min: int

    @property
    def log2_max(self) -> float:
        return self.log2_min + (1 << self.bits) / self.per_octave


FACTOR_SIGMA = SigmaCode(14, 256, -32)  # [2^-32, 2^32) at 1/256 octave, <= 0.14 % error


def quaternion_smallest_three(q_wxyz: Any) -> tuple[int, np.ndarray]:
    """(index of the largest |component|, the other three) with the largest made positive."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    q = q / np.linalg.norm(q)
    i = int(np.abs(q).argmax())
    if q[i] < 0:
        q = -q
    return i, np.delete(q, i)


def write_translation(w: BitWriter, t: Any, res_um: int, what: str) -> None:
    """Per axis a 6-bit width and the zigzag fixed-point value at res_um micrometres
    (error <= res / 2 per axis)."""
    for x in t:
        u = zigzag(round(x / (res_um / 1e6)))
        width = bits_for(u)
        if width > MAX_FIELD_BITS:
            raise CodecError(f"{what} too large for the translation resolution")
        w.write(width, 6)
        w.write(u, width)


def read_translation(r: BitReader, res_um: int, what: str) -> list[float]:
    t = []
    for _ in range(3):
        width = r.read(6)
        if width > MAX_FIELD_BITS:
            raise DecodeError(f"{what}: translation field too wide")
        t.append(unzigzag(r.read(width)) * (res_um / 1e6))
    return t


def write_rotation(w: BitWriter, q_wxyz: Any) -> None:
    """Smallest three: the index of the largest component (2 bits), the others (15 bits each)."""
    i, rest = quaternion_smallest_three(q_wxyz)
    levels = (1 << QUAT_BITS) - 1
    w.write(i, 2)
    w.write_fields(
        np.rint((rest + math.sqrt(0.5)) / math.sqrt(2) * levels).clip(0, levels).astype(np.uint64),
        QUAT_BITS,
    )


def read_rotation(r: BitReader) -> list[float]:
    """A unit quaternion [w, x, y, z] (any codes decode to one)."""
    i = r.read(2)
    levels = (1 << QUAT_BITS) - 1
    rest = r.read_array(3, QUAT_BITS).astype(np.float64) / levels * math.sqrt(2) - math.sqrt(0.5)
    q = np.insert(rest, i, math.sqrt(max(0.0, 1.0 - float(rest @ rest))))
    return (q / np.linalg.norm(q)).tolist()


def write_sigmas(
    w: BitWriter, C: np.ndarray, code: SigmaCode, what: str = "covariance"
) -> np.ndarray:
    """The six standard deviations sqrt(diag C) as log2 codes; returns them."""
    sigma = np.sqrt(np.diag(C))
    lsig = np.log2(sigma)
    if lsig.min() < code.log2_min or lsig.max() >= code.log2_max:
        raise CodecError(
            f"{what} standard deviations must lie in [2^{code.log2_min}, "
            f"2^{code.log2_max:g}) to be encoded"
        )
    w.write_fields(
        np.rint((lsig - code.log2_min) * code.per_octave)
        .clip(0, (1 << code.bits) - 1)
        .astype(np.uint64),
        code.bits,
    )
    return sigma


def read_sigmas(r: BitReader, code: SigmaCode) -> np.ndarray:
    return np.exp2(r.read_array(6, code.bits).astype(np.float64) / code.per_octave + code.log2_min)


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


def write_covariance(w: BitWriter, covariance: Any, what: str = "covariance") -> None:
    """6x6 SPD covariance: FACTOR_SIGMA standard deviations, then the 15 canonical partial
    correlations (13 bits each, atanh-uniform); any codes decode to a valid covariance."""
    C = np.array(covariance, dtype=np.float64)
    sigma = write_sigmas(w, C, FACTOR_SIGMA, what)
    try:
        z = _cpc_from_correlation(C / np.outer(sigma, sigma))
    except np.linalg.LinAlgError as exc:
        raise CodecError(f"{what} is too close to singular to encode") from exc
    a = np.arctanh(np.clip(z, -1 + 1e-15, 1 - 1e-15))
    cells = 1 << _CPC_BITS
    codes = np.floor((a + _CPC_ATANH_MAX) / (2 * _CPC_ATANH_MAX) * cells).clip(0, cells - 1)
    w.write_fields(codes.astype(np.uint64), _CPC_BITS)


def read_covariance(r: BitReader) -> list[list[float]]:
    """What write_covariance wrote: symmetric, positive definite."""
    sigma = read_sigmas(r, FACTOR_SIGMA)
    cells = 1 << _CPC_BITS
    a = (r.read_array(15, _CPC_BITS).astype(np.float64) + 0.5) / cells * 2 * _CPC_ATANH_MAX
    R = _correlation_from_cpc(np.tanh(a - _CPC_ATANH_MAX))
    C = R * np.outer(sigma, sigma)
    return ((C + C.T) / 2).tolist()


def check_keyframe(k: int, what: str) -> int:
    """Encoder side: a keyframe index must fit the wire's integer."""
    if not 0 <= k <= MAX_KEYFRAME:
        raise CodecError(f"{what} {k} outside the wire range 0..2^63-1")
    return k


def encode_factor_compact(f: Factor, settings: CodecSettings) -> list:
    w = BitWriter()
    w.write(_STATUS_CODE[f.status.value if f.status else None], 2)
    res_um = round(settings.translation_resolution_m * 1e6)
    write_translation(w, f.T_a_b.translation, res_um, "translation")
    write_rotation(w, f.T_a_b.quaternion_wxyz)
    write_covariance(w, f.covariance)
    ids = [None, None]
    corr = f.correspondences
    if corr:
        ids = [
            encode_ids([c.object_a for c in corr], w),
            encode_ids([c.object_b for c in corr], w),
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
    keyframes = []
    if f.keyframe_a is not None and f.keyframe_b is not None:
        keyframes = [check_keyframe(f.keyframe_a, "keyframe_a"),
                     check_keyframe(f.keyframe_b, "keyframe_b")]
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
        *keyframes,
    ]


def decode_factor_compact(payload: Any, limits: CodecLimits) -> Factor:
    fields = check_list(payload, "factor")
    if len(fields) not in (10, 12):  # the 11th and 12th, optional: keyframe_a, keyframe_b
        raise DecodeError(f"factor: expected 10 or 12 fields, got {len(fields)}")
    (fid, ra, sa, rb, sb, res_um, n_corr, ids_a, ids_b, blob) = fields[:10]
    keyframes = [check_int(k, f"factor.keyframe_{ab}", 0, MAX_KEYFRAME)
                 for k, ab in zip(fields[10:], "ab")]
    res_um = check_int(res_um, "factor.resolution_um", 1, 10**9)
    n_corr = check_int(n_corr, "factor.correspondences", 0, limits.max_correspondences)
    if type(blob) is not bytes:
        raise DecodeError("factor: the pose stream is not binary")
    r = BitReader(blob, "factor")
    status = _CODE_STATUS.get(r.read(2), "invalid")
    t = read_translation(r, res_um, "factor")
    q = read_rotation(r)
    C = read_covariance(r)
    corr: list[dict[str, Any]] = []
    if n_corr:
        a_ids = decode_ids(ids_a, n_corr, r, "factor.object_a")
        b_ids = decode_ids(ids_b, n_corr, r, "factor.object_b")
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
    doc: dict[str, Any] = {
        "factor_id": fid,
        "robot_a": ra,
        "session_a": sa,
        "robot_b": rb,
        "session_b": sb,
        "T_a_b": {"translation": t, "quaternion_wxyz": q},
        "covariance": C,
        "correspondences": corr,
        "status": status,
    }
    if keyframes:
        doc["keyframe_a"], doc["keyframe_b"] = keyframes
    return validate_model(Factor, doc, "decoded factor")


__all__ = [
    "FACTOR_SIGMA",
    "MAX_KEYFRAME",
    "QUAT_BITS",
    "SigmaCode",
    "check_keyframe",
    "decode_factor_compact",
    "encode_factor_compact",
    "quaternion_smallest_three",
    "read_covariance",
    "read_rotation",
    "read_sigmas",
    "read_translation",
    "write_covariance",
    "write_rotation",
    "write_sigmas",
    "write_translation",
]
