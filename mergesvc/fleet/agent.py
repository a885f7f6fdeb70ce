"""Vehicle agent: the paper's local map (association gates + semantic Kalman, tracking.py) with
poses and landmarks in a GTSAM ISAM2 graph, submaps cut and published over Zenoh, inter-robot
factors received and added to the graph.

`LocalMap` is the vehicle's mapping core (no I/O, testable alone); `Agent` puts it on Zenoh.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gtsam
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mergesvc.core.frames import FrameId
from mergesvc.core.model import Factor, ObjectNode, Submap
from mergesvc.core.tracking import Frame, ObjectTracker, Track, TrackingConfig
from mergesvc.errors import ConfigError, MergeError
from mergesvc.wire import Profile, Projection, decode_message, encode_message, keys

log = logging.getLogger(__name__)

X = gtsam.symbol_shorthand.X  # vehicle poses
L = gtsam.symbol_shorthand.L  # landmarks (tracked objects)
F = gtsam.symbol_shorthand.F  # other robots' session frames, from inter-robot factors


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
        (0.02, 0.05), description="odometry noise per step: rotation rad, translation m"
    )
    tracking: TrackingConfig = TrackingConfig(cos_min=0.6, window_s=60.0)


@dataclass
class LocalMap:
    """A vehicle's map in its own odometry frame: tracks plus an ISAM2 graph of poses (x_k,
    odometry BetweenFactorPose3) and landmarks (l_j, BearingRangeFactor3D per detection)."""

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
    frame_keys: dict[str, int] = field(default_factory=dict)  # other robots' frames -> F(i)
    path_xyz_m: list[np.ndarray] = field(default_factory=list)  # odometry estimate per frame

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
        """The most recently seen confirmed objects, positions from the smoothed graph."""
        tracks = [t for t in self.tracker.tracks if t.track_id in self._confirmed]
        if len(tracks) < 2:
            return None
        tracks.sort(key=lambda t: t.last_seen_s)
        window = tracks[-self.config.window_objects:]
        est = self.isam.calculateEstimate()
        nodes = [self._node(t, est) for t in window]
        self._last_cut_m = self.distance_m
        self._new_since_cut = 0
        return Submap(robot_id=self.config.robot, session_id=self.config.session, seq=seq,
                      stamp=stamp_s, objects=nodes)

    def _node(self, t: Track, est: gtsam.Values) -> ObjectNode:
        key = L(self.landmark_of[t.track_id])
        p = est.atPoint3(key) if est.exists(key) else t.position_xyz_m
        return ObjectNode(id=t.track_id, position=(float(p[0]), float(p[1]), float(p[2])),
                          embedding=t.mean_d.tolist(), variance=t.variance_d.tolist(),
                          n_obs=t.n_obs)

    def add_inter_robot(self, factor: Factor) -> str:
        """Add a received factor: the other robot's session frame becomes a variable tied to
        this session's frame (x_0). Returns a log line with the correction."""
        me = (factor.robot_a, factor.session_a) == (self.config.robot, self.config.session)
        other = (factor.robot_b, factor.session_b) if me else (factor.robot_a, factor.session_a)
        T = _pose_of(factor)
        T_me_other = T if me else T.inverse()
        cov = np.asarray(factor.covariance, dtype=np.float64)
        name = str(FrameId(*other))
        key = F(self.frame_keys.setdefault(name, len(self.frame_keys)))
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        graph.add(gtsam.BetweenFactorPose3(
            X(0), key, T_me_other, gtsam.noiseModel.Gaussian.Covariance(cov)))
        est = self.isam.calculateEstimate()
        before = est.atPose3(key) if est.exists(key) else None
        if before is None:
            values.insert(key, est.atPose3(X(0)).compose(T_me_other))
        self.isam.update(graph, values)
        after = self.isam.calculateEstimate().atPose3(key)
        moved = 0.0 if before is None else float(
            np.linalg.norm(after.translation() - before.translation()))
        return (f"factor {factor.factor_id}: frame {name} at "
                f"{np.round(after.translation(), 2).tolist()} in my frame"
                + (f" (moved {moved:.2f} m)" if before is not None else " (first estimate)"))


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


@dataclass
class AgentStats:
    frames: int = 0
    submaps_sent: int = 0
    bytes_sent: int = 0
    factors_received: int = 0
    bad_messages: int = 0


class Agent:
    """A vehicle on Zenoh: liveliness token, advanced publisher of submaps (cache, so a service
    that joins late or restarts recovers them), subscriber of its factors."""

    def __init__(
        self,
        config: AgentConfig,
        session: object,
        encode: Callable[[Submap, int], bytes],
        decode_factor: Callable[[bytes], Factor],
        submap_key: str,
        factor_key: str,
        alive_key: str,
        cache_samples: int = 10_000,
    ) -> None:
        import zenoh
        from zenoh.ext import CacheConfig, MissDetectionConfig, declare_advanced_publisher

        self.config = config
        self.local = LocalMap(config)
        self.stats = AgentStats()
        self._encode, self._decode = encode, decode_factor
        self._lock = threading.Lock()
        self._session = session
        self._token = session.liveliness().declare_token(alive_key)
        self._pub = declare_advanced_publisher(
            session, submap_key, cache=CacheConfig(max_samples=cache_samples),
            sample_miss_detection=MissDetectionConfig(heartbeat=0.5), publisher_detection=True,
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        self._sub = session.declare_subscriber(factor_key, self._on_factor)

    def _on_factor(self, sample: object) -> None:
        try:
            factor = self._decode(sample.payload.to_bytes())
            with self._lock:
                line = self.local.add_inter_robot(factor)
                self.stats.factors_received += 1
            log.info("%s: %s", self.config.robot, line)
        except MergeError as exc:  # not a factor, or not one this map can use
            self.stats.bad_messages += 1
            log.warning("%s: ignoring a bad factor message: %s", self.config.robot, exc)
        # Last resort of the factor callback on a running vehicle: a factor the local graph
        # cannot take (GTSAM refuses it), or a bug, is logged with its traceback and skipped;
        # the vehicle goes on mapping.
        except Exception:
            self.stats.bad_messages += 1
            log.exception("%s: ignoring a factor the local map could not take", self.config.robot)

    def run(self, frames: Iterable[Frame], time_scale: float = 0.0,
            stop: threading.Event | None = None) -> AgentStats:
        """Process frames; time_scale > 0 paces them (wall s per simulated s)."""
        start = time.monotonic()
        for fr in frames:
            if stop is not None and stop.is_set():
                break
            if time_scale > 0:
                delay = start + fr.stamp_s * time_scale - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            with self._lock:
                cut = self.local.add_frame(fr)
                sub = self.local.cut_submap(self.stats.submaps_sent, fr.stamp_s) if cut else None
            self.stats.frames += 1
            if sub is not None:
                payload = self._encode(sub, self.stats.submaps_sent)
                self._pub.put(payload)
                self.stats.submaps_sent += 1
                self.stats.bytes_sent += len(payload)
                log.info("%s: submap %d (%d objects, %d bytes)", self.config.robot,
                         sub.seq, len(sub.objects), len(payload))
        return self.stats

    def close(self) -> None:
        import zenoh

        for ent in (self._sub, self._pub, self._token):
            with contextlib.suppress(zenoh.ZError):  # already gone with the session
                ent.undeclare()

    def __enter__(self) -> Agent:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass(frozen=True)
class AgentRun:
    """One vehicle run as `mergesvc agent` starts it: who the vehicle is, where its frames
    come from (a seeded fleet world, or a recorded observation log), how its submaps are
    coded and which side of the key space it publishes on."""

    robot: str
    fleet: str = "fleet0"
    session: str = "s0"
    seed: int = 0  # fleet world seed (ignored with log_file)
    laps: int = 2
    objects: int = 24
    log_file: Path | None = None  # replay this observation log instead of the world
    profile: Profile = Profile.INT8
    projection: Path | None = None  # fleet projection (.npz); the compact profile needs it
    time_scale: float = 0.0  # wall s per simulated s; 0: no pacing
    acoustic: bool = False  # publish on the acoustic vehicle side (through the bridge)
    linger_s: float = 2.0  # stay up this long after the run, for late factors
    config: AgentConfig | None = None  # the agent settings; None: defaults for this robot


def _world_frames(run: AgentRun) -> Iterable[Frame]:
    from mergesvc.sim import fleet_world, read_observation_log

    if run.log_file is not None:
        return read_observation_log(run.log_file)
    sid = run.session
    return fleet_world(run.seed, laps=run.laps, n_objects=run.objects).frames(
        run.robot, int(sid.lstrip("s") or 0) if sid[1:].isdigit() else 0)


def run_agent(run: AgentRun, zenoh_config: Any) -> AgentStats:
    """Build the vehicle (frames, codec, keys), open a Zenoh session with `zenoh_config`, run
    the frames through an `Agent`, linger for factors, close. Raises MergeError (ConfigError
    for the compact profile without a projection), ValueError/OSError for unreadable input."""
    import zenoh

    proj = Projection.load(run.projection) if run.projection is not None else None
    if run.profile is Profile.COMPACT and proj is None:
        raise ConfigError("the compact profile needs a fleet projection")
    acfg = run.config or AgentConfig(robot=run.robot, session=run.session, fleet=run.fleet)
    if (acfg.robot, acfg.session, acfg.fleet) != (run.robot, run.session, run.fleet):
        raise ConfigError(
            f"agent settings are for {acfg.robot}/{acfg.session} in fleet {acfg.fleet}, the run "
            f"is {run.robot}/{run.session} in fleet {run.fleet}"
        )
    frames = _world_frames(run)
    root = keys.uw_root(run.fleet) if run.acoustic else keys.fleet_root(run.fleet)

    def encode(sub: Submap, seq: int) -> bytes:
        return encode_message(sub, run.profile, run.robot, seq, projection=proj)

    def decode_factor(data: bytes) -> Factor:
        _, f = decode_message(data)
        if not isinstance(f, Factor):
            raise MergeError("not a factor")
        return f

    with zenoh.open(zenoh_config) as session, Agent(
        acfg, session, encode, decode_factor,
        submap_key=keys.submap_key(root, run.robot, run.session),
        factor_key=keys.robot_factors(root, run.robot), alive_key=keys.alive_key(root, run.robot),
    ) as ag:
        stats = ag.run(frames, time_scale=run.time_scale)
        time.sleep(run.linger_s)
    return stats


__all__ = ["Agent", "AgentConfig", "AgentRun", "AgentStats", "LocalMap", "build_submaps",
           "run_agent"]
