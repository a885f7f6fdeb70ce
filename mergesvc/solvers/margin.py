"""Ambiguity of a solution: how much worse the best alternative is for each matched row.

A match is only as trustworthy as its margin over the best assignment that gives that submap
object a *different* map object (every other row free to change too). In a small, dense world
(a pool with a few look-alike objects a metre apart) several configurations can fit the
geometry; the optimum alone cannot tell, the margin can.
"""

from __future__ import annotations

import numpy as np

from mergesvc.solvers.exact import solve_exact
from mergesvc.solvers.problem import UNMATCHED, AssignmentProblem


def row_margins(
    problem: AssignmentProblem,
    assignment: np.ndarray,
    margin_needed: float,
    max_nodes: int = 20_000,
    time_limit_s: float | None = 0.5,
) -> np.ndarray:
    """(n1,) margin of each matched row (inf when it has no alternative; nan if unmatched).

    For row i matched to a_i: best objective over assignments with row i matched to another
    candidate, found exactly by removing (i, a_i) and adding a bonus B to row i's remaining
    candidates (B exceeds any possible objective change, so the optimum matches row i).
    The search prunes everything that cannot come within `margin_needed` of the solution: a
    row whose alternatives all stay below that is settled, its margin reported as the proven
    lower bound (>= margin_needed), not the exact value.
    """
    best = problem.score(assignment)
    out = np.full(problem.n1, np.nan)
    bonus = 2.0 * np.abs(problem.K).sum() + 1.0
    for i in np.flatnonzero(assignment != UNMATCHED):
        keep = ~((problem.rows == i) & (problem.cols == assignment[i]))
        if not np.any(keep & (problem.rows == i)):
            out[i] = np.inf
            continue
        idx = np.flatnonzero(keep)
        K = problem.K[np.ix_(idx, idx)].copy()
        on_row = problem.rows[idx] == i
        K[on_row, on_row] += bonus
        alt = AssignmentProblem(problem.n1, problem.n2, problem.rows[idx], problem.cols[idx], K)
        cutoff = best - margin_needed + bonus
        res = solve_exact(alt, max_nodes=max_nodes, time_limit_s=time_limit_s, cutoff=cutoff)
        # the proven upper bound on the alternatives (their best score when it beat the cutoff)
        out[i] = (best + bonus) - res.upper_bound
        if res.optimal and res.score <= cutoff:
            # nothing came within the margin (exact in the search; the bonus arithmetic may
            # round the reported bound a hair below it)
            out[i] = max(out[i], margin_needed)
    return out
