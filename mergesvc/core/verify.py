"""Verification stage: rigid transform of the matched centres (gtsam.Pose3.Align), residual gate
with outlier removal, accept/reject with a reason, and the transform's 6x6 covariance
(GTSAM order: rotation, translation); a gravity-aligned 4-DoF fit where the verticals are known.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np

from mergesvc.core.geometry import cross, pairwise_lengths
from mergesvc.core.model import RejectReason
from mergesvc.core.vertical import rotation_between

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


def align_weighted(sub_xyz: np.ndarray, map_xyz: np.ndarray, weights: np.ndarray
                   ) -> gtsam.Pose3 | None:
    """T_map_submap minimising sum_k w_k |T sub_k - map_k|^2 (weighted Kabsch). (k, 3) each,
    w (k,) positive; None below 3 points."""
    if len(sub_xyz) < 3:
        return None
    w = np.asarray(weights, dtype=np.float64) / np.sum(weights)
    mp, mq = w @ sub_xyz, w @ map_xyz
    H = ((sub_xyz - mp) * w[:, None]).T @ (map_xyz - mq)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return gtsam.Pose3(gtsam.Rot3(R), mq - R @ mp)


def transform_points(T: gtsam.Pose3, xyz: np.ndarray) -> np.ndarray:
    """(k, 3) -> (k, 3): T * p for every row."""
    M = T.matrix()  # one call into gtsam (rotation() and translation() are one each)
    return xyz @ np.ascontiguousarray(M[:3, :3]).T + M[:3, 3]


def skew(v: np.ndarray) -> np.ndarray:
    """[v]x (3, 3): skew(v) @ w = cross(v, w)."""
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def pose_covariance_info(
    T: gtsam.Pose3,
    sub_xyz: np.ndarray,
    sigma_m: np.ndarray | float,
    prior_info: np.ndarray | None = None,
) -> np.ndarray:
    """6x6 information of T (tangent space, rotation then translation, right perturbation).

    Linearised least squares: r_k = T exp(xi) p_k - q_k has Jacobian [-R [p_k]x, R]; the
    information is prior_info + sum_k J_k^T J_k / sigma_k^2.
    """
    p = np.asarray(sub_xyz, dtype=float).reshape(-1, 3)
    w = np.asarray(sigma_m, dtype=float)
    w = np.full(len(p), 1.0 / w**2) if w.ndim == 0 else 1.0 / w**2
    info = np.zeros((6, 6)) if prior_info is None else np.array(prior_info, dtype=float)
    # sum_k J_k^T J_k / s_k^2 with J_k = [-R [p_k]x, R]: R^T R = I, so the blocks are
    # [p]x^T [p]x = |p|^2 I - p p^T (rotation), -[p]x^T = [p]x and its transpose (cross),
    # I (translation); sums of [p_k]x are [sum p_k]x
    pw = p * w[:, None]
    info[:3, :3] += np.diag(np.full(3, float((pw * p).sum()))) - pw.T @ p
    cross_sum = skew(pw.sum(axis=0))  # sum_k w_k [p_k]x
    info[:3, 3:] += cross_sum
    info[3:, :3] += cross_sum.T
    info[3:, 3:] += np.diag(np.full(3, float(w.sum())))
    return info


def pose_covariance(
    T: gtsam.Pose3,
    sub_xyz: np.ndarray,
    sigma_m: np.ndarray | float,
    prior_info: np.ndarray | None = None,
) -> np.ndarray:
    """6x6 covariance of T: the inverse of `pose_covariance_info`."""
    return np.linalg.inv(pose_covariance_info(T, sub_xyz, sigma_m, prior_info))


def vertical_fit_covariance(
    T: gtsam.Pose3,
    sub_xyz: np.ndarray,
    sigma_m: np.ndarray | float,
    up_sub: np.ndarray,
    vertical_sigma_rad: float,
) -> np.ndarray:
    """6x6 covariance of a gravity-aligned (4-DoF) fit T_map_submap (GTSAM order, right
    perturbation): the yaw about up_sub and the translation from the points (their
    information in those four directions only), the tilt from the verticals' prior alone (the
    fit does not estimate it: the declared ups set it; each frame's up is known to
    vertical_sigma_rad, so their relative tilt to sqrt(2) times that), carried to the
    translation through the points' centroid, which the fit keeps in place. LinAlgError when
    the points do not fix the yaw. sub_xyz: (k, 3); sigma_m: one sigma or (k,)."""
    u = np.asarray(up_sub, dtype=np.float64) / np.linalg.norm(up_sub)
    B = np.zeros((6, 4))  # the fitted directions: yaw about up, then translation
    B[:3, 0] = u
    B[3:, 1:] = np.eye(3)
    info4 = B.T @ pose_covariance_info(T, sub_xyz, sigma_m) @ B
    cov = B @ np.linalg.inv(info4) @ B.T
    c = np.asarray(sub_xyz, dtype=np.float64).reshape(-1, 3).mean(axis=0)
    G = np.vstack([np.eye(3), skew(c)])  # a tilt delta about the centroid: xi = (delta, c x delta)
    tilt = 2.0 * vertical_sigma_rad**2 * (np.eye(3) - np.outer(u, u))  # both frames' ups
    out = cov + G @ tilt @ G.T
    return 0.5 * (out + out.T)


def consistent_subset(
    sub_xyz: np.ndarray, map_xyz: np.ndarray, tolerance_m: np.ndarray
) -> np.ndarray:
    """(k,) bool: a set of matches whose pairwise distances all agree, found by peeling.

    Two pairs can both be inliers of one rigid fit only if their distances in the two frames
    differ by at most the sum of their tolerances (the consistency graph of CLIPPER and PCM).
    While the kept pairs are not all consistent, the one with the fewest consistent partners
    goes (ties: the one with the largest total disagreement). A least-squares fit started
    from every pair is pulled off by gross outliers (a wrong match 100 m away) and can then
    drop the right pairs instead; started from this set, it is not.
    """
    k = len(sub_xyz)
    keep = np.ones(k, dtype=bool)
    if k < 3:
        return keep
    excess = np.abs(pairwise_lengths(sub_xyz) - pairwise_lengths(map_xyz))
    excess -= tolerance_m[:, None] + tolerance_m[None, :]
    ok = excess <= 0.0
    np.fill_diagonal(ok, True)
    while True:
        idx = np.flatnonzero(keep)
        sub_ok = ok[np.ix_(idx, idx)]
        if sub_ok.all():
            return keep
        degree = sub_ok.sum(axis=1)
        badness = np.maximum(excess[np.ix_(idx, idx)], 0.0).sum(axis=1)
        worst = np.lexsort((-badness, degree))[0]
        keep[idx[worst]] = False


def align_about_vertical(
    sub_xyz: np.ndarray, map_xyz: np.ndarray, up_sub: np.ndarray, up_map: np.ndarray,
    weights: np.ndarray | None = None,
) -> gtsam.Pose3 | None:
    """Gravity-aligned least squares: T_map_submap taking up_sub to up_map, then the yaw about
    the vertical and the translation that fit best. (k, 3) each, k >= 1 (k = 1: yaw 0);
    `weights` (k,): a weighted fit (default: equal).

    With R0 the smallest rotation up_sub -> up_map and p' = R0 p, the yaw is the angle that
    best aligns the horizontal parts of the centred p' onto those of the centred q:
    theta = atan2(sum w (p'_h x q_h) . up, sum w p'_h . q_h) (2-D Procrustes).
    """
    if len(sub_xyz) == 0:
        return None
    w = (np.full(len(sub_xyz), 1.0 / len(sub_xyz)) if weights is None
         else np.asarray(weights, dtype=np.float64) / np.sum(weights))
    mp, mq = w @ sub_xyz, w @ map_xyz
    R0 = rotation_between(up_sub, up_map)
    p = (sub_xyz - mp) @ R0.T
    q = map_xyz - mq
    ph = (p - np.outer(p @ up_map, up_map)) * w[:, None]
    qh = q - np.outer(q @ up_map, up_map)
    theta = float(np.arctan2(cross(ph, qh).sum(axis=0) @ up_map, float((ph * qh).sum())))
    Ry = gtsam.Rot3.AxisAngle(np.asarray(up_map, dtype=float), theta).matrix()
    R = Ry @ R0
    t = mq - R @ mp
    return gtsam.Pose3(gtsam.Rot3(R), t)


def fit_about_vertical(
    sub_xyz: np.ndarray,
    map_xyz: np.ndarray,
    tolerance_m: np.ndarray,
    up_sub: np.ndarray,
    up_map: np.ndarray,
    vertical_sigma_rad: float,
    sigma_floor_m: float = 1e-3,
    min_matches: int = 2,
    min_spread_m: float = 1e-6,
) -> RigidFit:
    """4-DoF fit (yaw + translation) of matched centres whose verticals are known, dropping the
    worst pair while any exceeds its tolerance (as `fit_rigid` does).

    sub_xyz, map_xyz: (k, 3); tolerance_m: (k,). Rejects with `too_few_matches` below
    min_matches, `degenerate_geometry` when the matches do not fix the yaw (no match lies
    min_spread_m or more from their centroid across the vertical: all on one vertical line),
    `residual_too_large` when fewer than min_matches pairs fit. The covariance is the fit's
    in yaw and translation and the verticals' prior (vertical_sigma_rad) in tilt
    (`vertical_fit_covariance`), full rank for two matches.
    """

    def estimate(idx: np.ndarray) -> gtsam.Pose3 | None:
        centred = sub_xyz[idx] - sub_xyz[idx].mean(axis=0)
        horizontal = centred - np.outer(centred @ up_sub, up_sub)
        if float(np.linalg.norm(horizontal, axis=1).max()) < min_spread_m:
            return None  # one above the other: the yaw is free
        return align_about_vertical(sub_xyz[idx], map_xyz[idx], up_sub, up_map)

    def covariance(T: gtsam.Pose3, pts: np.ndarray, sigma: float) -> np.ndarray:
        return vertical_fit_covariance(T, pts, sigma, up_sub, vertical_sigma_rad)

    return _fit_with_outliers(sub_xyz, map_xyz, tolerance_m, min_matches, sigma_floor_m,
                              estimate, dof_per_fit=4, covariance=covariance)


def fit_rigid(
    sub_xyz: np.ndarray,
    map_xyz: np.ndarray,
    tolerance_m: np.ndarray,
    min_matches: int = 3,
    sigma_floor_m: float = 1e-3,
) -> RigidFit:
    """Align matched centres (6-DoF), drop the worst pair while any exceeds its tolerance,
    decide. sub_xyz, map_xyz: (k, 3) matched centres; tolerance_m: (k,) residual gate per pair.
    """

    def estimate(idx: np.ndarray) -> gtsam.Pose3 | None:
        centred = sub_xyz[idx] - sub_xyz[idx].mean(axis=0)
        sv = np.linalg.svd(centred, compute_uv=False)
        if sv[0] == 0 or sv[1] < _COLLINEAR_RATIO * sv[0]:
            return None  # on a line: the rotation about it is free
        return align(sub_xyz[idx], map_xyz[idx])

    return _fit_with_outliers(sub_xyz, map_xyz, tolerance_m, min_matches, sigma_floor_m,
                              estimate, dof_per_fit=6)


def _fit_with_outliers(
    sub_xyz: np.ndarray,
    map_xyz: np.ndarray,
    tolerance_m: np.ndarray,
    min_matches: int,
    sigma_floor_m: float,
    estimate: Callable[[np.ndarray], gtsam.Pose3 | None],
    dof_per_fit: int,
    covariance: Callable[[gtsam.Pose3, np.ndarray, float], np.ndarray] = pose_covariance,
) -> RigidFit:
    """The residual gate of both fits: estimate T on the inliers, drop the worst pair while any
    exceeds its tolerance, then the covariance from the residuals. estimate(idx) -> T, or None
    when the inliers' geometry leaves it undetermined (`degenerate_geometry`)."""
    k = len(sub_xyz)
    inl = np.ones(k, dtype=bool)
    residual = np.full(k, np.nan)
    T: gtsam.Pose3 | None = None

    def reject(reason: RejectReason) -> RigidFit:
        rmse = float(np.sqrt(np.nanmean(residual[inl] ** 2))) if inl.any() and T else np.nan
        return RigidFit(reason, T, None, inl, residual, rmse)

    if k < min_matches:
        return reject(RejectReason.TOO_FEW_MATCHES)
    while True:
        idx = np.flatnonzero(inl)
        if len(idx) < min_matches:
            return reject(RejectReason.RESIDUAL_TOO_LARGE)
        T = estimate(idx)
        if T is None:
            return reject(RejectReason.DEGENERATE_GEOMETRY)
        residual = np.linalg.norm(transform_points(T, sub_xyz) - map_xyz, axis=1)
        ratio = np.where(inl, residual / tolerance_m, -np.inf)
        worst = int(np.argmax(ratio))
        if ratio[worst] <= 1.0:
            break
        inl[worst] = False
    dof = 3 * len(idx) - dof_per_fit
    rss = float((residual[idx] ** 2).sum())
    # per-axis noise from the residuals, never below the floor (3 exact points have rss 0)
    sigma = max(np.sqrt(rss / dof) if dof > 0 else 0.0, sigma_floor_m)
    try:
        cov = covariance(T, sub_xyz[idx], sigma)
    except np.linalg.LinAlgError:  # a direction the matches leave free
        return reject(RejectReason.DEGENERATE_GEOMETRY)
    rmse = float(np.sqrt(rss / len(idx)))
    return RigidFit(RejectReason.VERIFIED, T, cov, inl, residual, rmse)
