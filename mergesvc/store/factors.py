"""The store's factor rows: the factors sent (accepted or retracted, as the vehicles were told)
and those held (kept, not trusted yet), written with the submap that made them in one
transaction (`commit_unit`), read back in the order they were made. A mixin of Store
(store/database.py): it uses the store's connection, lock and clock.
"""

from __future__ import annotations

import logging
import sqlite3
from collections.abc import Callable, Iterator, Sequence
from contextlib import AbstractContextManager
from typing import Any

from mergesvc.core.frames import frame_name
from mergesvc.core.model import FactorStatus
from mergesvc.errors import StoreError
from mergesvc.store.records import (
    META_ANCHOR,
    PENDING,
    StoredFactor,
    _check_bytes,
    _check_factor_status,
    _check_id,
)

log = logging.getLogger(__name__)


class FactorRecords:
    """Factor rows (see the module docstring); Store provides the members below."""

    path: str
    _clock: Callable[[], float]

    def _transaction(self, write: bool = True) -> AbstractContextManager[sqlite3.Connection]:
        raise NotImplementedError

    def _paged(self, select: str, args: tuple[Any, ...], key: str,
               page: int) -> Iterator[tuple[Any, ...]]:
        raise NotImplementedError

    @staticmethod
    def _touch_frame(c: sqlite3.Connection, frame: str, robot_id: str, session_id: str,
                     t: float) -> bool:
        raise NotImplementedError

    def put_factor(
        self,
        factor_id: str,
        frame_a: str,
        frame_b: str,
        payload_bytes: bytes,
        status: FactorStatus | str = FactorStatus.ACCEPTED,
    ) -> bool:
        """Persist a factor; True if new. Idempotent on factor_id: the first write wins (a replay
        with other bytes is logged and ignored); change the status with `set_factor_status`."""
        factor_id = _check_id(factor_id, "factor_id")
        frame_a = _check_id(frame_a, "frame_a")
        frame_b = _check_id(frame_b, "frame_b")
        payload = _check_bytes(payload_bytes, "payload_bytes")
        st = _check_factor_status(status)
        now = self._clock()
        with self._transaction() as c:
            row = c.execute(
                "SELECT payload FROM factors WHERE factor_id = ?", (factor_id,)
            ).fetchone()
            if row is None:
                c.execute(
                    "INSERT INTO factors (factor_id, frame_a, frame_b, payload, status, "
                    "created_at_s, updated_at_s) VALUES (?, ?, ?, ?, ?, ?, ?)",
                    (factor_id, frame_a, frame_b, payload, st.value, now, now),
                )
                return True
        if bytes(row[0]) != payload:
            log.warning("factor %s replayed with different bytes: kept the first", factor_id)
        return False

    def set_factor_status(self, factor_id: str, status: FactorStatus | str) -> bool:
        """Set accepted / retracted; True if the status changed. StoreError if unknown."""
        st = _check_factor_status(status)
        with self._transaction() as c:
            row = c.execute(
                "SELECT status FROM factors WHERE factor_id = ?", (factor_id,)
            ).fetchone()
            if row is None:
                raise StoreError(f"no factor {factor_id!r} in {self.path}")
            if row[0] == st.value:
                return False
            c.execute(
                "UPDATE factors SET status = ?, updated_at_s = ? WHERE factor_id = ?",
                (st.value, self._clock(), factor_id),
            )
            return True

    def iter_factors(self, status: FactorStatus | str | None = None,
                     page: int = 500) -> Iterator[StoredFactor]:
        """The stored factors in creation order, like `factors()`, read `page` rows at a time
        (a restart's factors of a long mission are tens of MB of JSON)."""
        where, args = "", ()
        if status is not None:
            where, args = " AND status = ?", (_check_factor_status(status).value,)
        for r in self._paged("SELECT rowid, factor_id, frame_a, frame_b, payload, status, "
                             f"created_at_s, updated_at_s FROM factors WHERE rowid > ?{where}",
                             args, "rowid", page):
            yield StoredFactor(factor_id=r[1], frame_a=r[2], frame_b=r[3],
                               payload=bytes(r[4]), status=FactorStatus(r[5]),
                               created_at_s=float(r[6]), updated_at_s=float(r[7]))

    def factors(self, status: FactorStatus | str | None = None) -> list[StoredFactor]:
        """Stored factors in creation order, optionally only one status."""
        return list(self.iter_factors(status))

    def put_held_factor(self, factor_id: str, frame_a: str, frame_b: str,
                        payload_bytes: bytes) -> bool:
        """Keep a factor the service does not trust (yet): not sent, or withdrawn; True if
        new. It keeps its first creation time across holds."""
        factor_id = _check_id(factor_id, "factor_id")
        args = (factor_id, _check_id(frame_a, "frame_a"), _check_id(frame_b, "frame_b"),
                _check_bytes(payload_bytes, "payload_bytes"))
        with self._transaction() as c:
            first = c.execute("SELECT created_at_s FROM factors WHERE factor_id = ?",
                              (factor_id,)).fetchone()
            cur = c.execute("INSERT OR IGNORE INTO held_factors (factor_id, frame_a, frame_b, "
                            "payload, created_at_s) VALUES (?, ?, ?, ?, ?)",
                            (*args, first[0] if first else self._clock()))
            return cur.rowcount == 1

    def drop_held_factor(self, factor_id: str) -> bool:
        """A held factor is trusted now (or gone); True if it was held."""
        with self._transaction() as c:
            cur = c.execute("DELETE FROM held_factors WHERE factor_id = ?", (factor_id,))
            return cur.rowcount == 1

    def held_factors(self) -> list[StoredFactor]:
        """The held factors in creation order (status: retracted, as none is in force)."""
        with self._transaction(write=False) as c:
            present = c.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = "
                                "'held_factors'").fetchone()
            rows = c.execute("SELECT factor_id, frame_a, frame_b, payload, created_at_s FROM "
                             "held_factors ORDER BY created_at_s, rowid").fetchall() if present \
                else []
        return [StoredFactor(factor_id=r[0], frame_a=r[1], frame_b=r[2], payload=bytes(r[3]),
                             status=FactorStatus.RETRACTED, created_at_s=float(r[4]),
                             updated_at_s=float(r[4])) for r in rows]

    # -- frames ----------------------------------------------------------------------------------

    def answered(self, row_ids: Sequence[int]) -> None:
        """The messages of these committed rows were published."""
        if row_ids:
            with self._transaction() as c:
                c.executemany("DELETE FROM unanswered WHERE row_id = ?",
                              [(int(r),) for r in row_ids])

    def unanswered(self) -> list[tuple[int, bytes]]:
        """(row id, answer) of committed units whose messages may not have gone out (a crash
        between the commit and the publishing), oldest first; none in a read-only old file."""
        with self._transaction(write=False) as c:
            present = c.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = "
                                "'unanswered'").fetchone()
            return [(int(r), bytes(a)) for r, a in c.execute(
                "SELECT row_id, answer FROM unanswered ORDER BY row_id")] if present else []

    def commit_unit(
        self,
        row_id: int,
        status: str,
        detail: str,
        *,
        frame: tuple[str, str, float] | None = None,
        sent: Sequence[tuple[str, str, str, bytes]] = (),
        withdrawn: Sequence[str] = (),
        held: Sequence[tuple[str, str, str, bytes]] = (),
        anchor: str | None = None,
        answer: bytes | None = None,
    ) -> None:
        """One submap's unit of work in one transaction: its row's final status, its frame
        (robot, session, seen at), the factors it sent (id, frame a, frame b, payload: stored
        accepted, no longer held), withdrew (retracted) or holds, and the fleet's anchor if
        it is the first. Nothing is written unless all of it is."""
        now = self._clock()
        with self._transaction() as c:
            cur = c.execute("UPDATE submaps SET status = ?, detail = ?, processed_at_s = ? "
                            "WHERE id = ? AND status = ?",
                            (str(status), str(detail), now, int(row_id), PENDING))
            if cur.rowcount != 1:
                raise StoreError(f"submap row {row_id} is not pending in {self.path}")
            if frame is not None:
                self._touch_frame(c, frame_name(frame[0], frame[1]), frame[0], frame[1],
                                  frame[2])
            if answer is not None:  # its messages, until `answered` says they went out
                c.execute("INSERT OR REPLACE INTO unanswered (row_id, answer) VALUES (?, ?)",
                          (int(row_id), _check_bytes(answer, "answer")))
            for fid, fa, fb, payload in sent:
                c.execute("INSERT OR IGNORE INTO factors (factor_id, frame_a, frame_b, payload, "
                          "status, created_at_s, updated_at_s) VALUES (?, ?, ?, ?, ?, ?, ?)",
                          (_check_id(fid, "factor_id"), fa, fb, _check_bytes(payload, "payload"),
                           FactorStatus.ACCEPTED.value, now, now))
                c.execute("UPDATE factors SET status = ?, updated_at_s = ? WHERE factor_id = ?",
                          (FactorStatus.ACCEPTED.value, now, fid))
                c.execute("DELETE FROM held_factors WHERE factor_id = ?", (fid,))
            for fid in withdrawn:
                c.execute("UPDATE factors SET status = ?, updated_at_s = ? WHERE factor_id = ?",
                          (FactorStatus.RETRACTED.value, now, fid))
            for fid, fa, fb, payload in held:
                first = c.execute("SELECT created_at_s FROM factors WHERE factor_id = ?",
                                  (fid,)).fetchone()
                c.execute("INSERT OR IGNORE INTO held_factors (factor_id, frame_a, frame_b, "
                          "payload, created_at_s) VALUES (?, ?, ?, ?, ?)",
                          (_check_id(fid, "factor_id"), fa, fb,
                           _check_bytes(payload, "payload"), first[0] if first else now))
            if anchor is not None:
                c.execute("INSERT OR IGNORE INTO meta (key, value) VALUES (?, ?)",
                          (META_ANCHOR, anchor))


__all__ = ["FactorRecords"]
