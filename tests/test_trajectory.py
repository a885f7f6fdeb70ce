"""Trajectory evaluation (mergesvc.core.trajectory) against simple references: transforms
recovered exactly, ATE by brute force (scipy.optimize over the transform), gtsam's own
Umeyama, and evo when it happens to be installed (it is not a dependency: GPL-3.0)."""

from __future__ import annotations

import re

import gtsam
import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from mergesvc.core.trajectory import (
    as_poses,
    ate_rmse,
    final_pose_error,
    rotation_error_deg,
    umeyama_alignment,
)
from mergesvc.errors import InputError


def _pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _trajectory(rng: np.random.Generator, n: int = 40) -> np.ndarray:
    """A wandering trajectory of n poses (a random walk in position and orientation)."""
    poses = np.empty((n, 4, 4))
    T = np.eye(4)
    for k in range(n):
        step = _pose(Rotation.from_rotvec(rng.normal(0.0, 0.15, 3)).as_matrix(),
                     rng.normal([0.5, 0.0, 0.0], 0.2))
        T = T @ step
        poses[k] = T
    return poses


def _moved(poses: np.ndarray, T: np.ndarray, s: float = 1.0) -> np.ndarray:
    """The whole trajectory moved by the similarity (s, T): positions s R p + t, R R_k."""
    out = poses.copy()
    out[:, :3, :3] = T[:3, :3] @ poses[:, :3, :3]
    out[:, :3, 3] = s * poses[:, :3, 3] @ T[:3, :3].T + T[:3, 3]
    return out


RNG_T = _pose(Rotation.from_rotvec([0.3, -1.2, 2.0]).as_matrix(), np.array([4.0, -2.5, 7.0]))


# ---- Umeyama


@pytest.mark.parametrize("with_scale", [False, True])
def test_umeyama_recovers_a_known_transform_exactly(with_scale: bool) -> None:
    rng = np.random.default_rng(0)
    src = rng.normal(0.0, 3.0, (25, 3))
    s_true = 2.7 if with_scale else 1.0
    dst = s_true * src @ RNG_T[:3, :3].T + RNG_T[:3, 3]
    R, t, s = umeyama_alignment(src, dst, with_scale=with_scale)
    np.testing.assert_allclose(R, RNG_T[:3, :3], atol=1e-12)
    np.testing.assert_allclose(t, RNG_T[:3, 3], atol=1e-11)
    assert s == pytest.approx(s_true, abs=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_umeyama_without_scale_keeps_scale_one_even_when_the_data_is_scaled() -> None:
    rng = np.random.default_rng(1)
    src = rng.normal(size=(10, 3))
    _, _, s = umeyama_alignment(src, 3.0 * src)
    assert s == 1.0


def test_umeyama_agrees_with_gtsam_pose3_align_on_noisy_points() -> None:
    rng = np.random.default_rng(2)
    src = rng.normal(0.0, 2.0, (30, 3))
    dst = src @ RNG_T[:3, :3].T + RNG_T[:3, 3] + rng.normal(0.0, 0.05, (30, 3))
    R, t, _ = umeyama_alignment(src, dst)
    # gtsam.Pose3.Align(Point3Pairs) gives aTb for pairs (a_i, b_i) with a_i = aTb * b_i
    pairs = [(dst[k], src[k]) for k in range(len(src))]
    aTb = gtsam.Pose3.Align(pairs)
    np.testing.assert_allclose(R, aTb.rotation().matrix(), atol=1e-10)
    np.testing.assert_allclose(t, aTb.translation(), atol=1e-10)


def test_umeyama_returns_a_rotation_when_the_best_orthogonal_map_is_a_reflection() -> None:
    """Points mirrored through a plane: the unconstrained best fit is the mirror (det -1);
    Umeyama's correction returns the best proper rotation instead."""
    rng = np.random.default_rng(3)
    src = rng.normal(size=(12, 3)) * [3.0, 2.0, 1.0]
    dst = src * [1.0, 1.0, -1.0]
    R, t, s = umeyama_alignment(src, dst, with_scale=True)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert s > 0
    # the best proper rotation: no sampled rotation does better
    cost = ((s * src @ R.T + t - dst) ** 2).sum()
    for rot in Rotation.random(200, random_state=4).as_matrix():
        tt = dst.mean(0) - s * rot @ src.mean(0)
        assert ((s * src @ rot.T + tt - dst) ** 2).sum() >= cost - 1e-9


def test_umeyama_fits_coplanar_points() -> None:
    """Points on one plane (rank 2) still fix the rotation."""
    rng = np.random.default_rng(5)
    src = np.column_stack([rng.normal(size=(8, 2)), np.zeros(8)])
    dst = src @ RNG_T[:3, :3].T + RNG_T[:3, 3]
    R, t, _ = umeyama_alignment(src, dst)
    np.testing.assert_allclose(R, RNG_T[:3, :3], atol=1e-10)
    np.testing.assert_allclose(t, RNG_T[:3, 3], atol=1e-10)


@pytest.mark.parametrize(
    ("src", "message"),
    [
        (np.zeros((2, 3)), "at least 3"),
        (np.ones((5, 3)) * [1.0, 2.0, 3.0], "all the same point"),
        (np.ones((5, 3)) * [1e6, -2e6, 3e6], "all the same point"),
        (np.arange(5.0)[:, None] * [1.0, 2.0, 3.0] + [1.0, 0.0, 0.0], "collinear"),
        (np.array([[0.0, 0.0, 0.0], [np.nan, 1.0, 0.0], [0.0, 0.0, 1.0]]), "NaN or inf"),
        (np.zeros((4, 2)), "(n, 3)"),
    ],
)
def test_umeyama_refuses_inputs_that_do_not_fix_a_transform(
    src: np.ndarray, message: str
) -> None:
    dst = np.random.default_rng(6).normal(size=(len(src), 3))
    with pytest.raises(InputError, match=re.escape(message)):
        umeyama_alignment(src, dst)


def test_umeyama_refuses_a_degenerate_destination_and_a_size_mismatch() -> None:
    src = np.random.default_rng(7).normal(size=(6, 3))
    with pytest.raises(InputError, match="destination points are collinear"):
        umeyama_alignment(src, np.arange(6.0)[:, None] * [0.0, 0.0, 1.0])
    with pytest.raises(InputError, match="6 source points but 5"):
        umeyama_alignment(src, src[:5])


# ---- ATE


def test_ate_of_a_rigidly_moved_trajectory_is_zero_with_align() -> None:
    ref = _trajectory(np.random.default_rng(8))
    est = _moved(ref, RNG_T)
    assert ate_rmse(est, ref) == pytest.approx(0.0, abs=1e-10)
    assert ate_rmse(est, ref, align=False) > 1.0


def test_ate_with_scale_undoes_a_similarity() -> None:
    ref = _trajectory(np.random.default_rng(9))
    est = _moved(ref, RNG_T, s=0.4)
    assert ate_rmse(est, ref, with_scale=True) == pytest.approx(0.0, abs=1e-10)
    assert ate_rmse(est, ref) > 0.1  # a rigid alignment cannot undo the scale


def test_ate_without_align_of_a_pure_offset_is_the_offset() -> None:
    ref = _trajectory(np.random.default_rng(10))
    offset = np.array([0.3, -0.4, 1.2])
    est = ref.copy()
    est[:, :3, 3] += offset
    assert ate_rmse(est, ref, align=False) == pytest.approx(np.linalg.norm(offset), rel=1e-12)
    assert ate_rmse(est, ref) == pytest.approx(0.0, abs=1e-10)


def test_ate_takes_poses_or_positions() -> None:
    rng = np.random.default_rng(11)
    ref = _trajectory(rng)
    est = _moved(ref, RNG_T)
    est[:, :3, 3] += rng.normal(0.0, 0.1, (len(est), 3))
    a = ate_rmse(est, ref)
    assert ate_rmse(est[:, :3, 3], ref[:, :3, 3]) == a
    assert ate_rmse(est, ref[:, :3, 3]) == a


def _brute_force_ate(est_xyz: np.ndarray, ref_xyz: np.ndarray, with_scale: bool) -> float:
    """min over a 6-DoF (7 with scale) transform of the RMSE, by a generic optimiser started
    from several random transforms: knows nothing of Umeyama."""
    def residual(x: np.ndarray) -> np.ndarray:
        R = Rotation.from_rotvec(x[:3]).as_matrix()
        s = np.exp(x[6]) if with_scale else 1.0
        return (s * est_xyz @ R.T + x[3:6] - ref_xyz).ravel()

    rng = np.random.default_rng(12)
    best = np.inf
    for _ in range(8):
        x0 = np.concatenate([Rotation.random(random_state=rng).as_rotvec(),
                             rng.normal(size=3), [0.0]])
        sol = least_squares(residual, x0, xtol=1e-15, ftol=1e-15, gtol=1e-15)
        best = min(best, float(np.sqrt((sol.fun**2).sum() / len(est_xyz))))
    return best


@pytest.mark.parametrize("with_scale", [False, True])
def test_ate_equals_the_brute_force_minimum(with_scale: bool) -> None:
    rng = np.random.default_rng(13)
    ref = rng.normal(0.0, 2.0, (9, 3))
    est = (1.6 if with_scale else 1.0) * ref @ RNG_T[:3, :3].T + RNG_T[:3, 3]
    est += rng.normal(0.0, 0.2, est.shape)
    ours = ate_rmse(est, ref, with_scale=with_scale)
    brute = _brute_force_ate(est, ref, with_scale)
    assert ours > 0.05  # the noise is not aligned away
    assert ours == pytest.approx(brute, abs=1e-6)


def test_ate_refuses_mismatched_or_bad_trajectories() -> None:
    ref = _trajectory(np.random.default_rng(14), n=10)
    with pytest.raises(InputError, match="associated by index"):
        ate_rmse(ref[:9], ref)
    with pytest.raises(InputError, match="at least 3"):
        ate_rmse(ref[:2], ref[:2])
    bad = ref.copy()
    bad[3, 0, 0] = np.nan
    with pytest.raises(InputError, match="pose 3 holds NaN"):
        ate_rmse(bad, ref)
    bad = ref.copy()
    bad[2, :3, :3] *= 1.1
    with pytest.raises(InputError, match="pose 2 has a rotation block"):
        ate_rmse(bad, ref)
    with pytest.raises(InputError, match="with_scale needs align"):
        ate_rmse(ref, ref, align=False, with_scale=True)
    with pytest.raises(InputError, match="empty"):
        ate_rmse(np.zeros((0, 3)), np.zeros((0, 3)))
    # without alignment two poses are enough
    assert ate_rmse(ref[:2], ref[:2], align=False) == 0.0


def test_as_poses_refuses_reflections_and_bad_last_rows() -> None:
    T = np.eye(4)[None].repeat(2, axis=0)
    T[1, 2, 2] = -1.0
    with pytest.raises(InputError, match=r"pose 1 .*not a proper rotation"):
        as_poses(T)
    T = np.eye(4)[None].copy()
    T[0, 3, 0] = 1.0
    with pytest.raises(InputError, match="last row"):
        as_poses(T)
    with pytest.raises(InputError, match=r"\(n, 4, 4\)"):
        as_poses(np.eye(4))


# ---- rotation and final pose errors


@pytest.mark.parametrize("angle_deg", [0.0, 1e-7, 0.5, 30.0, 90.0, 179.0, 180.0])
def test_rotation_error_is_the_angle_between_the_poses(angle_deg: float) -> None:
    rng = np.random.default_rng(15)
    R_ref = Rotation.random(random_state=rng).as_matrix()
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    R_est = R_ref @ Rotation.from_rotvec(np.radians(angle_deg) * axis).as_matrix()
    got = rotation_error_deg(_pose(R_est, rng.normal(size=3)), _pose(R_ref, np.zeros(3)))
    assert got == pytest.approx(angle_deg, abs=1e-9)


def test_final_pose_error_of_a_rigidly_moved_trajectory_is_zero_with_align() -> None:
    ref = _trajectory(np.random.default_rng(16))
    est = _moved(ref, RNG_T)
    m, deg = final_pose_error(est, ref)
    assert m == pytest.approx(0.0, abs=1e-9)
    assert deg == pytest.approx(0.0, abs=1e-6)
    m, deg = final_pose_error(est, ref, align=False)
    assert m == pytest.approx(np.linalg.norm(est[-1, :3, 3] - ref[-1, :3, 3]))
    assert deg == pytest.approx(np.degrees(np.linalg.norm(Rotation.from_matrix(RNG_T[:3, :3])
                                                          .as_rotvec())))


def test_final_pose_error_is_the_last_pose_after_the_ate_alignment() -> None:
    """A drift that grows along the trajectory: the aligned last pose, computed by hand from
    the alignment ate_rmse uses (gtsam composes the poses), gives the same errors."""
    rng = np.random.default_rng(17)
    ref = _trajectory(rng)
    est = ref.copy()
    for k in range(len(est)):
        drift = _pose(Rotation.from_rotvec([0.0, 0.0, 0.004 * k]).as_matrix(),
                      np.array([0.01 * k, 0.0, 0.0]))
        est[k] = drift @ est[k]
    est = _moved(est, RNG_T)
    R, t, _ = umeyama_alignment(est[:, :3, 3], ref[:, :3, 3])
    last = gtsam.Pose3(gtsam.Rot3(R), t).compose(gtsam.Pose3(est[-1]))
    err = gtsam.Pose3(ref[-1]).between(last)
    m, deg = final_pose_error(est, ref)
    assert m == pytest.approx(np.linalg.norm(last.translation() - ref[-1, :3, 3]), rel=1e-9)
    assert deg == pytest.approx(np.degrees(np.linalg.norm(gtsam.Rot3.Logmap(err.rotation()))),
                                rel=1e-9)
    assert m > 0.05 and deg > 0.1


def test_final_pose_error_needs_poses() -> None:
    ref = _trajectory(np.random.default_rng(18), n=5)
    with pytest.raises(InputError, match=r"\(n, 4, 4\)"):
        final_pose_error(ref[:, :3, 3], ref[:, :3, 3])
    with pytest.raises(InputError, match="associated by index"):
        final_pose_error(ref[:4], ref)


# ---- evo, when installed


@pytest.mark.parametrize("with_scale", [False, True])
def test_ate_matches_evo_when_installed(with_scale: bool) -> None:
    evo_main_ape = pytest.importorskip("evo.main_ape")
    from evo.core.metrics import PoseRelation
    from evo.core.trajectory import PoseTrajectory3D

    rng = np.random.default_rng(19)
    ref = _trajectory(rng)
    est = _moved(ref, RNG_T, s=1.3 if with_scale else 1.0)
    est[:, :3, 3] += rng.normal(0.0, 0.1, (len(est), 3))
    stamps = np.arange(len(ref), dtype=float)
    result = evo_main_ape.ape(
        PoseTrajectory3D(poses_se3=list(ref), timestamps=stamps),
        PoseTrajectory3D(poses_se3=list(est), timestamps=stamps),
        pose_relation=PoseRelation.translation_part,
        align=True,
        correct_scale=with_scale,
    )
    assert ate_rmse(est, ref, with_scale=with_scale) == pytest.approx(
        result.stats["rmse"], rel=1e-9
    )
