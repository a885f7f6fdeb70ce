"""Every assignment scoring above a threshold, for tiny problems: the optimum and the margins
of its matches from one breadth-first search.

The rows are decided one at a time (fewest candidates first), every partial assignment at
once as numpy arrays: each is extended by each compatible candidate of the next row and by
"unmatched", and kept only while an upper bound on its completions beats the threshold
(its score, plus for each open row its best compatible candidate's gain against the decided
rows and half its best partner in each other open row, each at least 0). The bound is valid
for any sign of K, so what survives the last row is exactly the set of feasible assignments
scoring above the threshold. The search gives up (None) once more than `max_states` partial
assignments survive a row: then the branch and bound (exact.py) is the tool.
`NearOptimal.extend` carries a set over to added candidates when a bound proves that none of
them comes within the margin of the optimum.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mergesvc.core.solvers.bnb_state import ABS_TOL, REL_TOL
from mergesvc.core.solvers.exact import ExactResult
from mergesvc.core.solvers.problem import UNMATCHED, AssignmentProblem, block


@dataclass(frozen=True)
class NearOptimal:
    """The feasible assignments of `problem` scoring above `threshold`.

    score: (s,) their objective; chosen: (s, n1) candidate index per row, -1 = unmatched."""

    problem: AssignmentProblem
    threshold: float
    score: np.ndarray
    chosen: np.ndarray

    def best(self, states: int = 0) -> ExactResult | None:
        """The optimum as an ExactResult (None when nothing scored above the threshold)."""
        if len(self.score) == 0:
            return None
        k = int(self.score.argmax())
        pick = self.chosen[k]
        assignment = np.full(self.problem.n1, UNMATCHED, dtype=np.int64)
        assignment[pick >= 0] = self.problem.cols[pick[pick >= 0]]
        score = self.problem.score(assignment)
        return ExactResult(assignment.astype(np.int64), score, True, max(states, 1), score)

    def margins(self, assignment: np.ndarray, margin_needed: float,
                same: np.ndarray | None = None) -> np.ndarray:
        """`margin.row_margins` from the set: (n1,) margin of each matched row of
        `assignment` (an optimum; map node per row) over its best alternative (another
        candidate of the row, not one `same` (m,) marks); inf without any alternative, nan if
        unmatched; margin_needed when every alternative falls below the threshold (a proven
        lower bound if the threshold is at most the optimum less margin_needed)."""
        p = self.problem
        out = np.full(p.n1, np.nan)
        matched = np.flatnonzero(assignment != UNMATCHED)
        idx = p.assignment_to_indices(assignment)
        top = int(np.argmax(self.score)) if len(self.score) else -1
        pick = np.full(p.n1, -1, dtype=np.int64)
        pick[matched] = idx
        best = float(self.score[top]) if top >= 0 and np.array_equal(self.chosen[top], pick) \
            else p.score(assignment)
        ch = self.chosen
        for i, c in zip(matched.tolist(), idx.tolist(), strict=True):
            other = (p.rows == i) & (np.arange(p.m) != c)
            if same is not None:
                other &= ~same
            if not other.any():
                out[i] = np.inf
                continue
            alt = other[np.maximum(ch[:, i], 0)] & (ch[:, i] >= 0)
            out[i] = best - float(self.score[alt].max()) if alt.any() else margin_needed
        return out

    def extend(self, problem: AssignmentProblem, margin: float) -> NearOptimal | None:
        """This set as the set over `problem`, whose first self.problem.m candidates are this
        problem's (the same K and conflicts among them) and the rest new, when an upper bound
        proves that no feasible assignment holding a new candidate scores within `margin` of
        the optimum: then the optimum's score and every margin test (up to `margin`) read the
        same from either set; the set's threshold rises to that floor if it was below. None
        when the bound does not prove it (search `problem` again)."""
        m0, m = self.problem.m, problem.m
        if len(self.score) == 0:
            return None
        K = problem.K if problem.invalid_zero else 0.5 * (problem.K + problem.K.T)
        rows = problem.rows
        compat = _compatible(rows, problem.cols, problem.conflict)
        # best_in[d, l]: d's best compatible partner in row l (>= 0: l may stay unmatched)
        o = np.argsort(rows, kind="stable")
        present, starts = np.unique(rows[o], return_index=True)
        best_in = np.zeros((m, problem.n1))
        best_in[:, present] = _best_per_row(K, compat, starts, o)
        # an assignment holding new candidate c scores at most K_cc plus, for each other row,
        # its best compatible e's K_ee + 2 K_ce + e's best partners in the rows but c's; when
        # that does not prove it, the same with one more row decided (each of its candidates
        # compatible with c, or none): the row that bound credits most
        best = float(self.score.max())
        floor = best - max(margin, 1e-9) - (ABS_TOL + REL_TOL * abs(best))
        diag, total = K.diagonal(), best_in.sum(axis=1)
        for c in range(m0, m):
            gain = diag + 2.0 * K[c] + total - best_in[:, rows[c]]
            per_row = _best_per_row(gain[None, :], compat[c][None, :], starts, o)[0]
            if diag[c] + per_row.sum() < floor:
                continue
            others = present != rows[c]
            if not others.any():  # c's row is the only one: K_cc alone reached the floor
                return None
            j = int(present[others][np.argmax(per_row[others])])
            in_j = rows == j
            options = np.flatnonzero(in_j & compat[c])
            gain -= best_in[:, j]  # row j is decided now
            ok = compat[c] & ~in_j
            ok = np.vstack([ok, compat[options] & ok])  # none, then each option
            V = gain[None, :] + np.vstack([np.zeros(m), 2.0 * K[options]])
            bound = _best_per_row(V, ok, starts, o).sum(axis=1) + diag[c]
            bound[1:] += diag[options] + 2.0 * K[c, options]
            if bound.max() >= floor:
                return None
        # every assignment above the floor is in the set, and only those: its threshold
        keep = self.score > floor
        return NearOptimal(problem, max(self.threshold, floor), self.score[keep],
                           self.chosen[keep])


def _compatible(rows: np.ndarray, cols: np.ndarray, conflict: np.ndarray | None) -> np.ndarray:
    """(m, m) bool: which two candidates one feasible assignment can hold together."""
    compat = rows[:, None] != rows[None, :]
    compat &= cols[:, None] != cols[None, :]
    if conflict is not None:
        compat &= ~conflict
    return compat


def _best_per_row(V: np.ndarray, ok: np.ndarray, starts: np.ndarray,
                  order: np.ndarray | None = None) -> np.ndarray:
    """(k, rows): per row of the candidates (grouped by row, or by `order`; starts: each row's
    first position) the largest V where ok, at least 0 (a row may stay unmatched). V, ok:
    (k, m)."""
    picked = np.where(ok, V, -np.inf)
    best = np.maximum.reduceat(picked if order is None else picked[:, order], starts, axis=1)
    return np.maximum(best, 0.0, out=best)


def near_optimal(problem: AssignmentProblem, threshold: float, max_states: int = 2048
                 ) -> tuple[NearOptimal, int] | None:
    """The feasible assignments (rows may stay unmatched) scoring above threshold, and the
    most partial assignments any row kept; None when more than max_states survived a row."""
    m, n1 = problem.m, problem.n1
    rows, cols = problem.rows, problem.cols
    counts = np.bincount(rows, minlength=n1)
    # decide the rows with fewest candidates first; candidates regrouped in that order
    order = np.argsort(counts, kind="stable")
    order = order[counts[order] > 0]
    rank = np.empty(n1, dtype=np.int64)
    rank[order] = np.arange(len(order))
    o = np.argsort(rank[rows], kind="stable")
    same_order = bool((o[1:] > o[:-1]).all())
    K = problem.K if same_order else block(problem.K, o)
    if not problem.invalid_zero:
        K = 0.5 * (K + K.T)
    r, c = (rows, cols) if same_order else (rows[o], cols[o])
    conflict = problem.conflict
    compat = _compatible(r, c, conflict if same_order or conflict is None else block(conflict, o))
    starts = np.searchsorted(rank[r], np.arange(len(order)))
    # best partner of each candidate in each row (>= 0: the row may stay unmatched), and its
    # suffix sums in the decision order: half_from[:, k] = sum over rows k.. of that
    half_from = np.zeros((m, len(order) + 1))
    if m:
        best_in = _best_per_row(K, compat, starts)
        half_from[:, :-1] = np.cumsum(best_in[:, ::-1], axis=1)[:, ::-1]
    two_K = 2.0 * K
    tol = ABS_TOL + REL_TOL * abs(threshold)
    score = np.zeros(1)
    gain = K.diagonal()[None, :].copy()  # gain of adding each candidate to each state
    ok = np.ones((1, m), dtype=bool)
    trail = []  # per row: (parent state, candidate or -1) of each state kept
    most = 1
    for k in range(len(order)):
        lo, hi = starts[k], starts[k + 1] if k + 1 < len(order) else m
        si, ci = np.nonzero(ok[:, lo:hi])
        q = lo + ci
        s = len(score)
        parent = np.concatenate([np.arange(s), si])
        took = np.concatenate([np.full(s, -1), q])
        score = np.concatenate([score, score[si] + gain[si, q]])
        gain = np.concatenate([gain, gain[si] + two_K[q]])
        ok = np.concatenate([ok, ok[si] & compat[q]])
        # bound of each state's completions over the open rows k + 1 ..
        bound = score
        if hi < m:
            v = np.where(ok[:, hi:], gain[:, hi:] + half_from[hi:, k + 1], -np.inf)
            top = np.maximum.reduceat(v, starts[k + 1:] - hi, axis=1)
            bound = score + np.maximum(top, 0.0).sum(axis=1)
        live = bound > threshold - tol  # rounding keeps a borderline state, never drops it
        if not live.all():
            score, gain, ok = score[live], gain[live], ok[live]
            parent, took = parent[live], took[live]
        trail.append((parent, took))
        most = max(most, len(score))
        if len(score) > max_states:
            return None
    keep = np.flatnonzero(score > threshold)
    chosen = np.full((len(keep), n1), -1, dtype=np.int64)
    state = keep
    for k in range(len(order) - 1, -1, -1):
        parent, took = trail[k]
        t = took[state]
        chosen[:, order[k]] = np.where(t >= 0, o[np.maximum(t, 0)], -1)
        state = parent[state]
    return NearOptimal(problem, threshold, score[keep], chosen), most


__all__ = ["NearOptimal", "near_optimal"]
