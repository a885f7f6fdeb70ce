"""The merge service after faults (issue 25's findings), one test each, with real parts: a real
Store on tmp_path (its faults real SQLite errors where SQLite can make them: a page limit is a
full disk, a temporary trigger fails a transaction half way), real GTSAM, and the in-process
transport (fleet/transport.py) where the network is not the point."""

from __future__ import annotations

import json
import logging
import os
import shutil
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers import wait_for
from test_service_limits import make_submap, moved, payload

import mergesvc.fleet.service as service_module
from mergesvc.core.model import Factor, FactorStatus, ObjectNode, Odometry, Submap
from mergesvc.errors import SolverError, StoreError
from mergesvc.fleet.config import ConsistencyConfig, ServiceConfig
from mergesvc.fleet.queries import StoreFigures
from mergesvc.fleet.replies import SubmapResult
from mergesvc.fleet.service import MergeService
from mergesvc.fleet.transport import InProcessTransport
from mergesvc.store import CONFLICTS_KEPT, Store
from mergesvc.wire import decode_message, keys

FLEET = "faults"
ROOT = keys.fleet_root(FLEET)


class Fleet:
    """A service on an in-process transport, with what it sends: results, factors (key,
    Factor) and refusals."""

    def __init__(self, cfg: ServiceConfig, **kw: Any) -> None:
        self.t = InProcessTransport()
        self.results: list[SubmapResult] = []
        self.factors: list[tuple[str, Factor]] = []
        self.t.subscribe(keys.all_results(ROOT), lambda s: self.results.append(
            SubmapResult.model_validate_json(s.payload)))
        self.t.subscribe(keys.all_factors(ROOT), lambda s: self.factors.append(
            (s.key, decode_message(s.payload)[1])))
        self.svc = MergeService(cfg, self.t, **kw)

    def put(self, sub: Submap, data: bytes | None = None) -> None:
        self.t.put(keys.submap_key(ROOT, sub.robot_id, sub.session_id),
                   payload(sub) if data is None else data)

    def of(self, robot: str) -> list[SubmapResult]:
        return [r for r in list(self.results) if r.robot == robot]

    def factor_ids(self, status: FactorStatus = FactorStatus.ACCEPTED) -> set[str]:
        return {f.factor_id for _, f in list(self.factors) if f.status == status}

    def __enter__(self) -> Fleet:
        self.svc.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.svc.close()


def cfg_at(path: Path, **kw: Any) -> ServiceConfig:
    return ServiceConfig(fleet=FLEET, store=str(path), **kw)


def scene(robot: str = "a", seed: int = 1) -> Submap:
    """Eight objects: another robot's `moved` copy of them is a verified match."""
    return make_submap(robot, "s0", 0, n=8, seed=seed)


def outcomes(results: list[SubmapResult]) -> list[str]:
    return [r.outcome.value + ("" if r.code is None else f"/{r.code.value}") for r in results]


def disk_full(store: Store, full: bool) -> None:
    """A full disk, as SQLite sees it: no page beyond those the file has (SQLITE_FULL,
    'database or disk is full', on every write that needs one); `full=False` frees it."""
    with store._lock:
        assert store._conn is not None
        store._conn.execute(f"PRAGMA max_page_count={1 if full else 1_073_741_823}")


@pytest.fixture
def fast_backoff(monkeypatch: pytest.MonkeyPatch) -> None:
    """Store and solve retries after 0.2 s at most (the test waits for them)."""
    monkeypatch.setattr(service_module, "STORE_BACKOFF_MAX_S", 0.2)
    monkeypatch.setattr(service_module, "SOLVE_BACKOFF_MAX_S", 0.2)


# -- the merger on the in-process transport ----------------------------------------------------


def test_the_merger_runs_on_the_in_process_transport_without_zenoh(tmp_path: Path) -> None:
    """Two robots' overlapping submaps in through the in-process transport: the factor goes
    out to both robots through it, each submap gets its result; no Zenoh session exists."""
    with Fleet(cfg_at(tmp_path / "m.db")) as fl:
        assert type(fl.svc.transport) is InProcessTransport
        a = scene()
        fl.put(a)
        fl.put(moved(a, "b"))
        assert wait_for(lambda: len(fl.results) == 2, 20.0)
        assert wait_for(lambda: len(fl.factors) == 2, 5.0)
    (fid,) = fl.factor_ids()
    assert sorted(k for k, _ in fl.factors) == sorted(keys.factor_key(ROOT, r, fid)
                                                      for r in ("a", "b"))
    assert outcomes(fl.of("a")) == ["no_match"] and outcomes(fl.of("b")) == ["processed"]
    assert fl.of("b")[0].factors == [fid]


# -- 1. retractions found on restart are published ---------------------------------------------


def test_retractions_found_by_the_restart_solve_are_published(tmp_path: Path) -> None:
    """A service that published three factors between a and b (two agree, one is 1 rad off:
    every factor trusted at once, the consistency test off) is killed before its solve. The
    restart's solve (settle) rejects the wrong one: it is retracted in the store AND the
    retraction is sent to both robots (it used to be retracted silently: the vehicles kept a
    wrong loop closure for good)."""
    cfg = cfg_at(tmp_path / "r.db", consistency=ConsistencyConfig(enabled=False))
    first = Fleet(cfg)
    a = scene()
    for sub in (a, moved(a, "b"), moved(a, "b").model_copy(update={"seq": 1}),
                moved(a, "b", yaw=1.5).model_copy(update={"seq": 2})):
        first.svc.ingest(sub, optimize=False)
    sent = first.factor_ids()
    (wrong,) = first.of("b")[2].factors  # seq 2's
    first.svc.store.close()  # killed: no solve, no orderly close
    assert len(sent) == 3 and not first.factor_ids(FactorStatus.RETRACTED)

    with Fleet(cfg) as again:
        retracted = again.factor_ids(FactorStatus.RETRACTED)  # restore() ran in start()
        stored = {f.factor_id: f.status for f in again.svc.store.factors()}
    assert retracted == {wrong}
    assert sorted(k for k, f in again.factors if f.status == FactorStatus.RETRACTED) == sorted(
        keys.factor_key(ROOT, r, wrong) for r in ("a", "b"))
    assert stored[wrong] == FactorStatus.RETRACTED
    assert [s for fid, s in stored.items() if fid != wrong] == [FactorStatus.ACCEPTED] * 2


def test_answers_a_crash_left_unsent_are_published_by_the_restart(tmp_path: Path,
                                                                  monkeypatch) -> None:
    """Killed between a unit's commit and its publishing: the row is final and its factor
    stored, nothing went out. The restart publishes that submap's result and factor (once;
    a later restart publishes nothing again); the units that went out are not repeated."""
    cfg = cfg_at(tmp_path / "u.db")
    a = scene()
    first = Fleet(cfg)
    first.svc.ingest(a)  # published and marked answered
    assert outcomes(first.of("a")) == ["no_match"]
    monkeypatch.setattr(first.svc, "_answer", lambda uow: None)  # the kill, right after commit
    first.svc.ingest(moved(a, "b"))
    assert first.of("b") == [] and first.factors == []
    stored = [f.factor_id for f in first.svc.store.factors()]
    first.svc.store.close()
    assert len(stored) == 1

    with Fleet(cfg) as again:
        assert wait_for(lambda: len(again.of("b")) == 1)
        assert again.of("a") == []  # answered before the kill: not repeated
        (res,) = again.of("b")
        assert res.outcome.value == "processed" and res.factors == stored
        assert again.factor_ids() == set(stored)
        assert sorted(k for k, _ in again.factors) == sorted(
            keys.factor_key(ROOT, r, stored[0]) for r in ("a", "b"))
    with Fleet(cfg) as third:
        assert third.results == [] and third.factors == []


# -- 3. one unit of work per submap --------------------------------------------------------------


def near_singular_odometry() -> Odometry:
    """An odometry the wire model takes (Cholesky of its lower triangle) but the pose graph
    refuses (it symmetrises first): relative asymmetry 6e-10, near singular."""
    C = np.eye(6) * 1e-2
    C[5, 4], C[4, 5], C[5, 5] = 1e-2, 1e-2 * (1 + 6e-10), 1e-2 * (1 + 1e-10)
    assert np.abs(C - C.T).max() <= 1e-9 * np.abs(C).max()
    np.linalg.cholesky(C)  # what the model checks: passes
    with pytest.raises(np.linalg.LinAlgError):
        np.linalg.cholesky(0.5 * (C + C.T))
    return Odometry(from_keyframe=0, T_from_to={"translation": [1.0, 0.0, 0.0],
                                                "quaternion_wxyz": [1.0, 0.0, 0.0, 0.0]},
                    covariance=C.tolist())


def test_a_covariance_the_graph_refuses_is_refused_before_any_side_effect(
        tmp_path: Path) -> None:
    """b's submap matches a's but carries that odometry. Sent now, it is refused at the
    boundary (bad_submap, nothing stored). Stored before (an older service took it), the
    worker refuses it before any side effect: one final result (failed), no factor stored,
    held or published, nothing of it in the graph. It used to be stored with its factors as
    accepted, which were never held or published (and held again after a restart)."""
    a = scene()
    bad = moved(a, "b").model_copy(update={"keyframe": 1, "odometry": near_singular_odometry()})
    path = tmp_path / "u.db"
    with Store(path) as db:  # what an older service stored
        db.put_submap("a", "s0", 0, payload(a), 1.0)
        db.put_submap("b", "s0", 0, payload(bad), 2.0)
    with Fleet(cfg_at(path)) as fl:
        assert wait_for(lambda: len(fl.results) == 2, 20.0)
        fl.put(bad.model_copy(update={"seq": 1}))  # sent now: refused at the boundary
        assert wait_for(lambda: len(fl.results) == 3, 10.0)
        assert not fl.factors and not fl.svc.factors and not fl.svc.merger.held
        assert not any(n.startswith("b/") for n in fl.svc.graph.nodes)
        rows = {(r.robot_id, r.seq): r.status for r in fl.svc.store.submaps()}
        assert not fl.svc.store.factors() and not fl.svc.store.held_factors()
    assert outcomes(fl.of("b")) == ["failed/processing", "refused/bad_submap"]
    assert "positive definite" in fl.of("b")[0].detail
    assert rows == {("a", 0): "no_match", ("b", 0): "failed"}  # seq 1 never stored
    with Fleet(cfg_at(path)) as fl:  # a restart holds nothing of it either
        assert not fl.svc.factors and not fl.svc.merger.held and not fl.results


def test_a_commit_failing_half_way_leaves_no_half_state(tmp_path: Path, fast_backoff) -> None:
    """b's unit of work fails inside its transaction, after its row's status was updated,
    at the factor's insert (a temporary trigger raises: a real SQLite error). Nothing is
    final: the row is pending, no factor stored, held, in the graph or published; b is told
    `store` once (retry: not final) however often the worker tries. Once the store writes
    again the same unit commits: one final result, one factor, once."""
    with Fleet(cfg_at(tmp_path / "h.db")) as fl:
        a = scene()
        fl.put(a)
        assert wait_for(lambda: len(fl.results) == 1, 20.0)
        store = fl.svc.store
        with store._lock:
            store._conn.execute("CREATE TEMP TRIGGER fault BEFORE INSERT ON factors BEGIN "
                                "SELECT RAISE(ABORT, 'disk I/O error'); END")
        fl.put(moved(a, "b"))
        assert wait_for(lambda: fl.svc.stats.errors.get("store", 0) >= 2, 20.0)
        with fl.svc._lock:
            assert not fl.svc.factors and not fl.svc.merger.held
            assert not fl.svc.graph.factor_ids
        assert {(r.robot_id, r.status) for r in store.submaps()} == {
            ("a", "no_match"), ("b", "pending")}
        assert not store.factors() and not store.held_factors()
        assert not fl.factors and outcomes(fl.of("b")) == ["refused/store"]
        with store._lock:
            store._conn.execute("DROP TRIGGER fault")
        assert wait_for(lambda: len(fl.of("b")) == 2, 20.0)
        assert wait_for(lambda: len(fl.factors) == 2, 5.0)
        (fid,) = fl.factor_ids()
        assert [f.factor_id for f in store.factors("accepted")] == [fid]
        assert set(fl.svc.factors) == {fid}
    assert outcomes(fl.of("b")) == ["refused/store", "processed"]


# -- 6. a flood of conflicting replays ------------------------------------------------------------


def test_a_conflict_flood_is_rate_limited_bounded_and_leaves_others_alone(
        tmp_path: Path) -> None:
    """60 byte-variants of x's stored seq 0: each takes a token from x's bucket (burst 10):
    the first 9 are answered `conflict` (final), the other 51 `rate_limited`; the store keeps
    CONFLICTS_KEPT hashes, no payload; y's submaps after the flood are processed."""
    cfg = cfg_at(tmp_path / "c.db", submap_rate_hz=0.001, submap_burst=10)
    with Fleet(cfg) as fl:
        x = scene("x")
        fl.put(x)
        for i in range(60):
            variant = x.model_copy(update={"objects": [
                o.model_copy(update={"position": (o.position[0] + 0.01 * (i + 1),
                                                  *o.position[1:])}) for o in x.objects]})
            fl.put(variant)
        y = moved(x, "y")
        fl.put(y)
        fl.put(make_submap("y", "s0", 1, n=8, seed=9))
        assert wait_for(lambda: len(fl.of("y")) == 2, 30.0)
        assert wait_for(lambda: len(fl.of("x")) == 61, 10.0)
        conflicts = fl.svc.store.submap_conflicts()
        stored = fl.svc.store.stats()
    got = outcomes(fl.of("x"))  # (the refusals may come before the worker's result)
    assert sorted(set(got)) == ["no_match", "refused/conflict", "refused/rate_limited"]
    assert (got.count("no_match"), got.count("refused/conflict"),
            got.count("refused/rate_limited")) == (1, 9, 51)
    assert len(conflicts) == CONFLICTS_KEPT
    assert stored["rows"]["submaps"] == 3  # x's first bytes and y's two: no variant's
    assert stored["page_bytes"] < 10 * len(payload(x))  # 60 variants' bytes would not fit
    assert outcomes(fl.of("y"))[0] == "processed"


# -- 7. disk full --------------------------------------------------------------------------------


def test_a_full_disk_gives_a_retryable_answer_and_one_result_once_it_has_room(
        tmp_path: Path, fast_backoff) -> None:
    """a and b stored (b matches a), then the disk fills before they are processed. The
    worker cannot commit: nothing is marked final; a (the oldest row, the one it retries) is
    told `store` (not final) once.
    c, sent meanwhile, cannot be stored: `store` (retry). With room again: a and b get exactly
    one final result each (never failed then processed), and c sent again is processed; a
    restart answers nothing again."""
    path = tmp_path / "d.db"
    fl = Fleet(cfg_at(path))
    a = scene()
    fl.svc.store.put_submap("a", "s0", 0, payload(a), 1.0)
    fl.svc.store.put_submap("b", "s0", 0, payload(moved(a, "b")), 2.0)
    disk_full(fl.svc.store, True)
    with fl:
        assert wait_for(lambda: fl.svc.stats.errors.get("store", 0) >= 2, 20.0)
        fl.put(moved(a, "c"))
        assert wait_for(lambda: len(fl.of("c")) == 1, 10.0)
        assert wait_for(lambda: fl.svc.stats.errors.get("store", 0) >= 5, 20.0)
        assert outcomes(fl.of("a")) == ["refused/store"] and not fl.of("b")
        assert not fl.factors
        assert {r.status for r in fl.svc.store.submaps()} == {"pending"}
        assert len(fl.svc.store.submaps()) == 2
        disk_full(fl.svc.store, False)
        assert wait_for(lambda: len(fl.of("a")) == 2 and len(fl.of("b")) == 1, 20.0)
        fl.put(moved(a, "c"))  # the robot retries after `store`
        assert wait_for(lambda: len(fl.of("c")) == 2, 20.0)
    assert outcomes(fl.of("a")) == ["refused/store", "no_match"]
    assert outcomes(fl.of("b")) == ["processed"]
    assert outcomes(fl.of("c")) == ["refused/store", "processed"]
    assert "database or disk is full" in fl.of("c")[0].detail
    with Fleet(cfg_at(path)) as again:
        assert again.svc.store.final_seqs() == {("a", "s0"): 0, ("b", "s0"): 0, ("c", "s0"): 0}
        again.svc._wake.set()
        assert not wait_for(lambda: bool(again.results), 1.0)


# -- 9. damage found at start ----------------------------------------------------------------------


def test_a_truncated_wal_is_reported_at_start(tmp_path: Path, caplog) -> None:
    """Four submaps of a answered; the machine dies (the store and its WAL copied as they
    are) and the WAL is cut back to the second commit: SQLite opens it without a word and
    seqs 2 and 3 are gone. The restart says so: a loud log line and status store_damage
    naming the session and the seqs."""
    live = tmp_path / "live"
    live.mkdir()
    svc = MergeService(ServiceConfig(fleet=FLEET, store=str(live / "w.db")))
    wal = live / "w.db-wal"
    sizes = []
    for seq in range(4):
        svc.ingest(make_submap("a", "s0", seq, n=4), optimize=False)
        sizes.append(wal.stat().st_size)
    crashed = tmp_path / "crashed"
    crashed.mkdir()
    for name in ("w.db", "w.db-wal", "w.db.acks"):  # what the disk holds at the crash
        shutil.copy(live / name, crashed / name)
    svc.close()
    assert sizes[1] < sizes[3]
    os.truncate(crashed / "w.db-wal", sizes[1])
    with Store(crashed / "w.db") as db:  # SQLite: fine, two rows
        assert [r.seq for r in db.submaps()] == [0, 1]
    caplog.set_level(logging.ERROR, logger="mergesvc.fleet.service")
    with MergeService(ServiceConfig(fleet=FLEET, store=str(crashed / "w.db"))) as again:
        damage = again.status(poses=False)["store_damage"]
    assert len(damage) == 1 and "a/s0" in damage[0] and "2-3" in damage[0]
    assert any("lost" in r.getMessage() and "2-3" in r.getMessage() for r in caplog.records
               if r.levelno >= logging.ERROR)


# -- 10. queries never wait on a solve -------------------------------------------------------------


def test_queries_answer_during_a_solve_and_a_failed_solve_is_retried_and_flagged(
        tmp_path: Path, fast_backoff) -> None:
    """The graph's solve blocked (on an Event): status, the global map and a relocalize query
    answer meanwhile. Then the solve raises twice: status flags it (not ok, the error, how many
    failures, the age of the solution it serves) and the worker tries again until it solves."""
    with Fleet(cfg_at(tmp_path / "q.db")) as fl:
        a = scene()
        fl.put(a)
        fl.put(moved(a, "b"))
        assert wait_for(lambda: len(fl.results) == 2 and fl.svc.solution is not None, 20.0)
        graph = fl.svc.graph
        real = graph.optimize
        entered, release = threading.Event(), threading.Event()
        fails = [2]

        def blocking(*args: Any, **kw: Any) -> Any:
            entered.set()
            assert release.wait(30.0)
            if fails[0]:
                fails[0] -= 1
                raise SolverError("GTSAM: indeterminant linear system (injected)")
            return real(*args, **kw)

        graph.optimize = blocking  # (an instance attribute: this graph only)
        try:
            fl.put(moved(a, "c"))  # changes the graph: the worker solves
            assert entered.wait(20.0)
            answers: dict[str, Any] = {}

            def ask() -> None:
                answers["status"] = fl.svc.status()
                answers["map"] = fl.svc.global_map()
                answers["relocalize"] = fl.t.get(keys.relocalize_key(ROOT),
                                                 payload=payload(moved(a, "d")))

            th = threading.Thread(target=ask)
            th.start()
            th.join(20.0)  # generous: a query that waited on the solve would never return
            assert not th.is_alive(), "a query waited on the blocked solve"
            assert answers["map"][0] is not None and answers["relocalize"][0].ok
            release.set()
            assert wait_for(lambda: fl.svc.status(poses=False)["solve"]["failures"] >= 1, 10.0)
            flagged = fl.svc.status(poses=False)["solve"]
            assert wait_for(lambda: fl.svc.status(poses=False)["solve"]["ok"], 20.0)
            assert fails == [0] and not fl.svc._dirty
        finally:
            release.set()
            del graph.optimize
    assert answers["status"]["submaps"]["processed"] >= 2
    assert not flagged["ok"] and "indeterminant" in flagged["error"]
    assert flagged["solution_age_s"] is not None and flagged["solution_age_s"] >= 0.0


def test_a_status_query_does_no_io_and_its_store_figures_follow_the_store(
        tmp_path: Path) -> None:
    """A status query through the transport reads no store figure itself (each read released
    the GIL several times: 100-500 ms under load): it answers with those a thread of their own
    reads every status_refresh_s, and says how old they are; without poses it does not even
    build the reply (the same thread builds it after each read). They follow the store: a new
    submap shows within a few refreshes. In-process status() reads them exact."""
    with Fleet(cfg_at(tmp_path / "st.db", status_refresh_s=0.05)) as fl:
        a = scene()
        fl.put(a)
        assert wait_for(lambda: len(fl.results) == 1, 20.0)
        store, reads = fl.svc.store, []
        real_counts, real_stats, real_figures = store.counts, store.stats, store.figures
        asking = threading.local()

        def counted(real: Any) -> Any:
            def read(*a: Any, **k: Any) -> Any:
                if getattr(asking, "now", False):
                    reads.append(real.__name__)
                return real(*a, **k)
            return read

        store.counts, store.stats = counted(real_counts), counted(real_stats)
        store.figures = counted(real_figures)  # type: ignore[method-assign]
        real_status = fl.svc.status
        fl.svc.status = counted(real_status)  # type: ignore[method-assign]

        def status() -> dict[str, Any]:
            asking.now = True
            try:
                (reply,) = fl.t.get(keys.status_key(ROOT), {"poses": "false"})
            finally:
                asking.now = False
            assert reply.ok
            return json.loads(reply.payload)

        try:
            first = status()
            fl.put(moved(a, "b"))
            assert wait_for(lambda: len(fl.results) == 2, 20.0)
            assert wait_for(lambda: sum(status()["submaps"]["stored"].values()) == 2, 10.0)

            def poses() -> dict[str, Any]:  # built on demand, not the cached reply
                return json.loads(fl.t.get(keys.status_key(ROOT), {})[0].payload)["frame_poses"]

            assert wait_for(lambda: "b/s0" in poses(), 10.0)
        finally:
            del store.counts, store.stats, store.figures, fl.svc.status
        assert reads == []  # not one store read nor status build on the query's path
        assert sum(first["submaps"]["stored"].values()) == 1
        assert 0.0 <= first["store"]["age_s"] < 10.0
        assert fl.svc.status(poses=False)["store"]["age_s"] < 1.0  # in-process: read now
        assert fl.svc.status(poses=False)["store"]["rows"]["submaps"] == 2


def test_the_figures_thread_outlives_a_failed_read(tmp_path: Path,
                                                   caplog: pytest.LogCaptureFixture) -> None:
    """A read of the store's figures that fails (an I/O error, any exception) is logged once
    and the thread goes on: the next reads replace the figures it kept."""
    with Store(tmp_path / "fig.db") as store:
        figures = StoreFigures(store, 0.01)
        real, fails = store.figures, [OSError("injected I/O error"), StoreError("injected")]

        def flaky() -> Any:
            if fails:
                raise fails.pop(0)
            return real()

        store.figures = flaky  # type: ignore[method-assign]
        with caplog.at_level(logging.DEBUG, logger="mergesvc.fleet.queries"):
            figures.start()
            try:
                assert wait_for(lambda: not fails and figures._last is not None, 10.0)
                before = figures.get(fresh=False)[0]["submaps_pending"]
                store.put_submap("r", "s", 0, b"x" * 10, 0.0)
                assert wait_for(lambda: figures.get(fresh=False)[0]["submaps_pending"] == 1,
                                10.0)
            finally:
                figures.stop()
    assert before == 0
    assert [r.levelname for r in caplog.records if "not read" in r.message] == [
        "WARNING", "DEBUG"]


def test_the_prebuilt_status_reply_is_built_after_each_read_and_dropped_when_stale(
        tmp_path: Path) -> None:
    """The figures' thread builds the reply after each read; once it has stopped building (a
    stalled thread), the reply is dropped after two periods, so a query builds its own and
    its ages tell the truth."""
    with Store(tmp_path / "rep.db") as store:
        builds: list[int] = []

        def build() -> bytes:
            builds.append(1)
            return b"reply %d" % len(builds)

        figures = StoreFigures(store, 0.05, build)
        figures.start()
        try:
            assert wait_for(lambda: len(builds) >= 3, 10.0)
            assert figures.reply is not None and figures.reply.startswith(b"reply ")
        finally:
            figures.stop()
        assert wait_for(lambda: figures.reply is None, 10.0, step_s=0.02)


# -- 11. bounded state and a stable anchor -----------------------------------------------------


def test_per_robot_state_is_pruned_once_robots_go_idle(tmp_path: Path) -> None:
    """Ten robots send one submap each; session_idle_s later (the service's clock, injected)
    one more robot sends: the ten robots' open sessions and token buckets are gone."""
    now = [1000.0]
    cfg = cfg_at(tmp_path / "p.db", session_idle_s=60.0)
    with Fleet(cfg, clock=lambda: now[0]) as fl:
        for i in range(10):
            fl.put(make_submap(f"r{i}", "s0", 0, n=4, seed=i))
        assert wait_for(lambda: len(fl.results) == 10, 30.0)
        assert fl.svc.ingress.state_size() == (10, 10)
        now[0] += 61.0
        fl.put(make_submap("late", "s0", 0, n=4, seed=99))
        assert wait_for(lambda: len(fl.results) == 11, 20.0)
        assert fl.svc.ingress.state_size() == (1, 1)


def test_the_anchor_is_the_same_after_a_restart(tmp_path: Path) -> None:
    """b's submap is the first stored (frames[0]) but fails (its odometry is refused); a's is
    the first processed: a is the anchor, and stays the anchor after a restart."""
    path = tmp_path / "n.db"
    a = scene()
    bad = moved(a, "b").model_copy(update={"keyframe": 1, "odometry": near_singular_odometry()})
    with Store(path) as db:
        db.put_submap("b", "s0", 0, payload(bad), 1.0)
        db.put_submap("a", "s0", 0, payload(a), 2.0)
        assert db.frames()[0].frame == "b/s0"
    with Fleet(cfg_at(path)) as fl:
        assert wait_for(lambda: len(fl.results) == 2, 20.0)
        fl.put(moved(a, "c"))
        assert wait_for(lambda: len(fl.results) == 3, 20.0)
        first = fl.svc.anchor
        stored = fl.svc.store.meta("anchor")
    assert first == stored == "a/s0"
    with Fleet(cfg_at(path)) as fl:
        assert fl.svc.anchor == "a/s0"
        assert fl.svc.graph.anchor.startswith("a/s0")


# -- several embedding models in one fleet ---------------------------------------------------------


def widened(sub: Submap, robot: str, dim: int = 768) -> Submap:
    """The same scene seen by a robot running a `dim`-d model: each embedding padded with a
    fixed random projection of itself (unit length again), object ids renamed."""
    rng = np.random.default_rng(768)
    P = rng.normal(size=(dim - sub.dim, sub.dim)) / np.sqrt(sub.dim)
    objs = []
    for i, o in enumerate(sub.objects):
        e = np.asarray(o.embedding, dtype=np.float64)
        w = np.concatenate([e, P @ e])
        objs.append(ObjectNode(id=f"{robot}-w{i}", position=o.position,
                               embedding=[float(v) for v in w / np.linalg.norm(w)],
                               variance=o.variance, n_obs=o.n_obs))
    return sub.model_copy(update={"robot_id": robot, "objects": objs})


@pytest.mark.parametrize("first", [384, 768])
def test_a_384_and_a_768_model_share_a_fleet_either_first(tmp_path: Path, first: int) -> None:
    """AUVs with a 384-d detector (a1, a2) and cars with a 768-d one (c1, c2) over the same
    scene, either model first: every submap is processed, each model's robots get factors
    between them and none across models; status counts sessions per model."""
    a1 = scene("a1")
    by_model = {384: [a1, moved(a1, "a2")],
                768: [widened(a1, "c1"), moved(widened(a1, "c1"), "c2")]}
    with Fleet(cfg_at(tmp_path / f"x{first}.db")) as fl:
        for dim in (first, 384 + 768 - first):
            for sub in by_model[dim]:
                fl.put(sub)
        assert wait_for(lambda: len(fl.results) == 4, 30.0)
        assert wait_for(lambda: len(fl.factor_ids()) == 2, 5.0)
        models = fl.svc.status(poses=False)["models"]
    got = {r.robot: r.outcome.value for r in fl.results}
    assert got == {"a1": "no_match", "a2": "processed", "c1": "no_match", "c2": "processed"}
    pairs = {tuple(sorted((f.robot_a, f.robot_b))) for _, f in fl.factors}
    assert pairs == {("a1", "a2"), ("c1", "c2")}
    assert {k: v["sessions"] for k, v in models.items()} == {"384": 2, "768": 2}
