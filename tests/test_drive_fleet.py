"""The KITTI-00 drive fleet's odometry models (sim/drive_fleet.py): "orbslam" re-anchors the
real ORB-SLAM2 estimate; "vo" block-bootstraps its step errors, which keeps their size but not
the loop-closed consistency, so it drifts as raw visual odometry does."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from mergesvc.core.trajectory import ate_rmse
from mergesvc.errors import InputError
from mergesvc.sim.drive_fleet import _block_bootstrap, drive_fleet
from mergesvc.sim.real_data import KITTI_GT, KITTI_ORB, data_available

needs_kitti = pytest.mark.skipif(not data_available(None, KITTI_GT, KITTI_ORB),
                                 reason="../shared/data/kitti00 not present")


def _step_rms(T: np.ndarray, G: np.ndarray) -> np.ndarray:
    """(rotation rad, translation m) RMS of the per-step errors of poses T against G."""
    e = np.array([gtsam.Pose3.Logmap(gtsam.Pose3(np.linalg.inv(G[k - 1]) @ G[k]).between(
        gtsam.Pose3(np.linalg.inv(T[k - 1]) @ T[k]))) for k in range(1, len(T))])
    return np.sqrt((e ** 2).mean(axis=0)).reshape(2, 3).mean(axis=1)


def test_an_unknown_drift_is_refused() -> None:
    with pytest.raises(InputError, match="unknown drift 'lidar'"):
        drive_fleet(0, drift="lidar")


def test_block_bootstrap_draws_whole_runs() -> None:
    pool = np.arange(100, dtype=float)[:, None]
    out = _block_bootstrap(pool, 53, 10, np.random.default_rng(0))
    assert out.shape == (53, 1)
    d = np.diff(out[:, 0])
    # inside a block the rows are consecutive; a new block may start anywhere
    assert all(d[k] == 1.0 for k in range(53 - 1) if (k + 1) % 10)
    with pytest.raises(InputError, match="too few"):
        _block_bootstrap(pool[:5], 10, 10, np.random.default_rng(0))


@needs_kitti
def test_vo_drifts_more_than_the_loop_closed_estimate_with_the_same_step_errors() -> None:
    orb = drive_fleet(0)
    vo = drive_fleet(0, drift="vo")
    again = drive_fleet(0, drift="vo")
    other = drive_fleet(1, drift="vo")
    ate_orb, ate_vo = [], []
    for c_orb, c_vo, c_again, c_other in zip(orb.cars, vo.cars, again.cars, other.cars):
        np.testing.assert_array_equal(c_vo.T_true_grav, c_orb.T_true_grav)
        np.testing.assert_array_equal(c_vo.T_est_grav, c_again.T_est_grav)  # seeded
        assert not np.allclose(c_vo.T_est_grav, c_other.T_est_grav)
        ate_orb.append(ate_rmse(c_orb.T_est_grav, c_orb.T_true_grav))
        ate_vo.append(ate_rmse(c_vo.T_est_grav, c_vo.T_true_grav))
        # the steps are as wrong as the real ones (the same errors, other order) ...
        r_orb, r_vo = _step_rms(c_orb.T_est_grav, c_orb.T_true_grav), _step_rms(
            c_vo.T_est_grav, c_vo.T_true_grav)
        assert np.all(r_vo < 3.0 * r_orb) and np.all(r_vo > r_orb / 3.0), (r_orb, r_vo)
    # ... but they no longer cancel: more drift over the fleet (1.6 km stretches: measured
    # ORB-SLAM2 0.8-0.9 m, vo 1.3-9.5 m ATE per car)
    assert sum(ate_vo) > 1.5 * sum(ate_orb), (ate_orb, ate_vo)


@needs_kitti
def test_the_loop_closed_estimate_declares_its_bound_and_vo_none() -> None:
    """What bench merge's kitti00 cars declare (service.odometry_bounds): the RMS of each pose's
    error relative to its car's start, recomputed here from the poses, and the path length its
    error stays alike over; visual odometry without loop closures declares none."""
    orb = drive_fleet(0)
    e = np.array([gtsam.Pose3.Logmap(gtsam.Pose3(np.linalg.inv(c.T_true[0]) @ T).between(
        gtsam.Pose3(E))) for c in orb.cars for T, E in zip(c.T_true, c.T_est)])
    np.testing.assert_allclose(orb.odometry_bound_sigma, np.sqrt((e ** 2).mean(axis=0)),
                               rtol=1e-12)
    # measured: 0.010-0.013 rad and 2.1-3.2 m per axis, 134 m of a 1.6 km stretch
    assert all(0.0 < s < 0.05 for s in orb.odometry_bound_sigma[:3])
    assert all(0.5 < s < 10.0 for s in orb.odometry_bound_sigma[3:])
    assert 20.0 < orb.odometry_bound_span_m < 800.0
    vo = drive_fleet(0, drift="vo")
    assert vo.odometry_bound_sigma is None and vo.odometry_bound_span_m is None
