"""The service's store: one SQLite file in WAL mode holding every accepted submap (written before it
is processed), the inter-robot factors sent, and the robot-session frames seen. A restart redoes
`unprocessed_submaps()`; replays are idempotent on the natural keys.

Durability: `synchronous=FULL` by default. In WAL mode NORMAL already survives a process crash
(kill -9: a committed transaction is in the WAL file, which the OS keeps), but a power cut or OS
crash may roll back the last commits; FULL fsyncs the WAL at every commit, so a submap the service
acknowledged survives that too. Submaps arrive at most a few per second, so the fsync per commit
is affordable. NORMAL is available for bulk imports and tests.

Threads: one connection opened with `check_same_thread=False`, every public method but the
status figures holds one re-entrant lock for its whole transaction, so the Zenoh callback
thread and the worker thread may share a Store. The status figures (`counts`, `stats`,
`figures`) read through a second, read-only connection of their own under a lock of its own (a
file store), so they never wait for a commit's fsync.
Other processes (a status command) may open the same file: WAL lets readers run while one
writer commits; writers wait up to `busy_timeout_s`.
"""

from __future__ import annotations

import hashlib
import logging
import os
import sqlite3
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from enum import Enum
from pathlib import Path
from typing import Any

from mergesvc.core.frames import frame_name
from mergesvc.errors import ConfigError, InputError, StoreError, one_line
from mergesvc.store.factors import FactorRecords
from mergesvc.store.records import (
    _HELD,
    _MAX_STATUS_LENGTH,
    _META,
    _SCHEMA,
    _TABLES,
    _UNANSWERED,
    APPLICATION_ID,
    META_FLEET,
    PENDING,
    STORE_SCHEMA_VERSION,
    StoredFrame,
    StoredSubmap,
    SubmapConflictError,
    Synchronous,
    _check_bytes,
    _check_id,
    _check_time,
    _read_only,
)

log = logging.getLogger(__name__)
CONFLICTS_KEPT = 8  # conflicting variants of one submap key on record (their hashes)


def is_memory(path: str) -> bool:
    """A store path SQLite keeps in memory (no file)."""
    return path == ":memory:" or path.startswith("file::memory:")


class Store(FactorRecords):
    """The service's SQLite store. `Store(":memory:")` for tests; use as a context manager.

    Every write is one transaction, committed before the method returns.
    """

    def __init__(
        self,
        path: Path | str,
        *,
        synchronous: Synchronous | str = Synchronous.FULL,
        check_integrity: bool = True,
        busy_timeout_s: float = 5.0,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.path = str(path)
        self.synchronous = Synchronous(synchronous)
        self._clock = clock
        self._lock = threading.RLock()
        self._memory = is_memory(self.path)
        self._busy_timeout_s = busy_timeout_s
        self._reader_uri = (None if self._memory
                            else Path(self.path).resolve().as_uri() + "?mode=ro")
        self._reader: sqlite3.Connection | None = None  # the status figures' (_figures)
        self._reader_lock = threading.Lock()
        self._fleet: str | None = None  # the fleet to claim with a submap stored (claim_fleet)
        try:
            self._conn: sqlite3.Connection | None = sqlite3.connect(
                self.path,
                timeout=busy_timeout_s,
                isolation_level=None,  # autocommit; transactions are explicit (BEGIN IMMEDIATE)
                check_same_thread=False,  # shared by threads under self._lock
            )
        except sqlite3.Error as exc:
            raise StoreError(f"cannot open store {self.path}: {one_line(exc)}") from exc
        try:
            self._open(check_integrity)
        except sqlite3.DatabaseError as exc:
            self._conn.close()
            self._conn = None
            if _read_only(exc):
                raise StoreError(
                    f"store {self.path} is read-only (the service needs to write the file and "
                    f"its -wal and -shm files beside it): {one_line(exc)}"
                ) from exc
            raise StoreError(
                f"store {self.path} is unreadable or corrupt: {one_line(exc)}"
            ) from exc
        except BaseException:
            self._conn.close()
            self._conn = None
            raise

    # -- lifecycle -------------------------------------------------------------------------------

    def _open(self, check_integrity: bool) -> None:
        conn = self._conn
        if conn is None:  # only __init__ calls this, right after connecting
            raise StoreError(f"store {self.path} is closed")
        # The first statement reads the header: a file that is not SQLite fails here.
        mode = conn.execute("PRAGMA journal_mode=WAL").fetchone()[0]
        if not self._memory and str(mode).lower() != "wal":
            raise StoreError(f"store {self.path}: cannot enable WAL mode (journal_mode={mode})")
        conn.execute(f"PRAGMA synchronous={self.synchronous.value}")
        if check_integrity:
            rows = conn.execute("PRAGMA quick_check").fetchall()
            if [r[0] for r in rows] != ["ok"]:
                raise StoreError(f"store {self.path} is corrupt: {rows[0][0]}")
        with self._transaction() as c:
            tables = {
                r[0] for r in c.execute("SELECT name FROM sqlite_master WHERE type = 'table'")
            }
            tables.discard("sqlite_sequence")
            if not tables:
                self._create(c)
                return
            app_id = c.execute("PRAGMA application_id").fetchone()[0]
            if app_id != APPLICATION_ID or "schema_version" not in tables:
                raise StoreError(f"{self.path} is an SQLite file but not a mergesvc store")
            version = c.execute("SELECT MAX(version) FROM schema_version").fetchone()[0]
        if version is None or version > STORE_SCHEMA_VERSION:
            raise StoreError(
                f"store {self.path} has schema version {version}; this build reads version "
                f"{STORE_SCHEMA_VERSION} (written by a newer mergesvc?)"
            )
        if version < STORE_SCHEMA_VERSION:  # no older versions exist yet: nothing to migrate
            raise StoreError(f"store {self.path} has unknown old schema version {version}")
        for table, create in (("meta", _META), ("held_factors", _HELD),
                              ("unanswered", _UNANSWERED)):
            if table not in tables:
                try:
                    with self._transaction() as c:
                        c.execute(create)
                except StoreError:  # a read-only copy (export) reads what is there
                    log.debug("store %s: no %s table (read-only)", self.path, table)

    def _create(self, c: sqlite3.Connection) -> None:
        c.execute(f"PRAGMA application_id={APPLICATION_ID}")
        for statement in _SCHEMA.split(";"):
            if statement.strip():
                c.execute(statement)
        c.execute(
            "INSERT INTO schema_version (version, created_at_s) VALUES (?, ?)",
            (STORE_SCHEMA_VERSION, self._clock()),
        )
        log.info("created store %s (schema version %d)", self.path, STORE_SCHEMA_VERSION)

    def close(self) -> None:
        """Close the connections (checkpoints the WAL: the reader is closed first, under both
        locks, so no status read opens it again in between). Idempotent."""
        with self._reader_lock, self._lock:
            self._close_reader()
            if self._conn is not None:
                try:
                    self._conn.close()
                except sqlite3.Error as exc:
                    raise StoreError(f"closing store {self.path}: {one_line(exc)}") from exc
                finally:
                    self._conn = None

    @property
    def closed(self) -> bool:
        return self._conn is None

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @contextmanager
    def _transaction(self, write: bool = True) -> Iterator[sqlite3.Connection]:
        """One transaction under the lock; sqlite errors become StoreError."""
        with self._lock:
            conn = self._conn
            if conn is None:
                raise StoreError(f"store {self.path} is closed")
            try:
                # IMMEDIATE takes the write lock up front: no upgrade deadlock between processes.
                conn.execute("BEGIN IMMEDIATE" if write else "BEGIN")
            except sqlite3.Error as exc:
                raise StoreError(f"store {self.path}: {one_line(exc)}") from exc
            try:
                yield conn
                conn.execute("COMMIT")
            except BaseException as exc:
                if conn.in_transaction:
                    try:
                        conn.execute("ROLLBACK")
                    except sqlite3.Error:
                        log.exception("rollback failed on %s", self.path)
                if isinstance(exc, sqlite3.Error):
                    raise StoreError(f"store {self.path}: {one_line(exc)}") from exc
                raise

    def _close_reader(self) -> None:
        if self._reader is not None:
            try:
                self._reader.close()
            except sqlite3.Error:
                log.debug("closing the status reader of %s failed", self.path)
            self._reader = None

    @contextmanager
    def _figures(self) -> Iterator[sqlite3.Connection]:
        """A read transaction for the status figures: on a file store through the read-only
        connection (WAL: it reads the last commit while the writer commits, never waiting for
        its lock or its fsync), on a memory store through the one connection."""
        if self._memory:
            with self._transaction(write=False) as c:
                yield c
            return
        with self._reader_lock:
            if self.closed or self._reader_uri is None:
                raise StoreError(f"store {self.path} is closed")
            try:
                if self._reader is None:
                    self._reader = sqlite3.connect(
                        self._reader_uri, uri=True, timeout=self._busy_timeout_s,
                        isolation_level=None, check_same_thread=False)
                self._reader.execute("BEGIN")
                yield self._reader
                self._reader.execute("COMMIT")
            except sqlite3.Error as exc:  # a connection that failed is opened afresh next time
                self._close_reader()
                raise StoreError(f"store {self.path}: {one_line(exc)}") from exc
            except BaseException:
                self._close_reader()
                raise

    # -- submaps ---------------------------------------------------------------------------------

    def put_submap(
        self,
        robot_id: str,
        session_id: str,
        seq: int,
        payload_bytes: bytes,
        received_at_s: float,
    ) -> tuple[int, bool]:
        """Persist a submap; returns (row id, created).

        A replay of the same key with identical bytes returns the stored row and created=False.
        The same key with different bytes raises SubmapConflictError after recording the new
        payload's hash in `submap_conflicts` (at most CONFLICTS_KEPT per key). The
        robot-session frame is recorded in the same commit.
        """
        robot_id = _check_id(robot_id, "robot_id")
        session_id = _check_id(session_id, "session_id")
        if isinstance(seq, bool) or not isinstance(seq, int) or seq < 0:
            raise InputError(f"seq must be an integer >= 0, got {seq!r}")
        payload = _check_bytes(payload_bytes, "payload_bytes")
        t = _check_time(received_at_s, "received_at_s")
        frame = frame_name(robot_id, session_id)
        digest = hashlib.sha256(payload).hexdigest()
        with self._transaction() as c:
            row = c.execute(
                "SELECT id, sha256 FROM submaps WHERE robot_id = ? AND session_id = ? AND seq = ?",
                (robot_id, session_id, seq),
            ).fetchone()
            if row is None:
                cur = c.execute(
                    "INSERT INTO submaps (robot_id, session_id, seq, payload, sha256, "
                    "received_at_s) VALUES (?, ?, ?, ?, ?, ?)",
                    (robot_id, session_id, seq, payload, digest, t),
                )
                self._touch_frame(c, frame, robot_id, session_id, t)
                if self._fleet is not None:  # (claim_fleet) in the submap's commit
                    c.execute("INSERT OR IGNORE INTO meta (key, value) VALUES (?, ?)",
                              (META_FLEET, self._fleet))
                return int(cur.lastrowid), True
            row_id, stored_digest = row
            if stored_digest == digest:
                return int(row_id), False
            kept = c.execute(
                "SELECT COUNT(*) FROM submap_conflicts WHERE robot_id = ? AND session_id = ? "
                "AND seq = ?", (robot_id, session_id, seq)).fetchone()[0]
            if kept < CONFLICTS_KEPT:  # the hash only: a flood of variants costs no space
                c.execute(
                    "INSERT INTO submap_conflicts (robot_id, session_id, seq, payload, sha256, "
                    "received_at_s) VALUES (?, ?, ?, ?, ?, ?)",
                    (robot_id, session_id, seq, b"", digest, t),
                )
        # Raised after the commit, so the conflict is on record.
        raise SubmapConflictError(
            f"submap {frame}#{seq} was stored before with different content "
            f"(sha256 {stored_digest[:12]} vs {digest[:12]}); kept the first, logged the "
            "conflict (a restarted vehicle sends a new --session)"
        )

    def mark_processed(self, submap_row_id: int, status: str, detail: str = "") -> None:
        """Record the outcome of processing a submap (any status but PENDING). Idempotent."""
        status = str(status.value if isinstance(status, Enum) else status)
        if not 1 <= len(status) <= _MAX_STATUS_LENGTH or status == PENDING:
            raise InputError(f"status must be 1 to {_MAX_STATUS_LENGTH} characters, not {PENDING}")
        if not isinstance(detail, str):
            raise InputError("detail must be a string")
        with self._transaction() as c:
            cur = c.execute(
                "UPDATE submaps SET status = ?, detail = ?, processed_at_s = ? WHERE id = ?",
                (status, detail, self._clock(), int(submap_row_id)),
            )
            if cur.rowcount != 1:
                raise StoreError(f"no submap with row id {submap_row_id} in {self.path}")

    _SUBMAP_COLUMNS = (
        "id, robot_id, session_id, seq, payload, sha256, received_at_s, status, detail, "
        "processed_at_s"
    )

    @staticmethod
    def _submap(row: tuple[Any, ...]) -> StoredSubmap:
        return StoredSubmap(
            row_id=int(row[0]),
            robot_id=row[1],
            session_id=row[2],
            seq=int(row[3]),
            payload=bytes(row[4]),
            sha256=row[5],
            received_at_s=float(row[6]),
            status=row[7],
            detail=row[8],
            processed_at_s=None if row[9] is None else float(row[9]),
        )

    def unprocessed_submaps(self) -> list[StoredSubmap]:
        """Submaps still PENDING, in arrival order: what a restart must process."""
        with self._transaction(write=False) as c:
            rows = c.execute(
                f"SELECT {self._SUBMAP_COLUMNS} FROM submaps WHERE status = ? ORDER BY id",
                (PENDING,),
            ).fetchall()
        return [self._submap(r) for r in rows]

    def has_submap(self, robot_id: str, session_id: str, seq: int) -> bool:
        """Whether the submap (robot, session, seq) is stored."""
        with self._transaction(write=False) as c:
            row = c.execute(
                "SELECT 1 FROM submaps WHERE robot_id = ? AND session_id = ? AND seq = ?",
                (robot_id, session_id, int(seq)),
            ).fetchone()
        return row is not None

    def submap_digest(self, robot_id: str, session_id: str, seq: int) -> str | None:
        """The sha256 (hex) of the submap stored under (robot, session, seq), None if none."""
        with self._transaction(write=False) as c:
            row = c.execute(
                "SELECT sha256 FROM submaps WHERE robot_id = ? AND session_id = ? AND seq = ?",
                (robot_id, session_id, int(seq)),
            ).fetchone()
        return None if row is None else str(row[0])

    def final_seqs(self) -> dict[tuple[str, str], int]:
        """The highest seq per session whose submap has a final status (not pending)."""
        with self._transaction(write=False) as c:
            rows = c.execute("SELECT robot_id, session_id, MAX(seq) FROM submaps WHERE "
                             "status != ? GROUP BY robot_id, session_id", (PENDING,)).fetchall()
        return {(r, s): int(q) for r, s, q in rows}

    def pending_ids(self, limit: int = 64) -> list[int]:
        """Row ids of up to `limit` PENDING submaps, oldest first (the worker's queue)."""
        with self._transaction(write=False) as c:
            rows = c.execute(
                "SELECT id FROM submaps WHERE status = ? ORDER BY id LIMIT ?",
                (PENDING, int(limit)),
            ).fetchall()
        return [int(r[0]) for r in rows]

    def submap(self, submap_row_id: int) -> StoredSubmap:
        with self._transaction(write=False) as c:
            row = c.execute(
                f"SELECT {self._SUBMAP_COLUMNS} FROM submaps WHERE id = ?", (int(submap_row_id),)
            ).fetchone()
        if row is None:
            raise StoreError(f"no submap with row id {submap_row_id} in {self.path}")
        return self._submap(row)

    def submaps(
        self,
        robot_id: str | None = None,
        session_id: str | None = None,
        *,
        status: str | None = None,
    ) -> list[StoredSubmap]:
        """Stored submaps in arrival order, optionally filtered."""
        where, args = [], []
        for column, value in (("robot_id", robot_id), ("session_id", session_id)):
            if value is not None:
                where.append(f"{column} = ?")
                args.append(value)
        if status is not None:
            where.append("status = ?")
            args.append(str(status))
        clause = f" WHERE {' AND '.join(where)}" if where else ""
        with self._transaction(write=False) as c:
            rows = c.execute(
                f"SELECT {self._SUBMAP_COLUMNS} FROM submaps{clause} ORDER BY id", args
            ).fetchall()
        return [self._submap(r) for r in rows]

    def iter_submaps(self, page: int = 500) -> Iterator[StoredSubmap]:
        """Every stored submap in arrival order, like `submaps()`, read `page` rows at a time:
        a restart goes through a whole mission's submaps without holding them all at once."""
        for r in self._paged(f"SELECT {self._SUBMAP_COLUMNS} FROM submaps WHERE id > ?", (),
                             "id", page):
            yield self._submap(r)

    def _paged(self, select: str, args: tuple[Any, ...], key: str,
               page: int) -> Iterator[tuple[Any, ...]]:
        """The rows of `select` (its first column `key`, its WHERE starting `key > ?`, then
        `args`) in `key` order, `page` rows per read. Each page is its own read; rows added
        meanwhile come last, as they would."""
        last = 0
        while True:
            with self._transaction(write=False) as c:
                rows = c.execute(f"{select} ORDER BY {key} LIMIT ?",
                                 (last, *args, page)).fetchall()
            if not rows:
                return
            last = int(rows[-1][0])
            yield from rows

    def submap_conflicts(self) -> list[tuple[str, str, int, str, float]]:
        """(robot_id, session_id, seq, sha256 hex, received_at_s) of the conflicting replays on
        record (at most CONFLICTS_KEPT per key; only their hashes are kept)."""
        with self._transaction(write=False) as c:
            rows = c.execute(
                "SELECT robot_id, session_id, seq, sha256, received_at_s FROM submap_conflicts "
                "ORDER BY id"
            ).fetchall()
        return [(r[0], r[1], int(r[2]), str(r[3]), float(r[4])) for r in rows]

    # -- factors ---------------------------------------------------------------------------------


    @staticmethod
    def _touch_frame(
        c: sqlite3.Connection, frame: str, robot_id: str, session_id: str, t: float
    ) -> bool:
        cur = c.execute(
            "INSERT OR IGNORE INTO frames (frame, robot_id, session_id, first_seen_s, "
            "last_seen_s) VALUES (?, ?, ?, ?, ?)",
            (frame, robot_id, session_id, t, t),
        )
        if cur.rowcount == 1:
            return True
        c.execute(
            "UPDATE frames SET first_seen_s = MIN(first_seen_s, ?), "
            "last_seen_s = MAX(last_seen_s, ?) WHERE frame = ?",
            (t, t, frame),
        )
        return False

    def put_frame(self, robot_id: str, session_id: str, seen_at_s: float) -> bool:
        """Record that a robot-session frame was seen; True if new. (put_submap does this.)"""
        robot_id = _check_id(robot_id, "robot_id")
        session_id = _check_id(session_id, "session_id")
        t = _check_time(seen_at_s, "seen_at_s")
        frame = frame_name(robot_id, session_id)
        with self._transaction() as c:
            return self._touch_frame(c, frame, robot_id, session_id, t)

    def frames(self) -> list[StoredFrame]:
        """Frames in the order they were first recorded."""
        with self._transaction(write=False) as c:
            rows = c.execute(
                "SELECT frame, robot_id, session_id, first_seen_s, last_seen_s FROM frames "
                "ORDER BY rowid"
            ).fetchall()
        return [StoredFrame(r[0], r[1], r[2], float(r[3]), float(r[4])) for r in rows]

    # -- meta ------------------------------------------------------------------------------------

    def meta(self, key: str) -> str | None:
        """A fleet-wide fact stored once (e.g. META_EMBEDDING_DIM), None if not set."""
        with self._transaction(write=False) as c:
            try:
                row = c.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
            except sqlite3.OperationalError:  # a version-1 file opened read-only: no table
                return None
        return None if row is None else str(row[0])

    def set_meta_once(self, key: str, value: str) -> str:
        """Store `value` under `key` unless a value is there; returns the stored value (the
        first writer wins, atomically)."""
        key = _check_id(key, "meta key")
        if not isinstance(value, str):
            raise InputError("meta value must be a string")
        with self._transaction() as c:
            c.execute("INSERT OR IGNORE INTO meta (key, value) VALUES (?, ?)", (key, value))
            return str(c.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()[0])

    def claim_fleet(self, fleet: str) -> None:
        """Store `fleet`'s submaps from now on, or ConfigError when the store holds another
        fleet's (one store, one fleet's sessions, factors and frame). The claim is written
        with the first submap this store takes (`put_submap`): a service that stored nothing
        leaves no mark, and an older file is claimed by the fleet whose submaps it takes."""
        owner = self.meta(META_FLEET)
        if owner is not None and owner != fleet:
            raise ConfigError(f"store {self.path} holds fleet {owner}'s submaps, not {fleet}'s: "
                              f"serve --fleet {owner}, or pick another --store for {fleet}")
        self._fleet = fleet

    def set_meta(self, key: str, value: str) -> None:
        """Store `value` under `key`, replacing what was there (state derived as the service
        runs, e.g. its calibrated noise scales)."""
        key = _check_id(key, "meta key")
        if not isinstance(value, str):
            raise InputError("meta value must be a string")
        with self._transaction() as c:
            c.execute("INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)", (key, value))

    # -- status ----------------------------------------------------------------------------------

    def counts(self) -> dict[str, Any]:
        """For a status endpoint: submaps and factors per status, frames, refused replays (the
        last commit's, never waiting for a write)."""
        with self._figures() as c:
            return self._counts(c)

    def stats(self) -> dict[str, Any]:
        """Rows per table and sizes: file_bytes (main file), wal_bytes, page_bytes (logical);
        the last commit's, never waiting for a write."""
        with self._figures() as c:
            return self._stats(c)

    def figures(self) -> tuple[dict[str, Any], dict[str, Any]]:
        """(counts(), stats()) of one read: the same commit's."""
        with self._figures() as c:
            return self._counts(c), self._stats(c)

    @staticmethod
    def _counts(c: sqlite3.Connection) -> dict[str, Any]:
        submaps = dict(c.execute("SELECT status, COUNT(*) FROM submaps GROUP BY status"))
        factors = dict(c.execute("SELECT status, COUNT(*) FROM factors GROUP BY status"))
        n_frames = c.execute("SELECT COUNT(*) FROM frames").fetchone()[0]
        n_conflicts = c.execute("SELECT COUNT(*) FROM submap_conflicts").fetchone()[0]
        return {
            "submaps": {str(k): int(v) for k, v in submaps.items()},
            "submaps_pending": int(submaps.get(PENDING, 0)),
            "factors": {str(k): int(v) for k, v in factors.items()},
            "frames": int(n_frames),
            "submap_conflicts": int(n_conflicts),
        }

    def _stats(self, c: sqlite3.Connection) -> dict[str, Any]:
        present = {r[0] for r in c.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        rows = {t: int(c.execute(f"SELECT COUNT(*) FROM {t}").fetchone()[0])
                for t in _TABLES if t in present}
        page_bytes = int(c.execute("PRAGMA page_count").fetchone()[0]) * int(
            c.execute("PRAGMA page_size").fetchone()[0]
        )
        journal = str(c.execute("PRAGMA journal_mode").fetchone()[0])
        return {
            "path": self.path,
            "schema_version": STORE_SCHEMA_VERSION,
            "journal_mode": journal,
            "synchronous": self.synchronous.value,
            "rows": rows,
            "file_bytes": 0 if self._memory else _size(self.path),
            "wal_bytes": 0 if self._memory else _size(self.path + "-wal"),
            "page_bytes": page_bytes,
        }


def _size(path: str) -> int:
    """A file's size; 0 when it is not there (a WAL checkpointed away)."""
    try:
        return os.path.getsize(path)
    except OSError:
        return 0


__all__ = ["CONFLICTS_KEPT", "Store", "is_memory"]
