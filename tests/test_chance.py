"""core/chance.py: the a-contrario count against plain loops, and what it refuses in `match`:
submaps of places the map does not hold, not right answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mergesvc.bench.generalize import lacking_pairs
from mergesvc.core.arrays import ObjectArrays
from mergesvc.core.candidates import Candidates
from mergesvc.core.chance import candidate_ranks, chance_log10, log10_comb
from mergesvc.core.config import match_config
from mergesvc.core.model import RejectReason
from mergesvc.core.pipeline import match
from mergesvc.sim import Family, Scenario, make_scenario


def test_log10_comb_is_the_binomial_coefficient() -> None:
    for n in range(0, 70):
        for k in range(0, n + 1):
            assert log10_comb(n, k) == pytest.approx(math.log10(math.comb(n, k)), abs=1e-9)


def test_candidate_ranks_against_a_loop() -> None:
    rng = np.random.default_rng(3)
    for _ in range(40):
        n_sub, n_map = int(rng.integers(1, 8)), int(rng.integers(2, 30))
        pairs = [(i, a) for i in range(n_sub) for a in rng.choice(n_map, rng.integers(1, n_map),
                                                                    replace=False)]
        rows = np.array([p[0] for p in pairs])
        nodes = np.array([p[1] for p in pairs])
        aff = np.round(rng.normal(size=len(pairs)), 1)  # ties happen: they share a rank
        cands = Candidates(rows, nodes, aff, np.ones(len(pairs)))
        chosen_rows = np.unique(rows)[: int(rng.integers(1, n_sub + 1))]
        chosen = np.array([nodes[rng.choice(np.flatnonzero(rows == i))] for i in chosen_rows])
        got = candidate_ranks(cands, chosen_rows, chosen, n_sub)
        for j, (i, a) in enumerate(zip(chosen_rows, chosen, strict=True)):
            mine = aff[(rows == i) & (nodes == a)][0]
            assert got[j] == 1 + sum(1 for r, x in zip(rows, aff, strict=True)
                                     if r == i and x > mine)


def test_a_pair_that_is_not_a_candidate_ranks_after_its_rows_candidates() -> None:
    # the windowed path's objects placed by the common transform: found by position
    cands = Candidates(np.array([0, 0, 0, 1]), np.array([4, 7, 9, 2]),
                       np.array([0.9, 0.5, 0.7, 0.3]), np.ones(4))
    got = candidate_ranks(cands, np.array([0, 1]), np.array([5, 2]), 2)
    assert got.tolist() == [4, 1]
    got = candidate_ranks(cands, np.array([0, 1]), np.array([100, 8]), 3)
    assert got.tolist() == [4, 2]
    empty = Candidates(np.array([], dtype=np.int64), np.array([], dtype=np.int64),
                       np.array([]), np.array([]))
    assert candidate_ranks(empty, np.array([0]), np.array([3]), 1).tolist() == [1]


def test_chance_log10_against_its_formula() -> None:
    rng = np.random.default_rng(5)
    for _ in range(20):
        N, n = int(rng.integers(5, 200)), int(rng.integers(2, 25))
        k = int(rng.integers(1, n + 1))
        xyz = rng.uniform(0, 20, (N, 3))
        map_ = ObjectArrays([f"m{i}" for i in range(N)], xyz, rng.normal(size=(N, 8)),
                            np.ones(N), np.ones(N, dtype=int))
        ranks = rng.integers(1, 12, k)
        pred = rng.uniform(0, 20, (k, 3))
        res = rng.uniform(0, 3, k)
        rms = math.sqrt(sum(r * r for r in res) / k)
        want = math.log10(math.comb(n, k)) + 2 * math.log10(N)
        for i in range(k):
            radius = max(res[i], rms)
            near = sum(1 for p in xyz if np.linalg.norm(p - pred[i]) <= radius)
            want += math.log10(ranks[i]) + math.log10(max(near, 1) / N)
        assert chance_log10(map_, n, ranks, pred, res) == pytest.approx(want, abs=1e-9)


def test_a_submap_of_a_place_the_map_lacks_is_refused_and_right_answers_stay() -> None:
    # KITTI-like: 20 objects + 3 false against 605; the place's own objects taken out of the
    # map leaves the same kinds of objects in the same layout, and nothing to match
    on, off = match_config(), match_config(verify={"max_chance_log10": None})
    refused = 0
    for seed in range(12):
        sc = make_scenario(Family.KITTI, seed)
        right = match(sc.map, sc.submap, on)
        assert right.result.accepted
        assert right.result.matches == match(sc.map, sc.submap, off).result.matches
        assert right.extra["chance_log10"] < -30  # 20 matches: far beyond chance
        (lacking, _), = lacking_pairs([sc])
        before, after = match(lacking, sc.submap, off), match(lacking, sc.submap, on)
        assert not after.result.accepted
        if before.result.accepted:  # chance found a fit: its count says so
            refused += 1
            assert before.extra["chance_log10"] > 0
            assert after.result.reason is RejectReason.TOO_FEW_MATCHES
    assert refused >= 2  # 3 of these 12 without the check


def test_a_large_submap_in_windows_is_judged_on_its_common_transform() -> None:
    # 60 objects + 3 false: matched in windows; against the map without them, chance's fits
    # (up to 14 wrong matches) are refused, the right answers stand far beyond chance
    on, off = match_config(), match_config(verify={"max_chance_log10": None})
    assert on.windows.above_objects < 63
    refused = 0
    for seed in (0, 1, 3):
        sc = make_scenario(Family.KITTI, seed, n_sub=60)
        right = match(sc.map, sc.submap, on)
        assert right.result.accepted and len(right.result.matches) == 60
        assert right.extra["chance_log10"] < -100
        (lacking, sub), = lacking_pairs([sc])
        before, after = match(lacking, sub, off), match(lacking, sub, on)
        refused += before.result.accepted
        assert after.result.reason is not RejectReason.VERIFIED and not after.result.matches
    assert refused == 3


def _verdict(sc: Scenario, count: float, small: float, large: float, size: int) -> bool:
    cfg = match_config(verify={"max_chance_log10": small, "max_chance_log10_large": large,
                               "chance_large_objects": size})
    out = match(sc.map, sc.submap, cfg)
    assert out.extra["chance_log10"] == pytest.approx(count)  # computed whatever the limit
    return out.result.accepted


def test_the_limit_follows_the_submaps_size() -> None:
    # underwater: 2-6 objects against 20-40, counts of -4 to -0.5: each answer is refused just
    # under its own count and accepted just over it, by the limit for its size only
    checked = 0
    for seed in range(12):
        sc = make_scenario(Family.UNDERWATER, seed)
        n = len(sc.submap.objects)
        free = match(sc.map, sc.submap, match_config(verify={"max_chance_log10": None}))
        if not free.result.accepted:
            continue
        c = free.extra["chance_log10"]
        assert np.isfinite(c)
        assert _verdict(sc, c, c + 0.01, -50.0, n + 1)  # small: the large limit does not apply
        assert not _verdict(sc, c, c - 0.01, 50.0, n + 1)
        assert not _verdict(sc, c, c + 0.01, c - 0.01, n)  # large from n objects: the stricter
        assert _verdict(sc, c, c + 0.01, c + 0.01, n)
        checked += 1
    assert checked >= 8
