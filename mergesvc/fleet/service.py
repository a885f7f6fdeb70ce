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
    in that submap's keyframe frame.
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
the wire), which ties the two sessions' keyframes 0. The graph is optimized after every submap
that added a factor (or an odometry edge between two keyframes already in the graph), and not
otherwise; PoseGraph.optimize also returns its last solution while nothing changed.

Threads: Zenoh callbacks only validate, persist and enqueue; one worker thread matches. The
queue holds row ids only and is bounded: under a burst, ids that do not fit stay unprocessed in
the store and the worker picks them up when it is idle (memory stays bounded, nothing is lost).
"""

from __future__ import annotations

import contextlib
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
from pydantic import BaseModel, ConfigDict, Field

from mergesvc.core.config import MatchConfig
from mergesvc.core.factors import (
    OdometryEdge,
    anchoring_keyframe,
    factor_frames,
    factor_from_match,
    match_factor_id,
    odometry_edge,
    yields_factor,
)
from mergesvc.core.frames import FrameId, KeyframeId
from mergesvc.core.fusion import fuse_objects
from mergesvc.core.graph import GraphConfig, GraphSolution, PoseGraph
from mergesvc.core.model import (
    ErrorMessage,
    Factor,
    FactorStatus,
    ObjectMap,
    ObjectNode,
    Submap,
    Transform,
)
from mergesvc.core.pipeline import match
from mergesvc.errors import MergeError, SchemaError
from mergesvc.fleet.store import Store
from mergesvc.wire import Profile, Projection, decode_message, encode_message, keys

log = logging.getLogger(__name__)


class ServiceConfig(BaseModel):
    """Settings of `mergesvc serve`."""

    model_config = ConfigDict(extra="forbid")

    fleet: str = Field("fleet0", min_length=1, max_length=64)
    store: str = Field("mergesvc.db", description="SQLite file (WAL); ':memory:' for tests")
    factor_profile: Profile = Field(Profile.COMPACT, description="codec profile of factors")
    max_payload_bytes: int = Field(4 * 2**20, ge=1024, description="larger submaps are refused")
    queue_size: int = Field(64, ge=1, description="submaps waiting in memory (ids only)")
    min_map_objects: int = Field(3, ge=3, description="frames with fewer objects are not matched")
    drift_sigma: tuple[float, float] = Field(
        (0.05, 0.5),
        description="added to every factor's covariance: rotation rad, translation m. A "
        "session's map places objects of many keyframes with estimated (drifting) poses, and "
        "a frame-level factor (old clients) ties two whole drifting frames, so a factor "
        "differs from the truth by more than the fit's own covariance says",
    )
    match: MatchConfig = Field(
        default_factory=lambda: MatchConfig.model_validate(
            {"verify": {"min_matches": 4, "min_matches_vertical": 4, "gravity_aligned": True}}
        ),
        description="verified matching; an inter-robot factor needs 4 matched objects by "
        "default, with or without a known vertical (3 points admit coincidental fits in a "
        "small pool, and a wrong factor costs more than a late one)",
    )
    graph: GraphConfig = Field(
        GraphConfig(),
        description="the GNC pose graph over the sessions' keyframes (outlier thresholds)",
    )


@dataclass
class ServiceStats:
    submaps_received: int = 0
    submaps_duplicate: int = 0
    submaps_processed: int = 0
    submaps_rejected: int = 0  # bad payloads
    submaps_deferred: int = 0  # queue full: left in the store for later
    factors_accepted: int = 0
    factors_retracted: int = 0
    matches_tried: int = 0
    relocalize_queries: int = 0
    errors: dict[str, int] = field(default_factory=dict)
    latency_ms: list[float] = field(default_factory=list)

    def error(self, code: str) -> None:
        self.errors[code] = self.errors.get(code, 0) + 1


class RelocalizeReply(BaseModel):
    """Answer of the relocalize queryable: where the query submap's frame is in the anchor
    frame (the anchor session's keyframe 0).

    T_anchor_session: the pose of the frame the query submap's positions are in: its keyframe
    (`keyframe`, the vehicle's pose where it cut the submap) when the submap has one, else the
    new session's frame (its origin)."""

    model_config = ConfigDict(extra="forbid")

    localized: bool
    reason: str
    anchor: str | None = None
    T_anchor_session: Transform | None = None
    covariance: list[list[float]] | None = None
    matches: int = 0
    keyframe: int | None = Field(
        None, description="the query submap's keyframe T_anchor_session is the pose of; None: "
        "the session frame"
    )


@dataclass(frozen=True)
class HeldObject:
    """An object of a session as the service holds it: from the submap `seq` (the latest that
    held it), its position in the frame of that submap's keyframe."""

    seq: int
    keyframe: int
    node: ObjectNode


@dataclass
class SessionState:
    """One robot session: its keyframes, the odometry edges between them, its objects."""

    frame: FrameId
    keyframes: set[int] = field(default_factory=lambda: {0})
    edges: dict[tuple[int, int], OdometryEdge] = field(default_factory=dict)
    objects: dict[str, HeldObject] = field(default_factory=dict)
    up: dict[int, np.ndarray] = field(default_factory=dict)  # declared up per keyframe frame
    version: int = 0  # bumped by every submap
    _adjacent: dict[int, list[tuple[int, gtsam.Pose3]]] = field(
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
            self.up[k] = np.asarray(sub.up, dtype=np.float64)
        for o in sub.objects:  # the latest submap holding an object gives its estimate
            held = self.objects.get(o.id)
            if held is None or held.seq <= seq:
                self.objects[o.id] = HeldObject(seq, k, o)
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
        self.edges[pair] = edge
        self.keyframes.add(edge.from_.k)
        self._adjacent[pair[0]].append((pair[1], edge.T_from_to))
        self._adjacent[pair[1]].append((pair[0], edge.T_from_to.inverse()))
        return edge

    def propagate(self, seeds: Mapping[int, gtsam.Pose3]) -> dict[int, gtsam.Pose3]:
        """Poses of the keyframes reachable from `seeds` (keyframe -> pose) along odometry
        edges, each composed from the nearest seed (fewest edges); seeds keep their pose."""
        poses = dict(seeds)
        todo = deque(sorted(seeds))
        while todo:
            k = todo.popleft()
            for j, T_k_j in self._adjacent.get(k, ()):
                if j not in poses:
                    poses[j] = poses[k].compose(T_k_j)
                    todo.append(j)
        return poses


@dataclass(frozen=True)
class SessionMap:
    """A session's objects placed in its frame for matching: the map, each object's keyframe
    and the keyframe poses (in the session frame) used to place them."""

    map: ObjectMap
    keyframe_of: dict[str, int]
    poses: dict[int, gtsam.Pose3]



def _session_up(st: SessionState, poses: Mapping[int, gtsam.Pose3]) -> tuple[float, ...] | None:
    """The session frame's up, from the latest keyframe that declared one (its up rotated by
    that keyframe's pose in the session frame); None when no placed keyframe declared it."""
    for k in sorted(st.up, reverse=True):
        T = poses.get(k)
        if T is not None:
            u = np.asarray(T.rotation().matrix()) @ st.up[k]
            return tuple(float(x) for x in u / np.linalg.norm(u))
    return None

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
        self.clock = clock
        self.stats = ServiceStats()
        self.store = Store(config.store)
        self.graph = PoseGraph(config=config.graph)
        self.sessions: dict[str, SessionState] = {}  # "robot/session" -> its keyframes, objects
        self.factors: dict[str, Factor] = {}
        self.alive: set[str] = set()
        self._seq = 0
        self._lock = threading.RLock()
        self._queue: queue.Queue[int] = queue.Queue(maxsize=config.queue_size)
        self._stop = threading.Event()
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

        self.restore()
        s = self.session
        self._entities = [
            declare_advanced_subscriber(
                s, keys.all_submaps(self._root), self._on_submap,
                history=HistoryConfig(detect_late_publishers=True, max_samples=10_000),
                recovery=RecoveryConfig(heartbeat=True), subscriber_detection=True,
            ),
            s.declare_queryable(keys.relocalize_key(self._root), self._on_relocalize),
            s.declare_queryable(keys.status_key(self._root), self._on_status),
            s.liveliness().declare_subscriber(keys.all_alive(self._root), self._on_alive,
                                              history=True),
        ]
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
        for row in self.store.submaps():
            if row.status in ("processed", "no_match"):
                self._add_submap(self._decode_submap(row.payload))
        for f in self.store.factors():
            factor = Factor.model_validate_json(f.payload)
            if f.status == "accepted":
                self.graph.add_factor_model(factor, keyframe_nodes=True)
                self.factors[factor.factor_id] = factor
        if self.factors:
            self._optimize(publish=False)
        for row in self.store.unprocessed_submaps():
            self._offer(row.row_id)

    # ------------------------------------------------------------------ ingress

    def _publish_error(self, robot: str, code: str, detail: str, seq: int | None) -> None:
        import zenoh

        self.stats.error(code)
        if self.session is None:
            return
        try:
            msg = encode_message(ErrorMessage(code=code, detail=detail[:1000], about_seq=seq),
                                 Profile.FULL, "mergesvc", self._next_seq())
            self.session.put(keys.error_key(self._root, robot), msg)
        # an error report that cannot be made (a robot name no key can carry, an unencodable
        # detail, a closed session) is logged: it must not end the callback that reports it
        except (MergeError, ValueError, zenoh.ZError) as exc:
            log.warning("could not publish an error to %s: %s", robot, exc)

    def _next_seq(self) -> int:
        with self._lock:
            self._seq += 1
            return self._seq

    def _on_submap(self, sample: Any) -> None:
        key = str(sample.key_expr)
        robot = keys.submap_robot(self._root, key) or "unknown"
        self.stats.submaps_received += 1
        data = sample.payload.to_bytes()
        if len(data) > self.config.max_payload_bytes:
            self.stats.submaps_rejected += 1
            log.warning("refused a %d-byte submap from %s (limit %d)", len(data), robot,
                        self.config.max_payload_bytes)
            self._publish_error(robot, "oversize", f"{len(data)} bytes", None)
            return
        try:
            env, sub = decode_message(data, self.projections)
            if not isinstance(sub, Submap):
                raise SchemaError(f"expected a submap, got a {env.msg_type.value} message")
            if not (sub.robot_id == env.sender == robot):
                raise SchemaError(f"robot mismatch: key says {robot!r}, envelope "
                                  f"{env.sender!r}, submap {sub.robot_id!r}")
            if sub.seq is None:
                raise SchemaError("submap without seq")
        except MergeError as exc:
            self.stats.submaps_rejected += 1
            log.warning("bad submap on %s: %s", key, exc)
            self._publish_error(robot, "bad_submap", str(exc), None)
            return
        try:
            row_id, created = self.store.put_submap(sub.robot_id, sub.session_id, sub.seq, data,
                                                    self.clock())
        except MergeError as exc:
            self.stats.submaps_rejected += 1
            log.error("could not persist submap %s/%s/%s: %s", sub.robot_id, sub.session_id,
                      sub.seq, exc)
            self._publish_error(robot, "store", str(exc), sub.seq)
            return
        if not created:
            self.stats.submaps_duplicate += 1
            return
        self._offer(row_id)

    def ingest(self, sub: Submap, profile: Profile = Profile.FULL) -> int:
        """Persist and process one submap now, in the calling thread, as if it had arrived
        coded with `profile` (a restart reloads it like any other): offline replays and tests,
        with or without a Zenoh session (without one nothing is published). Returns its row
        id; a submap stored before is not processed again."""
        if sub.seq is None:
            raise SchemaError("submap without seq")
        data = encode_message(sub, profile, sub.robot_id, sub.seq)
        row_id, created = self.store.put_submap(sub.robot_id, sub.session_id, sub.seq, data,
                                                self.clock())
        self.stats.submaps_received += 1
        if created:
            self._process(row_id)
        else:
            self.stats.submaps_duplicate += 1
        return row_id

    def _offer(self, row_id: int) -> None:
        try:
            self._queue.put_nowait(row_id)
        except queue.Full:
            self.stats.submaps_deferred += 1  # stays unprocessed in the store: picked up later

    # ------------------------------------------------------------------ processing

    def _work(self) -> None:
        while not self._stop.is_set():
            try:
                row_id = self._queue.get(timeout=0.2)
            except queue.Empty:
                if self.stats.submaps_deferred:
                    for row in self.store.unprocessed_submaps()[: self.config.queue_size]:
                        self._offer(row.row_id)
                continue
            try:
                self._process(row_id)
            # Last resort of the only worker thread: one submap that fails in any way (a
            # solver, GTSAM, a bug) is logged with its traceback and marked failed; the
            # service goes on with the next one.
            except Exception as exc:
                log.exception("processing submap row %d failed", row_id)
                self.stats.error("processing")
                try:
                    self.store.mark_processed(row_id, "failed", str(exc)[:500])
                except MergeError as store_exc:
                    log.warning("could not mark submap row %d failed: %s", row_id, store_exc)

    def _decode_submap(self, payload: bytes) -> Submap:
        """A stored payload (checked to be a submap when it arrived) decoded again."""
        env, sub = decode_message(payload, self.projections)
        if not isinstance(sub, Submap):
            raise SchemaError(f"stored payload is a {env.msg_type.value} message, not a submap")
        return sub

    def _process(self, row_id: int) -> None:
        t0 = time.perf_counter()
        row = self.store.submap(row_id)
        if row.status != "pending":
            return
        sub = self._decode_submap(row.payload)
        me_id = FrameId(sub.robot_id, sub.session_id)
        me = str(me_id)
        new_factors = []
        with self._lock:
            others = [(name, sm) for name in self.sessions
                      if name != me and (sm := self._session_map(name)) is not None]
        for other, sm in others:
            other_id = FrameId.parse(other)
            self.stats.matches_tried += 1
            res = match(sm.map, sub, self.config.match).result
            if not yields_factor(res):
                continue
            factor = self._factor(res, sm, other_id, sub)
            # a replay after a crash finds the factor stored already: publish it again (its id
            # is deterministic, so receivers see the same factor twice at most)
            self.store.put_factor(factor.factor_id, other, me, factor.model_dump_json().encode(),
                                  "accepted")
            new_factors.append(factor)
        with self._lock:
            closes_loop = self._add_submap(sub)
            for factor in new_factors:
                if factor.factor_id not in self.factors:
                    self.factors[factor.factor_id] = factor
                    self.graph.add_factor_model(factor, keyframe_nodes=True)
        for factor in new_factors:
            self._publish_factor(factor)
            self.stats.factors_accepted += 1
        if new_factors or closes_loop:
            self._optimize(publish=True)
        self.store.mark_processed(row_id, "processed" if new_factors else "no_match",
                                  f"{len(new_factors)} factors")
        self.stats.submaps_processed += 1
        ms = (time.perf_counter() - t0) * 1e3
        self.stats.latency_ms.append(ms)
        del self.stats.latency_ms[:-1000]
        log.info("submap %s seq %s keyframe %s: %d objects, %d sessions tried, %d factors, "
                 "%.0f ms", me, sub.seq, sub.keyframe, len(sub.objects), len(others),
                 len(new_factors), ms)

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
        return factor_from_match(
            res, other, me, factor_id=fid, drift_sigma=self.config.drift_sigma,
            keyframe_a=ka, keyframe_b=sub.keyframe or 0, T_a_keyframe_a=sm.poses[ka],
        )

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
                                  known_inlier=True)
        self.graph.add_frame(st.node(0 if sub.keyframe is None else sub.keyframe))
        self._global = None
        return closes_loop

    def _session_map(self, name: str) -> SessionMap | None:
        """A session's objects placed in its frame (None with fewer than min_map_objects
        placed); cached until the session or the graph solution changes."""
        st = self.sessions[name]
        key = (st.version, self._solutions)
        cached = self._session_maps.get(name)
        if cached is not None and cached[0] == key:
            return cached[1]
        poses = self._session_poses(st)
        placed, keyframe_of = [], {}
        for oid, held in st.objects.items():
            T = poses.get(held.keyframe)
            if T is None:
                continue  # a keyframe the odometry does not join to keyframe 0 (yet)
            p = T.transformFrom(np.asarray(held.node.position, dtype=np.float64))
            placed.append(held.node if held.keyframe == 0 and T.equals(gtsam.Pose3(), 0.0)
                          else held.node.model_copy(update={"position": tuple(map(float, p))}))
            keyframe_of[oid] = held.keyframe
        sm = None
        if len(placed) >= self.config.min_map_objects:
            sm = SessionMap(ObjectMap(robot_id=st.frame.robot, session_id=st.frame.session,
                                      objects=placed, up=_session_up(st, poses)),
                            keyframe_of, poses)
        self._session_maps[name] = (key, sm)
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
            if sol is self.solution:
                return  # nothing changed since the last solve
            self.solution = sol
            self._solutions += 1
            self._global = None
            # ambiguous factors (GNC doubts them, but no two other paths confirm it) are kept
            retract = [fid for fid in sol.outlier_factor_ids if fid in self.factors]
        for fid in retract:
            factor = self.factors.pop(fid)
            self.store.set_factor_status(fid, "retracted")
            self.graph.remove_factor(fid)
            self.stats.factors_retracted += 1
            log.warning("factor %s rejected by GNC: retracted", fid)
            if publish:
                self._publish_factor(factor.model_copy(update={"status": FactorStatus.RETRACTED}))

    def _publish_factor(self, factor: Factor) -> None:
        if self.session is None:  # offline (ingest): nothing to publish to
            return
        payload = encode_message(factor, self.config.factor_profile, "mergesvc", self._next_seq())
        for robot in {factor.robot_a, factor.robot_b}:
            self.session.put(keys.factor_key(self._root, robot, factor.factor_id), payload)

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
                        owned[held.keyframe].append(held.node)
                for k in sorted(owned):
                    node = st.node(k)
                    frames[node], poses[node], frame_of[node] = owned[k], placed[k], name
            pairs = []
            for f in self.factors.values():
                a, b = (self.sessions.get(str(x)) for x in factor_frames(f))
                if a is None or b is None:
                    continue
                for c in f.correspondences:
                    ha, hb = a.objects.get(c.object_a), b.objects.get(c.object_b)
                    if ha is not None and hb is not None:
                        pairs.append((a.node(ha.keyframe), c.object_a,
                                      b.node(hb.keyframe), c.object_b))
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
        res = match(gmap, sub, self.config.match).result
        if not res.accepted:
            return RelocalizeReply(localized=False, reason=res.reason.value, anchor=anchor,
                                   matches=len(res.matches), keyframe=sub.keyframe)
        return RelocalizeReply(localized=True, reason="verified", anchor=anchor,
                               T_anchor_session=res.transform, covariance=res.covariance,
                               matches=len(res.matches), keyframe=sub.keyframe)

    def _on_relocalize(self, query: Any) -> None:
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
                query.reply(query.key_expr, reply.model_dump_json().encode())
            except MergeError as exc:
                self.stats.error("bad_relocalize")
                log.warning("bad relocalize query: %s", exc)
                query.reply_err(json.dumps({"error": "bad_request", "detail": str(exc)}).encode())
            # last resort: every query gets an answer, a failure inside (a solver, a bug) too
            except Exception as exc:
                log.exception("relocalize failed")
                query.reply_err(json.dumps({"error": "internal", "detail": str(exc)}).encode())

    def status(self) -> dict[str, Any]:
        lat = np.asarray(self.stats.latency_ms, dtype=np.float64)
        pct = {f"p{q}": float(np.percentile(lat, q)) if lat.size else float("nan")
               for q in (50, 90, 99)}
        with self._lock:
            frames = {f: len(st.objects) for f, st in self.sessions.items()}
            frame_poses = {f: T.tolist() for f, T in self._frame_poses().items()}
            keyframe_poses = {f: {str(k): T.tolist() for k, T in poses.items()}
                              for f, poses in self.keyframe_poses().items()}
        return {
            "fleet": self.config.fleet,
            "robots_alive": sorted(self.alive),
            "frames": frames,
            "submaps": {"received": self.stats.submaps_received,
                        "duplicate": self.stats.submaps_duplicate,
                        "processed": self.stats.submaps_processed,
                        "rejected": self.stats.submaps_rejected,
                        "deferred": self.stats.submaps_deferred,
                        "queued": self._queue.qsize()},
            "factors": {"accepted": self.stats.factors_accepted,
                        "retracted": self.stats.factors_retracted,
                        "active": len(self.factors)},
            "errors": dict(self.stats.errors),
            "latency_ms": pct,
            "anchor": self._anchor,
            "frame_poses": frame_poses,
            "keyframe_poses": keyframe_poses,
            "store": self.store.stats(),
        }

    def _on_status(self, query: Any) -> None:
        with query:
            try:
                query.reply(query.key_expr, json.dumps(self.status()).encode())
            # last resort: every query gets an answer, a failure inside (a bug) too
            except Exception as exc:
                log.exception("status failed")
                query.reply_err(json.dumps({"error": "internal", "detail": str(exc)}).encode())

    def _on_alive(self, sample: Any) -> None:
        import zenoh

        robot = keys.alive_robot(str(sample.key_expr))
        if sample.kind == zenoh.SampleKind.PUT:
            self.alive.add(robot)
        else:
            self.alive.discard(robot)


__all__ = [
    "HeldObject",
    "MergeService",
    "RelocalizeReply",
    "ServiceConfig",
    "ServiceStats",
    "SessionMap",
    "SessionState",
]
