"""End-to-end matching against the ground truth of seeded scenarios."""

from __future__ import annotations

import numpy as np
import pytest
from oracles import brute_force
from scipy.spatial.transform import Rotation

from mergesvc.bench import score_case
from mergesvc.bench.match import bench_scenario
from mergesvc.core.config import match_config
from mergesvc.core.model import ObjectArrays, RejectReason
from mergesvc.core.pipeline import match
from mergesvc.errors import SchemaError
from mergesvc.sim import Family, make_scenario


def _transform_error(sc, result) -> tuple[float, float]:
    """(rotation error in degrees, mean displacement of the submap objects in metres)."""
    t = np.array(result.transform.translation)
    w, x, y, z = result.transform.quaternion_wxyz
    R = Rotation.from_quat([x, y, z, w]).as_matrix()
    rot_deg = np.degrees(Rotation.from_matrix(R.T @ sc.R_map_submap).magnitude())
    p = sc.submap.arrays().position_xyz_m
    disp = (p @ R.T + t) - (p @ sc.R_map_submap.T + sc.t_map_submap)
    return float(rot_deg), float(np.linalg.norm(disp, axis=1).mean())


def test_verified_recovers_permutation_and_transform(kitti_scenario) -> None:
    sc = kitti_scenario
    out = match(sc.map, sc.submap)
    r = out.result
    s = score_case(sc, out)
    assert r.accepted and r.reason is RejectReason.VERIFIED
    assert s["accuracy"] >= 0.95 and s["wrong"] == 0
    assert s["outliers_unmatched"] == s["outliers"] > 0
    rot_deg, trans_m = _transform_error(sc, r)
    assert rot_deg < 3.0 and trans_m < 1.5
    cov = np.array(r.covariance)
    assert cov.shape == (6, 6) and np.all(np.linalg.eigvalsh(cov) > 0)
    assert {"candidates", "affinity", "solve", "exact", "verify", "total"} <= set(r.timings_ms)
    assert out.exact is not None and out.exact.optimal


@pytest.mark.parametrize("seed", range(8))
def test_verified_underwater_never_accepts_a_wrong_match(seed: int) -> None:
    sc = make_scenario(Family.UNDERWATER, seed)
    out = match(sc.map, sc.submap)
    s = score_case(sc, out)
    if out.result.accepted:
        assert s["wrong"] == 0
    assert s["accuracy"] >= 0.5


@pytest.mark.parametrize("seed", [0, 1, 2, 4, 5, 6])
def test_a_tiny_problem_is_solved_exactly_without_the_heuristic(seed, monkeypatch) -> None:
    """2-5 objects against a pool: the exact search answers the proposal (the brute-force
    optimum over its candidates) and RRWM never runs; a KITTI-sized problem still runs it."""
    from mergesvc.core import pipeline
    from mergesvc.core.candidates import retrieve
    from mergesvc.core.solvers import heuristic

    calls: list[int] = []
    real = heuristic.rrwm
    monkeypatch.setattr(heuristic, "rrwm", lambda *a, **k: calls.append(1) or real(*a, **k))
    cfg = match_config(None, mode="verified")
    for sc, tiny in ((bench_scenario(Family.UNDERWATER, seed), True),
                     (make_scenario(Family.KITTI, seed), False)):
        m_arr, s_arr = sc.map.arrays(), sc.submap.arrays()
        cands, _ = retrieve(s_arr, m_arr, cfg.candidates, cfg.affinity, cfg.seed)
        sigma_m, _ = pipeline.edge_scales(m_arr, cfg.affinity)
        calls.clear()
        prop = pipeline._propose(s_arr, m_arr, cands, cfg, sigma_m, pipeline.StageTimer())
        assert (prop.exact is not None) is tiny and bool(calls) is not tiny
        if tiny:
            best, score = brute_force(prop.signed)
            assert prop.signed.score(prop.assignment) == pytest.approx(score, abs=1e-9)
            assert prop.exact[0].optimal and np.array_equal(prop.exact[0].assignment, best)


def test_outliers_come_out_unmatched(underwater_scenario) -> None:
    sc = underwater_scenario
    out = match(sc.map, sc.submap)
    s = score_case(sc, out)
    assert s["outliers"] == 1 and s["outliers_unmatched"] == 1
    assert s["accuracy"] == 1.0


@pytest.mark.parametrize("solver", ["rrwm", "sm", "ipfp", "exact"])
@pytest.mark.parametrize("affinity", ["ucos", "bhattacharyya", "mahalanobis"])
def test_every_solver_and_affinity_in_verified_mode(solver, affinity, kitti_scenario) -> None:
    sc = kitti_scenario
    cfg = match_config(solver={"name": solver}, affinity={"kind": affinity})
    s = score_case(sc, match(sc.map, sc.submap, cfg))
    assert s["accuracy"] >= 0.9


@pytest.mark.parametrize("solver", ["rrwm", "sm", "ipfp"])
def test_paper_mode_matches_every_node(solver, small_kitti_scenario) -> None:
    sc = small_kitti_scenario
    cfg = match_config(mode="paper", solver={"name": solver})
    out = match(sc.map, sc.submap, cfg)
    assert out.result.reason is RejectReason.NOT_VERIFIED
    assert len(out.result.matches) == len(sc.submap.objects)
    assert len({m.map_object for m in out.result.matches}) == len(out.result.matches)
    assert "affinity" in out.result.timings_ms


def test_paper_mode_exact_and_raw_distances(small_kitti_scenario) -> None:
    sc = make_scenario(Family.KITTI, seed=2, n_map=12, n_sub=4, n_outliers=0)
    out = match(sc.map, sc.submap, match_config(mode="paper", solver={"name": "exact"}))
    assert out.exact is not None and out.exact.optimal
    assert len(out.result.matches) == 4
    raw = match_config(mode="paper", affinity={"kind": "mahalanobis", "raw_distances": True})
    assert len(match(sc.map, sc.submap, raw).result.matches) == 4


def test_dimension_mismatch_is_a_schema_error(kitti_scenario) -> None:
    sub = kitti_scenario.submap.arrays()
    short = ObjectArrays(sub.ids, sub.position_xyz_m, sub.embeddings_nd[:, :10],
                         sub.variances_nd[:, :10], sub.n_obs)
    with pytest.raises(SchemaError, match="dimensions differ"):
        match(kitti_scenario.map, short)


def test_unrelated_submap_is_not_accepted(kitti_scenario) -> None:
    """A submap from a different world has no true match: nothing may be accepted."""
    other = make_scenario(Family.KITTI, seed=99)
    out = match(kitti_scenario.map, other.submap)
    assert not out.result.accepted


def test_deterministic(kitti_scenario) -> None:
    a = match(kitti_scenario.map, kitti_scenario.submap).result
    b = match(kitti_scenario.map, kitti_scenario.submap).result
    assert a.matches == b.matches and a.transform == b.transform


def _positions_times(objs, k: float):
    """The same objects with their positions x k (another length unit)."""
    return objs.model_copy(update={"objects": [
        o.model_copy(update={"position": tuple(k * np.asarray(o.position))})
        for o in objs.objects]})


@pytest.mark.parametrize(("family", "seed"), [(Family.KITTI, 0), (Family.KITTI, 4),
                                              (Family.UNDERWATER, 1), (Family.UNDERWATER, 6)])
def test_no_length_unit_is_assumed(family: Family, seed: int) -> None:
    """Positions in millimetres or kilometres give the same matches, and the transform's
    translation in that unit (nothing is tuned to metres). The embeddings' scale is a known
    limit of ucos (tests/test_known_limits.py)."""
    sc = bench_scenario(family, seed)
    base = match(sc.map, sc.submap).result
    assert base.accepted
    pairs = sorted((m.submap_object, m.map_object) for m in base.matches)
    for pos in (1000.0, 0.001):
        got = match(_positions_times(sc.map, pos), _positions_times(sc.submap, pos)).result
        assert got.accepted, (pos, got.reason)
        assert sorted((m.submap_object, m.map_object) for m in got.matches) == pairs
        np.testing.assert_allclose(np.asarray(got.transform.translation) / pos,
                                   base.transform.translation, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(got.transform.quaternion_wxyz,
                                   base.transform.quaternion_wxyz, atol=1e-9)
