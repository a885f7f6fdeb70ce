"""Upper bounds of the exact branch and bound (exact.py), for one search node.

`bound` is the Gilmore-Lawler-style bound: an outer LAP over per-entry bounds (cheap partner
terms, then the injectivity-aware inner LAPs), with child bounds from the LAP duals and the LAP
solution as a feasible completion. With conflicts, the consistency bounds (row pairs and stars,
filtered against the incumbent) take over.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from mergesvc.core.solvers.bnb_state import (
    ABS_TOL,
    NO_MATCH,
    REL_TOL,
    UNASSIGNED,
    Node,
    Tables,
    prunes,
)
from mergesvc.core.solvers.primal import repair_slots, slots_score


@dataclass
class Bound:
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
    t: Tables, node: Node, U: np.ndarray, C: np.ndarray, allow_unmatched: bool
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
    primal[rows_u[~is_real]] = NO_MATCH
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
            primal = repair_slots(t, primal)
            primal_score = slots_score(t, primal)
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
    t: Tables,
    node: Node,
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


def bound(t: Tables, node: Node, allow_unmatched: bool, best: float) -> Bound | None:
    """Gilmore-Lawler-style bound plus the LAP solution as a feasible completion.

    The score of a completion is fixed + sum_i F[i, a_i] + 1/2 sum_{i != j open} P_ij(a_i, a_j);
    each open row i bounds its share by C[i, a] = F[i, a] + 1/2 (partner term), and an outer LAP
    over C respects injectivity. Stage 1 uses a cheap partner term (each j picks its best b
    independently); if that does not prune against `best`, stage 2 uses the exact inner LAPs.
    Both are valid for any sign of K. With conflicts, `_bound_consistent` takes over after
    the entry bounds. Returns None when the node has no feasible completion.
    """
    U = np.nonzero(node.assign == UNASSIGNED)[0]
    u = len(U)
    if u == 0:
        return Bound(node.fixed, node.assign.copy(), node.fixed, U)
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
    if u <= 1 or prunes(lap.value, best_now):
        return Bound(lap.value, lap.primal, lap.primal_score, U)

    # Stage 2, only for entries whose child survives stage 1: an entry whose child is already
    # pruned keeps its (larger, still valid) stage-1 value; it can only matter to the outer LAP
    # through completions using it, which are all bounded below the incumbent anyway. The
    # entrywise min of two valid entry bounds is a valid entry bound.
    nf = len(lap.free)
    pos = np.full(t.nc, -1, dtype=np.int64)
    pos[lap.free] = np.arange(nf)
    r_idx, a_idx = np.nonzero(feas)
    need = np.zeros_like(feas)
    threshold = best_now + ABS_TOL + REL_TOL * abs(best_now)
    need[r_idx, a_idx] = lap.est[r_idx, pos[t.ccol[U[r_idx], a_idx]]] > threshold
    strong = _strong_partner(t, node, U, feas, need, allow_unmatched)
    C = np.minimum(C, node.F[U] + 0.5 * strong)
    lap2 = _outer_lap(t, node, U, C, allow_unmatched)
    if lap2 is None:
        return None
    primal, primal_score = lap.primal, lap.primal_score
    if lap2.primal_score > primal_score:
        primal, primal_score = lap2.primal, lap2.primal_score
    return Bound(
        min(lap.value, lap2.value),
        primal,
        primal_score,
        U,
        lap.free,
        np.minimum(lap.est, lap2.est),
        np.minimum(lap.ban_est, lap2.ban_est),
    )


def _bound_consistent(
    t: Tables, node: Node, U: np.ndarray, allow_unmatched: bool, best: float
) -> Bound | None:
    """`bound` for problems with conflicts and at least two open rows (instead of stages 1
    and 2).

    The consistency bounds (`_filter_by_consistency`, entry bounds C included) come first; an
    outer LAP over the entries they leave adds injectivity and the primal completion, and its
    duals bound the children along with the stars and pairs. (The inner LAPs of stage 2 are
    skipped: measured on crowded drive maps, they pruned nothing the consistency bounds had
    not, at a third of the node cost.)
    """
    threshold = best + ABS_TOL + REL_TOL * abs(best)
    res = _filter_by_consistency(t, node, U, node.feas[U], allow_unmatched, threshold)
    if res is None:
        return None
    cb, filtered = res
    # After filtering the bounds hold only for completions that could beat the threshold:
    # report them no lower than it (which is what pruning proves anyway).
    floor = best if filtered else -math.inf
    if prunes(cb.value, best):
        return Bound(max(cb.value, floor), node.assign.copy(), -math.inf, U)
    lap = _outer_lap(t, node, U, cb.C, allow_unmatched)
    if lap is None:  # rows must match: infeasible, or nothing left beats the threshold
        return None if floor == -math.inf else Bound(floor, node.assign.copy(), -math.inf, U)
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
    if prunes(lap.value, max(best, lap.primal_score)):
        return Bound(lap.value, lap.primal, lap.primal_score, U)
    return Bound(lap.value, lap.primal, lap.primal_score, U, lap.free, lap.est, lap.ban_est)


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
    t: Tables,
    node: Node,
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
    scale = ABS_TOL + REL_TOL * float(np.abs(cmax).sum())
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
    t: Tables,
    node: Node,
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
