"""What the service answered as final, kept beside the store: the last seq per session whose
result was sent (a JSON line appended and fsynced per answer, in `{store}.acks`). A store that
loses committed rows (a truncated WAL file rolls back to the last intact commit, silently) is
caught at start: `lost` names every session the store holds less of than was answered.
"""

from __future__ import annotations

import json
import logging
import os
import threading
from pathlib import Path

from mergesvc.errors import StoreError, one_line

log = logging.getLogger(__name__)
COMPACT_EVERY = 10_000  # lines appended before the file is rewritten with one line a session


class AckLedger:
    """The last answered seq per (robot, session); `path` None keeps it in memory only."""

    def __init__(self, path: Path | str | None) -> None:
        self.path = None if path is None else Path(path)
        self._last: dict[tuple[str, str], int] = {}
        self._lines = 0
        self._lock = threading.Lock()
        if self.path is not None and self.path.exists():
            self._read()

    def _read(self) -> None:
        assert self.path is not None
        for n, line in enumerate(self.path.read_text(encoding="utf-8").splitlines(), 1):
            try:
                robot, session, seq = json.loads(line)
                key = (str(robot), str(session))
                self._last[key] = max(int(seq), self._last.get(key, -1))
            except (ValueError, TypeError) as exc:  # a torn last line: the append was cut
                log.warning("%s line %d unreadable (%s): skipped", self.path, n, one_line(exc))
            self._lines += 1

    def last(self) -> dict[tuple[str, str], int]:
        with self._lock:
            return dict(self._last)

    def record(self, robot: str, session: str, seq: int) -> None:
        """An answer was sent for this seq; durable before it returns (fsync)."""
        key = (robot, session)
        with self._lock:
            if seq <= self._last.get(key, -1):
                return
            self._last[key] = seq
            if self.path is None:
                return
            try:
                if self._lines >= COMPACT_EVERY:
                    self._rewrite()
                with self.path.open("a", encoding="utf-8") as fh:
                    fh.write(json.dumps([robot, session, seq]) + "\n")
                    fh.flush()
                    os.fsync(fh.fileno())
                self._lines += 1
            except OSError as exc:
                raise StoreError(f"cannot record an answer in {self.path}: {one_line(exc)}"
                                 ) from exc

    def _rewrite(self) -> None:
        assert self.path is not None
        tmp = self.path.with_name(self.path.name + ".tmp")
        with tmp.open("w", encoding="utf-8") as fh:
            for (robot, session), seq in self._last.items():
                fh.write(json.dumps([robot, session, seq]) + "\n")
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, self.path)
        self._lines = len(self._last)

    def lost(self, stored: dict[tuple[str, str], int]) -> list[str]:
        """One line per session whose answered seq the store does not reach (`stored`: the
        highest final seq the store holds per session)."""
        out = []
        for (robot, session), seq in sorted(self.last().items()):
            have = stored.get((robot, session), -1)
            if have < seq:
                out.append(f"{robot}/{session}: submaps answered up to seq {seq}, the store "
                           f"holds up to {have}" + (": every one lost" if have < 0 else
                                                     f": seqs {have + 1}-{seq} may be lost"))
        return out


__all__ = ["AckLedger"]
