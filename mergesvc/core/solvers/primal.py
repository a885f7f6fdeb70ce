"""Primal heuristics of the exact branch and bound (exact.py), on slot assignments.

Conflict repair, exact scoring, best-improvement local search, and the conversion of slots back
to map nodes.
"""

from __future__ import annotations

import numpy as np

from mergesvc.core.solvers.bnb_state import NO_MATCH, Tables
from mergesvc.core.solvers.problem import UNMATCHED


def repair_slots(t: Tables, slots: np.ndarray) -> np.ndarray:
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
    slots[mr[~keep]] = NO_MATCH
    return slots


def slots_score(t: Tables, slots: np.ndarray) -> float:
    """Score of a complete (n1,) slot assignment (NO_MATCH allowed)."""
    mr = np.nonzero(slots >= 0)[0]
    sl = slots[mr]
    return float(t.unary[mr, sl].sum()) + 0.5 * float(
        t.pair[mr[:, None], mr[None, :], sl[:, None], sl[None, :]].sum()
    )


def local_search(
    t: Tables, slots: np.ndarray, allow_unmatched: bool, max_moves: int = 10_000
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
                best_gain, best_move = float(-cur[mr[k]]), ("unmatch", int(mr[k]), NO_MATCH)
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


def to_cols(t: Tables, slots: np.ndarray) -> np.ndarray:
    """(n1,) slots -> (n1,) original map node per row or UNMATCHED."""
    out = np.full(t.n1, UNMATCHED, dtype=np.int64)
    m = slots >= 0
    out[m] = t.col_of[t.ccol[np.nonzero(m)[0], slots[m]]]
    return out
