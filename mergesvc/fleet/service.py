"""The merge service: submaps in (fleet/ingress.py: checked, persisted first), each merged as one
unit of work (fleet/merger.py) committed in one store transaction and only then published,
factors and a result per submap out, one GNC pose graph over every session's keyframes, the
queries (fleet/queries.py), over a Transport (fleet/transport.py). One worker merges pending
rows in batches (a large submap's matching beside it: fleet/lane.py) and solves after a batch
that changed the graph; the state lock is held only to apply a unit or a solution.

Guarantees: at most one final result per submap (published after its row's final status is
committed; after a crash the same result may be published again). A store that cannot write
leaves the row pending and retried with backoff, its robot told `store` (not final); a submap
whose processing raises is `failed`. Retractions found by a solve, a restart or `settle` are
published; a failed solve is retried with backoff and flagged in status; damage found at start
is logged loudly and reported in status (docs/store.md).
"""

from __future__ import annotations

import contextlib
import json
import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from mergesvc.core.frames import FrameId
from mergesvc.core.graph import PoseGraph
from mergesvc.core.model import ErrorMessage, Factor, FactorStatus, Submap
from mergesvc.errors import MergeError, SchemaError, StoreError, one_line
from mergesvc.fleet.answers import Answered, answer_of
from mergesvc.fleet.config import CLOSURE_GROUP, ServiceConfig
from mergesvc.fleet.ingress import Ingress
from mergesvc.fleet.lane import Lane
from mergesvc.fleet.merger import Merger, UnitOfWork, check_odometry
from mergesvc.fleet.mixed import ProfileViews
from mergesvc.fleet.noise_scales import NoiseScaleMemory
from mergesvc.fleet.outbox import Outbox
from mergesvc.fleet.queries import Queries, ServiceStats, StoreFigures
from mergesvc.fleet.replies import Outcome, RefusalCode, SubmapResult
from mergesvc.fleet.sessions import Sessions
from mergesvc.fleet.solve_process import optimizer, trim_heap
from mergesvc.fleet.transport import Query, Reply, Transport
from mergesvc.store import META_ANCHOR, AckLedger, Store, is_memory
from mergesvc.wire import Profile, Projection, decode_message, encode_message, keys

log = logging.getLogger(__name__)
SOLVE_BACKOFF_MAX_S = 60.0  # a failing solve is tried again after 1, 2, 4 ... this many s
STORE_BACKOFF_MAX_S = 30.0  # likewise a store that cannot write


def as_transport(session: Any) -> Transport | None:
    """A Transport from None (offline), a Transport, or a zenoh.Session (wrapped)."""
    if session is None or hasattr(session, "queryable"):  # (a Zenoh session has none)
        return session  # type: ignore[no-any-return]
    from mergesvc.fleet.zenoh_transport import ZenohTransport

    return ZenohTransport(session)


class MergeService:
    """The merge service. `start()` opens everything, `close()` stops it (idempotent)."""

    def __init__(self, config: ServiceConfig, session: Any = None,
                 projections: list[Projection] | None = None,
                 clock: Callable[[], float] = time.time) -> None:
        self.config = config
        self.session = session
        self.transport = as_transport(session)
        self.projections = {p.id: p for p in projections or []}
        self.clock = clock
        self.stats = ServiceStats()
        self.store = Store(config.store)
        self.acks = AckLedger(None if is_memory(config.store) else config.store + ".acks")
        self.graph = PoseGraph(config=config.graph)
        self.graph.optimizer = optimizer(config.solve_in_child, config.solve_timeout_s)
        if config.solve_inflation != 1.0:
            self.graph.set_noise_scale(CLOSURE_GROUP, config.solve_inflation ** 0.5)
        self.sessions = Sessions(config.min_map_objects)
        self.merger = Merger(config, self.graph, self.sessions, ProfileViews(self.projections))
        self._lock = threading.RLock()  # the state: held to apply work and solutions, to query
        # the graph's writers (worker, ingest): one submap or solve at a time; queries never
        self._process_lock = threading.Lock()
        self.queries = Queries(config, self.merger, self._lock)
        self.figures = StoreFigures(self.store, config.status_refresh_s,
                                    lambda: self._status_json(False, False))
        self._wake = threading.Event()  # set after a submap is stored: the worker looks
        self.lane = Lane(self.merger, config.large_submap_objects, self._wake.set,
                         config.solve_timeout_s)
        self.outbox = Outbox(config, self.transport, self.stats)
        self.answered = Answered(self.store)  # units whose messages went out (fleet/answers)
        self.scales = NoiseScaleMemory(self.store, self.graph)
        self.ingress = Ingress(config, self.store, self.stats, self.projections,
                               self.outbox.refusal, self._wake.set, clock)
        self._stop = threading.Event()
        self._worker: threading.Thread | None = None
        self._handles: list[Any] = []
        self._root = keys.fleet_root(config.fleet)
        self._dirty = False  # a processed submap changed the graph: solve it
        self._last_optimize = time.monotonic()
        self._solve_s = (0.0, 0.0)  # the last solve: (its duration, when it ended), monotonic
        self._solve = {"failures": 0, "error": None, "next_s": 0.0, "solved_at_s": None}
        self._store_failures = 0
        self._told_store: set[int] = set()  # rows whose robot was told `store` (_not_now)
        self._unstored_retractions: list[Factor] = []  # GNC retracted, not in the store yet
        self.alive: set[str] = set()
        self.damage: list[str] = []

    # -- what other modules read -------------------------------------------------------------

    @property
    def factors(self) -> Any:
        return self.merger.factors

    @property
    def solution(self) -> Any:
        return self.sessions.solution

    @property
    def anchor(self) -> str | None:
        return self.merger.anchor

    # -- lifecycle ---------------------------------------------------------------------------

    def start(self) -> MergeService:
        try:
            self.restore()
        except BaseException:
            self.close()  # the store is not left open by a service that never started
            raise
        t = self.transport
        if t is not None:
            self._handles = [
                t.subscribe(keys.all_submaps(self._root), self.ingress.on_sample, recover=True),
                t.queryable(keys.relocalize_key(self._root), self._on_relocalize),
                t.queryable(keys.status_key(self._root), self._on_status),
                t.liveliness(keys.all_alive(self._root), self._on_alive),
            ]
        self.ingress.start()
        self.figures.start()
        self._worker = threading.Thread(target=self._work, name="mergesvc-worker", daemon=True)
        self._worker.start()
        log.info("merge service up: fleet %s, %d sessions, %d factors restored",
                 self.config.fleet, len(self.sessions), len(self.factors))
        return self

    def close(self) -> None:
        self._stop.set()
        for h in self._handles:
            with contextlib.suppress(MergeError):
                h.close()
        self._handles = []
        self.ingress.stop()  # what was received is persisted before closing
        self.figures.stop()
        self.lane.close()
        if self._worker is not None:
            self._worker.join(timeout=10.0)
            self._worker = None
        self.answered.flush()
        self.store.close()

    def __enter__(self) -> MergeService:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def restore(self) -> None:
        """After a restart: damage checked, the sessions and the graph from the processed
        submaps, the factors with the verdicts they had, the graph solved as it grew, what
        that solve retracts published; then the worker redoes the pending rows."""
        self.store.claim_fleet(self.config.fleet)
        self.damage = self.acks.lost(self.store.final_seqs())
        for line in self.damage:
            log.error("store %s lost answered submaps: %s", self.store.path, line)
        if (anchor := self.store.meta(META_ANCHOR)) is not None:  # else the first processed's
            self.merger.set_anchor(anchor)
        for fr in self.store.frames():
            self.ingress.seen(fr.robot_id, fr.session_id, fr.last_seen_s)
        for row in self.store.iter_submaps():  # a page at a time: a mission's worth
            if row.status in ("processed", "no_match"):
                sub = self._decode(row.payload)
                self.merger.views.note(f"{sub.robot_id}/{sub.session_id}", row.payload)
                self.merger.restore(sub)
        rows = [(f.created_at_s, 0, i, f, True) for i, f in
                enumerate(self.store.iter_factors(FactorStatus.ACCEPTED))]
        rows += [(f.created_at_s, 1, i, f, False) for i, f in
                 enumerate(self.store.held_factors())]
        for *_, f, trusted in sorted(rows, key=lambda r: r[:3]):
            self.merger.restore_factor(Factor.model_validate_json(f.payload), trusted)
        self.scales.restore()
        if len(self.factors):
            # solved as it grew, with the noise scales the last solve had
            self.graph.calibrating = False
            try:
                self.graph.settle()
            except MergeError as exc:
                log.warning("pose graph optimisation failed: %s", exc)
            self._optimize()
            self.graph.calibrating = True
        self.answered.republish(self.outbox, self.merger.factor)
        self._wake.set()  # the worker takes the pending rows from the store

    # -- the worker --------------------------------------------------------------------------

    def _work(self) -> None:
        """Batches of pending rows, oldest first; the graph solved after a batch that changed
        it when the backlog is drained, or every optimize_interval_s while it is not."""
        while not self._stop.is_set():
            # the timeout bounds a lost wake-up, the backoffs and a solve's rest
            rest = max(self._rest(), self._solve["next_s"] - time.monotonic())
            self._wake.wait(timeout=min(1.0, max(0.05, rest)) if self._dirty else 1.0)
            self._wake.clear()  # before the store is read: a later commit is seen next round
            try:
                while not self._stop.is_set():
                    ids = self.lane.pending(self.store.pending_ids, self.config.queue_size)
                    stalled = False
                    for row_id in ids:
                        if self._stop.is_set():
                            return
                        if not self._process_row(row_id):
                            stalled = True  # the store cannot write: back off, retry later
                            break
                    waited = time.monotonic() - self._last_optimize
                    if self._dirty and self._rest() <= 0 and (
                            not ids or stalled or waited >= self.config.optimize_interval_s):
                        self._flush()
                    self.answered.flush()
                    if self._unstored_retractions:
                        with self._process_lock:
                            self._publish_retractions()
                    if not ids or stalled:
                        break
                if stalled:
                    self._stop.wait(min(STORE_BACKOFF_MAX_S, 2.0 ** self._store_failures))
                    self._wake.set()
            # last resort of the only worker thread: a failure outside one submap is logged and
            # the loop goes on after a pause
            except Exception:
                log.exception("merge worker: a round failed; retrying")
                self.stats.error("worker")
                self._stop.wait(1.0)

    def _process_row(self, row_id: int) -> bool:
        """Merge one stored row; False when the store could not commit (the row stays
        pending, its work rolled back). A submap whose processing raises is `failed`."""
        with self._process_lock:
            try:
                self._process(row_id)
            except StoreError as exc:
                self._store_failures += 1
                log.error("submap row %d: the store cannot write, retried later: %s", row_id,
                          one_line(exc))
                self._not_now(row_id, exc)
                return False
            except Exception as exc:
                log.exception("processing submap row %d failed", row_id)
                self.stats.error(RefusalCode.PROCESSING.value)
                self._fail(row_id, exc)
            self._told_store.discard(row_id)
            self._store_failures = 0
            return True

    def _not_now(self, row_id: int, exc: StoreError) -> None:
        """A row whose unit could not be committed: its robot is told `store` (not final; a
        replay of it is free) once per row, and its result follows once the store writes."""
        try:
            row = None if row_id in self._told_store else self.store.submap(row_id)
        except StoreError:  # (reads mostly work while writes do not)
            row = None
        if row is None:
            self.stats.error(RefusalCode.STORE.value)
            return
        self._told_store.add(row_id)
        self.outbox.refusal(row.robot_id, RefusalCode.STORE, f"stored; its result follows once "
                            f"the store can write ({one_line(exc)})", row.seq, row.session_id)

    def _fail(self, row_id: int, exc: Exception) -> None:
        """A row whose processing raised: `failed` (final) once the store says so."""
        row = self.store.submap(row_id)
        detail = f"{type(exc).__name__}: {exc}"[:1000]
        if row.status != "pending":  # committed already: its answer stands
            log.error("submap row %d failed after its commit: %s", row_id, detail)
            return
        try:
            self.store.mark_processed(row_id, "failed", detail[:500])
        except StoreError as store_exc:  # not final yet: retried like any unwritten row
            log.warning("could not mark submap row %d failed: %s", row_id, store_exc)
            return
        self.outbox.result(SubmapResult(
            robot=row.robot_id, session=row.session_id, seq=row.seq if row.seq >= 0 else None,
            outcome=Outcome.FAILED, code=RefusalCode.PROCESSING, detail=detail))

    def _decode(self, payload: bytes) -> Submap:
        """A stored payload (checked to be a submap when it arrived) decoded again."""
        env, sub = decode_message(payload, self.projections)
        if not isinstance(sub, Submap):
            raise SchemaError(f"stored payload is a {env.msg_type.value} message, not a submap")
        return sub

    def _process(self, row_id: int, lane: bool = True) -> None:
        t0 = time.perf_counter()
        row = self.store.submap(row_id)
        if row.status != "pending":
            return
        sub = self._decode(row.payload)
        if lane and self.lane.defers(row_id, sub, row.payload):  # (fleet/lane.py)
            return
        uow = self.merger.plan(row_id, sub, row.payload, self._lock, self.lane.pop(row_id))
        self.stats.count("matches_tried", uow.matches_tried)
        try:
            self._commit(uow)
        except BaseException:  # nothing of an uncommitted unit stays in memory
            with self._lock:
                self.merger.rollback(uow)
            raise
        with self._lock:
            self._dirty |= self.merger.apply(uow)
            self.queries.changed()
        self._answer(uow)
        ms = (time.perf_counter() - t0) * 1e3
        self.stats.timed(ms, max(0.0, (self.clock() - row.received_at_s) * 1e3))
        log.info("submap %s/%s seq %s keyframe %s: %d objects, %d sessions tried, %d factors "
                 "(%d sent, %d held), %.0f ms", sub.robot_id, sub.session_id, sub.seq,
                 sub.keyframe, len(sub.objects), uow.matches_tried, len(uow.factors),
                 len(uow.sent), len(uow.held), ms)

    def _commit(self, uow: UnitOfWork) -> None:
        """The unit's rows in one transaction (store/factors.py commit_unit)."""
        sub = uow.sub

        def rows(fs: list[Factor]) -> list[tuple[str, str, str, bytes]]:
            return [(f.factor_id, f"{f.robot_a}/{f.session_a}", f"{f.robot_b}/{f.session_b}",
                     f.model_dump_json().encode()) for f in fs]

        self.store.commit_unit(
            uow.row_id, uow.status, uow.detail,
            frame=(sub.robot_id, sub.session_id, self.clock()), sent=rows(uow.sent),
            withdrawn=[f.factor_id for f in uow.withdrawn],
            held=rows([*uow.held, *uow.withdrawn]),
            anchor=self.merger.anchor or str(FrameId(sub.robot_id, sub.session_id)),  # apply's
            answer=answer_of(uow.result, uow.sent, uow.withdrawn))

    def _answer(self, uow: UnitOfWork) -> None:
        """A committed unit's messages: its factors, retractions, its result (the answer is
        recorded beside the store first: store/acks.py)."""
        sub = uow.sub
        try:
            self.acks.record(sub.robot_id, sub.session_id, sub.seq or 0)
        except StoreError as exc:
            log.error("%s", exc)
        self.stats.count("factors_accepted", len(uow.sent))  # before a vehicle can see them
        self.stats.count("factors_matched", len(uow.factors))
        self.stats.count("factors_retracted", len(uow.withdrawn))
        self.stats.count("submaps_processed")
        for f in uow.sent:
            self.outbox.factor(f)
        for f in uow.withdrawn:
            self.outbox.factor(f.model_copy(update={"status": FactorStatus.RETRACTED}))
        self.outbox.result(uow.result)
        self.answered.add(uow.row_id)

    def ingest(self, sub: Submap, profile: Profile = Profile.FULL, optimize: bool = True) -> int:
        """Persist and process one submap now, in the calling thread, as if it had arrived
        coded with `profile` (a restart reloads it like any other): offline replays and tests.
        Returns its row id; a submap stored before is not processed again. `optimize`: solve
        the pose graph now (else with the next solve)."""
        if sub.seq is None:
            raise SchemaError("submap without seq")
        self.ingress.check_model(sub)
        check_odometry(sub)
        data = encode_message(sub, profile, sub.robot_id, sub.seq)
        row_id, created = self.store.put_submap(sub.robot_id, sub.session_id, sub.seq, data,
                                                self.clock())
        self.stats.count("submaps_received")
        if created:
            with self._process_lock:
                self._process(row_id, lane=False)
            if optimize:
                self._flush()
                self.answered.flush()
        else:
            self.stats.count("submaps_duplicate")
        return row_id

    # -- solving -----------------------------------------------------------------------------

    def _flush(self) -> None:
        """Solve the pose graph if a processed submap changed it and no backoff holds."""
        if self._dirty and time.monotonic() >= self._solve["next_s"]:
            self._last_optimize = time.monotonic()
            self._optimize()
            self._solve_s = (time.monotonic() - self._last_optimize, time.monotonic())

    def _rest(self) -> float:
        """Seconds until the worker may solve again: solves take at most `solve_duty` of its
        time, so submaps arriving meanwhile do not wait behind one solve after another."""
        took, ended = self._solve_s
        return took * (1.0 / self.config.solve_duty - 1.0) - (time.monotonic() - ended)

    def _optimize(self) -> None:
        """Solve (the state lock not held: queries go on), take the solution, retract what it
        rejects and publish the retractions. A failed solve keeps the graph dirty and is
        tried again after a backoff; status says so."""
        with self._process_lock:  # no submap changes the graph while it is solved
            self._solve_graph()

    def _solve_graph(self) -> None:
        try:
            sol = self.graph.optimize(marginals=False)
        except Exception as exc:
            s = self._solve
            s.update(failures=s["failures"] + 1, error=one_line(exc))
            s["next_s"] = time.monotonic() + min(SOLVE_BACKOFF_MAX_S, 2.0 ** s["failures"])
            self._dirty = True
            log.warning("pose graph optimisation failed (%d in a row): %s", s["failures"], exc)
            return
        self._dirty = False
        self._solve.update(failures=0, error=None, next_s=0.0, solved_at_s=self.clock())
        self.stats.count("optimizations")
        if sol is self.sessions.solution:
            return  # nothing changed since the last solve
        self.scales.save()
        retracted = []
        with self._lock:
            self.sessions.solved(sol)
            self.queries.changed()
            for fid in [f for f in sol.outlier_factor_ids if f in self.factors]:
                f = self.merger.retract(fid)
                if f is not None:
                    retracted.append(f)
                    log.warning("factor %s rejected by GNC: retracted", fid)
        self._unstored_retractions.extend(retracted)
        self._publish_retractions()
        trim_heap()

    def _publish_retractions(self) -> None:
        """Retractions stored, then published; one the store cannot write yet is kept and
        tried again each worker round (never published before the store has it)."""
        left = []
        for f in self._unstored_retractions:
            try:
                self.store.set_factor_status(f.factor_id, "retracted")
            except StoreError as exc:
                log.warning("retraction of %s not stored yet: %s", f.factor_id, one_line(exc))
                left.append(f)
                continue
            self.outbox.factor(f.model_copy(update={"status": FactorStatus.RETRACTED}))
            self.stats.count("factors_retracted")
        self._unstored_retractions = left

    # -- queries -----------------------------------------------------------------------------

    def global_map(self, dim: int | None = None) -> Any:
        return self.queries.global_map(dim)

    def keyframe_poses(self) -> dict[str, dict[int, np.ndarray]]:
        return self.queries.keyframe_poses()

    def relocalize(self, sub: Submap) -> Any:
        return self.queries.relocalize(sub)

    def status(self, poses: bool = True, fresh: bool = True) -> dict[str, Any]:
        """The service's state as strict JSON (StatusReply); `poses=False` leaves the
        (growing) pose fields empty; the store's figures read now (`fresh`) or the last read
        (`store.age_s` old)."""
        s = self._solve
        age = None if s["solved_at_s"] is None else max(0.0, self.clock() - s["solved_at_s"])
        return self.queries.status(
            self.stats, self.figures, poses=poses, fresh=fresh, alive=sorted(self.alive),
            solve={"ok": s["error"] is None, "error": s["error"], "failures": s["failures"],
                   "solution_age_s": age},
            frozen=self.graph.frozen_count, damage=self.damage)

    def _on_status(self, query: Query) -> Reply:
        poses = query.parameters.get("poses") not in ("false", "0", "no")
        fresh = self.config.status_refresh_s <= 0  # else the figures' thread's last read
        built = None if poses or fresh else self.figures.reply  # (StoreFigures)
        return Reply(built or self._status_json(poses, fresh), keys.JSON_ENCODING)

    def _status_json(self, poses: bool, fresh: bool) -> bytes:
        return json.dumps(self.status(poses, fresh), allow_nan=False).encode()

    def _on_relocalize(self, query: Query) -> Reply:
        self.stats.count("relocalize_queries")
        try:
            return Reply(self.relocalize(self.queries.relocalize_submap(
                query.payload, self.projections)).model_dump_json().encode(), keys.JSON_ENCODING)
        except MergeError as exc:
            self.stats.error("bad_relocalize")
            log.warning("bad relocalize query: %s", exc)
            doc = ErrorMessage(code="bad_request", detail=str(exc)[:1000])
            return Reply(doc.model_dump_json().encode(), keys.JSON_ENCODING, ok=False)

    def _on_alive(self, key: str, alive: bool) -> None:
        (self.alive.add if alive else self.alive.discard)(keys.alive_robot(key))


__all__ = ["MergeService", "as_transport"]
