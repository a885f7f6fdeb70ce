"""Candidate elimination before the exact search: bounds on flat arrays, no search tables.

Two candidates are compatible when they lie in different rows and cols and do not conflict. In
a feasible assignment S each chosen p takes the share K[p, p] + sum_{q in S, q != p} K[p, q]
of the objective, at most h(p) = K[p, p] + sum over the other rows j of max(0, the best K[p, q]
of a q in row j compatible with p). Every q of S is compatible with p, one per row, so any S
holding p scores at most star(p) = h(p) + sum over the other rows j of max(0, the best h(q) of a
q in row j compatible with p). A candidate whose star is at most a threshold is in no
assignment beating it; one whose whole contribution (K[p, p] + twice its partners) cannot be
positive is never needed (unmatching it never lowers a score: `exact.dominated`). Both drop
candidates, which tightens the others' bounds, so the tests repeat. Sound for any sign of K and
with unmatched rows allowed; work is linear in the compatible pairs (sparse on verified-mode
problems, where most candidate pairs conflict).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mergesvc.core.solvers.bnb_state import ABS_TOL, REL_TOL
from mergesvc.core.solvers.problem import AssignmentProblem


@dataclass(frozen=True)
class Partners:
    """The compatible ordered candidate pairs (p, q) of a problem, grouped by (p, row of q).

    p, q: (e,) candidate indices; k: (e,) symmetric K[p, q]; starts: (g,) first pair of each
    (p, row of q) group; group_p: (g,) its p."""

    p: np.ndarray
    q: np.ndarray
    k: np.ndarray
    starts: np.ndarray
    group_p: np.ndarray


def partners(problem: AssignmentProblem) -> Partners:
    """The problem's compatible pairs (computed once per problem, kept with it)."""
    cached = problem.__dict__.get("_partners")
    if cached is not None:
        return cached
    rows, cols = problem.rows, problem.cols
    ok = rows[:, None] != rows[None, :]
    ok &= cols[:, None] != cols[None, :]
    if problem.conflict is not None:
        ok &= ~problem.conflict
    # the q of each p in the order of their rows (stable): np.nonzero then lists the pairs
    # already grouped by (p, row of q), in the order a stable sort by that key would give
    by_row = None if bool(np.all(rows[1:] >= rows[:-1])) else np.argsort(rows, kind="stable")
    # the flat nonzero: np.nonzero's 2-D path is slower on a few hundred candidates
    flat = np.flatnonzero(ok if by_row is None else ok[:, by_row])
    p, q = np.divmod(flat, len(rows))
    if by_row is not None:
        q = by_row[q]
    K = problem.K
    k = K[p, q]
    if not problem.invalid_zero:  # a builder's K is symmetric already
        k = 0.5 * (k + K[q, p])
    key = p * max(problem.n1, 1) + rows[q]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]]) if len(key) else \
        np.zeros(0, dtype=np.int64)
    out = Partners(p, q, k, starts, p[starts])
    object.__setattr__(problem, "_partners", out)  # frozen dataclass: a private cache
    return out


def _best_per_group(values: np.ndarray, pp: Partners, m: int) -> np.ndarray:
    """(m,) sum over p's groups of max(0, the group's best value); values (e,), -inf = none."""
    if len(values) == 0:
        return np.zeros(m)
    best = np.maximum.reduceat(values, pp.starts)
    np.maximum(best, 0.0, out=best)
    return np.bincount(pp.group_p, weights=best, minlength=m)


@dataclass(frozen=True)
class Reduction:
    """What `eliminate` kept: alive (m,) bool; dropped_bound: the largest star of a candidate
    dropped for its star (-inf if none): no assignment holding a dropped candidate scores more
    than max(dropped_bound, the best over the kept ones)."""

    alive: np.ndarray
    dropped_bound: float


def eliminate(
    problem: AssignmentProblem,
    threshold: float,
    protect: np.ndarray | None = None,
    dominance: bool | np.ndarray = True,
    max_rounds: int = 20,
) -> Reduction:
    """Drop candidates that no assignment scoring above `threshold` holds (star bound), and with
    `dominance` those never needed (contribution <= 0), repeating while any goes.

    protect: optional (m,) bool, candidates kept whatever their bounds (an incumbent's).
    dominance: False, True, or (m,) bool: where the dominance test may drop candidates.
    Rows may stay unmatched. The optimum over the kept candidates is the problem's optimum,
    unless that optimum is at most max(threshold, dropped_bound) (module docstring).
    """
    m = problem.m
    alive = np.ones(m, dtype=bool)
    if m == 0:
        return Reduction(alive, -np.inf)
    pp = partners(problem)
    diag = np.asarray(problem.K.diagonal(), dtype=np.float64)
    keep = np.zeros(m, dtype=bool) if protect is None else np.asarray(protect, dtype=bool)
    dom = np.broadcast_to(np.asarray(dominance, dtype=bool), (m,)) & ~keep
    tol = ABS_TOL + REL_TOL * abs(threshold)
    dropped_bound = -np.inf
    dead_q = np.zeros(len(pp.q), dtype=bool)
    for _ in range(max_rounds):
        k = np.where(dead_q, -np.inf, pp.k) if dead_q.any() else pp.k
        half = _best_per_group(k, pp, m)
        h = diag + half
        hq = h[pp.q]
        if dead_q.any():
            hq[dead_q] = -np.inf
        star = h + _best_per_group(hq, pp, m)
        by_star = alive & ~keep & (star <= threshold + tol)
        drop = by_star
        if dom.any():
            drop = drop | (alive & dom & (diag + 2.0 * half <= 0.0))
        if not drop.any():
            break
        if by_star.any():
            dropped_bound = max(dropped_bound, float(star[by_star].max()))
        alive &= ~drop
        dead_q = ~alive[pp.q]  # a dropped candidate is nobody's partner any more
    return Reduction(alive, dropped_bound)


__all__ = ["Partners", "Reduction", "eliminate", "partners"]
