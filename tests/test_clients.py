"""The example clients under clients/ run against what the service really produces: the
GTSAM snippet (clients/gtsam_factors.py, no mergesvc import) on the factors `export` writes to
factors.json, and the export's factors.json / map.json themselves."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import gtsam
import numpy as np
import pytest
from test_keyframes import interleaved, mission, run_service

from mergesvc.core.model import Factor, ObjectMap
from mergesvc.core.poses import pose3_from_model
from mergesvc.fleet.export import export_store

CLIENTS = Path(__file__).resolve().parents[1] / "clients"


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, CLIENTS / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("clients")
    _, robots = mission()
    store = tmp / "merge.db"
    svc = run_service(interleaved(robots), store=str(store))
    status = svc.status()
    stored = {f.factor_id: f.status for f in svc.store.factors()}
    gmap, _ = svc.global_map()
    svc.close()
    res = export_store(store, tmp / "out")
    return status, stored, gmap, res.out_dir


def test_export_lists_every_factor_with_its_status(run) -> None:
    _, stored, _, out = run
    listed = json.loads((out / "factors.json").read_text())
    assert [f["factor_id"] for f in listed] == list(stored)
    assert {f["factor_id"]: f["status"] for f in listed} == stored
    for f in listed:
        Factor.model_validate(f)  # every entry is a valid factor object
    manifest = json.loads((out / "export.json").read_text())
    assert manifest["factors"].endswith("factors.json")


def test_export_writes_the_fused_global_map(run) -> None:
    _, _, gmap, out = run
    m = ObjectMap.model_validate_json((out / "map.json").read_text())
    assert gmap is not None and len(m.objects) == len(gmap.objects) > 0
    got = {o.id: o.position for o in m.objects}
    for o in gmap.objects:  # the export's restart solves the same graph
        np.testing.assert_allclose(got[o.id], o.position, atol=1e-3)


def test_gtsam_snippet_builds_the_factors_the_service_solved_with(run) -> None:
    status, _, _, out = run
    client = _load("gtsam_factors")
    keys: dict[tuple[str, str, int], int] = {}

    def key_of(robot: str, session: str, k: int) -> int:
        return keys.setdefault((robot, session, k), gtsam.symbol("x", len(keys)))

    g = client.InterRobotFactors(key_of)
    listed = json.loads((out / "factors.json").read_text())
    assert listed, "the mission produced no factor"
    for f in listed:
        g.apply(f)
    in_force = [f for f in listed if f["status"] == "accepted"]
    assert g.graph.nrFactors() == len(in_force) == len(g.index)

    # each BetweenFactorPose3 holds the factor's T_a_b and covariance, a -> b
    solved = {}
    for name, poses in status["keyframe_poses"].items():
        robot, session = name.split("/")
        for k, T in poses.items():
            solved[key_of(robot, session, int(k))] = gtsam.Pose3(np.asarray(T))
    values = gtsam.Values()
    for key, T in solved.items():
        values.insert(key, T)
    for f in in_force:
        factor = g.graph.at(g.index[f["factor_id"]])
        model = Factor.model_validate(f)
        assert factor.measured().equals(pose3_from_model(model.T_a_b), 1e-9)
        np.testing.assert_allclose(factor.noiseModel().covariance(), np.asarray(f["covariance"]),
                                   rtol=1e-6, atol=1e-12)
        # at the service's solution the factor is nearly satisfied: a client that had the
        # direction (b -> a) or the quaternion order wrong would see a large error
        if all(k in solved for k in factor.keys()):  # noqa: SIM118 (a gtsam factor)
            assert 2.0 * factor.error(values) < 50.0, f["factor_id"]

    # retract one, replace another: the graph follows
    first, second = in_force[0], in_force[-1]
    assert g.apply({**first, "status": "retracted"}) == "removed"
    assert first["factor_id"] not in g.index
    assert g.graph.nrFactors() == len(in_force) - 1
    moved = {**second, "T_a_b": {**second["T_a_b"], "translation": [9.0, 9.0, 9.0]}}
    assert g.apply(moved) == "replaced"
    assert g.graph.nrFactors() == len(in_force) - 1
    np.testing.assert_allclose(g.graph.at(g.index[second["factor_id"]]).measured().translation(),
                               [9.0, 9.0, 9.0])
    assert g.apply({**first, "status": "retracted"}) == "unknown, ignored"
    # an id seen tying other sessions is refused: a robot cannot shadow another's factors
    shadow = {**second, "robot_a": "intruder"}
    assert g.apply(shadow).startswith("refused")
    np.testing.assert_allclose(g.graph.at(g.index[second["factor_id"]]).measured().translation(),
                               [9.0, 9.0, 9.0])
