"""Pairwise geometric consistency of candidate assignments: the hard conflict constraint.

Two candidate pairs (i, a), (j, b) whose edge lengths disagree, |e_ij - e_ab| > k * tol_ij,
cannot both hold in a rigid configuration (the consistency graph of CLIPPER, PCM, ROMAN). The
conflict matrix feeds `AssignmentProblem.conflict`; the repair keeps heuristic answers feasible.
"""

from __future__ import annotations

import numpy as np

from mergesvc.core.solvers.problem import UNMATCHED, AssignmentProblem, block


def pairwise_conflicts(
    E1_m: np.ndarray,
    E2_m: np.ndarray,
    tol_m: np.ndarray,
    n_tol: float,
    rows: np.ndarray,
    cols: np.ndarray,
) -> np.ndarray:
    """(m, m) bool conflict matrix for `AssignmentProblem.conflict`.

    E1_m: (m, m) submap edge length e_ij of each candidate pair (p, q) = ((i, a), (j, b));
    E2_m: (m, m) map edge length e_ab; tol_m: (m, m) tolerance tol_ij (or a scalar);
    rows, cols: (m,) the candidates' submap and map nodes. Pairs sharing a row or a col are
    never both chosen anyway: they are left False, so the matrix says only what geometry adds.
    """
    conflict = np.abs(np.asarray(E1_m) - np.asarray(E2_m)) > n_tol * np.asarray(tol_m)
    conflict &= rows[:, None] != rows[None, :]
    conflict &= cols[:, None] != cols[None, :]
    # exactly symmetric even if the inputs were computed in float32 or asymmetrically rounded
    return conflict & conflict.T


def repair_conflicts(problem: AssignmentProblem, assignment: np.ndarray) -> np.ndarray:
    """Unmatch rows until no two matched candidates conflict. (n1,) -> (n1,).

    Greedy: drop the row in the most conflicts, ties broken by the smallest contribution to the
    objective (K[p, p] + sum over the other matched q of K[p, q] + K[q, p]). A heuristic answer
    stays a useful incumbent for the exact search instead of being discarded as infeasible.
    Unchanged when the problem has no conflict matrix. Raises SolverError when a chosen pair is
    not a candidate.
    """
    a = np.asarray(assignment).copy()
    if problem.conflict is None:
        return a
    rows = (a != UNMATCHED).nonzero()[0]
    if len(rows) < 2:
        return a
    idx = problem.assignment_to_indices(a)
    conflict, K = block(problem.conflict, idx), None
    while len(rows) >= 2:
        n_conf = conflict.sum(axis=1)
        if not n_conf.any():
            break
        if K is None:
            K = block(problem.K, idx)
        gain = K.sum(axis=0) + K.sum(axis=1) - K.diagonal()
        worst = np.lexsort((gain, -n_conf))[0]
        a[rows[worst]] = UNMATCHED
        keep = np.arange(len(rows)) != worst
        rows, idx = rows[keep], idx[keep]
        conflict, K = conflict[keep][:, keep], K[keep][:, keep]
    return a


__all__ = ["pairwise_conflicts", "repair_conflicts"]
