"""Tracking stage: per-object semantic Kalman filter (Singh & Leonard, diagonal: S_i = Sigma_post +
Sigma_i, K_i = Sigma_post S_i^-1, mu += K_i (y_i - mu), Sigma_post -= K_i S_i K_i^T), a 3-D position
Kalman filter, and the local-map data-association gates (cosine, Mahalanobis, time window, and
optionally a semantic distance relative to the tracker's recent associations)."""

from __future__ import annotations

import logging
from collections import Counter, deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from scipy.optimize import linear_sum_assignment

from mergesvc.errors import ConfigError, InputError

log = logging.getLogger(__name__)

#: Default squared-Mahalanobis gate: chi-square, 3 degrees of freedom, 99 %.
CHI2_3DOF_99 = 11.34

# Relative tolerance for the symmetry check of covariance matrices.
_SYM_RTOL = 1e-9
# Norms below this are treated as zero (cosine undefined).
_TINY_NORM = 1e-300
# Weight of the cosine tie-break in the assignment cost (squared-Mahalanobis units): pairs whose
# squared Mahalanobis distances differ by less than about this are ties, resolved by cosine.
_COS_TIE_WEIGHT = 1e-9
SEMANTIC_WINDOW = 256  # latest associations the semantic gate's reference is read from
SEMANTIC_WARMUP = 8  # tracks among them it needs before it refuses any


# --------------------------------------------------------------------------------------------
# Input validation helpers
# --------------------------------------------------------------------------------------------


def _as_float_array(value: Any, name: str) -> np.ndarray:
    """Convert to a float64 array (copy) or raise InputError naming the field."""
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be numeric: {exc}") from exc
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name} has non-finite values")
    return arr


def _check_embedding(value: Any, name: str, dim: int | None = None) -> np.ndarray:
    """Validate an embedding: finite, shape (d,), d >= 1, and d == dim when dim is given."""
    arr = _as_float_array(value, name)
    if arr.ndim != 1 or arr.shape[0] == 0:
        raise InputError(f"{name} must have shape (d,) with d >= 1, got {arr.shape}")
    if dim is not None and arr.shape[0] != dim:
        raise InputError(f"{name} has dimension {arr.shape[0]}, expected {dim}")
    return arr


def _check_variance(value: Any, name: str, dim: int) -> np.ndarray:
    """Validate a scalar or (d,) variance, > 0 and finite; returns it broadcast to (d,)."""
    arr = _as_float_array(value, name)
    if arr.ndim == 0:
        arr = np.full(dim, float(arr))
    elif arr.shape != (dim,):
        raise InputError(f"{name} must be a scalar or have shape ({dim},), got {arr.shape}")
    if not np.all(arr > 0.0):
        raise InputError(f"{name} must be > 0")
    return arr


def _check_cov(value: Any, name: str, dim: int) -> np.ndarray:
    """Validate a (dim, dim) covariance: finite, symmetric, positive definite; symmetrised copy."""
    arr = _as_float_array(value, name)
    if arr.shape != (dim, dim):
        raise InputError(f"{name} must have shape ({dim}, {dim}), got {arr.shape}")
    scale = max(1.0, float(np.max(np.abs(arr))))
    if not np.all(np.abs(arr - arr.T) <= _SYM_RTOL * scale):
        raise InputError(f"{name} is not symmetric")
    arr = 0.5 * (arr + arr.T)
    try:
        np.linalg.cholesky(arr)
    except np.linalg.LinAlgError:
        raise InputError(f"{name} is not positive definite") from None
    return arr


def _check_position(value: Any, name: str) -> np.ndarray:
    arr = _as_float_array(value, name)
    if arr.shape != (3,):
        raise InputError(f"{name} must have shape (3,), got {arr.shape}")
    return arr


def _frozen(arr: np.ndarray) -> np.ndarray:
    arr.flags.writeable = False
    return arr


# --------------------------------------------------------------------------------------------
# Semantic Kalman filter (diagonal)
# --------------------------------------------------------------------------------------------


@dataclass
class SemanticKalman:
    """Diagonal Kalman filter on one object's embedding (the paper's semantic uncertainty tracking).

    mean_d: (d,) posterior mean mu; variance_d: (d,) diagonal of Sigma_post; n_obs: observations.
    The state is static (no process noise); the observation model is y_i = x + v_i, H = I.
    """

    mean_d: np.ndarray
    variance_d: np.ndarray
    n_obs: int = 1

    @classmethod
    def from_observation(cls, embedding_d: Any, variance: Any) -> SemanticKalman:
        """Prior from the first observation: mu = y_1, Sigma_post = Sigma_1.

        embedding_d: (d,); variance: scalar s (Sigma_1 = s I) or (d,) diagonal.
        """
        y = _check_embedding(embedding_d, "embedding_d")
        var = _check_variance(variance, "variance", y.shape[0])
        return cls(mean_d=y, variance_d=var, n_obs=1)

    @property
    def dim(self) -> int:
        return int(self.mean_d.shape[0])

    def update(self, embedding_d: Any, variance: Any) -> SemanticKalman:
        """Fold in one observation y_i ~ N(x, Sigma_i), in place; returns self.

        embedding_d: (d,); variance: scalar s (Sigma_i = s I) or (d,) diagonal of Sigma_i.
        """
        y = _check_embedding(embedding_d, "embedding_d", self.dim)
        var = _check_variance(variance, "variance", self.dim)
        self._update(y, var)
        return self

    def _update(self, y: np.ndarray, var: np.ndarray) -> None:
        """Element-wise KF update on validated (d,) arrays, O(d)."""
        p = self.variance_d
        s = p + var  # S_i = Sigma_post + Sigma_i
        k = p / s  # K_i = Sigma_post S_i^-1
        self.mean_d = self.mean_d + k * (y - self.mean_d)  # mu += K_i (y_i - mu)
        # Sigma_post -= K_i S_i K_i^T  ==  (1 - K_i) Sigma_post  ==  Sigma_post Sigma_i / S_i;
        # the last form is used because it has no cancellation.
        self.variance_d = p * var / s
        self.n_obs += 1


def fuse_observations(embeddings_nd: Any, variances: Any) -> tuple[np.ndarray, np.ndarray]:
    """Fold n observations of one object into (mean_d, variance_d), vectorised.

    embeddings_nd: (n, d), n >= 1; variances: scalar s, (n,) per-observation scalars, or (n, d).
    Equals SemanticKalman.from_observation(y_1, .) followed by update(y_i, .) for i = 2..n: with
    the prior taken from the first observation and a static state, the sequential filter is the
    information-form sum  Sigma^-1 = sum_i Sigma_i^-1,  mu = Sigma sum_i Sigma_i^-1 y_i,
    so the result does not depend on the order of the observations.
    Returns mean_d (d,), variance_d (d,).
    """
    y = _as_float_array(embeddings_nd, "embeddings_nd")
    if y.ndim != 2 or y.shape[0] == 0 or y.shape[1] == 0:
        raise InputError(f"embeddings_nd must have shape (n, d) with n, d >= 1, got {y.shape}")
    n, d = y.shape
    v = _as_float_array(variances, "variances")
    if v.ndim == 0:
        v = np.full((n, d), float(v))
    elif v.shape == (n,):
        v = np.repeat(v[:, None], d, axis=1)
    elif v.shape != (n, d):
        raise InputError(f"variances must be a scalar, ({n},) or ({n}, {d}), got {v.shape}")
    if not np.all(v > 0.0):
        raise InputError("variances must be > 0")
    info = 1.0 / v  # Sigma_i^-1, (n, d)
    precision = info.sum(axis=0)  # (d,)
    # Weighted mean relative to the first observation (reduces cancellation for large offsets).
    mean = y[0] + (info * (y - y[0])).sum(axis=0) / precision
    return mean, 1.0 / precision


def fuse_gaussians(mu1: Any, var1: Any, mu2: Any, var2: Any) -> tuple[np.ndarray, np.ndarray]:
    """Product of two independent diagonal Gaussian estimates of the same object.

    mu1, mu2: (d,); var1, var2: scalar or (d,) diagonal variances.
    var = var1 var2 / (var1 + var2),  mu = mu1 + var1 / (var1 + var2) (mu2 - mu1)
    (one KF update of estimate 1 with estimate 2 as the observation).
    Returns mean_d (d,), variance_d (d,).
    """
    m1 = _check_embedding(mu1, "mu1")
    m2 = _check_embedding(mu2, "mu2", m1.shape[0])
    v1 = _check_variance(var1, "var1", m1.shape[0])
    v2 = _check_variance(var2, "var2", m1.shape[0])
    s = v1 + v2
    return m1 + (v1 / s) * (m2 - m1), v1 * v2 / s


def fuse_gaussians_full(mu1: Any, cov1: Any, mu2: Any, cov2: Any) -> tuple[np.ndarray, np.ndarray]:
    """Product of two independent Gaussian estimates with full covariances.

    mu1, mu2: (k,); cov1, cov2: (k, k) symmetric positive definite.
    K = cov1 (cov1 + cov2)^-1, mu = mu1 + K (mu2 - mu1), cov = (I - K) cov1 (I - K)^T + K cov2 K^T
    (Joseph form, equal to (I - K) cov1 but symmetric and PSD under rounding).
    Returns mean (k,), covariance (k, k).
    """
    m1 = _as_float_array(mu1, "mu1")
    if m1.ndim != 1 or m1.shape[0] == 0:
        raise InputError(f"mu1 must have shape (k,) with k >= 1, got {m1.shape}")
    k = m1.shape[0]
    m2 = _as_float_array(mu2, "mu2")
    if m2.shape != (k,):
        raise InputError(f"mu2 must have shape ({k},), got {m2.shape}")
    return _fuse_full(m1, _check_cov(cov1, "cov1", k), m2, _check_cov(cov2, "cov2", k))


def _fuse_full(
    m1: np.ndarray, p1: np.ndarray, m2: np.ndarray, p2: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Full-covariance KF update (H = I) on validated arrays; see fuse_gaussians_full."""
    s = p1 + p2  # S = P + R
    gain = np.linalg.solve(s, p1).T  # K = P S^-1  (S, P symmetric)
    mean = m1 + gain @ (m2 - m1)
    i_k = np.eye(m1.shape[0]) - gain
    cov = i_k @ p1 @ i_k.T + gain @ p2 @ gain.T  # Joseph form of (I - K) P
    return mean, 0.5 * (cov + cov.T)


# --------------------------------------------------------------------------------------------
# Position Kalman filter (3-D, full covariance)
# --------------------------------------------------------------------------------------------


@dataclass
class PositionKalman:
    """Kalman filter on a static object's 3-D world position, full 3x3 covariance, H = I.

    position_xyz_m: (3,); position_cov_33: (3, 3); n_obs: number of fused detections.
    """

    position_xyz_m: np.ndarray
    position_cov_33: np.ndarray
    n_obs: int = 1

    @classmethod
    def from_observation(cls, position_xyz_m: Any, position_cov_33: Any) -> PositionKalman:
        """Prior from the first detection: x = z_1, P = R_1. position (3,), cov (3, 3)."""
        z = _check_position(position_xyz_m, "position_xyz_m")
        r = _check_cov(position_cov_33, "position_cov_33", 3)
        return cls(position_xyz_m=z, position_cov_33=r, n_obs=1)

    def update(self, position_xyz_m: Any, position_cov_33: Any) -> PositionKalman:
        """Fold in one detection z ~ N(x, R), in place; returns self. z (3,), R (3, 3)."""
        z = _check_position(position_xyz_m, "position_xyz_m")
        r = _check_cov(position_cov_33, "position_cov_33", 3)
        self._update(z, r)
        return self

    def _update(self, z: np.ndarray, r: np.ndarray) -> None:
        self.position_xyz_m, self.position_cov_33 = _fuse_full(
            self.position_xyz_m, self.position_cov_33, z, r
        )
        self.n_obs += 1


# --------------------------------------------------------------------------------------------
# Data association
# --------------------------------------------------------------------------------------------


class TrackingConfig(BaseModel):
    """Data-association gates of the local map (all three must hold to associate)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    cos_min: float = Field(
        default=0.7, gt=0.0, le=1.0, description="minimum cosine of detection vs track mean"
    )
    maha_max: float = Field(
        default=CHI2_3DOF_99,
        gt=0.0,
        description="maximum squared Mahalanobis distance of the position (chi2 3 dof 99 %)",
    )
    window_s: float = Field(
        default=30.0, gt=0.0, description="maximum time since the track was last seen, seconds"
    )
    semantic_ratio: float | None = Field(
        default=None, gt=1.0, description="refuse an association whose semantic distance (the "
        "mean over dimensions of (y - mu)^2 / (track variance + detection variance)) exceeds "
        "this many times the median of the tracker's recent associations (each track's "
        "latest): a look-alike the cosine and position gates let through (two objects of one "
        "class a metre apart). Relative: a scale shared by every detection's declared "
        "variance does not matter. A refused view starts a track of its own. None: off"
    )


@dataclass(frozen=True, eq=False)
class Detection:
    """One object detection in the world frame.

    embedding_d: (d,) semantic embedding y_i; uncertainty_s: image uncertainty s (Sigma_i = s I)
    or a (d,) per-dimension variance; position_xyz_m: (3,) world position; position_cov_33:
    (3, 3) its covariance (symmetric positive definite); stamp_s: time stamp in seconds;
    truth_id: ground-truth object id, bookkeeping only (never used for association).
    Arrays are validated, copied to float64 and made read-only on construction.
    """

    embedding_d: np.ndarray
    uncertainty_s: float | np.ndarray
    position_xyz_m: np.ndarray
    position_cov_33: np.ndarray
    stamp_s: float
    truth_id: str | None = None

    def __post_init__(self) -> None:
        emb = _check_embedding(self.embedding_d, "embedding_d")
        if float(np.linalg.norm(emb)) <= _TINY_NORM:
            raise InputError("embedding_d has zero norm (cosine undefined)")
        unc = _as_float_array(self.uncertainty_s, "uncertainty_s")
        if unc.ndim != 0 and unc.shape != emb.shape:
            raise InputError(
                f"uncertainty_s must be a scalar or have shape {emb.shape}, got {unc.shape}"
            )
        if not np.all(unc > 0.0):
            raise InputError("uncertainty_s must be > 0")
        pos = _check_position(self.position_xyz_m, "position_xyz_m")
        cov = _check_cov(self.position_cov_33, "position_cov_33", 3)
        stamp = _as_float_array(self.stamp_s, "stamp_s")
        if stamp.ndim != 0:
            raise InputError(f"stamp_s must be a scalar, got shape {stamp.shape}")
        if self.truth_id is not None and not isinstance(self.truth_id, str):
            raise InputError(f"truth_id must be a str or None, got {type(self.truth_id).__name__}")
        object.__setattr__(self, "embedding_d", _frozen(emb))
        object.__setattr__(self, "uncertainty_s", float(unc) if unc.ndim == 0 else _frozen(unc))
        object.__setattr__(self, "position_xyz_m", _frozen(pos))
        object.__setattr__(self, "position_cov_33", _frozen(cov))
        object.__setattr__(self, "stamp_s", float(stamp))


@dataclass(frozen=True)
class Frame:
    """One frame of a vehicle: its pose estimate and the detections, in the frame the detections
    were placed (the run's estimated world frame, or the vehicle's own odometry frame).

    T_est / T_true: (4, 4) body poses; body_T_detections: the detections' raw body-frame
    positions are not kept, a vehicle only has them through T_est. up_body: the direction
    opposite to gravity in the body frame, as an IMU / AHRS measures it (None: not measured)."""

    k: int
    stamp_s: float
    T_est: np.ndarray
    T_true: np.ndarray
    detections: list[Detection]
    up_body: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class Track:
    """Read-only snapshot of one tracked object.

    mean_d, variance_d: (d,) semantic Kalman posterior; position_xyz_m (3,), position_cov_33
    (3, 3): position Kalman posterior; truth_id: majority ground-truth id of the associated
    detections (ties: the id seen first; None when no detection carried one).
    """

    track_id: str
    mean_d: np.ndarray
    variance_d: np.ndarray
    n_obs: int
    position_xyz_m: np.ndarray
    position_cov_33: np.ndarray
    first_seen_s: float
    last_seen_s: float
    truth_id: str | None
    truth_counts: Mapping[str, int]


@dataclass
class _TrackState:
    track_id: str
    semantic: SemanticKalman
    position: PositionKalman
    first_seen_s: float
    last_seen_s: float
    truth_counts: Counter[str] = field(default_factory=Counter)

    def add(self, det: Detection) -> None:
        dim = det.embedding_d.shape[0]
        self.semantic._update(
            det.embedding_d, _check_variance(det.uncertainty_s, "uncertainty_s", dim)
        )
        self.position._update(det.position_xyz_m, det.position_cov_33)
        self.first_seen_s = min(self.first_seen_s, det.stamp_s)
        self.last_seen_s = max(self.last_seen_s, det.stamp_s)
        if det.truth_id is not None:
            self.truth_counts[det.truth_id] += 1

    def snapshot(self) -> Track:
        common = self.truth_counts.most_common(1)
        return Track(
            track_id=self.track_id,
            mean_d=_frozen(self.semantic.mean_d.copy()),
            variance_d=_frozen(self.semantic.variance_d.copy()),
            n_obs=self.semantic.n_obs,
            position_xyz_m=_frozen(self.position.position_xyz_m.copy()),
            position_cov_33=_frozen(self.position.position_cov_33.copy()),
            first_seen_s=self.first_seen_s,
            last_seen_s=self.last_seen_s,
            truth_id=common[0][0] if common else None,
            truth_counts=dict(self.truth_counts),
        )


class ObjectTracker:
    """Local-map object tracker: gates, joint (Hungarian) association per frame, per-track filters.

    A detection may join a track only when all gates hold: cosine(y, mu_track) >= cos_min,
    squared Mahalanobis of the position on (P_track + R_det) <= maha_max, and
    |stamp - last_seen| <= window_s; with semantic_ratio, also the semantic distance at most
    that many times `_semantic_reference` (each track's latest among the last SEMANTIC_WINDOW
    associations, their median). Within a frame, detections are assigned jointly so no track
    receives two of them: as many detections as possible are associated to gated tracks, and
    among such assignments the summed squared Mahalanobis distance is minimal (ties by highest
    cosine). Unassigned detections start new tracks with ids "o0", "o1", ... in detection order.
    """

    def __init__(self, config: TrackingConfig | Mapping[str, Any] | None = None) -> None:
        if config is None:
            config = TrackingConfig()
        elif isinstance(config, Mapping):
            try:
                config = TrackingConfig.model_validate(dict(config))
            except ValidationError as exc:
                fields = ", ".join(".".join(map(str, e["loc"])) for e in exc.errors())
                raise ConfigError(f"invalid tracking config ({fields}): {exc}") from exc
        elif not isinstance(config, TrackingConfig):
            raise ConfigError(f"config must be a TrackingConfig, got {type(config).__name__}")
        self.config: TrackingConfig = config
        self._tracks: list[_TrackState] = []
        self._index: dict[str, int] = {}
        self._dim: int | None = None
        self._next_id = 0
        # (track, semantic distance) of the latest associations: semantic_ratio's reference
        self._sem_recent: deque[tuple[int, float]] = deque(maxlen=SEMANTIC_WINDOW)

    @property
    def dim(self) -> int | None:
        """Embedding dimension fixed by the first detection (None before any)."""
        return self._dim

    @property
    def tracks(self) -> tuple[Track, ...]:
        """Snapshots of all tracks, in creation order."""
        return tuple(t.snapshot() for t in self._tracks)

    def track(self, track_id: str) -> Track:
        """Snapshot of one track; InputError when the id is unknown."""
        try:
            return self._tracks[self._index[track_id]].snapshot()
        except KeyError:
            raise InputError(f"track_id {track_id!r} is unknown") from None

    def __len__(self) -> int:
        return len(self._tracks)

    def observe(self, detection: Detection) -> str:
        """Associate one detection (or start a track); returns its track id."""
        return self.observe_frame([detection])[0]

    def observe_frame(self, detections: Sequence[Detection]) -> list[str]:
        """Associate one frame's detections jointly; returns one track id per detection.

        Gating uses the track states before the frame; all detections are validated before any
        track changes, so a bad frame leaves the tracker untouched.
        """
        dets = list(detections)
        if not dets:
            return []
        dim = self._dim
        for j, det in enumerate(dets):
            if not isinstance(det, Detection):
                raise InputError(f"detections[{j}] must be a Detection, got {type(det).__name__}")
            if dim is None:
                dim = det.embedding_d.shape[0]
            elif det.embedding_d.shape[0] != dim:
                raise InputError(
                    f"detections[{j}].embedding_d has dimension {det.embedding_d.shape[0]}, "
                    f"expected {dim}"
                )
        self._dim = dim

        assigned = self._associate(dets)
        ids: list[str] = []
        for j, det in enumerate(dets):
            t = assigned.get(j)
            if t is None:
                ids.append(self._new_track(det))
            else:
                self._tracks[t].add(det)
                ids.append(self._tracks[t].track_id)
        return ids

    # -- internals ------------------------------------------------------------------------------

    def _gate(self, dets: list[Detection]
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Gated pairs of the frame.

        Returns cand (c,) indices of tracks passing the time gate, ok (n, c) bool all-gates mask,
        cost (n, c) float: squared Mahalanobis + cosine tie-break, valid where ok, and sem
        (n, c): the semantic distance of the pairs the other gates passed (NaN elsewhere, and
        everywhere without semantic_ratio).
        """
        cfg = self.config
        n = len(dets)
        stamps = np.array([d.stamp_s for d in dets])
        last = np.array([t.last_seen_s for t in self._tracks])
        in_window = np.abs(stamps[:, None] - last[None, :]) <= cfg.window_s  # (n, T)
        cand = np.flatnonzero(in_window.any(axis=0))
        if cand.size == 0:
            return cand, np.zeros((n, 0), bool), np.zeros((n, 0)), np.zeros((n, 0))
        in_window = in_window[:, cand]

        # Cosine gate: cos(y_j, mu_t) >= cos_min.
        y = np.stack([d.embedding_d for d in dets])  # (n, d)
        mu = np.stack([self._tracks[t].semantic.mean_d for t in cand])  # (c, d)
        mu_norm = np.linalg.norm(mu, axis=1)
        y_unit = y / np.linalg.norm(y, axis=1, keepdims=True)
        cos = (y_unit @ mu.T) / np.maximum(mu_norm, _TINY_NORM)[None, :]  # (n, c)
        cos = np.where(mu_norm[None, :] > _TINY_NORM, cos, -1.0)

        # Mahalanobis gate: (z - x)^T (P + R)^-1 (z - x) <= maha_max.
        z = np.stack([d.position_xyz_m for d in dets])  # (n, 3)
        r = np.stack([d.position_cov_33 for d in dets])  # (n, 3, 3)
        x = np.stack([self._tracks[t].position.position_xyz_m for t in cand])  # (c, 3)
        p = np.stack([self._tracks[t].position.position_cov_33 for t in cand])  # (c, 3, 3)
        diff = z[:, None, :] - x[None, :, :]  # (n, c, 3)
        s = r[:, None, :, :] + p[None, :, :, :]  # (n, c, 3, 3)
        sol = np.linalg.solve(s, diff[..., None])[..., 0]  # (n, c, 3)
        maha2 = np.einsum("nck,nck->nc", diff, sol)

        ok = in_window & (cos >= cfg.cos_min) & (maha2 <= cfg.maha_max)
        sem = np.full(ok.shape, np.nan)
        if cfg.semantic_ratio is not None and ok.any():
            # the semantic distance of the pairs the other gates passed
            j, t = np.nonzero(ok)
            var = np.stack([self._tracks[cand[i]].semantic.variance_d for i in t])
            s_det = np.stack([np.broadcast_to(np.asarray(dets[i].uncertainty_s,
                                                         dtype=np.float64), y.shape[1:])
                              for i in j])
            sem[j, t] = np.mean((y[j] - mu[t]) ** 2 / (var + s_det), axis=1)
            ref = self._semantic_reference()
            if ref is not None:
                ok[j, t] = sem[j, t] <= cfg.semantic_ratio * ref
        cost = maha2 + _COS_TIE_WEIGHT * (1.0 - cos)
        return cand, ok, cost, sem

    def _associate(self, dets: list[Detection]) -> dict[int, int]:
        """Map detection index -> internal track index for the associated detections."""
        if not self._tracks:
            return {}
        cand, ok, cost, sem = self._gate(dets)
        if not ok.any():
            return {}
        rows = np.flatnonzero(ok.any(axis=1))
        cols = np.flatnonzero(ok.any(axis=0))
        ok = ok[np.ix_(rows, cols)]
        cost = cost[np.ix_(rows, cols)]
        m = rows.size
        # Columns: gated tracks, then one "new track" column per detection. A new track costs more
        # than any m gated associations together, so the assignment first maximises the number
        # of associations, then minimises their summed cost (max cost per pair: maha_max + 2e-9).
        big = (m + 1) * (self.config.maha_max + 1.0)
        full = np.full((m, cols.size + m), np.inf)
        full[:, : cols.size] = np.where(ok, cost, np.inf)
        full[np.arange(m), cols.size + np.arange(m)] = big
        r_idx, c_idx = linear_sum_assignment(full)
        out: dict[int, int] = {}
        for ri, ci in zip(r_idx, c_idx, strict=True):
            if ci < cols.size:
                out[int(rows[ri])] = int(cand[cols[ci]])
                if np.isfinite(d := sem[rows[ri], cols[ci]]):
                    self._sem_recent.append((int(cand[cols[ci]]), float(d)))
        return out

    def _semantic_reference(self) -> float | None:
        """The median over the tracks of the latest associations of each one's latest semantic
        distance (one vote per track: an object seen often does not set it alone); None
        before SEMANTIC_WARMUP tracks are among them."""
        latest = dict(self._sem_recent)
        return float(np.median(list(latest.values()))) if len(latest) >= SEMANTIC_WARMUP \
            else None

    def _new_track(self, det: Detection) -> str:
        track_id = f"o{self._next_id}"
        self._next_id += 1
        dim = det.embedding_d.shape[0]
        state = _TrackState(
            track_id=track_id,
            semantic=SemanticKalman(
                mean_d=det.embedding_d.copy(),  # mu = y_1
                variance_d=_check_variance(det.uncertainty_s, "uncertainty_s", dim),  # Sigma_1
            ),
            position=PositionKalman(
                position_xyz_m=det.position_xyz_m.copy(),
                position_cov_33=det.position_cov_33.copy(),
            ),
            first_seen_s=det.stamp_s,
            last_seen_s=det.stamp_s,
        )
        if det.truth_id is not None:
            state.truth_counts[det.truth_id] += 1
        self._index[track_id] = len(self._tracks)
        self._tracks.append(state)
        log.debug("new track %s at t=%.3f", track_id, det.stamp_s)
        return track_id


__all__ = [
    "CHI2_3DOF_99",
    "SEMANTIC_WARMUP",
    "SEMANTIC_WINDOW",
    "Detection",
    "Frame",
    "ObjectTracker",
    "PositionKalman",
    "SemanticKalman",
    "Track",
    "TrackingConfig",
    "fuse_gaussians",
    "fuse_gaussians_full",
    "fuse_observations",
]
