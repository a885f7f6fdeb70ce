"""Frames without assumptions: the vertical declared, inferred or unknown; the 4-DoF fit; the
same matches in every axis convention; 2-object submaps."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mergesvc.bench import score_case
from mergesvc.core.config import MatchConfig, match_config
from mergesvc.core.model import RejectReason, Submap
from mergesvc.core.pipeline import match, vertical_relation
from mergesvc.core.verify import align_about_vertical, fit_about_vertical, transform_points
from mergesvc.core.vertical import (
    VerticalSource,
    frame_vertical,
    infer_up_axis,
    relate,
    rotation_between,
)
from mergesvc.sim import Family, Scenario, make_scenario, rotate_world, underwater_run
from mergesvc.wire import decode_message, encode_message

# world (ENU: x east, y north, z up) -> each convention's coordinates
CONVENTIONS = {
    "enu": np.eye(3),
    "camera": np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]),  # y down
    "ned": np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]),  # z down
    "random": Rotation.from_euler("xyz", [37.0, -71.0, 123.0], degrees=True).as_matrix(),
}


def _convert(sc: Scenario, Q_map: np.ndarray, Q_sub: np.ndarray, declare: bool) -> Scenario:
    """A scenario whose map is expressed in convention Q_map and submap in Q_sub, through
    files (`up` declared if asked)."""
    return rotate_world(sc, Q_map, Q_sub, declare_up=declare)


def _answer(out) -> tuple[bool, RejectReason, dict[str, str]]:
    r = out.result
    return r.accepted, r.reason, {m.submap_object: m.map_object for m in r.matches}


# ---------------------------------------------------------------------------- inference


def test_inferred_axis_is_the_vertical_of_a_wide_layout() -> None:
    rng = np.random.default_rng(0)
    xyz = rng.uniform([-100, -30, 0], [100, 30, 3], size=(200, 3))
    for Q in CONVENTIONS.values():
        axis = infer_up_axis(xyz @ Q.T)
        assert axis is not None
        assert abs(float(axis @ (Q @ [0, 0, 1]))) > 0.999


def test_nothing_is_inferred_from_a_round_or_tiny_layout() -> None:
    rng = np.random.default_rng(1)
    assert infer_up_axis(rng.normal(size=(500, 3))) is None  # as tall as wide
    assert infer_up_axis(rng.uniform([-9, -9, 0], [9, 9, 0.1], size=(5, 3))) is None  # 5 objects


def test_declared_beats_inferred_and_relations() -> None:
    sc = make_scenario(Family.KITTI, 0)
    declared = _convert(sc, np.eye(3), np.eye(3), declare=True).map.arrays()
    v = frame_vertical(declared)
    assert v is not None and v.source is VerticalSource.DECLARED
    inferred = frame_vertical(sc.map.arrays())
    assert inferred is not None and inferred.source is VerticalSource.INFERRED
    # a submap too small to show its vertical shares the map's axis, sign included
    rel = relate(inferred, None)
    assert rel is not None and rel.signed and not rel.declared
    assert relate(inferred, None, share=False) is None
    # axes that differ in coordinates (camera vs ENU) relate only up to sign
    cam_q = CONVENTIONS["camera"]
    cam = frame_vertical(_convert(sc, cam_q, cam_q, declare=False).map.arrays())
    rel = relate(inferred, cam)
    assert rel is not None and not rel.signed
    assert relate(None, cam) is None


def test_rotation_between_takes_a_to_b() -> None:
    rng = np.random.default_rng(2)
    for _ in range(50):
        a, b = rng.normal(size=(2, 3))
        a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
        for target in (b, -a, a):
            R = rotation_between(a, target)
            assert np.allclose(R @ a, target, atol=1e-9)
            assert np.allclose(R.T @ R, np.eye(3), atol=1e-9) and np.linalg.det(R) > 0


def test_rotation_between_keeps_its_answers_read_only() -> None:
    a, b = np.array([0.0, 0.0, 1.0]), np.array([0.0, -1.0, 0.0])
    R = rotation_between(a, b)
    assert rotation_between(a.copy(), b.copy()) is R  # kept: the same array again
    assert np.array_equal(R, rotation_between(a + 0.0, [0.0, -1.0, 0.0]))
    with pytest.raises(ValueError):
        R[0, 0] = 2.0  # no caller can change what the next one reads
    assert np.allclose(R @ a, b, atol=1e-12)


# ---------------------------------------------------------------------------- 4-DoF fit


def test_four_dof_fit_recovers_yaw_and_translation_from_two_points() -> None:
    rng = np.random.default_rng(3)
    for _ in range(20):
        up_map = rng.normal(size=3)
        up_map /= np.linalg.norm(up_map)
        R = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
        t = rng.normal(size=3) * 20
        sub = rng.normal(size=(2, 3)) * 5
        mp = sub @ R.T + t
        T = align_about_vertical(sub, mp, R.T @ up_map, up_map)
        assert np.allclose(T.rotation().matrix(), R, atol=1e-9)
        assert np.allclose(transform_points(T, sub), mp, atol=1e-9)


def test_four_dof_fit_matches_a_brute_force_yaw_search() -> None:
    """Least squares over yaw, checked against a 0.01-degree grid on noisy points."""
    rng = np.random.default_rng(4)
    up = np.array([0.0, 0.0, 1.0])
    sub = rng.normal(size=(6, 3)) * 4
    R = Rotation.from_euler("z", 73.0, degrees=True).as_matrix()
    mp = sub @ R.T + [3.0, -2.0, 1.0] + rng.normal(size=(6, 3)) * 0.3

    def cost(theta: float) -> float:
        Rz = Rotation.from_euler("z", theta, degrees=True).as_matrix()
        p = sub @ Rz.T
        return float(((p - p.mean(0)) - (mp - mp.mean(0))).__pow__(2).sum())

    grid = np.arange(0.0, 360.0, 0.01)
    best = grid[np.argmin([cost(x) for x in grid])]
    T = align_about_vertical(sub, mp, up, up)
    yaw = Rotation.from_matrix(T.rotation().matrix()).as_euler("zyx", degrees=True)[0] % 360
    assert abs(yaw - best) < 0.02


def test_four_dof_fit_rejects_a_wrong_vertical_offset_and_a_vertical_pair() -> None:
    up = np.array([0.0, -1.0, 0.0])  # camera axes
    sub = np.array([[0.0, 0.0, 0.0], [4.0, -1.5, 0.0]])  # second one 1.5 m higher
    tol = np.full(2, 0.3)
    good = sub + np.array([10.0, 0.0, 5.0])
    assert fit_about_vertical(sub, good, tol, up, up, np.radians(2)).accepted
    flipped = good.copy()
    flipped[1, 1] += 3.0  # 1.5 m lower instead: same distance in the plane, wrong offset
    assert fit_about_vertical(sub, flipped, tol, up, up, np.radians(2)).reason is (
        RejectReason.RESIDUAL_TOO_LARGE
    )
    above = np.array([[0.0, 0.0, 0.0], [0.05, -3.0, 0.0]])  # one above the other: no yaw
    fit = fit_about_vertical(above, above, tol, up, up, np.radians(2), min_spread_m=0.1)
    assert fit.reason is RejectReason.DEGENERATE_GEOMETRY
    cov = fit_about_vertical(sub, good, tol, up, up, np.radians(2)).covariance_66
    assert cov is not None and np.all(np.linalg.eigvalsh(cov) > 0)


# ---------------------------------------------------------------------------- conventions


@pytest.fixture(scope="module")
def drive_case() -> Scenario:
    return make_scenario(Family.KITTI, 2)


@pytest.mark.parametrize("declare", [False, True])
def test_same_matches_in_every_convention(drive_case: Scenario, declare: bool) -> None:
    base = _answer(match(drive_case.map, drive_case.submap))
    assert base[0] and base[1] is RejectReason.VERIFIED
    for name, Q in CONVENTIONS.items():
        sc = _convert(drive_case, Q, Q, declare)
        out = match(sc.map, sc.submap)
        assert _answer(out) == base, name
        assert score_case(sc, out)["rot_err_deg"] < 3.0, name


@pytest.mark.parametrize(
    ("map_conv", "sub_conv"), [("enu", "camera"), ("camera", "ned"), ("random", "enu")]
)
def test_map_and_submap_in_different_conventions(
    drive_case: Scenario, map_conv: str, sub_conv: str
) -> None:
    """Undeclared: the verticals are inferred from each layout and related up to sign."""
    base = _answer(match(drive_case.map, drive_case.submap))
    sc = _convert(drive_case, CONVENTIONS[map_conv], CONVENTIONS[sub_conv], declare=False)
    out = match(sc.map, sc.submap)
    assert _answer(out) == base
    assert score_case(sc, out)["rot_err_deg"] < 3.0


def test_declared_up_is_used_and_catches_a_flip(drive_case: Scenario) -> None:
    """ENU map, NED submap: declared, the flip between them is known and matches; declared
    wrongly (both 'z up'), the true transform turns up over and is refused as tilted."""
    ned = np.diag([1.0, -1.0, -1.0])
    sc = _convert(drive_case, np.eye(3), ned, declare=True)
    out = match(sc.map, sc.submap)
    assert out.result.accepted and score_case(sc, out)["wrong"] == 0
    wrong = sc.submap.model_copy(update={"up": (0.0, 0.0, 1.0)})
    out = match(sc.map, Submap.model_validate(wrong.model_dump()))
    assert out.result.reason is RejectReason.TILTED


def test_undeclared_same_convention_relates_with_sign(drive_case: Scenario) -> None:
    """Both layouts flat about the same coordinate axis: the sign relation is known, so a flat
    match turned over would be refused; in different conventions only the axis is."""
    rel = vertical_relation(drive_case.submap.arrays(), drive_case.map.arrays(), MatchConfig())
    assert rel is not None and rel.signed and not rel.declared
    sc = _convert(drive_case, np.eye(3), CONVENTIONS["camera"], declare=False)
    rel = vertical_relation(sc.submap.arrays(), sc.map.arrays(), MatchConfig())
    assert rel is not None and not rel.signed


# ---------------------------------------------------------------------------- 2 objects


@pytest.fixture(scope="module")
def pool_pairs() -> list[Scenario]:
    cases: list[Scenario] = []
    for seed in range(2):
        for run in (1, 2, 3):
            cases += underwater_run(run, seed).windows(2, 6)
    return cases


def test_two_object_submaps_are_matched_with_the_vertical(pool_pairs: list[Scenario]) -> None:
    accepted = right = returned = 0
    for sc in pool_pairs:
        out = match(sc.map, sc.submap)
        if out.result.accepted:
            s = score_case(sc, out)
            accepted += 1
            right += int(s["right"])
            returned += int(s["returned"])
            assert out.result.covariance is not None
            assert out.fit is not None and len(out.fit.inliers) == 2
        else:
            assert out.result.reason in {
                RejectReason.AMBIGUOUS, RejectReason.DEGENERATE_GEOMETRY,
                RejectReason.RESIDUAL_TOO_LARGE, RejectReason.TOO_FEW_MATCHES,
            }
    assert accepted >= len(pool_pairs) // 3
    assert right >= 0.95 * returned


def test_two_object_submaps_need_a_vertical(pool_pairs: list[Scenario]) -> None:
    """Without a vertical (inference and sharing off) two matches cannot fix a transform."""
    cfg = match_config(verify={"infer_vertical": False})
    for sc in pool_pairs[:6]:
        out = match(sc.map, sc.submap, cfg)
        assert not out.result.accepted
        assert out.result.reason in {RejectReason.TOO_FEW_MATCHES, RejectReason.AMBIGUOUS}


def test_two_object_path_is_the_same_in_every_convention(pool_pairs: list[Scenario]) -> None:
    for sc in pool_pairs[:8]:
        base = _answer(match(sc.map, sc.submap))
        for Q in CONVENTIONS.values():
            conv = _convert(sc, Q, Q, declare=False)
            assert _answer(match(conv.map, conv.submap)) == base


# ---------------------------------------------------------------------------- files, wire


def test_up_field_validates_and_travels_on_the_wire(drive_case: Scenario) -> None:
    doc = drive_case.submap.model_dump()
    with pytest.raises(ValueError, match="non-zero"):
        Submap.model_validate({**doc, "up": [0.0, 0.0, 0.0]})
    with pytest.raises(ValueError):
        Submap.model_validate({**doc, "up": [0.0, 1.0]})
    sub = Submap.model_validate({**doc, "up": [0.0, -2.0, 0.0]})
    assert np.allclose(sub.arrays().up_xyz, [0.0, -1.0, 0.0])
    for profile in ("full", "f16", "int8"):
        _, back = decode_message(encode_message(sub, profile, "car1", 3))
        assert np.allclose(back.up, (0.0, -1.0, 0.0))
        _, plain = decode_message(encode_message(drive_case.submap, profile, "car1", 3))
        assert plain.up is None
    tilted = Submap.model_validate({**doc, "up": [0.3, -1.0, 0.1]})
    _, back = decode_message(encode_message(tilted, "f16", "car1", 3))
    u = np.asarray(tilted.up) / np.linalg.norm(tilted.up)
    assert np.degrees(np.arccos(np.clip(np.dot(back.up, u), -1, 1))) < 0.5  # int8 codes


def test_a_flat_fit_turned_over_gets_the_four_dof_fit_instead() -> None:
    """Three matches nearly on a line: the noise picks the roll about that line; a fit that
    turns the vertical over is refitted about the known vertical and kept when it fits."""
    from mergesvc.core.pipeline import _upright
    from mergesvc.core.verify import fit_rigid
    from mergesvc.core.vertical import VerticalRelation

    up = np.array([0.0, 0.0, 1.0])
    sub = np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [10.0, 0.6, 0.0]])
    mp = sub * [1.0, -1.0, 1.0]  # the small offset seen on the other side: a mirror image
    tol = np.full(3, 0.5)
    six = fit_rigid(sub, mp, tol)
    assert six.accepted
    rel = VerticalRelation(up, up, signed=True, declared=False)
    assert rel.tilt_deg(six.T_map_submap.rotation().matrix()) > 170.0
    cfg = MatchConfig()
    out = _upright(six, sub, mp, tol, rel, 0.2, cfg)
    assert out.accepted and rel.tilt_deg(out.T_map_submap.rotation().matrix()) < 1e-6
    # declared both and the 4-DoF fit cannot fit it: tilted
    far = mp + np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, -4.0, 0.0]])
    six = fit_rigid(sub, far, np.full(3, 5.0))
    declared = VerticalRelation(up, up, signed=True, declared=True)
    assert _upright(six, sub, far, tol, declared, 0.2, cfg).reason is RejectReason.TILTED
    # no vertical: no test
    assert _upright(six, sub, far, tol, None, 0.2, cfg) is six


def test_a_narrow_strip_infers_no_vertical() -> None:
    """A row of objects along a kerb: thinner sideways than tall, so its least spread is not
    the vertical and nothing may be inferred."""
    rng = np.random.default_rng(7)
    xyz = rng.uniform([-50.0, -0.5, 0.0], [50.0, 0.5, 4.0], size=(40, 3))
    assert infer_up_axis(xyz) is None


def test_yaw_fit_about_a_tilted_vertical_matches_brute_force() -> None:
    """The 4-DoF fit with verticals off every axis: a grid search over the yaw about up_map
    (after taking up_sub onto up_map) finds no lower cost."""
    rng = np.random.default_rng(8)
    for _ in range(5):
        up_map = rng.normal(size=3)
        up_map /= np.linalg.norm(up_map)
        up_sub = rng.normal(size=3)
        up_sub /= np.linalg.norm(up_sub)
        sub = rng.normal(size=(5, 3)) * 4
        mp = rng.normal(size=(5, 3)) * 4
        T = align_about_vertical(sub, mp, up_sub, up_map)
        assert np.allclose(T.rotation().matrix() @ up_sub, up_map, atol=1e-9)
        R0 = rotation_between(up_sub, up_map)

        def cost(theta: float, up_map=up_map, R0=R0, sub=sub, mp=mp) -> float:
            R = Rotation.from_rotvec(theta * up_map).as_matrix() @ R0
            p = sub @ R.T
            return float((((p - p.mean(0)) - (mp - mp.mean(0))) ** 2).sum())

        best = min(cost(x) for x in np.radians(np.arange(0.0, 360.0, 0.05)))
        p = transform_points(T, sub)
        assert float((((p - p.mean(0)) - (mp - mp.mean(0))) ** 2).sum()) <= best + 1e-9


def test_four_dof_covariance_puts_the_gravity_prior_on_the_tilts() -> None:
    """Matches on a horizontal line leave the roll about that line to the prior alone: its
    variance is the prior's on both frames' verticals (2 sigma^2); the yaw is fixed by the
    points (GTSAM order: rotation first, in the submap frame)."""
    up = np.array([0.0, 0.0, 1.0])
    sub = np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [10.0, 0.0, 0.0], [15.0, 0.0, 0.0]])
    R = Rotation.from_euler("z", 40.0, degrees=True).as_matrix()
    mp = sub @ R.T + [1.0, 2.0, 3.0]
    sigma_g = np.radians(2.0)
    fit = fit_about_vertical(sub, mp, np.full(4, 0.3), up, up, sigma_g, sigma_floor_m=0.05)
    assert fit.accepted
    C = fit.covariance_66
    assert np.isclose(C[0, 0], 2 * sigma_g**2, rtol=1e-6)  # roll about the line (x): prior only
    assert C[2, 2] < 0.1 * sigma_g**2  # yaw (z): the points fix it


def test_small_submaps_in_another_convention(pool_pairs: list[Scenario]) -> None:
    """ENU map, small submaps in NED or camera axes. Declared, no accepted transform is turned
    over (the truth here carries the run's odometry drift, tens of degrees of yaw); undeclared,
    the shared vertical is wrong for them (the README says to declare `up`), yet the
    correspondences accepted stay right."""
    right = wrong = 0
    for sc in pool_pairs[:10]:
        for name in ("ned", "camera"):
            for declare in (True, False):
                conv = _convert(sc, CONVENTIONS["enu"], CONVENTIONS[name], declare=declare)
                out = match(conv.map, conv.submap)
                if not out.result.accepted:
                    continue
                s = score_case(conv, out)
                right, wrong = right + int(s["right"]), wrong + int(s["wrong"])
                if declare:
                    assert s["rot_err_deg"] < 90.0, name
    assert right > 0 and wrong <= 0.05 * (right + wrong)


def test_an_outlier_that_leaves_two_consistent_pairs_still_fits_about_the_vertical() -> None:
    """3 proposed matches of a 3-object submap, one 50 m off: the two consistent ones fix a
    4-DoF transform (the wrong one is an outlier), where a 6-DoF fit has too few."""
    from mergesvc.core.model import ObjectArrays
    from mergesvc.core.pipeline import _fit

    def arrays(xyz: np.ndarray, up: np.ndarray | None) -> ObjectArrays:
        n = len(xyz)
        return ObjectArrays([f"o{i}" for i in range(n)], xyz, np.ones((n, 4)), np.ones((n, 4)),
                            np.ones(n, dtype=np.int64), up)

    up = np.array([0.0, 0.0, 1.0])
    sub_xyz = np.array([[0.0, 0.0, 0.0], [4.0, 1.0, 0.5], [2.0, 6.0, 1.0]])
    Rz = Rotation.from_euler("z", 30.0, degrees=True).as_matrix()
    map_xyz = sub_xyz @ Rz.T + [10.0, 0.0, 0.0]
    map_xyz[2] += [50.0, 0.0, 0.0]
    sub, map_ = arrays(sub_xyz, up), arrays(map_xyz, up)
    rel = vertical_relation(sub, map_, MatchConfig())
    assert rel is not None and rel.declared
    fit = _fit(sub, map_, np.arange(3), 0.2, MatchConfig(), rel)
    assert fit.accepted and list(fit.inliers) == [True, True, False]
    assert np.allclose(fit.T_map_submap.rotation().matrix(), Rz, atol=1e-6)


@pytest.mark.parametrize("seed", range(6))
def test_gravity_aligned_fit_keeps_declared_up_and_is_not_worse(seed: int) -> None:
    """Both verticals declared (an IMU) and `verify.gravity_aligned`: the transform turns the
    submap's up onto the map's (within the tilt prior), the matches are the same, and the
    rotation error against the truth is no worse than the 6-DoF fit's by more than noise."""
    sc = make_scenario(Family.UNDERWATER, seed)
    ned = np.diag([1.0, -1.0, -1.0])
    conv = _convert(sc, np.eye(3), ned, declare=True)
    six = match(conv.map, conv.submap, _verify_config(gravity_aligned=False))
    four = match(conv.map, conv.submap, _verify_config(gravity_aligned=True))
    if not six.result.accepted:
        return
    assert four.result.accepted
    q = four.result.transform.quaternion_wxyz
    R = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()
    up_map, up_sub = np.asarray(conv.map.up), np.asarray(conv.submap.up)
    tilt = np.degrees(np.arccos(np.clip(up_map @ (R @ up_sub), -1.0, 1.0)))
    assert tilt < 0.5
    assert score_case(conv, four)["wrong"] == 0
    assert score_case(conv, four)["rot_err_deg"] <= score_case(conv, six)["rot_err_deg"] + 1.0


def _verify_config(**verify: object) -> MatchConfig:
    return MatchConfig.model_validate({"verify": verify})
