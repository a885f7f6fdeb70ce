"""The service's Transport over a Zenoh session (the only fleet module that names zenoh).

`subscribe(recover=True)` declares two subscribers on the key expression (and one on its
advanced publishers' liveliness tokens, below): the zenoh.ext advanced one (history and
recovery: the samples of advanced publishers, live or recovered from their caches, and the
timestamped ones it recovers from a cache-only publisher) and a plain one
(every other sample: a plain `put`, whose timestamp order across clients the advanced one may
not keep). A timestamped, unsequenced sample both get is passed on by whichever sees it first
(the last SEEN_SAMPLES remembered).

A publisher that (re)appears after the subscriber (a restart the robots reconnect to late) has
its cache asked for here, not by zenoh.ext's late-publisher detection: zenoh.ext delivers the
first live sample of a source it has no state for at once and then drops every older recovered
one as a duplicate, so a put racing the reconnection lost the backlog. The cache is asked from
the first sequence number not yet delivered from that publisher (`_Delivered`: every number
below a mark, and those above it), and a sequenced sample reaches the callback once whichever
way it came (zenoh.ext's history, live, the sweep), in any order.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Callable
from typing import Any

import zenoh

from mergesvc.core.model import ErrorMessage
from mergesvc.errors import TransportError
from mergesvc.fleet.transport import Query, Reply, Sample
from mergesvc.wire import keys

SEEN_SAMPLES = 4096
SOURCES_KEPT = 4096  # advanced publishers whose delivered sequence numbers are remembered
AHEAD_KEPT = 16_384  # numbers kept above a publisher's mark (more than a cache holds)
log = logging.getLogger(__name__)


class _Delivered:
    """Sequence numbers delivered per advanced publisher (zid, eid): all below its mark and
    the set above it. Bounded: SOURCES_KEPT publishers (the oldest forgotten: its replay then
    reaches the store, which keeps each submap once), AHEAD_KEPT numbers above a mark (then the
    mark moves up to the lowest: what is older is gone from any cache)."""

    def __init__(self) -> None:
        self._mark: dict[tuple[str, str], int] = {}
        self._ahead: dict[tuple[str, str], set[int]] = {}
        self._lock = threading.Lock()

    def first(self, source: tuple[str, str], sn: int) -> bool:
        """Whether `sn` of `source` is delivered now for the first time (and record it)."""
        with self._lock:
            mark = self._mark.pop(source, 0)  # re-inserted: the dict's order is by last use
            ahead = self._ahead.pop(source, set())
            new = sn >= mark and sn not in ahead
            if new:
                ahead.add(sn)
                if len(ahead) > AHEAD_KEPT:
                    mark = min(ahead)
                while mark in ahead:
                    ahead.discard(mark)
                    mark += 1
            self._mark[source], self._ahead[source] = mark, ahead
            while len(self._mark) > SOURCES_KEPT:
                oldest = next(iter(self._mark))
                del self._mark[oldest], self._ahead[oldest]
            return new

    def mark(self, source: tuple[str, str]) -> int:
        """The first sequence number of `source` not known to be delivered."""
        with self._lock:
            return self._mark.get(source, 0)


def _source(sample: Any) -> tuple[str, str]:
    sid = sample.source_info.source_id
    return str(sid.zid), str(sid.eid)


class _Handles:
    def __init__(self, *entities: Any, closed: threading.Event | None = None) -> None:
        self._entities = entities
        self.closed = closed or threading.Event()  # set on close: late replies are dropped

    def close(self) -> None:
        self.closed.set()
        for ent in self._entities:
            with contextlib.suppress(zenoh.ZError):  # undeclared already, with its session
                ent.undeclare()


class ZenohTransport:
    """A Transport on an open zenoh.Session (not closed here: its owner closes it)."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session
        self._seen: dict[tuple[str, str], None] = {}
        self._seen_lock = threading.Lock()
        self._delivered = _Delivered()

    def put(self, key: str, payload: bytes, encoding: str) -> None:
        try:
            self.session.put(key, payload, encoding=zenoh.Encoding(encoding))
        except zenoh.ZError as exc:  # a closed session, a key Zenoh refuses
            raise TransportError(f"could not publish on {key}: {exc}") from exc

    def subscribe(self, key_expr: str, callback: Callable[[Sample], None],
                  recover: bool = False) -> _Handles:
        def deliver(sample: Any) -> None:
            callback(Sample(str(sample.key_expr), sample.payload.to_bytes(),
                            str(sample.encoding)))

        if not recover:
            return _Handles(self.session.declare_subscriber(key_expr, deliver))
        from zenoh.ext import HistoryConfig, RecoveryConfig, declare_advanced_subscriber

        def sequenced(sample: Any) -> None:
            if sample.source_info is not None:
                if self._delivered.first(_source(sample), int(sample.source_info.source_sn)):
                    deliver(sample)
            elif sample.timestamp is not None and self._first_delivery(sample):
                deliver(sample)

        def unsequenced(sample: Any) -> None:
            if sample.source_info is None and (
                    sample.timestamp is None or self._first_delivery(sample)):
                deliver(sample)

        within = zenoh.KeyExpr(key_expr)
        closed = threading.Event()

        def swept(reply: Any) -> None:
            if reply.ok is not None and not closed.is_set() and \
                    within.intersects(reply.ok.key_expr):
                sequenced(reply.ok)

        def sweep(token: Any) -> None:
            """A publisher's cache from the first number not delivered yet (replies come on
            the publication key)."""
            if token.kind != zenoh.SampleKind.PUT or closed.is_set():
                return
            source = keys.advanced_publisher_source(str(token.key_expr))
            mark = self._delivered.mark(source) if source is not None else 0
            with contextlib.suppress(zenoh.ZError):  # the session is closing
                self.session.get(f"{token.key_expr}?_sn={mark}..", swept,
                                 consolidation=zenoh.ConsolidationMode.NONE,
                                 accept_replies=zenoh.ReplyKeyExpr.ANY)

        return _Handles(
            declare_advanced_subscriber(
                self.session, key_expr, sequenced,
                history=HistoryConfig(detect_late_publishers=False, max_samples=10_000),
                recovery=RecoveryConfig(heartbeat=True), subscriber_detection=True),
            self.session.declare_subscriber(key_expr, unsequenced),
            self.session.liveliness().declare_subscriber(
                keys.advanced_publishers(key_expr), sweep, history=True), closed=closed)

    def _first_delivery(self, sample: Any) -> bool:
        """Whether this timestamped, unsequenced sample is seen for the first time (both
        subscribers get it live); bounded: the store's (robot, session, seq) catches older
        repeats."""
        seen = (str(sample.key_expr), str(sample.timestamp))
        with self._seen_lock:
            if seen in self._seen:
                return False
            self._seen[seen] = None
            while len(self._seen) > SEEN_SAMPLES:
                self._seen.pop(next(iter(self._seen)))
            return True

    def queryable(self, key_expr: str, handler: Callable[[Query], Reply]) -> _Handles:
        def answer(query: Any) -> None:
            with query:  # a channel-less queryable must finish each query
                payload = query.payload.to_bytes() if query.payload is not None else None
                params = {str(k): str(v) for k, v in dict(query.parameters).items()}
                try:
                    reply = handler(Query(str(query.key_expr), params, payload))
                # last resort: every query gets an answer, a failure in the handler too
                except Exception as exc:
                    log.exception("a query on %s failed", key_expr)
                    doc = ErrorMessage(code="internal", detail=str(exc)[:1000])
                    reply = Reply(doc.model_dump_json().encode(), keys.JSON_ENCODING, ok=False)
                enc = zenoh.Encoding(reply.encoding)
                if reply.ok:
                    query.reply(query.key_expr, reply.payload, encoding=enc)
                else:
                    query.reply_err(reply.payload, encoding=enc)

        return _Handles(self.session.declare_queryable(key_expr, answer))

    def liveliness(self, key_expr: str, callback: Callable[[str, bool], None]) -> _Handles:
        def seen(sample: Any) -> None:
            callback(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)

        return _Handles(self.session.liveliness().declare_subscriber(key_expr, seen,
                                                                     history=True))


__all__ = ["SEEN_SAMPLES", "ZenohTransport"]
