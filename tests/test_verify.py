from __future__ import annotations

import gtsam
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mergesvc.core.model import RejectReason
from mergesvc.core.verify import fit_rigid, pose_covariance, transform_points


def _pose(rng: np.random.Generator) -> gtsam.Pose3:
    R = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
    return gtsam.Pose3(gtsam.Rot3(R), rng.normal(size=3) * 10)


def test_recovers_transform_and_removes_an_outlier() -> None:
    rng = np.random.default_rng(0)
    T = _pose(rng)
    sub = rng.uniform(-5, 5, size=(8, 3))
    mapped = transform_points(T, sub) + rng.normal(size=(8, 3)) * 0.01
    mapped[3] += [3.0, 0, 0]  # a wrong correspondence
    fit = fit_rigid(sub, mapped, np.full(8, 0.1))
    assert fit.accepted and fit.reason is RejectReason.VERIFIED
    assert fit.inliers.tolist() == [True, True, True, False, True, True, True, True]
    assert T.equals(fit.T_map_submap, 0.05)
    assert fit.covariance_66.shape == (6, 6)
    np.testing.assert_allclose(fit.covariance_66, fit.covariance_66.T)
    assert np.all(np.linalg.eigvalsh(fit.covariance_66) > 0)


def test_rejections() -> None:
    rng = np.random.default_rng(1)
    sub = rng.uniform(-5, 5, size=(2, 3))
    assert fit_rigid(sub, sub, np.ones(2)).reason is RejectReason.TOO_FEW_MATCHES
    line = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0.0]])
    assert fit_rigid(line, line, np.ones(4)).reason is RejectReason.DEGENERATE_GEOMETRY
    pts = rng.uniform(-5, 5, size=(4, 3))
    scrambled = rng.uniform(-5, 5, size=(4, 3))
    fit = fit_rigid(pts, scrambled, np.full(4, 0.01))
    assert fit.reason is RejectReason.RESIDUAL_TOO_LARGE and not fit.accepted


def test_covariance_matches_numerical_least_squares() -> None:
    """Sigma = sigma^2 (J^T J)^-1 with J from finite differences of T.retract(xi) * p."""
    rng = np.random.default_rng(2)
    T = _pose(rng)
    sub = rng.uniform(-5, 5, size=(6, 3))
    sigma = 0.2
    cov = pose_covariance(T, sub, sigma)
    J = np.zeros((3 * len(sub), 6))
    eps = 1e-6
    base = transform_points(T, sub).ravel()
    for k in range(6):
        xi = np.zeros(6)
        xi[k] = eps
        J[:, k] = (transform_points(T.retract(xi), sub).ravel() - base) / eps
    ref = sigma**2 * np.linalg.inv(J.T @ J)
    np.testing.assert_allclose(cov, ref, rtol=1e-4, atol=1e-10)


def test_covariance_is_consistent_with_monte_carlo() -> None:
    """Refitting noisy copies: the spread of the estimates matches the predicted covariance."""
    rng = np.random.default_rng(3)
    T = _pose(rng)
    sub = rng.uniform(-5, 5, size=(10, 3))
    sigma = 0.05
    errs = []
    for _ in range(300):
        noisy = transform_points(T, sub) + rng.normal(size=sub.shape) * sigma
        fit = fit_rigid(sub, noisy, np.full(10, 1.0))
        errs.append(T.localCoordinates(fit.T_map_submap))
    emp = np.cov(np.array(errs).T)
    pred = pose_covariance(T, sub, sigma)
    np.testing.assert_allclose(np.diag(emp), np.diag(pred), rtol=0.3)


@pytest.mark.parametrize("n", [3, 5])
def test_exact_points_give_floor_covariance(n: int) -> None:
    rng = np.random.default_rng(4)
    T = _pose(rng)
    sub = rng.uniform(-5, 5, size=(n, 3))
    fit = fit_rigid(sub, transform_points(T, sub), np.full(n, 0.1), sigma_floor_m=0.01)
    assert fit.accepted
    assert np.all(np.isfinite(fit.covariance_66))


def test_the_4dof_tilt_is_as_uncertain_as_the_verticals() -> None:
    """A gravity-aligned fit does not estimate the tilt: the declared ups set it. Monte Carlo
    with each frame's up off by 2 deg (per axis), 5 points, 5 cm noise: the reported tilt sigma
    is the real spread, and the tilt's NEES (2 dof) averages 2; yaw and translation stay
    honest too (NEES of all six about 6)."""
    from mergesvc.core.verify import fit_about_vertical

    rng = np.random.default_rng(7)
    sig_v, sig_p = np.radians(2.0), 0.05
    T_true = gtsam.Pose3(gtsam.Rot3.Yaw(0.7), np.array([4.0, -2.0, 0.3]))
    sub = rng.uniform([-3, -3, -0.5], [3, 3, 0.5], size=(5, 3))
    z = np.array([0.0, 0.0, 1.0])
    errs, covs = [], []
    for _ in range(800):
        up_s = gtsam.Rot3.Expmap(np.r_[rng.normal(0, sig_v, 2), 0.0]).matrix() @ z
        up_m = gtsam.Rot3.Expmap(np.r_[rng.normal(0, sig_v, 2), 0.0]).matrix() @ z
        q = transform_points(T_true, sub) + rng.normal(0, sig_p, sub.shape)
        fit = fit_about_vertical(sub + rng.normal(0, sig_p, sub.shape), q,
                                 np.full(5, 1.0), up_s, up_m, sig_v)
        assert fit.accepted
        errs.append(gtsam.Pose3.Logmap(T_true.between(fit.T_map_submap)))
        covs.append(fit.covariance_66)
    e, C = np.asarray(errs), np.asarray(covs)
    tilt_real = np.sqrt(np.mean(e[:, :2] ** 2, axis=0))
    tilt_said = np.sqrt(np.mean(C[:, [0, 1], [0, 1]], axis=0))
    np.testing.assert_allclose(tilt_said, tilt_real, rtol=0.2)
    nees_tilt = np.einsum("ni,nij,nj->n", e[:, :2], np.linalg.inv(C[:, :2, :2]), e[:, :2])
    assert 1.6 < nees_tilt.mean() < 2.5
    nees = np.einsum("ni,nij,nj->n", e, np.linalg.inv(C), e)
    assert 4.5 < nees.mean() < 8.0
