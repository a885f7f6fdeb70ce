"""`mergesvc bench soak`: a real `mergesvc serve` process under a fleet of N robots publishing at
their own rates for a set time, with hostile payloads, robots of another embedding model and
kill -9 restarts mixed in (issue 14). Reports throughput, latency and RSS over time, and what
became of every submap sent.

What runs:
  - the service: `mergesvc serve` as a subprocess (the command is passed in: cli gives
    `python -m mergesvc.cli`), an embedded router on a free loopback port (scouting off), its
    own store in a temporary folder, the fleet's embedding dimension declared
    (MERGESVC_SERVICE__EMBEDDING_DIM) as a deployment declares it. At `restarts` random moments
    it is killed with SIGKILL and started again on the same store; at the end it gets SIGTERM;
  - N valid robots, each a thread with its own Zenoh client session, publishing with the
    agents' advanced publisher (fleet/agent.py: cache of 10,000 samples, sample-miss detection
    with a 0.5 s heartbeat, publisher detection, CongestionControl.BLOCK; built here the same
    way, `agent_publisher`: bench may not import fleet), so a restart loses nothing. Each robot
    publishes at its own rate (uniform in `rate_hz`, seeded; Poisson arrivals) keyframe
    submaps with odometry of a seeded world shared by the fleet (`SoakWorld`: robots wander
    one area, so sessions overlap and the service finds inter-robot factors), coded int8.
    Half the robots (seeded) move to a second session at a random moment. Each (robot,
    session, seq) is sent once (its bytes kept; the cache may replay them) and recorded;
  - K mismatching robots: the same, with embeddings of `mismatch_dim` (another model): every
    one of their submaps must be refused (error code embedding_dim), nobody else's;
  - one attacker session sending `hostile_fraction` of all traffic as plain blocking puts, on
    the keys of robots h0..h3: random bytes, truncated, corrupted (re-drawn until the decoder
    refuses it), wrong schema or codec version, a NaN embedding, oversize (the service's
    `max_payload_bytes` + 1), a valid submap on another session's key, on a key with extra
    levels, or under another robot's name. The attacker pauses around each kill until every
    hostile payload sent was answered (bounded), so "every one refused and answered" is
    exact;
  - a monitor session counting the answers on error/**, factor/** and result/** (the
    service's result of each submap, where it sends one) per robot, and sampling
    the status queryable (`latency_ms`, `delay_ms`, queue) every `status_period_s`; the
    service's RSS (psutil if installed, else /proc/<pid>/status VmRSS) and the part of it in
    shared memory (/proc/<pid>/status RssShmem) every `rss_period_s`.

The end: publishing stops; the driver waits (at most `drain_timeout_s`) until every valid
submap sent is stored and none is pending, stops the service (SIGTERM), then reads the store
read-only (sqlite3): valid submaps lost (sent, never stored), duplicated (a key stored twice, or
a conflicting payload), failed, pending; rows of hostile or mismatching robots (must be none);
`PRAGMA integrity_check`; tracebacks in the service's log. Over time, from the store's
received/processed stamps and the send times: throughput (processed submaps/s) and end-to-end
latency (sent -> processed, p50/p99 per bin), with the status samples and RSS.

Targets printed: 0 valid lost, failed or pending; every hostile payload refused and answered;
the mismatching robots refused and the others never; RSS growth under 100 MB (the largest RSS
of any service process minus the first process's once warm: its sample nearest to min(30 s,
10 % of the run); the first sample, taken before the service's lazy imports, is reported too).
The growth is of the RSS without its shared memory: every robot here is a Zenoh client on the
same host, and zenoh 1.x moves each payload over 3 kB (a submap is) through the sender's shared
memory pool (16 MiB by default), which the service maps. Each pool counts in the service's RSS
in full once the pool has gone round (measured: 20 mappings of 16.0 MB, 320 MB of a 482 MB RSS
at 40 s of 20 robots), though it is the robots' memory, held once on the host, and a fleet
over the network has none. Both series are reported.

`SoakPlan.quick()` is the test's variant: 3 robots, 10 s, 1 restart, 1 mismatching robot, 20 %
hostile.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import logging
import math
import os
import re
import signal
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from mergesvc.bench.scoring import check_count
from mergesvc.core.model import ErrorMessage, ObjectNode, Odometry, Submap, Transform
from mergesvc.errors import InputError, MergeError
from mergesvc.wire import Profile, decode_message, encode_message, keys
from mergesvc.wire.session import make_zenoh_config

log = logging.getLogger(__name__)

#: The agents' publisher (fleet/agent.py `Agent`): samples kept for a late or restarted service.
CACHE_SAMPLES = 10_000
#: Sample-miss heartbeat of the agents' publisher, s.
HEARTBEAT_S = 0.5
#: The service's default `max_payload_bytes` (fleet/service.py ServiceConfig).
DEFAULT_MAX_PAYLOAD = 4 * 2**20
HOSTILE_ROBOTS = ("h0", "h1", "h2", "h3")
HOSTILE_SEQ0 = 10**9  # hostile submaps' seqs: never one a valid robot uses
RSS_TARGET_MB = 100.0
_FACTOR_ID = re.compile(r"^(?P<ra>[^.]+)\.(?P<sa>[^-]+)-(?P<rb>[^.]+)\.(?P<sb>[^-]+)-(?P<seq>\d+)$")


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

    @classmethod
    def quick(cls, seed: int = 0) -> SoakPlan:
        return cls(robots=3, duration_s=10.0, hostile_fraction=0.2, mismatch_robots=1,
                   restarts=1, seed=seed, rate_hz=(1.0, 2.0), status_period_s=1.0,
                   drain_timeout_s=60.0, restart_pause_s=(0.0, 0.5), world_objects=120,
                   area_m=80.0)

    def check(self) -> None:
        """InputError on a plan that cannot run or would break the service's limits."""
        check_count("robots", self.robots)
        check_count("mismatch robots", self.mismatch_robots, 0)
        check_count("restarts", self.restarts, 0)
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


# ------------------------------------------------------------------------------ hostile payloads


def _refused_by_decoder(data: bytes) -> bool:
    try:
        decode_message(data)
    except MergeError:
        return True
    return False


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


# ------------------------------------------------------------------------------ processes


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


def _proc_status_bytes(pid: int, field: str) -> int | None:
    """A kB field of /proc/<pid>/status in bytes; None when the process is gone or the kernel
    does not say."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(f"{field}:"):
                return int(line.split()[1]) * 1024
    except OSError:
        return None
    return None


def shmem_bytes(pid: int) -> int | None:
    """The part of process `pid`'s RSS in shared memory (RssShmem: the Zenoh shared memory
    pools of same-host clients it maps); None when it is gone or the kernel does not say."""
    return _proc_status_bytes(pid, "RssShmem")


def rss_bytes(pid: int) -> int | None:
    """Resident set size of process `pid` (None when it is gone)."""
    try:
        import psutil
    except ImportError:
        psutil = None
    if psutil is not None:
        try:
            return int(psutil.Process(pid).memory_info().rss)
        except psutil.Error:
            return None
    return _proc_status_bytes(pid, "VmRSS")


class ServiceProcess:
    """`mergesvc serve` as a subprocess on one store and one endpoint, started again after
    each kill; its output appended to `log_path`."""

    def __init__(self, command: Sequence[str], fleet: str, store: Path, endpoint: str,
                 zenoh_file: Path, log_path: Path, env: dict[str, str],
                 extra_args: Sequence[str] = ()) -> None:
        self.args = [*command, "serve", "--fleet", fleet, "--store", str(store), "--listen",
                     endpoint, "--config", str(zenoh_file), *extra_args]
        self.env, self.log_path = env, log_path
        self.proc: subprocess.Popen | None = None
        self.starts = 0

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc is not None and self.proc.poll() is None else None

    def start(self) -> None:
        with self.log_path.open("ab") as out:
            self.proc = subprocess.Popen(self.args, stdout=out, stderr=subprocess.STDOUT,
                                         env=self.env, start_new_session=True)
        self.starts += 1

    def kill(self) -> None:
        """SIGKILL: no clean shutdown."""
        if self.proc is not None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.proc.pid, signal.SIGKILL)
            self.proc.wait(timeout=30)

    def stop(self, timeout_s: float = 60.0) -> int | None:
        """SIGTERM, then SIGKILL after `timeout_s`; the exit code."""
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.kill()
        return self.proc.returncode


# ------------------------------------------------------------------------------ the ledger


@dataclass
class Ledger:
    """What was sent and what came back, shared by the driver's threads."""

    t0: float = field(default_factory=time.time)
    valid: dict[tuple[str, str, int], float] = field(default_factory=dict)  # key -> sent at
    mismatch: dict[tuple[str, str, int], float] = field(default_factory=dict)
    hostile: list[tuple[float, str]] = field(default_factory=list)  # (sent at, kind)
    errors: dict[str, Counter] = field(default_factory=lambda: defaultdict(Counter))
    factors: dict[str, set[str]] = field(default_factory=lambda: defaultdict(set))
    first_factor_at: dict[tuple[str, str, int], float] = field(default_factory=dict)
    results: dict[str, Counter] = field(default_factory=lambda: defaultdict(Counter))
    first_result_at: dict[tuple[str, str, int], float] = field(default_factory=dict)
    bytes_valid: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def hostile_answered(self) -> int:
        with self.lock:
            return sum(sum(self.errors[r].values()) for r in HOSTILE_ROBOTS)

    def on_error(self, sample: Any) -> None:
        robot = str(sample.key_expr).rsplit("/", 1)[-1]
        try:
            msg = decode_message(sample.payload.to_bytes())[1]
            code = msg.code if isinstance(msg, ErrorMessage) else "?"
        except MergeError:
            code = "undecodable"
        with self.lock:
            self.errors[robot][code] += 1

    def on_result(self, sample: Any) -> None:
        """The service's result of one submap (JSON on result/{robot}): counted per outcome."""
        robot = str(sample.key_expr).rsplit("/", 1)[-1]
        now = time.time()
        try:
            doc = json.loads(sample.payload.to_bytes())
            outcome = str(doc["outcome"])
            k = (robot, doc.get("session"), doc.get("seq"))
        except (ValueError, KeyError, TypeError):
            outcome, k = "unreadable", None
        with self.lock:
            self.results[robot][outcome] += 1
            if k is not None and k[1] is not None and k[2] is not None:
                self.first_result_at.setdefault((k[0], str(k[1]), int(k[2])), now)

    def on_factor(self, sample: Any) -> None:
        parts = str(sample.key_expr).rsplit("/", 2)
        robot, fid = parts[-2], parts[-1]
        now = time.time()
        with self.lock:
            self.factors[robot].add(fid)
            m = _FACTOR_ID.match(fid)
            if m is not None:
                k = (m["rb"], m["sb"], int(m["seq"]))
                self.first_factor_at.setdefault(k, now)


# ------------------------------------------------------------------------------ the run


def _seeds(seed: int, n: int) -> list[np.random.Generator]:
    return [np.random.default_rng(s) for s in np.random.SeedSequence([seed, 7]).spawn(n)]


class _Gate:
    """Pauses the attacker: `hold()` blocks new hostile sends until released."""

    def __init__(self) -> None:
        self._open = threading.Event()
        self._open.set()
        self.busy = threading.Lock()  # held by the attacker while it sends one payload

    def wait_open(self, stop: threading.Event) -> bool:
        while not self._open.wait(0.2):
            if stop.is_set():
                return False
        return True

    @contextlib.contextmanager
    def hold(self) -> Iterator[None]:
        self._open.clear()
        with self.busy:  # a send under way finishes first
            pass
        try:
            yield
        finally:
            self._open.set()


def _robot_loop(walk: RobotWalk, session: Any, plan: SoakPlan, rate_hz: float,
                switch_at_s: float | None, t_start: float, stop: threading.Event,
                ledger: Ledger, book: dict, publishers: list) -> None:
    """One robot: Poisson submaps at `rate_hz` until `stop`; a second session at `switch_at_s`.
    Its publishers stay declared (their caches) until the driver closes the session."""
    root = keys.fleet_root(plan.fleet)
    publishers.append(session.liveliness().declare_token(keys.alive_key(root, walk.robot)))
    pub = agent_publisher(session, keys.submap_key(root, walk.robot, walk.session))
    publishers.append(pub)
    seq, t_next = 0, t_start + float(walk.rng.exponential(1.0 / rate_hz))
    while not stop.wait(max(0.0, t_next - time.monotonic())):
        if switch_at_s is not None and time.monotonic() - t_start >= switch_at_s:
            switch_at_s = None
            walk.new_session("s1")
            pub = agent_publisher(session, keys.submap_key(root, walk.robot, walk.session))
            publishers.append(pub)
        sub = walk.next_submap(seq)
        data = encode_message(sub, plan.profile, walk.robot, seq)
        with ledger.lock:
            book[(walk.robot, walk.session, seq)] = time.time()
            ledger.bytes_valid += len(data)
        pub.put(data)
        seq += 1
        t_next += float(walk.rng.exponential(1.0 / rate_hz))


def _attacker_loop(session: Any, plan: SoakPlan, rate_hz: float, world: SoakWorld,
                   rng: np.random.Generator, t_start: float, stop: threading.Event,
                   gate: _Gate, ledger: Ledger) -> None:
    import zenoh

    root = keys.fleet_root(plan.fleet)
    kinds = list(HostileKind)
    n = 0
    victim = RobotWalk(world, "r00", plan.dim, plan.objects_per_submap, plan.step_m,
                       np.random.default_rng([plan.seed, 99]))
    t_next = t_start + float(rng.exponential(1.0 / rate_hz))
    while not stop.wait(max(0.0, t_next - time.monotonic())):
        t_next += float(rng.exponential(1.0 / rate_hz))
        if not gate.wait_open(stop):
            return
        with gate.busy:
            robot = HOSTILE_ROBOTS[n % len(HOSTILE_ROBOTS)]
            kind = kinds[int(rng.integers(len(kinds)))]
            walk = RobotWalk(world, robot, plan.dim, plan.objects_per_submap, plan.step_m,
                             np.random.default_rng([plan.seed, 100 + n]))
            seq = HOSTILE_SEQ0 + n
            suffix, data = hostile_payload(kind, robot, seq, walk.next_submap(seq),
                                           victim.next_submap(HOSTILE_SEQ0 + n),
                                           plan.max_payload_bytes, rng)
            with ledger.lock:
                ledger.hostile.append((time.time(), kind.value))
            session.put(f"{root}/{suffix}", data,
                        congestion_control=zenoh.CongestionControl.BLOCK)
            n += 1


def _status(session: Any, fleet: str, timeout_s: float = 2.0) -> tuple[dict | None, int]:
    """The status reply (None without one) and its size in bytes."""
    # the counts only: the merged poses grow with every keyframe (MergeService.status)
    selector = keys.status_key(keys.fleet_root(fleet)) + "?poses=false"
    for reply in session.get(selector, timeout=timeout_s):
        if reply.ok is not None:
            data = reply.ok.payload.to_bytes()
            return json.loads(data), len(data)
    return None, 0


def _wait(predicate: Callable[[], bool], timeout_s: float, step_s: float = 0.25) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(step_s)
    return predicate()


def _read_store(path: Path) -> sqlite3.Connection:
    return sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=10.0)


def _stored_keys(path: Path) -> tuple[set[tuple[str, str, int]], int]:
    """Keys of the stored submaps and how many are pending (empty before the store exists)."""
    if not path.exists():
        return set(), 0
    try:
        with contextlib.closing(_read_store(path)) as db:
            rows = db.execute("SELECT robot_id, session_id, seq, status FROM submaps").fetchall()
    except sqlite3.Error:
        return set(), -1
    return {(r, s, int(q)) for r, s, q, _ in rows}, sum(1 for *_, st in rows if st == "pending")


def run_soak(plan: SoakPlan, serve_command: Sequence[str] | None = None,
             serve_args: Sequence[str] = (), echo: Callable[[str], Any] = print,
             log_path: Path | None = None) -> dict[str, Any]:
    """Run the soak (see the module docstring) and return its report. `serve_command` starts
    the CLI (`[python, -m, mergesvc.cli]` by default), `serve_args` are added to `serve`
    (e.g. `--settings FILE`); the service's output goes to `log_path` (else a temporary
    file). Raises InputError for a bad plan, MergeError when the service does not come up."""
    import zenoh

    plan.check()
    command = list(serve_command or [sys.executable, "-m", "mergesvc.cli"])
    world = SoakWorld.make(plan)
    rngs = _seeds(plan.seed, plan.robots + plan.mismatch_robots + 3)
    ctl_rng, att_rng = rngs[-1], rngs[-2]
    with tempfile.TemporaryDirectory(prefix="mergesvc-soak-") as tmp:
        tmpdir = Path(tmp)
        store = tmpdir / "soak.db"
        port = _free_port()
        endpoint = f"tcp/127.0.0.1:{port}"
        zfile = tmpdir / "zenoh.json5"
        zfile.write_text(json.dumps({"scouting": {"multicast": {"enabled": False},
                                                  "gossip": {"enabled": False}, "delay": 0}}))
        env = {**os.environ, "PYTHONUNBUFFERED": "1",
               "MERGESVC_SERVICE__EMBEDDING_DIM": str(plan.dim)}
        svc = ServiceProcess(command, plan.fleet, store, endpoint, zfile,
                             log_path or tmpdir / "serve.log", env, serve_args)
        if log_path is not None:
            log_path.parent.mkdir(parents=True, exist_ok=True)
            log_path.write_bytes(b"")
        client = make_zenoh_config(mode="client", connect=[endpoint], scouting=False)
        ledger = Ledger()
        stop = threading.Event()
        sampler_stop = threading.Event()
        gate = _Gate()
        sessions: list[Any] = []
        publishers: list[list[Any]] = []
        threads: list[threading.Thread] = []
        samples: list[dict[str, Any]] = []
        rss: list[tuple[float, float, int, float]] = []  # (t, MB, incarnation, shmem MB)
        restarts: list[dict[str, float]] = []
        svc.start()
        try:
            monitor = zenoh.open(client) if _wait_router(client, plan.start_timeout_s) else None
            if monitor is None:
                raise MergeError(f"the service did not come up on {endpoint} (log: "
                                 f"{svc.log_path})")
            sessions.append(monitor)
            root = keys.fleet_root(plan.fleet)
            subs = [monitor.declare_subscriber(keys.all_errors(root), ledger.on_error),
                    monitor.declare_subscriber(keys.all_factors(root), ledger.on_factor),
                    monitor.declare_subscriber(f"{root}/result/**", ledger.on_result)]
            if not _wait(lambda: _status(monitor, plan.fleet)[0] is not None,
                         plan.start_timeout_s):
                raise MergeError(f"the service does not answer status (log: {svc.log_path})")
            t_start = time.monotonic()
            ledger.t0 = time.time()

            def sample_loop() -> None:
                next_status = 0.0
                while not sampler_stop.wait(plan.rss_period_s):
                    t = time.time() - ledger.t0
                    pid = svc.pid
                    b = rss_bytes(pid) if pid is not None else None
                    if b is not None:
                        shm = shmem_bytes(pid) if pid is not None else None
                        rss.append((t, b / 2**20, svc.starts, (shm or 0) / 2**20))
                    if time.monotonic() >= next_status:
                        next_status = time.monotonic() + plan.status_period_s
                        st, size = _status(monitor, plan.fleet)
                        if st is not None:
                            samples.append({
                                "t_s": t, "bytes": size, "incarnation": svc.starts,
                                "latency_ms": st.get("latency_ms"),
                                "delay_ms": st.get("delay_ms"),
                                "queued": st["submaps"]["queued"],
                                "stored": st["submaps"]["stored"],
                                "factors_active": st["factors"]["active"]})

            threads.append(threading.Thread(target=sample_loop, name="soak-sampler",
                                            daemon=True))
            # the robots: valid ones, then the mismatching ones
            rates = []
            for i in range(plan.robots + plan.mismatch_robots):
                mismatch = i >= plan.robots
                robot = f"m{i - plan.robots}" if mismatch else f"r{i:02d}"
                rng = rngs[i]
                rate = float(rng.uniform(*plan.rate_hz))
                rates.append(rate)
                switch = (float(rng.uniform(0.2, 0.8)) * plan.duration_s
                          if rng.random() < plan.second_session_p else None)
                walk = RobotWalk(world, robot, plan.mismatch_dim if mismatch else plan.dim,
                                 plan.objects_per_submap, plan.step_m, rng)
                s = zenoh.open(client)
                sessions.append(s)
                held: list[Any] = []
                publishers.append(held)
                book = ledger.mismatch if mismatch else ledger.valid
                threads.append(threading.Thread(
                    target=_robot_loop, name=f"soak-{robot}", daemon=True,
                    args=(walk, s, plan, rate, switch, t_start, stop, ledger, book, held)))
            valid_rate = sum(rates[: plan.robots])
            hostile_rate = valid_rate * plan.hostile_fraction / (1.0 - plan.hostile_fraction)
            if hostile_rate > 0:
                attacker = zenoh.open(client)
                sessions.append(attacker)
                threads.append(threading.Thread(
                    target=_attacker_loop, name="soak-attacker", daemon=True,
                    args=(attacker, plan, hostile_rate, world, att_rng, t_start, stop, gate,
                          ledger)))
            kill_at = sorted(float(x) for x in ctl_rng.uniform(0.15, 0.85, plan.restarts)
                             * plan.duration_s)
            echo(f"soak: {plan.robots} robots ({valid_rate:.1f} submaps/s), "
                 f"{plan.mismatch_robots} of another model, {hostile_rate:.2f} hostile/s, "
                 f"{plan.restarts} kill -9 at {', '.join(f'{t:.0f}' for t in kill_at) or '-'} "
                 f"s of {plan.duration_s:.0f} s; service on {endpoint}")
            for th in threads:
                th.start()
            for at in kill_at:
                while time.monotonic() - t_start < at:
                    time.sleep(min(0.2, max(0.0, at - (time.monotonic() - t_start))))
                restarts.append(_restart(svc, monitor, plan, gate, ledger, ctl_rng, echo))
            while time.monotonic() - t_start < plan.duration_s:
                time.sleep(0.2)
            stop.set()
            for th in threads[1:]:
                th.join(timeout=30.0)
            sent_at_end = len(ledger.valid)
            echo(f"soak: publishing stopped ({sent_at_end} valid submaps sent); draining")
            t_drain = time.monotonic()

            def drained() -> bool:
                stored, pending = _stored_keys(store)
                return pending == 0 and set(ledger.valid) <= stored

            is_drained = _wait(drained, plan.drain_timeout_s, 0.5)
            _wait(lambda: ledger.hostile_answered() >= len(ledger.hostile), 10.0)
            drain_s = time.monotonic() - t_drain
            sampler_stop.set()
            threads[0].join(timeout=10.0)
            for sub in subs:
                sub.undeclare()
            exit_code = svc.stop()
        finally:
            stop.set()
            sampler_stop.set()
            for held in publishers:
                for ent in held:
                    with contextlib.suppress(Exception):
                        ent.undeclare()
            for s in sessions:
                with contextlib.suppress(Exception):
                    s.close()
            svc.stop(timeout_s=10.0)
        log_text = svc.log_path.read_text(errors="replace")
        report = _report(plan, store, ledger, samples, rss, restarts, rates,
                         drained=is_drained, drain_s=drain_s, exit_code=exit_code,
                         log_text=log_text)
    return report


def _free_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _wait_router(config: Any, timeout_s: float) -> bool:
    """Whether a client session can open on the service's router within `timeout_s`."""
    import zenoh

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            zenoh.open(config).close()
            return True
        except zenoh.ZError:
            time.sleep(0.3)
    return False


def _restart(svc: ServiceProcess, monitor: Any, plan: SoakPlan, gate: _Gate, ledger: Ledger,
             rng: np.random.Generator, echo: Callable[[str], Any]) -> dict[str, float]:
    """kill -9 the service and start it again on the same store; the attacker waits (its
    payloads sent so far answered first, at most 10 s)."""
    with gate.hold():
        _wait(lambda: ledger.hostile_answered() >= len(ledger.hostile), 10.0, 0.1)
        t_kill = time.time()
        svc.kill()
        time.sleep(float(rng.uniform(*plan.restart_pause_s)))
        svc.start()
        up = _wait(lambda: _status(monitor, plan.fleet, 1.0)[0] is not None,
                   plan.start_timeout_s)
        t_up = time.time()
    if not up:
        raise MergeError(f"the service did not come back after a kill (log: {svc.log_path})")
    echo(f"soak: kill -9 at {t_kill - ledger.t0:.1f} s, answering again after "
         f"{t_up - t_kill:.1f} s")
    return {"killed_at_s": t_kill - ledger.t0, "down_s": t_up - t_kill}


# ------------------------------------------------------------------------------ the report


def _pct(values: Sequence[float], q: float) -> float | None:
    return float(np.percentile(np.asarray(values, dtype=np.float64), q)) if len(values) else None


def _report(plan: SoakPlan, store: Path, ledger: Ledger, samples: list[dict[str, Any]],
            rss: list[tuple[float, float, int, float]], restarts: list[dict[str, float]],
            rates: list[float], *, drained: bool, drain_s: float, exit_code: int | None,
            log_text: str) -> dict[str, Any]:
    with contextlib.closing(_read_store(store)) as db:
        rows = db.execute("SELECT robot_id, session_id, seq, status, received_at_s, "
                          "processed_at_s FROM submaps").fetchall()
        conflicts = int(db.execute("SELECT COUNT(*) FROM submap_conflicts").fetchone()[0])
        factor_rows = dict(db.execute("SELECT status, COUNT(*) FROM factors GROUP BY status"))
        integrity = str(db.execute("PRAGMA integrity_check").fetchone()[0])
    t0 = ledger.t0
    count = Counter((r, s, int(q)) for r, s, q, *_ in rows)
    row_of = {(r, s, int(q)): (st, rec, proc) for r, s, q, st, rec, proc in rows}
    valid = ledger.valid
    stored_valid = [k for k in valid if k in row_of]
    status_counts = Counter(row_of[k][0] for k in stored_valid)
    foreign = [k for k in row_of if k not in valid]
    # end-to-end latency (sent -> processed) and the store's delay (stored -> processed)
    e2e = [(row_of[k][2] - t0, (row_of[k][2] - valid[k]) * 1e3) for k in stored_valid
           if row_of[k][2] is not None and row_of[k][0] != "pending"]
    end_s = max([plan.duration_s] + [t for t, _ in e2e])
    bin_s = plan.bin_s or max(1.0, round(end_s / 40.0))
    edges = np.arange(0.0, end_s + bin_s, bin_s)
    series: dict[str, list] = {"t_s": [], "published_per_s": [], "processed_per_s": [],
                               "e2e_p50_ms": [], "e2e_p99_ms": []}
    sent_t = np.asarray([t - t0 for t in valid.values()])
    for lo, hi in itertools.pairwise(edges):
        lat = [ms for t, ms in e2e if lo <= t < hi]
        series["t_s"].append(float(lo))
        series["published_per_s"].append(float(np.sum((sent_t >= lo) & (sent_t < hi)) / bin_s))
        series["processed_per_s"].append(len(lat) / bin_s)
        series["e2e_p50_ms"].append(_pct(lat, 50))
        series["e2e_p99_ms"].append(_pct(lat, 99))
    rss_mb = [mb for _, mb, _, _ in rss]
    own_mb = [mb - shm for _, mb, _, shm in rss]  # without the clients' shared memory
    first = next((mb for _, mb, inc, _ in rss if inc == 1), None)
    # baseline: the first process once warm (its imports and first matches done), the sample
    # nearest to min(30 s, 10 % of the run) that precedes the first kill
    warm_s = min(30.0, 0.1 * plan.duration_s)
    warm = [(abs(t - warm_s), mb, mb - shm) for t, mb, inc, shm in rss if inc == 1]
    baseline = min(warm)[1] if warm else None
    own_baseline = min(warm)[2] if warm else None
    growth = (max(own_mb) - own_baseline) if own_mb and own_baseline is not None else None
    growth_total = (max(rss_mb) - baseline) if rss_mb and baseline is not None else None
    per_inc = {}
    for inc in sorted({r[2] for r in rss}):
        mbs = [mb for _, mb, i, _ in rss if i == inc]
        own = [mb for (_, _, i, _), mb in zip(rss, own_mb) if i == inc]
        per_inc[str(inc)] = {"first_mb": mbs[0], "max_mb": max(mbs), "last_mb": mbs[-1],
                             "max_own_mb": max(own), "last_own_mb": own[-1]}
    with ledger.lock:
        errors = {r: dict(c) for r, c in ledger.errors.items()}
        factors = {r: len(f) for r, f in ledger.factors.items()}
        first_factor = dict(ledger.first_factor_at)
        results = {r: dict(c) for r, c in ledger.results.items()}
        first_result = dict(ledger.first_result_at)
        hostile = list(ledger.hostile)
        mismatch = dict(ledger.mismatch)
    answer_ms = [(first_factor[k] - valid[k]) * 1e3 for k in valid if k in first_factor]
    result_ms = [(first_result[k] - valid[k]) * 1e3 for k in valid if k in first_result]
    for r in restarts:  # what the service could only get back from the publishers' caches
        down = (r["killed_at_s"] + t0, r["killed_at_s"] + r["down_s"] + t0)
        r["valid_sent_while_down"] = sum(1 for t in valid.values() if down[0] <= t < down[1])
    hostile_answers = sum(sum(errors.get(r, {}).values()) for r in HOSTILE_ROBOTS)
    mismatch_robots = sorted({r for r, _, _ in mismatch})
    valid_robots = sorted({r for r, _, _ in valid})
    valid_errors = {r: errors[r] for r in valid_robots if r in errors}
    lost = len(valid) - len(stored_valid)
    duplicated = sum(1 for k, n in count.items() if n > 1) + conflicts
    failed = status_counts.get("failed", 0)
    pending = status_counts.get("pending", 0)
    mismatch_refused = all(errors.get(r, {}).get("embedding_dim", 0) >= 1
                           for r in mismatch_robots)
    report: dict[str, Any] = {
        "plan": {k: (v.value if isinstance(v, Enum) else v) for k, v in asdict(plan).items()},
        "robot_rates_hz": rates,
        "restarts": restarts,
        "drained": drained, "drain_s": drain_s, "service_exit_code": exit_code,
        "valid": {"sent": len(valid), "stored": len(stored_valid), "lost": lost,
                  "duplicated": duplicated, "conflicts": conflicts,
                  "processed": status_counts.get("processed", 0),
                  "no_match": status_counts.get("no_match", 0), "failed": failed,
                  "pending": pending, "bytes_sent": ledger.bytes_valid,
                  "errors_answered": valid_errors},
        "mismatch": {"robots": mismatch_robots, "sent": len(mismatch),
                     "stored": sum(1 for k in row_of if k[0] in mismatch_robots),
                     "answers": {r: errors.get(r, {}) for r in mismatch_robots}},
        "hostile": {"sent": len(hostile), "by_kind": dict(Counter(k for _, k in hostile)),
                    "answered": hostile_answers,
                    "codes": dict(sum((Counter(errors.get(r, {})) for r in HOSTILE_ROBOTS),
                                      Counter())),
                    "stored": sum(1 for k in row_of if k[0] in HOSTILE_ROBOTS)},
        "foreign_rows": len(foreign),
        "factors": {"stored": {str(k): int(v) for k, v in factor_rows.items()},
                    "messages_per_robot": factors,
                    "answered_submaps": len(answer_ms),
                    "answer_ms": {"p50": _pct(answer_ms, 50), "p99": _pct(answer_ms, 99)}},
        "latency_ms": {"e2e_p50": _pct([ms for _, ms in e2e], 50),
                       "e2e_p99": _pct([ms for _, ms in e2e], 99),
                       "store_delay_p50": _pct([(row_of[k][2] - row_of[k][1]) * 1e3
                                                for k in stored_valid if row_of[k][2]], 50),
                       "store_delay_p99": _pct([(row_of[k][2] - row_of[k][1]) * 1e3
                                                for k in stored_valid if row_of[k][2]], 99)},
        "results": {"valid_answered": len(result_ms),
                    "answer_ms": {"p50": _pct(result_ms, 50), "p99": _pct(result_ms, 99)},
                    "per_robot": results},
        "series": series,
        "status_samples": samples,
        "rss": {"t_s": [r[0] for r in rss], "mb": rss_mb, "incarnation": [r[2] for r in rss],
                "shmem_mb": [r[3] for r in rss], "first_mb": first, "baseline_mb": baseline,
                "baseline_at_s": warm_s, "max_mb": max(rss_mb) if rss_mb else None,
                "own_baseline_mb": own_baseline, "max_own_mb": max(own_mb) if own_mb else None,
                # the target's: RSS without shared memory (module docstring)
                "growth_mb": growth, "growth_total_mb": growth_total,
                "per_incarnation": per_inc},
        "store_integrity": integrity,
        "service_log": {"tracebacks": log_text.count("Traceback (most recent call last)"),
                        "lines": log_text.count("\n")},
    }
    report["targets"] = {
        "valid_none_lost_failed_pending": lost == 0 and failed == 0 and pending == 0,
        "valid_none_duplicated": duplicated == 0,
        "hostile_all_refused_and_answered": (report["hostile"]["stored"] == 0
                                             and hostile_answers == len(hostile)),
        "mismatch_refused_others_not": (report["mismatch"]["stored"] == 0 and mismatch_refused
                                        and not valid_errors),
        "rss_growth_under_100mb": growth is not None and growth < RSS_TARGET_MB,
        "store_integrity_ok": integrity == "ok",
    }
    report["ok"] = all(report["targets"].values())
    return report


def soak_summary(report: dict[str, Any]) -> str:
    """The report's numbers for people: a few lines, the targets last."""
    v, h, m, r = report["valid"], report["hostile"], report["mismatch"], report["rss"]
    lat = report["latency_ms"]
    plan = report["plan"]

    def ms(x: float | None) -> str:
        return "-" if x is None else f"{x:.0f}"

    lines = [
        f"soak: {plan['robots']} robots, {plan['duration_s']:.0f} s, "
        f"{len(report['restarts'])} kill -9 restarts, hostile {plan['hostile_fraction']:.0%}, "
        f"{len(m['robots'])} robot(s) of another model",
        f"valid submaps: {v['sent']} sent, {v['stored']} stored, lost {v['lost']}, duplicated "
        f"{v['duplicated']}, failed {v['failed']}, pending {v['pending']} "
        f"({v['processed']} with factors, {v['no_match']} without); drained in "
        f"{report['drain_s']:.1f} s",
        f"latency sent -> processed: p50 {ms(lat['e2e_p50'])} ms, p99 {ms(lat['e2e_p99'])} ms; "
        f"stored -> processed p50 {ms(lat['store_delay_p50'])} ms, p99 "
        f"{ms(lat['store_delay_p99'])} ms; first factor back p50 "
        f"{ms(report['factors']['answer_ms']['p50'])} ms ({report['factors']['answered_submaps']} "
        f"submaps)",
        f"hostile: {h['sent']} sent, {h['answered']} answered, {h['stored']} stored; codes "
        f"{json.dumps(h['codes'], sort_keys=True)}",
        f"another model: {m['sent']} sent, {m['stored']} stored, answers "
        f"{json.dumps(m['answers'], sort_keys=True)}; errors to valid robots: "
        f"{json.dumps(v['errors_answered'], sort_keys=True)}",
        f"RSS: first {ms(r['first_mb'])} MB, at {r['baseline_at_s']:.0f} s "
        f"{ms(r['baseline_mb'])} MB, max {ms(r['max_mb'])} MB (without shared memory: at "
        f"{r['baseline_at_s']:.0f} s {ms(r['own_baseline_mb'])} MB, max {ms(r['max_own_mb'])} "
        f"MB); growth (max - at {r['baseline_at_s']:.0f} s) {ms(r['growth_mb'])} MB without "
        f"shared memory, {ms(r['growth_total_mb'])} MB with; store integrity "
        f"{report['store_integrity']}; tracebacks in the service log: "
        f"{report['service_log']['tracebacks']}",
        "targets: " + ", ".join(f"{k} {'ok' if ok else 'MISSED'}"
                                for k, ok in report["targets"].items()),
    ]
    return "\n".join(lines)


def plot_soak(report: dict[str, Any], path: Path) -> Path:
    """Throughput, latency (end to end and the service's own), and RSS over time, with the
    kills marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mergesvc.bench.figures import save_figure

    s = report["series"]
    fig, axes = plt.subplots(3, 1, figsize=(9, 8), dpi=110, sharex=True)
    ax = axes[0]
    ax.step(s["t_s"], s["published_per_s"], where="post", label="valid sent", color="0.5")
    ax.step(s["t_s"], s["processed_per_s"], where="post", label="processed", color="tab:blue")
    ax.set_ylabel("submaps / s")
    ax = axes[1]

    def nan(xs: list) -> list[float]:
        return [np.nan if x is None else x for x in xs]

    ax.plot(s["t_s"], nan(s["e2e_p50_ms"]), "o-", ms=3, label="sent -> processed p50")
    ax.plot(s["t_s"], nan(s["e2e_p99_ms"]), "o-", ms=3, label="sent -> processed p99")
    st = report["status_samples"]
    if st:
        t = [x["t_s"] for x in st]
        ax.plot(t, nan([(x["latency_ms"] or {}).get("p50") for x in st]), ":", color="k",
                label="status latency_ms p50 (processing)")
        ax.plot(t, nan([(x["latency_ms"] or {}).get("p99") for x in st]), "--", color="k",
                label="status latency_ms p99")
    ax.set_yscale("log")
    ax.set_ylabel("ms")
    ax = axes[2]
    ax.plot(report["rss"]["t_s"], report["rss"]["mb"], color="tab:green", label="service RSS")
    ax.plot(report["rss"]["t_s"], np.subtract(report["rss"]["mb"], report["rss"]["shmem_mb"]),
            color="tab:olive", label="without shared memory")
    ax.set_ylabel("MB")
    ax.set_xlabel("s since start")
    for ax in axes:
        for r in report["restarts"]:
            ax.axvline(r["killed_at_s"], color="tab:red", lw=0.8, alpha=0.7)
        ax.legend(fontsize=7, loc="upper left")
        ax.grid(alpha=0.3)
    plan = report["plan"]
    v = report["valid"]
    axes[0].set_title(
        f"soak: {plan['robots']} robots, {plan['duration_s']:.0f} s, {len(report['restarts'])} "
        f"kill -9 (red), {plan['hostile_fraction']:.0%} hostile; {v['sent']} valid sent, lost "
        f"{v['lost']}, failed {v['failed']}, pending {v['pending']}", fontsize=9)
    return save_figure(fig, path)


__all__ = ["HostileKind", "Ledger", "RobotWalk", "ServiceProcess", "SoakPlan", "SoakWorld",
           "agent_publisher", "hostile_payload", "plot_soak", "rss_bytes", "run_soak",
           "shmem_bytes", "soak_summary"]
