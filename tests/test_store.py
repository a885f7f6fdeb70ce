"""Tests of mergesvc.store: SQLite (WAL) persistence of submaps, factors and frames, including
a real kill -9 of a writing process."""

from __future__ import annotations

import hashlib
import os
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from mergesvc.core.model import FactorStatus
from mergesvc.errors import InputError, StoreError
from mergesvc.store import (
    PENDING,
    STORE_SCHEMA_VERSION,
    Store,
    SubmapConflictError,
    Synchronous,
)

REPO = Path(__file__).resolve().parents[1]


def payload(seq: int, size: int = 2000) -> bytes:
    return (f"submap {seq};".encode() * size)[:size]


@pytest.fixture
def store() -> Store:
    with Store(":memory:") as s:
        yield s


# --------------------------------------------------------------------------------------------
# Submaps
# --------------------------------------------------------------------------------------------


def test_submap_round_trip(store: Store) -> None:
    row, created = store.put_submap("auv1", "s1", 0, payload(0), 12.5)
    assert created
    (got,) = store.submaps()
    assert got.row_id == row
    assert (got.robot_id, got.session_id, got.seq, got.frame) == ("auv1", "s1", 0, "auv1/s1")
    assert got.payload == payload(0)
    assert got.received_at_s == 12.5
    assert got.status == PENDING and not got.processed and got.processed_at_s is None
    assert store.submap(row) == got
    assert [f.frame for f in store.frames()] == ["auv1/s1"]


def test_identical_replay_creates_nothing(store: Store) -> None:
    row, created = store.put_submap("auv1", "s1", 3, payload(3), 1.0)
    again, created_again = store.put_submap("auv1", "s1", 3, payload(3), 2.0)
    assert created and not created_again and again == row
    assert len(store.submaps()) == 1
    # Another session or robot with the same seq is another submap.
    assert store.put_submap("auv1", "s2", 3, payload(3), 1.0)[1]
    assert store.put_submap("auv2", "s1", 3, payload(3), 1.0)[1]
    assert len(store.submaps()) == 3


def test_conflicting_replay_raises_and_keeps_both(store: Store) -> None:
    store.put_submap("auv1", "s1", 0, payload(0), 1.0)
    with pytest.raises(SubmapConflictError, match=r"auv1/s1#0 .*different content"):
        store.put_submap("auv1", "s1", 0, b"other bytes", 2.0)
    assert issubclass(SubmapConflictError, StoreError)
    assert store.submaps()[0].payload == payload(0)  # the first write wins
    digest = hashlib.sha256(b"other bytes").hexdigest()
    assert store.submap_conflicts() == [("auv1", "s1", 0, digest, 2.0)]  # its hash only
    assert store.counts()["submap_conflicts"] == 1


def test_a_flood_of_conflicting_variants_keeps_a_few_hashes(store: Store) -> None:
    """700 byte-variants of one key: each refused, at most CONFLICTS_KEPT on record, none of
    their bytes kept (the store does not grow with the flood)."""
    from mergesvc.store import CONFLICTS_KEPT

    store.put_submap("auv1", "s1", 0, payload(0), 1.0)
    size = sum(len(p.payload) for p in store.submaps())
    for i in range(700):
        with pytest.raises(SubmapConflictError):
            store.put_submap("auv1", "s1", 0, payload(0) + i.to_bytes(2, "big"), 2.0)
    assert len(store.submap_conflicts()) == CONFLICTS_KEPT
    assert store.stats()["rows"]["submap_conflicts"] == CONFLICTS_KEPT
    assert sum(len(p.payload) for p in store.submaps()) == size


def test_processing_state_and_arrival_order(store: Store) -> None:
    rows = [store.put_submap("r", "s", seq, payload(seq), float(seq))[0] for seq in (5, 1, 3)]
    store.mark_processed(rows[1], "matched", "3 matches")
    pending = store.unprocessed_submaps()
    assert [s.seq for s in pending] == [5, 3]  # arrival order, not seq order
    done = store.submap(rows[1])
    assert done.status == "matched" and done.detail == "3 matches" and done.processed
    store.mark_processed(rows[1], "matched", "3 matches")  # replaying the outcome is harmless
    assert [s.seq for s in store.submaps(status="matched")] == [1]
    with pytest.raises(InputError):
        store.mark_processed(rows[0], PENDING)
    with pytest.raises(StoreError, match="no submap"):
        store.mark_processed(999, "matched")
    counts = store.counts()
    assert counts["submaps"] == {"pending": 2, "matched": 1}
    assert counts["submaps_pending"] == 2


def test_submap_filters(store: Store) -> None:
    for robot, session, seq in [("a", "1", 0), ("a", "2", 0), ("b", "1", 0), ("a", "1", 1)]:
        store.put_submap(robot, session, seq, payload(seq), 0.0)
    assert [(s.session_id, s.seq) for s in store.submaps(robot_id="a")] == [
        ("1", 0),
        ("2", 0),
        ("1", 1),
    ]
    assert len(store.submaps(robot_id="a", session_id="1")) == 2
    assert len(store.submaps(session_id="1")) == 3


def test_input_checks(store: Store) -> None:
    with pytest.raises(InputError):
        store.put_submap("r", "s", -1, b"x", 0.0)
    with pytest.raises(InputError):
        store.put_submap("r", "s", 0, "not bytes", 0.0)  # type: ignore[arg-type]
    with pytest.raises(InputError):
        store.put_submap("", "s", 0, b"x", 0.0)
    with pytest.raises(InputError):
        store.put_submap("r", "s", 0, b"x", float("nan"))
    assert store.submaps() == []


def test_unprocessed_submaps_survive_reopen(tmp_path: Path) -> None:
    path = tmp_path / "merge.db"
    with Store(path) as s:
        rows = [s.put_submap("r", "s", seq, payload(seq), float(seq))[0] for seq in range(4)]
        s.mark_processed(rows[0], "matched")
        s.put_factor("f1", "r/s", "q/s", b"factor")
    with Store(path) as s:
        assert [x.seq for x in s.unprocessed_submaps()] == [1, 2, 3]
        assert s.submap(rows[0]).status == "matched"
        assert [f.factor_id for f in s.factors()] == ["f1"]
        # A replay after the restart is recognised.
        assert s.put_submap("r", "s", 2, payload(2), 9.0) == (rows[2], False)


# --------------------------------------------------------------------------------------------
# Factors and frames
# --------------------------------------------------------------------------------------------


def test_factors(store: Store) -> None:
    assert store.put_factor("f1", "a/1", "b/1", b"one")
    assert not store.put_factor("f1", "a/1", "b/1", b"one")
    assert not store.put_factor("f1", "a/1", "b/1", b"changed")  # first write wins
    assert store.put_factor("f2", "a/1", "c/1", b"two", status="retracted")
    assert [f.factor_id for f in store.factors()] == ["f1", "f2"]
    assert store.factors()[0].payload == b"one"
    assert store.set_factor_status("f1", FactorStatus.RETRACTED)
    assert not store.set_factor_status("f1", "retracted")
    assert [f.factor_id for f in store.factors(status="retracted")] == ["f1", "f2"]
    assert store.factors(FactorStatus.ACCEPTED) == []
    assert store.set_factor_status("f2", "accepted")
    assert store.counts()["factors"] == {"accepted": 1, "retracted": 1}
    with pytest.raises(InputError):
        store.set_factor_status("f1", "maybe")
    with pytest.raises(StoreError, match="no factor"):
        store.set_factor_status("nope", "accepted")


def test_frames_track_first_and_last_seen() -> None:
    clock = iter(range(100)).__next__
    with Store(":memory:", clock=lambda: float(clock())) as store:
        store.put_submap("r", "s", 0, b"x", 10.0)
        store.put_submap("r", "s", 1, b"y", 30.0)
        assert store.put_frame("q", "s", 5.0)
        assert not store.put_frame("r", "s", 20.0)
        frames = store.frames()
        assert [(f.frame, f.first_seen_s, f.last_seen_s) for f in frames] == [
            ("r/s", 10.0, 30.0),
            ("q/s", 5.0, 5.0),
        ]


def test_stats(tmp_path: Path) -> None:
    path = tmp_path / "merge.db"
    with Store(path) as s:
        for seq in range(3):
            s.put_submap("r", "s", seq, payload(seq, 5000), 0.0)
        s.put_factor("f", "r/s", "q/s", b"z")
        st = s.stats()
        assert st["rows"] == {
            "schema_version": 1,
            "submaps": 3,
            "submap_conflicts": 0,
            "factors": 1,
            "frames": 1,
            "meta": 0,
            "held_factors": 0,
            "unanswered": 0,
        }
        assert st["journal_mode"] == "wal"
        assert st["synchronous"] == "FULL"
        assert st["schema_version"] == STORE_SCHEMA_VERSION
        assert st["wal_bytes"] > 15000  # the commits are in the WAL until a checkpoint
        assert st["page_bytes"] > 15000
    with Store(path) as s:  # close checkpointed the WAL into the main file
        assert s.stats()["file_bytes"] > 15000
    assert Store(":memory:").stats()["file_bytes"] == 0


@pytest.mark.parametrize("name", ["merge.db", "a b#%?.db"])
def test_status_figures_never_wait_for_a_write(tmp_path: Path, name: str) -> None:
    """counts() and stats() read the last commit through their own connection while another
    thread holds the store's write transaction (a commit's fsync: the status query's p99)."""
    with Store(tmp_path / name) as s:
        s.put_submap("r", "s", 0, payload(0, 100), 0.0)
        held, release = threading.Event(), threading.Event()

        def writer() -> None:
            with s._transaction() as c:
                c.execute("INSERT INTO meta (key, value) VALUES ('k', 'v')")
                held.set()
                release.wait(30.0)

        w = threading.Thread(target=writer)
        w.start()
        try:
            assert held.wait(30.0)
            got: list[tuple[dict, dict]] = []
            reader = threading.Thread(target=lambda: got.append((s.counts(), s.stats())))
            reader.start()
            reader.join(20.0)
            done_while_held = not reader.is_alive() and not release.is_set()
        finally:
            release.set()
            w.join()
            reader.join()
        assert done_while_held  # without its own connection it waits for the writer
        counts, stats = got[0]
        assert counts["submaps_pending"] == 1
        assert stats["rows"]["meta"] == 0  # the open transaction's row is not committed yet
        assert s.stats()["rows"]["meta"] == 1
    with pytest.raises(StoreError, match="closed"):
        s.counts()


# --------------------------------------------------------------------------------------------
# Concurrency and crashes
# --------------------------------------------------------------------------------------------


def test_threads_share_one_store(tmp_path: Path) -> None:
    """A callback thread and a worker thread write and read at the same time."""
    errors: list[BaseException] = []
    with Store(tmp_path / "merge.db", synchronous=Synchronous.NORMAL) as store:

        def writer(robot: str) -> None:
            try:
                for seq in range(100):
                    store.put_submap(robot, "s", seq, payload(seq, 200), float(seq))
            except BaseException as exc:  # pragma: no cover - reported below
                errors.append(exc)

        def worker() -> None:
            try:
                deadline = time.monotonic() + 30
                done = 0
                while done < 200 and time.monotonic() < deadline:
                    for sub in store.unprocessed_submaps():
                        store.mark_processed(sub.row_id, "matched")
                        done += 1
            except BaseException as exc:  # pragma: no cover - reported below
                errors.append(exc)

        threads = [threading.Thread(target=writer, args=(r,)) for r in ("a", "b")]
        threads.append(threading.Thread(target=worker))
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=60)
        assert errors == []
        assert store.counts()["submaps"] == {"matched": 200}


def test_second_connection_reads_while_first_is_open(tmp_path: Path) -> None:
    path = tmp_path / "merge.db"
    with Store(path) as writer, Store(path) as reader:
        writer.put_submap("r", "s", 0, b"x", 0.0)
        assert [s.seq for s in reader.unprocessed_submaps()] == [0]


CHILD = """
import sys
from mergesvc.store import Store
path, n, sync = sys.argv[1], int(sys.argv[2]), sys.argv[3]
with Store(path, synchronous=sync) as store:
    for seq in range(n):
        data = (f"submap {seq};".encode() * 300)[:3000]
        row, created = store.put_submap("auv1", "s1", seq, data, float(seq))
        print(seq, row, int(created), flush=True)  # after the commit returned
"""


@pytest.mark.parametrize("sync", ["FULL", "NORMAL"])
def test_kill_9_loses_no_committed_submap(tmp_path: Path, sync: str) -> None:
    """A child writes submaps and reports each commit; we SIGKILL it mid-stream. Every reported
    submap must be there after reopening, exactly once, intact; at most one more (committed but
    not yet reported)."""
    path = tmp_path / "merge.db"
    kill_after = 150
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(path), "1000000", sync],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=REPO,
        env=env,
    )
    watchdog = threading.Timer(60, proc.kill)  # bound the test whatever happens
    watchdog.start()
    reported: dict[int, int] = {}
    try:
        assert proc.stdout is not None
        while len(reported) < kill_after:
            line = proc.stdout.readline()
            if not line:
                break
            seq, row, created = map(int, line.split())
            assert created == 1
            reported[seq] = row
        assert len(reported) == kill_after, proc.stderr.read() if proc.stderr else ""
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
        # Lines already printed before the kill are commits too.
        for line in proc.stdout.read().splitlines():
            parts = line.split()
            if len(parts) == 3:
                reported[int(parts[0])] = int(parts[1])
    finally:
        watchdog.cancel()
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
    assert proc.returncode == -signal.SIGKILL
    assert os.path.exists(f"{path}-wal")  # recovery below really replays the WAL

    with Store(path) as store:  # quick_check runs on open
        rows = store.submaps()
    by_seq = {s.seq: s for s in rows}
    assert len(by_seq) == len(rows)  # nothing duplicated
    for seq, row in reported.items():
        assert by_seq[seq].row_id == row
        assert by_seq[seq].payload == (f"submap {seq};".encode() * 300)[:3000]
    assert sorted(by_seq) == list(range(len(rows)))  # sequential writes: no holes
    assert len(reported) <= len(rows) <= len(reported) + 1
    # The restart sees every submap as still to do, and replays are recognised.
    with Store(path) as store:
        assert len(store.unprocessed_submaps()) == len(rows)
        for seq in reported:
            data = (f"submap {seq};".encode() * 300)[:3000]
            assert store.put_submap("auv1", "s1", seq, data, 0.0) == (reported[seq], False)


# --------------------------------------------------------------------------------------------
# Bad files
# --------------------------------------------------------------------------------------------


def one_line(exc: pytest.ExceptionInfo[BaseException]) -> str:
    msg = str(exc.value)
    assert "\n" not in msg
    return msg


def test_newer_schema_version_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "merge.db"
    Store(path).close()
    with sqlite3.connect(path) as conn:
        conn.execute("UPDATE schema_version SET version = 99")
    conn.close()
    with pytest.raises(StoreError) as exc:
        Store(path)
    assert "schema version 99" in one_line(exc)


def test_foreign_sqlite_file_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "other.db"
    with sqlite3.connect(path) as conn:
        conn.execute("CREATE TABLE t (x)")
    conn.close()
    with pytest.raises(StoreError) as exc:
        Store(path)
    assert "not a mergesvc store" in one_line(exc)


def test_garbage_file_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "merge.db"
    path.write_bytes(os.urandom(8192))
    with pytest.raises(StoreError) as exc:
        Store(path)
    one_line(exc)


def test_damaged_pages_are_detected(tmp_path: Path) -> None:
    path = tmp_path / "merge.db"
    with Store(path) as s:
        for seq in range(50):
            s.put_submap("r", "s", seq, payload(seq, 3000), 0.0)
    data = bytearray(path.read_bytes())
    assert len(data) > 5 * 4096
    data[4096 : 4 * 4096] = b"\xa5" * (3 * 4096)  # overwrite pages 2-4, keep the header
    path.write_bytes(bytes(data))
    with pytest.raises(StoreError) as exc:
        Store(path)
    assert "corrupt" in one_line(exc)


def test_unopenable_path_and_closed_store(tmp_path: Path) -> None:
    with pytest.raises(StoreError):
        Store(tmp_path / "missing-dir" / "merge.db")
    s = Store(":memory:")
    s.close()
    s.close()  # idempotent
    assert s.closed
    with pytest.raises(StoreError, match="closed"):
        s.submaps()


# -- issue 14: the worker's queue, fleet facts, read-only files --------------------------------


def test_pending_ids_are_the_oldest_pending_rows(store: Store) -> None:
    ids = [store.put_submap("r", "s", seq, payload(seq), 0.0)[0] for seq in range(5)]
    store.mark_processed(ids[1], "processed")
    assert store.pending_ids(limit=2) == [ids[0], ids[2]]
    assert store.pending_ids() == [ids[0], ids[2], ids[3], ids[4]]


def test_meta_is_set_once_and_survives_reopen(tmp_path: Path) -> None:
    path = tmp_path / "m.db"
    with Store(path) as s:
        assert s.meta("embedding_dim") is None
        assert s.set_meta_once("embedding_dim", "384") == "384"
        assert s.set_meta_once("embedding_dim", "128") == "384"  # the first one stays
    with Store(path) as s:
        assert s.meta("embedding_dim") == "384"


def test_version_1_file_without_meta_gets_it(tmp_path: Path) -> None:
    """A store written before the meta table existed opens and gains the table."""
    path = tmp_path / "old.db"
    with Store(path) as s:
        s.put_submap("r", "s", 0, payload(0), 0.0)
    with sqlite3.connect(path) as c:
        c.execute("DROP TABLE meta")
    with Store(path) as s:
        assert s.meta("embedding_dim") is None
        assert s.set_meta_once("embedding_dim", "64") == "64"
        assert len(s.submaps()) == 1


def _open_as_nobody(path: Path) -> str:
    """Open `path` as a Store in a forked child running as uid 65534 (root may write any file):
    the error text, or 'opened'."""
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # child: no exec (the venv may not be readable by nobody), only sqlite
        try:
            os.close(r)
            os.setgid(65534)
            os.setuid(65534)
            try:
                Store(path).close()
                msg = "opened"
            except StoreError as exc:
                msg = str(exc)
            os.write(w, msg.encode())
        finally:
            os._exit(0)
    os.close(w)
    with os.fdopen(r, "rb") as f:
        out = f.read().decode()
    os.waitpid(pid, 0)
    return out


def test_read_only_store_is_reported_as_read_only(tmp_path: Path) -> None:
    import tempfile

    folder = Path(tempfile.mkdtemp(prefix="ro-store-"))  # tmp_path is not reachable by nobody
    try:
        path = folder / "ro.db"
        with Store(path) as s:
            s.put_submap("r", "s", 0, payload(0), 0.0)
        if os.geteuid() == 0:
            folder.chmod(0o755)
            msg = _open_as_nobody(path)
        else:
            path.chmod(0o444)
            folder.chmod(0o555)
            with pytest.raises(StoreError) as info:
                Store(path)
            msg = str(info.value)
        assert "read-only" in msg and "corrupt" not in msg, msg
    finally:
        folder.chmod(0o755)
        for p in folder.iterdir():
            p.chmod(0o644)
            p.unlink()
        folder.rmdir()


def test_paged_reads_give_what_the_whole_reads_give(store: Store) -> None:
    """A restart reads the store a page at a time (iter_submaps, iter_factors): pages of 2
    over 7 rows with mixed statuses, a status changed after the rows were written, and a
    filter, give exactly the rows and order of the one-shot reads."""
    rows = [store.put_submap(f"auv{k % 3}", "s1", k, payload(k, 50), float(k))[0]
            for k in range(7)]
    for r in rows[1::2]:
        store.mark_processed(r, "processed", "1 factors")
    store.mark_processed(rows[4], "no_match")
    assert list(store.iter_submaps(page=2)) == store.submaps()
    assert len(store.submaps()) == 7
    for k in range(7):
        st = (FactorStatus.ACCEPTED, FactorStatus.RETRACTED)[k % 2]
        assert store.put_factor(f"f{k}", "a/1", f"b/{k}", f"factor {k}".encode(), st)
    store.set_factor_status("f2", FactorStatus.RETRACTED)
    assert list(store.iter_factors(page=2)) == store.factors()
    accepted = list(store.iter_factors(FactorStatus.ACCEPTED, page=2))
    assert accepted == store.factors(FactorStatus.ACCEPTED)
    assert [f.factor_id for f in accepted] == ["f0", "f4", "f6"]


def test_the_figures_of_one_read_are_one_commits(tmp_path: Path) -> None:
    with Store(tmp_path / "f.db") as s:
        for seq in range(3):
            s.put_submap("r", "s", seq, payload(seq, 100), 0.0)
        counts, stats = s.figures()
        assert counts == s.counts() and stats == s.stats()
        assert counts["submaps_pending"] == stats["rows"]["submaps"] == 3
