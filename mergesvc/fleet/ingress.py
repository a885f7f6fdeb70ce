"""What comes in: every submap payload checked and persisted, in arrival order, before anything
else looks at it. The transport's callback only enqueues (bounded: `ingress_queue_size`); one
thread decodes, checks and stores each payload, then wakes the worker (the store is the queue).

Admission, before anything is stored: the size limit; a decodable submap whose key names its
own robot and session; its embedding model allowed (`embedding_dims`: none set, every model;
each model's maps are matched only with each other); an odometry covariance the pose graph will
take; at most `max_open_sessions_per_robot` sessions open per robot; a token bucket of
`submap_rate_hz` per robot (`submap_burst` at once). A replay of a stored submap is free; a
different payload under a stored key is a conflict: it takes a token, only its hash is kept,
and it is answered `conflict` (final). Every refusal is counted, logged and answered. Per-robot
state (open sessions, buckets) is dropped once a robot has been idle for `session_idle_s`.
"""

from __future__ import annotations

import hashlib
import logging
import queue
import threading
from collections import defaultdict
from collections.abc import Callable

from mergesvc.core.model import Submap
from mergesvc.errors import MergeError, SchemaError, StoreError
from mergesvc.fleet.config import ServiceConfig
from mergesvc.fleet.merger import check_odometry
from mergesvc.fleet.queries import ServiceStats
from mergesvc.fleet.replies import RefusalCode
from mergesvc.fleet.transport import Sample
from mergesvc.store import Store, SubmapConflictError
from mergesvc.wire import Projection, decode_message, keys
from mergesvc.wire.envelope import peek_submap_header

log = logging.getLogger(__name__)

# refuse(robot, code, detail, seq, session): answer a refused submap
Refuse = Callable[[str, RefusalCode, str, "int | None", "str | None"], None]


class RefusedError(SchemaError):
    """A submap refused at the boundary; `code` is the error code the robot is sent."""

    def __init__(self, code: RefusalCode, detail: str) -> None:
        super().__init__(detail)
        self.code = code


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

    def prune(self) -> int:
        """Forget the keys whose bucket has filled up again (their state is the default);
        returns how many."""
        with self._lock:
            now = self.clock()
            full = [k for k, (tok, t) in self._state.items()
                    if tok + max(0.0, now - t) * self.rate_hz >= self.burst]
            for k in full:
                del self._state[k]
            return len(full)

    def __len__(self) -> int:
        return len(self._state)


class Ingress:
    """The ingress thread and its admission rules (module docstring)."""

    def __init__(self, config: ServiceConfig, store: Store, stats: ServiceStats,
                 projections: dict[str, Projection], refuse: Refuse,
                 wake: Callable[[], None], clock: Callable[[], float]) -> None:
        self.config = config
        self.store = store
        self.stats = stats
        self.projections = projections
        self.refuse = refuse
        self.wake = wake
        self.clock = clock
        self.root = keys.fleet_root(config.fleet)
        self.allowed_dims = (set(config.embedding_dims) if config.embedding_dims
                             else {config.embedding_dim} if config.embedding_dim else None)
        self._open: dict[str, dict[str, float]] = defaultdict(dict)  # robot -> session -> seen
        self._bucket = TokenBucket(config.submap_rate_hz, config.submap_burst, clock)
        self._lock = threading.Lock()
        self._admitted = 0
        # pruned every 256 admissions, and at least once per session_idle_s / 4 of them
        self._prune_every_s = config.session_idle_s / 4
        self._pruned_at_s = clock()
        self._inbox: queue.Queue[tuple[str, bytes] | None] = queue.Queue(
            maxsize=config.ingress_queue_size)
        self._thread: threading.Thread | None = None

    # -- the transport's side ----------------------------------------------------------------

    def on_sample(self, sample: Sample) -> None:
        """The transport's callback: enqueue only."""
        if len(sample.payload) > self.config.max_payload_bytes:  # never queued
            self._refuse_payload(sample.key, RefusedError(
                RefusalCode.OVERSIZE, f"{len(sample.payload)}-byte submap exceeds the limit of "
                f"{self.config.max_payload_bytes}"))
            return
        try:
            self._inbox.put_nowait((sample.key, sample.payload))
        except queue.Full:
            self._refuse_payload(sample.key, RefusedError(
                RefusalCode.BUSY,
                f"{self._inbox.maxsize} submaps wait to be stored: send again later"))

    def _refuse_payload(self, key: str, exc: RefusedError) -> None:
        self.stats.count("submaps_received")
        self._answer(keys.submap_robot(self.root, key) or "unknown", key, exc, None)

    # -- the ingress thread ------------------------------------------------------------------

    def start(self) -> None:
        self._thread = threading.Thread(target=self._loop, name="mergesvc-ingress", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 30.0) -> None:
        """What was received is persisted before this returns."""
        if self._thread is not None:
            self._inbox.put(None)
            self._thread.join(timeout=timeout_s)
            self._thread = None

    def _loop(self) -> None:
        while True:
            item = self._inbox.get()
            if item is None:
                return
            try:
                self.receive(*item)
            # last resort: one payload that breaks the checks in an unforeseen way is logged;
            # the thread goes on with the next one
            except Exception:
                log.exception("ingress of a payload on %s failed", item[0])
                self.stats.error("ingress")

    def receive(self, key: str, data: bytes) -> int | None:
        """Check and persist one payload; its row id if it was stored now, else None."""
        robot = keys.submap_robot(self.root, key) or "unknown"
        self.stats.count("submaps_received")
        if len(data) > self.config.max_payload_bytes:
            self._answer(robot, key, RefusedError(
                RefusalCode.OVERSIZE, f"{len(data)}-byte submap exceeds the limit of "
                f"{self.config.max_payload_bytes}"), None)
            return None
        sub: Submap | None = None
        try:
            sub = self._decode(key, robot, data)
            replay = self.admit(sub, hashlib.sha256(data).hexdigest())
        except RefusedError as exc:
            self._answer(robot, key, exc, sub)
            return None
        except StoreError as exc:  # the store could not be read: not now, nothing final
            self._answer(robot, key, RefusedError(RefusalCode.STORE, str(exc)), sub)
            return None
        except MergeError as exc:
            self._answer(robot, key, RefusedError(RefusalCode.BAD_SUBMAP, str(exc)), sub, data)
            return None
        assert sub.seq is not None
        try:
            row_id, created = self.store.put_submap(sub.robot_id, sub.session_id, sub.seq,
                                                    data, self.clock())
        except SubmapConflictError as exc:  # final: the first bytes stay stored
            self._answer(robot, key, RefusedError(RefusalCode.CONFLICT, str(exc)), sub)
            return None
        except MergeError as exc:  # disk full, I/O: not now, nothing final
            log.error("could not persist submap %s/%s/%s: %s", sub.robot_id, sub.session_id,
                      sub.seq, exc)
            self._answer(robot, key, RefusedError(RefusalCode.STORE, str(exc)), sub)
            return None
        if not created or replay:
            self.stats.count("submaps_duplicate")
            return None
        self.wake()
        return row_id

    def _decode(self, key: str, robot: str, data: bytes) -> Submap:
        env, sub = decode_message(data, self.projections)
        if not isinstance(sub, Submap):
            raise SchemaError(f"expected a submap, got a {env.msg_type.value} message")
        if not (sub.robot_id == env.sender == robot):
            raise SchemaError(f"robot mismatch: key says {robot!r}, envelope "
                              f"{env.sender!r}, submap {sub.robot_id!r}")
        if sub.seq is None:
            raise SchemaError("submap without seq")
        expected = keys.submap_key(self.root, sub.robot_id, sub.session_id)
        if key != expected:
            raise SchemaError(f"key {key!r} does not match the submap (robot "
                              f"{sub.robot_id!r}, session {sub.session_id!r}): expected "
                              f"{expected!r}")
        check_odometry(sub)
        return sub

    def _answer(self, robot: str, key: str, exc: RefusedError, sub: Submap | None,
                data: bytes | None = None) -> None:
        """Count, log (one line) and answer a refused submap (`sub`: None when it did not
        decode; then its header, read from `data`, may still name it)."""
        self.stats.count("submaps_rejected")
        log.warning("refused a submap on %s (%s): %s", key, exc.code.value, exc)
        # the session and seq the robot can recognise: only a submap of its own (a robot
        # mismatch names another robot's submap: its seq means nothing to this one)
        if sub is not None:
            own = sub.robot_id == robot
            seq, session = (sub.seq, sub.session_id) if own else (None, None)
        else:  # objects the models refuse (NaN, a negative variance): the header still reads
            head = None if data is None else peek_submap_header(data)
            own = head is not None and head[0] == robot and self._keyed(key, robot, head[1])
            seq, session = (head[2], head[1]) if head is not None and own else (None, None)
        self.refuse(robot, exc.code, str(exc), seq, session)

    def _keyed(self, key: str, robot: str, session: str | None) -> bool:
        """Whether `key` is where robot's session `session` publishes (a name no key can hold
        is not)."""
        try:
            return session is not None and keys.submap_key(self.root, robot, session) == key
        except (MergeError, ValueError):
            return False

    # -- admission ---------------------------------------------------------------------------

    def check_model(self, sub: Submap) -> None:
        """Raises RefusedError when the fleet's settings do not take the submap's embedding
        model (its dimension)."""
        if self.allowed_dims is not None and sub.dim not in self.allowed_dims:
            raise RefusedError(RefusalCode.EMBEDDING_DIM, f"submap has {sub.dim}-d "
                               f"embeddings; this fleet takes "
                               f"{sorted(self.allowed_dims)} (service.embedding_dims)")

    def admit(self, sub: Submap, digest: str) -> bool:
        """The fleet's rules on a decoded submap (module docstring); True for a replay of a
        stored submap (free). Raises RefusedError."""
        assert sub.seq is not None
        stored = self.store.submap_digest(sub.robot_id, sub.session_id, sub.seq)
        if stored == digest:
            return True
        with self._lock:
            now = self.clock()
            self._admitted += 1
            if self._admitted % 256 == 0 or now - self._pruned_at_s >= self._prune_every_s:
                self.prune()
            if stored is not None:  # a conflict: answered once the store has its hash
                self._take(sub)
                return False
            self.check_model(sub)
            sessions = self._open[sub.robot_id]
            if sub.session_id not in sessions:
                idle = self.config.session_idle_s
                n_open = sum(1 for t in sessions.values() if now - t < idle)
                if n_open >= self.config.max_open_sessions_per_robot:
                    raise RefusedError(
                        RefusalCode.TOO_MANY_SESSIONS, f"robot {sub.robot_id!r} has {n_open} "
                        f"open sessions (limit {self.config.max_open_sessions_per_robot}, a "
                        f"session closes {idle:g} s after its last submap)")
            self._take(sub)
            sessions[sub.session_id] = now
        return False

    def _take(self, sub: Submap) -> None:
        if not self._bucket.take(sub.robot_id):
            raise RefusedError(RefusalCode.RATE_LIMITED, f"robot {sub.robot_id!r} sends more "
                               f"than {self.config.submap_rate_hz:g} submaps/s (burst "
                               f"{self.config.submap_burst})")

    def seen(self, robot: str, session: str, at_s: float) -> None:
        """A session known from the store (a restart): it counts as open from then."""
        with self._lock:
            self._open[robot][session] = max(at_s, self._open[robot].get(session, at_s))

    def prune(self) -> None:
        """Drop what closed sessions and idle robots left: sessions idle for session_idle_s,
        robots with none open, buckets that filled up again."""
        now = self.clock()
        self._pruned_at_s = now
        idle = self.config.session_idle_s
        for robot in list(self._open):
            sessions = self._open[robot]
            for s in [s for s, t in sessions.items() if now - t >= idle]:
                del sessions[s]
            if not sessions:
                del self._open[robot]
        self._bucket.prune()

    def state_size(self) -> tuple[int, int]:
        """(robots with open sessions, robots with a bucket): bounded by the active fleet."""
        with self._lock:
            return len(self._open), len(self._bucket)


__all__ = ["Ingress", "RefusedError", "TokenBucket"]
