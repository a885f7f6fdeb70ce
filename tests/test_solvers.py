"""Candidate-restricted RRWM / SM / IPFP against pygmtools, hardening, dense K layout."""

from __future__ import annotations

import numpy as np
import pygmtools as pygm
import pytest
from oracles import brute_force

from mergesvc.core.solvers import dense, heuristic
from mergesvc.core.solvers.hungarian import harden, harden_dense, prune_negative
from mergesvc.core.solvers.problem import UNMATCHED, AssignmentProblem

pygm.set_backend("numpy")


def planted(n: int, rng: np.random.Generator, noise: float = 0.05):
    """Two point sets related by a permutation; K from node + edge affinities (row-major)."""
    pts1 = rng.uniform(0, 10, size=(n, 2))
    perm = rng.permutation(n)
    pts2 = np.empty_like(pts1)
    pts2[perm] = pts1 + rng.normal(size=pts1.shape) * noise
    L1 = np.linalg.norm(pts1[:, None] - pts1[None], axis=2)
    L2 = np.linalg.norm(pts2[:, None] - pts2[None], axis=2)
    E = np.exp(-((L1[:, None, :, None] - L2[None, :, None, :]) ** 2) / 0.5)
    K = E.reshape(n * n, n * n)  # E[i, a, j, b] -> K[i * n + a, j * n + b]
    # zero the entries of conflicting pairs, diagonal = mild node affinity
    rows, cols = np.divmod(np.arange(n * n), n)
    conflict = (rows[:, None] == rows[None]) | (cols[:, None] == cols[None])
    K[conflict] = 0.0
    K[np.arange(n * n), np.arange(n * n)] = 0.1
    return AssignmentProblem.dense(K, n, n), perm


def to_column_major(problem: AssignmentProblem) -> np.ndarray:
    n1, n2 = problem.n1, problem.n2
    # column-major index a * n1 + i holds row-major entry i * n2 + a
    perm = (np.arange(n1)[None, :] * n2 + np.arange(n2)[:, None]).ravel()
    return problem.K[np.ix_(perm, perm)]


@pytest.mark.parametrize("seed", range(5))
def test_heuristics_agree_with_pygmtools_and_recover_planted(seed: int) -> None:
    rng = np.random.default_rng(seed)
    problem, perm = planted(7, rng)
    Kc = to_column_major(problem)
    n = np.array([7])
    ref_sm = harden_dense(np.asarray(pygm.sm(Kc, n, n)))
    ref_rrwm = harden_dense(np.asarray(pygm.rrwm(Kc, n, n)))
    ours_sm = harden(problem, heuristic.spectral(problem), unmatched_value=None)
    ours_rrwm = harden(problem, heuristic.rrwm(problem), unmatched_value=None)
    ours_ipfp = harden(problem, heuristic.ipfp(problem, heuristic.spectral(problem)), None)
    np.testing.assert_array_equal(ours_sm, ref_sm)
    np.testing.assert_array_equal(ours_rrwm, ref_rrwm)
    for got in (ours_sm, ours_rrwm, ours_ipfp):
        np.testing.assert_array_equal(got, perm)


def test_spectral_is_the_leading_eigenvector() -> None:
    problem, _ = planted(5, np.random.default_rng(9))
    x = heuristic.spectral(problem, max_iter=1000)
    masked = np.where(heuristic._conflict_mask(problem), 0.0, problem.K)
    np.fill_diagonal(masked, np.diag(problem.K))
    _, V = np.linalg.eigh(masked)
    np.testing.assert_allclose(np.abs(x), np.abs(V[:, -1]), atol=1e-6)


def test_column_major_reorder_round_trip() -> None:
    problem, _ = planted(4, np.random.default_rng(3))
    Kc = to_column_major(problem)
    np.testing.assert_array_equal(dense.column_major_to_row_major(Kc, 4, 4), problem.K)


def test_build_dense_K_matches_direct_construction() -> None:
    rng = np.random.default_rng(11)
    n1, n2, sigma = 3, 4, 0.7
    A = rng.random((n1, n2))
    e1 = np.array([[0, 1], [1, 2]])
    e2 = np.array([[0, 1], [1, 2], [0, 3]])
    l1, l2 = rng.uniform(1, 3, 2), rng.uniform(1, 3, 3)
    K = dense.build_dense_K(A, e1, l1, e2, l2, sigma)
    ref = np.zeros((n1 * n2, n1 * n2))
    for i in range(n1):
        for a in range(n2):
            ref[a * n1 + i, a * n1 + i] = A[i, a]
    for (i, j), li in zip(e1, l1):
        for (a, b), la in zip(e2, l2):
            v = np.exp(-((li - la) ** 2) / sigma)
            for (p, q), (r, s) in (((i, j), (a, b)), ((j, i), (b, a)), ((i, j), (b, a)),
                                   ((j, i), (a, b))):
                ref[r * n1 + p, s * n1 + q] = v
    np.testing.assert_allclose(K, ref)


def test_harden_respects_no_match_and_candidates() -> None:
    rows, cols = np.array([0, 0, 1, 2]), np.array([0, 1, 1, 1])
    problem = AssignmentProblem(3, 2, rows, cols, np.zeros((4, 4)))
    out = harden(problem, np.array([0.9, 0.8, 0.7, -0.5]), unmatched_value=0.0)
    np.testing.assert_array_equal(out, [0, 1, UNMATCHED])
    # no-match forbidden: row 2 has only col 1 -> the LAP moves row 1 off it only if it can
    out2 = harden(problem, np.array([0.9, 0.8, 0.7, -0.5]), unmatched_value=None)
    assert out2[2] == 1 or out2[1] == 1
    assert sum(v != UNMATCHED for v in out2) >= 2


@pytest.mark.parametrize("seed", range(20))
def test_prune_negative_never_lowers_the_score(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n1, n2 = 4, 5
    K = rng.normal(size=(n1 * n2, n1 * n2))
    problem = AssignmentProblem.dense((K + K.T) / 2, n1, n2)
    start = harden(problem, rng.random(n1 * n2), unmatched_value=None)
    pruned = prune_negative(problem, start)
    assert problem.score(pruned) >= problem.score(start) - 1e-12
    assert problem.is_feasible(pruned)
    _, best = brute_force(problem)
    assert problem.score(pruned) <= best + 1e-9


def test_pygmtools_wrapper_rejects_unknown_solver() -> None:
    from mergesvc.errors import SolverError

    with pytest.raises(SolverError):
        dense.solve_dense("astar", np.eye(4), 2, 2)
    # and the ipfp wrapper survives a flat K (pygmtools divides 0/0 there)
    X = dense.solve_dense("ipfp", np.zeros((4, 4)), 2, 2)
    assert X.shape == (2, 2)


def test_dense_solvers_leave_pygmtools_global_backend_alone(monkeypatch) -> None:
    """mergesvc names the numpy backend in each call: a user who set another global backend
    keeps it, and our calls do not depend on it (a backend that is not installed would fail)."""
    import importlib

    monkeypatch.setattr(pygm, "BACKEND", "pytorch")  # torch is not installed here
    importlib.reload(dense)  # module import must not reset the user's choice
    assert pygm.BACKEND == "pytorch"
    rng = np.random.default_rng(0)
    pos = rng.normal(size=(4, 3))
    edges = np.array([[0, 1], [1, 2], [2, 3], [0, 3]])
    lengths = np.linalg.norm(pos[edges[:, 0]] - pos[edges[:, 1]], axis=1)
    K = dense.build_dense_K(np.eye(4), edges, lengths, edges, lengths, sigma=1.0)
    X = dense.solve_dense("rrwm", K[0] if K.ndim == 3 else K, 4, 4)
    assert harden_dense(X).tolist() == [0, 1, 2, 3]
    assert pygm.BACKEND == "pytorch"



def _candidate_problem(rng: np.random.Generator) -> AssignmentProblem:
    """A pipeline-like problem: n1 submap points among n2 map points, k candidates per row
    (the true one and random others), node scores in (0, 1], edge affinities as in K."""
    n1 = int(rng.integers(2, 16))
    n2 = n1 + int(rng.integers(5, 60))
    pts2 = rng.uniform(0, 30, size=(n2, 3))
    truth = rng.permutation(n2)[:n1]
    pts1 = pts2[truth] + rng.normal(size=(n1, 3)) * 0.2
    k = min(int(rng.integers(3, 13)), n2)
    rows, cols = [], []
    for i in range(n1):
        others = rng.choice(np.setdiff1d(np.arange(n2), [truth[i]]), size=k - 1, replace=False)
        rows += [i] * k
        cols += [truth[i], *others]
    rows, cols = np.array(rows), np.array(cols)
    L1 = np.linalg.norm(pts1[:, None] - pts1[None], axis=2)
    L2 = np.linalg.norm(pts2[:, None] - pts2[None], axis=2)
    K = np.exp(-((L1[np.ix_(rows, rows)] - L2[np.ix_(cols, cols)]) ** 2) / 0.5) / n1
    K[(rows[:, None] == rows[None]) | (cols[:, None] == cols[None])] = 0.0
    np.fill_diagonal(K, rng.uniform(0.05, 1.0, len(rows)))
    return AssignmentProblem(n1, n2, rows, cols, K)


def test_rrwm_cap_tolerance_keeps_the_hard_answer() -> None:
    """RRWM's Sinkhorn stopping at RRWM_CAP_TOL gives the hard answer of the full 20 steps
    (pygmtools' count) on pipeline-like problems."""
    rng = np.random.default_rng(26)
    for _ in range(60):
        problem = _candidate_problem(rng)
        full = heuristic.rrwm(problem, cap_tol=0.0)
        fast = heuristic.rrwm(problem)
        np.testing.assert_array_equal(harden(problem, fast, 0.0), harden(problem, full, 0.0))
        np.testing.assert_allclose(fast, full, atol=1e-3)
