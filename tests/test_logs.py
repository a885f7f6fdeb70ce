"""Recorded observation logs (sim/logs.py): the format round-trips, bad lines are refused with
the line named, and nothing depends on where the log's odometry frame is: a vehicle whose
log starts at (12, 5, -0.3), yawed and tilted, sends the same submaps, gets the same factors
and corrects its trajectory by the same amount as one whose log starts at the origin (issue 15:
the reference agent once anchored factors at the first logged pose)."""

from __future__ import annotations

import json

import gtsam
import numpy as np
import pytest

from mergesvc.core.factors import factor_nodes
from mergesvc.core.tracking import Detection, Frame
from mergesvc.errors import SchemaError
from mergesvc.fleet.agent import AgentConfig, build_submaps
from mergesvc.fleet.config import ServiceConfig
from mergesvc.fleet.service import MergeService
from mergesvc.sim.fleet import fleet_world
from mergesvc.sim.logs import read_observation_log, write_observation_log

ROBOTS = ("auv1", "auv2")


def moved(frames: list[Frame], G: np.ndarray) -> list[Frame]:
    """The same frames in an odometry frame G away: poses G T, detections G p (body positions
    and the body-frame up unchanged)."""
    R = G[:3, :3]
    return [Frame(f.k, f.stamp_s, G @ f.T_est, G @ f.T_true,
                  [Detection(d.embedding_d, d.uncertainty_s, R @ d.position_xyz_m + G[:3, 3],
                             R @ d.position_cov_33 @ R.T, d.stamp_s, d.truth_id)
                   for d in f.detections], up_body=f.up_body) for f in frames]


@pytest.fixture(scope="module")
def world():
    w = fleet_world(0, ROBOTS, laps=1)
    return {r: list(w.frames(r)) for r in ROBOTS}


def test_a_log_round_trips_with_its_gravity(world, tmp_path) -> None:
    frames = world["auv2"][:40]
    assert all(f.up_body is not None for f in frames)
    path = tmp_path / "auv2.jsonl"
    assert write_observation_log(frames, path) == 40
    back = list(read_observation_log(path))
    assert len(back) == 40
    for a, b in zip(frames, back):
        np.testing.assert_allclose(b.T_est, a.T_est, atol=1e-9)
        np.testing.assert_allclose(b.up_body, a.up_body / np.linalg.norm(a.up_body), atol=1e-12)
        assert len(b.detections) == len(a.detections)
        for da, db in zip(a.detections, b.detections):
            np.testing.assert_allclose(db.position_xyz_m, da.position_xyz_m, atol=1e-9)
    rec = json.loads(path.read_text().splitlines()[0])
    assert set(rec) == {"stamp_s", "pose", "up_body", "detections"}


@pytest.mark.parametrize(("field", "value", "message"), [
    ("up_body", [0.0, 0.0, 0.0], "up_body"),
    ("up_body", [0.0, float("nan"), 1.0], "up_body"),
    ("up_body", [0.0, 1.0], "up_body"),
    ("position_body_m", [1.0, float("inf"), 0.0], "position_body_m"),
    ("pose", "bad", r"not an observation record .*stamp_s, pose \{translation"),
    # a detection's own values: named as the log names them, not as the code does
    ("embedding", [float("nan")] * 384, r"detections\[0\]: embedding has "
     "non-finite values$"),
    ("uncertainty", -1.0, r"detections\[0\]: uncertainty must be > 0$"),
])
def test_bad_lines_are_refused_with_the_line_named(world, tmp_path, field, value,
                                                   message) -> None:
    path = tmp_path / "log.jsonl"
    write_observation_log(world["auv1"][:3], path)
    lines = path.read_text().splitlines()
    rec = json.loads(lines[1])
    if field in ("up_body", "pose"):
        rec[field] = value
    else:
        rec["detections"][0][field] = value
    lines[1] = json.dumps(rec)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(SchemaError, match=rf"log.jsonl:2: .*{message}"):
        list(read_observation_log(path))


def _submaps(frames: list[Frame], robot: str, tmp_path, name: str):
    path = tmp_path / f"{name}.jsonl"
    write_observation_log(frames, path)
    return build_submaps(AgentConfig(robot=robot, session="s0"), read_observation_log(path))


def test_where_the_log_starts_changes_nothing(world, tmp_path) -> None:
    G = np.eye(4)
    G[:3, :3] = gtsam.Rot3.RzRyRx(np.radians(20.0), np.radians(-10.0), np.radians(40.0)).matrix()
    G[:3, 3] = [12.0, 5.0, -0.3]
    _, subs1 = _submaps(world["auv1"], "auv1", tmp_path, "auv1")
    lm_a, subs_a = _submaps(world["auv2"], "auv2", tmp_path, "auv2")
    lm_b, subs_b = _submaps(moved(world["auv2"], G), "auv2", tmp_path, "auv2_moved")
    assert np.linalg.norm(lm_b.poses_est[0][:3, 3] - [12.0, 5.0, -0.3]) < 1e-9

    # the same submaps: keyframe-relative objects, odometry and gravity
    assert len(subs_a) == len(subs_b) > 3
    for a, b in zip(subs_a, subs_b):
        assert a.keyframe == b.keyframe
        np.testing.assert_allclose([o.position for o in b.objects],
                                   [o.position for o in a.objects], atol=5e-3)  # ISAM2 numerics
        np.testing.assert_allclose(b.up, a.up, atol=1e-6)
        if a.odometry is not None:
            np.testing.assert_allclose(b.odometry.T_from_to.translation,
                                       a.odometry.T_from_to.translation, atol=1e-6)

    # the same factors from the service
    def factors(subs2):
        svc = MergeService(ServiceConfig(store=":memory:"), None)
        for i in range(max(len(subs1), len(subs2))):
            for s in (subs1[i:i + 1] + subs2[i:i + 1]):
                svc.ingest(s)
        out = [f for f in svc.factors.values()]
        svc.close()
        return out

    fa, fb = factors(subs_a), factors(subs_b)
    assert [f.factor_id for f in fa] == [f.factor_id for f in fb] and fa
    for a, b in zip(fa, fb):
        assert factor_nodes(a) == factor_nodes(b)
        np.testing.assert_allclose(b.T_a_b.translation, a.T_a_b.translation, atol=1e-2)

    # the vehicle corrects its trajectory by the same amount, in its own frame
    for f_a, f_b in zip(fa, fb):
        lm_a.add_inter_robot(f_a)
        lm_b.add_inter_robot(f_b)
    pa, pb = lm_a.own_poses(), lm_b.own_poses()
    back = np.linalg.inv(G) @ pb  # the moved vehicle's poses, back in the first frame
    diff = np.abs(back[:, :3, 3] - pa[:, :3, 3]).max()
    assert diff < 3e-3, diff
    # and the factors did move it: not a test of two untouched trajectories
    assert np.abs(pa[:, :3, 3] - np.stack(lm_a.poses_est)[:, :3, 3]).max() > 0.01  # 0.03 m
