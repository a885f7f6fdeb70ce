"""A store read from another process while the service writes it (the soak's judge): read-only
SQLite over WAL, the same tables the service writes, no write ever."""

from __future__ import annotations

import sqlite3
from collections import Counter
from pathlib import Path
from typing import Any

from mergesvc.errors import StoreError, one_line


class StoreReader:
    """Read-only view of a store file; a context manager."""

    def __init__(self, path: Path | str, timeout_s: float = 10.0) -> None:
        self.path = str(path)
        try:
            self._db = sqlite3.connect(f"file:{self.path}?mode=ro", uri=True,
                                       timeout=timeout_s)
        except sqlite3.Error as exc:
            raise StoreError(f"cannot read store {self.path}: {one_line(exc)}") from exc

    def __enter__(self) -> StoreReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._db.close()

    def _rows(self, sql: str) -> list[tuple[Any, ...]]:
        try:
            return self._db.execute(sql).fetchall()
        except sqlite3.Error as exc:
            raise StoreError(f"cannot read store {self.path}: {one_line(exc)}") from exc

    def submap_rows(self) -> list[tuple[str, str, int, str, float, float | None]]:
        """(robot, session, seq, status, received at, processed at) of every stored submap."""
        return [(r, s, int(q), st, float(rec), None if proc is None else float(proc))
                for r, s, q, st, rec, proc in self._rows(
                    "SELECT robot_id, session_id, seq, status, received_at_s, processed_at_s "
                    "FROM submaps")]

    def meta(self, key: str) -> str | None:
        """A fleet-wide fact stored once (Store.meta), None if not set or the file has no
        meta table (a version-1 file)."""
        try:
            row = self._db.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        except sqlite3.OperationalError:
            return None
        return None if row is None else str(row[0])

    def conflicts(self) -> int:
        return int(self._rows("SELECT COUNT(*) FROM submap_conflicts")[0][0])

    def conflicts_by_robot(self) -> Counter[str]:
        """Conflict rows per robot."""
        return Counter({str(r): int(n) for r, n in self._rows(
            "SELECT robot_id, COUNT(*) FROM submap_conflicts GROUP BY robot_id")})

    def conflict_bytes(self) -> int:
        """Bytes the conflict rows keep (their payloads: none, hashes only)."""
        return int(self._rows("SELECT COALESCE(SUM(LENGTH(payload)), 0) FROM "
                              "submap_conflicts")[0][0])

    def factor_counts(self) -> dict[str, int]:
        return {str(k): int(v) for k, v in self._rows(
            "SELECT status, COUNT(*) FROM factors GROUP BY status")}

    def integrity(self) -> str:
        return str(self._rows("PRAGMA integrity_check")[0][0])

    def status_counts(self) -> Counter[str]:
        return Counter(st for *_, st, _, _ in self.submap_rows())


__all__ = ["StoreReader"]
