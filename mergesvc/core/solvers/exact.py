"""Exact depth-first branch and bound for the candidate-restricted Lawler QAP of problem.py.

Honours the optional pairwise conflict constraint (geometric consistency, consistency.py) in the
bound, the propagation and every primal solution. Its oracles (brute force, pygmtools' A*) live
with the tests, in tests/oracles.py.

This module holds the entry points, the dominance presolve and the search loop with its
branching rule; the search state (tables, nodes, propagation) lives in bnb_state.py, the upper
bounds in bounds.py and the primal heuristics in primal.py.
"""

# Why our own exact solver: pygmtools' A* (the only exact graph-matching solver in our stack)
# exists only on the pytorch backend and was measured here growing exponentially: 5 vs 20 nodes
# 0.13 s, 8 vs 40 nodes 20 s, 10 vs 60 nodes 518 s. It also works on the dense n1*n2 affinity
# matrix, so it cannot exploit a candidate restriction (3-15 candidates per row) or a no-match
# option, which are exactly what make our problems small. tests/oracles.py keeps it available as
# an independent oracle when torch happens to be installed.

from __future__ import annotations

import copy
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import maximum_bipartite_matching

from mergesvc.core.solvers.bnb_state import (
    ABS_TOL,
    NO_MATCH,
    REL_TOL,
    Node,
    Tables,
    child,
    prunes,
    root,
)
from mergesvc.core.solvers.bounds import Bound, bound
from mergesvc.core.solvers.consistency import repair_conflicts
from mergesvc.core.solvers.primal import local_search, slots_score, to_cols
from mergesvc.core.solvers.problem import UNMATCHED, AssignmentProblem, block
from mergesvc.core.solvers.reduce import eliminate
from mergesvc.errors import SolverError

log = logging.getLogger(__name__)

# The dominance presolve forms an (m, m) matrix; above this many candidates it is skipped.
_PRESOLVE_MAX_CANDIDATES = 4000


@dataclass(frozen=True)
class ExactResult:
    """Outcome of `solve_exact`.

    assignment: (n1,) int, map node (col) per row, or UNMATCHED (-1)
    score: problem.score(assignment)
    optimal: True when the search completed, i.e. the assignment is proven optimal
    nodes_expanded: number of search nodes whose bound was evaluated (root included)
    upper_bound: best proven upper bound on the optimum (== score when optimal)
    """

    assignment: np.ndarray
    score: float
    optimal: bool
    nodes_expanded: int
    upper_bound: float


def _check_full_feasible(problem: AssignmentProblem) -> None:
    """Raise SolverError when no assignment matches every row (bipartite matching < n1)."""
    if problem.n1 == 0:
        return
    if problem.n1 > problem.n2 or problem.m == 0:
        raise SolverError("no feasible full assignment: fewer candidate cols than rows")
    graph = csr_matrix(
        (np.ones(problem.m), (problem.rows, problem.cols)), shape=(problem.n1, problem.n2)
    )
    match = maximum_bipartite_matching(graph, perm_type="column")
    if int((match >= 0).sum()) < problem.n1:
        raise SolverError("no feasible full assignment: candidate graph has no perfect matching")


def _choose_branch(
    t: Tables, b: Bound, best: float, allow_unmatched: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Pick what to branch on and its surviving children.

    Candidates are every open row (children: its free candidate cols, or unmatched) and every
    free col that must be used (children: the open rows that can take it). A child survives
    when its bound beats the incumbent. Branch on the candidate whose surviving children have
    the smallest total excess of bound over incumbent, a proxy for the work left below it: it
    fixes tightly constrained rows/cols first and keeps the tree narrow. (Measured against
    "fewest surviving children" with regret tie-break: ~25% fewer nodes on QAPLIB n=12 and on
    synthetic sparse problems.) Cols that may stay unused are not candidates: their "unused"
    child is the parent minus one col, with a weak bound, and branching there proved poor.
    Returns (rows, slots, bounds) of the children sorted ascending by bound (best last, popped
    first; slot NO_MATCH = leave the row unmatched). None when nothing survives.
    """
    est, ban_est, free, U = b.est, b.ban_est, b.free, b.open_rows
    assert est is not None and ban_est is not None and free is not None
    if best == -math.inf:
        # Unreachable in practice (the root LAP completion is scored before any branching),
        # but without an incumbent every feasible child survives: use a finite threshold.
        best = float(np.min(est[np.isfinite(est)], initial=b.value)) - 1.0
    u, nf = len(U), len(free)
    threshold = best + ABS_TOL + REL_TOL * abs(best)
    real = est[:, :nf]
    unm = est[:, nf:].max(axis=1) if allow_unmatched else np.full(u, -np.inf)
    row_opts = np.hstack([real, unm[:, None]])  # (u, nf + 1): cols, then unmatched
    row_excess = np.where(row_opts > threshold, row_opts - threshold, 0.0)
    if not row_excess.any(axis=1).all():
        return None  # some open row has no surviving option
    potential = row_excess.sum(axis=1)
    if nf:
        col_excess = np.where(real > threshold, real - threshold, 0.0)
        # A col can stay unused only if rows may go unmatched or there are more cols than rows.
        may_stay_free = (ban_est > threshold) & (allow_unmatched or nf > u)
        if not (col_excess.any(axis=0) | may_stay_free).all():
            return None  # a col that must be used has no row left to take it
        potential = np.concatenate([potential, np.where(may_stay_free, np.inf, col_excess.sum(0))])
    k = int(np.argmin(potential))
    if k < u:
        q = np.nonzero(row_opts[k] > threshold)[0]
        bounds = row_opts[k, q]
        rows = np.full(len(q), U[k])
        slots = np.full(len(q), NO_MATCH, dtype=np.int64)
        slots[q < nf] = t.slot_of[U[k], free[q[q < nf]]]
    else:
        q = k - u
        r = np.nonzero(real[:, q] > threshold)[0]
        bounds = real[r, q]
        rows = U[r]
        slots = t.slot_of[rows, free[q]]
    order = np.argsort(bounds, kind="stable")
    return rows[order], slots[order], bounds[order]


def dominated(
    problem: AssignmentProblem, slack: np.ndarray | None = None, max_rounds: int = 20
) -> np.ndarray:
    """(m,) bool: candidates that no optimum needs when rows may stay unmatched.

    In any assignment S holding p = (i, a), p contributes K[p, p] + sum_{q in S, q != p}
    (K[p, q] + K[q, p]). Each other row j holds at most one q, with a col other than a, or none:
    so the contribution is at most UB(p) = K[p, p] + sum_{j != i} max(0, max_q P[p, q]).
    When UB(p) <= 0, unmatching row i never lowers the score: p can go. UB only shrinks as
    candidates go, so several can go at once, and the test is repeated on what is left.
    Sound for any sign of K; on verified-mode problems it removes look-alikes that no
    geometry supports (measured: 60 -> 19-37 candidates underwater, 276 -> 227-268 on KITTI).
    slack: optional (m,) >= 0; p goes only when UB(p) <= -slack[p]. Any solution holding p
    then scores at most (the solution without p) - slack[p] <= optimum - slack[p]: the margin
    test uses this to drop alternatives that cannot come within its margin.
    """
    m = problem.m
    gone = np.zeros(m, dtype=bool)
    if m == 0:
        return gone
    order = np.argsort(problem.rows, kind="stable")
    rows, cols = problem.rows[order], problem.cols[order]
    if problem.invalid_zero:
        # candidate_K's problems: K symmetric, 0 where two candidates share a row or a col
        sorted_ = bool(np.all(problem.rows[1:] >= problem.rows[:-1]))
        P = problem.K * 2.0 if sorted_ else block(problem.K, order) * 2.0
        np.fill_diagonal(P, 0.0)
        if problem.conflict is not None:
            P[problem.conflict if sorted_ else block(problem.conflict, order)] = 0.0
    else:
        P = block(problem.K, order)
        P += P.T.copy()
        apart = rows[:, None] == rows[None, :]  # same row (and the diagonal)
        apart |= cols[:, None] == cols[None, :]  # same col: cannot coexist
        if problem.conflict is not None:
            apart |= block(problem.conflict, order)  # conflicting: cannot coexist
        P[apart] = 0.0
    np.maximum(P, 0.0, out=P)
    unary = np.diag(problem.K)[order]
    need = np.zeros(m) if slack is None else -np.asarray(slack, dtype=np.float64)[order]
    alive = np.ones(m, dtype=bool)
    starts = np.flatnonzero(np.r_[True, rows[1:] != rows[:-1]])
    for _ in range(max_rounds):
        ub = unary + np.maximum.reduceat(P, starts, axis=1).sum(1)
        drop = alive & (ub <= need)
        if not drop.any():
            break
        alive &= ~drop
        P[:, drop] = 0.0  # a dropped candidate is no partner any more
    gone[order] = ~alive
    return gone


def solve_exact(
    problem: AssignmentProblem,
    *,
    allow_unmatched: bool = True,
    incumbent: np.ndarray | None = None,
    max_nodes: int = 2_000_000,
    time_limit_s: float | None = None,
    clock: Callable[[], float] = time.monotonic,
    cutoff: float | None = None,
    gap: float = 0.0,
) -> ExactResult:
    """Maximise problem.score over feasible assignments by depth-first branch and bound.

    incumbent: optional (n1,) feasible assignment (map node per row or UNMATCHED) used as the
        initial lower bound; ignored when infeasible for `allow_unmatched`.
    max_nodes / time_limit_s: search budget; the root is always evaluated. When exhausted the
        best assignment found is returned with optimal=False and a valid upper_bound.
    gap: absolute optimality tolerance: subtrees that cannot beat the incumbent by more than
        gap are pruned, so the answer is proven within gap of the optimum (upper_bound says
        how close); 0 = exact. Near-ties (a map holding the same object twice) otherwise make
        the search walk every equivalent configuration.
    cutoff: only solutions scoring above it matter; subtrees that cannot beat it are pruned.
        The answer is the optimum when its score exceeds cutoff; otherwise the search proved
        that nothing beats cutoff (upper_bound <= max(score, cutoff) stays valid either way).
    Raises SolverError when allow_unmatched=False and no full assignment exists (with
    conflicts: also when the budget runs out before the search finds one).
    With unmatched rows allowed, candidates in no assignment beating the incumbent (or the
    cutoff) by more than gap, and dominated ones, are removed first (reduce.eliminate; the
    incumbent's are kept): the answer over what is left is the answer over the whole set.
    Conflicts (problem.conflict): an incumbent holding conflicting pairs is repaired first
    (`repair_conflicts`) when rows may stay unmatched, else ignored.
    """
    if cutoff is not None and not allow_unmatched:
        raise SolverError("a cutoff needs allow_unmatched (the empty assignment is the fallback)")
    incumbent = _repaired(problem, incumbent, allow_unmatched)
    dropped_bound = -math.inf
    if allow_unmatched and 0 < problem.m <= _PRESOLVE_MAX_CANDIDATES:
        # candidates in no assignment beating the incumbent (or the cutoff) by the gap, and
        # dominated ones, go before the search (reduce.py); the incumbent's stay
        floor, protect = 0.0, None  # leaving every row unmatched scores 0
        inc = None if incumbent is None else np.asarray(incumbent)
        if inc is not None and np.issubdtype(inc.dtype, np.integer) and \
                problem.is_feasible(inc):
            floor = max(floor, problem.score(inc))
            protect = np.zeros(problem.m, dtype=bool)
            protect[problem.assignment_to_indices(inc)] = True
        threshold = max(floor, -math.inf if cutoff is None else float(cutoff)) + gap
        red = eliminate(problem, threshold, protect)
        if not red.alive.all():
            problem = problem.subset(red.alive)
        # what a dropped candidate's assignments can score: no more than the threshold
        dropped_bound = min(red.dropped_bound, threshold)
    res = _solve_exact(
        problem,
        allow_unmatched=allow_unmatched,
        incumbent=incumbent,
        max_nodes=max_nodes,
        time_limit_s=time_limit_s,
        clock=clock,
        cutoff=cutoff,
        gap=gap,
    )
    if dropped_bound > res.upper_bound:
        res = ExactResult(res.assignment, res.score, res.optimal, res.nodes_expanded,
                          dropped_bound)
    return res


def _repaired(
    problem: AssignmentProblem, incumbent: np.ndarray | None, allow_unmatched: bool
) -> np.ndarray | None:
    """The incumbent with conflicting rows unmatched (when that is allowed and it is a valid
    candidate assignment otherwise); unchanged in every other case, left to the search to vet."""
    if incumbent is None or problem.conflict is None or not allow_unmatched:
        return incumbent
    inc = np.asarray(incumbent)
    if inc.shape != (problem.n1,) or not np.issubdtype(inc.dtype, np.integer):
        return incumbent
    try:
        return repair_conflicts(problem, inc)
    except SolverError:  # not a candidate assignment: the search ignores it
        return incumbent


def _solve_exact(
    problem: AssignmentProblem,
    *,
    allow_unmatched: bool,
    incumbent: np.ndarray | None,
    max_nodes: int,
    time_limit_s: float | None,
    clock: Callable[[], float],
    cutoff: float | None,
    gap: float,
) -> ExactResult:
    start = clock()
    if not allow_unmatched:
        _check_full_feasible(problem)
    search = ExactSearch(problem)
    res = search.run(
        allow_unmatched=allow_unmatched,
        incumbent=incumbent,
        max_nodes=max_nodes,
        time_limit_s=time_limit_s,
        clock=clock,
        cutoff=cutoff,
        start=start,
        gap=gap,
    )
    # the objective as the problem defines it (the tables hold the same numbers, summed in
    # another order): the bound keeps its gap over the score
    score = problem.score(res.assignment)
    upper = score + max(res.upper_bound - res.score, 0.0)
    return ExactResult(res.assignment, score, res.optimal, res.nodes_expanded, upper)


class ExactSearch:
    """The branch and bound over one problem's tables, reusable with changed node scores.

    `run(unary_add=...)` adds (m,) to the diagonal of K (the node scores) for that search only:
    problems that differ from this one only there (the margin test forces or forbids single
    candidates that way) share the tables instead of rebuilding them.
    """

    def __init__(self, problem: AssignmentProblem) -> None:
        self.problem = problem
        self.tables = Tables(problem)

    def run(
        self,
        *,
        allow_unmatched: bool = True,
        incumbent: np.ndarray | None = None,
        max_nodes: int = 2_000_000,
        time_limit_s: float | None = None,
        clock: Callable[[], float] = time.monotonic,
        cutoff: float | None = None,
        unary_add: np.ndarray | None = None,
        start: float | None = None,
        gap: float = 0.0,
    ) -> ExactResult:
        """Depth-first branch and bound; see `solve_exact` for the arguments. Scores in the
        result include `unary_add`. No presolve here."""
        if not gap >= 0.0:
            raise SolverError(f"gap must be >= 0, got {gap}")
        incumbent = _repaired(self.problem, incumbent, allow_unmatched)
        start = clock() if start is None else start
        t = self.tables
        if unary_add is not None:
            t = copy.copy(t)
            t.unary = self.tables.unary.copy()
            rows = self.problem.rows
            t.unary[
                rows, self.tables.slot_of[rows, np.searchsorted(t.col_of, self.problem.cols)]
            ] += np.asarray(unary_add, dtype=np.float64)
        n1 = t.n1
        best_slots: np.ndarray | None = None
        best = -math.inf
        if allow_unmatched:
            # Leaving every row unmatched is always feasible and scores 0.
            best_slots, best = np.full(n1, NO_MATCH, dtype=np.int64), 0.0
        if incumbent is not None:
            inc = np.asarray(incumbent)
            if (
                inc.shape == (n1,)
                and (np.issubdtype(inc.dtype, np.integer) or np.issubdtype(inc.dtype, np.floating))
                and np.all(np.isfinite(inc))
                and np.all(inc == np.round(inc))
                and self.problem.is_feasible(inc.astype(np.int64), allow_unmatched=allow_unmatched)
            ):
                inc = inc.astype(np.int64)
                slots = np.full(n1, NO_MATCH, dtype=np.int64)
                m = inc != UNMATCHED
                slots[m] = t.slot_of[np.nonzero(m)[0], np.searchsorted(t.col_of, inc[m])]
                slots = local_search(t, slots, allow_unmatched)
                s = slots_score(t, slots)
                if s > best:
                    best_slots, best = slots, s
            else:
                log.debug("ignoring infeasible incumbent")
        floor = -math.inf if cutoff is None else float(cutoff)
        best = max(best, floor)  # prune against the cutoff; best_slots keeps the real solution

        nodes = 0
        # DFS stack: (node, child rows, child slots, child bounds), children sorted ascending.
        stack: list[tuple[Node, np.ndarray, np.ndarray, np.ndarray]] = []
        stopped = False

        def expand(node: Node) -> float:
            """Evaluate a node, update the incumbent, push it when it must be branched on."""
            nonlocal best, best_slots, nodes
            nodes += 1
            b = bound(t, node, allow_unmatched, best + gap)
            if b is None:
                return -math.inf
            if b.primal_score > best:
                improved = local_search(t, b.primal, allow_unmatched)
                best, best_slots = slots_score(t, improved), improved
            if b.est is None or prunes(b.value, best + gap):
                # No child bounds: the node was pruned, is a leaf, or has one open row (the LAP
                # is exact then, so its completion is the subtree optimum).
                return b.value
            choice = _choose_branch(t, b, best + gap, allow_unmatched)
            if choice is not None:
                stack.append((node, *choice))
            return b.value

        root_bound = expand(root(t, allow_unmatched))
        while stack:
            node, rows_, slots_, ests = stack[-1]
            if len(slots_) == 0 or prunes(float(ests[-1]), best + gap):
                # Children are sorted ascending by bound: if the best one is pruned, all are.
                stack.pop()
                continue
            if nodes >= max_nodes or (time_limit_s is not None and clock() - start >= time_limit_s):
                stopped = True
                break
            stack[-1] = (node, rows_[:-1], slots_[:-1], ests[:-1])
            expand(child(t, node, int(rows_[-1]), int(slots_[-1])))

        if best_slots is None:
            # Rows must all match and no completion was conflict-free (or, without conflicts,
            # the root LAP itself failed although a full matching exists).
            raise SolverError("exact solver found no feasible assignment")
        score = slots_score(t, best_slots)
        # what pruning proved: nothing pruned beats max(score + gap, cutoff); the root bound
        # holds for everything
        pruned = min(max(score + gap, floor), root_bound)
        if stopped:
            open_max = max((float(e[-1]) for *_, e in stack if len(e)), default=-math.inf)
            upper = max(score, pruned, min(open_max, root_bound))
            log.debug("exact search stopped after %d nodes, gap %.6g", nodes, upper - score)
        else:
            upper = max(score, pruned)
        return ExactResult(to_cols(t, best_slots), score, not stopped, nodes, float(upper))


__all__ = ["ExactResult", "ExactSearch", "dominated", "solve_exact"]
