"""What the service answers about its state: status, the global map, keyframe poses, where a new
session is (relocalize). Each reads the last graph solution and the sessions under the
service's state lock, which the worker holds only to apply a unit of work, never through a
solve: a query never waits on a solve. The global map is fused per embedding model (a model's
objects are never fused or matched with another's), cached until the state changes. The
store's figures in a status reply are read by a thread of their own (`StoreFigures`): a status
query over the network does no I/O once they have been read.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np

from mergesvc.core.calibration import scale_standard_error
from mergesvc.core.config import match_config
from mergesvc.core.frames import FrameId
from mergesvc.core.fusion import fuse_objects
from mergesvc.core.model import ObjectMap, ObjectNode, Submap
from mergesvc.core.pipeline import match
from mergesvc.errors import SchemaError, one_line
from mergesvc.fleet.config import ServiceConfig
from mergesvc.fleet.merger import Merger
from mergesvc.fleet.replies import Outcome, RelocalizeReply, StatusReply, SubmapResult
from mergesvc.store import Store
from mergesvc.wire import Projection, decode_message

LATENCIES_KEPT = 1000  # per-submap timings the percentiles are taken over
log = logging.getLogger(__name__)


class StoreFigures:
    """The store's counts and sizes for status replies, read every `period_s` by a thread of
    its own. Each read releases the GIL several times, and in a busy service every release
    waits for the worker to hand it back: a status query that read the store itself took
    100-500 ms under load. `get(fresh=False)` gives the last read, however old (its age is
    returned; the thread goes on after a failed read, keeping the last figures), and reads only
    when there is none yet; `get(fresh=True)` reads now (in-process callers: exact). After
    each read the thread also builds `reply` with `build` (the status reply without poses, so
    a query only sends bytes: each Python step of building it waited for the GIL too)."""

    def __init__(self, store: Store, period_s: float,
                 build: Callable[[], bytes] | None = None) -> None:
        self.store = store
        self.period_s = period_s
        self.build = build
        self._reply: tuple[float, bytes] | None = None  # (when, the last `build`)
        self._last: tuple[float, dict[str, Any], dict[str, Any]] | None = None
        self._lock = threading.Lock()  # orders the replacements of _last
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        if self.period_s > 0 and self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._loop, name="mergesvc-figures",
                                            daemon=True)
            self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10.0)
            self._thread = None

    def _read(self) -> tuple[float, dict[str, Any], dict[str, Any]]:
        t = time.monotonic()
        counts, stats = self.store.figures()  # one read transaction: one commit's figures
        read = (t, counts, stats)
        with self._lock:  # a slower read that began earlier never replaces a later one
            if self._last is None or self._last[0] <= t:
                self._last = read
        return read

    def _loop(self) -> None:
        failing = False
        while not self._stop.is_set():
            try:
                self._read()
                failing = False
            except Exception as exc:  # a closed store, an I/O error: the last figures stand
                (log.debug if failing else log.warning)(
                    "store figures for status not read: %s", one_line(exc))
                failing = True
            if self.build is not None:
                try:
                    self._reply = (time.monotonic(), self.build())
                except Exception as exc:  # a query builds its own meanwhile
                    self._reply = None
                    log.debug("status reply not built: %s", one_line(exc))
            self._stop.wait(self.period_s)

    @property
    def reply(self) -> bytes | None:
        """The reply the thread built last, unless it is older than two periods (a stalled
        thread: a query then builds its own, whose ages tell the truth)."""
        built = self._reply
        if built is None or time.monotonic() - built[0] > 2.0 * self.period_s + 0.1:
            return None
        return built[1]

    def get(self, fresh: bool = True) -> tuple[dict[str, Any], dict[str, Any], float]:
        """(counts, stats, their age in seconds)."""
        last = self._last
        if fresh or last is None:
            last = self._read()
        return last[1], last[2], max(0.0, time.monotonic() - last[0])


@dataclass
class ServiceStats:
    """Counters the status reply reports (several threads add to them)."""

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

    def count(self, name: str, n: int = 1) -> None:
        with self._lock:
            setattr(self, name, getattr(self, name) + n)

    def error(self, code: str) -> None:
        with self._lock:  # callbacks of several transport threads count here
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

    def timed(self, latency_ms: float, delay_ms: float) -> None:
        with self._lock:
            self.latency_ms.append(latency_ms)
            del self.latency_ms[:-LATENCIES_KEPT]
            self.delay_ms.append(delay_ms)
            del self.delay_ms[:-LATENCIES_KEPT]

    def result_counts(self) -> dict[str, Any]:
        with self._lock:
            return {"processed": self.results_processed,
                    "no_match": dict(self.results_no_match),
                    "refused": dict(self.results_refused),
                    "failed": self.results_failed}

    def percentiles(self, name: str) -> dict[str, float | None]:
        with self._lock:
            a = np.asarray(getattr(self, name), dtype=np.float64)
        return {f"p{q}": float(np.percentile(a, q)) if a.size else None for q in (50, 90, 99)}


class Queries:
    """The service's state seen from outside (module docstring). `lock`: the state lock."""

    def __init__(self, config: ServiceConfig, merger: Merger, lock: threading.RLock) -> None:
        self.config = config
        self.merger = merger
        self.lock = lock
        self._global: dict[int, ObjectMap | None] = {}  # embedding dim -> fused map

    def changed(self) -> None:
        """The state changed (a unit of work applied, a solution taken): maps are stale."""
        self._global.clear()

    @property
    def anchor_dim(self) -> int | None:
        st = self.merger.sessions.get(self.merger.anchor or "")
        return None if st is None else st.dim

    def global_map(self, dim: int | None = None) -> tuple[ObjectMap | None, str | None]:
        """Objects of every session of one embedding model (default: the anchor's) aligned
        with the anchor, each placed with the solved pose of its keyframe, fused (None before
        any submap of that model is placed)."""
        with self.lock:
            sessions, anchor = self.merger.sessions, self.merger.anchor
            dim = self.anchor_dim if dim is None else dim
            if dim is None or not sessions:
                return None, anchor
            if dim in self._global:
                return self._global[dim], anchor
            solution = sessions.solution
            frames: dict[str, list[ObjectNode]] = {}
            poses: dict[str, gtsam.Pose3] = {}
            frame_of: dict[str, str] = {}
            for name, st in sessions.items():
                if st.dim != dim:
                    continue
                placed = sessions.anchor_poses(st, anchor, solution)
                owned: dict[int, list[ObjectNode]] = defaultdict(list)
                for held in st.objects.values():
                    if held.keyframe in placed:
                        owned[held.keyframe].append(held.node)  # built again: fleet/held.py
                for k in sorted(owned):
                    node = st.node(k)
                    frames[node], poses[node], frame_of[node] = owned[k], placed[k], name
            pairs = []
            for f in self.merger.factors.held():  # the object pairs, no Factor built
                a, b = sessions.get(f.frame_a), sessions.get(f.frame_b)
                if a is None or b is None or a.dim != dim:
                    continue
                for object_a, object_b in f.object_pairs():
                    ha, hb = a.objects.get(object_a), b.objects.get(object_b)
                    if ha is not None and hb is not None:
                        pairs.append((a.node(ha.keyframe), object_a,
                                      b.node(hb.keyframe), object_b))
            gmap = None
            if frames and anchor is not None:
                fused = fuse_objects(frames, poses, pairs, frame_of=frame_of)
                at = FrameId.parse(anchor)
                gmap = ObjectMap(robot_id=at.robot, session_id=at.session,
                                 objects=fused.objects)
            self._global[dim] = gmap
            return gmap, anchor

    def frame_poses(self) -> dict[str, np.ndarray]:
        """(4, 4) pose of every session's keyframe 0 (its frame origin) solved with the
        anchor, in the anchor frame."""
        with self.lock:
            sol = self.merger.sessions.solution
            if sol is None:
                return {}
            return {name: np.asarray(T.matrix()) for name, st in self.merger.sessions.items()
                    if (T := sol.T_anchor_frame.get(st.node(0))) is not None}

    def keyframe_poses(self) -> dict[str, dict[int, np.ndarray]]:
        """(4, 4) pose of every keyframe of the anchor's component in the anchor frame (solved,
        or composed by odometry from the nearest solved keyframe); {} before any solution."""
        with self.lock:
            sessions = self.merger.sessions
            if sessions.solution is None:
                return {}
            out = {}
            for name, st in sessions.items():
                placed = sessions.anchor_poses(st, self.merger.anchor, sessions.solution)
                if placed:
                    out[name] = {k: np.asarray(placed[k].matrix()) for k in sorted(placed)}
            return out

    def relocalize(self, sub: Submap) -> RelocalizeReply:
        """Where a new session is in the anchor frame, from a first submap matched against the
        global map of its embedding model: the pose of the submap's keyframe (or, without one,
        of its session frame) in the anchor frame (the anchor session's keyframe 0)."""
        gmap, anchor = self.global_map(sub.dim)
        if gmap is None or len(gmap.objects) < self.config.min_map_objects:
            return RelocalizeReply(localized=False, reason="no_map", anchor=anchor)
        cfg = match_config(self.config.match, verify={
            "max_chance_log10": self.config.relocalize_max_chance_log10})
        res = match(gmap, sub, cfg).result
        if not res.accepted:
            return RelocalizeReply(localized=False, reason=res.reason.value, anchor=anchor,
                                   matches=len(res.matches), keyframe=sub.keyframe)
        return RelocalizeReply(localized=True, reason="verified", anchor=anchor,
                               T_anchor_session=res.transform, covariance=res.covariance,
                               matches=len(res.matches), keyframe=sub.keyframe)

    def relocalize_submap(self, data: bytes | None,
                          projections: dict[str, Projection]) -> Submap:
        """The submap a relocalize query's payload codes; SchemaError if it codes none (the
        service answers it with its own `relocalize`, which the ROS 2 bridge wraps)."""
        if data is None:
            raise SchemaError("relocalize needs a submap in the query payload")
        if len(data) > self.config.max_payload_bytes:
            raise SchemaError(f"{len(data)}-byte query exceeds the limit")
        _, sub = decode_message(data, projections)
        if not isinstance(sub, Submap):
            raise SchemaError("relocalize needs a submap")
        return sub

    def status(self, stats: ServiceStats, figures: StoreFigures, *, poses: bool,
               alive: list[str], solve: dict[str, Any], frozen: int, damage: list[str],
               fresh: bool = True) -> dict[str, Any]:
        """The status reply (StatusReply, strict JSON: no NaN); the store's figures read now
        (`fresh`) or the last read (StoreFigures)."""
        counts, store_stats, age_s = figures.get(fresh)
        with self.lock:
            frames = {f: len(st.objects) for f, st in self.merger.sessions.items()}
            active, held = len(self.merger.factors), len(self.merger.held)
        frame_poses = ({f: T.tolist() for f, T in self.frame_poses().items()}
                       if poses else {})
        keyframe_poses = ({f: {str(k): T.tolist() for k, T in kf.items()}
                           for f, kf in self.keyframe_poses().items()} if poses else {})
        return StatusReply.model_validate({
            "fleet": self.config.fleet, "robots_alive": alive, "frames": frames,
            "models": self.models(),
            "submaps": {"received": stats.submaps_received,
                        "duplicate": stats.submaps_duplicate,
                        "processed": stats.submaps_processed,
                        "rejected": stats.submaps_rejected,
                        "queued": counts["submaps_pending"], "stored": counts["submaps"]},
            "factors": {"accepted": stats.factors_accepted,
                        "retracted": stats.factors_retracted, "active": active, "held": held},
            "results": stats.result_counts(), "errors": dict(stats.errors),
            "latency_ms": stats.percentiles("latency_ms"),
            "delay_ms": stats.percentiles("delay_ms"),
            "optimizations": stats.optimizations, "solve": solve, "frozen_keyframes": frozen,
            "embedding_dim": self.anchor_dim, "anchor": self.merger.anchor,
            "frame_poses": frame_poses, "keyframe_poses": keyframe_poses,
            "store": {**store_stats, "age_s": age_s}, "store_damage": list(damage),
            "noise": self.noise(),
        }).model_dump(mode="json")

    def noise(self) -> dict[str, dict[str, Any]]:
        """Each calibrated noise group: its sigma scale, and from the last calibration its
        redundancy and the scale's relative standard error per axis (status `noise`)."""
        with self.lock:
            groups = self.merger.graph.calibrated()
        out: dict[str, dict[str, Any]] = {}
        for g, (scale, comp) in sorted(groups.items()):
            row: dict[str, Any] = {"sigma_scale": scale.tolist()}
            if comp is not None:
                row["redundancy"] = np.maximum(comp.redundancy, 0.0).tolist()
                row["relative_se"] = [float(x) if np.isfinite(x) else None
                                      for x in scale_standard_error(comp)]
            out[g] = row
        return out

    def models(self) -> dict[str, dict[str, int]]:
        """Per embedding model (its dimension): sessions and objects held."""
        out: dict[str, dict[str, int]] = {}
        with self.lock:
            for st in self.merger.sessions.values():
                m = out.setdefault(str(st.dim), {"sessions": 0, "objects": 0})
                m["sessions"] += 1
                m["objects"] += len(st.objects)
        return out


__all__ = ["LATENCIES_KEPT", "Queries", "ServiceStats", "StoreFigures"]
