"""One pose-graph optimisation as plain arrays (a `SolveJob`): priors and between factors (keys,
4x4 poses, 6x6 covariances), the initial poses, and Levenberg-Marquardt or GNC (TLS loss) to
run. `run_job` builds the GTSAM graph from the arrays and optimises it; the arrays pickle in
microseconds, so the job can run in another process (GTSAM holds the GIL through an optimise,
and a thread of the caller's process could not run meanwhile). The same arrays give the same
graph and the same answer in any process. GTSAM's failures come out as SolverError. Pure.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import gtsam
import numpy as np

from mergesvc.errors import SolverError


@dataclass(frozen=True)
class SolveJob:
    """priors: keys (p,), poses (p, 4, 4), one isotropic sigma; between: keys (n, 2), poses
    (n, 4, 4), covariances (n, 6, 6) (GTSAM order), in the graph's order after the priors;
    initial: keys (k,), poses (k, 4, 4). gnc_known: the graph indices GNC trusts (None: plain
    Levenberg-Marquardt); gnc_probability: its inlier threshold's probability."""

    prior_keys: np.ndarray
    prior_poses: np.ndarray
    prior_sigma: float
    between_keys: np.ndarray
    between_poses: np.ndarray
    between_covs: np.ndarray
    initial_keys: np.ndarray
    initial_poses: np.ndarray
    what: str = "pose-graph"
    gnc_known: tuple[int, ...] | None = None
    gnc_probability: float = 0.99

    def without(self, between: Sequence[int], what: str) -> SolveJob:
        """The same job without the between factors at `between` (plain LM)."""
        keep = np.setdiff1d(np.arange(len(self.between_keys)), np.asarray(between, dtype=int))
        return replace(self, between_keys=self.between_keys[keep],
                       between_poses=self.between_poses[keep],
                       between_covs=self.between_covs[keep], what=what, gnc_known=None)

    def with_initial(self, values: gtsam.Values) -> SolveJob:
        keys = np.asarray(values.keys(), dtype=np.uint64)
        return replace(self, initial_keys=keys,
                       initial_poses=pose_arrays([values.atPose3(int(k)) for k in keys]))


@dataclass(frozen=True)
class SolveResult:
    """The optimised poses (keys (k,), poses (k, 4, 4)) and GNC's weight per between factor
    (None for plain LM)."""

    keys: np.ndarray
    poses: np.ndarray
    weights: np.ndarray | None = None

    def values(self) -> gtsam.Values:
        out = gtsam.Values()
        for k, T in zip(self.keys, self.poses, strict=True):
            out.insert(int(k), gtsam.Pose3(T))
        return out


Optimizer = Callable[[SolveJob], SolveResult]


def pose_arrays(poses: Sequence[gtsam.Pose3]) -> np.ndarray:
    return np.stack([T.matrix() for T in poses]) if poses else np.zeros((0, 4, 4))


def build(job: SolveJob) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """The GTSAM graph and initial values of a job (what core/graph.py builds itself)."""
    graph = gtsam.NonlinearFactorGraph()
    noise = gtsam.noiseModel.Isotropic.Sigma(6, job.prior_sigma)
    for k, T in zip(job.prior_keys, job.prior_poses, strict=True):
        graph.add(gtsam.PriorFactorPose3(int(k), gtsam.Pose3(T), noise))
    for (a, b), T, C in zip(job.between_keys, job.between_poses, job.between_covs, strict=True):
        model = gtsam.noiseModel.Gaussian.Covariance(np.array(C), False)
        graph.add(gtsam.BetweenFactorPose3(int(a), int(b), gtsam.Pose3(T), model))
    values = gtsam.Values()
    for k, T in zip(job.initial_keys, job.initial_poses, strict=True):
        values.insert(int(k), gtsam.Pose3(T))
    return graph, values


def run_job(job: SolveJob) -> SolveResult:
    """Optimise a job here, in this thread (holding the GIL throughout)."""
    graph, initial = build(job)
    weights = None
    try:
        if job.gnc_known is None:
            estimate = gtsam.LevenbergMarquardtOptimizer(
                graph, initial, gtsam.LevenbergMarquardtParams()).optimize()
        else:
            params = gtsam.GncLMParams(gtsam.LevenbergMarquardtParams())
            params.setLossType(gtsam.GncLossType.TLS)
            params.setKnownInliers(list(job.gnc_known))
            gnc = gtsam.GncLMOptimizer(graph, initial, params)
            gnc.setInlierCostThresholdsAtProbability(job.gnc_probability)
            estimate = gnc.optimize()
            weights = np.asarray(gnc.getWeights(), dtype=np.float64).ravel()[
                len(job.prior_keys):]
    except RuntimeError as exc:
        raise SolverError(f"{job.what} optimisation failed: {exc}") from exc
    keys = np.asarray(job.initial_keys, dtype=np.uint64)
    poses = pose_arrays([estimate.atPose3(int(k)) for k in keys])
    return SolveResult(keys, poses, weights)


__all__ = ["Optimizer", "SolveJob", "SolveResult", "build", "pose_arrays", "run_job"]
