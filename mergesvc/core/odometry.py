"""Odometry uncertainty: the covariance of a vehicle's dead-reckoned motion between two poses.

Model (docs/uncertainty.md): each odometry step i, the motion D_i measured in the body frame of
the pose before it, is off the truth by a right perturbation eta_i ~ N(0, Q_i) (GTSAM's Pose3
tangent order: rotation rad, then translation m), independent between steps. The motion over n
steps, T = D_1 ... D_n, is then off by xi = sum_i Ad(D_{i+1} ... D_n)^-1 eta_i to first order,
so Sigma = sum_i Ad_i Q_i Ad_i^T. The adjoint's lower-left block [t]x R carries a heading error
at step i into a sideways position error that grows with the path driven since: over a straight
stretch of n steps of length d the lateral variance grows as sigma_yaw^2 d^2 n^3 / 3, not as n.

Pure numpy and GTSAM: no I/O.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import gtsam
import numpy as np

from mergesvc.errors import InputError


def step_covariance(odometry_sigma: Sequence[float]) -> np.ndarray:
    """Q (6, 6) of one step from (rotation rad, translation m), the same on each axis, or 6
    sigmas in GTSAM order."""
    s = np.asarray(odometry_sigma, dtype=np.float64).ravel()
    if s.shape == (2,):
        s = np.repeat(s, 3)
    if s.shape != (6,) or not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise InputError(f"odometry sigma must be 2 or 6 positive numbers, got {s.tolist()}")
    return np.diag(s * s)


def compose_covariance(steps: Iterable[np.ndarray | gtsam.Pose3], Q: np.ndarray) -> np.ndarray:
    """Sigma (6, 6) of the composition of `steps` (each a Pose3 or (4, 4) step D_i, in order),
    each with step covariance Q, to first order (module docstring). No steps: zeros."""
    S = np.zeros((6, 6))
    for D in steps:
        P = D if isinstance(D, gtsam.Pose3) else gtsam.Pose3(np.asarray(D, dtype=np.float64))
        A = np.asarray(P.inverse().AdjointMap())
        S = A @ S @ A.T + Q
    return 0.5 * (S + S.T)


def chain_covariance(poses: Sequence[np.ndarray], Q: np.ndarray) -> np.ndarray:
    """Sigma of inv(poses[0]) poses[-1]: the steps between consecutive (4, 4) poses of a
    dead-reckoned trajectory composed (`compose_covariance`)."""
    if len(poses) < 2:
        raise InputError("a chain needs at least two poses")
    steps = (np.linalg.solve(poses[i], poses[i + 1]) for i in range(len(poses) - 1))
    return compose_covariance(steps, Q)


__all__ = ["chain_covariance", "compose_covariance", "step_covariance"]
