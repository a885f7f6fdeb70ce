"""Pose3 conversions and first-order pose algebra shared by the stages: wire Transforms and (4, 4)
matrices to gtsam.Pose3 and back (checked), composition and inversion with covariances in
GTSAM's tangent convention (right perturbation; rotation rad, then translation m), and the
error between two poses. Pure: no I/O.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gtsam
import numpy as np

from mergesvc.core.model import Transform
from mergesvc.errors import InputError

# Tolerance of the rotation check on (4, 4) inputs: |R^T R - I| and |det R - 1|.
_ROTATION_TOL = 1e-6
# Symmetry tolerance of covariance inputs, relative to the largest entry.
_SYM_RTOL = 1e-9


def as_pose3(T: gtsam.Pose3 | np.ndarray | Sequence[Sequence[float]], name: str) -> gtsam.Pose3:
    """A gtsam.Pose3 from a Pose3 or a (4, 4) homogeneous matrix with a proper rotation."""
    if isinstance(T, gtsam.Pose3):
        return T
    M = np.asarray(T, dtype=np.float64)
    if M.shape != (4, 4) or not np.all(np.isfinite(M)):
        raise InputError(f"{name} must be a gtsam.Pose3 or a finite (4, 4) matrix")
    R = M[:3, :3]
    if (
        np.abs(R.T @ R - np.eye(3)).max() > _ROTATION_TOL
        or abs(np.linalg.det(R) - 1.0) > _ROTATION_TOL
        or np.abs(M[3] - [0, 0, 0, 1]).max() > 0
    ):
        raise InputError(f"{name} is not a rigid transform (rotation not orthonormal, det 1)")
    return gtsam.Pose3(gtsam.Rot3.ClosestTo(R), M[:3, 3])


def check_covariance(C: Any, name: str) -> np.ndarray:
    """A valid 6x6 covariance as a read-only float64 array: `C` itself when it is one already
    (read-only, owning its data, exactly symmetric: a long mission's graph shares its
    odometry's arrays; whoever made it must not make it writable again), else a symmetrised
    copy. InputError unless finite, symmetric within 1e-9 of its largest entry, and positive
    definite once symmetrised (what the pose graph solves with)."""
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


def pose3_from_transform(
    translation: Sequence[float], quaternion_wxyz: Sequence[float]
) -> gtsam.Pose3:
    """gtsam.Pose3 from a translation (3,) and a quaternion (w, x, y, z), normalised here (the
    wire allows a norm off by 1e-3; Rot3.Quaternion assumes exactly 1)."""
    q = np.asarray(quaternion_wxyz, dtype=np.float64)
    norm = float(np.linalg.norm(q))
    if q.shape != (4,) or not np.isfinite(norm) or norm < 0.5:
        raise InputError(f"quaternion_wxyz must be 4 finite numbers of norm ~1, got {q}")
    w, x, y, z = (float(v) for v in q / norm)
    return gtsam.Pose3(gtsam.Rot3.Quaternion(w, x, y, z), np.asarray(translation, dtype=float))


def pose3_from_model(T: Transform) -> gtsam.Pose3:
    """gtsam.Pose3 of a wire Transform."""
    return pose3_from_transform(T.translation, T.quaternion_wxyz)


def transform_from_pose3(T: gtsam.Pose3 | np.ndarray) -> Transform:
    """The wire Transform of a gtsam.Pose3 (or a (4, 4) rigid transform)."""
    P = as_pose3(T, "transform")
    q = P.rotation().toQuaternion()
    return Transform(
        translation=tuple(float(x) for x in P.translation()),
        quaternion_wxyz=(float(q.w()), float(q.x()), float(q.y()), float(q.z())),
    )


def compose_with_covariance(T_a: gtsam.Pose3, S_a: np.ndarray, T_b: gtsam.Pose3,
             S_b: np.ndarray) -> tuple[gtsam.Pose3, np.ndarray]:
    """T_a * T_b with its covariance, both independent, to first order, in GTSAM's tangent
    convention (right perturbation, rotation then translation): Ad(T_b^-1) S_a Ad(T_b^-1)^T +
    S_b."""
    A = np.asarray(T_b.inverse().AdjointMap())
    return T_a.compose(T_b), A @ S_a @ A.T + S_b


def inverse_with_covariance(T: gtsam.Pose3, S: np.ndarray) -> tuple[gtsam.Pose3, np.ndarray]:
    """T^-1 with its covariance, to first order (right perturbation): Ad(T) S Ad(T)^T."""
    A = np.asarray(T.AdjointMap())
    return T.inverse(), A @ S @ A.T


def pose_error(T_est: gtsam.Pose3, T_true: gtsam.Pose3) -> tuple[float, float]:
    """(rotation error rad, translation error m) between two poses."""
    d = T_true.between(T_est)
    return float(np.linalg.norm(gtsam.Rot3.Logmap(d.rotation()))), float(
        np.linalg.norm(T_est.translation() - T_true.translation())
    )


__all__ = ["as_pose3", "check_covariance", "compose_with_covariance",
           "inverse_with_covariance", "pose3_from_model", "pose3_from_transform", "pose_error",
           "transform_from_pose3"]
