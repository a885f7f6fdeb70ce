"""The service's pose-graph settings: ServiceConfig.graph reaches the PoseGraph the service
builds (a real Zenoh session on 127.0.0.1, scouting off, as in test_service.py)."""

from __future__ import annotations

import zenoh
from helpers import cost_stream, free_port, zenoh_config

from mergesvc.core.graph import GraphConfig
from mergesvc.fleet.service import MergeService, ServiceConfig


def test_default_graph_settings() -> None:
    assert ServiceConfig().graph == GraphConfig()
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
    cfg = ServiceConfig(store=str(tmp_path / "s.db"), graph=GraphConfig(fold_hops=10))
    svc = MergeService(cfg, session=None)
    try:
        for i, sub in enumerate(subs):
            svc.ingest(sub, optimize=(i + 1) % 10 == 0 or i + 1 == len(subs))
        held = set(svc.factors)
        graph = svc.graph
        assert len(held) >= 100 and graph.folded_count >= 0.3 * len(held)
        assert held <= set(graph.factor_ids)
        svc.graph.add_frame("solve/again#0")  # one more solve: none retracted since
        svc._optimize(publish=False)
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
