"""Object map / submap payloads (MAP and SUBMAP messages): encode_objects, decode_objects.

The payload is a msgpack array: a small header (robot and session ids, seq, stamp, n, d, and how
each field is coded), then `blob`, one bit stream (MSB first) holding the per-object fields in
order (id deltas, label codes, n_obs - 1, isotropic flags, positions, variances, embeddings),
then, optionally, the declared vertical `up` and, for a submap with a keyframe, its `pose`
(keyframe and odometry). A payload without the optional fields is byte-identical to one from
before they existed; the encoder writes the shortest form that holds what the model has. What
each profile carries per object: mergesvc.wire.profiles; the layout, the odometry's coding per
profile and its error bounds: docs/wire.md §4.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from mergesvc.core.model import ObjectMap, Submap
from mergesvc.errors import CodecError, DecodeError, SchemaError
from mergesvc.wire.bits import BitReader, BitWriter, bits_for
from mergesvc.wire.factors import (
    MAX_KEYFRAME,
    SigmaCode,
    check_keyframe,
    read_covariance,
    read_rotation,
    read_sigmas,
    read_translation,
    write_covariance,
    write_rotation,
    write_sigmas,
    write_translation,
)
from mergesvc.wire.fields import (
    LOG2_MAX,
    LOG2_MIN,
    LOG_UNITS,
    check_int,
    check_list,
    check_str,
    check_variances,
    decode_ids,
    encode_ids,
    from_raw,
    log_decode,
    log_encode,
    log_range,
    to_raw,
    validate_model,
)
from mergesvc.wire.profiles import CodecLimits, CodecSettings, Envelope, MessageType, Profile
from mergesvc.wire.projection import Projection, dequantize_coefficients, quantize_coefficients

COMPACT_MAX_N_OBS = 255  # compact saturates n_obs here (a fusion weight, not an identity)
# compact odometry standard deviations: log2 in [-32, 32) at 1/32 octave (11 bits, <= 1.1 %)
ODOMETRY_SIGMA = SigmaCode(11, 32, -32)
_ODOMETRY_FULL_VALUES = 3 + 4 + 36  # translation, quaternion wxyz, covariance row-major


def encode_objects(
    m: ObjectMap,
    profile: Profile,
    sender: str,
    seq: int,
    settings: CodecSettings,
    projection: Projection | None,
) -> list:
    arr = m.arrays()
    n, d = arr.n, arr.dim
    w = BitWriter()
    ids_hdr = encode_ids(arr.ids, w)

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
        # one number per object: an isotropic variance as it is, a per-dimension one's mean
        # summed left to right (docs/wire.md §4.5: any encoder gets the same number)
        mean = np.cumsum(arr.variances_nd, axis=1)[:, -1] / d
        var_iso = np.where(iso, arr.variances_nd[:, 0], mean)
        iso[:] = True
        var_dim = np.zeros((0, d))
    else:
        var_iso, var_dim = arr.variances_nd[iso, 0], arr.variances_nd[~iso]
    check_variances(var_iso)
    check_variances(var_dim)
    var_mode = 0 if iso.all() else 1 if not iso.any() else 2
    if var_mode == 2:
        w.write_fields(iso.astype(np.uint64), 1)

    pos_hdr = None
    res_um = round(settings.position_resolution_m * 1e6)
    if profile is Profile.FULL:
        w.write_bytes(to_raw(arr.position_xyz_m, "<f8", "positions"))
    else:
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
        w.write_bytes(to_raw(var_iso, "<f4", "variances"))
        w.write_bytes(to_raw(var_dim, "<f4", "variances"))
    else:
        both = np.concatenate([var_iso, var_dim.ravel()])
        lo, hi = log_range(both)
        width = {Profile.F16: 16, Profile.INT8: 8}.get(profile)
        if width is None:  # compact: a step of at most 1/32 octave (<= 1.1 % error)
            width = max(1, bits_for(math.ceil((hi - lo) / 2)))
        w.write_fields(log_encode(both, lo, hi, width), width)
        var_hdr = [lo, hi, width]

    emb_hdr = None
    # the files' own values (ObjectArrays holds float32): f16, int8 and compact quantise from
    # what the model says, as they always did
    E = np.array([o.embedding for o in m.objects], dtype=np.float64)
    if profile is Profile.FULL:
        w.write_bytes(to_raw(E, "<f4", "embeddings"))
    elif profile is Profile.F16:
        w.write_bytes(to_raw(E, "<f2", "embeddings"))
    elif profile is Profile.INT8:
        peak = np.abs(E).max(axis=1)
        scale = (peak / 127.0).astype("<f4")
        safe = np.where(scale > 0, scale.astype(np.float64), 1.0)[:, None]
        w.write_bytes(to_raw(scale, "<f4", "int8 scales"))
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
    tail: list = [] if m.up is None else [encode_up(m.up)]
    if isinstance(m, Submap) and (m.keyframe is not None or m.odometry is not None):
        tail = [tail[0] if tail else None, encode_pose(m, profile, res_um)]
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
    codes = [check_int(x, "up", -127, 127) for x in check_list(v, "up", 3)]
    norm = math.sqrt(sum(c * c for c in codes))
    if norm == 0:
        raise DecodeError("up: the zero vector has no direction")
    return (codes[0] / norm, codes[1] / norm, codes[2] / norm)


def encode_pose(m: Submap, profile: Profile, res_um: int) -> list:
    """The pose field: [keyframe] or [keyframe, delta, odometry] (see the module docstring);
    res_um is the payload's position resolution (the odometry's translation step)."""
    if m.keyframe is None:
        raise CodecError("odometry needs keyframe")
    keyframe = check_keyframe(m.keyframe, "keyframe")
    odo = m.odometry
    if odo is None:
        return [keyframe]
    delta = keyframe - odo.from_keyframe
    if delta < 1:
        raise CodecError(
            f"odometry.from_keyframe {odo.from_keyframe} must be before keyframe {keyframe}"
        )
    T = odo.T_from_to
    if profile is Profile.FULL:
        values = np.concatenate(
            [T.translation, T.quaternion_wxyz, np.ravel(np.array(odo.covariance, np.float64))]
        )
        return [keyframe, delta, to_raw(values, "<f8", "odometry")]
    w = BitWriter()
    write_translation(w, T.translation, res_um, "odometry translation")
    write_rotation(w, T.quaternion_wxyz)
    if profile is Profile.COMPACT:
        write_sigmas(w, np.array(odo.covariance, np.float64), ODOMETRY_SIGMA, "odometry covariance")
    else:
        write_covariance(w, odo.covariance, "odometry covariance")
    return [keyframe, delta, w.getvalue()]


def decode_pose(v: Any, profile: Profile, res_um: int) -> dict[str, Any]:
    """The submap fields `keyframe` (and `odometry`) of a pose field, for the model to judge."""
    fields = check_list(v, "pose")
    if len(fields) not in (1, 3):
        raise DecodeError(
            f"pose: expected [keyframe] or [keyframe, delta, odometry], got {len(fields)} fields"
        )
    if fields[0] is None and len(fields) == 3:
        raise DecodeError("pose: odometry needs keyframe")
    keyframe = check_int(fields[0], "keyframe", 0, MAX_KEYFRAME)
    if len(fields) == 1:
        return {"keyframe": keyframe}
    delta = check_int(fields[1], "odometry.delta", -MAX_KEYFRAME, MAX_KEYFRAME)
    blob = fields[2]
    if type(blob) is not bytes:
        raise DecodeError("odometry: expected binary, got " + type(blob).__name__)
    if profile is Profile.FULL:
        if len(blob) != 8 * _ODOMETRY_FULL_VALUES:
            raise DecodeError(
                f"odometry: expected {8 * _ODOMETRY_FULL_VALUES} bytes, got {len(blob)}"
            )
        a = np.frombuffer(blob, dtype="<f8").astype(np.float64)  # NaN / inf: the model says
        t, q, C = a[:3].tolist(), a[3:7].tolist(), a[7:].reshape(6, 6).tolist()
    else:
        r = BitReader(blob, "odometry")
        t = read_translation(r, res_um, "odometry")
        q = read_rotation(r)
        if profile is Profile.COMPACT:
            C = np.diag(read_sigmas(r, ODOMETRY_SIGMA) ** 2).tolist()
        else:
            C = read_covariance(r)
        r.finish()
    return {
        "keyframe": keyframe,
        "odometry": {
            "from_keyframe": keyframe - delta,
            "T_from_to": {"translation": t, "quaternion_wxyz": q},
            "covariance": C,
        },
    }


def _find_projection(pid: str, projections: Mapping[str, Projection], what: str) -> Projection:
    if pid not in projections:
        have = ", ".join(sorted(projections)) or "none"
        raise DecodeError(
            f"{what} was coded with projection {pid}, which this decoder does not have "
            f"(have: {have}): give the command that decodes it that projection file (--projection)"
        )
    return projections[pid]


def decode_objects(
    payload: Any,
    env: Envelope,
    projections: Mapping[str, Projection],
    limits: CodecLimits,
) -> tuple[ObjectMap, str | None]:
    what = f"{env.msg_type.value} payload"
    fields = check_list(payload, what)
    # optional: the 15th the declared vertical, the 16th the pose (the 15th then may be nil)
    if len(fields) not in (14, 15, 16):
        raise DecodeError(f"{what}: expected 14 to 16 fields, got {len(fields)}")
    robot, session, seq, stamp, n, d, ids_hdr, label_hdr = fields[:8]
    nobs_bits, var_mode, pos_hdr, var_hdr, emb_hdr, blob = fields[8:14]
    has_up = len(fields) == 15 or (len(fields) == 16 and fields[14] is not None)
    up = decode_up(fields[14]) if has_up else None
    pose_field = fields[15] if len(fields) == 16 else None
    if len(fields) == 16 and env.msg_type is not MessageType.SUBMAP:
        raise DecodeError(f"{what}: a map carries no keyframe or odometry")
    robot = check_str(robot, "robot_id", optional=True, max_len=128) or env.sender
    session = check_str(session, "session_id", max_len=128)
    if seq is not None:
        seq = check_int(seq, "seq", -1, 2**63 - 1)
    if stamp is not None and type(stamp) is not float:
        raise DecodeError(f"stamp: expected a float, got {type(stamp).__name__}")
    n = check_int(n, "objects", 1, limits.max_objects)
    d = check_int(d, "embedding dimension", 1, limits.max_dim)
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

    ids = decode_ids(ids_hdr, n, r, "ids")
    labels: list[str | None] = [None] * n
    if label_hdr is not None:
        table = check_list(label_hdr, "labels")
        if not table or len(table) > n:
            raise DecodeError("labels: table must have 1..n entries")
        table = [check_str(s, "labels", optional=True, max_len=128) for s in table]
        codes = r.read_array(n, bits_for(len(table) - 1))
        if codes.max() >= len(table):
            raise DecodeError("labels: code outside the table")
        labels = [table[c] for c in codes.tolist()]
    nobs_bits = check_int(nobs_bits, "nobs_bits", 0, 32)
    n_obs = r.read_array(n, nobs_bits).astype(np.int64) + 1
    var_mode = check_int(var_mode, "var_mode", 0, 2)
    iso = r.read_array(n, 1).astype(bool) if var_mode == 2 else np.full(n, var_mode == 0)
    if profile is Profile.COMPACT and var_mode != 0:
        raise DecodeError("compact carries one variance per object (var_mode must be 0)")
    n_iso, n_dim = int(iso.sum()), int((~iso).sum())

    res_um = 0  # full: the odometry is exact
    if not lossy:
        pos = from_raw(r, 3 * n, "<f8", "positions").reshape(n, 3)
    else:
        res_um, *origin_widths = check_list(pos_hdr, "positions", 7)
        res_um = check_int(res_um, "positions.resolution_um", 1, 10**9)
        origin = [check_int(x, "positions.origin", -(2**53), 2**53) for x in origin_widths[:3]]
        widths = [check_int(x, "positions.width", 0, 32) for x in origin_widths[3:]]
        q = r.read_fields(np.tile(widths, n)).reshape(n, 3).astype(np.int64)
        pos = (q + np.array(origin, dtype=np.int64)).astype(np.float64) * (res_um / 1e6)

    if not lossy:
        var_iso = from_raw(r, n_iso, "<f4", "variances")
        var_dim = from_raw(r, n_dim * d, "<f4", "variances").reshape(n_dim, d)
    else:
        lo, hi, width = check_list(var_hdr, "variances", 3)
        lo = check_int(lo, "variances.lo", LOG2_MIN * LOG_UNITS, LOG2_MAX * LOG_UNITS)
        hi = check_int(hi, "variances.hi", lo + 1, LOG2_MAX * LOG_UNITS + 1)
        width = check_int(width, "variances.width", 1, 16)
        both = log_decode(r.read_array(n_iso + n_dim * d, width), lo, hi, width)
        var_iso, var_dim = both[:n_iso], both[n_iso:].reshape(n_dim, d)

    pid = None
    if profile is Profile.FULL:
        E = from_raw(r, n * d, "<f4", "embeddings").reshape(n, d)
    elif profile is Profile.F16:
        E = from_raw(r, n * d, "<f2", "embeddings").reshape(n, d)
    elif profile is Profile.INT8:
        scale = from_raw(r, n, "<f4", "int8 scales")
        if scale.min() < 0:
            raise SchemaError("int8 scales must not be negative")
        E = from_raw(r, n * d, "i1", "embeddings").reshape(n, d) * scale[:, None]
    else:
        pid_bytes, budget, step16 = check_list(emb_hdr, "embeddings", 3)
        if type(pid_bytes) is not bytes or len(pid_bytes) != 4:
            raise DecodeError("embeddings: projection id must be 4 bytes")
        pid = pid_bytes.hex()
        proj = _find_projection(pid, projections, f"{env.msg_type.value} {env.seq}")
        if proj.dim != d:
            raise DecodeError(f"projection {pid} is {proj.dim}-d, the message says {d}")
        budget = check_int(budget, "embeddings.bits", 0, 65535)
        step = check_int(step16, "embeddings.step", 1, 240) / 16
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
        if len(fields) == 16:
            doc.update(decode_pose(pose_field, profile, res_um))
    elif seq is not None or stamp is not None:
        raise DecodeError("a map carries no seq or stamp")
    return validate_model(model, doc, f"decoded {env.msg_type.value}"), pid


__all__ = [
    "COMPACT_MAX_N_OBS",
    "ODOMETRY_SIGMA",
    "decode_objects",
    "decode_pose",
    "decode_up",
    "encode_objects",
    "encode_pose",
    "encode_up",
]
