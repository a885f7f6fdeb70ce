"""The Zenoh bridge: `AcousticBridge` carries samples between the vehicle key space and the
topside through the link simulator, run in scaled real time.

Also the key mapping (`uplink_key`, `downlink_key`, `route_vehicle`) and the per-sample framing
that crosses the link (`frame_sample`, `unframe_sample`). Keys are built with
mergesvc.wire.keys (`under`, `all_under`, `BRIDGE_DOWNLINK`), as everywhere.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

import numpy as np
import zenoh

from mergesvc.errors import ConfigError, DecodeError, LinkError
from mergesvc.link.config import LinkConfig
from mergesvc.link.simulator import Delivery, LinkSimulator, LossEvent
from mergesvc.wire.keys import BRIDGE_DOWNLINK, all_under, under
from mergesvc.wire.session import open_session

log = logging.getLogger(__name__)


class Direction(str, Enum):
    UPLINK = "uplink"  # vehicle side -> topside
    DOWNLINK = "downlink"  # topside -> vehicle side


def key_suffix(key: str, prefix: str) -> str | None:
    """`key` relative to `prefix` ('a/b/c', 'a' -> 'b/c'); None if `key` is not under it."""
    if key.startswith(prefix + "/") and len(key) > len(prefix) + 1:
        return key[len(prefix) + 1 :]
    return None


def uplink_key(key: str, *, uw_prefix: str, top_prefix: str) -> str | None:
    """Vehicle-side key -> the topside key it is republished on (None: not bridged)."""
    suffix = key_suffix(key, uw_prefix)
    return None if suffix is None else under(top_prefix, suffix)


def downlink_key(key: str, *, uw_prefix: str, top_prefix: str) -> str | None:
    """Topside key -> vehicle-side key (None for keys already on the vehicle side, or foreign)."""
    if key_suffix(key, uw_prefix) is not None or key == uw_prefix:
        return None
    suffix = key_suffix(key, top_prefix)
    return None if suffix is None else under(uw_prefix, suffix)


def route_vehicle(suffix: str, vehicles: Sequence[str]) -> str | None:
    """The vehicle a key is about: its first path segment naming a vehicle ('submap/v2/..')."""
    known = set(vehicles)
    return next((seg for seg in suffix.split("/") if seg in known), None)


def frame_sample(suffix: str, payload: bytes) -> bytes:
    """What crosses the acoustic link per sample: suffix length (1 byte), key suffix, payload."""
    raw = suffix.encode("utf-8")
    if len(raw) > 255:
        raise LinkError(f"key suffix of {len(raw)} bytes is too long for the acoustic link")
    return bytes([len(raw)]) + raw + payload


def unframe_sample(data: bytes) -> tuple[str, bytes]:
    """Inverse of `frame_sample`."""
    if not data or len(data) < 1 + data[0]:
        raise DecodeError("truncated bridged sample")
    try:
        suffix = data[1 : 1 + data[0]].decode("utf-8")
    except UnicodeDecodeError as exc:
        raise DecodeError("bridged sample key is not UTF-8") from exc
    return suffix, bytes(data[1 + data[0] :])


@dataclass
class BridgeStats:
    received: dict[str, int] = field(default_factory=lambda: {d.value: 0 for d in Direction})
    published: dict[str, int] = field(default_factory=lambda: {d.value: 0 for d in Direction})
    ingress_dropped: dict[str, int] = field(default_factory=lambda: {d.value: 0 for d in Direction})
    lost: dict[str, int] = field(default_factory=lambda: {d.value: 0 for d in Direction})
    unroutable: int = 0
    oversize: int = 0
    publish_errors: int = 0
    link: dict[str, Any] = field(default_factory=dict)


class AcousticBridge:
    """Zenoh node that carries samples between the vehicle key space and the topside through
    the simulated acoustic link, run in scaled real time.

    Uplink: samples on `{uw_prefix}/**` are sent from the vehicle named in the key to `topside`
    and republished on `{top_prefix}/<suffix>`. Downlink: samples on `{top_prefix}/<k>` for each
    `k` in `downlink_keys` (key expressions below the prefix; default keys.BRIDGE_DOWNLINK, every
    factor) go from `topside` to the vehicle named in the key and are republished on
    `{uw_prefix}/<suffix>`. The key suffix travels over the link with the payload; encodings
    and attachments do not. Simulated time runs at `1 / time_scale` times wall time
    (time_scale=0.01: a 3 s packet takes 30 ms). Each direction has a bounded ingress queue
    (drop oldest, counted) in front of the simulator's bounded per-node queues.
    """

    _MAX_WAIT_S = 0.05  # wall-clock cap on one worker sleep, so close() is prompt

    def __init__(
        self,
        config: LinkConfig,
        *,
        uw_prefix: str,
        top_prefix: str,
        downlink_keys: Sequence[str] = BRIDGE_DOWNLINK,
        topside: str = "topside",
        zenoh_config: zenoh.Config | None = None,
        session: zenoh.Session | None = None,
        time_scale: float = 1.0,
        queue_size: int = 64,
        rng: np.random.Generator | None = None,
        seed: int = 0,
        clock: Callable[[], float] = time.monotonic,
        on_lost: Callable[[Direction, str, LossEvent], None] | None = None,
    ) -> None:
        if not time_scale > 0:
            raise ConfigError(f"time_scale must be > 0, got {time_scale}")
        if queue_size < 1:
            raise ConfigError(f"queue_size must be >= 1, got {queue_size}")
        for prefix in (uw_prefix, top_prefix):
            if not prefix or prefix.endswith("/") or "*" in prefix or "$" in prefix:
                raise ConfigError(f"bridge key prefix {prefix!r} must be a plain key expression")
        if topside not in config.tdma.nodes:
            raise ConfigError(f"topside {topside!r} is not in tdma.slot_order")
        self.uw_prefix, self.top_prefix, self.topside = uw_prefix, top_prefix, topside
        self.vehicles = [n for n in config.tdma.nodes if n != topside]
        self.time_scale = time_scale
        self._queue_size = queue_size
        self._clock = clock
        self._on_lost_cb = on_lost
        self._stats = BridgeStats()
        self._outbox: list[tuple[Direction, str, bytes]] = []
        self._sim = LinkSimulator(
            config,
            rng=rng if rng is not None else np.random.default_rng(seed),
            on_deliver=self._on_deliver,
            on_lost=self._on_lost,
        )
        self._ingress: dict[Direction, collections.deque[tuple[str, bytes]]] = {
            d: collections.deque() for d in Direction
        }
        self._ingress_lock = threading.Lock()
        self._sim_lock = threading.RLock()  # on_lost may call stats() from the worker
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._subscribers: list[Any] = []
        self._thread: threading.Thread | None = None
        self._owns_session = session is None
        self._session: zenoh.Session | None = session
        self._closed = False
        self._t0 = clock()
        try:
            if self._session is None:
                self._session = open_session(
                    zenoh_config if zenoh_config is not None else zenoh.Config()
                )
            remote = zenoh.Locality.REMOTE  # never re-bridge what this session republished
            self._subscribers.append(
                self._session.declare_subscriber(
                    all_under(uw_prefix), self._uplink_sample, allowed_origin=remote
                )
            )
            for k in downlink_keys:
                self._subscribers.append(
                    self._session.declare_subscriber(
                        under(top_prefix, k), self._downlink_sample, allowed_origin=remote
                    )
                )
            self._thread = threading.Thread(target=self._run, name="acoustic-bridge", daemon=True)
            self._thread.start()
        except zenoh.ZError as exc:
            self.close()
            raise LinkError(f"acoustic bridge could not start: {exc}") from exc
        except BaseException:
            self.close()
            raise
        log.info(
            "acoustic bridge %s <-> %s (rate %d, time_scale %g, vehicles %s)",
            all_under(uw_prefix),
            all_under(top_prefix),
            config.channel.rate.value,
            time_scale,
            ",".join(self.vehicles),
        )

    def __enter__(self) -> AcousticBridge:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def sim_now_s(self) -> float:
        """Current simulated time: wall time since start divided by `time_scale`."""
        return (self._clock() - self._t0) / self.time_scale

    def stats(self) -> BridgeStats:
        """A snapshot of the counters (the link's as `LinkStats.summary()`)."""
        with self._sim_lock, self._ingress_lock:
            snap = BridgeStats(
                received=dict(self._stats.received),
                published=dict(self._stats.published),
                ingress_dropped=dict(self._stats.ingress_dropped),
                lost=dict(self._stats.lost),
                unroutable=self._stats.unroutable,
                oversize=self._stats.oversize,
                publish_errors=self._stats.publish_errors,
                link=self._sim.stats.summary(),
            )
        return snap

    def close(self) -> None:
        """Stop the worker, undeclare subscribers, close the session if this bridge opened it.

        Messages still crossing the simulated link are dropped.
        """
        if self._closed:
            return
        self._closed = True
        for sub in self._subscribers:
            try:
                sub.undeclare()
            except zenoh.ZError as exc:
                log.debug("undeclare failed: %s", exc)
        self._subscribers.clear()
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            if self._thread.is_alive():
                log.warning("acoustic bridge worker did not stop within 5 s")
        if self._owns_session and self._session is not None:
            self._session.close()
        s = self._sim.stats
        log.info(
            "acoustic bridge closed: %d delivered, %d lost, %d pending, %d retransmissions",
            s.messages_delivered,
            s.messages_lost,
            self._sim.pending(),
            s.fragments_retransmitted,
        )

    # -- zenoh callbacks (zenoh threads): only enqueue -----------------------------------------

    def _uplink_sample(self, sample: zenoh.Sample) -> None:
        self._enqueue(Direction.UPLINK, str(sample.key_expr), sample.payload.to_bytes())

    def _downlink_sample(self, sample: zenoh.Sample) -> None:
        self._enqueue(Direction.DOWNLINK, str(sample.key_expr), sample.payload.to_bytes())

    def _enqueue(self, direction: Direction, key: str, payload: bytes) -> None:
        with self._ingress_lock:
            queue = self._ingress[direction]
            self._stats.received[direction.value] += 1
            if len(queue) >= self._queue_size:
                dropped_key, _ = queue.popleft()
                self._stats.ingress_dropped[direction.value] += 1
                log.warning("%s ingress queue full: dropped %s", direction.value, dropped_key)
            queue.append((key, payload))
        self._wake.set()

    # -- worker thread: owns the simulator -------------------------------------------------

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                self._wake.clear()
                with self._ingress_lock:
                    items = [(d, *item) for d in Direction for item in self._ingress[d]]
                    for queue in self._ingress.values():
                        queue.clear()
                with self._sim_lock:
                    now_s = self.sim_now_s()
                    self._sim.run_until(now_s)  # catch up before offering at `now_s`
                    for direction, key, payload in items:
                        self._offer(direction, key, payload)
                    self._sim.run_until(now_s)
                    outbox, self._outbox = self._outbox, []
                    next_s = self._sim.next_event_s()
                self._publish(outbox)
                wait_s = (next_s - self.sim_now_s()) * self.time_scale
                self._wake.wait(min(max(wait_s, 0.0), self._MAX_WAIT_S))
        except Exception:
            log.exception("acoustic bridge worker failed; bridge stopped")

    def _offer(self, direction: Direction, key: str, payload: bytes) -> None:
        if direction is Direction.UPLINK:
            suffix = key_suffix(key, self.uw_prefix)
            vehicle = None if suffix is None else route_vehicle(suffix, self.vehicles)
            src, dst = vehicle, self.topside
        else:
            top = downlink_key(key, uw_prefix=self.uw_prefix, top_prefix=self.top_prefix)
            suffix = None if top is None else key_suffix(key, self.top_prefix)
            vehicle = None if suffix is None else route_vehicle(suffix, self.vehicles)
            src, dst = self.topside, vehicle
        if suffix is None or vehicle is None:
            self._stats.unroutable += 1
            log.warning("%s sample %s names no known vehicle: not bridged", direction.value, key)
            return
        try:
            data = frame_sample(suffix, payload)
            self._sim.offer(src, dst, data)
        except LinkError as exc:
            self._stats.oversize += 1
            log.warning("%s sample %s not bridged: %s", direction.value, key, exc)

    def _on_deliver(self, delivery: Delivery) -> None:
        suffix, payload = unframe_sample(delivery.payload)
        if delivery.dst == self.topside:
            self._outbox.append((Direction.UPLINK, under(self.top_prefix, suffix), payload))
        else:
            self._outbox.append((Direction.DOWNLINK, under(self.uw_prefix, suffix), payload))

    def _on_lost(self, event: LossEvent) -> None:
        direction = Direction.UPLINK if event.dst == self.topside else Direction.DOWNLINK
        self._stats.lost[direction.value] += 1
        try:
            suffix, _ = unframe_sample(event.payload)
        except DecodeError:
            suffix = "?"
        log.warning(
            "acoustic link lost %s %s -> %s %s (%s)",
            direction.value,
            event.src,
            event.dst,
            suffix,
            event.reason.value,
        )
        if self._on_lost_cb is not None:
            self._on_lost_cb(direction, suffix, event)

    def _publish(self, outbox: list[tuple[Direction, str, bytes]]) -> None:
        session = self._session
        if session is None:  # closed while the worker held this outbox: nothing to send on
            return
        for direction, key, payload in outbox:
            try:
                session.put(key, payload)
            except zenoh.ZError as exc:
                with self._sim_lock:
                    self._stats.publish_errors += 1
                log.warning("republishing %s failed: %s", key, exc)
                continue
            with self._sim_lock:
                self._stats.published[direction.value] += 1


__all__ = [
    "AcousticBridge",
    "BridgeStats",
    "Direction",
    "downlink_key",
    "frame_sample",
    "key_suffix",
    "route_vehicle",
    "unframe_sample",
    "uplink_key",
]
