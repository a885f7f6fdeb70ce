"""fleet/held.py: what the merge service holds per object and per factor is compact and gives
back exactly what it was made of. Packed vectors unpack bit for bit; a session's map built
from the held objects is the one the service built from the submaps' ObjectNodes (the same
arrays for matching, the same ObjectMap); a held factor is the Factor it was made of."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest
from helpers import cost_stream

from mergesvc.core.model import Factor, ObjectMap, ObjectNode, Submap
from mergesvc.errors import InputError
from mergesvc.fleet.config import ServiceConfig
from mergesvc.fleet.held import FactorTable, HeldFactor, HeldObject, PackedVector
from mergesvc.fleet.service import MergeService
from mergesvc.fleet.sessions import session_up
from mergesvc.wire import Profile, decode_message, encode_message

D = 384


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return a.shape == b.shape and np.array_equal(a.view(np.uint64), b.view(np.uint64))


def wire_values(profile: Profile, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(embeddings, per-dimension variances) of 6 objects as a decoder of `profile` gives them."""
    rng = np.random.default_rng(seed)
    objs = [ObjectNode(id=f"o{i}", position=(float(i), 0.0, 0.0),
                       embedding=rng.normal(size=D).tolist(),
                       variance=rng.uniform(0.01, 0.2, size=D).tolist()) for i in range(6)]
    sub = Submap(robot_id="r", session_id="s", seq=0, objects=objs)
    _, back = decode_message(encode_message(sub, profile, "r", 0))
    return (np.array([o.embedding for o in back.objects]),
            np.array([o.variance for o in back.objects]))


@pytest.mark.parametrize(("profile", "emb_form", "emb_bytes", "var_bytes"), [
    (Profile.FULL, "float32", 4 * D, 4 * D),
    (Profile.F16, "float32", 4 * D, 8 * D),  # 16-bit log codes: hundreds of distinct values
    (Profile.INT8, "int8", D + 8, D + 8 * 256)])  # 8-bit log codes: a table
def test_wire_values_pack_small_and_unpack_bit_for_bit(profile, emb_form, emb_bytes,
                                                       var_bytes) -> None:
    emb, var = wire_values(profile)
    for e, v in zip(emb, var, strict=True):
        pe, pv = PackedVector.pack(e), PackedVector.pack(v)
        assert same_bits(pe.unpack(), e) and same_bits(pv.unpack(), v)
        assert (pe.form, pe.nbytes) == (emb_form, emb_bytes)
        assert pv.nbytes <= var_bytes


@pytest.mark.parametrize("values", [
    np.random.default_rng(1).normal(size=D),  # arbitrary float64: held as it is
    np.array([0.0, -0.0, 1.0, -0.0]),  # signed zeros survive
    np.zeros(5), np.full(7, 0.1), np.array([1e-300, -3e300, 5e-324]), np.array([2.5]),
    np.arange(-127, 128) * 0.003,  # int8 codes times a scale that float32 cannot hold
    np.random.default_rng(2).choice([0.1, 0.7, 1.3], size=D),  # few distinct values: a table
    np.empty(0),
])
def test_any_float64_vector_unpacks_bit_for_bit(values: np.ndarray) -> None:
    p = PackedVector.pack(values)
    out = p.unpack()
    assert out.dtype == np.float64 and same_bits(out, values), p
    assert p.nbytes <= 8 * len(values) and len(p) == len(values)
    assert out is not p.unpack()  # a new array each time: callers may write to it


def test_the_smallest_exact_form_is_kept() -> None:
    assert PackedVector.pack(np.random.default_rng(1).normal(size=D)).form == "float64"
    assert PackedVector.pack(np.arange(-127, 128) * 0.003).form == "int8"
    few = PackedVector.pack(np.random.default_rng(2).choice([0.1, 0.7, 1.3], size=D))
    assert (few.form, few.nbytes) == ("table", D + 3 * 8)
    with pytest.raises(InputError):
        PackedVector.pack(np.ones((2, 3)))


def test_a_held_object_is_compact_and_gives_its_node_back() -> None:
    emb, var = wire_values(Profile.INT8)
    for k, (e, v) in enumerate(zip(emb, var, strict=True)):
        node = ObjectNode(id=f"o{k}", position=(1.0, -2.0, 0.5), embedding=e.tolist(),
                          variance=v.tolist() if k % 2 else 0.05, n_obs=k + 1,
                          label=None if k % 3 else "rock")
        held = HeldObject.of(7, 3, node)
        assert (held.seq, held.keyframe, held.dim) == (7, 3, D)
        assert isinstance(held.embedding, PackedVector) and held.embedding.nbytes == D + 8
        assert isinstance(held.variance, PackedVector if k % 2 else float)
        assert held.node == node
        moved = held.node_at((4.0, 5.0, 6.0))
        assert moved == node.model_copy(update={"position": (4.0, 5.0, 6.0)})


# ------------------------------------------------------------------ against a served stream


def stream(n: int) -> list[Submap]:
    return cost_stream(n, seed=3, robots=3)


@pytest.fixture(scope="module")
def submaps() -> list[Submap]:
    return stream(90)


def serve(subs: list[Submap], profile: Profile):
    """The stream through a service (solved every 10 submaps, as the cost bench's batches);
    every submap as the service decoded it, every factor it published."""
    svc = MergeService(ServiceConfig(store=":memory:"), session=None)
    published: list[Factor] = []
    svc.outbox.factor = published.append
    decoded = []
    for i, sub in enumerate(subs):
        svc.ingest(sub, profile=profile, optimize=(i + 1) % 10 == 0 or i + 1 == len(subs))
        decoded.append(decode_message(encode_message(sub, profile, sub.robot_id, sub.seq))[1])
    return svc, decoded, published


def reference_map(svc: MergeService, name: str, nodes: dict[str, ObjectNode]) -> ObjectMap:
    """The session's map as the service built it before objects were held packed: every held
    object's ObjectNode placed with the pose of its keyframe (fleet/service.py, at 9081b62)."""
    st = svc.sessions[name]
    poses = svc.sessions.session_poses(st)
    placed = []
    for oid, held in st.objects.items():
        T = poses.get(held.keyframe)
        if T is None:
            continue
        node = nodes[oid]
        p = T.transformFrom(np.asarray(node.position, dtype=np.float64))
        placed.append(node if held.keyframe == 0 and T.equals(gtsam.Pose3(), 0.0)
                      else node.model_copy(update={"position": tuple(map(float, p))}))
    return ObjectMap(robot_id=st.frame.robot, session_id=st.frame.session, objects=placed,
                     up=session_up(st, poses))


@pytest.mark.parametrize("profile", [Profile.FULL, Profile.INT8])
def test_session_maps_from_held_objects_are_the_ones_from_the_nodes(submaps, profile) -> None:
    svc, decoded, published = serve(submaps, profile)
    try:
        latest: dict[str, dict[str, ObjectNode]] = {}  # session -> object -> latest node
        for sub in decoded:
            latest.setdefault(f"{sub.robot_id}/{sub.session_id}", {}).update(
                {o.id: o for o in sub.objects})
        compared = 0
        for name, st in svc.sessions.items():
            assert {oid: h.node for oid, h in st.objects.items()} == latest[name]
            for h in st.objects.values():  # packed: no list of Python floats is held
                assert isinstance(h.embedding, PackedVector)
                assert h.embedding.nbytes <= (D + 8 if profile is Profile.INT8 else 4 * D)
                assert isinstance(h.variance, float | PackedVector)
            sm = svc.sessions.session_map(name)
            if sm is None:
                continue
            ref = reference_map(svc, name, latest[name])
            assert sm.map == ref
            got, want = sm.arrays, ref.arrays()
            assert got.ids == want.ids
            for field in ("position_xyz_m", "embeddings_nd", "variances_nd",
                          "unit_embeddings_nd", "up_xyz"):
                assert same_bits(getattr(got, field), getattr(want, field)), (name, field)
            assert np.array_equal(got.n_obs, want.n_obs) and got.n_obs.dtype == want.n_obs.dtype
            compared += 1
        assert compared >= 5
        # every factor read back is the one published, and the one stored
        assert len(svc.factors) >= 10
        by_id = {f.factor_id: f for f in published}
        stored = {f.factor_id: Factor.model_validate_json(f.payload)
                  for f in svc.store.factors()}
        for fid, f in svc.factors.items():
            assert f == by_id[fid] == stored[fid]
            assert f.model_dump_json() == by_id[fid].model_dump_json()
    finally:
        svc.close()


def test_the_session_map_cache_stays_small(submaps, monkeypatch) -> None:
    """Session maps are cached per (session version, graph solution): after a new solution
    none of them can be used again (the cache is emptied), and at most SESSION_MAPS_CACHED
    are kept (the least recently used go first)."""
    import mergesvc.fleet.sessions as service

    svc, _, _ = serve(submaps[:40], Profile.FULL)
    try:
        for name in svc.sessions:
            svc.sessions.session_map(name)
        assert svc.sessions._maps
        solutions = svc.sessions.solutions
        for sub in submaps[40:]:
            svc.ingest(sub, optimize=True)
            if svc.sessions.solutions > solutions:
                break
        assert svc.sessions.solutions > solutions
        assert all(key[1] == svc.sessions.solutions for key, _ in svc.sessions._maps.values())
        monkeypatch.setattr(service, "SESSION_MAPS_CACHED", 2)
        names = list(svc.sessions)
        assert len(names) >= 3
        maps = [svc.sessions.session_map(name) for name in names]
        assert list(svc.sessions._maps) == names[-2:]
        assert svc.sessions.session_map(names[-1]) is maps[-1]  # a hit: the same map
    finally:
        svc.close()


# ------------------------------------------------------------------ factors


def a_factor(n_corr: int = 5, **kw) -> Factor:
    rng = np.random.default_rng(n_corr)
    A = rng.normal(size=(6, 6))
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    doc = {"factor_id": "auv1.s0-auv2.s1-7", "robot_a": "auv1", "session_a": "s0",
           "robot_b": "auv2", "session_b": "s1",
           "T_a_b": {"translation": rng.normal(size=3).tolist(), "quaternion_wxyz": q.tolist()},
           "covariance": (A @ A.T + np.eye(6)).tolist(),
           "correspondences": [{"object_a": f"o{i}", "object_b": f"o{i + 3}",
                                "score": math.pi / (i + 1)} for i in range(n_corr)],
           "status": "accepted", "keyframe_a": 4, "keyframe_b": 9} | kw
    return Factor.model_validate(doc)


@pytest.mark.parametrize("factor", [
    a_factor(), a_factor(0), a_factor(40),
    a_factor(status=None, keyframe_a=None, keyframe_b=None),
    a_factor(session_b="s/1#2"),
])
def test_a_held_factor_is_the_factor(factor: Factor) -> None:
    held = HeldFactor.of(factor)
    assert held.factor() == factor
    assert held.factor().model_dump_json() == factor.model_dump_json()
    assert held.frame_a == "auv1/s0" and held.frame_b == f"auv2/{factor.session_b}"
    assert list(held.object_pairs()) == [(c.object_a, c.object_b)
                                         for c in factor.correspondences]
    assert held.numbers.nbytes == 8 * (43 + len(factor.correspondences))


def test_the_factor_table_is_a_mapping_of_factors() -> None:
    t = FactorTable()
    f, g = a_factor(), a_factor(3, factor_id="other")
    t[f.factor_id] = f
    t[g.factor_id] = g
    assert len(t) == 2 and list(t) == [f.factor_id, "other"] and "other" in t
    assert t[f.factor_id] == f and list(t.values()) == [f, g]
    assert [h.factor_id for h in t.held()] == [f.factor_id, "other"]
    assert t.pop("other") == g and "other" not in t and len(t) == 1
    with pytest.raises(KeyError):
        t["other"]
    with pytest.raises(InputError):
        t["wrong id"] = f
