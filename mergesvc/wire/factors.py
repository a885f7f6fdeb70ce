"""The compact factor codec (FACTOR messages in `compact`; other profiles carry the JSON).

Compact factor payload, a msgpack array:
    [factor_id, robot_a, session_a, robot_b, session_b, resolution_um, n_correspondences,
     ids_a, ids_b, blob]
where `blob` is one bit stream (MSB first) holding, in order: the status code; per translation
axis a 6-bit width and the zigzag fixed-point value; the rotation as smallest three quaternion
components; the covariance as six log2 standard deviations and the 15 canonical partial
correlations of its correlation matrix (any codes decode to a valid covariance); then, with
correspondences, id deltas of both sides and the scores (float32 range, 8 bits each).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from mergesvc.core.model import Factor
from mergesvc.errors import CodecError, DecodeError
from mergesvc.wire.bits import MAX_FIELD_BITS, BitReader, BitWriter, bits_for, unzigzag, zigzag
from mergesvc.wire.fields import check_int, check_list, decode_ids, encode_ids, validate_model
from mergesvc.wire.profiles import CodecLimits, CodecSettings

# factor std devs: log2 in [-32, 32) at 1/256 octave (14 bits, <= 0.14 % error)
_SIGMA_BITS, _SIGMA_PER_OCTAVE, _SIGMA_LOG2_MIN = 14, 256, -32
_CPC_BITS, _CPC_ATANH_MAX = 13, 5.0  # factor partial correlations: atanh in (-5, 5)
_QUAT_BITS = 15  # smallest-three quaternion components
_SCORE_BITS = 8

# Wire codes: never renumber, only add.
_STATUS_CODE = {None: 0, "accepted": 1, "retracted": 2}
_CODE_STATUS = {v: k for k, v in _STATUS_CODE.items()}


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


def encode_factor_compact(f: Factor, settings: CodecSettings) -> list:
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


def decode_factor_compact(payload: Any, limits: CodecLimits) -> Factor:
    (fid, ra, sa, rb, sb, res_um, n_corr, ids_a, ids_b, blob) = check_list(payload, "factor", 10)
    res_um = check_int(res_um, "factor.resolution_um", 1, 10**9)
    n_corr = check_int(n_corr, "factor.correspondences", 0, limits.max_correspondences)
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
    return validate_model(Factor, doc, "decoded factor")


__all__ = [
    "decode_factor_compact",
    "encode_factor_compact",
    "quaternion_smallest_three",
]
