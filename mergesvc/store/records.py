"""The store's records and its tables: the SQL schema (version, application id), the rows it
hands out (StoredSubmap, StoredFactor, StoredFrame), the checks every write makes of its
arguments, and the errors it raises. Nothing here opens a file.
"""

from __future__ import annotations

import math
import sqlite3
from dataclasses import dataclass
from enum import Enum
from typing import Any

from mergesvc.core.frames import frame_name
from mergesvc.core.model import FactorStatus
from mergesvc.errors import InputError, StoreError

STORE_SCHEMA_VERSION = 1
#: `PRAGMA application_id` of a mergesvc store ("MRGS"), so a foreign SQLite file is refused.
APPLICATION_ID = 0x4D524753
#: Status of a submap that is stored but not yet processed.
PENDING = "pending"

_MAX_ID_LENGTH = 128
_MAX_STATUS_LENGTH = 64

_SCHEMA = """
CREATE TABLE schema_version (
    version INTEGER NOT NULL,
    created_at_s REAL NOT NULL
);
CREATE TABLE submaps (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    robot_id TEXT NOT NULL,
    session_id TEXT NOT NULL,
    seq INTEGER NOT NULL,
    payload BLOB NOT NULL,
    sha256 TEXT NOT NULL,
    received_at_s REAL NOT NULL,
    status TEXT NOT NULL DEFAULT 'pending',
    detail TEXT NOT NULL DEFAULT '',
    processed_at_s REAL,
    UNIQUE (robot_id, session_id, seq)
);
CREATE INDEX submaps_pending ON submaps (status, id);
CREATE TABLE submap_conflicts (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    robot_id TEXT NOT NULL,
    session_id TEXT NOT NULL,
    seq INTEGER NOT NULL,
    payload BLOB NOT NULL,
    sha256 TEXT NOT NULL,
    received_at_s REAL NOT NULL
);
CREATE TABLE factors (
    factor_id TEXT PRIMARY KEY,
    frame_a TEXT NOT NULL,
    frame_b TEXT NOT NULL,
    payload BLOB NOT NULL,
    status TEXT NOT NULL CHECK (status IN ('accepted', 'retracted')),
    created_at_s REAL NOT NULL,
    updated_at_s REAL NOT NULL
);
CREATE TABLE frames (
    frame TEXT PRIMARY KEY,
    robot_id TEXT NOT NULL,
    session_id TEXT NOT NULL,
    first_seen_s REAL NOT NULL,
    last_seen_s REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS meta (
    key TEXT PRIMARY KEY,
    value TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS held_factors (
    factor_id TEXT PRIMARY KEY,
    frame_a TEXT NOT NULL,
    frame_b TEXT NOT NULL,
    payload BLOB NOT NULL,
    created_at_s REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS unanswered (
    row_id INTEGER PRIMARY KEY,
    answer BLOB NOT NULL
);
"""
# `meta` (fleet-wide facts fixed once, e.g. the embedding dimension) came after version 1 was
# out: a version-1 file without it gets it when opened writable (an added table, nothing else
# changes); opened read-only, `meta()` answers None.
_META = "CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)"
# `held_factors` (factors the service keeps but does not trust yet: not sent, or withdrawn)
# came later still, added the same way.
_HELD = ("CREATE TABLE IF NOT EXISTS held_factors (factor_id TEXT PRIMARY KEY, frame_a TEXT "
         "NOT NULL, frame_b TEXT NOT NULL, payload BLOB NOT NULL, created_at_s REAL NOT NULL)")
# `unanswered` (a committed unit's messages until they were published: a restart publishes
# what a crash between the commit and the publishing left unsent) likewise.
_UNANSWERED = ("CREATE TABLE IF NOT EXISTS unanswered (row_id INTEGER PRIMARY KEY, answer BLOB "
               "NOT NULL)")
_TABLES = ("schema_version", "submaps", "submap_conflicts", "factors", "frames", "meta",
           "held_factors", "unanswered")
#: Meta key of the fleet's embedding dimension (fixed by the first accepted submap or the
#: service's setting).
META_EMBEDDING_DIM = "embedding_dim"
#: Meta key of the pose graph's calibrated noise scales (JSON: group -> 6 sigma scales).
META_NOISE_SCALES = "noise_scales"
#: Meta key of the fleet's anchor session ("robot/session"): fixed by the first unit of work,
#: so published coordinates stay in one frame across restarts.
META_ANCHOR = "anchor"
#: Meta key of the fleet whose submaps a store holds: fixed with the first one stored.
META_FLEET = "fleet"


def _read_only(exc: sqlite3.Error) -> bool:
    """Whether SQLite refused a write because the file (or its folder: WAL needs its -wal and
    -shm files beside it) is read-only."""
    name = str(getattr(exc, "sqlite_errorname", ""))
    return name.startswith("SQLITE_READONLY") or "readonly database" in str(exc)


class Synchronous(str, Enum):
    """SQLite `synchronous` setting (see the module docstring)."""

    NORMAL = "NORMAL"
    FULL = "FULL"


class SubmapConflictError(StoreError):
    """A submap key (robot, session, seq) was stored before with different bytes.

    The new payload is kept in `submap_conflicts` (nothing is lost); the stored one is unchanged.
    """


@dataclass(frozen=True)
class StoredSubmap:
    """One stored submap. status is PENDING until `mark_processed`."""

    row_id: int
    robot_id: str
    session_id: str
    seq: int
    payload: bytes
    sha256: str
    received_at_s: float
    status: str
    detail: str
    processed_at_s: float | None

    @property
    def frame(self) -> str:
        return frame_name(self.robot_id, self.session_id)

    @property
    def processed(self) -> bool:
        return self.status != PENDING


@dataclass(frozen=True)
class StoredFactor:
    factor_id: str
    frame_a: str
    frame_b: str
    payload: bytes
    status: FactorStatus
    created_at_s: float
    updated_at_s: float


@dataclass(frozen=True)
class StoredFrame:
    frame: str
    robot_id: str
    session_id: str
    first_seen_s: float
    last_seen_s: float


def _check_id(value: Any, name: str) -> str:
    if not isinstance(value, str) or not 1 <= len(value) <= _MAX_ID_LENGTH:
        raise InputError(f"{name} must be a string of 1 to {_MAX_ID_LENGTH} characters")
    return value


def _check_bytes(value: Any, name: str) -> bytes:
    if not isinstance(value, (bytes, bytearray, memoryview)):
        raise InputError(f"{name} must be bytes, got {type(value).__name__}")
    return bytes(value)


def _check_time(value: Any, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(f"{name} must be a finite number of seconds, got {value!r}")
    return float(value)


def _check_factor_status(status: Any) -> FactorStatus:
    try:
        return FactorStatus(status)
    except ValueError:
        allowed = ", ".join(s.value for s in FactorStatus)
        raise InputError(f"factor status must be one of {allowed}, got {status!r}") from None


__all__ = ["APPLICATION_ID", "META_ANCHOR", "META_EMBEDDING_DIM", "META_FLEET",
           "META_NOISE_SCALES", "PENDING", "STORE_SCHEMA_VERSION", "StoredFactor",
           "StoredFrame", "StoredSubmap", "SubmapConflictError", "Synchronous"]
