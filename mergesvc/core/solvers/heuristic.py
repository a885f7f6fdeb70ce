"""RRWM, spectral matching and IPFP over candidate assignments only (no dense n1*n2 K).

Why not pygmtools here: its solvers need K over all n1*n2 pairs in its column-major layout, and
measured on this machine pygmtools' RRWM takes ~60 ms even for 5 vs 30 nodes and ~120 ms for
20 vs 100 (fixed Sinkhorn loops in Python), over the whole 10 ms budget of a small match. These
are the same algorithms (Cho et al. 2010; Leordeanu & Hebert 2005; Leordeanu et al. 2009) on the
m candidate pairs; tests check them against pygmtools on dense problems. Paper mode keeps pygmtools.
"""

from __future__ import annotations

import numpy as np

from mergesvc.core.solvers.hungarian import harden
from mergesvc.core.solvers.problem import UNMATCHED, AssignmentProblem

# RRWM's Sinkhorn step stops once no column exceeds its cap by more than this: the last
# steps of up to 20 only move the soft scores by less (same hard answers: tests/test_solvers.py)
RRWM_CAP_TOL = 1e-4


def sinkhorn(x_m: np.ndarray, rows: np.ndarray, cols: np.ndarray, n1: int, n2: int,
             cap: float = 1.0, iters: int = 20) -> np.ndarray:
    """Sinkhorn with slack on the candidate scores, (m,) -> (m,): rows normalised to 1 (every
    submap node has one unit of mass), column sums only capped at 1 (a map node may stay
    unmatched); stops once no column sum exceeds `cap`."""
    x = np.maximum(x_m, 1e-300)
    for _ in range(iters):
        x = x / np.bincount(rows, x, n1)[rows]  # sums of values >= 1e-300: never below it
        cs = np.bincount(cols, x, n2)
        if cs.max() <= cap:
            return x
        x = x / np.maximum(cs, 1.0)[cols]
    return x


def _conflict_mask(problem: AssignmentProblem) -> np.ndarray:
    """(m, m) True where two candidates share a row or a column (they can never co-occur)."""
    return (problem.rows[:, None] == problem.rows[None, :]) | (
        problem.cols[:, None] == problem.cols[None, :]
    )


def _masked_K(problem: AssignmentProblem) -> np.ndarray:
    """K with the entries of candidates sharing a row or a col zeroed (the diagonal kept)."""
    if problem.invalid_zero:
        return problem.K
    K = np.where(_conflict_mask(problem), 0.0, problem.K)
    np.fill_diagonal(K, np.diag(problem.K))
    return K


def rrwm(
    problem: AssignmentProblem,
    max_iter: int = 100,
    alpha: float = 0.2,
    beta: float = 30.0,
    tol: float = 1e-6,
    cap_tol: float = RRWM_CAP_TOL,
) -> np.ndarray:
    """Reweighted random walks (Cho et al. 2010) on a non-negative K. Returns soft x (m,).

    cap_tol: the Sinkhorn step's column-cap tolerance (0: up to its 20 steps, as pygmtools)."""
    K = _masked_K(problem)
    d_max = max(K.sum(axis=1).max(), 1e-12)
    P = K / d_max  # eq. 5: random walk with absorbing reweighting
    x = np.full(problem.m, 1.0 / max(problem.m, 1))
    rows, cols, n1, n2 = problem.rows, problem.cols, problem.n1, problem.n2
    for _ in range(max_iter):
        x_new = P @ x
        # reweighted jump: exponential emphasis then bistochastic projection (eq. 7-8)
        y = np.exp(beta * x_new / max(x_new.max(), 1e-300))
        y = sinkhorn(y, rows, cols, n1, n2, 1.0 + cap_tol)
        x_new = alpha * x_new + (1 - alpha) * y
        x_new /= max(x_new.sum(), 1e-300)
        if np.abs(x_new - x).sum() < tol:
            return x_new
        x = x_new
    return x


def spectral(problem: AssignmentProblem, max_iter: int = 100, tol: float = 1e-9) -> np.ndarray:
    """Spectral matching (Leordeanu & Hebert 2005): leading eigenvector of K by power iteration."""
    K = _masked_K(problem)
    x = np.full(problem.m, 1.0 / np.sqrt(max(problem.m, 1)))
    for _ in range(max_iter):
        x_new = K @ x
        norm = np.linalg.norm(x_new)
        if norm == 0:
            return x
        x_new /= norm
        if np.abs(x_new - x).sum() < tol:
            return x_new
        x = x_new
    return x


def ipfp(
    problem: AssignmentProblem, x0_m: np.ndarray | None = None, max_iter: int = 50
) -> np.ndarray:
    """Integer projected fixed point (Leordeanu et al. 2009). Returns a 0/1 vector (m,).

    Works on any K (signed too): each step maximises the linearised objective with the
    Hungarian (no-match allowed), then a line search towards it; keeps the best discrete point.
    """
    K = _masked_K(problem)
    x = np.full(problem.m, 1.0 / max(problem.m, 1)) if x0_m is None else x0_m.astype(float)
    best, best_score = np.zeros(problem.m), 0.0
    for _ in range(max_iter):
        grad = 2 * K @ x
        b = _indicator(problem, harden(problem, grad, unmatched_value=0.0))
        score_b = float(b @ K @ b)
        if score_b > best_score:
            best, best_score = b, score_b
        d = b - x
        curv = float(d @ K @ d)
        slope = float(grad @ d)
        if slope <= 1e-12:
            break
        t = 1.0 if curv >= 0 else min(1.0, -slope / (2 * curv))
        x = x + t * d
    return best


def _indicator(problem: AssignmentProblem, assignment: np.ndarray) -> np.ndarray:
    x = np.zeros(problem.m)
    rows = np.flatnonzero(assignment != UNMATCHED)
    if len(rows):
        x[problem.assignment_to_indices(assignment)] = 1.0
    return x
