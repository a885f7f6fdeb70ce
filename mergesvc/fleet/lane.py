"""Large submaps matched beside the worker: a vehicle's whole map relocalized does not stall
the fleet.

A submap of more than `large_submap_objects` objects is matched (core/pipeline.py `match`,
against every session `Merger.to_match` picks) in a child process of low priority
(fleet/solve_process.py), one submap at a time, while the worker goes on merging the other
rows; the child exits after each submap (its memory goes back). The row stays pending
meanwhile: a restart matches it again. The later rows of its session wait for it (a session's
submaps are merged in order); so does another large submap until the lane is free. Once the
matches are back the worker merges the row as any other (`Merger.plan` with them): its matches
are against the sessions' maps of when it was sent, its factors fitted with the sessions as
they are when it is merged."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from mergesvc.core.config import MatchConfig
from mergesvc.core.frames import FrameId
from mergesvc.core.model import Submap
from mergesvc.core.pipeline import match
from mergesvc.errors import SolverError, one_line
from mergesvc.fleet.merger import MatchPlan, Merger
from mergesvc.fleet.solve_process import ProcessOptimizer

log = logging.getLogger(__name__)
CHILD_NICE = 10  # the lane's child yields the cores to the worker and the solver


@dataclass(frozen=True)
class MatchJob:
    """Each (map, submap) pair matched, in the child process: their MatchResults."""

    pairs: list[tuple[Any, Any]]
    config: MatchConfig
    what: str = "large submap's matching"

    def run(self) -> list[Any]:
        try:
            return [match(m, s, self.config).result for m, s in self.pairs]
        except Exception as exc:  # the parent's SolverError: the row is `failed`
            raise SolverError(f"matching failed: {type(exc).__name__}: {one_line(exc)}") \
                from None


class Lane:
    """The large submaps' matches (module docstring); `waiting` holds the rows the worker must
    leave pending for now. Called by the worker thread (`pending`, `defers`, `pop`), its own
    thread (the job) and `close`."""

    def __init__(self, merger: Merger, threshold: int, wake: Callable[[], None],
                 timeout_s: float | None = None) -> None:
        self.merger = merger
        self.threshold = threshold  # objects above which a submap takes the lane (0: never)
        self.timeout_s = timeout_s  # a child that has not answered by then is stopped
        self._wake = wake
        self._child = ProcessOptimizer(nice=CHILD_NICE)
        self._lock = threading.Lock()
        self._busy: tuple[int, str] | None = None  # (row, session) in the lane
        self._done: dict[int, tuple[MatchPlan, Any]] = {}  # row -> (plan, results or error)
        self._last: tuple[int, tuple[MatchPlan, Any]] | None = None  # popped last (a retry)
        self.waiting: set[int] = set()
        self._held: set[str] = set()  # sessions with a row waiting: their later rows wait too
        self.finished = 0  # submaps the lane finished (matched, failed, or nothing to match)
        self._closed = False

    def pending(self, read: Callable[[int], list[int]], n: int) -> list[int]:
        """The first n pending rows (`read(k)`: the first k) not known to wait, for a batch of
        the worker's (`defers` holds back those it finds waiting). With the lane free, every
        row is looked at again, in order (only here: a batch never sees a session's later row
        go before its first)."""
        with self._lock:
            if self._busy is None:
                self.waiting.clear()
                self._held.clear()
            waiting = self.waiting.copy()
        return [i for i in read(n + len(waiting)) if i not in waiting][:n]

    def defers(self, row_id: int, sub: Submap, payload: bytes) -> bool:
        """Whether the worker leaves `row_id` pending for now: the lane takes it (a large
        submap, the lane free), or it waits (the lane busy with another large one, or a row
        of its session waiting). False when its matches are ready (`pop`) or it is small."""
        me = str(FrameId(sub.robot_id, sub.session_id))
        with self._lock:
            if row_id in self._done or (self._last is not None and self._last[0] == row_id):
                return False
            if me in self._held or (self._busy is not None and self._large(sub)):
                self.waiting.add(row_id)
                self._held.add(me)  # its session's later rows wait behind it
                return True
            if not self._large(sub):
                return False
            self._busy = (row_id, me)
            self.waiting.add(row_id)
            self._held.add(me)
        try:
            todo = self.merger.to_match(sub, payload)
            # arrays, not the submap's models, go through the pipe (no Python object per value)
            job = MatchJob([(m, q.arrays() if isinstance(q, Submap) else q)
                            for m, q in todo.pairs], self.merger.config.match)
            # kept for the worker's plan: the sessions, not the pairs (they hold the decoded
            # submap, which the worker decodes again from the row)
            kept = MatchPlan(todo.others, [])
            threading.Thread(target=self._run, args=(row_id, kept, job), daemon=True,
                             name="mergesvc-lane").start()
        except BaseException:  # the lane free again; the row fails in the worker
            with self._lock:
                self._busy = None
            raise
        log.info("submap %s seq %s: %d objects, matched against %d sessions in the lane",
                 me, sub.seq, len(sub.objects), len(job.pairs))
        return True

    def pop(self, row_id: int) -> tuple[MatchPlan, list[Any]] | None:
        """The lane's matches of `row_id` (None: it has none); raises its failure. The last
        one popped is kept: a unit whose commit failed is planned again with it."""
        with self._lock:
            if row_id in self._done:
                self._last = (row_id, self._done.pop(row_id))
            elif self._last is None or self._last[0] != row_id:
                return None
            todo, out = self._last[1]
        if isinstance(out, Exception):
            raise out
        return todo, out

    def _large(self, sub: Submap) -> bool:
        return 0 < self.threshold < len(sub.objects)

    def _run(self, row_id: int, todo: MatchPlan, job: MatchJob) -> None:
        out: Any
        try:
            if self._closed:
                raise SolverError("the service is closing")
            out = self._child(job, self.timeout_s) if job.pairs else []
        except Exception as exc:  # handed to the worker: the row fails there
            log.error("lane: row %d: %s", row_id, one_line(exc))
            out = exc
        self._child.close()  # large submaps are rare: its memory goes back until the next
        with self._lock:
            self._done[row_id] = (todo, out)
            self._busy = None  # the worker's next batch looks at every row again (`pending`)
            self.finished += 1
        self._wake()

    def close(self) -> None:
        """Stop the lane now (a job in flight fails; its row stays pending)."""
        self._closed = True
        self._child.kill()


__all__ = ["Lane", "MatchJob"]
