"""The service's pose-graph settings: ServiceConfig.graph reaches the PoseGraph the service
builds (a real Zenoh session on 127.0.0.1, scouting off, as in test_service.py)."""

from __future__ import annotations

import zenoh
from helpers import cost_stream, free_port, zenoh_config

from mergesvc.core.calibration import CalibrationConfig
from mergesvc.core.config import GraphConfig
from mergesvc.core.poses import pose_error
from mergesvc.fleet.config import LIVE_KEYFRAMES, ServiceConfig, odometry_group
from mergesvc.fleet.service import MergeService


def test_default_graph_settings() -> None:
    assert ServiceConfig().graph == GraphConfig(max_live_nodes=LIVE_KEYFRAMES,
                                                calibration=CalibrationConfig(),
                                                rigid_chains=odometry_group(""))
    assert GraphConfig().rigid_chains is None  # rule 7 opt-in in PoseGraph
    assert ServiceConfig().graph.calibration.enabled  # odometry calibrated from residuals
    assert not GraphConfig().calibration.enabled  # opt-in in PoseGraph
    assert LIVE_KEYFRAMES >= 500  # the merge benchmarks never freeze (under 250 keyframes)
    assert ServiceConfig().graph.fold_hops == 0  # folding (core/graph.py rule 5) is opt-in


def test_graph_settings_reach_the_services_pose_graph() -> None:
    graph = GraphConfig(inlier_probability=0.99, outlier_weight=0.25, anchor_sigma=1e-4)
    assert graph != GraphConfig()
    cfg = ServiceConfig(fleet="g", store=":memory:", graph=graph)
    ep = f"tcp/127.0.0.1:{free_port()}"
    with zenoh.open(zenoh_config("router", listen=ep)) as rs, MergeService(cfg, rs) as svc:
        assert svc.graph.config == graph
        assert svc.graph.config.outlier_weight == 0.25


def test_graph_settings_from_a_settings_document() -> None:
    cfg = ServiceConfig.model_validate({"graph": {"outlier_weight": 0.3}})
    assert cfg.graph.outlier_weight == 0.3
    assert cfg.graph.inlier_probability == GraphConfig().inlier_probability


def test_a_folding_service_keeps_every_factor(tmp_path) -> None:
    """With folding on (graph.fold_hops = 10), a seeded stream (4 pool vehicles, session after
    session over the same objects): closures that agree with one nearby are folded (not
    solved, core/graph.py rule 5), yet every accepted factor is held, stored, in the graph and
    weighed by its solution; a restart holds the same factors and folds them again."""
    subs = cost_stream(150, seed=0, robots=4)
    # factors as folding was made for: the match's own, placed by the solution, their
    # covariance inflated by the drift (locally fitted ones are tighter: few fold)
    cfg = ServiceConfig(store=str(tmp_path / "s.db"), graph=GraphConfig(fold_hops=10),
                        local_fit=False)
    svc = MergeService(cfg, session=None)
    try:
        for i, sub in enumerate(subs):
            svc.ingest(sub, optimize=(i + 1) % 10 == 0 or i + 1 == len(subs))
        held = set(svc.factors)
        graph = svc.graph
        assert len(held) >= 100 and graph.folded_count >= 0.3 * len(held)
        assert held <= set(graph.factor_ids)
        svc.graph.add_frame("solve/again#0")  # one more solve: none retracted since
        svc._optimize()
        sol = svc.solution
        assert sol is not None and held <= set(sol.weights) and not sol.outlier_factor_ids
        assert set(sol.folded) == {f for f in graph.factor_ids if graph.representative(f)}
        stored = {f.factor_id for f in svc.store.factors("accepted")}
        assert stored == held
    finally:
        svc.close()
    again = MergeService(cfg, session=None)
    try:
        again.restore()
        assert set(again.factors) == held
        assert held <= set(again.graph.factor_ids)
        assert again.graph.folded_count >= 0.3 * len(held)
    finally:
        again.close()


def test_a_bounded_service_freezes_old_keyframes_and_restarts_the_same(
        tmp_path, monkeypatch) -> None:
    """With max_live_nodes = 30, a seeded stream (4 pool vehicles, 150 submaps): the oldest
    keyframes freeze (core/graph.py rule 6), every accepted factor is still held and weighed,
    the status says how many froze, and no solve holds more than the live keyframes and the
    frozen ones their factors reach (the whole graph: 162 keyframes). The same factors are
    retracted as by a service that solves the whole graph. A restart settles the graph as it
    grew: the same keyframes frozen near the same poses, no solve of the whole graph."""
    import mergesvc.fleet.service as service_module
    from mergesvc.core.graph_job import SolveJob, SolveResult, run_job

    sizes: list[int] = []

    def recording(job: SolveJob) -> SolveResult:
        if job.gnc_known is None:  # the least-squares solves
            sizes.append(len(job.initial_keys))
        return run_job(job)

    monkeypatch.setattr(service_module, "optimizer", lambda in_child, timeout_s: recording)
    cap = 30
    subs = cost_stream(150, seed=0, robots=4)

    def run(cfg: ServiceConfig) -> MergeService:
        svc = MergeService(cfg, session=None)
        for i, sub in enumerate(subs):
            svc.ingest(sub, optimize=(i + 1) % 10 == 0 or i + 1 == len(subs))
        return svc

    # loops within a session reach back to frozen keyframes, which a solve then holds too:
    # the bound below is that of factors between robots alone
    whole = run(ServiceConfig(store=str(tmp_path / "whole.db"), graph=GraphConfig(),
                              loop_gap_submaps=0))
    try:
        retracted_whole = {f.factor_id for f in whole.store.factors("retracted")}
        nodes = len(whole.solution.T_anchor_frame)
    finally:
        whole.close()
    sizes.clear()
    cfg = ServiceConfig(store=str(tmp_path / "s.db"), graph=GraphConfig(max_live_nodes=cap),
                        loop_gap_submaps=0)
    svc = run(cfg)
    try:
        held = set(svc.factors)
        graph, sol = svc.graph, svc.solution
        assert sol is not None and len(sol.T_anchor_frame) == nodes
        assert len(held) >= 100 and graph.frozen_count >= nodes - 3 * cap > 0
        assert held <= set(sol.weights)
        retracted = {f.factor_id for f in svc.store.factors("retracted")}
        assert retracted == retracted_whole and len(retracted) >= 2  # the same verdicts
        assert svc.status(poses=False)["frozen_keyframes"] == graph.frozen_count
        # live, a batch's new ones, and the frozen ones their closures reach (this pool: 40-50)
        assert max(sizes) < 0.6 * nodes
        frozen = dict(graph._frozen)
    finally:
        svc.close()
    sizes.clear()
    again = MergeService(cfg, session=None)
    try:
        again.restore()
        assert set(again.factors) == held
        assert again.graph.frozen_count >= len(frozen) - 10
        assert max(sizes) < 0.7 * nodes
        moved = [pose_error(again.solution.T_anchor_frame[n], T)[1]
                 for n, T in frozen.items() if n in again.graph._frozen]
        assert len(moved) >= len(frozen) - 10 and max(moved) < 0.5
    finally:
        again.close()
