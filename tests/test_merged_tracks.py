"""Which wrong correspondences an agent's tracker caused (fleet/scoring.py
`wrong_on_merged_tracks`): a track that took detections of two objects, matched as the one it
holds fewer of. In the pool-long world of seed 1 (6 laps) 12 of the 16 wrong pairs in force are
one such track (two look-alike anchors 0.95 m apart), matched again on each lap
(docs/benchmarks/merge.md)."""

from __future__ import annotations

import pytest

from mergesvc.fleet.scoring import wrong_on_merged_tracks


def test_a_wrong_pair_counts_only_when_one_track_holds_the_other_object() -> None:
    pairs = [("anchor_10", "anchor_2"),  # the map's track took anchor_2 too: the tracker's
             ("anchor_2", "anchor_10"),  # the submap's track took anchor_2: the tracker's
             ("crate_1", "crate_7"),  # clean tracks, wrong pair: the matcher's
             ("crate_1", "crate_1"),  # right (its track mixed: not a wrong pair at all)
             (None, "crate_3")]  # unknown truth: not judged
    counts_a = [{"anchor_10": 3, "anchor_2": 2}, {"anchor_2": 4}, {"crate_1": 5},
                {"crate_1": 3, "crate_7": 1}, {}]
    counts_b = [{"anchor_2": 3}, {"anchor_10": 2, "anchor_2": 1}, {"crate_7": 4},
                {"crate_1": 2}, {"crate_3": 2}]
    assert wrong_on_merged_tracks(pairs, counts_a, counts_b) == 2
    assert wrong_on_merged_tracks(pairs[2:], counts_a[2:], counts_b[2:]) == 0
    assert wrong_on_merged_tracks([], [], []) == 0
    with pytest.raises(ValueError):  # every pair needs its two tracks' counts
        wrong_on_merged_tracks(pairs, counts_a[:2], counts_b)
