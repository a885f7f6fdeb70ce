"""Discrete-event link simulator: TDMA slots and selective-repeat ARQ on a simulated clock.

`LinkSimulator` moves whole messages between nodes sharing one `AcousticChannel`, and reports
each as a `Delivery` or a `LossEvent` (with its `LossReason`); `LinkStats` counts what happened.
"""

from __future__ import annotations

import collections
import heapq
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

import numpy as np

from mergesvc.errors import ConfigError, DecodeError, LinkError
from mergesvc.link.arq import (
    ACK_ENTRY_HEADER_BYTES,
    CRC16_BYTES,
    MINIFRAME_BYTES,
    MSG_ID_MODULO,
    AckEntry,
    ack_entry,
    decode_ack,
    decode_fragment,
    encode_ack,
    encode_fragment,
    join_fragments,
    split_message,
)
from mergesvc.link.channel import AcousticChannel
from mergesvc.link.config import LinkConfig

_COMPLETED_WINDOW = 1024  # remembered completed ids per peer (< MSG_ID_MODULO, so ids can wrap)


# --------------------------------------------------------------------------------------------
# Events and statistics
# --------------------------------------------------------------------------------------------


class LossReason(str, Enum):
    RETRIES = "retries"  # a fragment used its whole transmission budget
    TIMEOUT = "timeout"  # older than arq.message_timeout_s
    QUEUE_OVERFLOW = "queue_overflow"  # dropped as the oldest waiting message
    CORRUPT = "corrupt"  # reassembled but failed its CRC-32 (discarded, never delivered)


@dataclass(frozen=True)
class Delivery:
    handle: int
    src: str
    dst: str
    payload: bytes
    offered_s: float
    delivered_s: float

    @property
    def latency_s(self) -> float:
        return self.delivered_s - self.offered_s


@dataclass(frozen=True)
class LossEvent:
    handle: int
    src: str
    dst: str
    payload: bytes
    reason: LossReason
    offered_s: float
    lost_s: float


@dataclass
class LinkStats:
    """Counters of one simulator; bytes are message bytes unless named `on_air`."""

    messages_offered: int = 0
    messages_delivered: int = 0
    messages_lost: int = 0
    lost_by_reason: dict[str, int] = field(default_factory=lambda: {r.value: 0 for r in LossReason})
    bytes_offered: int = 0
    bytes_delivered: int = 0
    bytes_on_air: int = 0
    packets_sent: int = 0
    frames_sent: int = 0
    frames_lost: int = 0
    frames_crc_failed: int = 0
    fragments_retransmitted: int = 0
    duplicates_dropped: int = 0
    acks_sent: int = 0
    acks_lost: int = 0
    reassemblies_expired: int = 0
    give_ups_after_delivery: int = 0
    corrupt_deliveries: int = 0  # ground truth: delivered bytes differ from sent (must stay 0)
    elapsed_s: float = 0.0
    latencies_s: collections.deque[float] = field(
        default_factory=lambda: collections.deque(maxlen=100_000)
    )

    @property
    def delivery_ratio(self) -> float:
        done = self.messages_delivered + self.messages_lost
        return self.messages_delivered / done if done else float("nan")

    @property
    def goodput_bps(self) -> float:
        return 8.0 * self.bytes_delivered / self.elapsed_s if self.elapsed_s > 0 else 0.0

    def latency_percentile_s(self, q: float) -> float:
        return float(np.percentile(self.latencies_s, q)) if self.latencies_s else float("nan")

    def summary(self) -> dict[str, Any]:
        """Plain-JSON view: counters, ratios and latency percentiles."""
        out: dict[str, Any] = {
            k: (dict(v) if isinstance(v, dict) else v)
            for k, v in self.__dict__.items()
            if k != "latencies_s"
        }
        out.update(
            delivery_ratio=self.delivery_ratio,
            goodput_bps=self.goodput_bps,
            latency_p50_s=self.latency_percentile_s(50),
            latency_p90_s=self.latency_percentile_s(90),
            latency_max_s=max(self.latencies_s, default=float("nan")),
        )
        return out


# --------------------------------------------------------------------------------------------
# Discrete-event simulator: TDMA + selective-repeat ARQ
# --------------------------------------------------------------------------------------------


@dataclass(eq=False)
class _Outgoing:
    handle: int
    src: str
    dst: str
    payload: bytes
    offered_s: float
    msg_id: int = -1
    frames: list[bytes] = field(default_factory=list)
    acked: list[bool] = field(default_factory=list)
    tx_count: list[int] = field(default_factory=list)
    arrival_s: list[float] = field(default_factory=list)  # when the last copy reaches dst
    delivered: bool = False
    lost: bool = False


@dataclass
class _Reassembly:
    count: int
    first_s: float
    parts: dict[int, bytes] = field(default_factory=dict)


@dataclass
class _RxState:
    partial: dict[int, _Reassembly] = field(default_factory=dict)
    completed: collections.OrderedDict[int, float] = field(default_factory=collections.OrderedDict)
    ack_pending: dict[int, None] = field(default_factory=dict)  # insertion-ordered set


@dataclass
class _Node:
    name: str
    queue: collections.deque[_Outgoing] = field(default_factory=collections.deque)
    in_flight: list[_Outgoing] = field(default_factory=list)
    rx: dict[str, _RxState] = field(default_factory=dict)
    last_slot_s: float = -math.inf


class _Ev(int, Enum):
    # Order at equal times: arrivals, then offers, then slots (an offer at a slot start is sent).
    ARRIVAL = 0
    OFFER = 1
    SLOT = 2


class LinkSimulator:
    """Several nodes sharing one acoustic channel by TDMA, with selective-repeat ARQ.

    Per slot the owner sends one ack mini-frame per peer with pending acks (bitmap of received
    fragments), then one packet of up to `frames` fragments to a single destination: the oldest
    in-flight message's fragments first, retransmissions and new fragments alike. A fragment is
    resent only when its receiver has had a slot (an ack opportunity) since it arrived and has
    not acked it. Messages arrive whole (CRC-32 checked) or are reported lost.
    """

    def __init__(
        self,
        config: LinkConfig,
        *,
        rng: np.random.Generator,
        on_deliver: Callable[[Delivery], None] | None = None,
        on_lost: Callable[[LossEvent], None] | None = None,
        start_s: float = 0.0,
    ) -> None:
        self.config = config
        self.channel = AcousticChannel(config.channel, rng)
        self.spec = self.channel.spec
        self.stats = LinkStats()
        self._on_deliver = on_deliver
        self._on_lost = on_lost
        self._order = config.tdma.slot_order
        self._nodes = {name: _Node(name) for name in config.tdma.nodes}
        self._events: list[tuple[float, int, int, _Ev, Any]] = []
        self._seq = 0
        self._next_handle = 0
        self._next_msg_id: dict[tuple[str, str], int] = {}
        self._by_msg_id: dict[tuple[str, str, int], _Outgoing] = {}
        self._scheduled_offers = 0
        self._start_s = start_s
        self.now_s = start_s
        first_slot = math.ceil(start_s / config.tdma.slot_s - 1e-9)
        self._push(first_slot * config.tdma.slot_s, _Ev.SLOT, first_slot)

    @property
    def nodes(self) -> list[str]:
        return list(self._nodes)

    # -- public API --------------------------------------------------------------------------

    def offer(self, src: str, dst: str, payload: bytes, *, at_s: float | None = None) -> int:
        """Queue `payload` from `src` to `dst` at `at_s` (default now); returns its handle."""
        if src not in self._nodes or dst not in self._nodes or src == dst:
            raise ConfigError(f"unknown or identical link endpoints {src!r} -> {dst!r}")
        if len(payload) > self.config.arq.max_message_bytes:
            raise LinkError(
                f"message of {len(payload)} bytes exceeds the link maximum "
                f"{self.config.arq.max_message_bytes}"
            )
        t = self.now_s if at_s is None else max(at_s, self.now_s)
        msg = _Outgoing(self._next_handle, src, dst, bytes(payload), t)
        self._next_handle += 1
        self._scheduled_offers += 1
        self._push(t, _Ev.OFFER, msg)
        return msg.handle

    def run_until(self, t_s: float) -> None:
        """Process every event up to and including `t_s` on the simulated clock."""
        while self._events and self._events[0][0] <= t_s:
            t, _, _, kind, data = heapq.heappop(self._events)
            self.now_s = t
            if kind is _Ev.ARRIVAL:
                self._on_arrival(*data)
            elif kind is _Ev.OFFER:
                self._enqueue(data)
            else:
                self._on_slot(data)
        self.now_s = max(self.now_s, t_s)
        self.stats.elapsed_s = self.now_s - self._start_s

    def next_event_s(self) -> float:
        return self._events[0][0]

    def pending(self) -> int:
        """Messages offered but neither delivered nor lost yet."""
        n = self._scheduled_offers
        for node in self._nodes.values():
            n += len(node.queue) + sum(not (m.delivered or m.lost) for m in node.in_flight)
        return n

    # -- events ------------------------------------------------------------------------------

    def _push(self, t: float, kind: _Ev, data: Any) -> None:
        heapq.heappush(self._events, (t, int(kind), self._seq, kind, data))
        self._seq += 1

    def _enqueue(self, msg: _Outgoing) -> None:
        self._scheduled_offers -= 1
        node = self._nodes[msg.src]
        self.stats.messages_offered += 1
        self.stats.bytes_offered += len(msg.payload)
        if len(node.queue) >= self.config.arq.max_queue_messages:
            self._lose(node.queue.popleft(), LossReason.QUEUE_OVERFLOW)
        node.queue.append(msg)

    def _on_slot(self, k: int) -> None:
        t = self.now_s
        self._push((k + 1) * self.config.tdma.slot_s, _Ev.SLOT, k + 1)
        node = self._nodes[self._order[k % len(self._order)]]
        self._expire(node, t)
        cursor = self._send_acks(node, t)
        self._send_data(node, cursor)
        node.last_slot_s = t

    def _expire(self, node: _Node, t: float) -> None:
        timeout_s = self.config.arq.message_timeout_s
        for msg in [m for m in (*node.in_flight, *node.queue) if t - m.offered_s > timeout_s]:
            if msg in node.in_flight:
                self._retire(node, msg)
            else:
                node.queue.remove(msg)
            self._lose(msg, LossReason.TIMEOUT)
        for rx in node.rx.values():
            for msg_id, r in list(rx.partial.items()):
                if t - r.first_s > self.config.arq.reassembly_timeout_s:
                    del rx.partial[msg_id]
                    rx.ack_pending.pop(msg_id, None)
                    self.stats.reassemblies_expired += 1

    def _send_acks(self, node: _Node, cursor: float) -> float:
        air_s = self.config.channel.miniframe_airtime_s
        peers = [src for src, rx in node.rx.items() if rx.ack_pending][: self.config.acks_per_slot]
        for src in peers:
            rx = node.rx.pop(src)
            node.rx[src] = rx  # rotate: peers left waiting go first next time
            frame = encode_ack(self._build_ack(rx))
            self.stats.acks_sent += 1
            self.stats.bytes_on_air += len(frame)
            if self.channel.transmit_miniframe(node.name, src):
                arrival = cursor + air_s + self.channel.propagation_delay_s(node.name, src)
                self._push(arrival, _Ev.ARRIVAL, ("ack", node.name, src, frame))
            else:
                self.stats.acks_lost += 1
            cursor += air_s
        return cursor

    def _build_ack(self, rx: _RxState) -> list[AckEntry]:
        room = MINIFRAME_BYTES - CRC16_BYTES
        entries: list[AckEntry] = []
        for msg_id in list(rx.ack_pending):
            if msg_id in rx.completed:
                entry = AckEntry(msg_id=msg_id, complete=True)
            elif msg_id in rx.partial and room > ACK_ENTRY_HEADER_BYTES:
                entry = ack_entry(msg_id, rx.partial[msg_id].parts, room - ACK_ENTRY_HEADER_BYTES)
            elif msg_id in rx.partial:
                break
            else:
                del rx.ack_pending[msg_id]
                continue
            if entry.encoded_bytes > room:
                break
            entries.append(entry)
            room -= entry.encoded_bytes
            del rx.ack_pending[msg_id]
        return entries

    def _promote(self, node: _Node) -> None:
        while node.queue and len(node.in_flight) < self.config.arq.max_in_flight:
            msg = node.queue.popleft()
            link = (msg.src, msg.dst)
            msg.msg_id = self._next_msg_id.get(link, 0)
            self._next_msg_id[link] = (msg.msg_id + 1) % MSG_ID_MODULO
            fragments = split_message(msg.msg_id, msg.payload, self.spec.fragment_payload_bytes)
            msg.frames = [encode_fragment(f) for f in fragments]
            msg.acked = [False] * len(fragments)
            msg.tx_count = [0] * len(fragments)
            msg.arrival_s = [math.inf] * len(fragments)
            self._by_msg_id[(msg.src, msg.dst, msg.msg_id)] = msg
            node.in_flight.append(msg)

    def _retire(self, node: _Node, msg: _Outgoing) -> None:
        # Done sending (fully acked, or given up in the sender's own slot, when none of its
        # frames is still on the way): the receiver can no longer complete it, so forget it.
        node.in_flight.remove(msg)
        key = (msg.src, msg.dst, msg.msg_id)
        if self._by_msg_id.get(key) is msg:
            del self._by_msg_id[key]

    def _eligible(self, msg: _Outgoing) -> list[int]:
        """Unacked fragments never sent, or whose receiver had an ack slot since they arrived."""
        ack_slot_s = self._nodes[msg.dst].last_slot_s
        return [
            i
            for i, acked in enumerate(msg.acked)
            if not acked and (msg.tx_count[i] == 0 or msg.arrival_s[i] <= ack_slot_s)
        ]

    def _send_data(self, node: _Node, cursor: float) -> None:
        max_tx = self.config.arq.max_tx_per_fragment
        for msg in list(node.in_flight):
            if any(msg.tx_count[i] >= max_tx for i in self._eligible(msg)):
                self._retire(node, msg)
                self._lose(msg, LossReason.RETRIES)
        self._promote(node)
        chosen: list[tuple[_Outgoing, int]] = []
        dst: str | None = None
        for msg in node.in_flight:
            if dst is not None and msg.dst != dst:
                continue
            eligible = self._eligible(msg)[: self.spec.frames - len(chosen)]
            chosen.extend((msg, i) for i in eligible)
            if eligible:
                dst = msg.dst
            if len(chosen) == self.spec.frames:
                break
        if dst is None:
            return
        frames = [msg.frames[i] for msg, i in chosen]
        received = self.channel.transmit_packet(node.name, dst, frames)
        arrival = cursor + self.spec.airtime_s + self.channel.propagation_delay_s(node.name, dst)
        self.stats.packets_sent += 1
        self.stats.frames_sent += len(frames)
        self.stats.frames_lost += len(frames) - len(received)
        self.stats.bytes_on_air += self.spec.packet_bytes  # fixed-length packets, padded
        for msg, i in chosen:
            self.stats.fragments_retransmitted += msg.tx_count[i] > 0
            msg.tx_count[i] += 1
            msg.arrival_s[i] = arrival
        if received:
            self._push(arrival, _Ev.ARRIVAL, ("data", node.name, dst, received))

    def _on_arrival(self, kind: str, src: str, dst: str, payload: Any) -> None:
        if kind == "ack":
            self._on_ack(self._nodes[dst], src, payload)
        else:
            self._on_data(self._nodes[dst], src, payload)

    def _on_ack(self, node: _Node, peer: str, frame: bytes) -> None:
        try:
            entries = decode_ack(frame)
        except DecodeError:
            self.stats.frames_crc_failed += 1
            return
        for entry in entries:
            msg = next(
                (m for m in node.in_flight if m.dst == peer and m.msg_id == entry.msg_id), None
            )
            if msg is None:
                continue
            for i in entry.received(len(msg.acked)):
                msg.acked[i] = True
            if all(msg.acked):
                self._retire(node, msg)

    def _on_data(self, node: _Node, src: str, frames: list[bytes]) -> None:
        rx = node.rx.setdefault(src, _RxState())
        for raw in frames:
            try:
                frag = decode_fragment(raw)
            except DecodeError:
                self.stats.frames_crc_failed += 1
                continue
            rx.ack_pending[frag.msg_id] = None
            if frag.msg_id in rx.completed:
                self.stats.duplicates_dropped += 1
                continue
            r = rx.partial.get(frag.msg_id)
            if r is None or r.count != frag.count:
                r = rx.partial[frag.msg_id] = _Reassembly(count=frag.count, first_s=self.now_s)
            if frag.index in r.parts:
                self.stats.duplicates_dropped += 1
                continue
            r.parts[frag.index] = frag.payload
            if len(r.parts) == r.count:
                del rx.partial[frag.msg_id]
                rx.completed[frag.msg_id] = self.now_s
                while len(rx.completed) > _COMPLETED_WINDOW:
                    rx.completed.popitem(last=False)
                self._complete(src, node.name, frag.msg_id, [r.parts[i] for i in range(r.count)])

    def _complete(self, src: str, dst: str, msg_id: int, parts: list[bytes]) -> None:
        msg = self._by_msg_id.get((src, dst, msg_id))
        try:
            message = join_fragments(parts)
        except DecodeError:
            if msg is not None:
                self._lose(msg, LossReason.CORRUPT)
            return
        if msg is None or msg.delivered:
            return  # a stale id reused after the sender gave up: nothing to attribute it to
        msg.delivered = True
        self.stats.messages_delivered += 1
        self.stats.bytes_delivered += len(message)
        self.stats.latencies_s.append(self.now_s - msg.offered_s)
        if message != msg.payload:
            self.stats.corrupt_deliveries += 1
        if self._on_deliver is not None:
            self._on_deliver(Delivery(msg.handle, src, dst, message, msg.offered_s, self.now_s))

    def _lose(self, msg: _Outgoing, reason: LossReason) -> None:
        if msg.delivered:
            # The receiver has it; only the final ack went missing (the sender cannot know).
            self.stats.give_ups_after_delivery += 1
            return
        if msg.lost:
            return
        msg.lost = True
        self.stats.messages_lost += 1
        self.stats.lost_by_reason[reason.value] += 1
        if self._on_lost is not None:
            self._on_lost(
                LossEvent(
                    msg.handle, msg.src, msg.dst, msg.payload, reason, msg.offered_s, self.now_s
                )
            )


__all__ = [
    "Delivery",
    "LinkSimulator",
    "LinkStats",
    "LossEvent",
    "LossReason",
]
