"""A factor of the pose graph as the graph (core/graph.py) and its policies (core/folding.py,
core/freezing.py) hold it, the check of a covariance given with one, and the Levenberg-Marquardt
solve they share. GTSAM's failures come out as SolverError, bad input as InputError. Pure.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np

from mergesvc.errors import InputError, SolverError

# Symmetry tolerance of covariance inputs, relative to the largest entry.
_SYM_RTOL = 1e-9


@dataclass(frozen=True, slots=True)
class GraphFactor:
    """T_a_b (p_a = T_a_b p_b) between two nodes, with its (6, 6) covariance (GTSAM order)."""

    factor_id: str
    frame_a: str
    frame_b: str
    T_a_b: gtsam.Pose3 | None  # None once sealed (rule 6): never solved again
    covariance_66: np.ndarray | None
    known_inlier: bool
    group: str | None = None  # its noise group (calibration), None: not calibrated

    def sealed(self) -> GraphFactor:
        """The same factor without its measurement (its ends are enough once it is sealed)."""
        return dataclasses.replace(self, T_a_b=None, covariance_66=None)


def check_covariance(C: Any, name: str) -> np.ndarray:
    """A valid covariance as a read-only float64 array: `C` itself when it is one already
    (read-only, owning its data, exactly symmetric: a long mission's graph shares its
    odometry's arrays; whoever made it must not make it writable again), else a symmetrised
    copy."""
    S = np.asarray(C, dtype=np.float64)
    if S.shape != (6, 6) or not np.all(np.isfinite(S)):
        raise InputError(f"{name} must be a finite (6, 6) matrix")
    if np.abs(S - S.T).max() > _SYM_RTOL * max(np.abs(S).max(), 1e-300):
        raise InputError(f"{name} must be symmetric")
    # shared only when nobody can write to it: read-only, owning its data, exactly symmetric
    shared = (S is C and not S.flags.writeable and S.base is None
              and np.array_equal(S, S.T))
    if not shared:
        S = 0.5 * (S + S.T)
    try:
        np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        raise InputError(f"{name} must be positive definite") from None
    S.setflags(write=False)
    return S


def levenberg_marquardt(graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values,
                        what: str) -> gtsam.Values:
    """GTSAM's Levenberg-Marquardt from `initial` with default parameters; SolverError (naming
    `what`) when it fails."""
    try:
        return gtsam.LevenbergMarquardtOptimizer(
            graph, initial, gtsam.LevenbergMarquardtParams()
        ).optimize()
    except RuntimeError as exc:
        raise SolverError(f"{what} optimisation failed: {exc}") from exc


__all__ = ["GraphFactor", "check_covariance", "levenberg_marquardt"]
