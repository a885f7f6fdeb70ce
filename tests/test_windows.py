"""Large submaps: windows cover the submap, and submaps far beyond the exact solver's reach
(120 and 1,000 objects cut from a map) are matched correctly."""

from __future__ import annotations

import numpy as np
import pytest

from mergesvc.core.config import match_config
from mergesvc.core.pipeline import match
from mergesvc.core.windows import consensus, one_to_one, partition
from mergesvc.sim.scale import cut_submap, scale_world


def test_partition_covers_every_object_once_in_compact_windows() -> None:
    rng = np.random.default_rng(0)
    xyz = np.column_stack([rng.uniform(0, 100, (1000, 2)), rng.normal(0, 1, 1000)])
    wins = partition(xyz, 32)
    allrows = np.concatenate(wins)
    assert sorted(allrows.tolist()) == list(range(1000))
    assert all(16 <= len(w) <= 32 for w in wins)
    # compact: a window of ~1/40 of a flat layout spans far less than the whole of it
    assert np.median([np.ptp(xyz[w, :2], axis=0).max() for w in wins]) < 35.0


def test_consensus_and_one_to_one() -> None:
    import gtsam

    rng = np.random.default_rng(1)
    sub = rng.uniform(-50, 50, (40, 3))
    T = gtsam.Pose3(gtsam.Rot3.Yaw(0.7), np.array([5.0, -3.0, 1.0]))
    mp = sub @ T.rotation().matrix().T + T.translation()
    mp[:8] += rng.uniform(20, 40, (8, 3))  # 8 wrong pairs
    wrong = gtsam.Pose3(gtsam.Rot3.Yaw(-1.0), np.zeros(3))
    got, inl = consensus(sub, mp, np.full(40, 1.0), [wrong, T])
    assert inl.tolist() == [False] * 8 + [True] * 32
    assert np.allclose(got.matrix(), T.matrix(), atol=1e-6)
    keep = one_to_one(np.array([0, 1, 2, 2]), np.array([7, 7, 8, 9]), np.array([0.5, 0.1, 1, 2]))
    assert keep.tolist() == [False, True, True, False]


@pytest.fixture(scope="module")
def world():
    return scale_world(3000, 64, 3)


@pytest.mark.parametrize("n_sub", [120, 1000])
def test_large_submaps_cut_from_the_map_are_matched(world, n_sub: int) -> None:
    case = cut_submap(world, n_sub, 5)
    out = match(world.map, case.submap, match_config())
    truth = case.truth
    a = out.assignment
    right = np.where(truth >= 0, a == truth, a < 0)
    assert out.result.accepted
    assert right.mean() >= 0.95, right.mean()
    assert np.sum((a >= 0) & (a != truth)) <= 0.01 * len(a)  # wrong matches, not misses
    # the answer is the windows' (the exact solver alone refuses a problem this large)
    assert out.n_candidates > 0 and "windows" in out.result.timings_ms
