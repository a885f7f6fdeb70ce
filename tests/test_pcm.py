"""Pairwise consistency of inter-robot factors: core/pcm.py (the loop test, the maximum clique
against brute force) and fleet/closures.py (which factors of a pair the graph trusts)."""

from __future__ import annotations

import itertools

import gtsam
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mergesvc.core.model import Factor
from mergesvc.core.pcm import loop_nees, max_clique
from mergesvc.core.poses import transform_from_pose3
from mergesvc.fleet.closures import ClosureSets, ConsistencyConfig


def _cliques(A: np.ndarray) -> list[tuple[int, ...]]:
    n = len(A)
    return [c for r in range(n + 1) for c in itertools.combinations(range(n), r)
            if all(A[a, b] for a, b in itertools.combinations(c, 2))]


@settings(max_examples=150, deadline=None)
@given(st.integers(1, 10), st.floats(0.1, 0.95), st.integers(0, 2**31 - 1))
def test_max_clique_against_brute_force(n: int, p: float, seed: int) -> None:
    rng = np.random.default_rng(seed)
    A = np.triu(rng.random((n, n)) < p, 1)
    A = A | A.T
    prefer = rng.random(n) < 0.4
    got = max_clique(A, prefer)
    assert all(A[a, b] for a, b in itertools.combinations(got, 2))
    cliques = _cliques(A)
    best = max(len(c) for c in cliques)
    assert len(got) == best
    assert prefer[got].sum() == max(prefer[list(c)].sum() for c in cliques if len(c) == best)


def test_max_clique_budget_still_answers_with_a_clique() -> None:
    rng = np.random.default_rng(0)
    A = np.triu(rng.random((70, 70)) < 0.9, 1)
    A = A | A.T
    got = max_clique(A, budget=50)
    assert got and all(A[a, b] for a, b in itertools.combinations(got, 2))


def _reference_nees(f, g, ca, cb) -> float:
    """The same loop error with the covariance by finite differences of the composition."""
    T = ca[0].compose(g[0]).compose(cb[0])
    e = np.asarray(gtsam.Pose3.Logmap(f[0].between(T)))

    def loop(xa: np.ndarray, xg: np.ndarray, xb: np.ndarray) -> np.ndarray:
        U = (ca[0].compose(gtsam.Pose3.Expmap(xa)).compose(g[0]).compose(gtsam.Pose3.Expmap(xg))
             .compose(cb[0]).compose(gtsam.Pose3.Expmap(xb)))
        return np.asarray(gtsam.Pose3.Logmap(T.between(U)))

    C = f[1].copy()
    for which, S in ((0, ca[1]), (1, g[1]), (2, cb[1])):
        J = np.zeros((6, 6))
        for k in range(6):
            d = np.zeros(6)
            d[k] = 1e-6
            args = [np.zeros(6)] * 3
            args[which] = d
            J[:, k] = loop(*args) / 1e-6
        C += J @ S @ J.T
    return float(e @ np.linalg.solve(C, e))


def test_loop_nees_against_a_reference() -> None:
    rng = np.random.default_rng(4)

    def pose() -> gtsam.Pose3:
        return gtsam.Pose3.Expmap(rng.normal(0, [0.3, 0.3, 1.0, 3.0, 3.0, 1.0]))

    def cov(scale: float) -> np.ndarray:
        A = rng.normal(size=(6, 6)) * scale
        return A @ A.T + np.eye(6) * scale**2

    for _ in range(5):
        f, g = (pose(), cov(0.05)), (pose(), cov(0.05))
        ca, cb = (pose(), cov(0.03)), (pose(), cov(0.03))
        assert loop_nees(f, g, ca, cb) == pytest.approx(_reference_nees(f, g, ca, cb), rel=1e-3)


def _factor(fid: str, ka: int, kb: int, T: gtsam.Pose3, sigma: float = 0.05,
            flip: bool = False) -> Factor:
    C = np.diag([sigma**2 / 25] * 3 + [sigma**2] * 3)
    if flip:  # written from robot b's side: the same measurement
        A = np.asarray(T.AdjointMap())
        return Factor(factor_id=fid, robot_a="b", session_a="s", robot_b="a", session_b="s",
                      T_a_b=transform_from_pose3(T.inverse()),
                      covariance=(A @ C @ A.T).tolist(), keyframe_a=kb, keyframe_b=ka)
    return Factor(factor_id=fid, robot_a="a", session_a="s", robot_b="b", session_b="s",
                  T_a_b=transform_from_pose3(T), covariance=C.tolist(), keyframe_a=ka,
                  keyframe_b=kb)


class _Chains:
    """Two straight odometry chains, a and b, 1 m a keyframe, tight."""

    def __init__(self) -> None:
        self.calls = 0

    def __call__(self, frame: str, k: int, targets: set[int]) -> dict:
        self.calls += 1
        C = np.eye(6) * 1e-6
        return {j: (gtsam.Pose3(gtsam.Rot3(), np.array([j - k, 0.0, 0.0])), C * (1 + abs(j - k)))
                for j in targets}


def _truth(ka: int, kb: int) -> gtsam.Pose3:
    """b's chain runs 10 m beside a's: keyframe kb of b seen from keyframe ka of a."""
    return gtsam.Pose3(gtsam.Rot3(), np.array([kb - ka, 10.0, 0.0]))


def test_consistent_factors_are_trusted_and_a_wrong_one_is_held() -> None:
    sets = ClosureSets(ConsistencyConfig(), _Chains())
    for i in range(4):
        v = sets.offer(_factor(f"f{i}", 2 * i, 2 * i + 1, _truth(2 * i, 2 * i + 1),
                               flip=i % 2 == 1))
        assert v.trusted == [f"f{i}"] and not v.withdrawn
    wrong = gtsam.Pose3(gtsam.Rot3.Yaw(0.3), np.array([3.0, 7.0, 0.0]))
    v = sets.offer(_factor("bad", 9, 9, wrong))
    assert not v.changed and not sets.is_trusted("bad") and sets.held() == ["bad"]
    # a consistent one after it is trusted; nothing else moves
    v = sets.offer(_factor("f4", 12, 12, _truth(12, 12)))
    assert v.trusted == ["f4"] and not v.withdrawn


def test_a_wrong_first_factor_is_withdrawn_when_the_right_ones_outnumber_it() -> None:
    sets = ClosureSets(ConsistencyConfig(), _Chains())
    wrong = gtsam.Pose3(gtsam.Rot3.Yaw(0.3), np.array([3.0, 7.0, 0.0]))
    assert sets.offer(_factor("bad", 0, 0, wrong)).trusted == ["bad"]  # nothing to test yet
    v1 = sets.offer(_factor("f1", 1, 1, _truth(1, 1)))
    assert not sets.is_trusted("f1") and not v1.changed  # one against one: the older stays
    v2 = sets.offer(_factor("f2", 2, 2, _truth(2, 2)))
    assert set(v2.trusted) == {"f1", "f2"} and v2.withdrawn == ["bad"]
    sets.forget("bad")
    assert sets.held() == []


def test_untestable_pairs_count_as_consistent() -> None:
    """Keyframes no chain joins (a lost submap): nothing to test, both trusted."""
    sets = ClosureSets(ConsistencyConfig(), lambda frame, k, targets: {})
    sets.offer(_factor("f1", 0, 0, _truth(0, 0)))
    sets.offer(_factor("f2", 5, 5, gtsam.Pose3(gtsam.Rot3.Yaw(1.0), np.array([9.0, 0, 0]))))
    assert sets.is_trusted("f1") and sets.is_trusted("f2")


def test_only_the_window_is_weighed_again() -> None:
    chains = _Chains()
    sets = ClosureSets(ConsistencyConfig(window=5), chains)
    for i in range(30):
        sets.offer(_factor(f"f{i}", i, i, _truth(i, i)))
    pair = next(iter(sets._pairs.values()))
    assert len(pair.meas) <= 5 and len(pair.ok) <= 2 * 5 * 5
    assert all(sets.is_trusted(f"f{i}") for i in range(30))
    assert chains.calls <= 2 * 30  # two walks a factor


def test_forgetting_a_factor_inside_the_window_brings_back_no_stale_one() -> None:
    """GNC retracts (forgets) factors inside the window: the next offers weigh the last ones
    that still hold their data (once a KeyError here failed every later submap of the pair)."""
    sets = ClosureSets(ConsistencyConfig(window=5), _Chains())
    for i in range(12):
        sets.offer(_factor(f"f{i}", i, i, _truth(i, i)))
    for i in (9, 10, 11):
        sets.forget(f"f{i}")
    for i in range(12, 20):
        v = sets.offer(_factor(f"f{i}", i, i, _truth(i, i)))
        assert v.trusted == [f"f{i}"] and not v.withdrawn
    pair = next(iter(sets._pairs.values()))
    assert len(pair.meas) == len(pair.keys) <= 5


def test_a_replay_changes_nothing_and_the_switch_turns_it_off() -> None:
    sets = ClosureSets(ConsistencyConfig(), _Chains())
    f = _factor("f1", 0, 0, _truth(0, 0))
    sets.offer(f)
    assert not sets.offer(f).changed
    off = ClosureSets(ConsistencyConfig(enabled=False), _Chains())
    wrong = gtsam.Pose3(gtsam.Rot3.Yaw(0.3), np.array([3.0, 7.0, 0.0]))
    off.offer(f)
    assert off.offer(_factor("bad", 1, 1, wrong)).trusted == ["bad"]
