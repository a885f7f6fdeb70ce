"""Ambiguity of a solution: how much worse the best alternative is for each matched row.

A match is only as trustworthy as its margin over the best assignment that gives that submap
object a *different* map object (every other row free to change too). In a small, dense world
(a pool with a few look-alike objects a metre apart) several configurations can fit the
geometry; the optimum alone cannot tell, the margin can.
"""

from __future__ import annotations

import numpy as np

from mergesvc.core.solvers.exact import ExactSearch
from mergesvc.core.solvers.problem import UNMATCHED, AssignmentProblem
from mergesvc.core.solvers.reduce import eliminate


def row_margins(
    problem: AssignmentProblem,
    assignment: np.ndarray,
    margin_needed: float,
    max_nodes: int = 20_000,
    time_limit_s: float | None = 0.5,
    same: np.ndarray | None = None,
) -> np.ndarray:
    """(n1,) margin of each matched row (inf when it has no alternative; nan if unmatched).

    For row i matched to a_i: best objective over assignments with row i matched to another
    candidate, found exactly by forbidding (i, a_i) (node score -B) and adding a bonus B to row
    i's other candidates (B exceeds any possible objective change, so the optimum matches row
    i). Only node scores change, so one set of search tables serves every row. The search
    prunes everything that cannot come within `margin_needed` of the solution: a row whose
    alternatives all stay below that is settled, its margin reported as the proven lower bound
    (>= margin_needed), not the exact value.
    same: optional (m,) bool, candidates that count as the chosen one (a map holding the same
    object twice, a metre apart, offers no real alternative); they are forbidden too.
    With a conflict matrix (problem.conflict) alternatives are conflict-free assignments: the
    presolve and the search honour it, and a single alternative candidate alone is always
    conflict-free, so the bonus still forces row i onto one.
    """
    best = problem.score(assignment)
    out = np.full(problem.n1, np.nan)
    matched = np.flatnonzero(assignment != UNMATCHED)
    if len(matched) == 0:
        return out
    bonus = 2.0 * np.abs(problem.K).sum() + 1.0
    # One reduced problem serves every row: a candidate in no assignment that comes within the
    # margin of the solution is no alternative for any row (reduce.py: its star bound); the
    # dominance test (unmatching never lowers) holds for the rows that get no bonus only.
    unmatched_rows = np.ones(problem.n1, dtype=bool)
    unmatched_rows[matched] = False
    keep = eliminate(problem, best - margin_needed, dominance=unmatched_rows[problem.rows]).alive
    base = problem.subset(keep) if not keep.all() else problem
    search = None  # its tables only when some row still has alternatives to search
    for i in matched:
        on_row = base.rows == i
        chosen = on_row & (base.cols == assignment[i])
        if same is not None:
            chosen |= on_row & same[keep]
        if not np.any(on_row & ~chosen):
            # no alternative at all, or only ones the reduction showed to fall short
            other = (problem.rows == i) & (problem.cols != assignment[i])
            if same is not None:
                other &= ~same
            has_any = np.any(other)
            out[i] = margin_needed if has_any else np.inf
            continue
        unary_add = np.where(chosen, -bonus, np.where(on_row, bonus, 0.0))
        cutoff = best - margin_needed + bonus
        search = search or ExactSearch(base)
        res = search.run(
            max_nodes=max_nodes, time_limit_s=time_limit_s, cutoff=cutoff, unary_add=unary_add
        )
        # the proven upper bound on the alternatives (their best score when it beat the
        # cutoff; the dropped ones score at most the cutoff)
        upper = res.upper_bound if base is problem else max(res.upper_bound, cutoff)
        out[i] = (best + bonus) - upper
        if res.optimal and res.score <= cutoff:
            # nothing came within the margin (exact in the search; the bonus arithmetic may
            # round the reported bound a hair below it)
            out[i] = max(out[i], margin_needed)
    return out
