"""A declared odometry bound (ServiceConfig.odometry_bounds): each keyframe of a robot whose
odometry is a loop-closed estimate is tied to its session's first keyframe by the odometry
between them, with the declared covariance; the merged trajectory then keeps that shape within
the bound (docs/pose_graph.md, "Odometry with a bound")."""

from __future__ import annotations

import itertools
import json

import gtsam
import numpy as np
import pytest
from helpers import cost_stream
from pydantic import ValidationError

from mergesvc.core.frames import FrameId
from mergesvc.core.poses import pose3_from_model
from mergesvc.fleet.config import ServiceConfig, bound_group
from mergesvc.fleet.export import export_store
from mergesvc.fleet.service import MergeService
from mergesvc.fleet.sessions import SessionState

BOUNDED = ("auv1", "auv2")
SIGMAS = (0.002, 0.002, 0.002, 0.02, 0.02, 0.02)
N_SUBMAPS = 100


def _odometry_chains(subs) -> dict[str, dict[int, gtsam.Pose3]]:
    """robot/session -> keyframe -> pose in keyframe 0's frame, composed from the submaps."""
    out: dict[str, dict[int, gtsam.Pose3]] = {}
    for sub in subs:
        chain = out.setdefault(f"{sub.robot_id}/{sub.session_id}", {0: gtsam.Pose3()})
        if sub.odometry is not None:
            chain[sub.keyframe] = chain[sub.odometry.from_keyframe].compose(
                pose3_from_model(sub.odometry.T_from_to))
    return out


def _run(cfg: ServiceConfig, subs) -> MergeService:
    svc = MergeService(cfg, session=None)
    for i, sub in enumerate(subs):
        svc.ingest(sub, optimize=(i + 1) % 10 == 0 or i + 1 == len(subs))
    return svc


def _shape_error(svc: MergeService, chains, robot: str) -> float:
    """Largest distance (m) between a robot's merged keyframe poses relative to its first
    keyframe and its odometry's."""
    sol = svc.solution
    worst = 0.0
    for name, chain in chains.items():
        if not name.startswith(robot + "/"):
            continue
        first = sol.T_anchor_frame[f"{name}#0"]
        for k, T in chain.items():
            merged = first.between(sol.T_anchor_frame[f"{name}#{k}"])
            worst = max(worst, float(np.linalg.norm(merged.translation() - T.translation())))
    return worst


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("bound")
    subs = cost_stream(150, seed=0, robots=4)[:N_SUBMAPS]
    free = _run(ServiceConfig(store=str(tmp / "free.db")), subs)
    free_error = {r: _shape_error(free, _odometry_chains(subs), r) for r in BOUNDED}
    free.close()
    # a small live window: bound edges whose first keyframe froze long ago
    graph = ServiceConfig().graph.model_copy(update={"max_live_nodes": 20})
    cfg = ServiceConfig(store=str(tmp / "bound.db"), graph=graph,
                        odometry_bounds=dict.fromkeys(BOUNDED, SIGMAS))
    svc = _run(cfg, subs)
    yield subs, free_error, svc, cfg, tmp
    svc.close()


def test_every_keyframe_of_a_bounded_robot_is_tied_to_its_first(runs) -> None:
    subs, _, svc, _, _ = runs
    chains = _odometry_chains(subs)
    ids = set(svc.graph.factor_ids)
    bound = {f for f in ids if f.startswith("bound:")}
    expected = {f"bound:{name}#{k}" for name, chain in chains.items()
                if name.split("/")[0] in BOUNDED for k in chain if k != 0}
    assert bound == expected and len(expected) >= 40
    for fid, (T, C) in svc.merger.bound_edges.items():
        name, k = fid.removeprefix("bound:").split("#")
        assert T.equals(chains[name][int(k)], 1e-9), fid
        np.testing.assert_array_equal(C, np.diag(np.square(SIGMAS)))
        a, b, known = svc.graph.factor_nodes(fid)
        assert (a, b, known) == (f"{name}#0", f"{name}#{k}", True)
    assert svc.graph.frozen_count > 0  # first keyframes froze: their bound edges still solve
    assert bound_group("auv1") in svc.graph.noise_scales  # calibrated apart from the steps


def test_a_bounded_robot_keeps_its_odometrys_shape(runs) -> None:
    """Without the bound, closures bend each robot's trajectory away from its odometry's shape
    by decimetres (measured 0.50 and 0.56 m); with a bound of 2 cm, by millimetres (5-7)."""
    subs, free_error, svc, _, _ = runs
    chains = _odometry_chains(subs)
    for robot in BOUNDED:
        held = _shape_error(svc, chains, robot)
        assert free_error[robot] > 0.1, free_error
        assert held < 0.1 * free_error[robot], (robot, held, free_error[robot])


def test_a_restart_and_the_export_hold_the_same_bound_edges(runs) -> None:
    _, _, svc, cfg, tmp = runs
    again = MergeService(cfg, session=None)
    try:
        again.restore()
        assert set(again.merger.bound_edges) == set(svc.merger.bound_edges)
    finally:
        again.close()
    res = export_store(cfg.store, tmp / "out", config=cfg)
    listed = json.loads(res.manifest.read_text())["edges"]
    assert {e["factor_id"] for e in listed if e["kind"] == "odometry_bound"} == set(
        svc.merger.bound_edges)
    assert res.graph.read_text().count("EDGE_SE3:QUAT") == res.edges == len(listed)


def test_origin_pose_waits_for_a_chain_to_the_first_keyframe() -> None:
    subs = [s for s in cost_stream(150, seed=0, robots=4)
            if s.robot_id == "auv1" and s.session_id == "s0" and s.odometry is not None][:6]
    chain = _odometry_chains(subs)["auv1/s0"]
    st = SessionState(FrameId("auv1", "s0"))
    late = subs[0]  # the edge from keyframe 0 arrives last
    for sub in subs[1:]:
        st.add(sub)
        assert st.origin_pose(sub.keyframe) is None
    st.add(late)
    for sub in subs:
        assert st.origin_pose(sub.keyframe).equals(chain[sub.keyframe], 1e-9)


def test_keyframes_that_arrive_before_their_chain_are_tied_when_it_joins(tmp_path) -> None:
    """Submaps whose odometry starts at a keyframe the service has not seen (the one before
    was delayed): their keyframes wait, and are tied to keyframe 0 when the late edge joins
    them."""
    own = [s for s in cost_stream(150, seed=0, robots=4)
           if s.robot_id == "auv1" and s.session_id == "s0"][:6]
    assert own[0].odometry.from_keyframe == 0
    assert all(b.odometry.from_keyframe == a.keyframe for a, b in itertools.pairwise(own))
    order = [own[0], own[2], own[3], own[4], own[5], own[1]]  # own[1]'s edge joins the rest
    cfg = ServiceConfig(store=str(tmp_path / "s.db"), odometry_bounds={"auv1": SIGMAS})
    svc = MergeService(cfg, session=None)
    try:
        seen = []
        for sub in order:
            svc.ingest(sub, optimize=False)
            seen.append(len(svc.merger.bound_edges))
        assert seen == [1, 1, 1, 1, 1, 6]
        assert svc.merger._unbound["auv1/s0"] == {}
        chain = _odometry_chains(own)["auv1/s0"]
        for sub in own:
            T, _ = svc.merger.bound_edges[f"bound:auv1/s0#{sub.keyframe}"]
            assert T.equals(chain[sub.keyframe], 1e-9)
    finally:
        svc.close()


def test_bound_edges_within_the_span_count_as_one(tmp_path) -> None:
    """odometry_bound_span_m: a keyframe's bound covariance is the declared one times the span
    over its odometry edge's length (at least once): the edges within one span carry one
    declared bound's information between them."""
    own = [s for s in cost_stream(150, seed=0, robots=4)
           if s.robot_id == "auv1" and s.session_id == "s0"][:8]
    span = 30.0
    cfg = ServiceConfig(store=str(tmp_path / "s.db"), odometry_bounds={"auv1": SIGMAS},
                        odometry_bound_span_m=span)
    svc = MergeService(cfg, session=None)
    try:
        for sub in own:
            svc.ingest(sub, optimize=False)
        shares = []
        for sub in own:
            step = np.linalg.norm(pose3_from_model(sub.odometry.T_from_to).translation())
            _, C = svc.merger.bound_edges[f"bound:auv1/s0#{sub.keyframe}"]
            shares.append(max(1.0, span / step))
            np.testing.assert_allclose(C, np.diag(np.square(SIGMAS)) * shares[-1], rtol=1e-12)
        assert max(shares) > 2.0  # the span covers several keyframes here
    finally:
        svc.close()


@pytest.mark.parametrize("sigmas", [(0.0, 1, 1, 1, 1, 1), (1, 1, 1, 1, 1, float("nan")),
                                    (1, 1, 1, 1, 1, -2.0)])
def test_a_bound_must_be_six_positive_finite_sigmas(sigmas) -> None:
    with pytest.raises(ValidationError, match="six finite standard deviations above 0"):
        ServiceConfig(odometry_bounds={"auv1": sigmas})
    with pytest.raises(ValidationError):
        ServiceConfig(odometry_bounds={"auv1": (1.0, 1.0)})
