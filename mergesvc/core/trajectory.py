"""Trajectory evaluation as users know it from evo and the TUM RGB-D benchmark: the Umeyama
alignment, the absolute trajectory error (ATE) and the error of the final pose.

Conventions (pinned by tests/test_trajectory.py):
- a pose is a 4x4 homogeneous matrix T_world_body (rotation R, translation t, last row 0 0 0 1);
  a trajectory is an (n, 4, 4) array, or just its (n, 3) positions where only positions count;
- two trajectories are associated by index (same n); associate by timestamp before calling;
- `ate_rmse(..., align=True)` is evo's `evo_ape ... --align` (APE, translation part): the
  estimate's positions are moved onto the reference's by the least-squares rigid transform
  (Umeyama 1991; `with_scale=True` is evo's `--align --correct_scale`, a similarity), then the
  root mean square of the position differences. The translation part of evo's APE,
  |trans(T_ref^-1 T_est)|, equals |t_est - t_ref|, so this is the same number.

Pure numpy: no files (mergesvc.wire.formats reads and writes TUM and g2o files).
"""

from __future__ import annotations

import numpy as np

from mergesvc.errors import InputError

# A rotation block further than this from orthonormal (max |R^T R - I|) is not a rotation.
ROTATION_TOL = 1e-5
# Singular values of the centred points below this fraction of the largest count as zero.
RANK_TOL = 1e-9


def as_poses(poses: object, what: str = "poses") -> np.ndarray:
    """`poses` as an (n, 4, 4) float array of rigid transforms, else InputError.

    Refuses another shape, NaN or inf, a last row other than 0 0 0 1, and a rotation block
    that is not a proper rotation (orthonormal within ROTATION_TOL, determinant +1)."""
    T = np.asarray(poses, dtype=float)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise InputError(f"{what}: expected an (n, 4, 4) array of poses, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        bad = int(np.argwhere(~np.isfinite(T))[0][0])
        raise InputError(f"{what}: pose {bad} holds NaN or inf")
    bottom = np.abs(T[:, 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=1)
    if np.any(bottom > ROTATION_TOL):
        bad = int(np.argmax(bottom))
        raise InputError(f"{what}: pose {bad} has last row {T[bad, 3].tolist()}, not 0 0 0 1")
    R = T[:, :3, :3]
    ortho = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(axis=(1, 2)) if len(T) else []
    for i, err in enumerate(ortho):
        if err > ROTATION_TOL or np.linalg.det(R[i]) < 0:
            raise InputError(
                f"{what}: pose {i} has a rotation block that is not a proper rotation "
                f"(|R^T R - I| = {err:.3g}, det = {np.linalg.det(R[i]):.6g})"
            )
    return T


def _positions(x: object, what: str) -> np.ndarray:
    """(n, 4, 4) poses or (n, 3) positions -> (n, 3) positions (checked)."""
    a = np.asarray(x, dtype=float)
    if a.ndim == 3:
        return as_poses(a, what)[:, :3, 3]
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputError(
            f"{what}: expected (n, 4, 4) poses or (n, 3) positions, got shape {a.shape}"
        )
    if not np.all(np.isfinite(a)):
        bad = int(np.argwhere(~np.isfinite(a))[0][0])
        raise InputError(f"{what}: position {bad} holds NaN or inf")
    return a


def _pair(est: object, ref: object) -> tuple[np.ndarray, np.ndarray]:
    e = _positions(est, "estimate")
    r = _positions(ref, "reference")
    if len(e) != len(r):
        raise InputError(
            f"the estimate has {len(e)} poses and the reference {len(r)}: they are associated "
            "by index, so they must have as many (associate by timestamp first)"
        )
    if len(e) == 0:
        raise InputError("empty trajectories: there is no error to compute")
    return e, r


def _check_spread(points: np.ndarray, centred: np.ndarray, what: str) -> None:
    """Refuse points whose spread does not fix a rotation: all equal, or on one line."""
    sv = np.linalg.svd(centred, compute_uv=False)
    scale = max(1.0, float(np.abs(points).max()))  # rounding in the centring scales with it
    if sv[0] <= 1e-10 * np.sqrt(len(points)) * scale:
        raise InputError(
            f"umeyama_alignment: the {what} points are all the same point: no rotation fits"
        )
    if sv[1] <= RANK_TOL * sv[0]:
        raise InputError(
            f"umeyama_alignment: the {what} points are collinear: the rotation about their line "
            "is undetermined (at least 3 points not on one line are needed)"
        )


def umeyama_alignment(
    src_xyz: np.ndarray, dst_xyz: np.ndarray, with_scale: bool = False
) -> tuple[np.ndarray, np.ndarray, float]:
    """The least-squares transform mapping src onto dst (Umeyama 1991).

    Minimises sum_i |dst_i - (s R src_i + t)|^2 over proper rotations R (det +1), t, and s
    (s = 1 unless with_scale). Returns (R (3, 3), t (3,), s).

    InputError: shapes other than two (n, 3) arrays of the same n, NaN or inf, fewer than 3
    points, or points that do not fix a rotation (all equal, or collinear) on either side."""
    src = np.asarray(src_xyz, dtype=float)
    dst = np.asarray(dst_xyz, dtype=float)
    for name, a in (("source", src), ("destination", dst)):
        if a.ndim != 2 or a.shape[1] != 3:
            raise InputError(f"umeyama_alignment: {name} must be (n, 3), got shape {a.shape}")
        if not np.all(np.isfinite(a)):
            raise InputError(f"umeyama_alignment: the {name} points hold NaN or inf")
    if len(src) != len(dst):
        raise InputError(
            f"umeyama_alignment: {len(src)} source points but {len(dst)} destination points"
        )
    n = len(src)
    if n < 3:
        raise InputError(
            f"umeyama_alignment: {n} point(s); at least 3 (not on one line) are needed"
        )
    mu_s = src.mean(axis=0)
    mu_d = dst.mean(axis=0)
    X = src - mu_s
    Y = dst - mu_d
    _check_spread(src, X, "source")
    _check_spread(dst, Y, "destination")
    cov = Y.T @ X / n
    U, D, Vt = np.linalg.svd(cov)
    S = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:  # the best orthogonal map is a reflection
        S[2] = -1.0
    R = (U * S) @ Vt
    s = float((D * S).sum() / (X**2).sum(axis=1).mean()) if with_scale else 1.0
    t = mu_d - s * R @ mu_s
    return R, t, s


def ate_rmse(
    est: np.ndarray, ref: np.ndarray, *, align: bool = True, with_scale: bool = False
) -> float:
    """Absolute trajectory error (metres): the RMSE of the position differences.

    est, ref: (n, 4, 4) poses or (n, 3) positions, associated by index. align: first move the
    estimate onto the reference by the Umeyama transform of their positions (evo's `--align`;
    with_scale adds the scale, evo's `--correct_scale`); needs 3 positions not on one line.
    Without align, the plain RMSE of the differences."""
    e, r = _pair(est, ref)
    if with_scale and not align:
        raise InputError("ate_rmse: with_scale needs align=True (the scale is fitted)")
    if align:
        R, t, s = umeyama_alignment(e, r, with_scale=with_scale)
        e = s * e @ R.T + t
    return float(np.sqrt(((e - r) ** 2).sum(axis=1).mean()))


def rotation_error_deg(T_est: np.ndarray, T_ref: np.ndarray) -> float:
    """Angle (degrees, in [0, 180]) of R_ref^T R_est: the rotation between two poses.

    Computed as atan2(|vee(E - E^T)| / 2, (tr E - 1) / 2), accurate for small angles too
    (arccos of the trace alone loses half the digits near 0)."""
    a, b = as_poses(np.stack([np.asarray(T_est, float), np.asarray(T_ref, float)]), "pose pair")
    E = b[:3, :3].T @ a[:3, :3]
    skew = np.array([E[2, 1] - E[1, 2], E[0, 2] - E[2, 0], E[1, 0] - E[0, 1]])
    sin = np.linalg.norm(skew) / 2.0
    cos = (np.trace(E) - 1.0) / 2.0
    return float(np.degrees(np.arctan2(sin, cos)))


def final_pose_error(
    est_poses: np.ndarray,
    ref_poses: np.ndarray,
    *,
    align: bool = True,
    with_scale: bool = False,
) -> tuple[float, float]:
    """Error of the last pose: (translation error in metres, rotation error in degrees).

    With align, the whole estimated trajectory is first moved by the transform ate_rmse uses
    (Umeyama on all positions, scale only with with_scale), then the last poses compared."""
    e = as_poses(est_poses, "estimate")
    r = as_poses(ref_poses, "reference")
    _pair(e, r)
    if with_scale and not align:
        raise InputError("final_pose_error: with_scale needs align=True (the scale is fitted)")
    last = e[-1].copy()
    if align:
        R, t, s = umeyama_alignment(e[:, :3, 3], r[:, :3, 3], with_scale=with_scale)
        last[:3, :3] = R @ last[:3, :3]
        last[:3, 3] = s * R @ last[:3, 3] + t
    return float(np.linalg.norm(last[:3, 3] - r[-1][:3, 3])), rotation_error_deg(last, r[-1])


__all__ = [
    "RANK_TOL",
    "ROTATION_TOL",
    "as_poses",
    "ate_rmse",
    "final_pose_error",
    "rotation_error_deg",
    "umeyama_alignment",
]
