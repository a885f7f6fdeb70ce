"""core/odometry.py: the first-order covariance of composed odometry steps, against a Monte-Carlo
reference (the steps perturbed as the model says, composed, the error's sample covariance)."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from mergesvc.core.odometry import chain_covariance, compose_covariance, step_covariance
from mergesvc.errors import InputError


def _steps(n: int, turn_rad: float = 0.02, step_m: float = 0.5) -> list[np.ndarray]:
    return [gtsam.Pose3(gtsam.Rot3.Yaw(turn_rad), np.array([step_m, 0.0, 0.0])).matrix()
            for _ in range(n)]


def _monte_carlo(steps: list[np.ndarray], Q: np.ndarray, draws: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    L = np.linalg.cholesky(Q)
    T_true = gtsam.Pose3()
    for D in steps:
        T_true = T_true.compose(gtsam.Pose3(D))
    errs = np.empty((draws, 6))
    for d in range(draws):
        T = gtsam.Pose3()
        for D in steps:
            T = T.compose(gtsam.Pose3(D)).compose(gtsam.Pose3.Expmap(L @ rng.standard_normal(6)))
        errs[d] = gtsam.Pose3.Logmap(T_true.between(T))
    return np.cov(errs.T)


def test_composition_matches_monte_carlo() -> None:
    Q = step_covariance((0.004, 0.02))
    steps = _steps(20)
    S = compose_covariance(steps, Q)
    ref = _monte_carlo(steps, Q, 1500, 1)
    scale = np.sqrt(np.outer(np.diag(ref), np.diag(ref)))
    # within sampling noise (1,500 draws: about 4 % on a variance, 5 % of a correlation)
    assert np.abs((S - ref) / scale).max() < 0.12
    # and not a per-axis random walk (n Q): the heading error moves the position sideways
    assert S[4, 4] > 2 * 20 * Q[4, 4]
    assert abs(S[2, 4]) / np.sqrt(S[2, 2] * S[4, 4]) > 0.5  # yaw and lateral correlated


def test_heading_error_grows_sideways_as_n_cubed() -> None:
    """A straight path: yaw noise only; the lateral variance is sigma^2 d^2 sum_i i^2."""
    sigma, d = 0.003, 0.5
    Q = np.diag([1e-12, 1e-12, sigma**2, 1e-12, 1e-12, 1e-12])
    for n in (10, 40):
        S = compose_covariance(_steps(n, turn_rad=0.0, step_m=d), Q)
        expected = sigma**2 * d**2 * sum(i * i for i in range(n))
        assert S[4, 4] == pytest.approx(expected, rel=1e-6)
        assert S[2, 2] == pytest.approx(n * sigma**2, rel=1e-9)


def test_chain_covariance_is_the_steps_between_poses() -> None:
    Q = step_covariance([0.001, 0.002, 0.003, 0.01, 0.02, 0.03])
    steps = _steps(7, turn_rad=0.1)
    poses = [np.eye(4)]
    for D in steps:
        poses.append(poses[-1] @ D)
    T0 = gtsam.Pose3(gtsam.Rot3.Ypr(0.3, 0.1, -0.2), np.array([4.0, -1.0, 2.0])).matrix()
    moved = [T0 @ P for P in poses]  # the frame the chain is written in does not matter
    np.testing.assert_allclose(chain_covariance(moved, Q), compose_covariance(steps, Q),
                               rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(compose_covariance([], Q), np.zeros((6, 6)))


@pytest.mark.parametrize("bad", [(0.0, 0.1), (0.1,), (np.nan, 0.1), [1, 2, 3], (-1.0, 1.0)])
def test_bad_step_sigma_is_refused(bad: object) -> None:
    with pytest.raises(InputError):
        step_covariance(bad)  # type: ignore[arg-type]


def test_a_chain_needs_two_poses() -> None:
    with pytest.raises(InputError):
        chain_covariance([np.eye(4)], step_covariance((0.1, 0.1)))
