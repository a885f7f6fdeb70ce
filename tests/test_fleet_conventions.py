"""The whole merge chain (agents' local maps, submaps, the service's matching, factors, graph,
calibration, rigid test; the scores) does not depend on the vehicles' axis conventions: the
pool fleet replayed with its vehicles in NED, camera and a random rotation gives the merge it
gives in the core axes (x forward, y left, z up): the same factors and precision, the ATE
within 5 % (the noise calibration scales each vehicle's odometry per axis of its own frame,
from a seeded Monte-Carlo estimate whose draws fall on other axes in another convention: its
scales, and so the solve, differ by a few per cent; measured 1.5-2 %)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from mergesvc.bench.merge import STRETCHES_QUICK
from mergesvc.fleet.agent import AgentConfig
from mergesvc.fleet.config import ServiceConfig
from mergesvc.fleet.replay import replay_world
from mergesvc.sim.conventions import C_CAMERA, C_NED, random_rotation
from mergesvc.sim.drive_fleet import drive_fleet
from mergesvc.sim.fleet import fleet_world
from mergesvc.sim.fleet_conventions import in_conventions
from mergesvc.sim.real_data import KITTI_GT, KITTI_ORB, data_available

needs_kitti = pytest.mark.skipif(not data_available(None, KITTI_GT, KITTI_ORB),
                                 reason="../shared/data/kitti00 not present")


def _replay(world, up) -> dict:
    return replay_world(world, service=ServiceConfig(),
                        agent=lambda r: AgentConfig(robot=r, up=up(r)), seed=0)


def test_frames_are_the_same_motion_in_other_axes() -> None:
    world = fleet_world(0, ("auv1", "auv2"), 1, 24)
    C = random_rotation(np.random.default_rng(1))
    cw = in_conventions(world, {"auv2": C})
    for name, conv in (("auv1", np.eye(3)), ("auv2", C)):
        start, start_c = world.session_start(name), cw.session_start(name)
        for f, g in zip(world.frames(name), cw.frames(name), strict=True):
            # the same true world pose of the body; odometry and detections renamed by C
            assert np.allclose(start @ f.T_est @ np.linalg.inv(f.T_true),
                               start_c @ g.T_est @ np.linalg.inv(g.T_true), atol=1e-9)
            assert np.allclose(g.T_est[:3, 3], conv @ f.T_est[:3, 3])
            for d, e in zip(f.detections, g.detections, strict=True):
                assert np.allclose(e.position_xyz_m, conv @ d.position_xyz_m)
    assert np.allclose(cw.up("auv2"), C[:, 2])
    assert cw.object_ids == world.object_ids
    # the true starts as the scoring reads them: every way, in the vehicles' conventions
    S1, S2 = cw.session_start("auv1"), cw.session_start("auv2")
    assert np.allclose(cw.robot("auv2").T_world_start, S2)
    assert np.allclose([r.T_world_start for r in cw.robots], [S1, S2])
    assert np.allclose(cw.T_rel_true("auv1", "auv2"), np.linalg.inv(S1) @ S2)
    assert np.allclose(S2[:3, :3] @ C[:, 2], world.session_start("auv2")[:3, 2])  # up is up


def test_merge_is_the_same_in_every_convention(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.ERROR)
    world = fleet_world(0, ("auv1", "auv2", "auv3"), 2, 24)
    mixed = in_conventions(world, {"auv1": C_NED, "auv2": C_CAMERA,
                                   "auv3": random_rotation(np.random.default_rng(3))})
    core = _replay(world, lambda r: (0.0, 0.0, 1.0))
    other = _replay(mixed, mixed.up)
    assert other["factors_accepted"] == core["factors_accepted"] > 20
    assert other["precision"] == core["precision"]
    bent = 0
    for name, a in core["robots"].items():
        b = other["robots"][name]
        assert b["ate_odometry_m"] == pytest.approx(a["ate_odometry_m"], rel=1e-6)
        assert b["ate_merged_m"] == pytest.approx(a["ate_merged_m"], rel=0.05, abs=0.005)
        assert b["final_rot_err_deg"] == pytest.approx(a["final_rot_err_deg"], abs=0.1)
        bent += a["ate_merged_m"] < 0.9 * a["ate_odometry_m"]
    assert bent >= 1  # the merge moved a trajectory: not odometry compared with itself
    assert other["fleet_ate_merged_m"] == pytest.approx(core["fleet_ate_merged_m"], rel=0.05)


@needs_kitti
def test_a_drive_fleet_in_other_conventions() -> None:
    """The wrapper takes any fleet world: the KITTI-00 cars (camera axes, cars' records
    without a settable start) renamed, their starts and verticals with them."""
    world = drive_fleet(0, stretches=STRETCHES_QUICK)
    C = random_rotation(np.random.default_rng(2))
    cw = in_conventions(world, {"car2": C})
    S = cw.session_start("car2")
    assert np.allclose([r.T_world_start for r in cw.robots],
                       [world.session_start("car1"), S, world.session_start("car3")])
    assert [r.name for r in cw.robots] == ["car1", "car2", "car3"]
    assert np.array_equal(cw.robot("car2").frames_idx, world.robot("car2").frames_idx)
    assert np.allclose(cw.T_rel_true("car1", "car2"),
                       np.linalg.inv(world.session_start("car1")) @ S)
    f, g = next(world.frames("car2")), next(cw.frames("car2"))
    assert np.allclose(g.up_body, C @ f.up_body)
    # the vertical in the odometry frame: the first frame's IMU (its body is that frame)
    assert np.allclose(world.up("car2"), f.up_body, atol=1e-6)
    assert np.allclose(cw.up("car2"), C @ f.up_body, atol=1e-6)
