"""A committed unit's messages until they went out. Each unit of work stores, in its own
transaction, what it will publish (its result, the factors it sends and withdraws); once they
are published the row is marked answered (in batches). A restart publishes the messages of
every unit a crash left between its commit and that mark: the same result and factors once
more at most, which receivers take as a repeat (docs/wire.md §11.2)."""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Callable
from typing import Any

from mergesvc.core.model import Factor, FactorStatus
from mergesvc.errors import StoreError, one_line
from mergesvc.fleet.replies import SubmapResult

log = logging.getLogger(__name__)


def answer_of(result: SubmapResult, sent: list[Factor], withdrawn: list[Factor]) -> bytes:
    """What a unit publishes, as the store keeps it until it went out."""
    return json.dumps({"result": result.model_dump(mode="json"),
                       "sent": [f.factor_id for f in sent],
                       "withdrawn": [f.factor_id for f in withdrawn]}).encode()


class Answered:
    """Rows whose messages went out, marked in the store a batch at a time."""

    def __init__(self, store: Any) -> None:
        self.store = store
        self._rows: list[int] = []
        self._lock = threading.Lock()

    def add(self, row_id: int) -> None:
        with self._lock:
            self._rows.append(row_id)

    def flush(self) -> None:
        """Mark the rows answered; a store that cannot write keeps them for the next flush
        (a crash meanwhile publishes them again: allowed)."""
        with self._lock:
            rows, self._rows = self._rows, []
        try:
            self.store.answered(rows)
        except StoreError as exc:
            log.warning("answered rows not marked yet: %s", one_line(exc))
            with self._lock:
                self._rows[:0] = rows

    def republish(self, outbox: Any, factor: Callable[[str], Factor | None]) -> int:
        """After a restart: the messages of every unit not marked answered, in commit order
        (`factor`: a factor id -> the factor as the service holds it). Returns how many."""
        rows = self.store.unanswered()
        for _, blob in rows:
            answer = json.loads(blob)
            for fid in answer["sent"]:
                f = factor(fid)
                if f is not None:
                    outbox.factor(f)
            for fid in answer["withdrawn"]:
                f = factor(fid)
                if f is not None:
                    outbox.factor(f.model_copy(update={"status": FactorStatus.RETRACTED}))
            outbox.result(SubmapResult.model_validate(answer["result"]))
        for row_id, _ in rows:
            self.add(row_id)
        self.flush()
        if rows:
            log.warning("published again the answers of %d submaps a crash left unsent",
                        len(rows))
        return len(rows)


__all__ = ["Answered", "answer_of"]
