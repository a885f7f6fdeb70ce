"""A factor of the pose graph as the graph (core/graph.py) and its policies (core/folding.py,
core/freezing.py) hold it, and the Levenberg-Marquardt solve they share (its covariance is
checked by core/poses.py's check_covariance). GTSAM's failures come out as SolverError. Pure.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import gtsam
import numpy as np

from mergesvc.errors import SolverError


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


__all__ = ["GraphFactor", "levenberg_marquardt"]
