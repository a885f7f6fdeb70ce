"""Tests of mergesvc.core.tracking: semantic / position Kalman filters and data-association
gates."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from mergesvc.core.tracking import (
    CHI2_3DOF_99,
    Detection,
    ObjectTracker,
    PositionKalman,
    SemanticKalman,
    TrackingConfig,
    fuse_gaussians,
    fuse_gaussians_full,
    fuse_observations,
)
from mergesvc.errors import ConfigError, InputError

# --------------------------------------------------------------------------------------------
# Dense references
# --------------------------------------------------------------------------------------------


def dense_kf(ys: np.ndarray, rs: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Standard KF with full matrices, H = I, prior from the first observation.

    ys: (n, d); rs: n (d, d) observation covariances. Returns mean (d,), covariance (d, d).
    """
    x = ys[0].copy()
    p = rs[0].copy()
    eye = np.eye(len(x))
    for y, r in zip(ys[1:], rs[1:], strict=True):
        s = eye @ p @ eye.T + r
        k = p @ eye.T @ np.linalg.inv(s)
        x = x + k @ (y - eye @ x)
        p = p - k @ s @ k.T
    return x, p


def dense_product(
    m1: np.ndarray, c1: np.ndarray, m2: np.ndarray, c2: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Product of Gaussians in information form with full matrices."""
    i1, i2 = np.linalg.inv(c1), np.linalg.inv(c2)
    cov = np.linalg.inv(i1 + i2)
    return cov @ (i1 @ m1 + i2 @ m2), cov


def random_spd(rng: np.random.Generator, k: int, scale: float = 1.0) -> np.ndarray:
    a = rng.normal(size=(k, k))
    return scale * (a @ a.T / k + 0.1 * np.eye(k))


# --------------------------------------------------------------------------------------------
# Semantic Kalman
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("d", [1, 3, 16, 64])
@pytest.mark.parametrize("per_dim", [False, True])
def test_diagonal_kalman_matches_dense_reference(d: int, per_dim: bool) -> None:
    rng = np.random.default_rng(100 + d + 1000 * per_dim)
    for _ in range(5):
        n = int(rng.integers(1, 12))
        ys = rng.normal(size=(n, d))
        if per_dim:
            vs: list[Any] = [rng.uniform(0.05, 3.0, size=d) for _ in range(n)]
            rs = [np.diag(v) for v in vs]
        else:
            vs = [float(rng.uniform(0.05, 3.0)) for _ in range(n)]
            rs = [v * np.eye(d) for v in vs]
        kf = SemanticKalman.from_observation(ys[0], vs[0])
        for y, v in zip(ys[1:], vs[1:], strict=True):
            kf.update(y, v)
        ref_x, ref_p = dense_kf(ys, rs)
        assert kf.n_obs == n
        np.testing.assert_allclose(kf.mean_d, ref_x, rtol=0, atol=1e-10)
        np.testing.assert_allclose(kf.variance_d, np.diag(ref_p), rtol=0, atol=1e-10)
        # Off-diagonal of the dense reference stays zero: the diagonal filter loses nothing.
        np.testing.assert_allclose(ref_p - np.diag(np.diag(ref_p)), 0.0, atol=1e-12)
        mean_b, var_b = fuse_observations(ys, np.array(vs))
        np.testing.assert_allclose(mean_b, ref_x, rtol=0, atol=1e-10)
        np.testing.assert_allclose(var_b, np.diag(ref_p), rtol=0, atol=1e-10)


def test_equal_scalar_variance_gives_average_and_s_over_n() -> None:
    rng = np.random.default_rng(1)
    n, d, s = 7, 12, 0.4
    ys = rng.normal(size=(n, d))
    kf = SemanticKalman.from_observation(ys[0], s)
    for y in ys[1:]:
        kf.update(y, s)
    np.testing.assert_allclose(kf.mean_d, ys.mean(axis=0), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(kf.variance_d, np.full(d, s / n), rtol=1e-12)
    mean_b, var_b = fuse_observations(ys, s)
    np.testing.assert_allclose(mean_b, ys.mean(axis=0), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(var_b, np.full(d, s / n), rtol=1e-12)


variances_st = st.floats(min_value=1e-3, max_value=1e3, allow_nan=False, allow_infinity=False)


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(1, 10),
    d=st.integers(1, 8),
    form=st.sampled_from(["scalar", "per_obs", "per_dim"]),
)
def test_batch_equals_sequential_and_is_order_independent(
    seed: int, n: int, d: int, form: str
) -> None:
    rng = np.random.default_rng(seed)
    ys = rng.normal(scale=5.0, size=(n, d))
    if form == "scalar":
        v: Any = float(rng.uniform(1e-2, 10.0))
        rows: list[Any] = [v] * n
    elif form == "per_obs":
        v = rng.uniform(1e-2, 10.0, size=n)
        rows = list(v)
    else:
        v = rng.uniform(1e-2, 10.0, size=(n, d))
        rows = list(v)
    kf = SemanticKalman.from_observation(ys[0], rows[0])
    for y, r in zip(ys[1:], rows[1:], strict=True):
        kf.update(y, r)
    mean_b, var_b = fuse_observations(ys, v)
    np.testing.assert_allclose(mean_b, kf.mean_d, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(var_b, kf.variance_d, rtol=1e-9)

    perm = rng.permutation(n)
    kf2 = SemanticKalman.from_observation(ys[perm[0]], rows[perm[0]])
    for i in perm[1:]:
        kf2.update(ys[i], rows[i])
    np.testing.assert_allclose(kf2.mean_d, kf.mean_d, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(kf2.variance_d, kf.variance_d, rtol=1e-9)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), d=st.integers(1, 10), v1=variances_st, v2=variances_st)
def test_fuse_gaussians_matches_dense_product(seed: int, d: int, v1: float, v2: float) -> None:
    rng = np.random.default_rng(seed)
    m1, m2 = rng.normal(size=d), rng.normal(size=d)
    var1 = v1 * rng.uniform(0.5, 2.0, size=d)
    var2 = v2 * rng.uniform(0.5, 2.0, size=d)
    mean, var = fuse_gaussians(m1, var1, m2, var2)
    ref_m, ref_c = dense_product(m1, np.diag(var1), m2, np.diag(var2))
    np.testing.assert_allclose(mean, ref_m, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(var, np.diag(ref_c), rtol=1e-9)
    # Scalar variances broadcast.
    mean_s, var_s = fuse_gaussians(m1, v1, m2, v2)
    ref_m, ref_c = dense_product(m1, v1 * np.eye(d), m2, v2 * np.eye(d))
    np.testing.assert_allclose(mean_s, ref_m, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(var_s, np.diag(ref_c), rtol=1e-9)


def test_fuse_gaussians_equals_fusing_the_underlying_observations() -> None:
    rng = np.random.default_rng(5)
    ys, vs = rng.normal(size=(6, 4)), rng.uniform(0.1, 2.0, size=(6, 4))
    a = fuse_observations(ys[:2], vs[:2])
    b = fuse_observations(ys[2:], vs[2:])
    whole = fuse_observations(ys, vs)
    merged = fuse_gaussians(a[0], a[1], b[0], b[1])
    np.testing.assert_allclose(merged[0], whole[0], atol=1e-12)
    np.testing.assert_allclose(merged[1], whole[1], rtol=1e-12)


# --------------------------------------------------------------------------------------------
# Position Kalman
# --------------------------------------------------------------------------------------------


def test_position_kalman_matches_dense_reference() -> None:
    rng = np.random.default_rng(7)
    for _ in range(10):
        n = int(rng.integers(1, 8))
        zs = rng.normal(scale=10.0, size=(n, 3))
        rs = [random_spd(rng, 3, scale=float(rng.uniform(0.01, 4.0))) for _ in range(n)]
        kf = PositionKalman.from_observation(zs[0], rs[0])
        for z, r in zip(zs[1:], rs[1:], strict=True):
            kf.update(z, r)
        ref_x, ref_p = dense_kf(zs, rs)
        assert kf.n_obs == n
        np.testing.assert_allclose(kf.position_xyz_m, ref_x, atol=1e-10)
        np.testing.assert_allclose(kf.position_cov_33, ref_p, atol=1e-10)
        np.testing.assert_array_equal(kf.position_cov_33, kf.position_cov_33.T)


def test_fuse_gaussians_full_matches_dense_product() -> None:
    rng = np.random.default_rng(8)
    for k in (1, 3, 5):
        m1, m2 = rng.normal(size=k), rng.normal(size=k)
        c1, c2 = random_spd(rng, k), random_spd(rng, k, 3.0)
        mean, cov = fuse_gaussians_full(m1, c1, m2, c2)
        ref_m, ref_c = dense_product(m1, c1, m2, c2)
        np.testing.assert_allclose(mean, ref_m, atol=1e-10)
        np.testing.assert_allclose(cov, ref_c, atol=1e-10)


# --------------------------------------------------------------------------------------------
# Gates and association
# --------------------------------------------------------------------------------------------

D = 8
E0 = np.eye(D)[0]


def det(
    emb: Any = E0,
    pos: Any = (0.0, 0.0, 0.0),
    t: float = 0.0,
    s: Any = 0.1,
    cov: Any = None,
    truth: str | None = None,
) -> Detection:
    return Detection(
        embedding_d=np.asarray(emb, float),
        uncertainty_s=s,
        position_xyz_m=np.asarray(pos, float),
        position_cov_33=np.eye(3) * 0.25 if cov is None else cov,
        stamp_s=t,
        truth_id=truth,
    )


def rotated(cos: float) -> np.ndarray:
    """Unit vector at the given cosine to E0."""
    v = np.zeros(D)
    v[0], v[1] = cos, np.sqrt(1.0 - cos**2)
    return v


def test_detection_passing_all_gates_associates() -> None:
    tr = ObjectTracker()
    a = tr.observe(det(truth="A"))
    # cos 0.8 >= 0.7; Mahalanobis: 1 m on cov 0.5 I -> 2 <= 11.34; 20 s <= 30 s.
    b = tr.observe(det(emb=rotated(0.8), pos=(1.0, 0.0, 0.0), t=20.0, truth="A"))
    assert a == b == "o0"
    (track,) = tr.tracks
    assert track.n_obs == 2 and track.truth_id == "A"
    assert track.first_seen_s == 0.0 and track.last_seen_s == 20.0


@pytest.mark.parametrize(
    "kwargs",
    [
        {"emb": rotated(0.6)},  # cosine gate fails (0.6 < 0.7)
        {"pos": (2.5, 0.0, 0.0)},  # Mahalanobis gate fails: 6.25 / 0.5 = 12.5 > 11.34
        {"t": 30.5},  # window gate fails
    ],
    ids=["cosine", "mahalanobis", "window"],
)
def test_detection_failing_one_gate_starts_new_track(kwargs: dict[str, Any]) -> None:
    tr = ObjectTracker()
    assert tr.observe(det()) == "o0"
    assert tr.observe(det(**kwargs)) == "o1"
    assert [t.n_obs for t in tr.tracks] == [1, 1]


@pytest.mark.parametrize(
    "kwargs",
    [
        {"emb": rotated(0.75)},
        {"pos": (2.3, 0.0, 0.0)},  # 5.29 / 0.5 = 10.58 <= 11.34
        {"t": 30.0},
        {"t": -29.0},  # out-of-order stamp within the window
    ],
    ids=["cosine", "mahalanobis", "window", "past"],
)
def test_detection_just_inside_each_gate_associates(kwargs: dict[str, Any]) -> None:
    tr = ObjectTracker()
    tr.observe(det())
    assert tr.observe(det(**kwargs)) == "o0"


def test_custom_config_changes_gates() -> None:
    tr = ObjectTracker(TrackingConfig(cos_min=0.5, maha_max=20.0, window_s=100.0))
    tr.observe(det())
    assert tr.observe(det(emb=rotated(0.6), pos=(2.5, 0.0, 0.0), t=90.0)) == "o0"
    tr2 = ObjectTracker({"cos_min": 0.95})
    tr2.observe(det())
    assert tr2.observe(det(emb=rotated(0.9))) == "o1"


def test_window_uses_last_seen() -> None:
    tr = ObjectTracker()
    for t in (0.0, 25.0, 50.0, 75.0):  # each within 30 s of the previous one
        assert tr.observe(det(t=t)) == "o0"
    assert tr.observe(det(t=106.0)) == "o1"


def test_nearest_by_mahalanobis_wins() -> None:
    tr = ObjectTracker(TrackingConfig(maha_max=1e6))
    # Track o0 at x = +2 has a large covariance along x, o1 at y = -1 a small one:
    # Euclidean-nearest is o1, Mahalanobis-nearest is o0.
    # One frame: three tracks (detections of one frame never share a track).
    tr.observe_frame(
        [
            det(pos=(2.0, 0.0, 0.0), cov=np.diag([25.0, 0.1, 0.1])),
            det(pos=(0.0, -1.0, 0.0), cov=np.diag([0.01, 0.01, 0.01])),
            det(pos=(0.0, 5.0, 0.0)),
        ]
    )
    assert len(tr) == 3
    assert tr.observe(det(pos=(0.0, 0.0, 0.0), cov=np.eye(3) * 0.01, t=3.0)) == "o0"


def test_tie_in_mahalanobis_goes_to_highest_cosine() -> None:
    tr = ObjectTracker()
    tr.observe_frame(
        [
            det(emb=rotated(0.9), pos=(1.0, 0.0, 0.0)),
            det(emb=E0, pos=(-1.0, 0.0, 0.0)),
            det(emb=rotated(0.8), pos=(0.0, 1.0, 0.0)),
        ]
    )
    assert tr.observe(det(emb=E0, pos=(0.0, 0.0, 0.0), t=1.0)) == "o1"
    tr = ObjectTracker()
    tr.observe_frame([det(emb=E0, pos=(1.0, 0.0, 0.0)), det(emb=rotated(0.9), pos=(-1, 0, 0))])
    assert tr.observe(det(emb=E0, pos=(0.0, 0.0, 0.0), t=1.0)) == "o0"


def test_frame_never_assigns_two_detections_to_one_track() -> None:
    tr = ObjectTracker()
    tr.observe(det())
    ids = tr.observe_frame([det(pos=(0.5, 0, 0), t=1.0), det(pos=(0.1, 0, 0), t=1.0)])
    assert ids == ["o1", "o0"]  # nearer detection wins, the other starts a track
    assert [t.n_obs for t in tr.tracks] == [2, 1]


def test_frame_assignment_is_joint_not_greedy() -> None:
    tr = ObjectTracker()
    tr.observe_frame([det(pos=(0.0, 0.0, 0.0)), det(pos=(2.0, 0.0, 0.0))])  # o0, o1
    # Detection a gates to both (nearest o0); b gates only to o0. A greedy pass would give o0 to
    # a and a new track to b; the joint assignment associates both.
    a = det(pos=(0.9, 0.0, 0.0), t=1.0)
    b = det(pos=(-1.5, 0.0, 0.0), t=1.0)
    assert tr.observe_frame([a, b]) == ["o1", "o0"]
    assert len(tr) == 2


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_random_frames_have_distinct_track_ids(seed: int) -> None:
    rng = np.random.default_rng(seed)
    tr = ObjectTracker(TrackingConfig(cos_min=0.1, maha_max=50.0))
    total = 0
    for f in range(6):
        n = int(rng.integers(1, 7))
        total += n
        frame = [
            det(
                emb=E0 + 0.3 * rng.normal(size=D),
                pos=rng.normal(scale=1.5, size=3),
                t=float(f),
            )
            for _ in range(n)
        ]
        ids = tr.observe_frame(frame)
        assert len(ids) == n and len(set(ids)) == n
    assert sum(t.n_obs for t in tr.tracks) == total


def test_tracks_are_snapshots() -> None:
    tr = ObjectTracker()
    tr.observe(det())
    snap = tr.tracks[0]
    with pytest.raises(ValueError):
        snap.mean_d[0] = 5.0
    tr.observe(det(t=1.0))
    assert snap.n_obs == 1 and tr.track("o0").n_obs == 2


def test_track_fields_follow_the_filters() -> None:
    tr = ObjectTracker()
    rng = np.random.default_rng(3)
    embs = E0 + 0.05 * rng.normal(size=(4, D))
    us = [0.1, 0.2, 0.05, 0.3]
    poss = 0.1 * rng.normal(size=(4, 3))
    covs = [random_spd(rng, 3, 0.2) for _ in range(4)]
    for i in range(4):
        tr.observe(det(emb=embs[i], s=us[i], pos=poss[i], cov=covs[i], t=float(i)))
    (track,) = tr.tracks
    mean, var = fuse_observations(embs, np.array(us))
    np.testing.assert_allclose(track.mean_d, mean, atol=1e-12)
    np.testing.assert_allclose(track.variance_d, var, rtol=1e-12)
    ref_x, ref_p = dense_kf(poss, covs)
    np.testing.assert_allclose(track.position_xyz_m, ref_x, atol=1e-10)
    np.testing.assert_allclose(track.position_cov_33, ref_p, atol=1e-10)
    assert track.n_obs == 4 and track.truth_id is None


def test_end_to_end_ten_objects() -> None:
    rng = np.random.default_rng(2024)
    n_obj, n_rep, d = 10, 5, 64
    centres = rng.uniform(-25.0, 25.0, size=(n_obj, 3))
    while True:  # keep objects at least 4 m apart
        gaps = np.linalg.norm(centres[:, None] - centres[None], axis=2) + 1e3 * np.eye(n_obj)
        if gaps.min() >= 4.0:
            break
        centres = rng.uniform(-25.0, 25.0, size=(n_obj, 3))
    protos = rng.normal(size=(n_obj, d))
    protos /= np.linalg.norm(protos, axis=1, keepdims=True)
    pos_sigma = 0.3
    obs = [(i, k) for i in range(n_obj) for k in range(n_rep)]
    order = rng.permutation(len(obs))
    # Pack the shuffled observations into frames of up to 4 detections of distinct objects.
    frames: list[list[Detection]] = []
    current: list[Detection] = []
    for step, o in enumerate(order):
        i, _ = obs[o]
        if len(current) == 4 or any(x.truth_id == f"T{i}" for x in current):
            frames.append(current)
            current = []
        s = float(rng.uniform(0.001, 0.004))
        current.append(
            det(
                emb=protos[i] + rng.normal(scale=np.sqrt(s), size=d),
                s=s,
                pos=centres[i] + rng.normal(scale=pos_sigma, size=3),
                cov=np.eye(3) * pos_sigma**2,
                t=0.5 * step,
                truth=f"T{i}",
            )
        )
    frames.append(current)
    tr = ObjectTracker()
    for frame in frames:
        ids = tr.observe_frame(frame)
        assert len(set(ids)) == len(ids)
    tracks = tr.tracks
    assert len(tracks) == n_obj
    assert sorted(t.truth_id for t in tracks) == sorted(f"T{i}" for i in range(n_obj))
    assert all(t.n_obs == n_rep for t in tracks)
    assert all(t.truth_counts == {t.truth_id: n_rep} for t in tracks)
    for t in tracks:
        i = int(t.truth_id[1:])  # type: ignore[index]
        assert np.linalg.norm(t.position_xyz_m - centres[i]) < 4 * pos_sigma
        assert float(t.mean_d @ protos[i]) / np.linalg.norm(t.mean_d) > 0.9


def test_majority_truth_id() -> None:
    tr = ObjectTracker()
    for k, truth in enumerate(["B", "A", "A", None, "B", "A"]):
        tr.observe(det(t=float(k), truth=truth))
    (track,) = tr.tracks
    assert track.truth_id == "A" and track.truth_counts == {"A": 3, "B": 2}
    assert track.n_obs == 6


# --------------------------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------------------------

GOOD: dict[str, Any] = {
    "embedding_d": E0,
    "uncertainty_s": 0.1,
    "position_xyz_m": np.zeros(3),
    "position_cov_33": np.eye(3),
    "stamp_s": 0.0,
}


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("embedding_d", np.zeros(D)),
        ("embedding_d", np.full(D, np.nan)),
        ("embedding_d", np.ones((2, D))),
        ("embedding_d", np.array([])),
        ("embedding_d", "abc"),
        ("uncertainty_s", 0.0),
        ("uncertainty_s", -1.0),
        ("uncertainty_s", np.inf),
        ("uncertainty_s", np.ones(D + 1)),
        ("position_xyz_m", np.zeros(2)),
        ("position_xyz_m", np.array([0.0, np.nan, 0.0])),
        ("position_cov_33", np.eye(2)),
        ("position_cov_33", np.diag([1.0, 1.0, -1.0])),
        ("position_cov_33", np.diag([1.0, 1.0, 0.0])),
        ("position_cov_33", np.array([[1.0, 0.5, 0], [0, 1.0, 0], [0, 0, 1.0]])),
        ("position_cov_33", np.full((3, 3), np.inf)),
        ("stamp_s", np.nan),
        ("stamp_s", np.zeros(2)),
        ("truth_id", 7),
    ],
)
def test_bad_detection_raises_input_error_naming_field(field: str, value: Any) -> None:
    with pytest.raises(InputError, match=field):
        Detection(**{**GOOD, field: value})


def test_dimension_mismatch_with_tracks_raises_and_leaves_tracker_untouched() -> None:
    tr = ObjectTracker()
    tr.observe(Detection(**GOOD))
    bad = Detection(**{**GOOD, "embedding_d": np.ones(D + 2)})
    with pytest.raises(InputError, match="embedding_d"):
        tr.observe_frame([Detection(**GOOD), bad])
    assert len(tr) == 1 and tr.tracks[0].n_obs == 1
    with pytest.raises(InputError, match="detections"):
        tr.observe_frame([GOOD])  # type: ignore[list-item]


def test_bad_filter_inputs_raise_input_error() -> None:
    kf = SemanticKalman.from_observation(np.ones(3), 1.0)
    with pytest.raises(InputError, match="embedding_d"):
        kf.update(np.ones(4), 1.0)
    with pytest.raises(InputError, match="variance"):
        kf.update(np.ones(3), np.array([1.0, 0.0, 1.0]))
    with pytest.raises(InputError, match="variance"):
        SemanticKalman.from_observation(np.ones(3), np.nan)
    with pytest.raises(InputError, match="embeddings_nd"):
        fuse_observations(np.zeros((0, 3)), 1.0)
    with pytest.raises(InputError, match="variances"):
        fuse_observations(np.zeros((2, 3)), np.ones(3))
    with pytest.raises(InputError, match="variances"):
        fuse_observations(np.zeros((2, 3)), np.array([1.0, -1.0]))
    with pytest.raises(InputError, match="mu2"):
        fuse_gaussians(np.ones(3), 1.0, np.ones(2), 1.0)
    with pytest.raises(InputError, match="var2"):
        fuse_gaussians(np.ones(3), 1.0, np.ones(3), 0.0)
    with pytest.raises(InputError, match="cov2"):
        fuse_gaussians_full(np.ones(3), np.eye(3), np.ones(3), -np.eye(3))
    with pytest.raises(InputError, match="position_cov_33"):
        PositionKalman.from_observation(np.zeros(3), np.zeros((3, 3)))
    with pytest.raises(InputError, match="track_id"):
        ObjectTracker().track("o9")


def test_config_validation() -> None:
    cfg = TrackingConfig()
    assert (cfg.cos_min, cfg.maha_max, cfg.window_s) == (0.7, CHI2_3DOF_99, 30.0)
    for bad in ({"cos_min": 0.0}, {"cos_min": 1.5}, {"maha_max": -1.0}, {"window_s": 0.0}):
        with pytest.raises(ValidationError):
            TrackingConfig(**bad)
    with pytest.raises(ValidationError):
        TrackingConfig(gate=3.0)  # type: ignore[call-arg]
    with pytest.raises(ConfigError, match="window_s"):
        ObjectTracker({"window_s": -1.0})
    with pytest.raises(ConfigError):
        ObjectTracker(3.0)  # type: ignore[arg-type]


# --------------------------------------------------------------------------------------------
# The semantic gate relative to recent associations (look-alikes)
# --------------------------------------------------------------------------------------------


def _look_alikes(seed: int = 0, d: int = 64) -> tuple[np.ndarray, np.ndarray, np.random.Generator]:
    """Two instances of one class: cosine ~0.9 to each other, far above any cosine gate."""
    rng = np.random.default_rng(seed)
    c = rng.standard_normal(d)
    a, b = (c + 0.3 * rng.standard_normal(d) for _ in range(2))
    return a / np.linalg.norm(a), b / np.linalg.norm(b), rng


NOISE = 0.02 / 8.0  # a view's deviation from its instance per dimension (d = 64): cos ~0.9998


def _others(tr: ObjectTracker, rng: np.random.Generator, n: int, s: float, t0: float = 0.0,
            views: int = 3) -> None:
    """n other objects, 100 m apart and unlike each other, each seen `views` times."""
    embs = [e / np.linalg.norm(e) for e in rng.standard_normal((n, 64))]
    for v in range(views):
        for k, e in enumerate(embs):
            tr.observe(det(emb=e + NOISE * rng.standard_normal(64), pos=(100.0 * (k + 1), 0, 0),
                           t=t0 + v, s=s))


def _run(config: TrackingConfig, s: float, others: int) -> tuple[list[str], float]:
    """`others` objects seen, then object A 20 times, then B (1 m from A, A out of view), A
    again, B again: the track ids of those last three, and the cosine of B to A."""
    a, b, rng = _look_alikes()
    tr = ObjectTracker(config)
    _others(tr, rng, others, s)
    first = len(tr)
    for k in range(20):
        tr.observe(det(emb=a + NOISE * rng.standard_normal(64), t=3.0 + k, s=s))
    ids = [tr.observe(det(emb=b + NOISE * rng.standard_normal(64), pos=(1.0, 0.0, 0.0), t=23.0,
                          s=s)),
           tr.observe(det(emb=a + NOISE * rng.standard_normal(64), t=24.0, s=s)),
           tr.observe(det(emb=b + NOISE * rng.standard_normal(64), pos=(1.0, 0.0, 0.0), t=25.0,
                          s=s))]
    return [f"+{int(i[1:]) - first}" for i in ids], float(a @ b)  # ids after the others'


def test_a_look_alike_a_metre_away_starts_its_own_track() -> None:
    plain = TrackingConfig(cos_min=0.6, window_s=60.0)
    gated = plain.model_copy(update={"semantic_ratio": 2.2})
    ids, cos_ab = _run(plain, 0.05, 10)
    assert cos_ab > 0.8 and ids == ["+0", "+0", "+0"]  # without it: one track of both objects
    ids, _ = _run(gated, 0.05, 10)
    assert ids == ["+1", "+0", "+1"]  # B its own track; A and B each keep theirs
    # relative: a scale shared by every declared variance does not matter
    assert _run(gated, 5.0, 10)[0] == ids
    # and it refuses nothing before it has seen enough tracks to compare with
    from mergesvc.core.tracking import SEMANTIC_WARMUP

    assert _run(gated, 0.05, SEMANTIC_WARMUP - 2)[0] == ["+0", "+0", "+0"]


def test_an_object_seen_most_does_not_set_the_reference_alone() -> None:
    """One object seen 300 times with identical views (distance 0) fills the window; the
    others' ordinary views still join their tracks (each track has one vote)."""
    rng = np.random.default_rng(5)
    tr = ObjectTracker(TrackingConfig(cos_min=0.6, window_s=1e6, semantic_ratio=2.0))
    _others(tr, rng, 9, 0.05, views=2)
    n = len(tr)
    a = np.eye(64)[3]
    for k in range(300):
        tr.observe(det(emb=a, pos=(-50.0, 0, 0), t=10.0 + k, s=0.05))
    before = len(tr)
    assert before == n + 1
    _others(tr, np.random.default_rng(5), 9, 0.05, t0=400.0, views=1)  # the same 9 objects
    assert len(tr) == before, "an ordinary view of a known object was refused"


def test_the_semantic_gate_against_a_brute_force_reference() -> None:
    """Several detections and tracks in one frame, per-dimension uncertainties: the pairs the
    tracker lets through are those whose every gate a plain loop passes."""
    rng = np.random.default_rng(11)
    cfg = TrackingConfig(cos_min=0.5, window_s=1e6, semantic_ratio=1.5)
    tr = ObjectTracker(cfg)
    base = [np.eye(64)[k] + 0.4 * np.eye(64)[(k + 1) % 64] for k in range(12)]
    for v in range(3):  # 12 objects, 5 m apart, 3 views each (one frame per round)
        tr.observe_frame([det(emb=e + 0.05 * rng.standard_normal(64), pos=(5.0 * k, 0, 0),
                              t=float(v), s=rng.uniform(0.01, 0.1, 64))
                          for k, e in enumerate(base)])
    assert len(tr) == 12
    # a frame: ordinary views of the even objects, look-alikes (half another object) at the odd
    dets = [det(emb=base[k] + (0.6 * base[(k + 5) % 12] if k % 2 else 0.0)
                + 0.05 * rng.standard_normal(64), pos=(5.0 * k + rng.normal(0, 0.5), 0, 0),
                t=5.0, s=rng.uniform(0.01, 0.1, 64)) for k in range(12)]
    ref = tr._semantic_reference()
    assert ref is not None and ref > 0
    cand, ok, _, sem = tr._gate(dets)
    tracks = tr.tracks
    for j, d in enumerate(dets):
        for c, ti in enumerate(cand):
            trk = tracks[ti]
            cos = d.embedding_d @ trk.mean_d / np.linalg.norm(d.embedding_d) / np.linalg.norm(
                trk.mean_d)
            diff = d.position_xyz_m - trk.position_xyz_m
            maha2 = diff @ np.linalg.solve(d.position_cov_33 + trk.position_cov_33, diff)
            dist = np.mean((d.embedding_d - trk.mean_d) ** 2 / (trk.variance_d + d.uncertainty_s))
            others = cos >= cfg.cos_min and maha2 <= cfg.maha_max
            assert ok[j, c] == (others and dist <= cfg.semantic_ratio * ref), (j, c)
            if others:
                assert sem[j, c] == pytest.approx(dist, rel=1e-12)
    passed = np.isfinite(sem)  # the pairs the other gates passed
    assert ok[passed].any() and not ok[passed].all()  # the semantic gate refused some of them


def test_semantic_ratio_must_exceed_one() -> None:
    with pytest.raises(ConfigError, match="semantic_ratio"):
        ObjectTracker({"semantic_ratio": 0.5})
