"""Merge service over Zenoh: submaps in (persisted first), verified matching against every other
robot session's map, inter-robot factors out, one multi-robot GNC pose graph over every
session's keyframes, fused global objects, relocalization and status queryables.

Per session the service holds (`SessionState`, rebuilt from the stored submaps on restart):
  - its keyframes: nodes "{robot}/{session}#{k}" of the pose graph (frames.KeyframeId).
    Keyframe 0 is the session's first pose, the origin of its frame. A submap with `keyframe`
    set has its positions in that keyframe's body frame; one without (old clients, `mergesvc
    match` files) is anchored at keyframe 0 with identity, i.e. in the session frame;
  - its odometry edges: each keyframe submap's `odometry` (from_keyframe -> keyframe), added to
    the graph as known inliers (never weighed by GNC, never retracted);
  - its objects: each object id from the submap with the highest seq holding it, its position
    in that submap's keyframe frame, its embedding and variance packed without loss (held
    compact, fleet/held.py: a long mission's state grew by 70 kB per submap as pydantic models;
    the accepted factors are held the same way).
A session's map for matching places every object with the current pose of its keyframe in the
session frame: keyframe 0 is the identity; keyframes the last graph solution holds (the session
is in the anchor's component) take their optimized pose relative to the solved keyframe 0; the
others are composed along odometry edges from the nearest (fewest edges) keyframe that has a
pose. Keyframes not joined to keyframe 0 by odometry (a lost submap broke the chain) are
skipped, with their objects, until they are joined (by later odometry, or by inter-robot
factors that put both pieces in the solved graph).

Matching submap b (positions in its keyframe Kb) against session a's map gives T_{a,Kb}; the
factor ties keyframe Ka of a (the keyframe most matched map objects hang on, ties to the
latest) to Kb: T_{Ka,Kb} = inv(T_{a,Ka}) T_{a,Kb} (core/factors.py). A submap without keyframe
matched against objects of a's keyframe 0 gives the frame-level factor of old (no keyframes on
the wire), which ties the two sessions' keyframes 0. Factors are published as soon as their
submap is matched; the graph is solved once per batch of submaps the worker takes from the store
(`queue_size`), at the latest every `optimize_interval_s` during a longer backlog, and only when
a submap added a factor (or an odometry edge between two keyframes already in the graph);
PoseGraph.optimize also returns its last solution while nothing changed. One solve costs about
as much as the graph is large: solving per submap made the cost per submap grow with every
accepted factor.

Admission (the Zenoh callback, before anything is stored): the size limit; a decodable submap
whose key is exactly submap/{robot}/{session} of its own payload (robot and session); the
fleet's embedding dimension (`embedding_dim`, else the first accepted submap's, kept in the store
so a restart keeps it: one robot's other model never makes another robot's submaps fail); per
robot at most `max_open_sessions_per_robot` sessions seen in the last `session_idle_s`, and a
token bucket of `submap_rate_hz` new submaps per second (up to `submap_burst` at once; replays of
stored submaps are free). A refusal is logged, counted (status "errors") and answered on the
robot's error key. Each submap is matched against at most `max_candidate_frames` other sessions,
the ones whose objects look most like its own by one index over the whole fleet's objects
(core/retrieval.py), at most `max_frames_per_robot` of one robot: the matching cost per submap
does not grow with the fleet, and one robot's many sessions cannot make everyone's submaps
expensive.

Threads: the Zenoh callback only enqueues the payload (bounded: `ingress_queue_size`); one
ingress thread checks, persists (fsync) and wakes the worker, in arrival order; one worker
thread matches. (Measured: 1,000 plain puts of 12.5 kB, default congestion control, reached the
service 1,000 of 1,000 times with an enqueue-only callback, 319 times with the fsync in the
callback.) A sample still in the ingress queue at a kill -9 is not stored: the vehicles'
advanced publishers replay it from their cache when the service is back.
Two subscribers on submap/**: the advanced one takes the samples that carry a source sequence
number (advanced publishers: it recovers their gaps) and the timestamped ones it recovers from
a cache-only publisher, a plain one every other sample (a timestamped sample both get is taken
once). The
advanced subscriber orders unsequenced samples by timestamp per clock and drops one older than
the last delivered; the router stamps all clients' puts with its clock, so of concurrent plain
publishers' submaps about 1 run in 40 (3 clients x 10 submaps) lost one.
The store is the queue: the worker takes the oldest pending rows (`Store.pending_ids`), so
nothing that was persisted can be forgotten by an in-memory queue, and memory stays bounded
under a burst. The wake-up flag is cleared before the store is read and set after each commit,
so a submap stored while the worker reads is seen on its next round.

Answers (fleet/replies.py, docs/wire.md §7 and §11): every submap gets one result on
result/{robot} (JSON, `SubmapResult`): processed with its factor ids, no_match with the verdict
of each candidate frame tried, refused with the error code (also sent, as before, as a coded
error message on error/{robot}), or failed (processing raised). A duplicate of a stored submap
gets none (its first copy had one). Status counts the results by outcome, reason and code.
Encodings: coded messages `application/msgpack`, JSON documents `application/json`
(keys.MSGPACK_ENCODING, keys.JSON_ENCODING); a query's error reply is an ErrorMessage as JSON.
"""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import queue
import threading
import time
from collections import defaultdict, deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from mergesvc.core.calibration import CalibrationConfig, scale_covariance
from mergesvc.core.config import GraphConfig, MatchConfig
from mergesvc.core.factors import (
    OdometryEdge,
    anchoring_keyframe,
    factor_from_match,
    local_fit,
    match_factor_id,
    odometry_edge,
    yields_factor,
)
from mergesvc.core.frames import FrameId, KeyframeId
from mergesvc.core.fusion import fuse_objects
from mergesvc.core.graph import GraphSolution, PoseGraph
from mergesvc.core.model import (
    ErrorMessage,
    Factor,
    FactorStatus,
    ObjectArrays,
    ObjectMap,
    ObjectNode,
    Submap,
)
from mergesvc.core.pipeline import match
from mergesvc.core.poses import compose_with_covariance, inverse_with_covariance
from mergesvc.core.retrieval import FleetIndex
from mergesvc.errors import ConfigError, MergeError, SchemaError, one_line
from mergesvc.fleet.closures import ClosureSets, ConsistencyConfig
from mergesvc.fleet.held import FactorTable, HeldObject, PackedVector
from mergesvc.fleet.mixed import ProfileViews
from mergesvc.fleet.replies import (
    NO_FRAMES,
    FrameTried,
    Outcome,
    RefusalCode,
    RelocalizeReply,
    StatusReply,
    SubmapResult,
)
from mergesvc.fleet.store import (
    META_EMBEDDING_DIM,
    META_NOISE_SCALES,
    Store,
    SubmapConflictError,
)
from mergesvc.wire import Profile, Projection, decode_message, encode_message, keys

# timestamped, unsequenced samples remembered to deliver each once (of two subscribers)
SEEN_SAMPLES = 4096
# session maps kept for matching: only those built since the last graph solution can be used
# again, and each holds its objects' arrays (about 1 MB per 100 objects at 384-d). Measured on
# the soak's stream: 16 maps hit 47 % of lookups, 8 37 %, 4 20 %, at the same cost per submap
SESSION_MAPS_CACHED = 8
log = logging.getLogger(__name__)


# Keyframes the service's pose graph solves at most (GraphConfig.max_live_nodes, rule 6 of
# core/graph.py); older ones are frozen. The 20-robot soak stream (3,200 submaps stored, 10,550
# factors): one solve 0.39 s and +63 MB of peak memory over the whole graph, 0.15 s and +16 MB
# with 1,000 live; the merge benchmarks' graphs (under 250 keyframes) never reach it.
LIVE_KEYFRAMES = 1000
CLOSURE_GROUP = "closures"  # the noise group of every inter-robot factor (calibration)


def odometry_group(robot: str) -> str:
    """The noise group of a robot's odometry edges: every session of one robot together."""
    return f"odometry:{robot}"


class ServiceConfig(BaseModel):
    """Settings of `mergesvc serve`."""

    model_config = ConfigDict(extra="forbid")

    fleet: str = Field("fleet0", min_length=1, max_length=64)
    store: str = Field("mergesvc.db", description="SQLite file (WAL); ':memory:' for tests")
    factor_profile: Profile = Field(
        Profile.COMPACT, description="codec profile of factors: compact (a bit stream, ~100 "
        "bytes) or full (the factor document as a msgpack map, with its correlations: for "
        "clients that do not decode the compact factor); f16 and int8 do not exist for factors",
    )
    max_payload_bytes: int = Field(4 * 2**20, ge=1024, description="larger submaps are refused")
    queue_size: int = Field(
        64, ge=1, description="pending submaps the worker takes from the store at once (one "
        "batch: the pose graph is solved once per batch)",
    )
    optimize_interval_s: float = Field(
        2.0, ge=0.0, description="during a backlog longer than one batch, the pose graph is "
        "solved at most this often (and always when the backlog is drained)",
    )
    embedding_dim: int | None = Field(
        None, ge=1, le=4096, description="the fleet's embedding dimension; None: fixed by the "
        "first accepted submap and kept in the store. Submaps of another dimension are refused "
        "(error code embedding_dim)",
    )
    max_open_sessions_per_robot: int = Field(
        4, ge=1, description="sessions a robot may have open (a submap within session_idle_s); "
        "a submap of one more is refused (error code too_many_sessions)",
    )
    session_idle_s: float = Field(
        600.0, gt=0.0, description="a session without a submap for this long no longer counts "
        "as open",
    )
    submap_rate_hz: float = Field(
        5.0, gt=0.0, description="new submaps per second a robot may send on average (token "
        "bucket; replays of stored submaps are free); more are refused (error code "
        "rate_limited)",
    )
    submap_burst: int = Field(
        600, ge=1, description="new submaps a robot may send at once (the bucket's size: "
        "covers the backlog a vehicle's cache replays after a service restart)",
    )
    ingress_queue_size: int = Field(
        10_000, ge=1, description="received submaps waiting to be checked and persisted (the "
        "Zenoh callback only enqueues: an fsync in the callback made a fast publisher's "
        "samples drop); more are refused (error code busy)",
    )
    max_candidate_frames: int = Field(
        3, ge=1, description="other sessions each submap is matched against at most: those "
        "whose objects look most like the submap's (one index over the fleet's objects, "
        "core/retrieval.py), so the cost per submap does not grow with the fleet",
    )
    max_frames_per_robot: int = Field(
        2, ge=1, description="... of which at most this many sessions of one robot (a robot "
        "that opens many sessions cannot take every slot)",
    )
    min_map_objects: int = Field(3, ge=3, description="frames with fewer objects are not matched")
    drift_sigma: tuple[float, float] = Field(
        (0.05, 0.5),
        description="added to every factor's covariance: rotation rad, translation m. A "
        "session's map places objects of many keyframes with estimated (drifting) poses, and "
        "a frame-level factor (old clients) ties two whole drifting frames, so a factor "
        "differs from the truth by more than the fit's own covariance says",
    )
    consistency: ConsistencyConfig = Field(
        ConsistencyConfig(), description="the pairwise-consistency test factors between two "
        "sessions pass before the graph trusts them (fleet/closures.py)")
    solve_inflation: float = Field(
        4.0, ge=1.0, description="every inter-robot factor's covariance is multiplied by this "
        "when solving (not in what is sent): successive factors share objects and errors, "
        "so the graph counts them as fewer (docs/uncertainty.md)")
    local_fit: bool = Field(
        True, description="fit each factor on the matched objects with the other session's "
        "placed around its anchoring keyframe by odometry (not by the merged solution, whose "
        "errors would become the factor's), the placements' covariance carried into the "
        "factor's; false: the match's own transform, placed by the solution, drift_sigma added")
    local_drift_sigma: tuple[float, float] = Field(
        (0.0, 0.0), description="added to a locally fitted factor's covariance: rotation rad, "
        "translation m (its placement uncertainty is in it already)")
    local_range_weighted: bool = Field(
        True, description="in the local fit, an object's noise grows with its range from the "
        "keyframe that placed it (sonar, stereo): far objects weigh less")
    local_sigma_floor_m: float = Field(
        0.01, gt=0.0, description="the smallest object noise (m) a local fit's covariance "
        "assumes, when two or three matches leave no residual to estimate it")
    match: MatchConfig = Field(
        default_factory=lambda: MatchConfig.model_validate(
            {"verify": {"min_matches": 4, "min_matches_vertical": 4, "gravity_aligned": True}}
        ),
        description="verified matching; an inter-robot factor needs 4 matched objects by "
        "default, with or without a known vertical (3 points admit coincidental fits in a "
        "small pool, and a wrong factor costs more than a late one)",
    )
    graph: GraphConfig = Field(
        GraphConfig(max_live_nodes=LIVE_KEYFRAMES, calibration=CalibrationConfig()),
        description="the GNC pose graph over the sessions' keyframes (outlier thresholds; "
        f"max_live_nodes, {LIVE_KEYFRAMES} here: past that many keyframes the oldest freeze at "
        "their solved poses, core/graph.py rule 6, so a long mission's solve stays the same "
        "size; fold_hops > 0 folds a closure into one it agrees with nearby, rule 5: a smaller "
        "graph, off by default as it cost accuracy where the odometry drifts more than its "
        "covariance says, docs/benchmarks.md)",
    )

    @field_validator("factor_profile")
    @classmethod
    def _factor_profile(cls, v: Profile) -> Profile:
        if v not in (Profile.FULL, Profile.COMPACT):
            raise ValueError(f"factors are coded full or compact, not {v.value} (docs/wire.md "
                             "§2)")
        return v


@dataclass
class ServiceStats:
    submaps_received: int = 0
    submaps_duplicate: int = 0
    submaps_processed: int = 0
    submaps_rejected: int = 0  # refused at the boundary (bad payloads, limits)
    factors_accepted: int = 0  # sent: trusted by the consistency sets
    factors_matched: int = 0  # fitted from accepted matches (sent, held or replayed)
    factors_retracted: int = 0
    matches_tried: int = 0
    relocalize_queries: int = 0
    optimizations: int = 0
    errors: dict[str, int] = field(default_factory=dict)
    results_processed: int = 0
    results_failed: int = 0
    results_no_match: dict[str, int] = field(default_factory=dict)  # per reason
    results_refused: dict[str, int] = field(default_factory=dict)  # per code
    latency_ms: list[float] = field(default_factory=list)  # processing time per submap
    delay_ms: list[float] = field(default_factory=list)  # stored -> processed, per submap
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def error(self, code: str) -> None:
        with self._lock:  # callbacks of several Zenoh threads count here
            self.errors[code] = self.errors.get(code, 0) + 1

    def result(self, res: SubmapResult) -> None:
        with self._lock:
            if res.outcome is Outcome.PROCESSED:
                self.results_processed += 1
            elif res.outcome is Outcome.FAILED:
                self.results_failed += 1
            elif res.outcome is Outcome.NO_MATCH:
                reason = str(getattr(res.reason, "value", res.reason))
                self.results_no_match[reason] = self.results_no_match.get(reason, 0) + 1
            elif res.code is not None:
                code = res.code.value
                self.results_refused[code] = self.results_refused.get(code, 0) + 1

    def result_counts(self) -> dict[str, Any]:
        with self._lock:
            return {"processed": self.results_processed,
                    "no_match": dict(self.results_no_match),
                    "refused": dict(self.results_refused),
                    "failed": self.results_failed}


class TokenBucket:
    """Per-key token bucket: `rate_hz` tokens a second, at most `burst` held."""

    def __init__(self, rate_hz: float, burst: int, clock: Callable[[], float]) -> None:
        self.rate_hz, self.burst, self.clock = rate_hz, burst, clock
        self._state: dict[str, tuple[float, float]] = {}  # key -> (tokens, at time)
        self._lock = threading.Lock()

    def take(self, key: str) -> bool:
        """One token for `key` if it has one."""
        with self._lock:
            now = self.clock()
            tokens, t = self._state.get(key, (float(self.burst), now))
            tokens = min(float(self.burst), tokens + max(0.0, now - t) * self.rate_hz)
            ok = tokens >= 1.0
            self._state[key] = (tokens - 1.0 if ok else tokens, now)
            return ok


class RefusedError(SchemaError):
    """A submap refused at the boundary; `code` is the error code the robot is sent."""

    def __init__(self, code: RefusalCode, detail: str) -> None:
        super().__init__(detail)
        self.code = code


@dataclass
class SessionState:
    """One robot session: its keyframes, the odometry edges between them, its objects."""

    frame: FrameId
    keyframes: set[int] = field(default_factory=lambda: {0})
    edges: dict[tuple[int, int], OdometryEdge] = field(default_factory=dict)
    objects: dict[str, HeldObject] = field(default_factory=dict)  # compact: fleet/held.py
    up: dict[int, np.ndarray] = field(default_factory=dict)  # declared up per keyframe frame
    version: int = 0  # bumped by every submap
    # the last declared up and odometry covariance: a vehicle sends the same ones again and
    # again, held once (a long mission's keyframes each held their own copy)
    _last_up: np.ndarray | None = field(default=None, repr=False)
    _last_cov: np.ndarray | None = field(default=None, repr=False)
    # keyframe -> its odometry neighbours (the keyframes of its edges, either way)
    _adjacent: dict[int, list[int]] = field(
        default_factory=lambda: defaultdict(list), repr=False
    )

    @property
    def name(self) -> str:
        return str(self.frame)

    def node(self, k: int) -> str:
        """The pose-graph node of keyframe k: "{robot}/{session}#{k}"."""
        return str(KeyframeId(self.frame, k))

    def add(self, sub: Submap) -> OdometryEdge | None:
        """Take a submap in (idempotent); returns its odometry edge when it is new."""
        k = 0 if sub.keyframe is None else sub.keyframe
        seq = sub.seq if sub.seq is not None else -1
        self.keyframes.add(k)
        if sub.up is not None:
            up = np.asarray(sub.up, dtype=np.float64)
            if self._last_up is None or not np.array_equal(up, self._last_up):
                up.setflags(write=False)  # shared by the keyframes that declare it
                self._last_up = up
            self.up[k] = self._last_up
        for o in sub.objects:  # the latest submap holding an object gives its estimate
            held = self.objects.get(o.id)
            if held is None or held.seq <= seq:
                self.objects[o.id] = HeldObject.of(seq, k, o)
        self.version += 1
        edge = odometry_edge(sub)
        if edge is None:
            return None
        pair = (edge.from_.k, edge.to.k)
        old = self.edges.get(pair)
        if old is not None:
            if not old.T_from_to.equals(edge.T_from_to, 1e-9):
                log.warning("%s: odometry %d -> %d sent again with another value: kept the "
                            "first", self.name, *pair)
            return None
        if self._last_cov is None or not np.array_equal(edge.covariance, self._last_cov):
            self._last_cov = edge.covariance  # (read-only: odometry_edge)
        edge = OdometryEdge(KeyframeId(self.frame, edge.from_.k), KeyframeId(self.frame, edge.to.k),
                            edge.T_from_to, self._last_cov)  # this session's names, held once
        self.edges[pair] = edge
        self.keyframes.add(edge.from_.k)
        self._adjacent[pair[0]].append(pair[1])
        self._adjacent[pair[1]].append(pair[0])
        return edge

    def placements(self, source: int, targets: set[int], scale: np.ndarray | None = None
                   ) -> dict[int, tuple[gtsam.Pose3, np.ndarray]]:
        """Pose and covariance of each target keyframe in `source`'s frame, composed along
        odometry edges from it (fewest edges first), each edge's covariance scaled per axis by
        `scale` (sigma, GTSAM order); targets not joined to it are absent."""
        def scaled(C: np.ndarray) -> np.ndarray:
            return C if scale is None else scale_covariance(C, scale)

        out = {source: (gtsam.Pose3(), np.zeros((6, 6)))}
        todo, left = deque([source]), set(targets) - {source}
        while todo and left:
            k = todo.popleft()
            T_k, S_k = out[k]
            for j in self._adjacent.get(k, ()):
                if j in out:
                    continue
                edge = self.edges.get((k, j))
                if edge is not None:
                    step = (edge.T_from_to, scaled(edge.covariance))
                else:
                    e = self.edges[(j, k)]
                    step = inverse_with_covariance(e.T_from_to, scaled(e.covariance))
                out[j] = compose_with_covariance(T_k, S_k, *step)
                left.discard(j)
                todo.append(j)
        return {k: v for k, v in out.items() if k in targets}

    def propagate(self, seeds: Mapping[int, gtsam.Pose3]) -> dict[int, gtsam.Pose3]:
        """Poses of the keyframes reachable from `seeds` (keyframe -> pose) along odometry
        edges, each composed from the nearest seed (fewest edges); seeds keep their pose."""
        poses = dict(seeds)
        todo = deque(sorted(seeds))
        while todo:
            k = todo.popleft()
            for j in self._adjacent.get(k, ()):
                if j not in poses:
                    edge = self.edges.get((k, j))
                    poses[j] = poses[k].compose(edge.T_from_to if edge is not None
                                                else self.edges[(j, k)].T_from_to.inverse())
                    todo.append(j)
        return poses


@dataclass(frozen=True)
class SessionMap:
    """A session's objects placed in its frame for matching: the held objects and where they
    are placed (positions in the session frame), each object's keyframe and the keyframe poses
    (in the session frame) used to place them. `arrays` is what `match` computes on (made once,
    when first matched); `map` the same objects as an ObjectMap (built when asked)."""

    frame: FrameId
    objects: tuple[HeldObject, ...]
    positions: tuple[tuple[float, float, float], ...]
    up: tuple[float, ...] | None
    keyframe_of: dict[str, int]
    poses: dict[int, gtsam.Pose3]

    @property
    def dim(self) -> int:
        return self.objects[0].dim

    @functools.cached_property
    def arrays(self) -> ObjectArrays:
        """The objects as ObjectArrays: the values ObjectMap.arrays() gives for `map`."""
        objs = self.objects
        var = np.empty((len(objs), self.dim))
        for k, h in enumerate(objs):
            v = h.variance
            var[k] = v.unpack() if isinstance(v, PackedVector) else v  # a number broadcasts
        return ObjectArrays(
            ids=[h.id for h in objs],
            position_xyz_m=np.array(self.positions, dtype=np.float64),
            embeddings_nd=np.array([h.embedding.unpack() for h in objs], dtype=np.float64),
            variances_nd=var,
            n_obs=np.array([h.n_obs for h in objs], dtype=np.int64),
            up_xyz=None if self.up is None else np.asarray(self.up, dtype=np.float64),
        )

    @property
    def map(self) -> ObjectMap:
        return ObjectMap(robot_id=self.frame.robot, session_id=self.frame.session,
                         objects=[h.node_at(p) for h, p in zip(self.objects, self.positions,
                                                               strict=True)],
                         up=self.up)



def _frames_of(factor: Factor) -> tuple[str, str]:
    """The two frame names a factor joins, as the store keeps them."""
    return (str(FrameId(factor.robot_a, factor.session_a)),
            str(FrameId(factor.robot_b, factor.session_b)))


def session_up(st: SessionState, poses: Mapping[int, gtsam.Pose3]) -> tuple[float, ...] | None:
    """The session frame's up, from the latest keyframe that declared one (its up rotated by
    that keyframe's pose in the session frame); None when no placed keyframe declared it."""
    for k in sorted(st.up, reverse=True):
        T = poses.get(k)
        if T is not None:
            u = np.asarray(T.rotation().matrix()) @ st.up[k]
            return tuple(float(x) for x in u / np.linalg.norm(u))
    return None


@functools.cache
def _malloc_trim() -> Callable[[int], int] | None:
    try:
        import ctypes

        fn = ctypes.CDLL("libc.so.6").malloc_trim
        fn.argtypes, fn.restype = [ctypes.c_size_t], ctypes.c_int
        return fn  # type: ignore[no-any-return]
    except (OSError, AttributeError):  # not glibc: nothing to trim
        return None


def _trim_heap() -> None:
    """Hand the C heap's free pages back to the system (glibc `malloc_trim(0)`; a no-op
    elsewhere). Each solve allocates and frees GTSAM's linear systems, tens of MB on a long
    mission's graph; glibc keeps what was freed inside its heap, so the service's RSS grew by
    the largest solve so far and by fragmentation. Measured on the 20-robot soak stream
    in-process: RSS slope 39 -> 15-18 kB per submap; 1-3 ms per call."""
    fn = _malloc_trim()
    if fn is not None:
        fn(0)


def _reply_err(query: Any, code: str, detail: str) -> None:
    """A query's error reply: an ErrorMessage document as JSON (the one error shape)."""
    import zenoh

    doc = ErrorMessage(code=code, detail=detail[:1000]).model_dump_json()
    query.reply_err(doc.encode(), encoding=zenoh.Encoding(keys.JSON_ENCODING))


class MergeService:
    """The merge service. `start()` opens everything, `close()` stops it (idempotent)."""

    def __init__(
        self,
        config: ServiceConfig,
        session: Any,
        projections: list[Projection] | None = None,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.config = config
        self.session = session
        self.projections = {p.id: p for p in projections or []}
        self._views = ProfileViews(self.projections)  # matching across profiles (fleet/mixed.py)
        self.clock = clock
        self.stats = ServiceStats()
        self.store = Store(config.store)
        self.graph = PoseGraph(config=config.graph)
        if config.solve_inflation != 1.0:
            self.graph.set_noise_scale(CLOSURE_GROUP, config.solve_inflation ** 0.5)
        self.sessions: dict[str, SessionState] = {}  # "robot/session" -> its keyframes, objects
        self.factors = FactorTable()  # factor id -> Factor, held compact (fleet/held.py)
        self._held: dict[str, Factor] = {}  # factors the consistency sets do not trust (yet)
        self._scales_saved: dict[str, np.ndarray] = {}  # noise scales as last stored
        self._closures = ClosureSets(config.consistency, self._chains)
        self.alive: set[str] = set()
        self._seq = 0
        self._lock = threading.RLock()
        self._wake = threading.Event()  # set after a submap is stored: the worker looks
        self._process_lock = threading.Lock()  # one submap processed at a time (worker, ingest)
        self._failed_rows: set[int] = set()  # failed and could not be marked: not retried
        # (key, timestamp) of unsequenced samples delivered (both subscribers get them)
        self._seen: dict[tuple[str, str], None] = {}
        self._seen_lock = threading.Lock()
        self._dirty = False  # a processed submap changed the graph: solve it
        self._last_optimize = time.monotonic()
        self._dim: int | None = config.embedding_dim
        self._admit_lock = threading.Lock()
        self._open: dict[str, dict[str, float]] = defaultdict(dict)  # robot -> session -> seen
        self._bucket = TokenBucket(config.submap_rate_hz, config.submap_burst, clock)
        self._index = FleetIndex()  # every session's object embeddings (candidate frames)
        self._indexed: dict[str, int] = {}  # session -> its version in the index
        self._stop = threading.Event()
        self._inbox: queue.Queue[tuple[str, bytes] | None] = queue.Queue(
            maxsize=config.ingress_queue_size)
        self._ingress: threading.Thread | None = None
        self._worker: threading.Thread | None = None
        self._entities: list[Any] = []
        self._root = keys.fleet_root(config.fleet)
        self._global: ObjectMap | None = None
        self._anchor: str | None = None  # the anchor session "robot/session"
        # session -> ((session version, solution count), its map): rebuilt when either changes
        self._session_maps: dict[str, tuple[tuple[int, int], SessionMap | None]] = {}
        self.solution: GraphSolution | None = None
        self._solutions = 0  # solutions taken so far (keys the session maps' cache)

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> MergeService:
        from zenoh.ext import HistoryConfig, RecoveryConfig, declare_advanced_subscriber

        try:
            self.restore()
        except BaseException:
            self.close()  # the store is not left open by a service that never started
            raise
        s = self.session
        self._entities = [
            declare_advanced_subscriber(
                s, keys.all_submaps(self._root), self._on_sequenced_submap,
                history=HistoryConfig(detect_late_publishers=True, max_samples=10_000),
                recovery=RecoveryConfig(heartbeat=True), subscriber_detection=True,
            ),
            s.declare_subscriber(keys.all_submaps(self._root), self._on_unsequenced_submap),
            s.declare_queryable(keys.relocalize_key(self._root), self._on_relocalize),
            s.declare_queryable(keys.status_key(self._root), self._on_status),
            s.liveliness().declare_subscriber(keys.all_alive(self._root), self._on_alive,
                                              history=True),
        ]
        self._ingress = threading.Thread(target=self._ingest_loop, name="mergesvc-ingress",
                                         daemon=True)
        self._ingress.start()
        self._worker = threading.Thread(target=self._work, name="mergesvc-worker", daemon=True)
        self._worker.start()
        log.info("merge service up: fleet %s, %d sessions, %d keyframes, %d factors restored",
                 self.config.fleet, len(self.sessions),
                 sum(len(st.keyframes) for st in self.sessions.values()), len(self.factors))
        return self

    def close(self) -> None:
        import zenoh

        self._stop.set()
        for ent in self._entities:
            with contextlib.suppress(zenoh.ZError):  # undeclared already, with its session
                ent.undeclare()
        self._entities = []
        if self._ingress is not None:  # what was received is persisted before closing
            self._inbox.put(None)
            self._ingress.join(timeout=30.0)
            self._ingress = None
        if self._worker is not None:
            self._worker.join(timeout=10.0)
            self._worker = None
        self.store.close()

    def __enter__(self) -> MergeService:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def restore(self) -> None:
        """After a restart: the sessions (keyframes, odometry edges, objects) from the processed
        submaps, the accepted factors, the graph solved once; then redo the submaps that were
        persisted but not processed. The graph is the one the service had: the same nodes,
        odometry edges and factors."""
        frames = self.store.frames()
        if frames:
            self._set_anchor(frames[0].frame)  # published coordinates stay in one frame
        for fr in frames:
            self._open[fr.robot_id][fr.session_id] = fr.last_seen_s
        self._restore_dim()
        for row in self.store.iter_submaps():  # a page at a time: a mission's worth
            if row.status in ("processed", "no_match"):
                sub = self._decode_submap(row.payload)
                self._views.note(str(FrameId(sub.robot_id, sub.session_id)), row.payload)
                self._add_submap(sub)
        # the factors in force and those held, in the order they were made: the consistency
        # sets take them back with the verdicts they had
        rows = [(f.created_at_s, 0, i, f, True) for i, f in
                enumerate(self.store.iter_factors(FactorStatus.ACCEPTED))]
        rows += [(f.created_at_s, 1, i, f, False) for i, f in
                 enumerate(self.store.held_factors())]
        for *_, f, trusted in sorted(rows, key=lambda r: r[:3]):
            factor = Factor.model_validate_json(f.payload)
            self._closures.offer(factor, trusted=trusted)
            if trusted:
                self.graph.add_factor_model(factor, keyframe_nodes=True, group=CLOSURE_GROUP)
                self.factors[factor.factor_id] = factor
            else:
                self._held[factor.factor_id] = factor
        self._restore_scales()
        if self.factors:
            # solved as it grew (the old keyframes frozen on the way, rule 6), with the noise
            # scales the last solve had, calibrated again only from the next submap on
            self.graph.calibrating = False
            try:
                self.graph.settle()
            except MergeError as exc:
                log.warning("pose graph optimisation failed: %s", exc)
            self._optimize(publish=False)
            self.graph.calibrating = True
        self._wake.set()  # the worker takes the pending rows from the store

    def _restore_scales(self) -> None:
        """The calibrated noise scales the service had (its last solve's), so that a restart
        solves the graph as it was solved."""
        stored = self.store.meta(META_NOISE_SCALES)
        try:
            scales = json.loads(stored) if stored else {}
            for group, s in scales.items():
                self.graph.set_noise_scale(group, s)
        except (ValueError, TypeError, AttributeError, MergeError) as exc:
            log.warning("stored noise scales unreadable, calibrating afresh: %s", one_line(exc))
        self._scales_saved = self.graph.noise_scales

    def _save_scales(self) -> None:
        """Keep the noise scales the last solution was solved with, when they changed."""
        now = self.graph.solved_noise_scales
        if now.keys() == self._scales_saved.keys() and all(
                np.array_equal(now[g], self._scales_saved[g]) for g in now):
            return
        self._scales_saved = now
        with contextlib.suppress(MergeError):  # a read-only copy (export) keeps none
            if not self.store.closed:
                self.store.set_meta(META_NOISE_SCALES, json.dumps(
                    {g: [float(x) for x in v] for g, v in now.items()}))

    def _restore_dim(self) -> None:
        """The fleet's embedding dimension: the setting, else the store's, else the first
        stored submap's (a store written before the dimension was kept)."""
        stored = self.store.meta(META_EMBEDDING_DIM)
        if stored is None:
            first = self.store.submaps()[:1]
            if first:
                stored = str(self._decode_submap(first[0].payload).dim)
        if stored is not None and self._dim is not None and int(stored) != self._dim:
            raise ConfigError(f"service.embedding_dim is {self._dim} but the store "
                              f"{self.store.path} holds a fleet of {stored}-d embeddings: use "
                              "another store")
        if self._dim is None and stored is not None:
            self._dim = int(stored)
        if self._dim is not None and not self.store.closed:
            with contextlib.suppress(MergeError):  # a read-only copy (export) keeps none
                self.store.set_meta_once(META_EMBEDDING_DIM, str(self._dim))

    # ------------------------------------------------------------------ ingress

    def _put(self, key: str, payload: bytes, json_doc: bool) -> None:
        """Publish with the encoding of what is sent (module docstring: Answers)."""
        import zenoh

        if self.session is None:  # offline (ingest): nothing to publish to
            return
        enc = keys.JSON_ENCODING if json_doc else keys.MSGPACK_ENCODING
        self.session.put(key, payload, encoding=zenoh.Encoding(enc))

    def _publish_error(self, robot: str, code: RefusalCode, detail: str, seq: int | None,
                       session: str | None = None) -> None:
        """The error message on error/{robot} and the refused result on result/{robot}."""
        import zenoh

        self.stats.error(code.value)
        try:
            res = SubmapResult(robot=robot, session=session, seq=seq, outcome=Outcome.REFUSED,
                               code=code, detail=detail[:1000])
        except ValueError as exc:  # a robot or session name from the key no reply can carry
            log.warning("no result for a refused submap of %r: %s", robot[:80], one_line(exc))
        else:
            self._publish_result(res)
        try:
            msg = encode_message(ErrorMessage(code=code.value, detail=detail[:1000],
                                              about_seq=seq),
                                 Profile.FULL, "mergesvc", self._next_seq())
            self._put(keys.error_key(self._root, robot), msg, json_doc=False)
        # an error report that cannot be made (a robot name no key can carry, an unencodable
        # detail, a closed session) is logged: it must not end the callback that reports it
        except (MergeError, ValueError, zenoh.ZError) as exc:
            log.warning("could not publish an error to %s: %s", robot, exc)

    def _publish_result(self, res: SubmapResult) -> None:
        """Count a submap's result and send it on result/{robot} (JSON)."""
        import zenoh

        self.stats.result(res)
        try:
            self._put(keys.result_key(self._root, res.robot), res.model_dump_json().encode(),
                      json_doc=True)
        # as for errors: a result that cannot be sent is logged, the caller goes on
        except (MergeError, ValueError, zenoh.ZError) as exc:
            log.warning("could not publish a result to %s: %s", res.robot, exc)

    def _next_seq(self) -> int:
        with self._lock:
            self._seq += 1
            return self._seq

    def _on_sequenced_submap(self, sample: Any) -> None:
        """The advanced subscriber's callback: samples of advanced publishers, live or
        recovered from their caches. A publisher with a cache but no sample-miss detection
        stamps its samples (no sequence number): those come here when recovered, and live
        through the plain subscriber too; `_first_delivery` lets one through."""
        if sample.source_info is not None or (
                sample.timestamp is not None and self._first_delivery(sample)):
            self._on_submap(sample)

    def _on_unsequenced_submap(self, sample: Any) -> None:
        """The plain subscriber's callback: samples without a source sequence number (a plain
        `put`, a publisher without sample-miss detection), which the advanced subscriber may
        drop when they arrive out of timestamp order (module docstring)."""
        if sample.source_info is None and (
                sample.timestamp is None or self._first_delivery(sample)):
            self._on_submap(sample)

    def _first_delivery(self, sample: Any) -> bool:
        """Whether this timestamped, unsequenced sample is seen for the first time by either
        subscriber (both get it live). Bounded: the store's (robot, session, seq) check
        catches an older repeat."""
        seen = (str(sample.key_expr), str(sample.timestamp))
        with self._seen_lock:
            if seen in self._seen:
                return False
            self._seen[seen] = None
            while len(self._seen) > SEEN_SAMPLES:
                self._seen.pop(next(iter(self._seen)))
            return True

    def _on_submap(self, sample: Any) -> None:
        """Zenoh callback: enqueue only (see Threads in the module docstring)."""
        key = str(sample.key_expr)
        if len(sample.payload) > self.config.max_payload_bytes:
            # refused before it is copied or queued: the queue holds no oversize payloads
            robot = keys.submap_robot(self._root, key) or "unknown"
            with self.stats._lock:
                self.stats.submaps_received += 1
            self._refuse(robot, key, RefusedError(
                RefusalCode.OVERSIZE, f"{len(sample.payload)}-byte submap exceeds the limit of "
                f"{self.config.max_payload_bytes}"), None)
            return
        data = sample.payload.to_bytes()
        try:
            self._inbox.put_nowait((key, data))
        except queue.Full:
            robot = keys.submap_robot(self._root, key) or "unknown"
            with self.stats._lock:
                self.stats.submaps_received += 1
            self._refuse(robot, key, RefusedError(
                RefusalCode.BUSY,
                f"{self._inbox.maxsize} submaps wait to be stored: send again later"), None)

    def _ingest_loop(self) -> None:
        """The ingress thread: each received payload checked and persisted, in arrival order."""
        while True:
            item = self._inbox.get()
            if item is None:
                return
            try:
                self._receive(*item)
            # last resort: one payload that breaks the checks in an unforeseen way is logged;
            # the thread goes on with the next one
            except Exception:
                log.exception("ingress of a payload on %s failed", item[0])
                self.stats.error("ingress")

    def _receive(self, key: str, data: bytes) -> None:
        robot = keys.submap_robot(self._root, key) or "unknown"
        with self.stats._lock:
            self.stats.submaps_received += 1
        if len(data) > self.config.max_payload_bytes:
            limit = self.config.max_payload_bytes
            self._refuse(robot, key, RefusedError(
                RefusalCode.OVERSIZE, f"{len(data)}-byte submap exceeds the limit of {limit}"),
                None)
            return
        sub: Submap | None = None
        try:
            env, sub = decode_message(data, self.projections)
            if not isinstance(sub, Submap):
                raise SchemaError(f"expected a submap, got a {env.msg_type.value} message")
            if not (sub.robot_id == env.sender == robot):
                raise SchemaError(f"robot mismatch: key says {robot!r}, envelope "
                                  f"{env.sender!r}, submap {sub.robot_id!r}")
            if sub.seq is None:
                raise SchemaError("submap without seq")
            expected = keys.submap_key(self._root, sub.robot_id, sub.session_id)
            if key != expected:
                raise SchemaError(f"key {key!r} does not match the submap (robot "
                                  f"{sub.robot_id!r}, session {sub.session_id!r}): expected "
                                  f"{expected!r}")
            self._admit(sub)
        except RefusedError as exc:
            self._refuse(robot, key, exc, sub)
            return
        except MergeError as exc:
            self._refuse(robot, key, RefusedError(RefusalCode.BAD_SUBMAP, str(exc)),
                         sub if isinstance(sub, Submap) else None)
            return
        try:
            _, created = self.store.put_submap(sub.robot_id, sub.session_id, sub.seq, data,
                                               self.clock())
        except MergeError as exc:
            with self.stats._lock:
                self.stats.submaps_rejected += 1
            log.error("could not persist submap %s/%s/%s: %s", sub.robot_id, sub.session_id,
                      sub.seq, exc)
            code = (RefusalCode.CONFLICT if isinstance(exc, SubmapConflictError)
                    else RefusalCode.STORE)  # conflict: final, the first bytes stay stored
            self._publish_error(robot, code, str(exc), sub.seq, sub.session_id)
            return
        if not created:
            with self.stats._lock:
                self.stats.submaps_duplicate += 1
            return
        self._wake.set()

    def _refuse(self, robot: str, key: str, exc: RefusedError, sub: Submap | None) -> None:
        """Count, log (one line) and answer a refused submap (`sub`: None when it did not
        decode)."""
        with self.stats._lock:
            self.stats.submaps_rejected += 1
        log.warning("refused a submap on %s (%s): %s", key, exc.code.value, exc)
        # the session and seq the robot can recognise: only a submap of its own (a robot
        # mismatch names another robot's submap: its seq means nothing to this one)
        own = sub is not None and sub.robot_id == robot
        self._publish_error(robot, exc.code, str(exc), sub.seq if own else None,
                            sub.session_id if own else None)

    def _admit(self, sub: Submap) -> None:
        """The fleet's rules on a decoded submap (see the module docstring); raises RefusedError.
        Replays of a stored submap pass (they change nothing)."""
        if sub.seq is not None and self.store.has_submap(sub.robot_id, sub.session_id, sub.seq):
            return
        dim = sub.dim
        with self._admit_lock:
            if self._dim is None:
                self._dim = int(self.store.set_meta_once(META_EMBEDDING_DIM, str(dim)))
                log.info("fleet embedding dimension fixed at %d", self._dim)
            if dim != self._dim:
                raise RefusedError(RefusalCode.EMBEDDING_DIM, f"submap has {dim}-d embeddings, "
                                   f"the fleet {self._dim}-d (service.embedding_dim)")
            now = self.clock()
            sessions = self._open[sub.robot_id]
            if sub.session_id not in sessions:
                idle = self.config.session_idle_s
                n_open = sum(1 for t in sessions.values() if now - t < idle)
                if n_open >= self.config.max_open_sessions_per_robot:
                    raise RefusedError(
                        RefusalCode.TOO_MANY_SESSIONS, f"robot {sub.robot_id!r} has {n_open} "
                        f"open sessions (limit {self.config.max_open_sessions_per_robot}, a "
                        f"session closes {idle:g} s after its last submap)")
            if not self._bucket.take(sub.robot_id):
                raise RefusedError(RefusalCode.RATE_LIMITED, f"robot {sub.robot_id!r} sends more "
                                   f"than {self.config.submap_rate_hz:g} submaps/s (burst "
                                   f"{self.config.submap_burst})")
            sessions[sub.session_id] = now

    def ingest(self, sub: Submap, profile: Profile = Profile.FULL, optimize: bool = True) -> int:
        """Persist and process one submap now, in the calling thread, as if it had arrived
        coded with `profile` (a restart reloads it like any other): offline replays and tests,
        with or without a Zenoh session (without one nothing is published). Returns its row
        id; a submap stored before is not processed again. A submap of another embedding
        dimension than the fleet's raises SchemaError. `optimize`: solve the pose graph now
        (else with the next solve)."""
        if sub.seq is None:
            raise SchemaError("submap without seq")
        with self._admit_lock:
            if self._dim is None:
                self._dim = int(self.store.set_meta_once(META_EMBEDDING_DIM, str(sub.dim)))
        if sub.dim != self._dim:
            raise SchemaError(f"submap has {sub.dim}-d embeddings, the fleet {self._dim}-d")
        data = encode_message(sub, profile, sub.robot_id, sub.seq)
        row_id, created = self.store.put_submap(sub.robot_id, sub.session_id, sub.seq, data,
                                                self.clock())
        self.stats.submaps_received += 1
        if created:
            self._process(row_id)
            if optimize:
                self._flush()
        else:
            self.stats.submaps_duplicate += 1
        return row_id

    # ------------------------------------------------------------------ processing

    def _work(self) -> None:
        """The worker: batches of pending rows from the store, oldest first; the graph solved
        after each batch that changed it when the backlog is drained, or every
        optimize_interval_s while it is not."""
        while not self._stop.is_set():
            self._wake.wait(timeout=1.0)  # the timeout only bounds a lost wake-up
            # cleared before the store is read: a submap committed after this is seen next round
            self._wake.clear()
            # Last resort of the only worker thread: a failure outside one submap (the store,
            # the graph solve) is logged and the loop goes on after a pause.
            try:
                while not self._stop.is_set():
                    # rows that failed and could not be marked are skipped, not counted
                    limit = self.config.queue_size + len(self._failed_rows)
                    ids = [i for i in self.store.pending_ids(limit)
                           if i not in self._failed_rows]
                    for row_id in ids:
                        if self._stop.is_set():
                            return
                        self._process_row(row_id)
                    waited = time.monotonic() - self._last_optimize
                    if self._dirty and (not ids or waited >= self.config.optimize_interval_s):
                        self._flush()
                    if not ids:
                        break
            except Exception:
                log.exception("merge worker: a round failed; retrying")
                self.stats.error("worker")
                self._stop.wait(1.0)

    def _process_row(self, row_id: int) -> None:
        """Process one row; one submap that fails in any way (a solver, GTSAM, a bug) is logged
        with its traceback and marked failed; the worker goes on with the next one."""
        try:
            self._process(row_id)
        except Exception as exc:
            log.exception("processing submap row %d failed", row_id)
            self.stats.error(RefusalCode.PROCESSING.value)
            try:
                self.store.mark_processed(row_id, "failed", str(exc)[:500])
            except MergeError as store_exc:
                log.warning("could not mark submap row %d failed: %s", row_id, store_exc)
                self._failed_rows.add(row_id)
            self._result_of_failure(row_id, exc)

    def _result_of_failure(self, row_id: int, exc: Exception) -> None:
        """The `failed` result of a stored submap whose processing raised."""
        try:
            row = self.store.submap(row_id)
        except MergeError as store_exc:  # the store is gone too: only the log knows
            log.warning("no result for submap row %d: %s", row_id, store_exc)
            return
        detail = f"{type(exc).__name__}: {exc}"[:1000]
        self._publish_result(SubmapResult(robot=row.robot_id, session=row.session_id,
                                          seq=row.seq if row.seq >= 0 else None,
                                          outcome=Outcome.FAILED, code=RefusalCode.PROCESSING,
                                          detail=detail))

    def _flush(self) -> None:
        """Solve the pose graph if a processed submap changed it; publish retractions."""
        if self._dirty:
            self._dirty = False
            self._last_optimize = time.monotonic()
            self._optimize(publish=True)

    def _decode_submap(self, payload: bytes) -> Submap:
        """A stored payload (checked to be a submap when it arrived) decoded again."""
        env, sub = decode_message(payload, self.projections)
        if not isinstance(sub, Submap):
            raise SchemaError(f"stored payload is a {env.msg_type.value} message, not a submap")
        return sub

    def _process(self, row_id: int) -> None:
        with self._process_lock:
            self._process_locked(row_id)

    def _candidate_frames(self, me: str, sub: Submap) -> list[tuple[str, SessionMap]]:
        """The other sessions a submap of session `me` is matched against: the fleet index's
        best (core/retrieval.py: the sessions whose objects look most like the submap's), at
        most max_candidate_frames, at most max_frames_per_robot of one robot, only maps of the
        submap's embedding dimension (other models are never matched)."""
        with self._lock:
            for name, st in self.sessions.items():  # sessions changed since they were indexed
                if self._indexed.get(name) != st.version:
                    emb = [h.embedding.unpack() for h in st.objects.values()]
                    self._index.update(name, np.array(emb, dtype=np.float64)
                                       if emb else np.zeros((0, sub.dim)))
                    self._indexed[name] = st.version
            emb = np.asarray([o.embedding for o in sub.objects], dtype=np.float64)
            ranked = self._index.rank(emb, exclude=me)
            per_robot: dict[str, int] = defaultdict(int)
            out: list[tuple[str, SessionMap]] = []
            for fs in ranked:
                if len(out) >= self.config.max_candidate_frames:
                    break
                robot = self.sessions[fs.frame].frame.robot
                if per_robot[robot] >= self.config.max_frames_per_robot:
                    continue
                sm = self._session_map(fs.frame)
                if sm is not None and sm.dim == sub.dim:
                    out.append((fs.frame, sm))
                    per_robot[robot] += 1
            return out

    def _process_locked(self, row_id: int) -> None:
        t0 = time.perf_counter()
        row = self.store.submap(row_id)
        if row.status != "pending":
            return
        sub = self._decode_submap(row.payload)
        me_id = FrameId(sub.robot_id, sub.session_id)
        me = str(me_id)
        code = self._views.note(me, row.payload)  # compact: how its embeddings were coded
        new_factors = []
        tried: list[FrameTried] = []
        others = self._candidate_frames(me, sub)
        for other, sm in others:
            other_id = FrameId.parse(other)
            self.stats.matches_tried += 1
            res = match(*self._views.pair(other, sm.arrays, sub, code), self.config.match).result
            if not yields_factor(res):
                tried.append(FrameTried(frame=other, reason=res.reason,
                                        matches=len(res.matches)))
                continue
            factor = self._factor(res, sm, other_id, sub)
            tried.append(FrameTried(frame=other, reason=res.reason, matches=len(res.matches),
                                    factor_id=factor.factor_id))
            new_factors.append((other, factor))
        # stored only once every candidate was matched: a submap that fails half way leaves no
        # factor behind that the running service never held (a restart would restore it).
        # A replay after a crash finds a factor stored already: it is published again (its id
        # is deterministic, so receivers see the same factor twice at most)
        new_factors = [f for _, f in new_factors]
        self.stats.factors_matched += len(new_factors)
        with self._lock:
            closes_loop = self._add_submap(sub)
            sent, withdrawn = self._trust(new_factors)
        for factor in [*new_factors, *withdrawn]:  # held: kept, not sent
            if factor.factor_id in self._held:
                self.store.put_held_factor(factor.factor_id, *_frames_of(factor),
                                           factor.model_dump_json().encode())
        for factor in sent:
            self.store.put_factor(factor.factor_id, *_frames_of(factor),
                                  factor.model_dump_json().encode(), "accepted")
            self.store.set_factor_status(factor.factor_id, "accepted")
            self.store.drop_held_factor(factor.factor_id)
        for factor in withdrawn:
            self.store.set_factor_status(factor.factor_id, "retracted")
        for factor in sent:
            self._publish_factor(factor)  # a send that fails is logged: the submap is processed
            self.stats.factors_accepted += 1
        for factor in withdrawn:
            self._publish_factor(factor.model_copy(update={"status": FactorStatus.RETRACTED}))
            self.stats.factors_retracted += 1
        if sent or withdrawn or closes_loop:
            self._dirty = True  # solved after the batch (_flush)
        self.store.mark_processed(row_id, "processed" if new_factors else "no_match",
                                  f"{len(new_factors)} factors")
        self.stats.submaps_processed += 1
        self._publish_result(SubmapResult(
            robot=sub.robot_id, session=sub.session_id, seq=sub.seq,
            outcome=Outcome.PROCESSED if new_factors else Outcome.NO_MATCH,
            factors=[f.factor_id for f in new_factors], tried=tried,
            reason=None if new_factors else (tried[0].reason if tried else NO_FRAMES)))
        ms = (time.perf_counter() - t0) * 1e3
        self.stats.latency_ms.append(ms)
        del self.stats.latency_ms[:-1000]
        self.stats.delay_ms.append(max(0.0, (self.clock() - row.received_at_s) * 1e3))
        del self.stats.delay_ms[:-1000]
        log.info("submap %s seq %s keyframe %s: %d objects, %d sessions tried, %d factors, "
                 "%.0f ms", me, sub.seq, sub.keyframe, len(sub.objects), len(others),
                 len(new_factors), ms)

    def _trust(self, new: list[Factor]) -> tuple[list[Factor], list[Factor]]:
        """New factors offered to the pairwise-consistency sets (fleet/closures.py): the
        factors to put in the graph and send now (new ones trusted, held ones trusted again),
        and those to withdraw (trusted ones the sets dropped: out of the graph, retracted)."""
        involved: dict[str, None] = {}
        for f in new:
            if f.factor_id in self.factors or f.factor_id in self._held:
                continue  # a replay
            self._held[f.factor_id] = f
            v = self._closures.offer(f)
            involved.update(dict.fromkeys([f.factor_id, *v.trusted, *v.withdrawn]))
        sent, withdrawn = [], []
        for fid in involved:
            if self._closures.is_trusted(fid) and fid in self._held:
                f = self._held.pop(fid)
                self.factors[fid] = f
                self.graph.add_factor_model(f, keyframe_nodes=True, group=CLOSURE_GROUP)
                sent.append(f)
            elif not self._closures.is_trusted(fid) and fid in self.factors:
                f = self.factors.pop(fid)
                self.graph.remove_factor(fid)
                self._held[fid] = f
                withdrawn.append(f)
        return sent, withdrawn

    def _chains(self, frame: str, k: int, targets: set[int]
                ) -> dict[int, tuple[gtsam.Pose3, np.ndarray]]:
        """Odometry from keyframe k of a session to each target (fleet/closures.py)."""
        st = self.sessions.get(frame)
        if st is None:
            return {}
        scale = self.graph.noise_scales.get(odometry_group(st.frame.robot))
        return st.placements(k, targets, scale)

    def _factor(self, res: Any, sm: SessionMap, other: FrameId, sub: Submap) -> Factor:
        """The factor of an accepted match of `sub` against session `other`'s map: pose level
        (keyframe Ka of other -> the submap's keyframe) unless both ends are keyframe 0 and the
        submap has no keyframe (an old client against frame-anchored objects: the frame-level
        factor of old, which ties the same two nodes)."""
        me = FrameId(sub.robot_id, sub.session_id)
        fid = match_factor_id(other, me, sub.seq if sub.seq is not None else 0)
        ka = anchoring_keyframe(res, sm.keyframe_of)
        if sub.keyframe is None and ka == 0:
            return factor_from_match(res, other, me, factor_id=fid,
                                     drift_sigma=self.config.drift_sigma)
        measured = self._local_fit(res, other, ka, sub) if self.config.local_fit else None
        if measured is not None:
            return factor_from_match(res, other, me, factor_id=fid,
                                     drift_sigma=self.config.local_drift_sigma,
                                     keyframe_a=ka, keyframe_b=sub.keyframe or 0,
                                     measured=measured)
        return factor_from_match(
            res, other, me, factor_id=fid, drift_sigma=self.config.drift_sigma,
            keyframe_a=ka, keyframe_b=sub.keyframe or 0, T_a_keyframe_a=sm.poses[ka],
        )

    def _local_fit(self, res: Any, other: FrameId, ka: int, sub: Submap
                   ) -> tuple[gtsam.Pose3, np.ndarray] | None:
        """T_{Ka,Kb} fitted on the matched objects with the other session's placed around Ka
        by its odometry (core/factors.py local_fit); None when that cannot be done (a matched
        object's keyframe not joined to Ka by odometry, too few pairs)."""
        st = self.sessions[str(other)]
        mine = {o.id: o for o in sub.objects}
        pairs = [(st.objects[m.map_object], mine[m.submap_object]) for m in res.matches
                 if m.map_object in st.objects and m.submap_object in mine]
        if not pairs:
            return None
        scale = self.graph.noise_scales.get(odometry_group(other.robot))
        placed = st.placements(ka, {h.keyframe for h, _ in pairs}, scale)
        v = self.config.match.verify
        up_map = st.up.get(ka) if v.gravity_aligned and sub.up is not None else None
        return local_fit(
            np.array([o.position for _, o in pairs], dtype=np.float64),
            np.array([h.position for h, _ in pairs], dtype=np.float64),
            [h.keyframe for h, _ in pairs], placed,
            up_sub=None if up_map is None else np.asarray(sub.up, dtype=np.float64),
            up_map=up_map,
            vertical_sigma_rad=np.radians(v.vertical_sigma_deg),
            sigma_floor_m=self.config.local_sigma_floor_m,
            range_weighted=self.config.local_range_weighted)

    def _set_anchor(self, name: str) -> None:
        self._anchor = name
        self.graph.anchor = str(KeyframeId.origin(FrameId.parse(name)))

    def _add_submap(self, sub: Submap) -> bool:
        """A processed submap into its session's state and the graph (its keyframe node, its
        odometry edge as a known inlier). True when the edge joined two nodes the graph had
        already (it may close a loop: the graph must be solved again)."""
        name = str(FrameId(sub.robot_id, sub.session_id))
        st = self.sessions.get(name)
        if st is None:
            st = self.sessions[name] = SessionState(FrameId(sub.robot_id, sub.session_id))
            self.store.put_frame(sub.robot_id, sub.session_id, self.clock())
            self.graph.add_frame(st.node(0))
            if self._anchor is None:
                self._set_anchor(name)
        edge = st.add(sub)
        closes_loop = False
        if edge is not None:
            a, b = str(edge.from_), str(edge.to)
            closes_loop = self.graph.has_node(a) and self.graph.has_node(b)
            self.graph.add_factor(edge.edge_id, a, b, edge.T_from_to, edge.covariance,
                                  known_inlier=True, group=odometry_group(sub.robot_id))
        self.graph.add_frame(st.node(0 if sub.keyframe is None else sub.keyframe))
        self._global = None
        return closes_loop

    def _session_map(self, name: str) -> SessionMap | None:
        """A session's objects placed in its frame (None with fewer than min_map_objects
        placed); cached until the session or the graph solution changes (every solution
        clears the cache, which keeps the SESSION_MAPS_CACHED last used)."""
        st = self.sessions[name]
        key = (st.version, self._solutions)
        cached = self._session_maps.pop(name, None)
        if cached is not None and cached[0] == key:
            self._session_maps[name] = cached  # the most recently used last
            return cached[1]
        poses = self._session_poses(st)
        placed, positions, keyframe_of = [], [], {}
        for oid, held in st.objects.items():
            T = poses.get(held.keyframe)
            if T is None:
                continue  # a keyframe the odometry does not join to keyframe 0 (yet)
            placed.append(held)
            if held.keyframe == 0 and T.equals(gtsam.Pose3(), 0.0):
                positions.append(held.position)
            else:
                p = T.transformFrom(np.asarray(held.position, dtype=np.float64))
                positions.append(tuple(map(float, p)))
            keyframe_of[oid] = held.keyframe
        sm = None
        if len(placed) >= self.config.min_map_objects:
            sm = SessionMap(st.frame, tuple(placed), tuple(positions), session_up(st, poses),
                            keyframe_of, poses)
        self._session_maps[name] = (key, sm)
        while len(self._session_maps) > SESSION_MAPS_CACHED:
            del self._session_maps[next(iter(self._session_maps))]
        return sm

    def _session_poses(self, st: SessionState) -> dict[int, gtsam.Pose3]:
        """Pose of each placeable keyframe in the session frame (see the module docstring)."""
        sol = self.solution
        seeds = {0: gtsam.Pose3()}
        if sol is not None and (origin := sol.T_anchor_frame.get(st.node(0))) is not None:
            inv = origin.inverse()
            seeds = {k: inv.compose(T) for k in st.keyframes
                     if (T := sol.T_anchor_frame.get(st.node(k))) is not None}
            seeds[0] = gtsam.Pose3()
        return st.propagate(seeds)

    def _anchor_poses(self, st: SessionState) -> dict[int, gtsam.Pose3]:
        """Pose of each keyframe of a session in the anchor frame: the solved ones, and those
        joined to them by odometry (composed from the nearest); {} outside the anchor's
        component. Before any solution, only the anchor session, by odometry."""
        sol = self.solution
        if sol is None:
            return st.propagate({0: gtsam.Pose3()}) if st.name == self._anchor else {}
        seeds = {k: T for k in st.keyframes
                 if (T := sol.T_anchor_frame.get(st.node(k))) is not None}
        return st.propagate(seeds) if seeds else {}

    def _optimize(self, publish: bool) -> None:
        with self._lock:
            try:
                sol = self.graph.optimize(marginals=False)
            except MergeError as exc:
                log.warning("pose graph optimisation failed: %s", exc)
                return
            self.stats.optimizations += 1
            if sol is self.solution:
                return  # nothing changed since the last solve
            self._save_scales()
            self.solution = sol
            self._solutions += 1
            self._session_maps.clear()  # keyed by the solution: none could be used again
            self._global = None
            # ambiguous factors (GNC doubts them, but no two other paths confirm it) are kept
            retracted = []
            for fid in [f for f in sol.outlier_factor_ids if f in self.factors]:
                self.store.set_factor_status(fid, "retracted")
                retracted.append(self.factors.pop(fid))  # under the lock: global_map reads
                self.graph.remove_factor(fid)
                self._closures.forget(fid)  # judged: never trusted again
                self.stats.factors_retracted += 1
                log.warning("factor %s rejected by GNC: retracted", fid)
        _trim_heap()  # outside the lock: the ingress and status replies need not wait
        if publish:
            for factor in retracted:
                self._publish_factor(factor.model_copy(update={"status": FactorStatus.RETRACTED}))

    def _publish_factor(self, factor: Factor) -> None:
        """Send a factor to both its robots; a send that fails is logged (the factor is stored
        and in the graph: a restart's replay publishes it again)."""
        import zenoh

        if self.session is None:  # offline (ingest): nothing to publish to
            return
        try:
            payload = encode_message(factor, self.config.factor_profile, "mergesvc",
                                     self._next_seq())
            for robot in sorted({factor.robot_a, factor.robot_b}):
                self._put(keys.factor_key(self._root, robot, factor.factor_id), payload,
                          json_doc=False)
        except (MergeError, ValueError, zenoh.ZError) as exc:
            log.warning("could not publish factor %s: %s", factor.factor_id, exc)

    # ------------------------------------------------------------------ queries

    def global_map(self) -> tuple[ObjectMap | None, str | None]:
        """Objects of every session aligned with the anchor, each placed with the optimized
        pose of its keyframe, fused (None before any submap)."""
        with self._lock:
            if self._global is not None or not self.sessions:
                return self._global, self._anchor
            anchor = self._anchor
            frames: dict[str, list[ObjectNode]] = {}
            poses: dict[str, gtsam.Pose3] = {}
            frame_of: dict[str, str] = {}
            for name, st in self.sessions.items():
                placed = self._anchor_poses(st)
                owned: dict[int, list[ObjectNode]] = defaultdict(list)
                for held in st.objects.values():
                    if held.keyframe in placed:
                        owned[held.keyframe].append(held.node)  # built again: fleet/held.py
                for k in sorted(owned):
                    node = st.node(k)
                    frames[node], poses[node], frame_of[node] = owned[k], placed[k], name
            pairs = []
            for f in self.factors.held():  # the object pairs, no Factor built
                a, b = self.sessions.get(f.frame_a), self.sessions.get(f.frame_b)
                if a is None or b is None:
                    continue
                for object_a, object_b in f.object_pairs():
                    ha, hb = a.objects.get(object_a), b.objects.get(object_b)
                    if ha is not None and hb is not None:
                        pairs.append((a.node(ha.keyframe), object_a,
                                      b.node(hb.keyframe), object_b))
            if not frames:
                return None, anchor
            fused = fuse_objects(frames, poses, pairs, frame_of=frame_of)
            at = FrameId.parse(anchor)
            self._global = ObjectMap(robot_id=at.robot, session_id=at.session,
                                     objects=fused.objects)
            return self._global, anchor

    def _frame_poses(self) -> dict[str, np.ndarray]:
        """(4, 4) pose of every session's keyframe 0 (its frame origin) solved with the
        anchor, in the anchor frame."""
        if self.solution is None:
            return {}
        out = {}
        for name, st in self.sessions.items():
            T = self.solution.T_anchor_frame.get(st.node(0))
            if T is not None:
                out[name] = np.asarray(T.matrix())
        return out

    def keyframe_poses(self) -> dict[str, dict[int, np.ndarray]]:
        """(4, 4) pose of every keyframe of the anchor's component in the anchor frame (solved,
        or composed by odometry from the nearest solved keyframe); {} before any solution."""
        if self.solution is None:
            return {}
        out = {}
        for name, st in self.sessions.items():
            placed = self._anchor_poses(st)
            if placed:
                out[name] = {k: np.asarray(placed[k].matrix()) for k in sorted(placed)}
        return out

    def relocalize(self, sub: Submap) -> RelocalizeReply:
        """Where a new session is in the anchor frame, from a first submap matched against the
        global map: the pose of the submap's keyframe (or, without one, of its session frame)
        in the anchor frame (the anchor session's keyframe 0)."""
        gmap, anchor = self.global_map()
        if gmap is None or len(gmap.objects) < self.config.min_map_objects:
            return RelocalizeReply(localized=False, reason="no_map")
        if sub.dim != gmap.dim:
            raise SchemaError(f"query has {sub.dim}-d embeddings, the fleet {gmap.dim}-d")
        res = match(gmap, sub, self.config.match).result
        if not res.accepted:
            return RelocalizeReply(localized=False, reason=res.reason.value, anchor=anchor,
                                   matches=len(res.matches), keyframe=sub.keyframe)
        return RelocalizeReply(localized=True, reason="verified", anchor=anchor,
                               T_anchor_session=res.transform, covariance=res.covariance,
                               matches=len(res.matches), keyframe=sub.keyframe)

    def _on_relocalize(self, query: Any) -> None:
        import zenoh

        self.stats.relocalize_queries += 1
        with query:
            try:
                payload = query.payload
                if payload is None:
                    raise SchemaError("relocalize needs a submap in the query payload")
                data = payload.to_bytes()
                if len(data) > self.config.max_payload_bytes:
                    raise SchemaError(f"{len(data)}-byte query exceeds the limit")
                _, sub = decode_message(data, self.projections)
                if not isinstance(sub, Submap):
                    raise SchemaError("relocalize needs a submap")
                reply = self.relocalize(sub)
                query.reply(query.key_expr, reply.model_dump_json().encode(),
                            encoding=zenoh.Encoding(keys.JSON_ENCODING))
            except MergeError as exc:
                self.stats.error("bad_relocalize")
                log.warning("bad relocalize query: %s", exc)
                _reply_err(query, "bad_request", str(exc))
            # last resort: every query gets an answer, a failure inside (a solver, a bug) too
            except Exception as exc:
                log.exception("relocalize failed")
                _reply_err(query, "internal", str(exc))

    def status(self, poses: bool = True) -> dict[str, Any]:
        """The service's state as strict JSON (no NaN: a percentile of nothing is null), as
        `StatusReply` (fleet/replies.py) checks it. `poses=False` leaves `frame_poses` and
        `keyframe_poses` empty: they grow with every keyframe (hundreds of kB after minutes of
        a fleet), which a monitor polling the counts does not need (query `status?poses=false`).
        """

        def pct(values: list[float]) -> dict[str, float | None]:
            a = np.asarray(list(values), dtype=np.float64)  # a copy: the worker appends
            return {f"p{q}": float(np.percentile(a, q)) if a.size else None
                    for q in (50, 90, 99)}

        counts = self.store.counts()
        frame_poses: dict[str, Any] = {}
        keyframe_poses: dict[str, Any] = {}
        with self._lock:
            frames = {f: len(st.objects) for f, st in self.sessions.items()}
            if poses:
                frame_poses = {f: T.tolist() for f, T in self._frame_poses().items()}
                keyframe_poses = {f: {str(k): T.tolist() for k, T in kf.items()}
                                  for f, kf in self.keyframe_poses().items()}
        return StatusReply.model_validate({
            "fleet": self.config.fleet,
            "robots_alive": sorted(self.alive),
            "frames": frames,
            "submaps": {"received": self.stats.submaps_received,
                        "duplicate": self.stats.submaps_duplicate,
                        "processed": self.stats.submaps_processed,
                        "rejected": self.stats.submaps_rejected,
                        "queued": counts["submaps_pending"],
                        "stored": counts["submaps"]},
            "factors": {"accepted": self.stats.factors_accepted,
                        "retracted": self.stats.factors_retracted,
                        "active": len(self.factors)},
            "results": self.stats.result_counts(),
            "errors": dict(self.stats.errors),
            "latency_ms": pct(self.stats.latency_ms),
            "delay_ms": pct(self.stats.delay_ms),
            "optimizations": self.stats.optimizations,
            "frozen_keyframes": self.graph.frozen_count,
            "embedding_dim": self._dim,
            "anchor": self._anchor,
            "frame_poses": frame_poses,
            "keyframe_poses": keyframe_poses,
            "store": self.store.stats(),
        }).model_dump(mode="json")

    def _on_status(self, query: Any) -> None:
        import zenoh

        with query:
            try:
                poses = query.parameters.get("poses") not in ("false", "0", "no")
                query.reply(query.key_expr,
                            json.dumps(self.status(poses=poses), allow_nan=False).encode(),
                            encoding=zenoh.Encoding(keys.JSON_ENCODING))
            # last resort: every query gets an answer, a failure inside (a bug) too
            except Exception as exc:
                log.exception("status failed")
                _reply_err(query, "internal", str(exc))

    def _on_alive(self, sample: Any) -> None:
        import zenoh

        robot = keys.alive_robot(str(sample.key_expr))
        if sample.kind == zenoh.SampleKind.PUT:
            self.alive.add(robot)
        else:
            self.alive.discard(robot)


__all__ = [
    "CLOSURE_GROUP",
    "HeldObject",
    "MergeService",
    "RefusedError",
    "RelocalizeReply",
    "ServiceConfig",
    "ServiceStats",
    "SessionMap",
    "SessionState",
    "TokenBucket",
    "odometry_group",
    "session_up",
]
