"""Tests of the tiny-problem search (solvers/near.py) and of the candidate elimination before
the branch and bound (solvers/reduce.py), both against brute force."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from oracles import brute_force, brute_margin
from test_consistency import conflicted_problem
from test_exact import random_problem

from mergesvc.core.solvers.near import near_optimal
from mergesvc.core.solvers.problem import UNMATCHED, AssignmentProblem
from mergesvc.core.solvers.reduce import eliminate


def every_assignment(problem: AssignmentProblem) -> tuple[np.ndarray, np.ndarray]:
    """(s, n1) every feasible assignment (rows may stay unmatched) and (s,) their scores."""
    options = [[UNMATCHED, *problem.cols[problem.rows == r].tolist()] for r in range(problem.n1)]
    found = [np.array(c) for c in itertools.product(*options)]
    found = [a for a in found if problem.is_feasible(a)]
    return np.array(found).reshape(len(found), problem.n1), np.array(
        [problem.score(a) for a in found])


def between_scores(scores: np.ndarray, q: float) -> float:
    """A threshold halfway between two distinct scores near the q-quantile (no ties on it)."""
    u = np.unique(np.round(scores, 9))
    k = min(int(q * len(u)), len(u) - 1)
    return float(u[k] - 0.5) if k == 0 else float(0.5 * (u[k - 1] + u[k]))


def mixed_problems(seed: int, count: int, n_max: int = 4):
    """Random problems with and without conflicts (mixed-sign K, ties, empty rows)."""
    rng = np.random.default_rng(seed)
    for k in range(count):
        yield (random_problem(rng, n_max, n_max) if k % 2 else
               conflicted_problem(rng, n_max, n_max))


def test_near_optimal_is_every_assignment_above_the_threshold() -> None:
    found_some = 0
    for problem in mixed_problems(11, 100):
        every, scores = every_assignment(problem)
        threshold = between_scores(scores, 0.8)
        res = near_optimal(problem, threshold, max_states=10**6)
        assert res is not None
        near = res[0]
        got = np.full(near.chosen.shape, UNMATCHED)
        got[near.chosen >= 0] = problem.cols[near.chosen[near.chosen >= 0]]
        want = every[scores > threshold]
        assert sorted(map(tuple, got.tolist())) == sorted(map(tuple, want.tolist()))
        assert near.score == pytest.approx([problem.score(a) for a in got], abs=1e-9)
        found_some += len(want) > 0
    assert found_some > 40


def test_near_optimal_best_and_margins_match_brute_force() -> None:
    needed, checked, settled = 0.5, 0, 0
    for problem in mixed_problems(12, 100):
        _, opt = brute_force(problem, allow_unmatched=True)
        near, _ = near_optimal(problem, max(opt, 0.0) - needed, max_states=10**6)
        best = near.best()
        assert best is not None and best.optimal
        assert best.score == pytest.approx(opt, abs=1e-9) == best.upper_bound
        assert problem.is_feasible(best.assignment)
        margins = near.margins(best.assignment, needed)
        for i in range(problem.n1):
            if best.assignment[i] == UNMATCHED:
                assert np.isnan(margins[i])
                continue
            true = brute_margin(problem, best.assignment, i)
            checked += 1
            if not np.isfinite(true):
                assert margins[i] == np.inf
            elif true < needed - 1e-9:
                assert margins[i] == pytest.approx(true, abs=1e-6)
            else:
                settled += 1
                assert needed - 1e-9 <= margins[i] <= true + 1e-6
    assert checked > 80 and settled > 10


def test_a_set_extended_to_new_candidates_is_the_search_over_all_of_them() -> None:
    """`extend`: when it keeps the set, the set is every assignment of all the candidates
    scoring above its threshold (brute force), that threshold at most the optimum less the
    margin, whatever the first search's threshold was; it keeps the set often."""
    rng = np.random.default_rng(14)
    margin, kept, searched = 0.5, 0, 0
    for problem in mixed_problems(13, 300, n_max=5):
        if problem.m < 2:
            continue
        first = problem.subset(np.arange(problem.m) < int(rng.integers(1, problem.m)))
        _, scores0 = every_assignment(first)
        below = margin + float(rng.choice([0.0, rng.uniform(0.0, 2.0)]))
        near, _ = near_optimal(first, max(scores0.max(), 0.0) - below, max_states=10**6)
        extended = near.extend(problem, margin)
        if extended is None:
            searched += 1
            continue
        kept += 1
        every, scores = every_assignment(problem)
        assert extended.best().score == pytest.approx(scores.max(), abs=1e-9)
        assert extended.threshold <= scores.max() - margin
        got = np.full(extended.chosen.shape, UNMATCHED)
        got[extended.chosen >= 0] = problem.cols[extended.chosen[extended.chosen >= 0]]
        want = every[scores > extended.threshold]
        assert sorted(map(tuple, got.tolist())) == sorted(map(tuple, want.tolist()))
    assert kept > 30 and searched > 30


def test_near_optimal_gives_up_beyond_its_state_budget() -> None:
    # 6 rows x 6 cols, every pair a candidate, K = 0: every partial assignment ties
    problem = AssignmentProblem.dense(np.zeros((36, 36)), 6, 6)
    assert near_optimal(problem, -1.0, max_states=100) is None
    assert near_optimal(problem, -1.0, max_states=10**6) is not None


def test_elimination_keeps_every_assignment_that_beats_the_threshold() -> None:
    """What eliminate drops is in no assignment above the threshold (star bound), or never
    needed (dominated): the best over what it keeps is the optimum whenever that beats the
    threshold, and dropped_bound bounds what it dropped."""
    removed = 0
    for problem in mixed_problems(13, 150):
        _, opt = brute_force(problem, allow_unmatched=True)
        every, scores = every_assignment(problem)
        threshold = between_scores(scores, 0.7)
        red = eliminate(problem, threshold)
        removed += int((~red.alive).sum())
        kept = brute_force(problem.subset(red.alive), allow_unmatched=True)[1]
        if opt > threshold + 1e-9:
            assert kept == pytest.approx(opt, abs=1e-9)
        else:
            assert opt <= max(threshold, red.dropped_bound) + 1e-9
        # with the star test alone, every assignment above the threshold survives
        alive = eliminate(problem, threshold, dominance=False).alive
        for a in every[scores > threshold + 1e-9]:
            assert alive[problem.assignment_to_indices(a)].all()
    assert removed > 50


def test_elimination_keeps_what_it_is_told_to() -> None:
    problem = conflicted_problem(np.random.default_rng(14), 5, 5)
    protect = np.zeros(problem.m, dtype=bool)
    protect[::2] = True
    red = eliminate(problem, 1e9, protect=protect)
    assert red.alive[protect].all() and not red.alive[~protect].any()
