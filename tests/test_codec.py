from __future__ import annotations

import hashlib
import math
from pathlib import Path

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from mergesvc.bench import score_case
from mergesvc.core.model import ErrorMessage, Factor, ObjectMap, Submap
from mergesvc.core.pipeline import match
from mergesvc.errors import CodecError, DecodeError, InputError, SchemaError
from mergesvc.sim import make_scenario
from mergesvc.wire import bits as codec
from mergesvc.wire import projection
from mergesvc.wire.bits import BitReader, BitWriter, bounded_bits
from mergesvc.wire.envelope import decode_message, encode_message
from mergesvc.wire.files import decode_file, encode_file, load_model
from mergesvc.wire.profiles import CodecLimits, CodecSettings, MessageType, Profile
from mergesvc.wire.projection import Projection

D = 16
RES_M = 0.01  # default position resolution
FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


WORLD = np.random.default_rng(99).normal(size=(4, D))  # class-like structure of one world


def _objects(n: int, rng: np.random.Generator, labels: bool = True) -> list[dict]:
    out = []
    for k in range(n):
        emb = rng.normal(size=4) @ WORLD + 0.05 * rng.normal(size=D)
        var = float(rng.uniform(0.01, 1)) if k % 3 else rng.uniform(0.01, 1, size=D).tolist()
        obj = {
            "id": f"o{3 * k + 7}",
            "position": rng.uniform(-40, 40, size=3).tolist(),
            "embedding": emb.tolist(),
            "variance": var,
            "n_obs": int(rng.integers(1, 12)),
        }
        if labels and k % 2:
            obj["label"] = ["buoy", "tire", "crate"][k % 3]
        out.append(obj)
    return out


def _submap(n: int = 9, seed: int = 0, **kw) -> Submap:
    rng = np.random.default_rng(seed)
    return Submap(
        robot_id="auv2", session_id="s1", seq=5, stamp=12.5, objects=_objects(n, rng, **kw)
    )


def _factor(rng: np.random.Generator, n_corr: int = 3, max_cond: float = 3e3) -> Factor:
    while True:
        A = rng.normal(size=(6, 6 + int(rng.integers(0, 6))))
        if np.linalg.cond(A @ A.T) < max_cond:
            break
    Cn = A @ A.T
    d = np.sqrt(np.diag(Cn))
    sig = np.concatenate([np.exp(rng.uniform(-9, 0, 3)), np.exp(rng.uniform(-7, 2.3, 3))])
    C = Cn / np.outer(d, d) * np.outer(sig, sig)
    q = Rotation.random(random_state=int(rng.integers(1 << 31))).as_quat()
    return Factor(
        factor_id="f17",
        robot_a="auv1",
        session_a="s0",
        robot_b="auv2",
        session_b="s1",
        T_a_b={
            "translation": rng.uniform(-1000, 1000, 3).tolist(),
            "quaternion_wxyz": [q[3], q[0], q[1], q[2]],
        },
        covariance=((C + C.T) / 2).tolist(),
        correspondences=[
            {"object_a": f"m{40 + 3 * k}", "object_b": f"s{k}", "score": float(rng.uniform(0.2, 1))}
            for k in range(n_corr)
        ],
        status="accepted",
    )


def _odometry(
    rng: np.random.Generator, from_keyframe: int = 1233, move_m: float = 5.0
) -> dict:
    """A random odometry step: rotation < 0.3 rad, translation within move_m per axis, a
    covariance with correlations (std devs 1e-4..0.05 rad, 1e-3..0.5 m)."""
    A = rng.normal(size=(6, 9))
    Cn = A @ A.T
    d = np.sqrt(np.diag(Cn))
    sig = np.concatenate([np.exp(rng.uniform(-9, -3, 3)), np.exp(rng.uniform(-7, -0.7, 3))])
    C = Cn / np.outer(d, d) * np.outer(sig, sig)
    q = Rotation.from_rotvec(rng.uniform(-0.17, 0.17, 3)).as_quat()
    return {
        "from_keyframe": from_keyframe,
        "T_from_to": {
            "translation": rng.uniform(-move_m, move_m, 3).tolist(),
            "quaternion_wxyz": [q[3], q[0], q[1], q[2]],
        },
        "covariance": ((C + C.T) / 2).tolist(),
    }


def _posed(sub: Submap, rng: np.random.Generator, keyframe: int = 1234, **kw) -> Submap:
    """`sub` anchored at `keyframe` with odometry from keyframe - 1."""
    doc = {**sub.model_dump(), "keyframe": keyframe, "odometry": _odometry(rng, keyframe - 1, **kw)}
    return Submap.model_validate(doc)


def _rotation_error(q1, q2) -> float:
    R1 = Rotation.from_quat([*q1[1:], q1[0]])
    R2 = Rotation.from_quat([*q2[1:], q2[0]])
    return float((R1.inv() * R2).magnitude())


@pytest.fixture(scope="module")
def fleet() -> tuple[Submap, Projection]:
    """A submap and a projection fitted on other objects of the same world."""
    rng = np.random.default_rng(1)
    train = np.array([o["embedding"] for o in _objects(200, rng)])
    return _submap(), Projection.fit(train)


def _round(model, profile, proj=None, **kw):
    data = encode_message(model, profile, "auv2", 5, projection=proj, **kw)
    env, out = decode_message(data, proj)
    return data, env, out


# ------------------------------------------------------------------ bit packing


@given(
    st.lists(
        st.integers(0, codec.MAX_FIELD_BITS).flatmap(
            lambda w: st.tuples(st.just(w), st.integers(0, (1 << w) - 1))
        ),
        max_size=40,
    )
)
@FUZZ
def test_bit_packer_matches_brute_force(fields: list[tuple[int, int]]) -> None:
    w = BitWriter()
    for width, value in fields:
        w.write(value, width)
    data = w.getvalue()
    bits = "".join(format(v, f"0{width}b") if width else "" for width, v in fields)
    bits += "0" * (-len(bits) % 8)
    assert data == bytes(int(bits[i : i + 8], 2) for i in range(0, len(bits), 8))
    r = BitReader(data)
    assert [r.read(width) for width, _ in fields] == [v for _, v in fields]
    r.finish()
    # vectorised read of the same stream
    r = BitReader(data)
    got = r.read_fields(np.array([width for width, _ in fields], dtype=np.int64))
    assert got.tolist() == [v for _, v in fields]


def test_bit_fields_are_bounded() -> None:
    assert bounded_bits(0, 25, 0.01) == 12  # ceil(log2(2501))
    assert bounded_bits(-1, 1, 1) == 2 and bounded_bits(3, 3, 0.1) == 0
    assert all(codec.unzigzag(codec.zigzag(v)) == v for v in range(-300, 300))
    w = BitWriter()
    with pytest.raises(CodecError):
        w.write(8, 3)
    w.write(5, 3)
    w.write_bytes(b"ab")
    r = BitReader(w.getvalue())
    assert r.read(3) == 5 and r.read_bytes(2) == b"ab"
    with pytest.raises(DecodeError, match="truncated"):
        r.read(1)


# ------------------------------------------------------------------ object profiles


def test_full_is_exact_to_float32(fleet) -> None:
    sub, _ = fleet
    _, env, out = _round(sub, "full")
    assert (env.msg_type, env.sender, env.seq, env.profile) == (
        MessageType.SUBMAP,
        "auv2",
        5,
        Profile.FULL,
    )
    assert isinstance(out, Submap) and (out.seq, out.stamp, out.robot_id) == (5, 12.5, "auv2")
    for a, b in zip(sub.objects, out.objects):
        assert (a.id, a.position, a.n_obs, a.label) == (b.id, b.position, b.n_obs, b.label)
        assert b.embedding == np.float32(a.embedding).astype(float).tolist()
        assert type(a.variance) is type(b.variance)
        assert np.array_equal(np.float32(a.variance), np.float32(b.variance))


@pytest.mark.parametrize("profile", ["f16", "int8"])
def test_f16_int8_within_bounds(fleet, profile: str) -> None:
    sub, _ = fleet
    _, _, out = _round(sub, profile)
    a, b = sub.arrays(), out.arrays()
    assert a.ids == b.ids and np.array_equal(a.n_obs, b.n_obs)
    assert [o.label for o in sub.objects] == [o.label for o in out.objects]
    assert np.abs(a.position_xyz_m - b.position_xyz_m).max() <= RES_M / 2 + 1e-9
    E, Eh = a.embeddings_nd, b.embeddings_nd
    if profile == "f16":  # float16: relative 2^-11 per component
        assert np.all(np.abs(Eh - E) <= 2.0**-11 * np.abs(E) + 2.0**-24)
        width = 16
    else:  # int8 with a scale per vector: half a step of max|e| / 127
        peak = np.abs(E).max(axis=1, keepdims=True)
        assert np.all(np.abs(Eh - E) <= peak / 254 * (1 + 1e-6))
        width = 8
    # variances log-quantised over the message's range (+1/64 octave of range rounding)
    octaves = np.log2(a.variances_nd.max() / a.variances_nd.min()) + 2 / 64
    half_step = octaves / (2 * ((1 << width) - 1))
    assert np.abs(np.log2(b.variances_nd / a.variances_nd)).max() <= half_step + 1e-12
    assert [isinstance(o.variance, list) for o in sub.objects] == [
        isinstance(o.variance, list) for o in out.objects
    ]


def test_compact_error_is_what_the_projection_drops(fleet) -> None:
    sub, proj = fleet
    st_ = CodecSettings()
    _, env, out = _round(sub, "compact", proj)
    assert env.projection_id == proj.id
    a, b = sub.arrays(), out.arrays()
    assert a.ids == b.ids and np.array_equal(np.minimum(a.n_obs, 255), b.n_obs)
    assert np.abs(a.position_xyz_m - b.position_xyz_m).max() <= RES_M / 2 + 1e-9
    # one variance per object, the mean, within 1/64 octave (step <= 1/32 octave)
    assert all(isinstance(o.variance, float) for o in out.objects)
    assert np.abs(np.log2(b.uncertainty_s / a.uncertainty_s)).max() <= 1 / 64 + 1e-12
    # embedding error = coefficient error (orthonormal basis), bounded per coefficient by
    # half a step, or by the distance beyond the outer bin centre, or |c| without bits
    bits = proj.bit_allocation(st_.embedding_bits)
    assert bits.sum() == min(st_.embedding_bits, 8 * proj.k)
    step = np.array([st_.coef_step_scale * projection._MAX_STEP[x] if x else 0 for x in bits])
    c = proj.coefficients(a.embeddings_nd) / proj.scale_k
    outer = (np.where(bits > 0, 2.0 ** (bits - 1), 0) - 0.5) * step
    bound = np.where(bits > 0, np.maximum(step / 2, np.abs(c) - outer), np.abs(c))
    bound = np.sqrt(((bound * proj.scale_k) ** 2).sum(axis=1))
    kept = proj.reconstruct(proj.coefficients(a.embeddings_nd))
    err = np.linalg.norm(b.embeddings_nd - kept, axis=1)
    assert np.all(err <= bound * (1 + 1e-3) + 1e-4)
    cos = (a.unit_embeddings_nd * b.unit_embeddings_nd).sum(axis=1)
    assert cos.min() > 0.95  # the projection was fitted on this world


def test_envelope_fields_and_other_messages() -> None:
    sub = _submap(4)
    # robot id differs from sender, submap seq differs from the envelope seq, or is None
    env, out = decode_message(encode_message(sub, "int8", "relay", 9))
    assert (env.sender, env.seq, out.robot_id, out.seq) == ("relay", 9, "auv2", 5)
    no_seq = sub.model_copy(update={"seq": None})
    _, out = decode_message(encode_message(no_seq, "f16", "auv2", 3))
    assert out.seq is None
    m = ObjectMap(robot_id="svc", session_id="g", objects=sub.objects)
    env, out = decode_message(encode_message(m, "full", "svc", 1))
    assert env.msg_type is MessageType.MAP and type(out) is ObjectMap
    err = ErrorMessage(code="decode_failed", detail="bad submap", about_seq=4)
    env, out = decode_message(encode_message(err, "compact", "svc", 2))
    assert env.msg_type is MessageType.ERROR and out == err


def test_ids_fall_back_to_strings() -> None:
    objs = _objects(5, np.random.default_rng(3))
    for k, o in enumerate(objs):
        o["id"] = ["a1", "b2", "m007", "x", "lobster-cage"][k]
    sub = Submap(robot_id="r", session_id="s", objects=objs)
    _, _, out = _round(sub, "int8")
    assert [o.id for o in out.objects] == [o.id for o in sub.objects]


def test_compact_bytes_per_object_on_a_20_object_submap() -> None:
    sc = make_scenario("kitti", 0)
    sub = Submap(robot_id="car2", session_id="s1", seq=0, objects=sc.submap.objects[:20])
    assert len(sub.objects) == 20
    proj = Projection.fit(sc.map.arrays().embeddings_nd)
    data = encode_message(sub, "compact", "car2", 0, projection=proj)
    assert len(data) / 20 <= 64
    full = encode_message(sub, "full", "car2", 0)
    assert len(full) / len(data) > 20


def test_compact_matches_agree_with_float32() -> None:
    """Node accuracy after a compact round trip of map and submap stays within the budget
    (1 point) of float32's; projection fitted on map embeddings only."""
    for family, seed in (("kitti", 0), ("underwater", 3)):
        sc = make_scenario(family, seed)
        proj = Projection.fit(sc.map.arrays().embeddings_nd)
        _, sub = decode_message(encode_message(sc.submap, "compact", "r", 0, projection=proj), proj)
        _, mp = decode_message(encode_message(sc.map, "compact", "svc", 0, projection=proj), proj)
        ref = score_case(sc, match(sc.map, sc.submap))["accuracy"]
        got = score_case(sc, match(mp, sub))["accuracy"]
        assert got >= ref - 0.01, (family, seed, ref, got)


# ------------------------------------------------------------------ projection


def test_projection_save_load_and_refusal(tmp_path: Path, fleet) -> None:
    sub, proj = fleet
    again = Projection.fit(
        np.array([o["embedding"] for o in _objects(200, np.random.default_rng(1))])
    )
    assert again.id == proj.id and len(proj.id) == 8  # content hash: both ends agree
    path = proj.save(tmp_path / "p.npz")
    loaded = Projection.load(path)
    assert loaded.id == proj.id and np.array_equal(loaded.basis_kd, proj.basis_kd)
    # tampered content no longer matches its id
    with np.load(path) as z:
        arrays = dict(z)
    arrays["mean"] = arrays["mean"] + 1
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(SchemaError, match="does not match"):
        Projection.load(tmp_path / "bad.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(DecodeError):
        Projection.load(tmp_path / "junk.npz")
    # a decoder without the projection refuses, naming the id
    data = encode_message(sub, "compact", "auv2", 1, projection=proj)
    with pytest.raises(DecodeError, match=proj.id):
        decode_message(data)
    other = Projection.fit(np.random.default_rng(5).normal(size=(50, D)))
    with pytest.raises(DecodeError, match="does not have"):
        decode_message(data, [other])
    with pytest.raises(CodecError):
        encode_message(sub, "compact", "auv2", 1)


# ------------------------------------------------------------------ decoding hostile bytes


def _valid_messages() -> list[tuple[bytes, Projection | None]]:
    sub = _submap(4, seed=2)
    proj = Projection.fit(np.random.default_rng(4).normal(size=(30, D)))
    out = [(encode_message(sub, p, "auv2", 3), None) for p in ("full", "f16", "int8")]
    out.append((encode_message(sub, "compact", "auv2", 3, projection=proj), proj))
    f = _factor(np.random.default_rng(0))
    out += [(encode_message(f, p, "svc", 1), None) for p in ("full", "compact")]
    out.append((encode_message(ErrorMessage(code="x"), "full", "svc", 1), None))
    # keyframe + odometry (issue 11): appended, so the indexes above stay
    posed = _posed(sub, np.random.default_rng(6))
    out += [(encode_message(posed, p, "auv2", 3), None) for p in ("full", "f16")]
    out.append((encode_message(posed, "compact", "auv2", 3, projection=proj), proj))
    fk = f.model_copy(update={"keyframe_a": 1234, "keyframe_b": 77})
    out += [(encode_message(fk, p, "svc", 1), None) for p in ("full", "compact")]
    return out


VALID = _valid_messages()


def _decode_safely(data: bytes, proj: Projection | None = None) -> None:
    try:
        decode_message(data, proj)
    except (DecodeError, SchemaError) as exc:
        assert "\n" not in str(exc)


@given(st.binary(max_size=300))
@FUZZ
def test_random_bytes_only_raise_decode_errors(data: bytes) -> None:
    _decode_safely(data)


@given(
    st.sampled_from(range(len(VALID))),
    st.lists(
        st.tuples(st.integers(0, 10**6), st.integers(0, 255), st.sampled_from("fdit")),
        min_size=1,
        max_size=6,
    ),
)
@FUZZ
def test_mutated_messages_only_raise_decode_errors(which: int, edits: list) -> None:
    data, proj = VALID[which]
    buf = bytearray(data)
    for pos, byte, op in edits:
        i = pos % max(len(buf), 1)
        if op == "f" and buf:
            buf[i] ^= 1 << (byte % 8)
        elif op == "d" and buf:
            del buf[i]
        elif op == "i":
            buf.insert(i, byte)
        else:
            del buf[i:]
    _decode_safely(bytes(buf), proj)


_msgpack_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats()
    | st.text(max_size=8)
    | st.binary(max_size=16),
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=4), inner, max_size=3)
    ),
    max_leaves=8,
)


@given(st.sampled_from(range(len(VALID))), st.data())
@FUZZ
def test_structurally_mutated_messages_only_raise_decode_errors(which: int, data) -> None:
    """Replace one field anywhere in the decoded msgpack tree with a random value."""
    raw, proj = VALID[which]
    tree = msgpack.unpackb(raw, raw=False)
    node, path = tree, []
    while isinstance(node, list | dict) and node and data.draw(st.booleans()):
        keys = list(range(len(node))) if isinstance(node, list) else list(node)
        key = data.draw(st.sampled_from(keys))
        path.append((node, key))
        node = node[key]
    if not path:
        path.append((tree, data.draw(st.integers(0, len(tree) - 1))))
    parent, key = path[-1]
    parent[key] = data.draw(_msgpack_values)
    _decode_safely(msgpack.packb(tree, use_bin_type=True), proj)


def test_versions_types_and_limits() -> None:
    data, _ = VALID[0]
    tree = msgpack.unpackb(data, raw=False)
    for k, v, err, msg in [
        (0, 2, SchemaError, "schema_version 2"),
        (1, 99, SchemaError, "codec_version"),
        (2, 42, DecodeError, "unknown message type"),
        (2, 5, DecodeError, "reserved"),
        (5, 9, DecodeError, "unknown profile"),
        (3, "", DecodeError, "sender"),
        (4, -1, DecodeError, "seq"),
    ]:
        bad = list(tree)
        bad[k] = v
        with pytest.raises(err, match=msg):
            decode_message(msgpack.packb(bad, use_bin_type=True))
    with pytest.raises(DecodeError, match="exceeds"):
        decode_message(data, limits=CodecLimits(max_message_bytes=len(data) - 1))
    with pytest.raises(DecodeError, match="objects"):
        decode_message(data, limits=CodecLimits(max_objects=3))
    with pytest.raises(DecodeError, match="dimension"):
        decode_message(data, limits=CodecLimits(max_dim=D - 1))
    with pytest.raises(DecodeError, match="exceeds the limit"):
        decode_message(data, limits=CodecLimits(max_values=4 * D - 1))
    with pytest.raises(DecodeError):
        decode_message(b"")
    with pytest.raises(CodecError, match="wire limits"):
        encode_message(_submap(4), "full", "a", 0, limits=CodecLimits(max_objects=3))


def test_decompression_bomb_is_refused_before_allocating() -> None:
    """A 100-byte compact message claiming 20 000 objects of 4096 dims."""
    data, proj = VALID[3]
    tree = msgpack.unpackb(data, raw=False)
    tree[6][4], tree[6][5] = 20_000, 4096
    with pytest.raises(DecodeError, match="exceeds the limit"):
        decode_message(msgpack.packb(tree, use_bin_type=True), proj)
    tree[6][4], tree[6][5] = 20_000, D  # within the limits, but the stream is far too short
    with pytest.raises(DecodeError, match="truncated"):
        decode_message(msgpack.packb(tree, use_bin_type=True), proj)


def test_nan_and_inf_are_rejected() -> None:
    sub = _submap(3)
    tree = msgpack.unpackb(encode_message(sub, "full", "auv2", 5), raw=False)
    blob = bytearray(tree[6][13])
    blob[-4:] = np.array([np.nan], dtype="<f4").tobytes()  # last embedding value
    tree[6][13] = bytes(blob)
    with pytest.raises(SchemaError, match="NaN"):
        decode_message(msgpack.packb(tree, use_bin_type=True))
    tree = msgpack.unpackb(encode_message(sub, "full", "auv2", 5), raw=False)
    tree[6][3] = float("inf")  # stamp
    with pytest.raises(SchemaError, match="stamp"):
        decode_message(msgpack.packb(tree, use_bin_type=True))
    big = sub.model_copy(
        update={
            "objects": [
                sub.objects[0].model_copy(update={"embedding": [1e6] * D}),
                *sub.objects[1:],
            ]
        }
    )
    with pytest.raises(CodecError, match="float16"):
        encode_message(big, "f16", "auv2", 5)


# ------------------------------------------------------------------ factors


@given(st.integers(0, 2**32 - 1))
@settings(max_examples=60, deadline=None)
def test_factor_compact_round_trip(seed: int) -> None:
    """Stated tolerances (covariances with condition number < 3e3): rotation <= 1.5e-4 rad,
    translation <= half the 1 mm resolution per axis, std devs <= 0.14 %, correlations
    <= 2e-3, KL(true || decoded) <= 1e-3 nats; decoded covariance symmetric and PD."""
    rng = np.random.default_rng(seed)
    f = _factor(rng, n_corr=int(rng.integers(0, 5)))
    data = encode_message(f, "compact", "svc", 1)
    env, g = decode_message(data)
    assert env.msg_type is MessageType.FACTOR and env.profile is Profile.COMPACT
    assert (g.factor_id, g.robot_b, g.status) == (f.factor_id, f.robot_b, f.status)
    q1, q2 = f.T_a_b.quaternion_wxyz, g.T_a_b.quaternion_wxyz
    R1 = Rotation.from_quat([*q1[1:], q1[0]])
    R2 = Rotation.from_quat([*q2[1:], q2[0]])
    assert (R1.inv() * R2).magnitude() <= 1.5e-4  # 15-bit smallest-three: measured <= 1.05e-4
    assert np.abs(np.subtract(g.T_a_b.translation, f.T_a_b.translation)).max() <= 5e-4 + 1e-9
    C, Ch = np.array(f.covariance), np.array(g.covariance)
    assert np.array_equal(Ch, Ch.T)
    np.linalg.cholesky(Ch)
    s, sh = np.sqrt(np.diag(C)), np.sqrt(np.diag(Ch))
    assert np.abs(sh / s - 1).max() <= 2 ** (1 / 512) - 1 + 1e-9
    assert np.abs(Ch / np.outer(sh, sh) - C / np.outer(s, s)).max() <= 2e-3
    kl = 0.5 * (
        np.trace(np.linalg.solve(Ch, C)) - 6 + np.linalg.slogdet(Ch)[1] - np.linalg.slogdet(C)[1]
    )
    assert kl <= 1e-3
    assert [(c.object_a, c.object_b) for c in g.correspondences] == [
        (c.object_a, c.object_b) for c in f.correspondences
    ]
    if f.correspondences:
        scores = np.array([c.score for c in f.correspondences])
        span = np.ptp(scores)
        got = np.array([c.score for c in g.correspondences])
        assert np.abs(got - scores).max() <= span / 510 + 1e-6
    n_corr_bytes = 12 * len(f.correspondences)
    assert len(data) <= 100 + n_corr_bytes  # pose + covariance in ~50 bytes, rest ids


def test_factor_full_is_exact_and_bad_covariance_is_refused() -> None:
    f = _factor(np.random.default_rng(7))
    env, g = decode_message(encode_message(f, "int8", "svc", 1))
    assert env.profile is Profile.FULL and g == f
    # an ill-conditioned covariance still decodes symmetric positive definite
    C = np.diag([1e-8, 1, 1, 1, 1, 1.0])
    C[1, 2] = C[2, 1] = 0.999999
    g = f.model_copy(update={"covariance": C.tolist()})
    _, h = decode_message(encode_message(g, "compact", "svc", 1))
    np.linalg.cholesky(np.array(h.covariance))
    with pytest.raises(ValueError, match="positive definite"):
        Factor(**{**f.model_dump(), "covariance": np.diag([1, 1, 1, 1, 1, -1.0]).tolist()})


# ------------------------------------------------------------------ keyframes and odometry

# Messages without keyframes are byte-identical to the codec before issue 11: these are the
# encodings of `_pinned_models()` by that codec (commit 02a19cd); values chosen exactly
# representable (powers of two, no correlations) so the bytes do not depend on the platform.
PINNED = [
    ("submap full", 150, "ed364451100be06bb7bd592bf549378c"),
    ("submap f16", 101, "6e0c1a2b983d6b7f8aace2404d855d03"),
    ("submap int8", 96, "3a460569727a37a1f0fb81647b5cf906"),
    ("submap up int8", 92, "6f13a41295679729346298f2e39be02f"),
    ("map f16", 95, "398818fdd0bd56998f5abb6bd763a021"),
    ("factor full", 651, "d10e6b2429184ec487ac1b773a832080"),
    ("factor compact", 110, "26e8d3e50c95bcb1c2975929604c8850"),
]


def _pinned_models() -> dict[str, tuple]:
    objs = [
        {"id": "o7", "position": [1.25, -3.5, 0.75], "embedding": [0.5, -0.25, 1.0, 2.0],
         "variance": 0.125, "n_obs": 3, "label": "buoy"},
        {"id": "o10", "position": [-2.0, 4.25, 1.5], "embedding": [-1.0, 0.75, 0.0, 0.5],
         "variance": [0.25, 0.5, 1.0, 2.0], "n_obs": 1},
    ]  # fmt: skip
    sub = Submap(robot_id="auv2", session_id="s1", seq=5, stamp=12.5, objects=objs)
    sub_up = Submap(robot_id="auv2", session_id="s1", seq=5, objects=objs, up=(0.0, 0.0, 1.0))
    f = Factor(
        factor_id="f17", robot_a="auv1", session_a="s0", robot_b="auv2", session_b="s1",
        T_a_b={"translation": [12.5, -3.25, 0.5], "quaternion_wxyz": [1.0, 0.0, 0.0, 0.0]},
        covariance=np.diag([0.25] * 6).tolist(),
        correspondences=[{"object_a": "m40", "object_b": "s0", "score": 0.5},
                         {"object_a": "m43", "object_b": "s1", "score": 1.0}],
        status="accepted",
    )  # fmt: skip
    return {
        "submap full": (sub, "full"),
        "submap f16": (sub, "f16"),
        "submap int8": (sub, "int8"),
        "submap up int8": (sub_up, "int8"),
        "map f16": (ObjectMap(robot_id="svc", session_id="g", objects=objs), "f16"),
        "factor full": (f, "full"),
        "factor compact": (f, "compact"),
    }


def test_messages_without_keyframes_are_unchanged() -> None:
    models = _pinned_models()
    for name, n_bytes, digest in PINNED:
        model, profile = models[name]
        data = encode_message(model, profile, "auv2", 5)
        assert (len(data), hashlib.sha256(data).hexdigest()[:32]) == (n_bytes, digest), name
    # the full factor's document has no keyframe keys when they are absent
    tree = msgpack.unpackb(encode_message(models["factor full"][0], "full", "s", 1), raw=False)
    assert "keyframe_a" not in tree[6] and "keyframe_b" not in tree[6]


@pytest.mark.parametrize("profile", ["full", "f16", "int8", "compact"])
@pytest.mark.parametrize("up", [False, True])
def test_pose_fields_are_trailing_and_optional(fleet, profile: str, up: bool) -> None:
    """With keyframe (and odometry) the payload gains a 16th field and nothing else changes:
    without it, the message is the one of the same submap without keyframe."""
    sub, proj = fleet
    if up:
        sub = sub.model_copy(update={"up": (0.0, 0.0, 1.0)})
    plain = msgpack.unpackb(encode_message(sub, profile, "auv2", 5, projection=proj), raw=False)
    assert len(plain[6]) == (15 if up else 14)
    for posed in (sub.model_copy(update={"keyframe": 9}), _posed(sub, np.random.default_rng(2))):
        data = encode_message(posed, profile, "auv2", 5, projection=proj)
        tree = msgpack.unpackb(data, raw=False)
        assert len(tree[6]) == 16 and (tree[6][14] is None) != up
        assert tree[6][15][0] == posed.keyframe
        assert tree[6][:14] == plain[6][:14] and tree[:6] == plain[:6]
        stripped = [*tree[:6], tree[6][:15] if up else tree[6][:14]]
        assert msgpack.packb(stripped, use_bin_type=True) == encode_message(
            sub, profile, "auv2", 5, projection=proj
        )
        _, out = decode_message(data, proj)
        assert out.keyframe == posed.keyframe and (out.up is None) != up


@pytest.mark.parametrize("profile", ["full", "f16", "int8", "compact"])
def test_keyframe_and_odometry_round_trip(fleet, profile: str) -> None:
    """full: exact. f16 / int8 / compact: translation within half the position resolution per
    axis, rotation <= 1.5e-4 rad (15-bit smallest three); f16 / int8: std devs <= 0.14 %,
    correlations <= 2e-3; compact: std devs within half a 1/32 octave step (<= 1.1 %), the
    covariance diagonal (compact drops the odometry's correlations)."""
    sub, proj = fleet
    for seed in range(20):
        posed = _posed(sub, np.random.default_rng(seed), keyframe=1 + 997 * seed)
        _, out = decode_message(encode_message(posed, profile, "auv2", 5, projection=proj), proj)
        assert isinstance(out, Submap) and out.keyframe == posed.keyframe
        a, b = posed.odometry, out.odometry
        assert b is not None and b.from_keyframe == a.from_keyframe
        if profile == "full":
            assert b == a  # bit for bit (the objects: float32 embeddings, as always)
            continue
        assert np.abs(np.subtract(b.T_from_to.translation, a.T_from_to.translation)).max() <= (
            RES_M / 2 + 1e-9
        )
        assert _rotation_error(a.T_from_to.quaternion_wxyz, b.T_from_to.quaternion_wxyz) <= 1.5e-4
        C, Ch = np.array(a.covariance), np.array(b.covariance)
        np.linalg.cholesky(Ch)
        s, sh = np.sqrt(np.diag(C)), np.sqrt(np.diag(Ch))
        if profile == "compact":
            assert np.abs(np.log2(sh / s)).max() <= 1 / 64 + 1e-12
            assert np.array_equal(Ch, np.diag(np.diag(Ch)))
        else:
            assert np.abs(sh / s - 1).max() <= 2 ** (1 / 512) - 1 + 1e-9
            assert np.abs(Ch / np.outer(sh, sh) - C / np.outer(s, s)).max() <= 2e-3
    # a keyframe without odometry (a session's first submap), and keyframe 0
    for k in (0, 2**40):
        first = sub.model_copy(update={"keyframe": k})
        _, out = decode_message(encode_message(first, profile, "a", 5, projection=proj), proj)
        assert out.keyframe == k and out.odometry is None


def test_compact_pose_budget(fleet) -> None:
    """Keyframe + odometry add at most 32 bytes to a compact submap (measured: 30 for a 5 m
    step at keyframe 1234); also for keyframes < 65536 and steps up to 80 m per axis."""
    sub, proj = fleet
    base = len(encode_message(sub, "compact", "auv2", 5, projection=proj))
    rng = np.random.default_rng(3)
    added = []
    for keyframe, move_m in [(1234, 5.0), (100, 1.0), (65535, 80.0)]:
        for _ in range(5):
            posed = _posed(sub, rng, keyframe=keyframe, move_m=move_m)
            added.append(len(encode_message(posed, "compact", "auv2", 5, projection=proj)) - base)
    assert max(added) <= 32, added
    only_keyframe = sub.model_copy(update={"keyframe": 1234})
    assert len(encode_message(only_keyframe, "compact", "auv2", 5, projection=proj)) - base <= 8


def _with_pose(pose, profile: str = "full", up=None, sub: Submap | None = None) -> bytes:
    """A hand-built submap message carrying `pose` as its 16th payload field."""
    sub = sub or _submap(3)
    tree = msgpack.unpackb(encode_message(sub, profile, "auv2", 5), raw=False)
    tree[6] = [*tree[6][:14], up, pose]
    return msgpack.packb(tree, use_bin_type=True)


def test_malformed_pose_is_refused_cleanly() -> None:
    sub = _submap(3)
    posed = _posed(sub, np.random.default_rng(1), keyframe=20)
    full = msgpack.unpackb(encode_message(posed, "full", "auv2", 5), raw=False)[6][15]
    f16 = msgpack.unpackb(encode_message(posed, "f16", "auv2", 5), raw=False)[6][15]
    assert decode_message(_with_pose(full))[1].odometry == posed.odometry  # the builder works
    nan = bytearray(full[2])
    nan[8:16] = np.array([np.nan], dtype="<f8").tobytes()  # translation y
    inf = bytearray(full[2])
    inf[-8:] = np.array([np.inf], dtype="<f8").tobytes()  # covariance[5][5]
    asym = np.frombuffer(full[2], dtype="<f8").copy()
    asym[7 + 1] += 1.0  # covariance[0][1]
    neg = np.frombuffer(full[2], dtype="<f8").copy()
    neg[7] = -1.0  # covariance[0][0]
    quat = np.frombuffer(full[2], dtype="<f8").copy()
    quat[3] = 2.0  # quaternion w
    cases = [
        ([None, 1, full[2]], DecodeError, "odometry needs keyframe"),
        ([20, 0, full[2]], SchemaError, "from_keyframe 20 must be before keyframe 20"),
        ([20, -3, full[2]], SchemaError, "from_keyframe 23 must be before keyframe 20"),
        ([20, 21, full[2]], SchemaError, "odometry.from_keyframe"),
        ([20, 1, bytes(nan)], SchemaError, "translation.1: .*finite"),
        ([20, 1, bytes(inf)], SchemaError, "covariance.5.5: .*finite"),
        ([20, 1, asym.tobytes()], SchemaError, "symmetric"),
        ([20, 1, neg.tobytes()], SchemaError, "positive definite"),
        ([20, 1, quat.tobytes()], SchemaError, "unit norm"),
        ([20, 1, full[2][:-8]], DecodeError, "expected 344 bytes"),
        ([20, 1, [0.0] * 43], DecodeError, "expected binary"),
        ([-1], DecodeError, "keyframe: -1 outside"),
        ([2**64 - 1], DecodeError, "keyframe"),
        (["7"], DecodeError, "keyframe: expected an integer"),
        ([20, 1.0, full[2]], DecodeError, "odometry.delta"),
        ([20, 1], DecodeError, "expected \\[keyframe\\] or"),
        ([], DecodeError, "got 0 fields"),
        (None, DecodeError, "pose: expected an array"),
        ({"keyframe": 3}, DecodeError, "pose: expected an array"),
    ]
    for pose, err, msg in cases:
        with pytest.raises(err, match=msg) as info:
            decode_message(_with_pose(pose))
        assert "\n" not in str(info.value)
    # lossy profiles: the bit stream must be complete, and nothing may follow it
    for blob, msg in [(f16[2][:-3], "truncated"), (f16[2] + b"\0", "trailing")]:
        with pytest.raises(DecodeError, match=msg):
            decode_message(_with_pose([20, 1, blob], "f16"))
    # the 15th field may be nil only when a pose follows; a map carries no pose; 17 fields
    tree = msgpack.unpackb(encode_message(sub, "int8", "auv2", 5), raw=False)
    for payload, msg in [
        ([*tree[6], None], "up: expected an array"),
        ([*tree[6], None, [3], 0], "expected 14 to 16 fields, got 17"),
    ]:
        with pytest.raises(DecodeError, match=msg):
            decode_message(msgpack.packb([*tree[:6], payload], use_bin_type=True))
    m = ObjectMap(robot_id="svc", session_id="g", objects=sub.objects)
    tree = msgpack.unpackb(encode_message(m, "full", "svc", 1), raw=False)
    tree[6] = [*tree[6], None, [3]]
    with pytest.raises(DecodeError, match="a map carries no keyframe"):
        decode_message(msgpack.packb(tree, use_bin_type=True))
    # the encoder refuses what the models would (model_copy skips validation)
    for update, msg in [
        ({"keyframe": None}, "odometry needs keyframe"),
        ({"keyframe": 19 - 20}, "outside the wire range"),
        ({"keyframe": 19}, "must be before keyframe 19"),
        ({"keyframe": 2**63}, "outside the wire range"),
    ]:
        with pytest.raises(CodecError, match=msg):
            encode_message(posed.model_copy(update=update), "full", "auv2", 5)
    huge = posed.odometry.model_copy(update={"covariance": np.diag([1e20] * 6).tolist()})
    with pytest.raises(CodecError, match="odometry covariance standard deviations"):
        encode_message(posed.model_copy(update={"odometry": huge}), "compact", "a", 5,
                       projection=Projection.fit(np.random.default_rng(4).normal(size=(30, D))))


def test_factor_keyframes_round_trip() -> None:
    f = _factor(np.random.default_rng(11))
    fk = f.model_copy(update={"keyframe_a": 1234, "keyframe_b": 0})
    for profile in ("full", "f16", "compact"):
        env, g = decode_message(encode_message(fk, profile, "svc", 1))
        assert (g.keyframe_a, g.keyframe_b) == (1234, 0)
        if env.profile is Profile.FULL:
            assert g == fk
        plain = encode_message(f, profile, "svc", 1)
        added = len(encode_message(fk, profile, "svc", 1)) - len(plain)
        assert added <= (4 if profile == "compact" else 26)  # compact: two msgpack integers
        assert decode_message(plain)[1].keyframe_a is None
    tree = msgpack.unpackb(encode_message(fk, "compact", "svc", 1), raw=False)
    assert tree[6][10:] == [1234, 0]
    assert tree[6][:10] == msgpack.unpackb(encode_message(f, "compact", "svc", 1), raw=False)[6]
    big = fk.model_copy(update={"keyframe_a": 2**63 - 1, "keyframe_b": 2**40})
    assert decode_message(encode_message(big, "compact", "svc", 1))[1].keyframe_a == 2**63 - 1
    # malformed: one of the two, a non-integer, out of range, a one-sided full document
    for tail, msg in [
        ([7], "expected 10 or 12 fields, got 11"),
        ([7, None], "keyframe_b: expected an integer"),
        ([7, -1], "keyframe_b: -1 outside"),
        ([7, 1, 2], "got 13"),
    ]:
        bad = [*tree[:6], [*tree[6][:10], *tail]]
        with pytest.raises(DecodeError, match=msg):
            decode_message(msgpack.packb(bad, use_bin_type=True))
    doc = {**fk.model_dump(mode="json"), "keyframe_b": None}
    raw = msgpack.unpackb(encode_message(fk, "full", "svc", 1), raw=False)
    raw[6] = doc
    with pytest.raises(SchemaError, match="keyframe_a and keyframe_b go together"):
        decode_message(msgpack.packb(raw, use_bin_type=True))
    with pytest.raises(CodecError, match="keyframe_a"):
        encode_message(fk.model_copy(update={"keyframe_a": 2**64}), "compact", "svc", 1)
    for profile in ("full", "compact"):
        with pytest.raises(CodecError, match="go together"):
            encode_message(fk.model_copy(update={"keyframe_b": None}), profile, "svc", 1)


# ------------------------------------------------------------------ files


def test_files_round_trip_and_match(tmp_path: Path) -> None:
    sc = make_scenario("underwater", 1)
    (tmp_path / "sub.json").write_text(sc.submap.model_dump_json())
    (tmp_path / "map.json").write_text(sc.map.model_dump_json())
    out = tmp_path / "out"
    out.mkdir()
    # compact without the fleet's projection: refused (a one-off fit the service would not
    # have), before anything is written
    with pytest.raises(InputError, match="projection make"):
        encode_file(tmp_path / "map.json", out / "map.bin", "compact")
    assert not (out / "map.bin").exists() and not list(out.glob("projection-*.npz"))
    proj = Projection.fit(make_scenario("underwater", 7).map.arrays().embeddings_nd)
    proj_path = proj.save(out / f"projection-{proj.id}.npz")
    stats = encode_file(tmp_path / "map.json", out / "map.bin", "compact", proj_path)
    assert stats.msg_type is MessageType.MAP and stats.n_objects == len(sc.map.objects)
    assert stats.projection_id == proj.id and stats.bytes_per_object < 64
    env, _ = decode_file(out / "map.bin", out / "map.json")  # found beside it
    assert env.projection_id == stats.projection_id
    # the submap, decoded elsewhere with --projection
    s2 = encode_file(tmp_path / "sub.json", out / "sub.bin", "compact", proj)
    assert s2.msg_type is MessageType.SUBMAP
    moved = tmp_path / "elsewhere.bin"
    moved.write_bytes((out / "sub.bin").read_bytes())
    with pytest.raises(DecodeError, match="--projection"):
        decode_file(moved, tmp_path / "x.json")
    decode_file(moved, out / "sub.json", projection=proj_path)
    mp, sub = load_model(ObjectMap, out / "map.json"), load_model(Submap, out / "sub.json")
    assert sub.seq == sc.submap.seq and [o.id for o in sub.objects] == [
        o.id for o in sc.submap.objects
    ]
    outcome = match(mp, sub)  # the matcher accepts decoded files (accuracy: tested above)
    assert {m.submap_object for m in outcome.result.matches} <= {o.id for o in sub.objects}
    # factors and exact profiles through files too
    f = _factor(np.random.default_rng(1))
    (tmp_path / "f.json").write_text(f.model_dump_json())
    assert encode_file(tmp_path / "f.json", out / "f.bin", "compact").n_bytes < 150
    _, g = decode_file(out / "f.bin", out / "f.json")
    assert Factor.model_validate_json((out / "f.json").read_text()) == g
    with pytest.raises(DecodeError):
        decode_file(tmp_path / "missing.bin", out / "y.json")


def test_all_is_exported() -> None:
    assert all(hasattr(codec, name) for name in codec.__all__)
    assert math.isclose(CodecSettings().position_resolution_m, RES_M)
