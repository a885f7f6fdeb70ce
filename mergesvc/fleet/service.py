"""Merge service over Zenoh: submaps in (persisted first), verified matching against every other
robot-session frame, inter-robot factors out, a GNC pose graph over the frames, fused global
objects, relocalization and status queryables.

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
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mergesvc.core.config import MatchConfig
from mergesvc.core.factors import factor_frames, factor_from_match, match_factor_id, yields_factor
from mergesvc.core.frames import FrameId
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
        description="added to every factor's covariance: rotation rad, translation m. Odometry "
        "frames drift, so the same pair of frames seen through different stretches of two "
        "trajectories differs by more than the fit's own covariance says",
    )
    match: MatchConfig = Field(
        default_factory=lambda: MatchConfig.model_validate(
            {"verify": {"min_matches": 4, "min_matches_vertical": 4}}
        ),
        description="verified matching; an inter-robot factor needs 4 matched objects by "
        "default, with or without a known vertical (3 points admit coincidental fits in a "
        "small pool, and a wrong factor costs more than a late one)",
    )
    graph: GraphConfig = Field(
        GraphConfig(), description="the GNC pose graph over the frames (outlier thresholds)"
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
    """Answer of the relocalize queryable: the new session's frame in the anchor frame."""

    model_config = ConfigDict(extra="forbid")

    localized: bool
    reason: str
    anchor: str | None = None
    T_anchor_session: Transform | None = None
    covariance: list[list[float]] | None = None
    matches: int = 0


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
        self.frames: dict[str, dict[str, ObjectNode]] = {}  # frame -> object id -> node
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
        self._anchor: str | None = None
        self._frame_maps: dict[str, ObjectMap] = {}  # validated once per frame change
        self.solution: GraphSolution | None = None

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> MergeService:
        from zenoh.ext import HistoryConfig, RecoveryConfig, declare_advanced_subscriber

        self._rebuild()
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
        log.info("merge service up: fleet %s, %d frames, %d factors restored",
                 self.config.fleet, len(self.frames), len(self.factors))
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

    def _rebuild(self) -> None:
        """After a restart: frames from processed submaps, factors, the graph; then redo the
        submaps that were persisted but not processed."""
        frames = self.store.frames()
        if frames:
            self._anchor = frames[0].frame  # published coordinates stay in one frame
            self.graph.anchor = self._anchor
        for row in self.store.submaps():
            if row.status in ("processed", "no_match"):
                sub = self._decode_submap(row.payload)
                self._add_to_frame(sub)
        for f in self.store.factors():
            factor = Factor.model_validate_json(f.payload)
            if f.status == "accepted":
                self.graph.add_factor_model(factor)
                self.factors[factor.factor_id] = factor
        if self.factors:
            self._optimize(publish=False)
        for row in self.store.unprocessed_submaps():
            self._offer(row.row_id)

    # ------------------------------------------------------------------ ingress

    def _publish_error(self, robot: str, code: str, detail: str, seq: int | None) -> None:
        import zenoh

        self.stats.error(code)
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
            others = [(f, self._frame_map(f)) for f, objs in self.frames.items()
                      if f != me and len(objs) >= self.config.min_map_objects]
        for other, map_ in others:
            other_id = FrameId.parse(other)
            self.stats.matches_tried += 1
            res = match(map_, sub, self.config.match).result
            if not yields_factor(res):
                continue
            factor = factor_from_match(
                res, other_id, me_id, factor_id=match_factor_id(other_id, me_id, sub.seq),
                drift_sigma=self.config.drift_sigma,
            )
            # a replay after a crash finds the factor stored already: publish it again (its id
            # is deterministic, so receivers see the same factor twice at most)
            self.store.put_factor(factor.factor_id, other, me, factor.model_dump_json().encode(),
                                  "accepted")
            new_factors.append(factor)
        with self._lock:
            self._add_to_frame(sub)
            for factor in new_factors:
                if factor.factor_id not in self.factors:
                    self.factors[factor.factor_id] = factor
                    self.graph.add_factor_model(factor)
        for factor in new_factors:
            self._publish_factor(factor)
            self.stats.factors_accepted += 1
        if new_factors:
            self._optimize(publish=True)
        self.store.mark_processed(row_id, "processed" if new_factors else "no_match",
                                  f"{len(new_factors)} factors")
        self.stats.submaps_processed += 1
        ms = (time.perf_counter() - t0) * 1e3
        self.stats.latency_ms.append(ms)
        del self.stats.latency_ms[:-1000]
        log.info("submap %s seq %s: %d objects, %d frames tried, %d factors, %.0f ms",
                 me, sub.seq, len(sub.objects), len(others), len(new_factors), ms)

    def _frame_map(self, name: str) -> ObjectMap:
        """A frame's objects as a map (its arrays cached with it until the frame changes)."""
        if name not in self._frame_maps:
            frame = FrameId.parse(name)
            self._frame_maps[name] = ObjectMap(robot_id=frame.robot, session_id=frame.session,
                                               objects=list(self.frames[name].values()))
        return self._frame_maps[name]

    def _add_to_frame(self, sub: Submap) -> None:
        name = str(FrameId(sub.robot_id, sub.session_id))
        if name not in self.frames:
            self.store.put_frame(sub.robot_id, sub.session_id, self.clock())
            self.graph.add_frame(name)
        objs = self.frames.setdefault(name, {})
        for o in sub.objects:  # the latest estimate of an object replaces the older one
            objs[o.id] = o
        self._frame_maps.pop(name, None)
        self._global = None
        if self._anchor is None:
            self._anchor = name
            self.graph.anchor = name

    def _optimize(self, publish: bool) -> None:
        with self._lock:
            try:
                sol = self.graph.optimize()
            except MergeError as exc:
                log.warning("pose graph optimisation failed: %s", exc)
                return
            self.solution = sol
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
        payload = encode_message(factor, self.config.factor_profile, "mergesvc", self._next_seq())
        for robot in {factor.robot_a, factor.robot_b}:
            self.session.put(keys.factor_key(self._root, robot, factor.factor_id), payload)

    # ------------------------------------------------------------------ queries

    def global_map(self) -> tuple[ObjectMap | None, str | None]:
        """Objects of every frame aligned to the anchor, fused (None before any alignment)."""
        with self._lock:
            if self._global is not None or not self.frames:
                return self._global, self._anchor
            poses = self._frame_poses()
            anchor = self._anchor
            poses.setdefault(anchor, np.eye(4))
            frames = {f: list(o.values()) for f, o in self.frames.items() if f in poses}
            pairs = []
            for f in self.factors.values():
                a, b = (str(x) for x in factor_frames(f))
                pairs += [(a, c.object_a, b, c.object_b) for c in f.correspondences]
            fused = fuse_objects(frames, poses, pairs)
            at = FrameId.parse(anchor)
            self._global = ObjectMap(robot_id=at.robot, session_id=at.session,
                                     objects=fused.objects)
            self._anchor = anchor
            return self._global, anchor

    def _frame_poses(self) -> dict[str, np.ndarray]:
        """(4, 4) pose of every frame aligned with the anchor, in the anchor frame."""
        if self.solution is None:
            return {}
        return {f: np.asarray(T.matrix()) for f, T in self.solution.T_anchor_frame.items()}

    def relocalize(self, sub: Submap) -> RelocalizeReply:
        """Where a new session's frame is in the anchor frame, from a first submap."""
        gmap, anchor = self.global_map()
        if gmap is None or len(gmap.objects) < self.config.min_map_objects:
            return RelocalizeReply(localized=False, reason="no_map")
        res = match(gmap, sub, self.config.match).result
        if not res.accepted:
            return RelocalizeReply(localized=False, reason=res.reason.value, anchor=anchor,
                                   matches=len(res.matches))
        return RelocalizeReply(localized=True, reason="verified", anchor=anchor,
                               T_anchor_session=res.transform, covariance=res.covariance,
                               matches=len(res.matches))

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
        lat = np.asarray(self.stats.latency_ms or [np.nan])
        return {
            "fleet": self.config.fleet,
            "robots_alive": sorted(self.alive),
            "frames": {f: len(o) for f, o in self.frames.items()},
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
            "latency_ms": {"p50": float(np.nanpercentile(lat, 50)),
                           "p90": float(np.nanpercentile(lat, 90)),
                           "p99": float(np.nanpercentile(lat, 99))},
            "anchor": self._anchor,
            "frame_poses": {f: T.tolist() for f, T in self._frame_poses().items()},
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


__all__ = ["MergeService", "RelocalizeReply", "ServiceConfig", "ServiceStats"]
