"""A second decoder of the mergesvc wire protocol, written from docs/wire.md alone.

It imports nothing of mergesvc: plain msgpack, numpy, hashlib and math. tests/test_wire_spec.py
decodes the golden vectors with it and encodes their inputs with it; if it needs to know
something docs/wire.md does not say, the spec is incomplete. `decode(data, projections)`
returns {"envelope": ..., "message": ...} as in the golden NAME.json files, or raises
`RefusedError`; `encode(inp, projections)` codes a NAME.in.json into NAME.bin's bytes.
"""

from __future__ import annotations

import hashlib
import itertools
import math
import struct
import zlib
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

TYPES = {1: "submap", 2: "map", 3: "factor", 4: "error"}  # 5, 6 reserved: refused
PROFILES = {0: "full", 1: "f16", 2: "int8", 3: "compact"}
STATUS = {0: None, 1: "accepted", 2: "retracted"}
MAX_STEP = {1: 1.596, 2: 0.9957, 3: 0.5860, 4: 0.3352, 5: 0.1881, 6: 0.1041, 7: 0.0569,
            8: 0.0308}
MAX_MESSAGE = 16 * 2**20
MAX_OBJECTS, MAX_DIM, MAX_VALUES, MAX_CORR = 20_000, 4096, 4_000_000, 10_000
U63 = 2**63 - 1


class RefusedError(Exception):
    """The message breaks docs/wire.md."""


def need(cond: bool, why: str) -> None:
    if not cond:
        raise RefusedError(why)


def an_int(v: Any, lo: int, hi: int, what: str) -> int:
    need(type(v) is int, f"{what}: not an integer")
    need(lo <= v <= hi, f"{what}: {v} outside {lo}..{hi}")
    return v


def a_str(v: Any, what: str, lo: int = 0, hi: int = 128) -> str:
    need(type(v) is str, f"{what}: not a string")
    need(lo <= len(v) <= hi, f"{what}: length outside {lo}..{hi}")
    return v


def a_float(v: Any, what: str) -> float:
    need(type(v) in (int, float), f"{what}: not a number")
    need(math.isfinite(v), f"{what}: not finite")
    return float(v)


def an_array(v: Any, what: str, n: int | None = None) -> list:
    need(type(v) is list, f"{what}: not an array")
    need(n is None or len(v) == n, f"{what}: expected {n} elements")
    return v


def bits_for(v: int) -> int:
    return int(v).bit_length()


def unzigzag(u: int) -> int:
    return u // 2 if u % 2 == 0 else -(u + 1) // 2


class Bits:
    """docs/wire.md §3: MSB-first fields, zero padding before byte sections and at the end."""

    def __init__(self, data: bytes) -> None:
        self.data = data
        self.pos = 0

    def read(self, width: int) -> int:
        need(0 <= width <= 56, "bit field wider than 56")
        need(self.pos + width <= 8 * len(self.data), "bit stream truncated")
        v = 0
        for _ in range(width):
            byte = self.data[self.pos >> 3]
            v = (v << 1) | ((byte >> (7 - (self.pos & 7))) & 1)
            self.pos += 1
        return v

    def many(self, n: int, width: int) -> list[int]:
        need(self.pos + n * width <= 8 * len(self.data), "bit stream truncated")
        return [self.read(width) for _ in range(n)]

    def align(self) -> None:
        pad = -self.pos % 8
        need(self.read(pad) == 0, "padding bits are not zero")

    def raw(self, n: int) -> bytes:
        self.align()
        need(self.pos // 8 + n <= len(self.data), "bit stream truncated")
        out = self.data[self.pos // 8 : self.pos // 8 + n]
        self.pos += 8 * n
        return out

    def f32(self) -> float:
        return struct.unpack(">f", self.read(32).to_bytes(4, "big"))[0]

    def finish(self) -> None:
        self.align()
        need(self.pos == 8 * len(self.data), "bytes after the bit stream")


def floats(raw: bytes, dtype: str, what: str) -> np.ndarray:
    a = np.frombuffer(raw, dtype=dtype).astype(np.float64)
    need(bool(np.all(np.isfinite(a))), f"{what}: NaN or infinity")
    return a


# ------------------------------------------------------------------ projections (§5)

def projection_id(mean: np.ndarray, basis: np.ndarray, scale: np.ndarray) -> str:
    h = hashlib.sha256(b"mergesvc-projection-1")
    h.update(struct.pack("<II", basis.shape[0], mean.shape[0]))
    for a in (mean, basis, scale):
        h.update(np.ascontiguousarray(a, dtype="<f4").tobytes())
    return h.hexdigest()[:8]


def load_projection(path: Path) -> dict[str, Any]:
    with np.load(path, allow_pickle=False) as z:
        p = {k: z[k].astype("<f4") for k in ("mean", "basis", "scale")}
        stored = str(z["id"])
    p["id"] = projection_id(p["mean"], p["basis"], p["scale"])
    need(p["id"] == stored, "projection id does not match its content")
    return p


def bit_allocation(scale: np.ndarray, budget: int) -> list[int]:
    bits = [0] * len(scale)
    v = [float(s) for s in scale]
    live = set(range(len(scale)))
    for _ in range(min(budget, 8 * len(scale))):
        j = max(sorted(live), key=lambda i: v[i])  # max returns the first (lowest j) of ties
        bits[j] += 1
        v[j] /= 2
        if bits[j] == 8:
            live.discard(j)
    return bits


# ------------------------------------------------------------------ shared fields

def read_ids(hdr: Any, n: int, r: Bits, what: str) -> list[str]:
    """§4.1."""
    hdr = an_array(hdr, what)
    need(len(hdr) > 0, f"{what}: empty header")
    kind = an_int(hdr[0], 0, 1, what)
    if kind == 0:
        ids = an_array(an_array(hdr, what, 2)[1], what, n)
        return [a_str(s, what, 1) for s in ids]
    _, prefix, first, dmin, width = an_array(hdr, what, 5)
    prefix = a_str(prefix, what)
    value = an_int(first, 0, 10**16 - 1, what)
    dmin = an_int(dmin, -(10**16), 10**16, what)
    width = an_int(width, 0, 56, what)
    out = [value]
    for u in r.many(n - 1, width):
        value += u + dmin
        need(0 <= value < 10**16, f"{what}: id number out of range")
        out.append(value)
    return [f"{prefix}{v}" for v in out]


def read_translation(r: Bits, res_um: int) -> list[float]:
    """§6.2 item 2."""
    t = []
    for _ in range(3):
        w = r.read(6)
        need(w <= 56, "translation field too wide")
        t.append(unzigzag(r.read(w)) * (res_um / 1e6))
    return t


def read_rotation(r: Bits) -> list[float]:
    """§6.2 item 3."""
    i = r.read(2)
    L = 2**15 - 1
    rest = [k / L * math.sqrt(2) - math.sqrt(0.5) for k in r.many(3, 15)]
    big = math.sqrt(max(0.0, 1.0 - sum(x * x for x in rest)))
    q = np.array([*rest[:i], big, *rest[i:]])
    return (q / np.linalg.norm(q)).tolist()


def read_sigmas(r: Bits, bits: int, per_octave: int) -> np.ndarray:
    return np.array([2.0 ** (k / per_octave - 32) for k in r.many(6, bits)])


def read_covariance(r: Bits) -> list[list[float]]:
    """§6.2 item 4: six 14-bit sigmas, 15 13-bit CPCs."""
    sigma = read_sigmas(r, 14, 256)
    z = [math.tanh((g + 0.5) / 8192 * 2 * 5.0 - 5.0) for g in r.many(15, 13)]
    L = np.zeros((6, 6))
    L[0, 0] = 1.0
    k = 0
    for i in range(1, 6):
        rem = 1.0
        for j in range(i):
            L[i, j] = z[k] * math.sqrt(rem)
            rem -= L[i, j] ** 2
            k += 1
        L[i, i] = math.sqrt(max(rem, 0.0))
    R = L @ L.T
    R = (R + R.T) / 2
    C = R * np.outer(sigma, sigma)
    return ((C + C.T) / 2).tolist()


# ------------------------------------------------------------------ document checks (§8)

def check_pose(T: dict, C: list[list[float]], what: str) -> None:
    q = T["quaternion_wxyz"]
    need(all(math.isfinite(x) for x in [*T["translation"], *q]), f"{what}: not finite")
    need(abs(math.sqrt(sum(x * x for x in q)) - 1) <= 1e-3, f"{what}: quaternion not unit")
    M = np.array(C, dtype=np.float64)
    need(M.shape == (6, 6) and bool(np.all(np.isfinite(M))), f"{what}: covariance not 6x6")
    need(float(np.abs(M - M.T).max()) <= 1e-9 * float(np.abs(M).max()),
         f"{what}: covariance not symmetric")
    try:
        np.linalg.cholesky(M)
    except np.linalg.LinAlgError:
        raise RefusedError(f"{what}: covariance not positive definite") from None


# ------------------------------------------------------------------ maps and submaps (§4)

def decode_objects(p: Any, msg_type: str, profile: str, sender: str, env_seq: int,
                   projections: dict[str, dict]) -> dict[str, Any]:
    f = an_array(p, "objects payload")
    need(len(f) in (14, 15, 16), "objects payload: 14..16 elements")
    need(not (len(f) == 16 and msg_type == "map"), "a map has no pose")
    robot = f[0] if f[0] is not None else sender
    robot = a_str(robot, "robot_id", 1)
    session = a_str(f[1], "session_id", 1)
    seq = f[2]
    if seq is not None:
        seq = an_int(seq, -1, U63, "seq")
    stamp = f[3]
    need(stamp is None or (type(stamp) is float and math.isfinite(stamp)),
         "stamp: not a finite float")
    if msg_type == "map":
        need(seq is None and stamp is None, "a map has no seq or stamp")
    n = an_int(f[4], 1, MAX_OBJECTS, "n")
    d = an_int(f[5], 1, MAX_DIM, "d")
    need(n * d <= MAX_VALUES, "n x d too large")
    labels_hdr, nobs_bits, var_mode, pos_hdr, var_hdr, emb_hdr, blob = f[7:14]
    need(type(blob) is bytes, "blob: not bin")
    lossy = profile != "full"
    need((pos_hdr is not None) == lossy and (var_hdr is not None) == lossy,
         "headers do not match the profile")
    need((emb_hdr is not None) == (profile == "compact"), "headers do not match the profile")
    r = Bits(blob)

    ids = read_ids(f[6], n, r, "ids")
    labels: list[str | None] = [None] * n
    if labels_hdr is not None:
        table = an_array(labels_hdr, "labels")
        need(1 <= len(table) <= n, "labels: table of 1..n entries")
        for s in table:
            need(s is None or (type(s) is str and len(s) <= 128), "labels: bad entry")
        codes = r.many(n, bits_for(len(table) - 1))
        need(all(c < len(table) for c in codes), "labels: code outside the table")
        labels = [table[c] for c in codes]
    nobs_bits = an_int(nobs_bits, 0, 32, "nobs_bits")
    n_obs = [v + 1 for v in r.many(n, nobs_bits)]
    var_mode = an_int(var_mode, 0, 2, "var_mode")
    need(profile != "compact" or var_mode == 0, "compact: var_mode must be 0")
    iso = [bool(b) for b in r.many(n, 1)] if var_mode == 2 else [var_mode == 0] * n
    n_iso = sum(iso)
    n_dim = n - n_iso

    res_um = 0
    if not lossy:
        pos = floats(r.raw(24 * n), "<f8", "positions").reshape(n, 3)
    else:
        res_um, ox, oy, oz, wx, wy, wz = an_array(pos_hdr, "positions", 7)
        res_um = an_int(res_um, 1, 10**9, "resolution_um")
        origin = [an_int(o, -(2**53), 2**53, "origin") for o in (ox, oy, oz)]
        widths = [an_int(w, 0, 32, "width") for w in (wx, wy, wz)]
        pos = np.array([[float(r.read(widths[a]) + origin[a]) * (res_um / 1e6)
                         for a in range(3)] for _ in range(n)])

    if not lossy:
        v_iso = floats(r.raw(4 * n_iso), "<f4", "variances")
        v_dim = floats(r.raw(4 * n_dim * d), "<f4", "variances").reshape(n_dim, d)
    else:
        lo, hi, width = an_array(var_hdr, "variances", 3)
        lo = an_int(lo, -126 * 64, 127 * 64, "variances.lo")
        hi = an_int(hi, lo + 1, 127 * 64 + 1, "variances.hi")
        width = an_int(width, 1, 16, "variances.width")
        levels = 2**width - 1
        codes = np.array(r.many(n_iso + n_dim * d, width), dtype=np.float64)
        v = np.exp2((lo + codes * (hi - lo) / levels) / 64)
        v_iso, v_dim = v[:n_iso], v[n_iso:].reshape(n_dim, d)

    pid = None
    if profile == "full":
        E = floats(r.raw(4 * n * d), "<f4", "embeddings").reshape(n, d)
    elif profile == "f16":
        E = floats(r.raw(2 * n * d), "<f2", "embeddings").reshape(n, d)
    elif profile == "int8":
        s = floats(r.raw(4 * n), "<f4", "int8 scales")
        need(bool(np.all(s >= 0)), "int8: negative scale")
        E = np.frombuffer(r.raw(n * d), dtype="i1").reshape(n, d).astype(np.float64) * s[:, None]
    else:
        pid_b, budget, step16 = an_array(emb_hdr, "embeddings", 3)
        need(type(pid_b) is bytes and len(pid_b) == 4, "projection id: 4 bytes")
        pid = pid_b.hex()
        need(pid in projections, f"projection {pid} unknown")
        proj = projections[pid]
        need(proj["mean"].shape[0] == d, "projection dimension differs")
        budget = an_int(budget, 0, 65535, "budget_bits")
        step = an_int(step16, 1, 240, "step16") / 16
        bits = bit_allocation(proj["scale"], budget)
        sigma = proj["scale"].astype(np.float64)
        E = np.zeros((n, d))
        for i in range(n):
            c = np.zeros(len(bits))
            for j, b in enumerate(bits):
                q = r.read(b)
                if b:
                    c[j] = (q - 2 ** (b - 1) + 0.5) * ((step * MAX_STEP[b]) * sigma[j])
            E[i] = proj["mean"].astype(np.float64) + c @ proj["basis"].astype(np.float64)
    r.finish()

    objects = []
    k_iso = k_dim = 0
    for i in range(n):
        if iso[i]:
            var: Any = float(v_iso[k_iso])
            k_iso += 1
            need(var > 0, "variance <= 0")
        else:
            var = v_dim[k_dim].tolist()
            k_dim += 1
            need(min(var) > 0, "variance <= 0")
        need(bool(np.all(np.isfinite(pos[i]))), "position not finite")
        need(bool(np.all(np.abs(pos[i]) <= 1e9)), "position beyond +-1e9 m")
        obj = {"id": ids[i], "position": pos[i].tolist(), "embedding": E[i].tolist(),
               "variance": var, "n_obs": n_obs[i]}
        if labels[i] is not None:
            obj["label"] = labels[i]
        objects.append(obj)
    need(len(set(ids)) == n, "ids not unique")
    doc: dict[str, Any] = {"schema_version": 1, "robot_id": robot, "session_id": session,
                           "objects": objects}
    has_up = len(f) == 15 or (len(f) == 16 and f[14] is not None)
    if has_up:
        c = [an_int(x, -127, 127, "up") for x in an_array(f[14], "up", 3)]
        norm = math.sqrt(sum(x * x for x in c))
        need(norm > 0, "up: zero vector")
        doc["up"] = [x / norm for x in c]
    if msg_type == "submap":
        s = env_seq if seq is None else None if seq == -1 else seq
        if s is not None:
            doc["seq"] = s
        if stamp is not None:
            doc["stamp"] = stamp
        if len(f) == 16:
            doc.update(decode_pose(f[15], profile, res_um))
    return doc


def decode_pose(v: Any, profile: str, res_um: int) -> dict[str, Any]:
    """§4.8."""
    p = an_array(v, "pose")
    need(len(p) in (1, 3), "pose: 1 or 3 elements")
    keyframe = an_int(p[0], 0, U63, "keyframe")
    if len(p) == 1:
        return {"keyframe": keyframe}
    delta = an_int(p[1], -U63, U63, "delta")
    from_kf = keyframe - delta
    need(0 <= from_kf < keyframe, "odometry: from_keyframe not before keyframe")
    blob = p[2]
    need(type(blob) is bytes, "odometry: not bin")
    if profile == "full":
        need(len(blob) == 344, "odometry: 344 bytes")
        a = np.frombuffer(blob, dtype="<f8").astype(np.float64)
        t, q, C = a[:3].tolist(), a[3:7].tolist(), a[7:].reshape(6, 6).tolist()
    else:
        r = Bits(blob)
        t = read_translation(r, res_um)
        q = read_rotation(r)
        if profile == "compact":
            C = np.diag(read_sigmas(r, 11, 32) ** 2).tolist()
        else:
            C = read_covariance(r)
        r.finish()
    T = {"translation": t, "quaternion_wxyz": q}
    check_pose(T, C, "odometry")
    return {"keyframe": keyframe,
            "odometry": {"from_keyframe": from_kf, "T_from_to": T, "covariance": C}}


# ------------------------------------------------------------------ factors (§6)

FACTOR_KEYS = {"schema_version", "factor_id", "robot_a", "session_a", "robot_b", "session_b",
               "T_a_b", "covariance", "correspondences", "status", "keyframe_a", "keyframe_b"}
NAMES = ("factor_id", "robot_a", "session_a", "robot_b", "session_b")


def decode_factor_full(p: Any) -> dict[str, Any]:
    need(type(p) is dict, "factor: not a map")
    need(set(p) <= FACTOR_KEYS, "factor: unknown keys")
    need(all(k in p for k in (*NAMES, "T_a_b", "covariance")), "factor: missing keys")
    an_int(p.get("schema_version", 1), 1, 1, "schema_version")
    doc: dict[str, Any] = {"schema_version": 1}
    for k in NAMES:
        doc[k] = a_str(p[k], k, 1)
    T = p["T_a_b"]
    need(type(T) is dict and set(T) == {"translation", "quaternion_wxyz"}, "T_a_b")
    T = {"translation": [a_float(x, "t") for x in an_array(T["translation"], "t", 3)],
         "quaternion_wxyz": [a_float(x, "q") for x in an_array(T["quaternion_wxyz"], "q", 4)]}
    C = [[a_float(x, "covariance") for x in an_array(row, "covariance", 6)]
         for row in an_array(p["covariance"], "covariance", 6)]
    check_pose(T, C, "factor")
    doc["T_a_b"], doc["covariance"] = T, C
    corr = []
    for c in an_array(p.get("correspondences", []), "correspondences"):
        need(type(c) is dict and set(c) == {"object_a", "object_b", "score"}, "correspondence")
        corr.append({"object_a": a_str(c["object_a"], "object_a", 1),
                     "object_b": a_str(c["object_b"], "object_b", 1),
                     "score": a_float(c["score"], "score")})
    need(len(corr) <= MAX_CORR, "too many correspondences")
    doc["correspondences"] = corr
    status = p.get("status")
    need(status in (None, "accepted", "retracted"), "status")
    if status is not None:
        doc["status"] = status
    ka, kb = p.get("keyframe_a"), p.get("keyframe_b")
    need((ka is None) == (kb is None), "keyframe_a and keyframe_b go together")
    if ka is not None:
        doc["keyframe_a"] = an_int(ka, 0, U63, "keyframe_a")
        doc["keyframe_b"] = an_int(kb, 0, U63, "keyframe_b")
    return doc


def decode_factor_compact(p: Any) -> dict[str, Any]:
    f = an_array(p, "factor")
    need(len(f) in (10, 12), "factor: 10 or 12 elements")
    doc: dict[str, Any] = {"schema_version": 1}
    for k, v in zip(NAMES, f[:5]):
        doc[k] = a_str(v, k, 1)
    res_um = an_int(f[5], 1, 10**9, "resolution_um")
    n_corr = an_int(f[6], 0, MAX_CORR, "n_corr")
    ids_a, ids_b, blob = f[7:10]
    need(type(blob) is bytes, "factor blob: not bin")
    r = Bits(blob)
    code = r.read(2)
    need(code in STATUS, "factor: unknown status")
    T = {"translation": read_translation(r, res_um), "quaternion_wxyz": read_rotation(r)}
    C = read_covariance(r)
    corr = []
    if n_corr:
        a = read_ids(ids_a, n_corr, r, "ids_a")
        b = read_ids(ids_b, n_corr, r, "ids_b")
        lo, hi = r.f32(), r.f32()
        need(math.isfinite(lo) and math.isfinite(hi) and lo <= hi, "score range")
        codes = r.many(n_corr, 8 if hi > lo else 0)
        corr = [{"object_a": x, "object_b": y, "score": lo + c / 255 * (hi - lo)}
                for x, y, c in zip(a, b, codes)]
    else:
        need(ids_a is None and ids_b is None, "ids without correspondences")
    r.finish()
    check_pose(T, C, "factor")
    doc.update({"T_a_b": T, "covariance": C, "correspondences": corr})
    if STATUS[code] is not None:
        doc["status"] = STATUS[code]
    if len(f) == 12:
        doc["keyframe_a"] = an_int(f[10], 0, U63, "keyframe_a")
        doc["keyframe_b"] = an_int(f[11], 0, U63, "keyframe_b")
    return doc


# ------------------------------------------------------------------ the envelope (§2)

def decode(data: bytes, projections: dict[str, dict] | None = None) -> dict[str, Any]:
    need(0 < len(data) <= MAX_MESSAGE, "empty or larger than 16 MiB")
    try:
        env = msgpack.unpackb(data, raw=False, strict_map_key=True, max_ext_len=0,
                              max_str_len=65536, max_array_len=20_000, max_map_len=64)
    except Exception as exc:  # the msgpack library's own errors: not msgpack, extra bytes
        raise RefusedError(f"not a msgpack message: {exc}") from None
    env = an_array(env, "envelope", 7)
    an_int(env[0], 1, 1, "schema_version")
    an_int(env[1], 1, 1, "codec_version")
    msg_type = TYPES.get(an_int(env[2], 0, 255, "type"))
    need(msg_type is not None, "unknown or reserved type")
    sender = a_str(env[3], "sender", 1)
    seq = an_int(env[4], 0, U63, "seq")
    profile = PROFILES.get(an_int(env[5], 0, 255, "profile"))
    need(profile is not None, "unknown profile")
    envelope: dict[str, Any] = {"schema_version": 1, "codec_version": 1, "type": msg_type,
                                "sender": sender, "seq": seq, "profile": profile}
    p = env[6]
    if msg_type in ("map", "submap"):
        message = decode_objects(p, msg_type, profile, sender, seq, projections or {})
        if profile == "compact":
            envelope["projection_id"] = p[12][0].hex()
    elif msg_type == "factor":
        need(profile in ("full", "compact"), "a factor is full or compact")
        message = decode_factor_full(p) if profile == "full" else decode_factor_compact(p)
    else:
        code, detail, about = an_array(p, "error", 3)
        message = {"schema_version": 1, "code": a_str(code, "code", 1, 64),
                   "detail": a_str(detail, "detail", 0, 1024)}
        if about is not None:
            message["about_seq"] = an_int(about, 0, U63, "about_seq")
    return {"envelope": envelope, "message": message}


# ------------------------------------------------------------------ the acoustic link (§12)

def crc16_ccitt_false(data: bytes) -> int:
    """Polynomial 0x1021, initial value 0xFFFF, no reflection, no final xor."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else crc << 1
            crc &= 0xFFFF
    return crc


def unframe_link(frames: list[bytes]) -> tuple[str, bytes]:
    """Fragments of one bridged sample, in any order -> (key suffix, message)."""
    parts: dict[int, bytes] = {}
    ids, counts = set(), set()
    for fr in frames:
        need(len(fr) >= 6, "fragment shorter than its header and CRC")
        body, crc = fr[:-2], fr[-2:]
        need(crc16_ccitt_false(body) == int.from_bytes(crc, "big"), "fragment CRC-16 mismatch")
        word = int.from_bytes(body[:4], "big")
        msg_id, index, count = word >> 20, (word >> 10) & 0x3FF, (word & 0x3FF) + 1
        need(index < count, "fragment index beyond its count")
        ids.add(msg_id)
        counts.add(count)
        parts[index] = body[4:]
    need(len(ids) == 1 and len(counts) == 1, "fragments of different messages")
    need(sorted(parts) == list(range(counts.pop())), "fragments missing")
    data = b"".join(parts[i] for i in sorted(parts))
    need(len(data) >= 4, "shorter than the CRC-32 trailer")
    sample, crc = data[:-4], data[-4:]
    need(zlib.crc32(sample) == int.from_bytes(crc, "big"), "message CRC-32 mismatch")
    need(len(sample) >= 1 + sample[0], "sample shorter than its key suffix")
    return sample[1 : 1 + sample[0]].decode("utf-8"), sample[1 + sample[0] :]


# ------------------------------------------------------------------ the encoder (a sender)
#
# `encode(inp, projections)` codes `inp` (what a golden NAME.in.json holds: the document and
# the encoder's choices in the spec's terms) as docs/wire.md says a sender does; for every
# golden vector it must give NAME.bin byte for byte.

TYPE_CODES = {v: k for k, v in TYPES.items()}
PROFILE_CODES = {v: k for k, v in PROFILES.items()}
STATUS_CODES = {v: k for k, v in STATUS.items()}


class BitsOut:
    """§3: fields MSB first; zero padding before a byte section and at the end."""

    def __init__(self) -> None:
        self.bits: list[int] = []

    def write(self, value: int, width: int) -> None:
        need(0 <= width <= 56 and 0 <= value < 2**width, f"{value} does not fit {width} bits")
        self.bits += [(value >> (width - 1 - i)) & 1 for i in range(width)]

    def pad(self) -> None:
        self.bits += [0] * (-len(self.bits) % 8)

    def raw(self, data: bytes) -> None:
        self.pad()
        for byte in data:
            self.write(byte, 8)

    def f32(self, x: float) -> None:
        self.write(int.from_bytes(struct.pack(">f", x), "big"), 32)

    def finish(self) -> bytes:
        self.pad()
        return bytes(int("".join(map(str, self.bits[i:i + 8])), 2)
                     for i in range(0, len(self.bits), 8))


def rint(x: float) -> int:
    """Round half to even (§1)."""
    return int(np.rint(x))


def zigzag(v: int) -> int:
    return 2 * v if v >= 0 else -2 * v - 1


def write_ids(ids: list[str], w: BitsOut) -> list:
    """§4.1: kind 1 when every id is one prefix and ASCII digits (no leading zero, <= 16 of
    them, below 10^16); the deltas into the stream now."""
    prefix, values = None, []
    for s in ids:
        k = len(s)
        while k > 0 and s[k - 1] in "0123456789":
            k -= 1
        stem, digits = s[:k], s[k:]
        if not digits or (len(digits) > 1 and digits[0] == "0") or len(digits) > 16 or (
                int(digits) >= 10**16) or (prefix is not None and stem != prefix):
            return [0, list(ids)]
        prefix = stem
        values.append(int(digits))
    deltas = [b - a for a, b in itertools.pairwise(values)]
    dmin = min(deltas) if deltas else 0
    width = bits_for(max(x - dmin for x in deltas)) if deltas else 0
    for x in deltas:
        w.write(x - dmin, width)
    return [1, prefix, values[0], dmin, width]


def write_translation(w: BitsOut, t: list[float], res_um: int) -> None:
    """§6.2 item 2."""
    for x in t:
        u = zigzag(rint(x / (res_um / 1e6)))
        w.write(bits_for(u), 6)
        w.write(u, bits_for(u))


def write_rotation(w: BitsOut, q_wxyz: list[float]) -> None:
    """§6.2 item 3."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    q = q / np.linalg.norm(q)
    i = max(range(4), key=lambda j: (abs(q[j]), -j))  # the largest, the lowest index on ties
    if q[i] < 0:
        q = -q
    w.write(i, 2)
    L = 2**15 - 1
    for r in (q[j] for j in range(4) if j != i):
        w.write(min(max(rint((r + math.sqrt(0.5)) / math.sqrt(2) * L), 0), L), 15)


def write_sigmas(w: BitsOut, C: np.ndarray, bits: int, per_octave: int) -> np.ndarray:
    """§6.2 item 4 / §4.8: log2 codes of sqrt(diag C), from 2^-32."""
    sigma = np.sqrt(np.diag(C))
    for s in sigma:
        need(-32 <= math.log2(s) < -32 + 2**bits / per_octave, "sigma out of range")
        w.write(min(max(rint((math.log2(s) + 32) * per_octave), 0), 2**bits - 1), bits)
    return sigma


def write_covariance(w: BitsOut, covariance: list[list[float]]) -> None:
    """§6.2 item 4: 14-bit sigmas, 15 13-bit CPCs, z clipped before atanh."""
    C = np.asarray(covariance, dtype=np.float64)
    sigma = write_sigmas(w, C, 14, 256)
    L = np.linalg.cholesky(C / np.outer(sigma, sigma))
    zmax = 1 - 1e-15
    for i in range(1, 6):
        rem = 1.0
        for j in range(i):
            z = min(max(L[i, j] / math.sqrt(max(rem, 1e-300)), -zmax), zmax)
            rem -= L[i, j] ** 2
            w.write(min(max(math.floor((math.atanh(z) + 5) / 10 * 8192), 0), 8191), 13)


def encode_objects(inp: dict[str, Any], proj: dict | None) -> list:
    """§4: a map or submap payload."""
    doc, profile, is_submap = inp["document"], inp["profile"], inp["type"] == "submap"
    objs = doc["objects"]
    n, d = len(objs), len(objs[0]["embedding"])
    w = BitsOut()
    ids_hdr = write_ids([o["id"] for o in objs], w)
    labels = [o.get("label") for o in objs]
    label_hdr = None
    if any(lab is not None for lab in labels):  # nil first, then code-point order
        label_hdr = ([None] if None in labels else []) + sorted(
            {lab for lab in labels if lab is not None})
        for lab in labels:
            w.write(label_hdr.index(lab), bits_for(len(label_hdr) - 1))
    n_obs = [min(o["n_obs"], 255) if profile == "compact" else o["n_obs"] for o in objs]
    nobs_bits = bits_for(max(n_obs) - 1)
    for k in n_obs:
        w.write(k - 1, nobs_bits)
    iso = [not isinstance(o["variance"], list) for o in objs]
    if profile == "compact":  # one number: the variance, or the mean summed left to right
        v_iso = []
        for o in objs:
            v = o["variance"]
            if isinstance(v, list):
                total = 0.0
                for x in v:
                    total += x
                v = total / d
            v_iso.append(v)
        v_dim: list[float] = []
        iso = [True] * n
    else:
        v_iso = [o["variance"] for o in objs if not isinstance(o["variance"], list)]
        v_dim = [x for o in objs if isinstance(o["variance"], list) for x in o["variance"]]
    var_mode = 0 if all(iso) else 1 if not any(iso) else 2
    if var_mode == 2:
        for flag in iso:
            w.write(int(flag), 1)

    P = np.array([o["position"] for o in objs], dtype=np.float64)
    pos_hdr = None
    if profile == "full":
        w.raw(P.astype("<f8").tobytes())
    else:
        res_um = inp["resolution_um"]
        q_abs = [[rint(x / (res_um / 1e6)) for x in p] for p in P]
        origin = [min(q[a] for q in q_abs) for a in range(3)]
        widths = [bits_for(max(q[a] - origin[a] for q in q_abs)) for a in range(3)]
        for q in q_abs:
            for a in range(3):
                w.write(q[a] - origin[a], widths[a])
        pos_hdr = [res_um, *origin, *widths]

    var_hdr = None
    if profile == "full":
        w.raw(np.asarray(v_iso, dtype="<f4").tobytes())
        w.raw(np.asarray(v_dim, dtype="<f4").tobytes())
    else:
        ls = [math.log2(v) * 64 for v in v_iso + v_dim]
        lo = math.floor(min(ls))
        hi = max(math.ceil(max(ls)), lo + 1)
        width = {"f16": 16, "int8": 8}.get(profile) or max(1, bits_for(math.ceil((hi - lo) / 2)))
        levels = 2**width - 1
        for x in ls:
            w.write(min(max(rint((x - lo) / (hi - lo) * levels), 0), levels), width)
        var_hdr = [lo, hi, width]

    E = np.array([o["embedding"] for o in objs], dtype=np.float64)
    emb_hdr = None
    if profile == "full":
        w.raw(E.astype("<f4").tobytes())
    elif profile == "f16":
        w.raw(E.astype("<f2").tobytes())  # numpy rounds float64 to binary16 once
    elif profile == "int8":
        scales = [np.float32(np.abs(e).max() / 127) for e in E]
        w.raw(np.array(scales, dtype="<f4").tobytes())
        codes = [[min(max(rint(x / float(s)), -127), 127) if s > 0 else 0 for x in e]
                 for e, s in zip(E, scales)]
        w.raw(np.array(codes, dtype="i1").tobytes())
    else:
        need(proj is not None, "compact needs the projection")
        budget, step = inp["budget_bits"], inp["step16"] / 16
        bits = bit_allocation(proj["scale"], budget)
        sigma = proj["scale"].astype(np.float64)
        C = (E - proj["mean"].astype(np.float64)) @ proj["basis"].astype(np.float64).T
        for c in C:
            for j, b in enumerate(bits):
                if b:
                    q = math.floor(c[j] / sigma[j] / (step * MAX_STEP[b])) + 2 ** (b - 1)
                    w.write(min(max(q, 0), 2**b - 1), b)
        emb_hdr = [bytes.fromhex(proj["id"]), budget, inp["step16"]]

    seq_field = None
    if is_submap and doc.get("seq") != inp["seq"]:
        seq_field = -1 if doc.get("seq") is None else doc["seq"]
    payload = [None if doc["robot_id"] == inp["sender"] else doc["robot_id"], doc["session_id"],
               seq_field, doc.get("stamp"), n, d, ids_hdr, label_hdr, nobs_bits, var_mode,
               pos_hdr, var_hdr, emb_hdr, w.finish()]
    up = doc.get("up")
    if up is not None:
        peak = max(abs(x) for x in up)
        up = [rint(127 * x / peak) for x in up]
    if is_submap and doc.get("keyframe") is not None:
        payload += [up, encode_pose(doc, profile, pos_hdr[0] if pos_hdr else 0)]
    elif up is not None:
        payload.append(up)
    return payload


def encode_pose(doc: dict[str, Any], profile: str, res_um: int) -> list:
    """§4.8."""
    keyframe, odo = doc["keyframe"], doc.get("odometry")
    if odo is None:
        return [keyframe]
    T, C = odo["T_from_to"], odo["covariance"]
    if profile == "full":
        values = [*T["translation"], *T["quaternion_wxyz"], *(x for row in C for x in row)]
        return [keyframe, keyframe - odo["from_keyframe"], np.array(values, "<f8").tobytes()]
    w = BitsOut()
    write_translation(w, T["translation"], res_um)
    write_rotation(w, T["quaternion_wxyz"])
    if profile == "compact":
        write_sigmas(w, np.asarray(C, dtype=np.float64), 11, 32)
    else:
        write_covariance(w, C)
    return [keyframe, keyframe - odo["from_keyframe"], w.finish()]


def encode_factor(inp: dict[str, Any]) -> Any:
    """§6: full, the document as a msgpack map (keys in the documented order); compact."""
    doc = inp["document"]
    corr = doc.get("correspondences", [])
    if inp["profile"] == "full":
        out: dict[str, Any] = {"schema_version": 1}
        for k in NAMES:
            out[k] = doc[k]
        out["T_a_b"] = {"translation": [float(x) for x in doc["T_a_b"]["translation"]],
                        "quaternion_wxyz": [float(x) for x in doc["T_a_b"]["quaternion_wxyz"]]}
        out["covariance"] = [[float(x) for x in row] for row in doc["covariance"]]
        out["correspondences"] = [{"object_a": c["object_a"], "object_b": c["object_b"],
                                   "score": float(c["score"])} for c in corr]
        out["status"] = doc.get("status")
        if doc.get("keyframe_a") is not None:
            out["keyframe_a"], out["keyframe_b"] = doc["keyframe_a"], doc["keyframe_b"]
        return out
    w = BitsOut()
    w.write(STATUS_CODES[doc.get("status")], 2)
    res_um = inp["translation_resolution_um"]
    write_translation(w, doc["T_a_b"]["translation"], res_um)
    write_rotation(w, doc["T_a_b"]["quaternion_wxyz"])
    write_covariance(w, doc["covariance"])
    ids: list[Any] = [None, None]
    if corr:
        ids = [write_ids([c["object_a"] for c in corr], w),
               write_ids([c["object_b"] for c in corr], w)]
        lo = float(np.float32(min(c["score"] for c in corr)))
        hi = float(np.float32(max(c["score"] for c in corr)))
        w.f32(lo)
        w.f32(hi)
        if hi > lo:
            for c in corr:
                w.write(min(max(rint((c["score"] - lo) / (hi - lo) * 255), 0), 255), 8)
    tail = [] if doc.get("keyframe_a") is None else [doc["keyframe_a"], doc["keyframe_b"]]
    return [*(doc[k] for k in NAMES), res_um, len(corr), *ids, w.finish(), *tail]


def encode(inp: dict[str, Any], projections: dict[str, dict] | None = None) -> bytes:
    """§2: one message, packed as mergesvc packs (§1: shortest integers, float64 floats)."""
    kind, profile, doc = inp["type"], inp["profile"], inp["document"]
    if kind in ("map", "submap"):
        proj = next(iter((projections or {}).values()), None) if profile == "compact" else None
        payload = encode_objects(inp, proj)
    elif kind == "factor":
        payload = encode_factor(inp)
    else:
        payload = [doc["code"], doc.get("detail", ""), doc.get("about_seq")]
    envelope = [1, 1, TYPE_CODES[kind], inp["sender"], inp["seq"], PROFILE_CODES[profile],
                payload]
    return msgpack.packb(envelope, use_bin_type=True)
