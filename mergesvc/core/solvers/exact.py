"""Exact depth-first branch and bound for the candidate-restricted Lawler QAP of problem.py.

Honours the optional pairwise conflict constraint (geometric consistency, consistency.py) in the
bound, the propagation and every primal solution. Also a brute-force reference (tiny problems
only) and an optional pygmtools A* cross-check.
"""

# Why our own exact solver: pygmtools' A* (the only exact graph-matching solver in our stack)
# exists only on the pytorch backend and was measured here growing exponentially: 5 vs 20 nodes
# 0.13 s, 8 vs 40 nodes 20 s, 10 vs 60 nodes 518 s. It also works on the dense n1*n2 affinity
# matrix, so it cannot exploit a candidate restriction (3-15 candidates per row) or a no-match
# option, which are exactly what make our problems small. `astar_crosscheck` keeps it available
# as an independent oracle when torch happens to be installed.

from __future__ import annotations

import copy
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import maximum_bipartite_matching

from mergesvc.core.solvers.consistency import repair_conflicts
from mergesvc.core.solvers.problem import UNMATCHED, AssignmentProblem
from mergesvc.errors import SolverError

logger = logging.getLogger(__name__)

# Slot codes in the internal per-row state (slots index a row's candidate list).
_UNASSIGNED = -2
_NO_MATCH = -1

# Pruning tolerance: absolute plus relative, so large-magnitude integer objectives (QAPLIB costs
# up to ~1e8) are not kept alive by float rounding in sums of hundreds of terms.
_ABS_TOL = 1e-9
_REL_TOL = 1e-10

# The dense per-row-pair block tensor has n1^2 * kmax^2 entries (two float64 copies); refuse
# problems where that gets large, an exact search on them would not finish anyway.
_MAX_BLOCK_ENTRIES = 4_000_000

BRUTE_FORCE_LIMIT = 2_000_000

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


def _prunes(bound: float, best: float) -> bool:
    """True when a subtree with upper bound `bound` cannot beat the incumbent value `best`."""
    if best == -math.inf:
        return False
    return bound <= best + _ABS_TOL + _REL_TOL * abs(best)


class _Tables:
    """Per-problem precomputation, indexed by (row, slot) where slot is a row's candidate number.

    kmax: max candidates per row (>= 1); nc: number of distinct candidate cols ("compact cols").
    slot_p: (n1, kmax) int, candidate index into problem.K, -1 for padding
    ccol: (n1, kmax) int, compact col of each slot, -1 for padding
    valid: (n1, kmax) bool, slot is a real candidate
    col_of: (nc,) int, original map node of each compact col
    slot_of: (n1, nc) int, slot of (row, compact col), -1 when not a candidate
    unary: (n1, kmax) float, u_i(a) = K[p, p] (0 on padding)
    pair: (n1, n1, kmax, kmax) float, P_ij(a, b) = K[p, q] + K[q, p]; 0 on i == j and padding
    pair_ex: like pair but -inf where b is padding, shares a's col, conflicts with a, or
        i == j; the max over b of a pair_ex row is the "best partner" term of the bound
    conf: (n1, n1, kmax, kmax) bool in the layout of pair, (i, a) conflicts with (j, b); None
        when the problem has no conflicts (every conflict test is then skipped)
    """

    def __init__(self, problem: AssignmentProblem) -> None:
        n1 = problem.n1
        rows = np.asarray(problem.rows, dtype=np.int64)
        cols = np.asarray(problem.cols, dtype=np.int64)
        K = np.asarray(problem.K, dtype=np.float64)
        counts = np.bincount(rows, minlength=n1) if n1 else np.zeros(0, dtype=np.int64)
        kmax = max(int(counts.max()) if n1 else 0, 1)
        if n1 * n1 * kmax * kmax > _MAX_BLOCK_ENTRIES:
            raise SolverError(
                f"problem too large for the exact solver ({n1} rows, up to {kmax} candidates)"
            )
        self.n1, self.kmax = n1, kmax
        self.col_of, compact = np.unique(cols, return_inverse=True)
        self.nc = len(self.col_of)

        # Slot of each candidate within its row: stable order of appearance.
        order = np.argsort(rows, kind="stable")
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]]) if n1 else np.zeros(0, np.int64)
        slot = np.empty(len(rows), dtype=np.int64)
        slot[order] = np.arange(len(rows)) - np.repeat(starts, counts)

        self.slot_p = np.full((n1, kmax), -1, dtype=np.int64)
        self.slot_p[rows, slot] = np.arange(len(rows))
        self.ccol = np.full((n1, kmax), -1, dtype=np.int64)
        self.ccol[rows, slot] = compact
        self.valid = self.slot_p >= 0
        self.slot_of = np.full((n1, self.nc), -1, dtype=np.int64)
        self.slot_of[rows, compact] = slot
        self.counts = counts

        self.unary = np.zeros((n1, kmax))
        self.unary[rows, slot] = np.diag(K)

        # Gather K into row-pair blocks once: Kb[i, a, j, b] = K[p(i,a), p(j,b)].
        p = np.where(self.valid, self.slot_p, 0)
        if len(rows) == 0:
            K = np.zeros((1, 1))  # every slot is padding; gather from a dummy entry
        Kb = K[p.reshape(-1)[:, None], p.reshape(-1)[None, :]].reshape(n1, kmax, n1, kmax)
        pair = Kb + Kb.transpose(2, 3, 0, 1)
        pair = pair.transpose(0, 2, 1, 3).copy()  # -> (i, j, a, b)
        pad = ~(self.valid[:, None, :, None] & self.valid[None, :, None, :])
        pair[pad] = 0.0
        idx = np.arange(n1)
        pair[idx, idx] = 0.0
        self.pair = pair

        excl = self.ccol[:, None, :, None] == self.ccol[None, :, None, :]  # same col
        excl |= ~self.valid[None, :, None, :]
        excl[idx, idx] = True

        self.conf: np.ndarray | None = None
        if problem.conflict is not None and problem.conflict.any() and len(rows):
            flat = p.reshape(-1)
            Cb = problem.conflict.take(flat, axis=0).take(flat, axis=1)  # bool: take is fast
            conf = Cb.reshape(n1, kmax, n1, kmax).transpose(0, 2, 1, 3).copy()
            conf[pad] = False
            conf[idx, idx] = False
            self.conf = conf
            # a partner that conflicts with (i, a) is no partner: the bound only counts
            # partners consistent with the slot it bounds
            excl |= conf
        self.pair_ex = np.where(excl, -np.inf, pair)


class _Node:
    """State of one search node; arrays are shared copy-on-write between parent and children.

    assign: (n1,) int slot per row, _NO_MATCH or _UNASSIGNED
    used: (nc,) bool, compact col taken by an assigned row
    feas: (n1, kmax) bool, slot is a candidate whose col is still free and that conflicts with
        no assigned row
    fixed: score of the assigned rows among themselves
    F: (n1, kmax) float, u_i(a) + sum over assigned j of P_ij(a, a_j)
    best: (n1, n1, kmax) float, max over feasible b (col != col(a), no conflict with a) of
        P_ij(a, b); -inf if none. Kept up to date only without conflicts (an upper bound on
        it otherwise, exact at the root)
    best_col: (n1, n1, kmax) int, compact col of that maximiser (-1 if none), so only entries
        whose partner col gets used need recomputing when a col is taken
    """

    __slots__ = ("F", "assign", "best", "best_col", "feas", "fixed", "used")

    def __init__(
        self,
        assign: np.ndarray,
        used: np.ndarray,
        feas: np.ndarray,
        fixed: float,
        F: np.ndarray,
        best: np.ndarray,
        best_col: np.ndarray,
    ) -> None:
        self.assign, self.used, self.feas, self.fixed = assign, used, feas, fixed
        self.F, self.best, self.best_col = F, best, best_col


def _root(t: _Tables, allow_unmatched: bool) -> _Node:
    assign = np.full(t.n1, _UNASSIGNED, dtype=np.int64)
    if allow_unmatched:
        # Rows without candidates can only stay unmatched: fix them instead of branching.
        assign[t.counts == 0] = _NO_MATCH
    used = np.zeros(t.nc, dtype=bool)
    feas = t.valid.copy()
    arg = np.argmax(t.pair_ex, axis=3)
    best = np.take_along_axis(t.pair_ex, arg[..., None], axis=3)[..., 0]
    best_col = np.where(np.isfinite(best), t.ccol[np.arange(t.n1)[None, :, None], arg], -1)
    return _Node(assign, used, feas, 0.0, t.unary.copy(), best, best_col)


def _child(t: _Tables, node: _Node, i: int, a: int) -> _Node:
    """Child node: row i set to slot a (or _NO_MATCH)."""
    assign = node.assign.copy()
    assign[i] = a
    if a == _NO_MATCH:
        # Unmatched contributes nothing and takes no col: everything else is shared.
        return _Node(assign, node.used, node.feas, node.fixed, node.F, node.best, node.best_col)
    c = int(t.ccol[i, a])
    fixed = node.fixed + float(node.F[i, a])
    F = node.F + t.pair[:, i, :, a]
    used = node.used.copy()
    used[c] = True
    feas = node.feas & (t.ccol != c)
    best, best_col = node.best, node.best_col
    if t.conf is not None:
        # Propagate the conflicts of (i, a). The best-partner tables are not maintained: with
        # conflicts the bound recomputes partners over what is left (`_consistency_bound`).
        feas &= ~t.conf[i, :, a, :]
        return _Node(assign, used, feas, fixed, F, best, best_col)
    # Only "best partner" entries whose maximiser sits on col c change; recompute those, and only
    # for pairs of still-unassigned rows with a still-feasible slot (others are never read).
    open_rows = assign == _UNASSIGNED
    stale = (best_col == c) & open_rows[:, None, None] & open_rows[None, :, None]
    stale &= feas[:, None, :]
    if stale.any():
        best, best_col = best.copy(), best_col.copy()
        si, sj, sa = np.nonzero(stale)
        cand = np.where(feas[sj], t.pair_ex[si, sj, sa, :], -np.inf)  # (ns, kmax)
        arg = np.argmax(cand, axis=1)
        val = cand[np.arange(len(arg)), arg]
        best[si, sj, sa] = val
        best_col[si, sj, sa] = np.where(np.isfinite(val), t.ccol[sj, arg], -1)
    return _Node(assign, used, feas, fixed, F, best, best_col)


@dataclass
class _Bound:
    """Bound evaluation of a node.

    value: upper bound on any completion; primal: (n1,) slots of the best LAP completion found
    (feasible); primal_score: its exact score; open_rows: (u,) unassigned rows.
    Child bounds, in the outer LAP's column space (None when no branching is needed):
    free: (nf,) compact cols still free; est: (u, nf + u or nf) bound on the subtree forcing
    open row r onto column q (columns >= nf are the "unmatched" dummies), -inf if infeasible;
    ban_est: (nf,) bound on the subtree where free col q stays unused.
    """

    value: float
    primal: np.ndarray
    primal_score: float
    open_rows: np.ndarray
    free: np.ndarray | None = None
    est: np.ndarray | None = None
    ban_est: np.ndarray | None = None


def _lap_duals(M: np.ndarray, lc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Dual prices of an optimal max-LAP, recovered from its solution.

    M: (u, ncols) entry values (-inf = forbidden), ncols >= u; lc: (u,) column of row r.
    Returns row prices y (u,) and column prices z (ncols,) >= 0 with y_r + z_q >= M[r, q]
    everywhere (dual feasible by construction, whatever the rounding). z is the least
    fixed point of z_q = max(0, max_r M[r, q] - M[r, lc_r] + z_{lc_r}) (longest alternating
    paths, Bellman-Ford); at an optimum it is 0 on unused columns, so sum(y) + sum(z) equals
    the LAP value.
    """
    u = M.shape[0]
    R = M - M[np.arange(u), lc][:, None]
    z = np.zeros(M.shape[1])
    for _ in range(u + 1):
        z_new = np.maximum((R + z[lc][:, None]).max(axis=0), 0.0)
        if np.array_equal(z_new, z):
            break
        z = z_new
    y = (M - z[None, :]).max(axis=1)
    return y, z


@dataclass
class _Lap:
    """Outer LAP result: bound, LAP completion (slots + exact score), dual child bounds."""

    value: float
    primal: np.ndarray
    primal_score: float
    free: np.ndarray
    est: np.ndarray
    ban_est: np.ndarray


def _outer_lap(
    t: _Tables, node: _Node, U: np.ndarray, C: np.ndarray, allow_unmatched: bool
) -> _Lap | None:
    """LAP over open rows x free cols (+ u "unmatched" dummies worth 0) with entry costs C.

    The LAP enforces injectivity between the open rows, which the per-entry costs ignore.
    C: (u, kmax), -inf where infeasible. Returns None when no completion exists. The LAP
    solution, repaired when two of its pairs conflict, is a feasible completion and is scored
    exactly (primal heuristic; -inf when it conflicts and rows may not go unmatched). Child bounds
    come from LAP duals (y, z): forcing (r, q) gives at most dual - (y_r + z_q - M[r, q]),
    keeping col q unused at most dual - z_q.
    """
    u = C.shape[0]
    free = np.nonzero(~node.used)[0]
    nf = len(free)
    pos = np.full(t.nc, -1, dtype=np.int64)
    pos[free] = np.arange(nf)
    M = np.full((u, nf + (u if allow_unmatched else 0)), -np.inf)
    r_idx, a_idx = np.nonzero(np.isfinite(C))
    M[r_idx, pos[t.ccol[U[r_idx], a_idx]]] = C[r_idx, a_idx]
    if allow_unmatched:
        M[:, nf:] = 0.0
    if M.shape[1] < u:
        return None
    try:
        lr, lc = linear_sum_assignment(M, maximize=True)
    except ValueError:  # scipy: "cost matrix is infeasible" (some row cannot be placed)
        return None
    value = node.fixed + float(M[lr, lc].sum())
    if not math.isfinite(value):
        return None

    primal = node.assign.copy()
    is_real = lc < nf
    rows_u = U[lr]
    primal[rows_u[~is_real]] = _NO_MATCH
    mr = rows_u[is_real]
    slots = t.slot_of[mr, free[lc[is_real]]]
    primal[mr] = slots
    clash = t.conf is not None and bool(
        t.conf[mr[:, None], mr[None, :], slots[:, None], slots[None, :]].any()
    )
    if clash:
        # The LAP ignores conflicts between open rows (assigned rows conflict with none of
        # their slots, by propagation): repair, or drop the completion when rows must match.
        if allow_unmatched:
            primal = _repair_slots(t, primal)
            primal_score = _slots_score(t, primal)
        else:
            primal_score = -math.inf
    else:
        primal_score = (
            node.fixed
            + float(node.F[mr, slots].sum())
            + 0.5 * float(t.pair[mr[:, None], mr[None, :], slots[:, None], slots[None, :]].sum())
        )

    y, z = _lap_duals(M, lc)  # lr == arange(u) since u <= ncols
    dual_value = node.fixed + float(y.sum() + z.sum())
    est = np.minimum(dual_value - (y[:, None] + z[None, :] - M), value)
    ban_est = np.minimum(dual_value - z[:nf], value)
    return _Lap(value, primal, primal_score, free, est, ban_est)


def _strong_partner(
    t: _Tables,
    node: _Node,
    U: np.ndarray,
    feas: np.ndarray,
    need: np.ndarray,
    allow_unmatched: bool,
) -> np.ndarray:
    """Injectivity-aware partner term: for each open (i, a), an LAP over the other open rows.

    feas: (u, kmax) feasible slots of the open rows; need: (u, kmax) entries to compute.
    Returns (u, kmax): max over injective choices b_j (free cols != col(a), or unmatched when
    allowed) of sum_{j open, j != i} P_ij(a, b_j); -inf where infeasible, +inf (no information)
    where not needed.
    This is the classical Gilmore-Lawler inner problem; the cheap term instead lets every j pick
    its best b independently. It costs u*kmax small LAPs, so it runs only when the cheap bound
    fails to prune.
    """
    u, _ = feas.shape
    out = np.where(need, -np.inf, np.inf)
    if u == 1:
        out[need & feas] = 0.0
        return out
    # Fast path: where the other rows' independent best partners (the cheap term) sit on
    # distinct cols, that choice is injective, so the inner LAP equals the cheap term and adds
    # nothing: leave +inf there. Only entries with a col collision need a LAP. On sparse
    # candidate sets (a 20-object submap against a large map) that is most of them.
    Ug = U[:, None]
    best = node.best[Ug, U[None, :]]  # (u, u, kmax): [r, s, a]
    bcol = node.best_col[Ug, U[None, :]]
    idx = np.arange(u)
    live = np.isfinite(best)
    if allow_unmatched:
        live &= best > 0.0  # a partner worth <= 0 stays unmatched: it takes no col
    live[idx, idx] = False
    # rows without a live partner get a distinct negative code, so they never collide (an
    # infeasible partner makes the cheap term -inf already, which the LAP cannot lower)
    bcol = np.where(live, bcol, -1 - idx[None, :, None])
    collide = (np.diff(np.sort(bcol, axis=1), axis=1) == 0).any(axis=1)  # (u, kmax): [r, a]
    need = need & feas
    out[need & ~collide] = np.inf
    need &= collide
    if not need.any():
        return out
    free = np.nonzero(~node.used)[0]
    nf = len(free)
    pos = np.full(t.nc, -1, dtype=np.int64)
    pos[free] = np.arange(nf)
    PU = t.pair_ex[np.ix_(U, U)]  # (u, u, kmax, kmax), -inf on r == s and same col
    s_idx, b_idx = np.nonzero(feas)
    f_idx = pos[t.ccol[U[s_idx], b_idx]]
    n_extra = u - 1 if allow_unmatched else 0
    rows = np.arange(u - 1)
    for r in range(u):
        slots = np.nonzero(need[r])[0]
        if len(slots) == 0:
            continue
        # cost[n, s, f] = -P_rs(a_n, b) for the slot b of row s on free col f (rows s != r).
        keep = s_idx != r
        s_loc = s_idx[keep] - (s_idx[keep] > r)
        neg = np.full((len(slots), u - 1, nf + n_extra), np.inf)
        neg[:, s_loc, f_idx[keep]] = -PU[r][s_idx[keep], :, b_idx[keep]][:, slots].T
        if n_extra:
            neg[:, :, nf:] = 0.0
        for n, cost in enumerate(neg):
            try:
                cols = linear_sum_assignment(cost)[1]
            except ValueError:  # some other row cannot coexist with (r, a)
                continue
            out[r, slots[n]] = -cost[rows, cols].sum()
    return out


def _bound(t: _Tables, node: _Node, allow_unmatched: bool, best: float) -> _Bound | None:
    """Gilmore-Lawler-style bound plus the LAP solution as a feasible completion.

    The score of a completion is fixed + sum_i F[i, a_i] + 1/2 sum_{i != j open} P_ij(a_i, a_j);
    each open row i bounds its share by C[i, a] = F[i, a] + 1/2 (partner term), and an outer LAP
    over C respects injectivity. Stage 1 uses a cheap partner term (each j picks its best b
    independently); if that does not prune against `best`, stage 2 uses the exact inner LAPs.
    Both are valid for any sign of K. With conflicts, `_bound_consistent` takes over after
    the entry bounds. Returns None when the node has no feasible completion.
    """
    U = np.nonzero(node.assign == _UNASSIGNED)[0]
    u = len(U)
    if u == 0:
        return _Bound(node.fixed, node.assign.copy(), node.fixed, U)
    if t.conf is not None and u >= 2:
        return _bound_consistent(t, node, U, allow_unmatched, best)

    # Stage 1. With unmatched rows allowed a partner may contribute 0 (it stays unmatched).
    # Valid for any sign: P_ij(a_i, a_j) / 2 never exceeds half of either side's best partner.
    partner = node.best[np.ix_(U, U)]  # (u, u, kmax)
    if allow_unmatched:
        partner = np.maximum(partner, 0.0)
    partner[np.arange(u), np.arange(u)] = 0.0
    feas = node.feas[U]
    C = node.F[U] + 0.5 * partner.sum(axis=1)
    C[~feas] = -np.inf
    lap = _outer_lap(t, node, U, C, allow_unmatched)
    if lap is None:
        return None
    best_now = max(best, lap.primal_score)
    if u <= 1 or _prunes(lap.value, best_now):
        return _Bound(lap.value, lap.primal, lap.primal_score, U)

    # Stage 2, only for entries whose child survives stage 1: an entry whose child is already
    # pruned keeps its (larger, still valid) stage-1 value; it can only matter to the outer LAP
    # through completions using it, which are all bounded below the incumbent anyway. The
    # entrywise min of two valid entry bounds is a valid entry bound.
    nf = len(lap.free)
    pos = np.full(t.nc, -1, dtype=np.int64)
    pos[lap.free] = np.arange(nf)
    r_idx, a_idx = np.nonzero(feas)
    need = np.zeros_like(feas)
    threshold = best_now + _ABS_TOL + _REL_TOL * abs(best_now)
    need[r_idx, a_idx] = lap.est[r_idx, pos[t.ccol[U[r_idx], a_idx]]] > threshold
    strong = _strong_partner(t, node, U, feas, need, allow_unmatched)
    C = np.minimum(C, node.F[U] + 0.5 * strong)
    lap2 = _outer_lap(t, node, U, C, allow_unmatched)
    if lap2 is None:
        return None
    primal, primal_score = lap.primal, lap.primal_score
    if lap2.primal_score > primal_score:
        primal, primal_score = lap2.primal, lap2.primal_score
    return _Bound(
        min(lap.value, lap2.value),
        primal,
        primal_score,
        U,
        lap.free,
        np.minimum(lap.est, lap2.est),
        np.minimum(lap.ban_est, lap2.ban_est),
    )


def _bound_consistent(
    t: _Tables, node: _Node, U: np.ndarray, allow_unmatched: bool, best: float
) -> _Bound | None:
    """`_bound` for problems with conflicts and at least two open rows (instead of stages 1
    and 2).

    The consistency bounds (`_filter_by_consistency`, entry bounds C included) come first; an
    outer LAP over the entries they leave adds injectivity and the primal completion, and its
    duals bound the children along with the stars and pairs. (The inner LAPs of stage 2 are
    skipped: measured on crowded drive maps, they pruned nothing the consistency bounds had
    not, at a third of the node cost.)
    """
    threshold = best + _ABS_TOL + _REL_TOL * abs(best)
    res = _filter_by_consistency(t, node, U, node.feas[U], allow_unmatched, threshold)
    if res is None:
        return None
    cb, filtered = res
    # After filtering the bounds hold only for completions that could beat the threshold:
    # report them no lower than it (which is what pruning proves anyway).
    floor = best if filtered else -math.inf
    if _prunes(cb.value, best):
        return _Bound(max(cb.value, floor), node.assign.copy(), -math.inf, U)
    lap = _outer_lap(t, node, U, cb.C, allow_unmatched)
    if lap is None:  # rows must match: infeasible, or nothing left beats the threshold
        return None if floor == -math.inf else _Bound(floor, node.assign.copy(), -math.inf, U)
    lap.value = max(min(lap.value, cb.value), floor)
    nf = len(lap.free)
    pos = np.full(t.nc, -1, dtype=np.int64)
    pos[lap.free] = np.arange(nf)
    r_idx, a_idx = np.nonzero(np.isfinite(cb.est))
    cols = pos[t.ccol[U[r_idx], a_idx]]
    lap.est[r_idx, cols] = np.minimum(lap.est[r_idx, cols], cb.est[r_idx, a_idx])
    if allow_unmatched:
        lap.est[:, nf:] = np.minimum(lap.est[:, nf:], cb.est_unm[:, None])
    lap.ban_est = np.minimum(lap.ban_est, lap.value)
    if _prunes(lap.value, max(best, lap.primal_score)):
        return _Bound(lap.value, lap.primal, lap.primal_score, U)
    return _Bound(lap.value, lap.primal, lap.primal_score, U, lap.free, lap.est, lap.ban_est)


@dataclass
class _Consistent:
    """Consistency bounds of a node's open rows (problems with conflicts), absolute values.

    C: (u, kmax) entry bounds over the surviving slots (-inf elsewhere); value: bound on the
    node; est: (u, kmax) bound on the child forcing each slot; est_unm: (u,) bound on the child
    leaving each row unmatched (-inf when rows must match).
    """

    C: np.ndarray
    value: float
    est: np.ndarray
    est_unm: np.ndarray


def _consistency_bound(
    t: _Tables,
    node: _Node,
    U: np.ndarray,
    alive: np.ndarray,
    allow_unmatched: bool,
    must: np.ndarray | None = None,
) -> _Consistent | None:
    """Bounds that use the conflicts between the open rows' candidates. alive: (u, kmax);
    must: optional (u,) bool, rows that may not stay unmatched (in the completions of interest).

    The GL entry bound C[r, a] = F[r, a] + 1/2 sum_j (best partner of (r, a) in row j) counts
    only partners among the alive slots. The outer LAP lets every row claim its best entry
    although those entries may conflict; two bounds use that they cannot:
    - row pairs: a completion's matched pairs are pairwise compatible (no conflict, distinct
      cols), so pairing the open rows up, fixed + sum over pairs (r, s) of B_rs (the best
      compatible C[r, a] + C[s, b], either row possibly unmatched) + sum over unpaired rows of
      max_a C[r, a] bounds it. The pairing greedily takes the pairs that lose most (a false
      detection whose best candidates contradict the true matches loses its whole claim).
    - stars: the child forcing (r, a) keeps of every other row only what is compatible with
      (r, a) (what propagation will leave): C[r, a] + sum over the others of their best there.
    Both bound the children too; the best child of any one row bounds the node. Works on each
    row's alive slots only: after a few assignments propagation leaves a handful per row.
    Returns None when rows must match and some row or pair of rows has no compatible choice.
    """
    u, kmax = alive.shape
    ar = np.arange(u)
    kf = max(int(alive.sum(axis=1).max()), 1)
    # G[r, s, a, b] = P_rs(a, b) for compatible alive slots, -inf otherwise
    if 3 * kf >= 2 * kmax:
        # most slots alive (near the root): a block slice is far cheaper than a gather
        sl = np.broadcast_to(np.arange(kmax), (u, kmax))
        ok = alive
        G = t.pair_ex[np.ix_(U, U)]
    else:
        sl = np.argsort(~alive, axis=1, kind="stable")[:, :kf]  # (u, kf) alive slots first
        ok = np.take_along_axis(alive, sl, axis=1)
        G = t.pair_ex[U[:, None, None, None], U[None, :, None, None], sl[:, None, :, None],
                      sl[None, :, None, :]]
    if not ok.all():
        G = np.where(ok[:, None, :, None] & ok[None, :, None, :], G, -np.inf)
    compat = np.isfinite(G)
    # what an unmatched row contributes: 0 when it may stay unmatched, else it is no option
    if must is None:
        must = np.full(u, not allow_unmatched)
    floor = np.where(must, -np.inf, 0.0)
    floor3 = floor[None, :, None]
    partner = np.maximum(G.max(axis=3), floor3)  # (u, u, kf): best partner of (r, a) in row s
    partner[ar, ar] = 0.0
    Cc = np.take_along_axis(node.F[U], sl, axis=1) + 0.5 * partner.sum(axis=1)
    Cc[~ok] = -np.inf
    if not np.isfinite(Cc[must]).any(axis=1).all():
        return None
    # other[r, s, a]: best bound of row s compatible with row r at its a-th slot
    other = np.where(compat, Cc[None, :, None, :], -np.inf).max(axis=3)
    np.maximum(other, floor3, out=other)
    with_r = Cc[:, None, :] + other  # pair (r, s), r at its a-th slot
    other[ar, ar] = 0.0
    star = Cc + other.sum(axis=1)  # (u, kf)
    cmax = np.maximum(Cc.max(axis=1), floor)
    # B[r, s]: r matched (s as it may), or r unmatched when it may be and s at its best
    B = np.maximum(with_r.max(axis=2), np.where(must[:, None], -np.inf, cmax[None, :]))
    off = ~np.eye(u, dtype=bool)
    if not np.isfinite(B[off]).all():
        return None
    loss = cmax[:, None] + cmax[None, :] - B
    np.fill_diagonal(loss, -np.inf)
    mate = np.full(u, -1, dtype=np.int64)
    scale = _ABS_TOL + _REL_TOL * float(np.abs(cmax).sum())
    for _ in range(u // 2):
        k = int(np.argmax(loss))
        r, q = divmod(k, u)
        if not loss[r, q] > scale:
            break
        mate[r], mate[q] = q, r
        loss[[r, q], :] = -np.inf
        loss[:, [r, q]] = -np.inf
    single = mate < 0
    mate0 = np.maximum(mate, 0)
    pair_value = float(cmax[single].sum()) + 0.5 * float(B[~single, mate[~single]].sum())
    # child bounds: the rest of the pair bound plus the forced row's pair (or own) best, and
    # the star bound
    rest = pair_value - np.where(single, cmax, B[ar, mate0])
    own = np.where(single[:, None], Cc, with_r[ar, mate0])
    child = np.minimum(rest[:, None] + own, star)
    child[~ok] = -np.inf
    star_unm = cmax.sum() - cmax  # the others unrestricted
    child_unm = np.minimum(rest + np.where(single, 0.0, cmax[mate0]), star_unm)
    child_unm[must] = -np.inf
    value = min(pair_value, float(np.maximum(child.max(axis=1), child_unm).min()))
    C = np.full((u, kmax), -np.inf)
    est = np.full((u, kmax), -np.inf)
    C[ar[:, None], sl] = Cc
    est[ar[:, None], sl] = child
    return _Consistent(C, node.fixed + value, node.fixed + est, node.fixed + child_unm)


def _filter_by_consistency(
    t: _Tables,
    node: _Node,
    U: np.ndarray,
    alive: np.ndarray,
    allow_unmatched: bool,
    threshold: float,
    max_rounds: int = 4,
) -> tuple[_Consistent, bool] | None:
    """`_consistency_bound`, then drop the slots whose child cannot beat `threshold` and
    bound again: a dead slot no longer props up other rows' partner terms and stars, so the
    bound tightens and more slots die. Repeats while that happens (up to max_rounds).

    Returns (bounds, filtered); after filtering, the bounds hold for the completions that could
    beat the threshold only. None when the node has no feasible completion at all.
    """
    cb = _consistency_bound(t, node, U, alive, allow_unmatched)
    if cb is None:
        return None
    filtered = False
    must = np.full(len(U), not allow_unmatched)
    for _ in range(max_rounds - 1):
        if cb.value <= threshold:
            break
        dead = alive & (cb.est <= threshold)
        # a row whose unmatched child cannot beat the threshold must be matched: its
        # candidates then bound the stars and pairs of the others without the "0" option
        forced = ~must & (cb.est_unm <= threshold)
        if not dead.any() and not forced.any():
            break
        alive = alive & ~dead
        must = must | forced
        nxt = _consistency_bound(t, node, U, alive, allow_unmatched, must)
        filtered = True
        if nxt is None:  # no full completion beats the threshold
            cb.value = -math.inf
            break
        cb = nxt
    return cb, filtered


def _repair_slots(t: _Tables, slots: np.ndarray) -> np.ndarray:
    """Unmatch rows of an (n1,) slot assignment until no two matched pairs conflict.

    Greedy: keep the rows in order of their share of the objective, each only if it conflicts
    with none kept so far."""
    slots = slots.copy()
    if t.conf is None:
        return slots
    mr = np.nonzero(slots >= 0)[0]
    sl = slots[mr]
    clash = t.conf[mr[:, None], mr[None, :], sl[:, None], sl[None, :]]
    if not clash.any():
        return slots
    pair = t.pair[mr[:, None], mr[None, :], sl[:, None], sl[None, :]]
    share = t.unary[mr, sl] + 0.5 * pair.sum(axis=1)
    keep = np.zeros(len(mr), dtype=bool)
    for k in np.argsort(-share, kind="stable"):
        keep[k] = not clash[k, keep].any()
    slots[mr[~keep]] = _NO_MATCH
    return slots


def _slots_score(t: _Tables, slots: np.ndarray) -> float:
    """Score of a complete (n1,) slot assignment (_NO_MATCH allowed)."""
    mr = np.nonzero(slots >= 0)[0]
    sl = slots[mr]
    return float(t.unary[mr, sl].sum()) + 0.5 * float(
        t.pair[mr[:, None], mr[None, :], sl[:, None], sl[None, :]].sum()
    )


def _local_search(
    t: _Tables, slots: np.ndarray, allow_unmatched: bool, max_moves: int = 10_000
) -> np.ndarray:
    """Best-improvement local search from a feasible (n1,) slot assignment.

    Moves: move a row to a free candidate col, unmatch a row (when allowed), swap the cols of
    two matched rows (when both pairs are candidates). A better incumbent early prunes far more
    of the tree than it costs (QAPLIB: the LAP completions alone often miss the optimum).
    With conflicts, the start must be conflict-free and no move creates a conflict.
    """
    n1 = t.n1
    slots = slots.copy()
    if n1 == 0 or t.nc == 0:
        return slots
    scale = float(np.abs(t.pair).max(initial=0.0) + np.abs(t.unary).max(initial=0.0))
    eps = 1e-12 * max(scale, 1.0) * n1
    for _ in range(max_moves):
        mr = np.nonzero(slots >= 0)[0]
        sl = slots[mr]
        # G[i, b] = u_i(b) + sum over matched j != i of P_ij(b, s_j): row i's share if at slot b.
        G = t.unary + t.pair[:, mr, :, sl].sum(axis=0)
        cur = np.zeros(n1)
        cur[mr] = G[mr, sl]
        used = np.zeros(t.nc, dtype=bool)
        used[t.ccol[mr, sl]] = True

        ok_move = t.valid & ~used[np.maximum(t.ccol, 0)]
        n_conf = None
        if t.conf is not None:
            # n_conf[i, b]: matched rows j != i whose slot conflicts with (i, b)
            n_conf = t.conf[:, mr, :, sl].sum(axis=0)
            ok_move &= n_conf == 0
        move = np.where(ok_move, G - cur[:, None], -np.inf)
        best_gain, best_move = -np.inf, None
        if move.size:
            i, b = np.unravel_index(int(np.argmax(move)), move.shape)
            best_gain, best_move = float(move[i, b]), ("move", int(i), int(b))
        if allow_unmatched and len(mr):
            k = int(np.argmin(cur[mr]))
            if -cur[mr[k]] > best_gain:
                best_gain, best_move = float(-cur[mr[k]]), ("unmatch", int(mr[k]), _NO_MATCH)
        if len(mr) >= 2:
            cm = t.ccol[mr, sl]
            bi = t.slot_of[mr[:, None], cm[None, :]]  # row i takes j's col
            ok = (bi >= 0) & (bi.T >= 0)
            np.fill_diagonal(ok, False)
            if ok.any():
                bi0 = np.maximum(bi, 0)
                bj0 = bi0.T  # row j takes i's col
                ri, rj = mr[:, None], mr[None, :]
                if n_conf is not None:
                    # the new pairs may conflict with neither each other nor the other rows
                    # (n_conf counts j's current slot, which leaves)
                    ok &= n_conf[ri, bi0] == t.conf[ri, rj, bi0, sl[None, :]]
                    ok &= n_conf[rj, bj0] == t.conf[rj, ri, bj0, sl[:, None]]
                    ok &= ~t.conf[ri, rj, bi0, bj0]
                # New shares of i and j minus their old shares; the (i, j) pair term is counted
                # in both G's / both cur's, so correct it once on each side.
                gain = (
                    G[ri, bi0]
                    - t.pair[ri, rj, bi0, sl[None, :]]
                    + G[rj, bj0]
                    - t.pair[rj, ri, bj0, sl[:, None]]
                    + t.pair[ri, rj, bi0, bj0]
                    - (cur[ri] + cur[rj] - t.pair[ri, rj, sl[:, None], sl[None, :]])
                )
                gain = np.where(ok, gain, -np.inf)
                x, y = np.unravel_index(int(np.argmax(gain)), gain.shape)
                if gain[x, y] > best_gain:
                    best_gain = float(gain[x, y])
                    best_move = ("swap", int(x), int(y))
        if best_move is None or best_gain <= eps:
            break
        kind, i, b = best_move
        if kind == "swap":
            ri, rj = mr[i], mr[b]
            si, sj = t.slot_of[ri, cm[b]], t.slot_of[rj, cm[i]]
            slots[ri], slots[rj] = si, sj
        else:
            slots[i] = b
    return slots


def _to_cols(t: _Tables, slots: np.ndarray) -> np.ndarray:
    """(n1,) slots -> (n1,) original map node per row or UNMATCHED."""
    out = np.full(t.n1, UNMATCHED, dtype=np.int64)
    m = slots >= 0
    out[m] = t.col_of[t.ccol[np.nonzero(m)[0], slots[m]]]
    return out


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
    t: _Tables, b: _Bound, best: float, allow_unmatched: bool
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
    first; slot _NO_MATCH = leave the row unmatched). None when nothing survives.
    """
    est, ban_est, free, U = b.est, b.ban_est, b.free, b.open_rows
    assert est is not None and ban_est is not None and free is not None
    if best == -math.inf:
        # Unreachable in practice (the root LAP completion is scored before any branching),
        # but without an incumbent every feasible child survives: use a finite threshold.
        best = float(np.min(est[np.isfinite(est)], initial=b.value)) - 1.0
    u, nf = len(U), len(free)
    threshold = best + _ABS_TOL + _REL_TOL * abs(best)
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
        slots = np.full(len(q), _NO_MATCH, dtype=np.int64)
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
    P = problem.K[np.ix_(order, order)]
    P += P.T.copy()
    apart = rows[:, None] == rows[None, :]  # same row (and the diagonal)
    apart |= cols[:, None] == cols[None, :]  # same col: cannot coexist
    if problem.conflict is not None:
        apart |= problem.conflict[np.ix_(order, order)]  # conflicting: cannot coexist either
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
    With unmatched rows allowed, dominated candidates (`dominated`) are removed first: the
    optimum over what is left is the optimum over the whole candidate set.
    Conflicts (problem.conflict): an incumbent holding conflicting pairs is repaired first
    (`repair_conflicts`) when rows may stay unmatched, else ignored.
    """
    if cutoff is not None and not allow_unmatched:
        raise SolverError("a cutoff needs allow_unmatched (the empty assignment is the fallback)")
    incumbent = _repaired(problem, incumbent, allow_unmatched)
    if allow_unmatched and 0 < problem.m <= _PRESOLVE_MAX_CANDIDATES:
        gone = dominated(problem)
        if gone.any():
            if incumbent is not None and problem.is_feasible(np.asarray(incumbent)):
                # unmatching a dominated candidate never lowers the incumbent's score
                incumbent = np.asarray(incumbent).copy()
                lookup = set(zip(problem.rows[gone].tolist(), problem.cols[gone].tolist()))
                for i, a in enumerate(incumbent.tolist()):
                    if (i, a) in lookup:
                        incumbent[i] = UNMATCHED
            problem = problem.subset(~gone)
    return _solve_exact(
        problem,
        allow_unmatched=allow_unmatched,
        incumbent=incumbent,
        max_nodes=max_nodes,
        time_limit_s=time_limit_s,
        clock=clock,
        cutoff=cutoff,
        gap=gap,
    )


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
        self.tables = _Tables(problem)

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
            best_slots, best = np.full(n1, _NO_MATCH, dtype=np.int64), 0.0
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
                slots = np.full(n1, _NO_MATCH, dtype=np.int64)
                m = inc != UNMATCHED
                slots[m] = t.slot_of[np.nonzero(m)[0], np.searchsorted(t.col_of, inc[m])]
                slots = _local_search(t, slots, allow_unmatched)
                s = _slots_score(t, slots)
                if s > best:
                    best_slots, best = slots, s
            else:
                logger.debug("ignoring infeasible incumbent")
        floor = -math.inf if cutoff is None else float(cutoff)
        best = max(best, floor)  # prune against the cutoff; best_slots keeps the real solution

        nodes = 0
        # DFS stack: (node, child rows, child slots, child bounds), children sorted ascending.
        stack: list[tuple[_Node, np.ndarray, np.ndarray, np.ndarray]] = []
        stopped = False

        def expand(node: _Node) -> float:
            """Evaluate a node, update the incumbent, push it when it must be branched on."""
            nonlocal best, best_slots, nodes
            nodes += 1
            b = _bound(t, node, allow_unmatched, best + gap)
            if b is None:
                return -math.inf
            if b.primal_score > best:
                improved = _local_search(t, b.primal, allow_unmatched)
                best, best_slots = _slots_score(t, improved), improved
            if b.est is None or _prunes(b.value, best + gap):
                # No child bounds: the node was pruned, is a leaf, or has one open row (the LAP
                # is exact then, so its completion is the subtree optimum).
                return b.value
            choice = _choose_branch(t, b, best + gap, allow_unmatched)
            if choice is not None:
                stack.append((node, *choice))
            return b.value

        root_bound = expand(_root(t, allow_unmatched))
        while stack:
            node, rows_, slots_, ests = stack[-1]
            if len(slots_) == 0 or _prunes(float(ests[-1]), best + gap):
                # Children are sorted ascending by bound: if the best one is pruned, all are.
                stack.pop()
                continue
            if nodes >= max_nodes or (time_limit_s is not None and clock() - start >= time_limit_s):
                stopped = True
                break
            stack[-1] = (node, rows_[:-1], slots_[:-1], ests[:-1])
            expand(_child(t, node, int(rows_[-1]), int(slots_[-1])))

        if best_slots is None:
            # Rows must all match and no completion was conflict-free (or, without conflicts,
            # the root LAP itself failed although a full matching exists).
            raise SolverError("exact solver found no feasible assignment")
        score = _slots_score(t, best_slots)
        # what pruning proved: nothing pruned beats max(score + gap, cutoff); the root bound
        # holds for everything
        pruned = min(max(score + gap, floor), root_bound)
        if stopped:
            open_max = max((float(e[-1]) for *_, e in stack if len(e)), default=-math.inf)
            upper = max(score, pruned, min(open_max, root_bound))
            logger.debug("exact search stopped after %d nodes, gap %.6g", nodes, upper - score)
        else:
            upper = max(score, pruned)
        return ExactResult(_to_cols(t, best_slots), score, not stopped, nodes, float(upper))


def brute_force(
    problem: AssignmentProblem, allow_unmatched: bool = True
) -> tuple[np.ndarray, float]:
    """Enumerate every feasible assignment (tiny problems only).

    Returns ((n1,) map node per row or UNMATCHED, score). Raises SolverError when the product of
    per-row option counts exceeds BRUTE_FORCE_LIMIT, or when allow_unmatched=False and no full
    assignment exists.
    """
    n1 = problem.n1
    K = np.asarray(problem.K, dtype=np.float64)
    options: list[list[tuple[int, int]]] = [[] for _ in range(n1)]
    for p, (r, c) in enumerate(zip(problem.rows.tolist(), problem.cols.tolist(), strict=True)):
        options[r].append((c, p))
    if allow_unmatched:
        for opt in options:
            opt.append((UNMATCHED, -1))
    total = math.prod(len(o) for o in options)
    if total > BRUTE_FORCE_LIMIT:
        raise SolverError(f"brute force over {total} combinations exceeds {BRUTE_FORCE_LIMIT}")
    sym = (K + K.T).tolist()
    diag = np.diag(K).tolist()
    clash: list[set[int]] = [set() for _ in range(problem.m)]
    if problem.conflict is not None:
        for p, q in zip(*np.nonzero(problem.conflict), strict=True):
            clash[int(p)].add(int(q))

    best_score = -math.inf
    best: list[int] | None = None
    chosen_p: list[int] = []
    chosen_c: list[int] = [UNMATCHED] * n1
    used: set[int] = set()

    # Depth-first enumeration with an incremental score: K[p,p] plus (K[p,q] + K[q,p]) against
    # everything chosen so far; far cheaper than re-summing a submatrix per leaf.
    def rec(i: int, score: float) -> None:
        nonlocal best_score, best
        if i == n1:
            if score > best_score:
                best_score, best = score, list(chosen_c)
            return
        for c, p in options[i]:
            if p < 0:
                chosen_c[i] = UNMATCHED
                rec(i + 1, score)
                continue
            if c in used or any(q in clash[p] for q in chosen_p):
                continue
            row = sym[p]
            delta = diag[p] + sum(row[q] for q in chosen_p)
            used.add(c)
            chosen_p.append(p)
            chosen_c[i] = c
            rec(i + 1, score + delta)
            chosen_p.pop()
            used.discard(c)
        chosen_c[i] = UNMATCHED

    rec(0, 0.0)
    if best is None:
        raise SolverError("no feasible full assignment")
    assignment = np.asarray(best, dtype=np.int64)
    return assignment, problem.score(assignment)


def astar_crosscheck(problem: AssignmentProblem) -> np.ndarray:
    """Solve a dense problem with pygmtools' exact A* (pytorch backend) as an independent oracle.

    Returns (n1,) map node per row (UNMATCHED where A* left a row unmatched). Raises SolverError
    when torch is missing or the problem is not dense (all n1*n2 pairs are candidates).
    """
    try:
        import torch
    except ImportError as exc:
        raise SolverError("pygmtools A* needs torch; install torch to use the cross-check") from exc
    import pygmtools

    n1, n2 = problem.n1, problem.n2
    if problem.m != n1 * n2:
        raise SolverError("pygmtools A* cross-check needs a dense problem (all n1*n2 pairs)")
    # pygmtools indexes the affinity matrix column-major: pair (i, a) -> a * n1 + i.
    pg = np.asarray(problem.cols) * n1 + np.asarray(problem.rows)
    Kpg = np.zeros((n1 * n2, n1 * n2))
    Kpg[np.ix_(pg, pg)] = problem.K
    X = pygmtools.astar(
        torch.from_numpy(Kpg)[None],
        n1=torch.tensor([n1]),
        n2=torch.tensor([n2]),
        backend="pytorch",
    )
    X = np.asarray(X[0].detach().cpu().numpy())
    return np.where(X.max(axis=1) > 0.5, X.argmax(axis=1), UNMATCHED).astype(np.int64)


__all__ = ["ExactResult", "astar_crosscheck", "brute_force", "solve_exact"]
