"""The service's pose-graph settings: ServiceConfig.graph reaches the PoseGraph the service
builds (a real Zenoh session on 127.0.0.1, scouting off, as in test_service.py)."""

from __future__ import annotations

import zenoh
from helpers import free_port, zenoh_config

from mergesvc.core.graph import GraphConfig
from mergesvc.fleet.service import MergeService, ServiceConfig


def test_default_graph_settings() -> None:
    assert ServiceConfig().graph == GraphConfig()


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
