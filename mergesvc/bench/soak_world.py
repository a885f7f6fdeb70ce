"""The soak's traffic: a seeded world the robots wander (`SoakWorld`, `RobotWalk`: keyframe
submaps with odometry, so sessions overlap and the service finds factors), the attacker's
hostile payloads (`hostile_payload`: each one the decoder or the service must refuse) and when
it sends them (`hostile_schedule`: a number fixed by the plan, not by the machine), and the
agents' advanced publisher built the same way as fleet/agent.py's (bench may not import fleet).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum
from typing import Any

import msgpack
import numpy as np

from mergesvc.bench.scoring import check_count
from mergesvc.core.model import ObjectNode, Odometry, Submap, Transform
from mergesvc.errors import InputError, MergeError
from mergesvc.wire import Profile, decode_message, encode_message, keys

#: The agents' publisher (fleet/agent.py `Agent`): samples kept for a late or restarted service.
CACHE_SAMPLES = 10_000
#: Sample-miss heartbeat of the agents' publisher, s.
HEARTBEAT_S = 0.5
#: The service's default `max_payload_bytes` (fleet/config.py ServiceConfig).
DEFAULT_MAX_PAYLOAD = 4 * 2**20
HOSTILE_ROBOTS = ("h0", "h1", "h2", "h3")
HOSTILE_SEQ0 = 10**9  # hostile submaps' seqs: never one a valid robot uses
FLOOD_ROBOT = "f0"  # the conflict flood's robot (its one submap is valid; its variants are not)
LARGE_ROBOT = "L0"  # the large submap's robot (a whole map relocalized)


class HostileKind(str, Enum):
    """What the attacker sends."""

    RANDOM_BYTES = "random_bytes"
    TRUNCATED = "truncated"
    CORRUPTED = "corrupted"
    SCHEMA_VERSION = "schema_version"
    CODEC_VERSION = "codec_version"
    NAN = "nan"
    OVERSIZE = "oversize"
    KEY_SESSION = "key_session"  # a valid submap on another session's key
    EXTRA_LEVELS = "extra_levels"  # submap/{robot}/{session}/extra/deep
    OTHER_ROBOT = "other_robot"  # a valid robot's submap on the attacker's key


@dataclass
class SoakPlan:
    robots: int = 5
    duration_s: float = 120.0
    hostile_fraction: float = 0.1
    mismatch_robots: int = 1
    restarts: int = 2
    seed: int = 0
    rate_hz: tuple[float, float] = (0.2, 2.0)  # each robot's rate, uniform in this range
    objects_per_submap: int = 8
    dim: int = 384
    mismatch_dim: int = 128
    world_objects: int = 400
    area_m: float = 240.0
    step_m: float = 4.0  # distance between a robot's keyframes
    second_session_p: float = 0.5  # robots that move to a second session during the run
    max_payload_bytes: int = DEFAULT_MAX_PAYLOAD  # the service's: oversize payloads exceed it
    max_rate_hz: float = 5.0  # the service's submap_rate_hz: every robot must stay below it
    fleet: str = "soak"
    profile: Profile = Profile.INT8
    status_period_s: float = 3.0
    rss_period_s: float = 1.0
    drain_timeout_s: float = 180.0
    start_timeout_s: float = 60.0
    restart_pause_s: tuple[float, float] = (0.0, 2.0)  # down time after a kill, uniform
    bin_s: float | None = None  # time bins of the series; None: about 40 bins
    # a conflict flood: this many byte-variants of one stored (robot, session, seq), sent as
    # fast as they go at `flood_at` of the run (0: none); the others' latency is compared
    # in a window of `flood_window_s` after it and the same window before it
    flood_variants: int = 700
    flood_at: float = 0.5
    flood_window_s: float = 20.0
    # a full disk: at `disk_full_at` of the run (0: none) the service is restarted with its
    # file size limit a little (`disk_full_margin_bytes`) above its largest file's size, held
    # so for `disk_full_s`, then restarted without it
    disk_full_at: float = 0.4
    disk_full_s: float = 45.0
    disk_full_margin_bytes: int = 512 * 1024
    # a large submap: at `large_at` of the run (0 objects: none), LARGE_ROBOT sends one submap
    # of `large_objects` objects (the whole world seen from one keyframe, the rest other
    # objects far away); the others' latency is compared in a window of `large_window_s`
    # after it and the same window before it
    large_objects: int = 5000
    large_at: float = 0.7
    large_window_s: float = 30.0

    @classmethod
    def quick(cls, seed: int = 0) -> SoakPlan:
        return cls(robots=3, duration_s=10.0, hostile_fraction=0.2, mismatch_robots=1,
                   restarts=1, seed=seed, rate_hz=(1.0, 2.0), status_period_s=0.5,
                   drain_timeout_s=60.0, restart_pause_s=(0.0, 0.5), world_objects=120,
                   area_m=80.0, flood_variants=60, flood_at=0.1, flood_window_s=3.0,
                   disk_full_at=0.0, large_objects=400, large_at=0.3, large_window_s=3.0)

    def check(self) -> None:
        """InputError on a plan that cannot run or would break the service's limits."""
        check_count("robots", self.robots)
        check_count("mismatch robots", self.mismatch_robots, 0)
        check_count("restarts", self.restarts, 0)
        check_count("flood variants", self.flood_variants, 0)
        if not 0.0 < self.flood_at < 1.0:
            raise InputError(f"flood_at must be in (0, 1), got {self.flood_at}")
        if self.large_objects and not (0.0 < self.large_at < 1.0
                                       and self.large_objects > self.world_objects):
            raise InputError(f"large_at must be in (0, 1) and large_objects above the world's "
                             f"{self.world_objects}, got {self.large_at}, {self.large_objects}")
        if not 0.0 <= self.disk_full_at < 1.0 or self.disk_full_s < 0:
            raise InputError(f"disk_full_at must be in [0, 1) and disk_full_s >= 0, got "
                             f"{self.disk_full_at}, {self.disk_full_s}")
        if not self.duration_s > 0:
            raise InputError(f"duration must be > 0 s, got {self.duration_s}")
        if not 0.0 <= self.hostile_fraction < 1.0:
            raise InputError(f"hostile fraction must be in [0, 1), got {self.hostile_fraction}")
        lo, hi = self.rate_hz
        if not 0 < lo <= hi < self.max_rate_hz:
            raise InputError(f"robot rates {lo}-{hi} Hz must be > 0 and below the service's "
                             f"submap_rate_hz {self.max_rate_hz}")
        if self.mismatch_dim == self.dim:
            raise InputError("mismatch_dim must differ from the fleet's dim")
        if self.objects_per_submap > self.world_objects:
            raise InputError("objects_per_submap exceeds world_objects")


# ------------------------------------------------------------------------------ the world


@dataclass
class SoakWorld:
    """Objects of one area shared by the fleet: positions (M, 3) m and unit embeddings (M, D)."""

    position_xyz_m: np.ndarray
    embeddings_nd: np.ndarray
    area_m: float

    @classmethod
    def make(cls, plan: SoakPlan) -> SoakWorld:
        rng = np.random.default_rng([plan.seed, 1])
        m = plan.world_objects
        xyz = np.column_stack([rng.uniform(0, plan.area_m, (m, 2)), rng.uniform(-2, 2, m)])
        e = rng.normal(size=(m, plan.dim))
        return cls(xyz, e / np.linalg.norm(e, axis=1, keepdims=True), plan.area_m)


def _pose(x: float, y: float, yaw: float) -> np.ndarray:
    T = np.eye(4)
    c, s = math.cos(yaw), math.sin(yaw)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:2, 3] = x, y
    return T


def _transform(T: np.ndarray) -> Transform:
    """A yaw-only pose (the walks turn about z only) as a Transform."""
    yaw = math.atan2(T[1, 0], T[0, 0])
    return Transform(translation=tuple(float(x) for x in T[:3, 3]),
                     quaternion_wxyz=(math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)))


_ODOMETRY_COV = np.diag([1e-4, 1e-4, 1e-4, 4e-3, 4e-3, 4e-3]).tolist()


class RobotWalk:
    """One robot's submaps: a seeded walk through the world; each keyframe's submap holds the
    nearest objects, positions in the keyframe's body frame (small noise), embeddings of `dim`
    (the first `dim` of the world's, renormalised: another model when it differs), odometry
    from the previous keyframe, z up."""

    def __init__(self, world: SoakWorld, robot: str, dim: int, n_objects: int,
                 step_m: float, rng: np.random.Generator) -> None:
        self.world, self.robot, self.dim, self.n = world, robot, dim, n_objects
        self.step_m, self.rng = step_m, rng
        self.xy = rng.uniform(0.2, 0.8, 2) * world.area_m
        self.yaw = float(rng.uniform(-math.pi, math.pi))
        e = world.embeddings_nd[:, :dim]
        self.emb = e / np.linalg.norm(e, axis=1, keepdims=True)
        self.session = "s0"
        self.keyframe = 0
        self._T_prev: np.ndarray | None = None

    def new_session(self, session: str) -> None:
        self.session, self.keyframe, self._T_prev = session, 0, None

    def next_submap(self, seq: int) -> Submap:
        """The submap at the next keyframe (the robot moves `step_m` first, after keyframe 0)."""
        if self._T_prev is not None:
            self.yaw += float(self.rng.normal(0.0, 0.4))
            nxt = self.xy + self.step_m * np.array([math.cos(self.yaw), math.sin(self.yaw)])
            if not np.all((nxt > 0) & (nxt < self.world.area_m)):  # turn back at the edge
                self.yaw += math.pi
                nxt = self.xy + self.step_m * np.array([math.cos(self.yaw), math.sin(self.yaw)])
            self.xy = np.clip(nxt, 0.0, self.world.area_m)
        T = _pose(float(self.xy[0]), float(self.xy[1]), self.yaw)
        d = np.linalg.norm(self.world.position_xyz_m[:, :2] - self.xy, axis=1)
        near = np.argsort(d)[: self.n]
        p_world = self.world.position_xyz_m[near]
        Tinv = np.linalg.inv(T)
        p_body = p_world @ Tinv[:3, :3].T + Tinv[:3, 3] + self.rng.normal(0, 0.05, p_world.shape)
        objs = []
        for j, p in zip(near, p_body):
            e = self.emb[j] + self.rng.normal(0.0, 0.02 / math.sqrt(self.dim), self.dim)
            objs.append(ObjectNode(id=f"o{j}", position=tuple(float(x) for x in p),
                                   embedding=[float(x) for x in e / np.linalg.norm(e)],
                                   variance=0.01, n_obs=int(self.rng.integers(2, 7))))
        odo = None
        if self._T_prev is not None:
            odo = Odometry(from_keyframe=self.keyframe - 1,
                           T_from_to=_transform(np.linalg.inv(self._T_prev) @ T),
                           covariance=_ODOMETRY_COV)
        sub = Submap(robot_id=self.robot, session_id=self.session, seq=seq, objects=objs,
                     up=(0.0, 0.0, 1.0), keyframe=self.keyframe, odometry=odo,
                     stamp=float(seq))
        self._T_prev = T
        self.keyframe += 1
        return sub


def large_submap(world: SoakWorld, plan: SoakPlan) -> Submap:
    """LARGE_ROBOT's one submap: every world object seen from a keyframe of its own, and
    `plan.large_objects` in all with objects of random appearance in an area beside the world."""
    rng = np.random.default_rng([plan.seed, 97])
    sub = RobotWalk(world, LARGE_ROBOT, plan.dim, len(world.position_xyz_m), plan.step_m,
                    rng).next_submap(0)
    n = plan.large_objects - len(sub.objects)
    xyz = np.column_stack([rng.uniform(0, world.area_m, n) + 2 * world.area_m,
                           rng.uniform(0, world.area_m, n), rng.uniform(-2, 2, n)])
    e = rng.normal(size=(n, plan.dim))
    e /= np.linalg.norm(e, axis=1, keepdims=True)
    more = [ObjectNode(id=f"x{i}", position=tuple(float(v) for v in p),
                       embedding=[float(v) for v in row], variance=0.01, n_obs=2)
            for i, (p, row) in enumerate(zip(xyz, e))]
    return sub.model_copy(update={"objects": [*sub.objects, *more]})


# ------------------------------------------------------------------------------ hostile payloads


def _refused_by_decoder(data: bytes) -> bool:
    try:
        decode_message(data)
    except MergeError:
        return True
    return False


def flood_payloads(good: Submap, n: int, profile: Profile) -> list[bytes]:
    """The valid payload of `good` (its robot's seq 0) and `n` byte-variants of it: each the
    same submap with one embedding value nudged, so each decodes and conflicts with the first."""
    seq = good.seq if good.seq is not None else 0
    out = [encode_message(good, profile, good.robot_id, seq)]
    for i in range(n):
        objs = list(good.objects)
        e = list(objs[0].embedding)
        e[i % len(e)] += 1e-3 * (1 + i // len(e))
        objs[0] = objs[0].model_copy(update={"embedding": e})
        out.append(encode_message(good.model_copy(update={"objects": objs}), profile,
                                  good.robot_id, seq))
    return out


def hostile_schedule(rate_hz: float, duration_s: float, rng: np.random.Generator
                     ) -> np.ndarray:
    """Send times (N,) in s from the start of a Poisson stream of `rate_hz` over `duration_s`,
    N = round(rate_hz * duration_s) (its expected count): fixed here, so that a slow machine
    sends as many as a fast one. Given their number, a Poisson stream's times are independent
    and uniform over the span: sorted uniform draws."""
    n = round(rate_hz * duration_s)
    return np.sort(rng.uniform(0.0, duration_s, n))


def hostile_payload(kind: HostileKind, robot: str, seq: int, good: Submap,
                    other: Submap, max_payload_bytes: int, rng: np.random.Generator
                    ) -> tuple[str, bytes]:
    """(key suffix below the fleet root, payload) of one hostile message from `robot`.

    `good` is a valid submap of `robot` (session s0, seq `seq`), `other` one of a valid robot.
    Every kind is refused by the service: by the decoder (checked here for the corrupted kind,
    re-drawn until it is), the size limit, or the key and name checks."""
    full = encode_message(good, Profile.FULL, robot, seq)
    key = f"submap/{robot}/{good.session_id}"
    if kind is HostileKind.RANDOM_BYTES:
        return key, rng.bytes(int(rng.integers(1, 4096)))
    if kind is HostileKind.TRUNCATED:
        return key, full[: int(rng.integers(1, len(full)))]
    if kind is HostileKind.CORRUPTED:
        for _ in range(50):
            data = bytearray(full)
            at = int(rng.integers(0, len(data) - 8))
            n = int(rng.integers(1, 32))
            data[at:at + n] = rng.bytes(min(n, len(data) - at))
            if _refused_by_decoder(bytes(data)):
                return key, bytes(data)
        return key, full[: len(full) // 2]  # 50 corruptions the decoder took: truncate instead
    if kind in (HostileKind.SCHEMA_VERSION, HostileKind.CODEC_VERSION, HostileKind.NAN):
        tree = msgpack.unpackb(full, raw=False)
        if kind is HostileKind.SCHEMA_VERSION:
            tree[0] = 2
        elif kind is HostileKind.CODEC_VERSION:
            tree[1] = 99
        else:
            blob = bytearray(tree[6][13])
            blob[-4:] = np.array([np.nan], dtype="<f4").tobytes()  # the last embedding value
            tree[6][13] = bytes(blob)
        return key, msgpack.packb(tree, use_bin_type=True)
    if kind is HostileKind.OVERSIZE:
        return key, rng.bytes(max_payload_bytes + 1)
    if kind is HostileKind.KEY_SESSION:
        return f"submap/{robot}/x{good.session_id}", full
    if kind is HostileKind.EXTRA_LEVELS:
        return f"{key}/extra/deep", full
    # OTHER_ROBOT: a valid robot's message under the attacker's key
    return key, encode_message(other, Profile.FULL, other.robot_id, seq)


def agent_publisher(session: Any, key: str, cache_samples: int = CACHE_SAMPLES) -> Any:
    """The submap publisher exactly as the reference agent declares it (fleet/agent.py Agent):
    zenoh-ext advanced publisher with a cache, sample-miss detection (heartbeat), publisher
    detection, blocking congestion control, the msgpack encoding."""
    import zenoh
    from zenoh.ext import CacheConfig, MissDetectionConfig, declare_advanced_publisher

    return declare_advanced_publisher(
        session, key, cache=CacheConfig(max_samples=cache_samples),
        sample_miss_detection=MissDetectionConfig(heartbeat=HEARTBEAT_S),
        publisher_detection=True, congestion_control=zenoh.CongestionControl.BLOCK,
        encoding=zenoh.Encoding(keys.MSGPACK_ENCODING),
    )


__all__ = ["CACHE_SAMPLES", "DEFAULT_MAX_PAYLOAD", "FLOOD_ROBOT", "HEARTBEAT_S", "HOSTILE_ROBOTS",
           "HOSTILE_SEQ0", "LARGE_ROBOT", "HostileKind", "RobotWalk", "SoakPlan", "SoakWorld",
           "agent_publisher", "flood_payloads", "hostile_payload", "hostile_schedule",
           "large_submap"]
