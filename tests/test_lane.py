"""Large submaps matched beside the worker (fleet/lane.py), with real parts: the service on the
in-process transport, a real store, real matching in the lane's real child process. The lane's
child is held shut by a gate where a test needs the large submap still in the lane: the other
robots' submaps are merged meanwhile, its own session's later ones wait, and once it is let
through its result is the one the worker would have given."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers import wait_for
from test_faults import Fleet, cfg_at, outcomes
from test_service_limits import make_submap, moved, payload

from mergesvc.core.model import Submap
from mergesvc.errors import SolverError
from mergesvc.fleet.config import ServiceConfig
from mergesvc.fleet.lane import Lane, MatchJob
from mergesvc.fleet.service import MergeService
from mergesvc.fleet.solve_process import ProcessOptimizer


def scene60() -> Submap:
    """a's 60 objects: a large submap (threshold 20) of another robot seeing them matches."""
    return make_submap("a", "s0", 0, n=60, seed=1)


def part(sub: Submap, n: int = 8) -> Submap:
    """A small submap: the first n objects."""
    return sub.model_copy(update={"objects": sub.objects[:n]})


class Gate:
    """The lane's child behind a gate: a job waits until `opened` (then the real child runs
    it, within `timeout_s` when set); killed (the service closing), the job fails."""

    def __init__(self, lane: Lane) -> None:
        self.real, self.opened, self.entered = lane._child, threading.Event(), threading.Event()
        self.timeout_s: float | None = None
        self.closed = False
        lane._child = self  # type: ignore[assignment]

    def __call__(self, job: Any, timeout_s: float | None = None) -> Any:
        self.entered.set()
        assert self.opened.wait(60.0)
        if self.closed:
            raise SolverError("closed")
        return self.real(job, self.timeout_s or timeout_s)

    def kill(self) -> None:  # (the service closing)
        self.closed = True
        self.opened.set()
        self.real.kill()

    def close(self) -> None:
        self.real.close()


def test_a_large_submap_does_not_hold_the_others_and_gives_the_workers_answer(
        tmp_path: Path) -> None:
    """c's 60-object submap goes to the lane (threshold 20). While its child is held, b's
    submap is merged (its factor with a sent), and c's next submap waits behind its first.
    Let through, c's submaps are answered in order, and c's factor is the one a service
    matching in its worker (threshold 0, `ingest`) makes: same id, same pose to 1e-9."""
    a = scene60()
    big = moved(a, "c")
    with Fleet(cfg_at(tmp_path / "l.db", large_submap_objects=20)) as fl:
        gate = Gate(fl.svc.lane)
        fl.put(a)
        assert wait_for(lambda: len(fl.of("a")) == 1, 20.0)
        fl.put(big)
        assert gate.entered.wait(20.0)
        fl.put(part(big).model_copy(update={"seq": 1}))  # small, waits behind seq 0
        fl.put(part(moved(a, "b")))
        assert wait_for(lambda: len(fl.of("b")) == 1, 20.0)
        assert outcomes(fl.of("b")) == ["processed"]
        assert fl.of("c") == [] and len(fl.svc.lane.waiting) == 2  # c's two rows
        gate.opened.set()
        assert wait_for(lambda: len(fl.of("c")) == 2, 30.0)
        assert [r.seq for r in fl.of("c")] == [0, 1]
        assert outcomes(fl.of("c"))[0] == "processed"
        assert fl.svc.lane.finished == 2  # a's (no other session yet) and c's
        lane_factor = fl.svc.merger.factor(fl.of("c")[0].factors[0])
        kept = fl.svc.lane._last  # for a retried plan: the sessions, not c's decoded submap
        assert kept is not None and kept[1][0].others and kept[1][0].pairs == []
    with MergeService(cfg_at(tmp_path / "w.db", large_submap_objects=0)) as svc:
        svc.ingest(a)
        svc.ingest(big)
        worker_factor = svc.merger.factor(lane_factor.factor_id)
    assert worker_factor is not None and lane_factor is not None
    def pose(f: Any) -> list[float]:
        return [*f.T_a_b.translation, *f.T_a_b.quaternion_wxyz]

    np.testing.assert_allclose(pose(lane_factor), pose(worker_factor), atol=1e-9)
    np.testing.assert_allclose(lane_factor.covariance, worker_factor.covariance, atol=1e-9)


def test_a_lane_that_dies_fails_its_submap_only_and_a_restart_matches_a_pending_one(
        tmp_path: Path) -> None:
    """The lane's child stopped mid-match (it did not answer in time): that submap is
    `failed` (one result), the service goes on merging. A service closed with a large
    submap in its lane leaves it pending; the next one matches it (processed once)."""
    a = scene60()
    cfg = cfg_at(tmp_path / "d.db", large_submap_objects=20)
    with Fleet(cfg) as fl:
        gate = Gate(fl.svc.lane)
        fl.put(a)
        # a merged first: c put with it may be planned before a's session is placed (nothing
        # to match, so no job enters the lane; seen under load)
        assert wait_for(lambda: len(fl.of("a")) == 1, 20.0)
        fl.put(moved(a, "c"))
        assert gate.entered.wait(20.0)
        gate.timeout_s = 1e-3  # (a child takes longer than that to start)
        gate.opened.set()
        assert wait_for(lambda: len(fl.of("c")) == 1, 60.0)  # a child killed under load
        assert outcomes(fl.of("c")) == ["failed/processing"]
        fl.put(part(moved(a, "b")))
        assert wait_for(lambda: outcomes(fl.of("b")) == ["processed"], 20.0)

    with Fleet(cfg) as fl:
        gate = Gate(fl.svc.lane)
        # the restarted service has a's session placed again before d is planned
        assert wait_for(lambda: fl.svc.merger.sessions.session_map("a/s0") is not None, 20.0)
        fl.put(moved(a, "d"))
        assert gate.entered.wait(20.0)
    assert fl.of("d") == []  # closed with it in the lane: still pending
    with Fleet(cfg) as again:
        assert wait_for(lambda: len(again.of("d")) == 1, 30.0)
        assert outcomes(again.of("d")) == ["processed"]


@pytest.mark.parametrize("objects", [20, 21])
def test_only_submaps_above_the_threshold_take_the_lane(tmp_path: Path, objects: int) -> None:
    a = scene60()
    with Fleet(cfg_at(tmp_path / "t.db", large_submap_objects=20)) as fl:
        fl.put(a)
        fl.put(part(moved(a, "c"), objects))
        assert wait_for(lambda: len(fl.of("c")) == 1, 30.0)
        assert fl.svc.lane.finished == 1 + (objects > 20)  # a's too


def test_a_session_waits_for_its_large_submap_until_the_next_batch() -> None:
    """A worker's batch [c's large seq 0, b's small, c's small seq 1]: the lane takes c's first
    and finishes at once (no other session to match); c's second still waits in this batch
    (it used to go first: the lane's thread freed the session mid-batch), b's does not; the
    next batch looks at every row again, in order, and c's first gets its (empty) matches."""
    svc = MergeService(ServiceConfig(fleet="lane", store=":memory:", large_submap_objects=20))
    try:
        lane = svc.lane
        big = moved(scene60(), "c")
        small_c = part(big).model_copy(update={"seq": 1})
        small_b = part(moved(scene60(), "b"))
        rows = [1, 2, 3]
        assert lane.pending(lambda k: rows[:k], 64) == rows
        assert lane.defers(1, big, payload(big))
        assert wait_for(lambda: lane.finished == 1, 20.0)
        assert not lane.defers(2, small_b, payload(small_b))
        assert lane.defers(3, small_c, payload(small_c))
        assert lane.pending(lambda k: rows[:k], 64) == rows
        assert not lane.defers(1, big, payload(big))
        got = lane.pop(1)
        assert got is not None and got[0].others == [] and got[1] == []
        assert lane.pop(1) == got  # kept: a commit that failed plans it again with them
        assert not lane.defers(3, small_c, payload(small_c))
    finally:
        svc.close()


def test_a_killed_child_starts_no_other() -> None:
    """`kill` (the service closing) stops the child for good: a job that comes after it fails
    at once instead of starting a child that close would wait for."""
    child = ProcessOptimizer()
    child.kill()
    with pytest.raises(SolverError, match="stopped for good"):
        child(MatchJob([], ServiceConfig().match))
    assert child.starts == 0
