"""The live view's feed from the network: what `mergesvc view` hears on a fleet's keys.

    submap/**   every vehicle's submaps, each once, with what the vehicles' publication
                caches hold for a view that joins late or reconnects (the service's own
                recovering subscription, fleet/zenoh_transport.py)
    factor/**   every factor the service sends, accepted and retracted (each comes once per
                robot of the factor; the scene keeps one)
    status      the service's queryable, polled: merged keyframe poses, anchor, latency

Decoding needs the fleet projection for compact submaps (`projections`); a message that does
not decode is counted and logged, never fatal.
"""

from __future__ import annotations

import contextlib
import json
import logging
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from mergesvc.core.model import Factor, Submap
from mergesvc.errors import MergeError
from mergesvc.fleet.transport import Sample
from mergesvc.fleet.zenoh_transport import ZenohTransport
from mergesvc.view.live import LiveView
from mergesvc.wire import Projection, decode_message, keys

log = logging.getLogger(__name__)


@dataclass
class FeedStats:
    submaps: int = 0
    factors: int = 0
    statuses: int = 0
    undecodable: int = 0


class ZenohFeed:
    """Feeds a LiveView from a fleet's keys on an open Zenoh session (the caller owns the
    session). `start()` subscribes and starts polling the status every `status_period_s`;
    `close()` stops both (idempotent)."""

    def __init__(self, view: LiveView, session: Any, fleet: str,
                 projections: Sequence[Projection] = (), status_period_s: float = 1.0,
                 status_timeout_s: float = 2.0) -> None:
        self.view = view
        self.session = session
        self.root = keys.fleet_root(fleet)
        self.projections = {p.id: p for p in projections}
        self.status_period_s = status_period_s
        self.status_timeout_s = status_timeout_s
        self.stats = FeedStats()
        self._entities: list[Any] = []
        self._stop = threading.Event()
        self._poller: threading.Thread | None = None
        self._warned: set[str] = set()

    def start(self) -> ZenohFeed:
        transport = ZenohTransport(self.session)
        self._entities = [
            transport.subscribe(keys.all_submaps(self.root), self._on_submap, recover=True),
            transport.subscribe(keys.all_factors(self.root), self._on_factor),
        ]
        self._poller = threading.Thread(target=self._poll, name="mergesvc-view-status",
                                        daemon=True)
        self._poller.start()
        return self

    def close(self) -> None:
        import zenoh

        self._stop.set()
        if self._poller is not None:
            self._poller.join(timeout=self.status_timeout_s + 5.0)
            self._poller = None
        for ent in self._entities:
            with contextlib.suppress(zenoh.ZError):  # undeclared already, with its session
                ent.close()
        self._entities = []

    def __enter__(self) -> ZenohFeed:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def poll_status(self) -> dict[str, Any] | None:
        """Ask the service for its status once; hand it to the view. None: no answer."""
        import zenoh

        try:
            replies = self.session.get(keys.status_key(self.root), timeout=self.status_timeout_s)
            for reply in replies:
                if reply.ok is None:
                    continue
                status = json.loads(reply.ok.payload.to_bytes())
                self.stats.statuses += 1
                self.view.on_status(status)
                return status
        except (zenoh.ZError, ValueError) as exc:  # closed session, or not JSON
            self._warn("status", f"status query failed: {exc}")
        return None

    def _poll(self) -> None:
        while not self._stop.is_set():
            self.poll_status()
            self._stop.wait(self.status_period_s)

    def _decode(self, sample: Sample) -> Any:
        try:
            return decode_message(sample.payload, self.projections)[1]
        except MergeError as exc:
            self.stats.undecodable += 1
            self._warn(type(exc).__name__, f"undecodable message on {sample.key}: {exc} "
                       "(compact submaps need --projection)")
            return None

    def _on_submap(self, sample: Sample) -> None:
        sub = self._decode(sample)
        if isinstance(sub, Submap):
            self.stats.submaps += 1
            self._guard(self.view.on_submap, sub)

    def _on_factor(self, sample: Sample) -> None:
        factor = self._decode(sample)
        if isinstance(factor, Factor):
            self.stats.factors += 1
            self._guard(self.view.on_factor, factor)

    def _guard(self, fn: Any, msg: Any) -> None:
        # Last resort of a Zenoh callback: a message the view cannot draw (a bug, or geometry
        # GTSAM refuses) is logged with its traceback and skipped; the view goes on.
        try:
            fn(msg)
        except Exception:
            log.exception("view: could not draw a %s", type(msg).__name__)

    def _warn(self, kind: str, text: str) -> None:
        if kind not in self._warned:  # once per kind: a stream of them says nothing more
            self._warned.add(kind)
            log.warning("view: %s", text)


def observer(view: LiveView, status_period_s: float = 1.0) -> Any:
    """For `run_demo(..., attach=...)` (fleet/demo.py, which may not import this layer):
    `attach(session, fleet, projection_file)` starts a ZenohFeed of `view` on the demo's
    session and returns `detach()`, which polls the status once more (the recording ends with
    the merged state), stops the feed and closes the view."""

    def attach(session: Any, fleet: str, projection_file: Any) -> Any:
        projections = [Projection.load(projection_file)] if projection_file else []
        feed = ZenohFeed(view, session, fleet, projections,
                         status_period_s=status_period_s).start()

        def detach() -> None:
            try:
                feed.poll_status()
                feed.close()
            finally:
                view.close()

        return detach

    return attach
__all__ = ["FeedStats", "ZenohFeed", "observer"]
