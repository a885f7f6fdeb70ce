"""Verification stage: rigid transform of the matched centres (gtsam.Pose3.Align), residual gate
with outlier removal, accept/reject with a reason, and the transform's 6x6 covariance
(GTSAM order: rotation, translation).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from mergesvc.model import RejectReason

# Below this ratio of the second to the first singular value the matched centres are (nearly) on
# a line and the rotation about that line is unobservable.
_COLLINEAR_RATIO = 0.02


@dataclass(frozen=True)
class RigidFit:
    """Outcome of fitting T_map_submap to matched centres.

    inliers: (k,) bool over the input pairs; residual_m: (k,) distance after alignment.
    """

    reason: RejectReason
    T_map_submap: gtsam.Pose3 | None
    covariance_66: np.ndarray | None
    inliers: np.ndarray
    residual_m: np.ndarray
    rmse_m: float

    @property
    def accepted(self) -> bool:
        return self.reason is RejectReason.VERIFIED


def align(sub_xyz: np.ndarray, map_xyz: np.ndarray) -> gtsam.Pose3 | None:
    """T_map_submap with map = T * sub, least squares (Umeyama via gtsam). (k, 3) each."""
    if len(sub_xyz) < 3:
        return None
    return gtsam.Pose3.Align(
        np.ascontiguousarray(map_xyz.T, dtype=np.float64),
        np.ascontiguousarray(sub_xyz.T, dtype=np.float64),
    )


def transform_points(T: gtsam.Pose3, xyz: np.ndarray) -> np.ndarray:
    """(k, 3) -> (k, 3): T * p for every row."""
    return xyz @ T.rotation().matrix().T + T.translation()


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def pose_covariance(
    T: gtsam.Pose3, sub_xyz: np.ndarray, sigma_m: np.ndarray | float
) -> np.ndarray:
    """6x6 covariance of T (tangent space, rotation then translation, right perturbation).

    Linearised least squares: r_k = T exp(xi) p_k - q_k has Jacobian [-R [p_k]x, R];
    Sigma = (sum_k J_k^T J_k / sigma_k^2)^-1.
    """
    R = T.rotation().matrix()
    sig = np.broadcast_to(np.asarray(sigma_m, dtype=float), (len(sub_xyz),))
    info = np.zeros((6, 6))
    for p, s in zip(sub_xyz, sig):
        J = np.hstack([-R @ _skew(p), R])
        info += J.T @ J / s**2
    return np.linalg.inv(info)


def fit_rigid(
    sub_xyz: np.ndarray,
    map_xyz: np.ndarray,
    tolerance_m: np.ndarray,
    min_matches: int = 3,
    sigma_floor_m: float = 1e-3,
) -> RigidFit:
    """Align matched centres, drop the worst pair while any exceeds its tolerance, decide.

    sub_xyz, map_xyz: (k, 3) matched centres; tolerance_m: (k,) residual gate per pair.
    """
    k = len(sub_xyz)
    inl = np.ones(k, dtype=bool)
    residual = np.full(k, np.nan)

    def reject(reason: RejectReason, T: gtsam.Pose3 | None = None) -> RigidFit:
        rmse = float(np.sqrt(np.nanmean(residual[inl] ** 2))) if inl.any() and T else np.nan
        return RigidFit(reason, T, None, inl, residual, rmse)

    if k < min_matches:
        return reject(RejectReason.TOO_FEW_MATCHES)
    while True:
        idx = np.flatnonzero(inl)
        if len(idx) < min_matches:
            return reject(RejectReason.RESIDUAL_TOO_LARGE)
        centred = sub_xyz[idx] - sub_xyz[idx].mean(axis=0)
        sv = np.linalg.svd(centred, compute_uv=False)
        if sv[0] == 0 or sv[1] < _COLLINEAR_RATIO * sv[0]:
            return reject(RejectReason.DEGENERATE_GEOMETRY)
        T = align(sub_xyz[idx], map_xyz[idx])
        if T is None:
            return reject(RejectReason.DEGENERATE_GEOMETRY)
        residual = np.linalg.norm(transform_points(T, sub_xyz) - map_xyz, axis=1)
        ratio = np.where(inl, residual / tolerance_m, -np.inf)
        worst = int(np.argmax(ratio))
        if ratio[worst] <= 1.0:
            break
        inl[worst] = False
    dof = 3 * len(idx) - 6
    rss = float((residual[idx] ** 2).sum())
    # per-axis noise from the residuals, never below the floor (3 exact points have rss 0)
    sigma = max(np.sqrt(rss / dof) if dof > 0 else 0.0, sigma_floor_m)
    cov = pose_covariance(T, sub_xyz[idx], sigma)
    rmse = float(np.sqrt(rss / len(idx)))
    return RigidFit(RejectReason.VERIFIED, T, cov, inl, residual, rmse)
