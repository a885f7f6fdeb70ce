"""The service's Transport over a Zenoh session (the only fleet module that names zenoh).

`subscribe(recover=True)` declares two subscribers on the key expression: the zenoh.ext
advanced one (history and recovery: the samples of advanced publishers, live or recovered from
their caches, and the timestamped ones it recovers from a cache-only publisher) and a plain one
(every other sample: a plain `put`, whose timestamp order across clients the advanced one may
not keep). Each sample reaches the callback once: a timestamped, unsequenced sample both get is
passed on by whichever sees it first (the last SEEN_SAMPLES remembered).

A publisher that (re)appears after the subscriber (a restart the robots reconnect to late) has
its whole cache asked for here, not by zenoh.ext's late-publisher detection: zenoh.ext delivers
the first live sample of a source it has no state for at once and then drops every older
recovered one as a duplicate, so a put racing the reconnection lost the backlog. The sweep's
samples are passed on in any order and more than once: the store keeps each (robot, session,
seq) once and takes a replay for free.
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
log = logging.getLogger(__name__)


class _Handles:
    def __init__(self, *entities: Any) -> None:
        self._entities = entities

    def close(self) -> None:
        for ent in self._entities:
            with contextlib.suppress(zenoh.ZError):  # undeclared already, with its session
                ent.undeclare()


class ZenohTransport:
    """A Transport on an open zenoh.Session (not closed here: its owner closes it)."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session
        self._seen: dict[tuple[str, str], None] = {}
        self._seen_lock = threading.Lock()

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
            if sample.source_info is not None or (
                    sample.timestamp is not None and self._first_delivery(sample)):
                deliver(sample)

        def unsequenced(sample: Any) -> None:
            if sample.source_info is None and (
                    sample.timestamp is None or self._first_delivery(sample)):
                deliver(sample)

        within = zenoh.KeyExpr(key_expr)

        def swept(reply: Any) -> None:
            if reply.ok is not None and within.intersects(reply.ok.key_expr):
                sequenced(reply.ok)

        def sweep(token: Any) -> None:
            """A publisher's cache, all of it (replies come on the publication key)."""
            if token.kind == zenoh.SampleKind.PUT:
                with contextlib.suppress(zenoh.ZError):  # the session is closing
                    self.session.get(str(token.key_expr), swept,
                                     consolidation=zenoh.ConsolidationMode.NONE,
                                     accept_replies=zenoh.ReplyKeyExpr.ANY)

        return _Handles(
            declare_advanced_subscriber(
                self.session, key_expr, sequenced,
                history=HistoryConfig(detect_late_publishers=False, max_samples=10_000),
                recovery=RecoveryConfig(heartbeat=True), subscriber_detection=True),
            self.session.declare_subscriber(key_expr, unsequenced),
            self.session.liveliness().declare_subscriber(
                keys.advanced_publishers(key_expr), sweep, history=True))

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
