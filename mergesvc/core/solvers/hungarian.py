"""Hardening: a soft or scored assignment -> one-to-one hard assignment (Hungarian / LAP)."""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from mergesvc.core.solvers.consistency import repair_conflicts
from mergesvc.core.solvers.problem import UNMATCHED, AssignmentProblem, block

# Value of a forbidden (non-candidate) cell; finite so linear_sum_assignment always succeeds.
_FORBIDDEN = -1e12


def harden(
    problem: AssignmentProblem, x_m: np.ndarray, unmatched_value: float | None = 0.0
) -> np.ndarray:
    """Maximum-weight one-to-one assignment of candidate scores x_m (m,).

    Each row may take its own "no match" column worth `unmatched_value`; None forbids no-match
    (every row with a candidate is matched, as in the paper). Returns (n1,) map node or UNMATCHED.
    """
    n1, n2 = problem.n1, problem.n2
    W = np.full((n1, n2 + n1), _FORBIDDEN)
    W[problem.rows, problem.cols] = x_m
    if unmatched_value is not None:
        W[np.arange(n1), n2 + np.arange(n1)] = unmatched_value
    r, c = linear_sum_assignment(W, maximize=True)
    out = np.full(n1, UNMATCHED, dtype=np.int64)
    ok = (c < n2) & (W[r, c] > _FORBIDDEN / 2)
    out[r[ok]] = c[ok]
    return out


def harden_dense(X: np.ndarray) -> np.ndarray:
    """Paper mode: Hungarian on a dense (n1, n2) soft matrix, every row matched (n1 <= n2)."""
    r, c = linear_sum_assignment(X, maximize=True)
    out = np.full(X.shape[0], UNMATCHED, dtype=np.int64)
    out[r] = c
    return out


def prune_negative(problem: AssignmentProblem, assignment: np.ndarray) -> np.ndarray:
    """Drop matches whose marginal contribution to the objective is negative, worst first.

    (n1,) -> (n1,). Never lowers the objective: every removal raises it. When the problem has a
    conflict matrix, conflicting matches go first (`repair_conflicts`; that step may lower the
    objective), so the answer is always feasible.
    """
    a = repair_conflicts(problem, assignment)
    rows = (a != UNMATCHED).nonzero()[0]
    if len(rows) == 0:
        return a
    K = block(problem.K, problem.assignment_to_indices(a))
    while len(rows):
        # contribution of p: K_pp + sum_{q != p} (K_pq + K_qp)
        diag = K.diagonal()
        gain = diag + K.sum(axis=0) + K.sum(axis=1) - 2 * diag
        worst = int(np.argmin(gain))
        if gain[worst] >= 0:
            break
        a[rows[worst]] = UNMATCHED
        keep = np.arange(len(rows)) != worst
        rows, K = rows[keep], K[keep][:, keep]
    return a
