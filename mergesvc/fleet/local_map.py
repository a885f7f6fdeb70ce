"""The vehicle's mapping core, no I/O: the paper's local map (association gates and semantic
Kalman, core/tracking.py) with poses and landmarks in a GTSAM ISAM2 graph, keyframe submaps cut
from it with their odometry and its propagated covariance, and inter-robot factors added to
(or retracted from) its graph. `build_submaps` runs a whole sequence of frames offline.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import gtsam
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator

from mergesvc.core.factors import is_loop
from mergesvc.core.frames import FrameId
from mergesvc.core.model import Factor, FactorStatus, ObjectNode, Odometry, Submap, Transform
from mergesvc.core.odometry import chain_covariance, step_covariance
from mergesvc.core.tracking import Frame, ObjectTracker, Track, TrackingConfig
from mergesvc.errors import InputError
from mergesvc.wire.keys import check_name

MAX_HELD = 10_000  # factors on own keyframes not reached yet, held at most
X = gtsam.symbol_shorthand.X  # vehicle poses
L = gtsam.symbol_shorthand.L  # landmarks (tracked objects)
F = gtsam.symbol_shorthand.F  # other robots' keyframes, from inter-robot factors


class AgentConfig(BaseModel):
    """What a vehicle does with its observations."""

    model_config = ConfigDict(extra="forbid")

    robot: str = Field(min_length=1, max_length=64)
    session: str = Field("s0", min_length=1, max_length=64)
    fleet: str = Field("fleet0", min_length=1, max_length=64)
    cut_every_objects: int = Field(3, ge=1, description="cut a submap after this many new objects")
    cut_every_m: float = Field(15.0, gt=0, description="... or after this distance travelled")
    window_objects: int = Field(8, ge=2, description="recently seen objects in one submap")
    min_obs: int = Field(2, ge=1, description="objects seen fewer times are not sent")
    odometry_sigma: tuple[float, float] = Field(
        (0.005, 0.02),
        description="odometry noise per step: rotation rad, translation m. Set it to your "
        "vehicle's: a sigma far looser than the real noise lets every loop closure bend the "
        "trajectory (0.02 rad against a true 0.0035 made merged trajectories worse than "
        "odometry alone in the pool demo)",
    )
    tracking: TrackingConfig = TrackingConfig(cos_min=0.6, window_s=60.0)
    up: tuple[float, float, float] | None = Field(
        None,
        description="the direction opposite to gravity in the vehicle's odometry frame, when "
        "its IMU or attitude sensor gives it (e.g. [0, 0, 1] for z up, [0, -1, 0] for a "
        "camera's y down). Each submap then declares `up` in its keyframe frame, so the "
        "service fits inter-robot factors about gravity (4-DoF) instead of guessing the tilt "
        "from a few nearly coplanar objects. None: not known, nothing declared",
    )

    @field_validator("robot", "session", "fleet")
    @classmethod
    def _key_names(cls, v: str, info: ValidationInfo) -> str:
        return check_name(info.field_name, v)

    @field_validator("up")
    @classmethod
    def _up_is_a_direction(cls, v: tuple[float, float, float] | None
                           ) -> tuple[float, float, float] | None:
        if v is not None and not (np.all(np.isfinite(v)) and np.linalg.norm(v) > 0):
            raise ValueError(f"up must be a finite, non-zero direction, got {list(v)}")
        return v


@dataclass
class _Received:
    """An inter-robot factor in the ISAM2 graph: its index there and the variable it ties to."""

    factor: Factor
    index: int
    other_key: int  # an own pose for a loop (two own keyframes)

    @property
    def loop(self) -> bool:
        return is_loop(self.factor)


@dataclass
class LocalMap:
    """A vehicle's map in its own odometry frame: tracks plus an ISAM2 graph of poses (x_k,
    odometry BetweenFactorPose3) and landmarks (l_j, BearingRangeFactor3D per detection), and
    the other robots' keyframes that inter-robot factors tie to (f_i, BetweenFactorPose3).

    Poses are indexed by frame: x_k is the k-th frame this map took (k = 0 the session's first
    pose, the origin of the session frame). A submap is cut at the frame just added, its
    keyframe, and is anchored there (see `cut_submap`)."""

    config: AgentConfig
    tracker: ObjectTracker = field(init=False)
    isam: gtsam.ISAM2 = field(init=False)
    landmark_of: dict[str, int] = field(default_factory=dict)
    frames_seen: int = 0
    distance_m: float = 0.0
    _prev_pose: np.ndarray | None = None
    _last_cut_m: float = 0.0
    _new_since_cut: int = 0
    _confirmed: set[str] = field(default_factory=set)
    # other robots' keyframes ("robot/session", keyframe) -> index i of the variable F(i)
    other_keys: dict[tuple[str, int], int] = field(default_factory=dict)
    path_xyz_m: list[np.ndarray] = field(default_factory=list)  # odometry estimate per frame
    poses_est: list[np.ndarray] = field(default_factory=list)  # raw odometry pose per frame
    up_body: list[np.ndarray | None] = field(default_factory=list)  # AHRS gravity per frame
    stamps_s: list[float] = field(default_factory=list)
    keyframes: list[int] = field(default_factory=list)  # the keyframe of every submap cut
    # keyframes whose submap the service will never hold (refused for good, failed): the next
    # submap's odometry starts from the last keyframe before them, so its chain stays joined
    lost: set[int] = field(default_factory=set)
    _received: dict[str, _Received] = field(default_factory=dict)  # factor id -> in the graph
    # factor id -> (own keyframe not reached yet, the factor) (a restart on the same session
    # is told of its earlier factors at once): added when the keyframe is (`add_held`)
    _held: dict[str, tuple[int, Factor]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.tracker = ObjectTracker(self.config.tracking)
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(0.05)
        self.isam = gtsam.ISAM2(params)

    def add_frame(self, frame: Frame) -> bool:
        """Odometry + detections of one frame; True when a submap should be cut now."""
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        k = self.frames_seen
        T = gtsam.Pose3(frame.T_est)
        if self._prev_pose is None:
            graph.add(gtsam.PriorFactorPose3(X(k), T, gtsam.noiseModel.Isotropic.Sigma(6, 1e-4)))
        else:
            step = gtsam.Pose3(self._prev_pose).between(T)
            r, t = self.config.odometry_sigma
            noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([r, r, r, t, t, t]))
            graph.add(gtsam.BetweenFactorPose3(X(k - 1), X(k), step, noise))
            self.distance_m += float(np.linalg.norm(step.translation()))
        values.insert(X(k), T)
        ids = self.tracker.observe_frame(frame.detections)
        T_inv = np.linalg.inv(frame.T_est)
        for det, tid in zip(frame.detections, ids):
            body = T_inv[:3, :3] @ det.position_xyz_m + T_inv[:3, 3]
            rng_m = float(np.linalg.norm(body))
            if rng_m < 1e-3:
                continue
            if tid not in self.landmark_of:
                self.landmark_of[tid] = len(self.landmark_of)
                values.insert(L(self.landmark_of[tid]), gtsam.Point3(*det.position_xyz_m))
            sigma = float(np.sqrt(np.trace(det.position_cov_33) / 3.0))
            noise = gtsam.noiseModel.Diagonal.Sigmas(
                np.array([sigma / max(rng_m, 0.5)] * 2 + [sigma])
            )
            graph.add(gtsam.BearingRangeFactor3D(
                X(k), L(self.landmark_of[tid]), gtsam.Unit3(body), rng_m, noise))
        self.isam.update(graph, values)
        self._prev_pose = frame.T_est
        self.path_xyz_m.append(frame.T_est[:3, 3].copy())
        self.poses_est.append(np.array(frame.T_est, dtype=np.float64))
        self.up_body.append(None if frame.up_body is None
                            else np.asarray(frame.up_body, dtype=np.float64))
        self.stamps_s.append(float(frame.stamp_s))
        self.frames_seen += 1
        for t in self.tracker.tracks:
            if t.n_obs >= self.config.min_obs and t.track_id not in self._confirmed:
                self._confirmed.add(t.track_id)
                self._new_since_cut += 1
        return (
            self._new_since_cut >= self.config.cut_every_objects
            or (self.distance_m - self._last_cut_m >= self.config.cut_every_m
                and self._new_since_cut > 0)
        )

    def cut_submap(self, seq: int, stamp_s: float) -> Submap | None:
        """The most recently seen confirmed objects, anchored at the pose just added.

        The submap's `keyframe` is k, the index of the last frame added: object positions are
        the smoothed (ISAM2) landmark estimates expressed in the smoothed x_k's body frame,
        p_k = T_k^-1 p. Its `odometry` is the vehicle's raw motion since the previous submap's
        keyframe not known `lost` (keyframe 0, the session origin, before any): see
        `odometry`."""
        tracks = [t for t in self.tracker.tracks if t.track_id in self._confirmed]
        if len(tracks) < 2 or self.frames_seen == 0:
            return None
        k = self.frames_seen - 1
        if self.keyframes and k <= self.keyframes[-1]:
            return None  # one submap per keyframe
        prev = next((j for j in reversed(self.keyframes) if j not in self.lost), 0)
        tracks.sort(key=lambda t: t.last_seen_s)
        window = tracks[-self.config.window_objects:]
        est = self.isam.calculateEstimate()
        T_k_inv = np.linalg.inv(est.atPose3(X(k)).matrix())
        nodes = [self._node(t, est, T_k_inv) for t in window]
        self._last_cut_m = self.distance_m
        self._new_since_cut = 0
        self.keyframes.append(k)
        up = None
        if self.up_body[k] is not None:  # the AHRS measured gravity in this keyframe's body
            up_k = self.up_body[k]
        elif self.config.up is not None:  # gravity in the keyframe's body frame: R_k^T up
            up_k = T_k_inv[:3, :3] @ np.asarray(self.config.up, dtype=np.float64)
        else:
            up_k = None
        if up_k is not None and np.all(np.isfinite(up_k)) and np.linalg.norm(up_k) > 0:
            up = tuple(float(x) for x in up_k / np.linalg.norm(up_k))
        return Submap(robot_id=self.config.robot, session_id=self.config.session, seq=seq,
                      stamp=stamp_s, objects=nodes, keyframe=k, up=up,
                      odometry=self.odometry(prev, k) if k > prev else None)

    def odometry(self, from_keyframe: int, to_keyframe: int) -> Odometry:
        """The vehicle's raw odometry from one of its poses to a later one: T_from_to =
        inv(T_est[from]) T_est[to], the composition of the odometry steps in between (not the
        smoothed estimate, so that the service can use it as a factor independent of the
        landmarks this vehicle also sends), with the steps' covariance composed to first order
        (core/odometry.py: a heading error grows into sideways position error)."""
        if not 0 <= from_keyframe < to_keyframe < self.frames_seen:
            raise InputError(
                f"odometry needs 0 <= from < to < {self.frames_seen}, got {from_keyframe}, "
                f"{to_keyframe}")
        T = np.linalg.inv(self.poses_est[from_keyframe]) @ self.poses_est[to_keyframe]
        cov = chain_covariance(self.poses_est[from_keyframe:to_keyframe + 1],
                               step_covariance(self.config.odometry_sigma))
        return Odometry(from_keyframe=from_keyframe, T_from_to=_transform(T),
                        covariance=cov.tolist())

    def _node(self, t: Track, est: gtsam.Values, T_k_inv: np.ndarray) -> ObjectNode:
        key = L(self.landmark_of[t.track_id])
        p = est.atPoint3(key) if est.exists(key) else t.position_xyz_m
        p = T_k_inv[:3, :3] @ np.asarray(p, dtype=np.float64) + T_k_inv[:3, 3]
        return ObjectNode(id=t.track_id, position=(float(p[0]), float(p[1]), float(p[2])),
                          embedding=t.mean_d.tolist(), variance=t.variance_d.tolist(),
                          n_obs=t.n_obs)

    def own_poses(self, est: gtsam.Values | None = None) -> np.ndarray:
        """(n, 4, 4) smoothed estimate of every own pose x_0 .. x_{n-1}, in the session frame."""
        if not self.frames_seen:
            return np.zeros((0, 4, 4))
        est = self.isam.calculateEstimate() if est is None else est
        return np.stack([est.atPose3(X(k)).matrix() for k in range(self.frames_seen)])

    def add_inter_robot(self, factor: Factor) -> str:
        """Add (or, with status `retracted`, remove) a received inter-robot factor. Returns a
        log line with how much the own trajectory moved.

        A pose-level factor (`keyframe_a`/`keyframe_b` set) becomes a BetweenFactorPose3 from
        the own keyframe pose x_k to a variable for the other robot's keyframe, one variable
        per other (robot, session, keyframe), first estimated as x_k composed with the factor.
        A frame-level factor (keyframes absent) is the same between the session origins:
        own keyframe 0 and the other session's keyframe 0. One factor to a new variable only
        places it; two factors to the same other keyframe from different own keyframes close
        a loop through it and correct the own trajectory.

        A retracted factor is removed from ISAM2 (removeFactorIndices); a variable left without
        factors gets a weak prior at its current estimate, so the system stays well-posed
        (the prior touches only that variable, not the own poses). A factor id already in the
        graph with the same content is ignored; with new content it replaces the old one.
        A factor between two keyframes of this session (a loop the service found in its own
        map) is a BetweenFactorPose3 between the two own poses. Others are ignored."""
        mine = (self.config.robot, self.config.session)
        me_a = (factor.robot_a, factor.session_a) == mine
        me_b = (factor.robot_b, factor.session_b) == mine
        fid = factor.factor_id
        if not (me_a or me_b):
            return f"factor {fid}: not about this session: ignored"
        loop = me_a and me_b
        if factor.status == FactorStatus.RETRACTED:
            if self._held.pop(fid, None) is not None:
                return f"factor {fid} retracted: it was held, not yet in the graph"
            return self._retract(factor)
        old = self._received.get(fid)
        if old is not None and _same(old.factor, factor):
            return f"factor {fid}: already in the graph: ignored"
        own_k = (factor.keyframe_a if me_a else factor.keyframe_b) or 0
        other_k = (factor.keyframe_b if me_a else factor.keyframe_a) or 0
        if loop and own_k == other_k:
            return f"factor {fid}: ties keyframe {own_k} to itself: ignored"
        self._held.pop(fid, None)
        latest = max(own_k, other_k) if loop else own_k  # the own keyframe it waits for
        if latest >= self.frames_seen:
            if len(self._held) >= MAX_HELD:
                raise InputError(f"factor {fid} ties own keyframe {latest}, this map has "
                                 f"{self.frames_seen} poses and holds {MAX_HELD} such factors")
            self._held[fid] = (latest, factor)
            return (f"factor {fid}: ties my keyframe {latest}, not reached yet ("
                    f"{self.frames_seen} poses): held until then")
        other = (str(FrameId(factor.robot_b, factor.session_b) if me_a
                     else FrameId(factor.robot_a, factor.session_a)), other_k)
        T_ab = _pose_of(factor)
        cov = np.asarray(factor.covariance, dtype=np.float64)
        if me_a:
            T_me_other = T_ab
        else:  # (T exp(xi))^-1 = T^-1 exp(-Ad_T xi): the inverse's covariance is Ad C Ad^T
            T_me_other = T_ab.inverse()
            Ad = T_ab.AdjointMap()
            cov = Ad @ cov @ Ad.T
            cov = 0.5 * (cov + cov.T)
        key = X(other_k) if loop else F(self.other_keys.setdefault(other, len(self.other_keys)))
        est = self.isam.calculateEstimate()
        before = self.own_poses(est)
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        graph.add(gtsam.BetweenFactorPose3(
            X(own_k), key, T_me_other, gtsam.noiseModel.Gaussian.Covariance(cov)))
        first = not est.exists(key)
        if first:
            values.insert(key, est.atPose3(X(own_k)).compose(T_me_other))
        remove: list[int] = []
        if old is not None:  # same id, new content: replace it
            del self._received[fid]
            remove.append(old.index)
            if old.other_key != key and not old.loop:
                self._keep_posed(old.other_key, graph, est)
        res = self.isam.update(graph, values, remove)
        self._received[fid] = _Received(factor, int(res.getNewFactorsIndices()[0]), key)
        after_est = self._settle()
        at = after_est.atPose3(key).translation()
        name = f"{other[0]}#{other[1]}"
        return (f"factor {fid}: keyframe {name} at {np.round(at, 2).tolist()} from my "
                f"keyframe {own_k}" + (" (first estimate)" if first else "")
                + ("; replaced the earlier version" if old is not None else "")
                + "; " + _moved(before, self.own_poses(after_est)))

    def add_held(self) -> list[str]:
        """Add the held factors whose own keyframe this map has reached now, in the order
        they came; their log lines."""
        due = [f for k, f in self._held.values() if k < self.frames_seen]
        return [self.add_inter_robot(f) for f in due]

    def _retract(self, factor: Factor) -> str:
        rec = self._received.pop(factor.factor_id, None)
        if rec is None:
            return f"factor {factor.factor_id} retracted: it was not in the graph"
        est = self.isam.calculateEstimate()
        before = self.own_poses(est)
        graph = gtsam.NonlinearFactorGraph()
        if not rec.loop:
            self._keep_posed(rec.other_key, graph, est)
        self.isam.update(graph, gtsam.Values(), [rec.index])
        after_est = self._settle()
        return (f"factor {factor.factor_id} retracted: removed from the graph; "
                + _moved(before, self.own_poses(after_est)))

    def _keep_posed(self, key: int, graph: gtsam.NonlinearFactorGraph,
                    est: gtsam.Values) -> None:
        """A weak prior on an other robot's keyframe variable about to lose its last factor."""
        if any(r.other_key == key for r in self._received.values()):
            return
        graph.add(gtsam.PriorFactorPose3(key, est.atPose3(key),
                                         gtsam.noiseModel.Isotropic.Sigma(6, 1e3)))

    def _settle(self, rounds: int = 4, tol_m: float = 1e-3) -> gtsam.Values:
        """ISAM2 relinearizes only every few updates: after a loop closure, relinearize until
        the own poses stop moving (at most `rounds` times)."""
        prev = self.own_poses()
        est = self.isam.calculateEstimate()
        for _ in range(rounds):
            self.isam.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), [],
                             force_relinearize=True)
            est = self.isam.calculateEstimate()
            now = self.own_poses(est)
            if not len(now) or np.abs(now[:, :3, 3] - prev[:, :3, 3]).max() < tol_m:
                break
            prev = now
        return est


def odometry_covariance(n_steps: int, odometry_sigma: tuple[float, float]) -> np.ndarray:
    """6x6 covariance (GTSAM order: rotation, then translation) of n_steps composed odometry
    steps, each with independent noise diag(r^2, r^2, r^2, t^2, t^2, t^2): n_steps times the
    per-step covariance.

    This treats the composition as a random walk on each axis separately: it ignores that
    the steps' noise is in each step's own body frame (rotated along the way), that heading
    errors grow into lateral position errors along the path (the rotation-translation
    correlation, and a translation variance growing faster than linearly on long curved
    stretches), and any correlation between the steps. Good enough between keyframes a few
    tens of steps apart; it understates the translation uncertainty of long stretches."""
    r, t = odometry_sigma
    return float(n_steps) * np.diag([r * r] * 3 + [t * t] * 3)


def _transform(T: np.ndarray) -> Transform:
    q = gtsam.Rot3(np.asarray(T[:3, :3], dtype=np.float64)).toQuaternion()
    w = np.array([q.w(), q.x(), q.y(), q.z()])
    w /= np.linalg.norm(w)
    return Transform(translation=tuple(float(x) for x in T[:3, 3]),
                     quaternion_wxyz=tuple(float(x) for x in w))


def _same(a: Factor, b: Factor) -> bool:
    return a.model_dump(exclude={"status"}) == b.model_dump(exclude={"status"})


def _moved(before: np.ndarray, after: np.ndarray) -> str:
    """How much the own trajectory moved: max and mean translation change of the poses."""
    if not len(before):
        return "own trajectory: no poses"
    d = np.linalg.norm(after[:, :3, 3] - before[:, :3, 3], axis=1)
    return f"own trajectory moved max {d.max():.3f} m, mean {d.mean():.3f} m"


def _pose_of(factor: Factor) -> gtsam.Pose3:
    w, x, y, z = factor.T_a_b.quaternion_wxyz
    return gtsam.Pose3(gtsam.Rot3.Quaternion(w, x, y, z), gtsam.Point3(*factor.T_a_b.translation))


def build_submaps(config: AgentConfig, frames: Iterable[Frame]) -> tuple[LocalMap, list[Submap]]:
    """Run a vehicle's frames through its local map offline: every submap it would send."""
    lm = LocalMap(config)
    out: list[Submap] = []
    for fr in frames:
        if lm.add_frame(fr):
            sub = lm.cut_submap(len(out), fr.stamp_s)
            if sub is not None:
                out.append(sub)
    return lm, out


__all__ = ["AgentConfig", "LocalMap", "build_submaps", "odometry_covariance"]
