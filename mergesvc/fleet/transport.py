"""The service's view of the network: publish, subscribe, answer queries, watch liveliness.

`Transport` is the whole interface the service uses; `ZenohTransport` (fleet/zenoh_transport.py)
is the real one, `InProcessTransport` here delivers within one process (tests and benchmarks:
no sockets, same semantics for the service: each sample once, in order, queries answered by
the handler's return value). Key expressions follow Zenoh's: `*` one chunk, `**` any number.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol


@dataclass(frozen=True)
class Sample:
    """A published value as a subscriber gets it."""

    key: str
    payload: bytes
    encoding: str = ""


@dataclass(frozen=True)
class Reply:
    """A query's answer: ok (payload, encoding) or an error (payload: an ErrorMessage)."""

    payload: bytes
    encoding: str
    ok: bool = True


@dataclass(frozen=True)
class Query:
    key: str
    parameters: dict[str, str] = field(default_factory=dict)
    payload: bytes | None = None


class Handle(Protocol):
    def close(self) -> None: ...


class Transport(Protocol):
    """What the merge service needs of a network."""

    def put(self, key: str, payload: bytes, encoding: str) -> None:
        """Publish one value (best effort: errors are TransportError)."""

    def subscribe(self, key_expr: str, callback: Callable[[Sample], None],
                  recover: bool = False) -> Handle:
        """Deliver every sample on key_expr once; `recover`: also those publishers with a
        cache sent before this subscriber was there (late joiners, a restart)."""

    def queryable(self, key_expr: str, handler: Callable[[Query], Reply]) -> Handle:
        """Answer queries on key_expr with handler's reply."""

    def liveliness(self, key_expr: str, callback: Callable[[str, bool], None]) -> Handle:
        """callback(key, alive) for every liveliness token on key_expr, present ones first."""


def key_matches(key_expr: str, key: str) -> bool:
    """Whether `key` (no wildcards) is in `key_expr` (`*`: one chunk, `**`: zero or more)."""
    pat, parts = key_expr.split("/"), key.split("/")

    def match(i: int, j: int) -> bool:
        if i == len(pat):
            return j == len(parts)
        if pat[i] == "**":
            return any(match(i + 1, k) for k in range(j, len(parts) + 1))
        return j < len(parts) and pat[i] in ("*", parts[j]) and match(i + 1, j + 1)

    return match(0, 0)


class _Registration:
    def __init__(self, owner: InProcessTransport, table: list, entry: object) -> None:
        self._owner, self._table, self._entry = owner, table, entry

    def close(self) -> None:
        with self._owner._lock:
            if self._entry in self._table:
                self._table.remove(self._entry)


class InProcessTransport:
    """A Transport inside one process: puts call the matching subscribers in the caller's
    thread (in order), queries call the queryable's handler, `declare_token` / `drop_token`
    stand in for liveliness. `history` keeps every put so a `recover` subscriber gets what was
    published before it (an advanced publisher's cache)."""

    def __init__(self) -> None:
        self._lock = threading.RLock()
        self._subs: list[tuple[str, Callable[[Sample], None]]] = []
        self._queryables: list[tuple[str, Callable[[Query], Reply]]] = []
        self._live: list[tuple[str, Callable[[str, bool], None]]] = []
        self._tokens: set[str] = set()
        self.history: list[Sample] = []

    def put(self, key: str, payload: bytes, encoding: str = "") -> None:
        sample = Sample(key, bytes(payload), encoding)
        with self._lock:
            self.history.append(sample)
            subs = [cb for expr, cb in self._subs if key_matches(expr, key)]
        for cb in subs:
            cb(sample)

    def subscribe(self, key_expr: str, callback: Callable[[Sample], None],
                  recover: bool = False) -> Handle:
        with self._lock:
            entry = (key_expr, callback)
            self._subs.append(entry)
            past = [s for s in self.history if key_matches(key_expr, s.key)] if recover else []
        for s in past:
            callback(s)
        return _Registration(self, self._subs, entry)

    def queryable(self, key_expr: str, handler: Callable[[Query], Reply]) -> Handle:
        with self._lock:
            entry = (key_expr, handler)
            self._queryables.append(entry)
        return _Registration(self, self._queryables, entry)

    def get(self, key: str, parameters: dict[str, str] | None = None,
            payload: bytes | None = None) -> list[Reply]:
        """A query, as a client sends it: every matching queryable's reply."""
        with self._lock:
            handlers = [h for expr, h in self._queryables if key_matches(expr, key)]
        return [h(Query(key, dict(parameters or {}), payload)) for h in handlers]

    def liveliness(self, key_expr: str, callback: Callable[[str, bool], None]) -> Handle:
        with self._lock:
            entry = (key_expr, callback)
            self._live.append(entry)
            present = sorted(t for t in self._tokens if key_matches(key_expr, t))
        for t in present:
            callback(t, True)
        return _Registration(self, self._live, entry)

    def declare_token(self, key: str) -> None:
        self._token(key, True)

    def drop_token(self, key: str) -> None:
        self._token(key, False)

    def _token(self, key: str, alive: bool) -> None:
        with self._lock:
            (self._tokens.add if alive else self._tokens.discard)(key)
            cbs = [cb for expr, cb in self._live if key_matches(expr, key)]
        for cb in cbs:
            cb(key, alive)


__all__ = ["Handle", "InProcessTransport", "Query", "Reply", "Sample", "Transport",
           "key_matches"]
