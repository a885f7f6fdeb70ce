"""core/factors.py local_fit: a factor fitted on objects placed by odometry around the anchoring
keyframe. Its covariance against a Monte-Carlo reference (the objects' noise and the
placements' drawn as the model says, the fit redone, the spread of its error)."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from mergesvc.core.factors import local_fit


def _scene(seed: int, vertical: bool):
    rng = np.random.default_rng(seed)
    T_true = gtsam.Pose3(gtsam.Rot3.Yaw(0.4) if vertical else gtsam.Rot3.Ypr(0.4, 0.05, -0.03),
                         np.array([3.0, -2.0, 0.5]))
    kfs = [7, 7, 7, 9, 9, 12, 12, 12]
    placements_true = {7: gtsam.Pose3(),
                       9: gtsam.Pose3(gtsam.Rot3.Yaw(0.2), np.array([2.0, 0.5, 0])),
                       12: gtsam.Pose3(gtsam.Rot3.Yaw(0.5), np.array([4.0, 1.5, 0.1]))}
    S = {7: np.zeros((6, 6)), 9: np.diag([1e-6, 1e-6, 4e-4, 1e-4, 1e-4, 1e-6]),
         12: np.diag([2e-6, 2e-6, 1e-3, 4e-4, 4e-4, 2e-6])}
    world = rng.uniform([-4, -4, -1], [6, 6, 1], size=(len(kfs), 3))  # in Ka's frame
    sub = np.array([T_true.transformTo(x) for x in world])
    body = np.array([placements_true[g].transformTo(x) for x, g in zip(world, kfs)])
    return T_true, kfs, placements_true, S, sub, body


@pytest.mark.parametrize("vertical", [True, False])
def test_covariance_against_monte_carlo(vertical: bool) -> None:
    T_true, kfs, P, S, sub, body = _scene(1, vertical)
    up = np.array([0.0, 0.0, 1.0]) if vertical else None
    sigma = 0.05
    rng = np.random.default_rng(2)
    errs, covs = [], []
    for _ in range(400):
        placed = {}
        for g, T in P.items():
            eta = rng.multivariate_normal(np.zeros(6), S[g]) if S[g].any() else np.zeros(6)
            placed[g] = (T.compose(gtsam.Pose3.Expmap(eta)), S[g])
        out = local_fit(sub + rng.normal(0, sigma, sub.shape),
                        body + rng.normal(0, sigma, body.shape), kfs, placed,
                        up_sub=up, up_map=up, vertical_sigma_rad=1e-4, range_weighted=False)
        assert out is not None
        errs.append(gtsam.Pose3.Logmap(T_true.between(out[0])))
        covs.append(out[1])
    e = np.asarray(errs)
    C_mc = np.cov(e.T)
    C_model = np.mean(covs, axis=0)
    axes = [2, 3, 4, 5] if vertical else range(6)  # the 4-DoF fit does not move the tilt
    for a in axes:
        # the model's sigma against the spread of 400 fits (about 4 % sampling noise): honest,
        # or conservative by the part of the placements' error the residuals show already and
        # by the placement weighting (the covariance is the fit weighed by noise alone's)
        ratio = np.sqrt(C_model[a, a] / C_mc[a, a])
        assert 0.85 < ratio < 1.35, (a, ratio)
    # the placements matter: without them the yaw sigma would be far too small
    no_drift = local_fit(sub, body, kfs, {g: (T, np.zeros((6, 6))) for g, T in P.items()},
                         up_sub=up, up_map=up, vertical_sigma_rad=1e-4, sigma_floor_m=sigma,
                         range_weighted=False)
    assert no_drift is not None and no_drift[1][2, 2] < 0.5 * C_mc[2, 2]


def test_exact_points_give_the_transform_and_far_objects_weigh_less() -> None:
    T_true, kfs, P, S, sub, body = _scene(3, True)
    placed = {g: (T, S[g]) for g, T in P.items()}
    up = np.array([0.0, 0.0, 1.0])
    for weighted in (False, True):
        T, _ = local_fit(sub, body, kfs, placed, up_sub=up, up_map=up,
                         range_weighted=weighted)
        assert T.equals(T_true, 1e-9)
    # one far object with a gross error: the weighted fit is pulled less
    far = np.array([40.0, 0.0, 0.0])
    sub2 = np.vstack([sub, T_true.transformTo(far) + np.array([0.0, 3.0, 0.0])])
    body2 = np.vstack([body, far])
    errs = []
    for weighted in (False, True):
        T, _ = local_fit(sub2, body2, [*kfs, 7], placed, up_sub=up, up_map=up,
                         range_weighted=weighted)
        errs.append(np.linalg.norm(gtsam.Pose3.Logmap(T_true.between(T))))
    assert errs[1] < 0.7 * errs[0]


def test_what_cannot_be_fitted() -> None:
    _, kfs, P, S, sub, body = _scene(4, False)
    placed = {g: (T, S[g]) for g, T in P.items()}
    assert local_fit(sub[:2], body[:2], kfs[:2], placed) is None  # 6-DoF needs 3
    assert local_fit(sub, body, [99] * len(kfs), placed) is None  # a keyframe not placed
    line = np.outer(np.arange(4.0), [1.0, 0.0, 0.0])
    assert local_fit(line, line, [7] * 4, placed) is None  # on a line
    up = np.array([0.0, 0.0, 1.0])
    above = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    assert local_fit(above, above, [7, 7], placed, up_sub=up, up_map=up) is None


@pytest.mark.parametrize("vertical", [True, False])
def test_objects_placed_by_an_uncertain_chain_weigh_less(vertical: bool) -> None:
    """Three objects of keyframe 12, placed by a chain whose heading is known to 3 degrees,
    among five of Ka itself: weighed by their placement too, the fit's yaw spreads less than
    weighed by their own noise alone, and its covariance does not understate that spread."""
    T_true, _, P, _, _, _ = _scene(5, vertical)
    rng = np.random.default_rng(6)
    kfs = [7] * 5 + [12] * 3
    world = rng.uniform([-4, -4, -1], [6, 6, 1], size=(len(kfs), 3))
    sub = np.array([T_true.transformTo(x) for x in world])
    body = np.array([P[g].transformTo(x) for x, g in zip(world, kfs)])
    S = {7: np.zeros((6, 6)), 12: np.diag([1e-6, 1e-6, np.radians(3.0) ** 2, 1e-4, 1e-4, 1e-6])}
    up = np.array([0.0, 0.0, 1.0]) if vertical else None
    yaw: dict[bool, list[float]] = {True: [], False: []}
    model: dict[bool, list[float]] = {True: [], False: []}
    for _ in range(300):
        eta = rng.multivariate_normal(np.zeros(6), S[12])
        placed = {7: (P[7], S[7]), 12: (P[12].compose(gtsam.Pose3.Expmap(eta)), S[12])}
        s_noisy = sub + rng.normal(0, 0.05, sub.shape)
        for weighted in (True, False):
            out = local_fit(s_noisy, body, kfs, placed, up_sub=up, up_map=up,
                            vertical_sigma_rad=1e-4, range_weighted=False,
                            placement_weighted=weighted)
            assert out is not None
            yaw[weighted].append(gtsam.Pose3.Logmap(T_true.between(out[0]))[2])
            model[weighted].append(out[1][2, 2])
    spread = {w: float(np.std(v)) for w, v in yaw.items()}
    assert spread[True] < 0.8 * spread[False], spread
    # the covariance is the fit weighed by noise alone's: honest for it, conservative for the
    # placement-weighted fit (measured 1.1x and 1.9x their spreads in yaw)
    ratio = {w: float(np.sqrt(np.mean(model[w])) / spread[w]) for w in (True, False)}
    assert 0.8 < ratio[False] < 1.5 and 1.0 < ratio[True] < 2.5, ratio


def test_the_verticals_tilt_turns_the_points_about_the_weighted_centroid() -> None:
    """A gravity-aligned fit keeps the weighted centroid in place, so the verticals' error
    (each frame's up off by vertical_sigma_rad) moves the translation by the tilt times the
    lever arm from that centroid, not from the plain mean: here five near objects and four
    25 m away, weighed less by their range. The covariance's tilt part (with the prior less
    without it) against the fit's own response to tilted ups (central differences)."""
    rng = np.random.default_rng(7)
    T_true = gtsam.Pose3(gtsam.Rot3.Yaw(0.4), np.array([3.0, -2.0, 0.5]))
    world = np.vstack([rng.uniform([-2, -2, -1], [2, 2, 1], size=(5, 3)),
                       rng.uniform([23, -2, -1], [27, 2, 1], size=(4, 3))])
    sub = np.array([T_true.transformTo(x) for x in world])
    placed = {7: (gtsam.Pose3(), np.zeros((6, 6)))}
    up, v = np.array([0.0, 0.0, 1.0]), 0.01

    def fit(u_sub: np.ndarray, u_map: np.ndarray, sigma: float) -> tuple[gtsam.Pose3, np.ndarray]:
        out = local_fit(sub, world, [7] * len(world), placed, up_sub=u_sub, up_map=u_map,
                        vertical_sigma_rad=sigma, sigma_floor_m=1e-3)
        assert out is not None
        return out

    C = fit(up, up, v)[1]
    tilt_model = C - fit(up, up, 0.0)[1]
    h, cols = 1e-6, []
    for side in (0, 1):
        for axis in (0, 1):
            d = np.zeros(3)
            d[axis] = h
            turned = [up, up]
            turned[side] = gtsam.Rot3.Expmap(d).matrix() @ up
            plus = fit(turned[0], turned[1], v)[0]
            turned[side] = gtsam.Rot3.Expmap(-d).matrix() @ up
            minus = fit(turned[0], turned[1], v)[0]
            cols.append(gtsam.Pose3.Logmap(minus.between(plus)) / (2 * h))
    J = np.array(cols).T  # (6, 4): the fit's response to each frame's two tilts
    tilt_fit = v**2 * J @ J.T
    # the vertical translation and its covariance with the tilts: the lever arm's effect (the
    # horizontal parts move by the lever arm's small vertical extent, left to the model's
    # first order)
    idx = [0, 1, 5]
    np.testing.assert_allclose(tilt_model[idx, 5], tilt_fit[idx, 5], rtol=0.02)
