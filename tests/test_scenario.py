"""Scenario runs: seeded, tracked, with ground truth that the geometry agrees with."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import spearmanr

from mergesvc.core.pipeline import match
from mergesvc.sim import drive_run, image_s_dataset, underwater_run


@pytest.fixture(scope="module")
def pool():
    return underwater_run(2, seed=3)


def test_runs_are_deterministic(pool) -> None:
    again = underwater_run(2, seed=3)
    assert [t.track_id for t in again.tracks_map] == [t.track_id for t in pool.tracks_map]
    a, b = again.map.arrays(), pool.map.arrays()
    assert np.array_equal(a.embeddings_nd, b.embeddings_nd)
    other = underwater_run(2, seed=4)
    assert not np.array_equal(other.map.arrays().position_xyz_m[:3], b.position_xyz_m[:3])


def test_map_objects_come_from_the_tracker(pool) -> None:
    arr = pool.map.arrays()
    assert arr.n == len(pool.tracks_map) >= 8
    assert arr.n_obs.min() >= 2  # single flashes are not sent
    # fused variances shrink with observations (semantic Kalman): s ~ s_obs / n_obs
    s = arr.uncertainty_s
    assert spearmanr(arr.n_obs, s)[0] < -0.3
    assert set(pool.object_classes) <= {
        "towfish", "lobster_cage", "buoy", "tire", "anchor", "crate", "cone"
    }


def test_odometry_drifts_and_submaps_come_from_the_second_half(pool) -> None:
    drift = [pool.drift_m(k) for k in range(len(pool.stamps_s))]
    assert drift[0] == 0.0 and max(drift) > 0.2
    subs = pool.windows(4, 3)
    assert len(subs) == 3
    for sc in subs:
        assert len(sc.submap.objects) == 4
        assert sc.submap.stamp >= pool.stamps_s[pool.split]


def test_truth_agrees_with_geometry(pool) -> None:
    """The true transform puts each matched submap object near its true map object (within the
    drift and noise of a pool run): truth and frames are consistent."""
    close = total = 0
    m = {n.id: np.array(n.position) for n in pool.map.objects}
    for sc in pool.windows(3, 6):
        for node in sc.submap.objects:
            tid = sc.truth[node.id]
            assert (tid is None) == (len(sc.equivalent[node.id]) == 0)
            if tid is None:
                continue
            assert tid in sc.equivalent[node.id]
            placed = sc.R_map_submap @ np.array(node.position) + sc.t_map_submap
            total += 1
            close += np.linalg.norm(placed - m[tid]) < 3.0
    assert total >= 8 and close / total > 0.8


def test_drive_has_kitti_scale_and_four_places() -> None:
    run = drive_run(seed=1)
    assert 450 <= len(run.map.objects) <= 700
    path = np.linalg.norm(np.diff(run.poses_true[:, :2, 3], axis=0), axis=1).sum()
    assert 1800 < path < 2600
    places = run.places(4, 20)
    assert len(places) == 4
    assert all(len(sc.submap.objects) == 20 for sc in places)
    outcome = match(places[0].map, places[0].submap)
    got = {x.submap_object: x.map_object for x in outcome.result.matches}
    right = sum(places[0].is_correct(s, m) for s, m in got.items())
    assert outcome.result.accepted and right >= 12


def test_image_uncertainty_predicts_the_error() -> None:
    y, loss, s = image_s_dataset(2000, seed=0)
    assert y.shape == (2000, 384)
    assert s.min() >= 0.05 and s.max() <= 0.5
    assert spearmanr(s, loss)[0] > 0.8


def test_kitti_trajectory_file(tmp_path) -> None:
    """A KITTI pose file (camera frame: z forward) drives the run instead of the street loop."""
    n = 400
    t = np.linspace(0, 2 * np.pi, n)
    R = np.zeros((n, 3, 4))
    # a 300 m circle in the x-z plane, camera looking along the direction of travel
    R[:, 0, 3], R[:, 2, 3] = 150 * np.sin(t), 150 * (1 - np.cos(t))
    fwd = np.stack([np.cos(t), np.zeros(n), np.sin(t)], axis=1)  # derivative direction
    right = np.cross(fwd, [0, -1, 0])
    R[:, :, 0], R[:, :, 1], R[:, :, 2] = right, np.tile([0, 1, 0], (n, 1)), fwd
    path = tmp_path / "poses.txt"
    np.savetxt(path, np.concatenate([R[:, :, :4].reshape(n, 12)] * 2))
    run = drive_run(seed=0, trajectory=path)
    assert len(run.map.objects) > 50 and len(run.tracks_revisit) > 20
