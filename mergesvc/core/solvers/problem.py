"""The assignment problem every solver works on: a Lawler QAP restricted to candidate pairs.

maximise  score(S) = sum_{p in S} sum_{q in S} K[p, q]
over sets S of candidate assignments p = (rows[p], cols[p]) that use each submap node (row) at
most once (exactly once when unmatched rows are not allowed) and each map node (col) at most once,
and, when a conflict matrix is given, never hold two conflicting candidates (pairwise geometric
consistency, the consistency graph of CLIPPER / PCM: two pairs whose distances disagree cannot
both hold in a rigid configuration).
Diagonal of K: node affinity of the pair; off-diagonal: edge affinity of the two pairs.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from mergesvc.errors import SolverError

UNMATCHED = -1
# rows x cols up to which a problem keeps an (n1, n2) table of candidate indices
_CELL_TABLE_MAX = 1 << 16
_UNMATCHED_CELL = -2  # the cell table's entry for an unmatched row


def block(X: np.ndarray, rows: np.ndarray, cols: np.ndarray | None = None) -> np.ndarray:
    """X[np.ix_(rows, cols)] for integer index arrays (cols defaults to rows), in two takes:
    the same array at a third of ix_'s cost on the small blocks the solvers read."""
    return X.take(rows, axis=0).take(rows if cols is None else cols, axis=1)


@dataclass(frozen=True)
class AssignmentProblem:
    """Candidate-restricted Lawler QAP.

    rows: (m,) int, submap node index of each candidate assignment, in [0, n1)
    cols: (m,) int, map node index of each candidate assignment, in [0, n2)
    K: (m, m) float64, symmetric affinity between candidate assignments
    conflict: optional (m, m) bool, symmetric, False on the diagonal: conflict[p, q] means p
        and q cannot both be in a feasible assignment (a hard constraint; `score` ignores it)
    """

    n1: int
    n2: int
    rows: np.ndarray
    cols: np.ndarray
    K: np.ndarray
    conflict: np.ndarray | None = None
    # K is 0 wherever two candidates share a row or a col (the solvers need not mask it)
    invalid_zero: bool = False

    @classmethod
    def trusted(cls, n1: int, n2: int, rows: np.ndarray, cols: np.ndarray, K: np.ndarray,
                conflict: np.ndarray | None = None, invalid_zero: bool = False
                ) -> AssignmentProblem:
        """A problem whose builder guarantees the invariants `__post_init__` checks (ranges,
        no duplicate pair, finite symmetric K, a symmetric conflict matrix False on its
        diagonal): affinity.candidate_K, whose O(m^2) checks would cost as much as K."""
        out = object.__new__(cls)
        for name, value in (("n1", n1), ("n2", n2), ("rows", rows), ("cols", cols), ("K", K),
                            ("conflict", conflict), ("invalid_zero", invalid_zero)):
            object.__setattr__(out, name, value)
        return out

    def __post_init__(self) -> None:
        m = len(self.rows)
        if self.rows.shape != (m,) or self.cols.shape != (m,):
            raise SolverError("rows and cols must be 1-d arrays of equal length")
        if self.K.shape != (m, m):
            raise SolverError(f"K must be ({m}, {m}), got {self.K.shape}")
        if m and (self.rows.min() < 0 or self.rows.max() >= self.n1):
            raise SolverError("rows out of range [0, n1)")
        if m and (self.cols.min() < 0 or self.cols.max() >= self.n2):
            raise SolverError("cols out of range [0, n2)")
        if not np.all(np.isfinite(self.K)):
            raise SolverError("K has non-finite entries")
        pairs = self.rows.astype(np.int64) * max(self.n2, 1) + self.cols
        if len(np.unique(pairs)) != m:
            raise SolverError("duplicate candidate assignments")
        if self.conflict is not None:
            C = self.conflict
            if not isinstance(C, np.ndarray) or C.dtype != np.bool_:
                raise SolverError("conflict must be a bool numpy array")
            if C.shape != (m, m):
                raise SolverError(f"conflict must be ({m}, {m}), got {C.shape}")
            if not np.array_equal(C, C.T):
                raise SolverError("conflict must be symmetric")
            if C.diagonal().any():
                raise SolverError("conflict must be False on the diagonal")

    @property
    def m(self) -> int:
        return len(self.rows)

    @classmethod
    def dense(cls, K: np.ndarray, n1: int, n2: int) -> AssignmentProblem:
        """All n1*n2 pairs; K indexed row-major, p = i * n2 + a."""
        rows, cols = np.divmod(np.arange(n1 * n2), n2)
        return cls(n1, n2, rows, cols, np.asarray(K, dtype=np.float64))

    def subset(self, keep: np.ndarray) -> AssignmentProblem:
        """The problem over the candidates where `keep` (m,) bool is true; same rows and cols."""
        idx = np.flatnonzero(keep)
        conflict = None if self.conflict is None else block(self.conflict, idx)
        # a subset of a valid problem is valid: no O(m^2) checks again
        return AssignmentProblem.trusted(
            self.n1, self.n2, self.rows[idx], self.cols[idx], block(self.K, idx), conflict,
            self.invalid_zero,
        )

    def conflicts_of(self, assignment: np.ndarray) -> np.ndarray:
        """(n1,) number of other matched rows each matched row conflicts with (0 if unmatched).

        Raises SolverError when a chosen pair is not a candidate."""
        a = np.asarray(assignment)
        out = np.zeros(self.n1, dtype=np.int64)
        idx = self.assignment_to_indices(a)  # raises on a non-candidate, conflicts or not
        if self.conflict is None:
            return out
        out[(a != UNMATCHED).nonzero()[0]] = block(self.conflict, idx).sum(axis=1)
        return out

    def assignment_to_indices(self, assignment: np.ndarray) -> np.ndarray:
        """(n1,) map node per row (UNMATCHED = -1) -> indices of the chosen candidates.

        Raises SolverError when a chosen pair is not a candidate.
        """
        a = np.asarray(assignment)
        table = self._cell_index
        if table is not None and a.shape == (self.n1,) and a.dtype.kind == "i" and (
                self.n1 == 0 or int(a.min()) >= UNMATCHED):
            try:  # one gather: UNMATCHED (-1) reads the table's first column
                idx = table[self._row_range, a + 1]
            except IndexError:  # a column n2 or beyond: the general path says which
                pass
            else:
                idx = idx[idx != _UNMATCHED_CELL]
                if len(idx) == 0 or int(idx.min()) >= 0:
                    return idx
        rows = (a != UNMATCHED).nonzero()[0]
        if len(rows) == 0:
            return np.zeros(0, dtype=np.int64)
        cols = a[rows].astype(np.int64)
        if int(cols.min()) < 0 or int(cols.max()) >= self.n2:  # (keys would alias)
            k = int(np.flatnonzero((cols < 0) | (cols >= self.n2))[0])
            raise SolverError(f"pair ({int(rows[k])}, {int(cols[k])}) is not a candidate")
        keys = rows * max(self.n2, 1) + cols
        sorted_keys, order = self._key_index
        at = np.minimum(np.searchsorted(sorted_keys, keys), max(len(sorted_keys) - 1, 0))
        hit = (sorted_keys[at] == keys) if len(sorted_keys) else np.zeros(len(keys), bool)
        if not hit.all():
            k = int(np.flatnonzero(~hit)[0])
            raise SolverError(f"pair ({int(rows[k])}, {int(a[rows[k]])}) is not a candidate")
        return order[at].astype(np.int64)

    @functools.cached_property
    def _cell_index(self) -> np.ndarray | None:
        """(n1, n2 + 1) candidate index of each (row, col) at column col + 1, -1 where none,
        and a first column of _UNMATCHED_CELL (what an UNMATCHED row reads); None when that
        table would be large (the sorted keys serve then)."""
        if self.n1 * self.n2 > _CELL_TABLE_MAX:
            return None
        table = np.full((self.n1, self.n2 + 1), -1, dtype=np.int64)
        table[:, 0] = _UNMATCHED_CELL
        table[self.rows, self.cols + 1] = np.arange(self.m)
        return table

    @functools.cached_property
    def _row_range(self) -> np.ndarray:
        return np.arange(self.n1)

    @functools.cached_property
    def _key_index(self) -> tuple[np.ndarray, np.ndarray]:
        """Sorted keys row * n2 + col of the candidates, and the candidate index of each."""
        keys = self.rows.astype(np.int64) * max(self.n2, 1) + self.cols
        order = np.argsort(keys, kind="stable")
        return keys[order], order

    def score(self, assignment: np.ndarray) -> float:
        """Objective of a hard assignment given as (n1,) map node per row or UNMATCHED."""
        idx = self.assignment_to_indices(assignment)
        return float(block(self.K, idx).sum())

    def is_feasible(self, assignment: np.ndarray, allow_unmatched: bool = True) -> bool:
        a = np.asarray(assignment)
        if a.shape != (self.n1,):
            return False
        used = a[a != UNMATCHED]
        if len(np.unique(used)) != len(used):
            return False
        if not allow_unmatched and len(used) != self.n1:
            return False
        try:
            return not self.conflicts_of(a).any()
        except SolverError:  # a chosen pair is not a candidate
            return False
