"""Search state of the exact branch and bound (exact.py): per-problem tables and search nodes.

Slot codes and pruning tolerances, the per-problem precomputation (`Tables`, indexed by row and
candidate slot), the search node (`Node`) and how the root and a child node are built (with
propagation of the taken col and of conflicts, and the incremental "best partner" tables).
"""

from __future__ import annotations

import math

import numpy as np

from mergesvc.core.solvers.problem import AssignmentProblem
from mergesvc.errors import SolverError

# Slot codes in the internal per-row state (slots index a row's candidate list).
UNASSIGNED = -2
NO_MATCH = -1

# Pruning tolerance: absolute plus relative, so large-magnitude integer objectives (QAPLIB costs
# up to ~1e8) are not kept alive by float rounding in sums of hundreds of terms.
ABS_TOL = 1e-9
REL_TOL = 1e-10

# The dense per-row-pair block tensor has n1^2 * kmax^2 entries (two float64 copies); refuse
# problems where that gets large, an exact search on them would not finish anyway.
_MAX_BLOCK_ENTRIES = 4_000_000


class TooLargeError(SolverError):
    """The problem's tables would exceed `_MAX_BLOCK_ENTRIES`: no exact search on it."""


def prunes(bound: float, best: float) -> bool:
    """True when a subtree with upper bound `bound` cannot beat the incumbent value `best`."""
    if best == -math.inf:
        return False
    return bound <= best + ABS_TOL + REL_TOL * abs(best)


class Tables:
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
            raise TooLargeError(
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
        if problem.conflict is not None and len(rows):
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


class Node:
    """State of one search node; arrays are shared copy-on-write between parent and children.

    assign: (n1,) int slot per row, NO_MATCH or UNASSIGNED
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


def root(t: Tables, allow_unmatched: bool) -> Node:
    assign = np.full(t.n1, UNASSIGNED, dtype=np.int64)
    if allow_unmatched:
        # Rows without candidates can only stay unmatched: fix them instead of branching.
        assign[t.counts == 0] = NO_MATCH
    used = np.zeros(t.nc, dtype=bool)
    feas = t.valid.copy()
    arg = np.argmax(t.pair_ex, axis=3)
    best = np.take_along_axis(t.pair_ex, arg[..., None], axis=3)[..., 0]
    best_col = np.where(np.isfinite(best), t.ccol[np.arange(t.n1)[None, :, None], arg], -1)
    return Node(assign, used, feas, 0.0, t.unary.copy(), best, best_col)


def child(t: Tables, node: Node, i: int, a: int) -> Node:
    """Child node: row i set to slot a (or NO_MATCH)."""
    assign = node.assign.copy()
    assign[i] = a
    if a == NO_MATCH:
        # Unmatched contributes nothing and takes no col: everything else is shared.
        return Node(assign, node.used, node.feas, node.fixed, node.F, node.best, node.best_col)
    c = int(t.ccol[i, a])
    fixed = node.fixed + float(node.F[i, a])
    F = node.F + t.pair[:, i, :, a]
    used = node.used.copy()
    used[c] = True
    feas = node.feas & (t.ccol != c)
    best, best_col = node.best, node.best_col
    if t.conf is not None:
        # Propagate the conflicts of (i, a). The best-partner tables are not maintained: with
        # conflicts the bound recomputes partners over what is left (bounds.py,
        # `_consistency_bound`).
        feas &= ~t.conf[i, :, a, :]
        return Node(assign, used, feas, fixed, F, best, best_col)
    # Only "best partner" entries whose maximiser sits on col c change; recompute those, and only
    # for pairs of still-unassigned rows with a still-feasible slot (others are never read).
    open_rows = assign == UNASSIGNED
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
    return Node(assign, used, feas, fixed, F, best, best_col)
