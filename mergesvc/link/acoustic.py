"""Acoustic link: WHOI Micro-Modem channel, selective-repeat ARQ over TDMA, and a Zenoh bridge.

Frame error rate vs SNR follows the published Micro-Modem curves (as tabulated in WHOI ros_acomms),
interpolated linearly in dB; a packet is cut at its first bad frame.

Layers, bottom up: `AcousticChannel` (rates, airtime, propagation, frame losses) ->
fragment/ack wire format (`encode_fragment`, `encode_ack`) -> `LinkSimulator` (TDMA slots,
selective-repeat ARQ, discrete events on a simulated clock) -> `AcousticBridge` (the simulator
run in scaled real time between two Zenoh key spaces). `simulate_workload` and `sweep_link` are
the benchmark drivers.
"""

from __future__ import annotations

import binascii
import collections
import functools
import heapq
import importlib.resources
import json
import logging
import math
import threading
import time
import zlib
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

import numpy as np
import zenoh
from pydantic import BaseModel, ConfigDict, Field, model_validator

from mergesvc.errors import ConfigError, DecodeError, LinkError

logger = logging.getLogger(__name__)

SOUND_SPEED_MPS = 1500.0
MINIFRAME_BYTES = 96
"""Largest mini-frame (used for acks)."""
FRAGMENT_HEADER_BYTES = 6
"""Per-frame header: msg id (12 bit) | fragment index (10 bit) | last index (10 bit), CRC-16."""
MESSAGE_TRAILER_BYTES = 4
"""CRC-32 of the whole message, appended before fragmentation."""
MSG_ID_MODULO = 1 << 12
MAX_FRAGMENTS = 1 << 10
MAX_MESSAGE_BYTES = 65536
"""Largest message the ARQ layer accepts (bytes, before the CRC-32 trailer)."""
_COMPLETED_WINDOW = 1024  # remembered completed ids per peer (< MSG_ID_MODULO, so ids can wrap)
_ACK_ENTRY_HEADER_BYTES = 5  # msg id + flags (2), base (2), bitmap length (1)
_ACK_COMPLETE_BYTES = 2
_CRC16_BYTES = 2
_FLAG_COMPLETE = 0x1


# --------------------------------------------------------------------------------------------
# Modem rates and frame error rate
# --------------------------------------------------------------------------------------------


class ModemRate(int, Enum):
    """Micro-Modem PSK packet rates modelled here."""

    RATE1 = 1
    RATE3 = 3
    RATE5 = 5


@dataclass(frozen=True)
class RateSpec:
    """Packet geometry of one modem rate: fixed-length packets of `frames` equal frames."""

    packet_bytes: int
    frames: int
    airtime_s: float

    @property
    def frame_bytes(self) -> int:
        """Bytes per frame (rate 5: 2048 // 7 = 292, so 2044 of the 2048 bytes are usable)."""
        return self.packet_bytes // self.frames

    @property
    def fragment_payload_bytes(self) -> int:
        """Message bytes carried by one frame after the fragment header."""
        return self.frame_bytes - FRAGMENT_HEADER_BYTES


RATE_SPECS: dict[ModemRate, RateSpec] = {
    ModemRate.RATE1: RateSpec(packet_bytes=192, frames=2, airtime_s=3.07),
    ModemRate.RATE3: RateSpec(packet_bytes=512, frames=1, airtime_s=3.07),
    ModemRate.RATE5: RateSpec(packet_bytes=2048, frames=7, airtime_s=3.0),
}


@dataclass(frozen=True)
class FerCurve:
    """Frame error probability against SNR; shapes (n,), SNR strictly increasing."""

    snr_db: np.ndarray
    frame_error_prob: np.ndarray

    def __call__(self, snr_db: float) -> float:
        # Clamped outside the table, as in ros_acomms (np.interp holds the end values).
        return float(np.interp(snr_db, self.snr_db, self.frame_error_prob))


@functools.cache
def fer_curves() -> dict[ModemRate, FerCurve]:
    """The published Micro-Modem FER table shipped as package data (`data/micromodem_fer.json`)."""
    resource = importlib.resources.files("mergesvc") / "data" / "micromodem_fer.json"
    try:
        table = json.loads(resource.read_text(encoding="utf-8"))
        curves = {}
        for rate in ModemRate:
            entry = table[f"rate{rate.value}"]
            snr_db = np.asarray(entry["snr_db"], dtype=float)
            prob = np.asarray(entry["frame_error_prob"], dtype=float)
            if snr_db.shape != prob.shape or snr_db.ndim != 1 or snr_db.size < 2:
                raise ValueError(f"rate {rate.value}: snr_db and frame_error_prob differ in shape")
            if np.any(np.diff(snr_db) <= 0) or np.any((prob < 0) | (prob > 1)):
                raise ValueError(
                    f"rate {rate.value}: SNR not increasing or probability not in [0, 1]"
                )
            curves[rate] = FerCurve(snr_db=snr_db, frame_error_prob=prob)
    except (OSError, KeyError, TypeError, ValueError) as exc:
        raise DecodeError(f"invalid Micro-Modem FER table {resource}: {exc}") from exc
    return curves


def frame_error_prob(rate: ModemRate, snr_db: float) -> float:
    """Frame error probability of `rate` at `snr_db` (linear interpolation in dB)."""
    return fer_curves()[ModemRate(rate)](snr_db)


# --------------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------------


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class SnrModel(_Section):
    """SNR of one link: fixed (spread 0) or drawn per packet from N(mean, spread^2)."""

    mean_db: float = Field(-6.5, description="mean SNR at the receiver (dB)")
    spread_db: float = Field(0.0, ge=0.0, description="std dev of the per-packet SNR draw (dB)")


class ChannelConfig(_Section):
    rate: ModemRate = Field(ModemRate.RATE1, description="Micro-Modem packet rate (1, 3 or 5)")
    snr: SnrModel = Field(default_factory=SnrModel, description="SNR of every link by default")
    link_snr: dict[str, SnrModel] = Field(
        default_factory=dict, description="per-link SNR, keyed 'src->dst' (directional)"
    )
    range_m: float = Field(1000.0, gt=0, description="distance between any two nodes by default")
    link_range_m: dict[str, float] = Field(
        default_factory=dict, description="per-link range (m), keyed 'a->b' (symmetric)"
    )
    sound_speed_mps: float = Field(SOUND_SPEED_MPS, gt=0)
    miniframe_airtime_s: float = Field(
        0.5, ge=0, description="airtime of one ack mini-frame (an assumption, not measured)"
    )
    miniframe_fer: float | None = Field(
        None, ge=0, le=1, description="ack mini-frame loss probability; None: rate-1 curve"
    )
    fixed_fer: float | None = Field(
        None, ge=0, le=1, description="override the curve with a fixed frame error rate"
    )
    corrupt_bad_frame_prob: float = Field(
        0.0, ge=0, le=1, description="chance a bad frame is passed up corrupted instead of dropped"
    )


class TdmaConfig(_Section):
    slot_order: list[str] = Field(
        default_factory=lambda: ["topside", "v1", "v2", "v3"],
        min_length=2,
        description="one TDMA cycle: the node owning each slot (a node may own several)",
    )
    slot_s: float = Field(6.0, gt=0, description="slot length: acks + one packet + propagation")
    max_acks_per_slot: int | None = Field(
        None, ge=0, description="ack mini-frames per slot (one per peer); None: number of peers"
    )

    @property
    def nodes(self) -> list[str]:
        return list(dict.fromkeys(self.slot_order))


class ArqConfig(_Section):
    max_message_bytes: int = Field(MAX_MESSAGE_BYTES, ge=1, le=MAX_MESSAGE_BYTES)
    max_tx_per_fragment: int = Field(8, ge=1, description="transmissions of one fragment, at most")
    message_timeout_s: float = Field(1800.0, gt=0, description="age at which a message is lost")
    max_in_flight: int = Field(2, ge=1, le=64, description="messages being sent per node")
    max_queue_messages: int = Field(
        4, ge=1, description="messages waiting per node; when full the oldest is dropped"
    )
    reassembly_timeout_s: float = Field(3600.0, gt=0, description="receiver drops partials after")


class LinkConfig(_Section):
    channel: ChannelConfig = Field(default_factory=ChannelConfig)
    tdma: TdmaConfig = Field(default_factory=TdmaConfig)
    arq: ArqConfig = Field(default_factory=ArqConfig)

    @model_validator(mode="after")
    def _check(self) -> LinkConfig:
        nodes = set(self.tdma.nodes)
        for name, table in (
            ("link_snr", self.channel.link_snr),
            ("link_range_m", self.channel.link_range_m),
        ):
            for key in table:
                a, b = _split_link_key(key)
                if a not in nodes or b not in nodes:
                    raise ValueError(f"channel.{name}[{key!r}] names a node not in tdma.slot_order")
        if any(r <= 0 for r in self.channel.link_range_m.values()):
            raise ValueError("channel.link_range_m: ranges must be > 0")
        spec = RATE_SPECS[self.channel.rate]
        max_range_m = max([self.channel.range_m, *self.channel.link_range_m.values()])
        busy_s = (
            self.acks_per_slot * self.channel.miniframe_airtime_s
            + spec.airtime_s
            + max_range_m / self.channel.sound_speed_mps
        )
        if busy_s > self.tdma.slot_s + 1e-9:
            raise ValueError(
                f"tdma.slot_s {self.tdma.slot_s} s is shorter than acks + packet + propagation "
                f"({busy_s:.3f} s): transmissions would overlap the next slot"
            )
        largest = spec.fragment_payload_bytes * MAX_FRAGMENTS - MESSAGE_TRAILER_BYTES
        if self.arq.max_message_bytes > largest:
            raise ValueError(
                f"arq.max_message_bytes exceeds {largest} bytes at rate {self.channel.rate.value}"
            )
        return self

    @property
    def acks_per_slot(self) -> int:
        n = self.tdma.max_acks_per_slot
        return len(self.tdma.nodes) - 1 if n is None else n


def _split_link_key(key: str) -> tuple[str, str]:
    parts = key.split("->")
    if len(parts) != 2 or not parts[0] or not parts[1]:
        raise ValueError(f"link key {key!r} must look like 'src->dst'")
    return parts[0].strip(), parts[1].strip()


# --------------------------------------------------------------------------------------------
# Channel
# --------------------------------------------------------------------------------------------


class AcousticChannel:
    """Physical layer: per-packet SNR draw, per-frame Bernoulli errors, cut at the first bad frame.

    All randomness comes from the injected generator, consumed in a fixed pattern per packet
    (one SNR draw if spread > 0, then one uniform per frame of the rate) so runs are repeatable.
    """

    def __init__(self, config: ChannelConfig, rng: np.random.Generator) -> None:
        self.config = config
        self.spec = RATE_SPECS[config.rate]
        self._rng = rng
        self._snr = {_split_link_key(k): v for k, v in config.link_snr.items()}
        self._range_m: dict[tuple[str, str], float] = {}
        for key, range_m in config.link_range_m.items():
            a, b = _split_link_key(key)
            self._range_m[(a, b)] = self._range_m[(b, a)] = range_m

    def range_m(self, a: str, b: str) -> float:
        return self._range_m.get((a, b), self.config.range_m)

    def propagation_delay_s(self, a: str, b: str) -> float:
        return self.range_m(a, b) / self.config.sound_speed_mps

    def snr_model(self, src: str, dst: str) -> SnrModel:
        return self._snr.get((src, dst), self.config.snr)

    def draw_snr_db(self, src: str, dst: str) -> float:
        model = self.snr_model(src, dst)
        if model.spread_db == 0.0:
            return model.mean_db
        return model.mean_db + model.spread_db * float(self._rng.standard_normal())

    def frame_error_prob(self, snr_db: float) -> float:
        if self.config.fixed_fer is not None:
            return self.config.fixed_fer
        return frame_error_prob(self.config.rate, snr_db)

    def transmit_packet(self, src: str, dst: str, frames: Sequence[bytes]) -> list[bytes]:
        """Frames decoded by `dst`: those before the first bad frame (a packet is cut there).

        The bad frame itself is passed up with corrupted bytes with probability
        `corrupt_bad_frame_prob` (a modem-level check that missed), otherwise dropped.
        """
        if not 0 < len(frames) <= self.spec.frames:
            raise ValueError(
                f"a rate-{self.config.rate.value} packet holds 1..{self.spec.frames} frames"
            )
        p_bad = self.frame_error_prob(self.draw_snr_db(src, dst))
        bad = self._rng.random(self.spec.frames)[: len(frames)] < p_bad
        n_good = int(np.argmax(bad)) if bad.any() else len(frames)
        received = list(frames[:n_good])
        corrupt_p = self.config.corrupt_bad_frame_prob
        if n_good < len(frames) and corrupt_p > 0.0 and self._rng.random() < corrupt_p:
            received.append(self._corrupt(frames[n_good]))
        return received

    def transmit_miniframe(self, src: str, dst: str) -> bool:
        """Whether an ack mini-frame gets through (rate-1 curve unless `miniframe_fer` is set)."""
        snr_db = self.draw_snr_db(src, dst)
        if self.config.miniframe_fer is not None:
            p_bad = self.config.miniframe_fer
        else:
            p_bad = frame_error_prob(ModemRate.RATE1, snr_db)
        return bool(self._rng.random() >= p_bad)

    def _corrupt(self, frame: bytes) -> bytes:
        data = bytearray(frame)
        n_flips = 1 + int(self._rng.integers(0, 4))
        for pos in self._rng.integers(0, len(data), size=n_flips):
            data[int(pos)] ^= int(self._rng.integers(1, 256))
        return bytes(data)


# --------------------------------------------------------------------------------------------
# Wire format: fragments and acks
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Fragment:
    """One frame's worth of a message: `index` of `count` fragments of message `msg_id`."""

    msg_id: int
    index: int
    count: int
    payload: bytes


def _crc16(data: bytes) -> bytes:
    return binascii.crc_hqx(data, 0xFFFF).to_bytes(2, "big")


def encode_fragment(fragment: Fragment) -> bytes:
    """Header (4 bytes: msg id 12 bit, index 10 bit, last index 10 bit) + payload + CRC-16."""
    if not (
        0 <= fragment.msg_id < MSG_ID_MODULO
        and 1 <= fragment.count <= MAX_FRAGMENTS
        and 0 <= fragment.index < fragment.count
    ):
        raise ValueError(
            f"fragment header out of range: {fragment.msg_id}/{fragment.index}/{fragment.count}"
        )
    word = (fragment.msg_id << 20) | (fragment.index << 10) | (fragment.count - 1)
    body = word.to_bytes(4, "big") + fragment.payload
    return body + _crc16(body)


def decode_fragment(frame: bytes) -> Fragment:
    """Inverse of `encode_fragment`; raises DecodeError on a CRC mismatch or a bad header."""
    if len(frame) < FRAGMENT_HEADER_BYTES:
        raise DecodeError(f"fragment of {len(frame)} bytes is shorter than its header")
    body, crc = frame[:-_CRC16_BYTES], frame[-_CRC16_BYTES:]
    if _crc16(body) != crc:
        raise DecodeError("fragment CRC-16 mismatch")
    word = int.from_bytes(body[:4], "big")
    msg_id, index, count = word >> 20, (word >> 10) & 0x3FF, (word & 0x3FF) + 1
    if index >= count:
        raise DecodeError(f"fragment index {index} >= count {count}")
    return Fragment(msg_id=msg_id, index=index, count=count, payload=bytes(body[4:]))


def split_message(msg_id: int, message: bytes, fragment_payload_bytes: int) -> list[Fragment]:
    """Message + CRC-32 trailer cut into fragments of at most `fragment_payload_bytes`."""
    data = message + zlib.crc32(message).to_bytes(MESSAGE_TRAILER_BYTES, "big")
    count = math.ceil(len(data) / fragment_payload_bytes)
    if count > MAX_FRAGMENTS:
        raise LinkError(
            f"message of {len(message)} bytes needs {count} > {MAX_FRAGMENTS} fragments"
        )
    return [
        Fragment(
            msg_id, i, count, data[i * fragment_payload_bytes : (i + 1) * fragment_payload_bytes]
        )
        for i in range(count)
    ]


def join_fragments(payloads: Sequence[bytes]) -> bytes:
    """Fragment payloads in index order -> message; DecodeError if the CRC-32 does not match."""
    data = b"".join(payloads)
    if len(data) < MESSAGE_TRAILER_BYTES:
        raise DecodeError("reassembled message shorter than its CRC-32 trailer")
    message, crc = data[:-MESSAGE_TRAILER_BYTES], data[-MESSAGE_TRAILER_BYTES:]
    if zlib.crc32(message).to_bytes(MESSAGE_TRAILER_BYTES, "big") != crc:
        raise DecodeError("reassembled message CRC-32 mismatch")
    return message


@dataclass(frozen=True)
class AckEntry:
    """Receiver state of one message: complete, or all fragments below `base` plus a bitmap.

    Bit i of `bitmap` (byte i // 8, LSB first) is set when fragment `base + i` was received.
    """

    msg_id: int
    complete: bool
    base: int = 0
    bitmap: bytes = b""

    @property
    def encoded_bytes(self) -> int:
        return _ACK_COMPLETE_BYTES if self.complete else _ACK_ENTRY_HEADER_BYTES + len(self.bitmap)

    def received(self, count: int) -> Iterable[int]:
        """Fragment indices this entry acknowledges, for a message of `count` fragments."""
        if self.complete:
            yield from range(count)
            return
        yield from range(min(self.base, count))
        for i in range(8 * len(self.bitmap)):
            if self.bitmap[i // 8] >> (i % 8) & 1 and self.base + i < count:
                yield self.base + i


def encode_ack(entries: Sequence[AckEntry]) -> bytes:
    """Entries + CRC-16 in one mini-frame (at most MINIFRAME_BYTES)."""
    out = bytearray()
    for e in entries:
        out += ((e.msg_id << 4) | (_FLAG_COMPLETE if e.complete else 0)).to_bytes(2, "big")
        if not e.complete:
            out += e.base.to_bytes(2, "big") + len(e.bitmap).to_bytes(1, "big") + e.bitmap
    out += _crc16(bytes(out))
    if len(out) > MINIFRAME_BYTES:
        raise ValueError(
            f"ack of {len(out)} bytes does not fit a {MINIFRAME_BYTES}-byte mini-frame"
        )
    return bytes(out)


def decode_ack(frame: bytes) -> list[AckEntry]:
    """Inverse of `encode_ack`; DecodeError on a CRC mismatch or truncated entry."""
    if len(frame) < _CRC16_BYTES or _crc16(frame[:-_CRC16_BYTES]) != frame[-_CRC16_BYTES:]:
        raise DecodeError("ack CRC-16 mismatch")
    body, pos, entries = frame[:-_CRC16_BYTES], 0, []
    while pos < len(body):
        if pos + 2 > len(body):
            raise DecodeError("truncated ack entry")
        word = int.from_bytes(body[pos : pos + 2], "big")
        pos += 2
        if word & _FLAG_COMPLETE:
            entries.append(AckEntry(msg_id=word >> 4, complete=True))
            continue
        if pos + 3 > len(body):
            raise DecodeError("truncated ack entry")
        base, n = int.from_bytes(body[pos : pos + 2], "big"), body[pos + 2]
        bitmap = bytes(body[pos + 3 : pos + 3 + n])
        if len(bitmap) != n:
            raise DecodeError("truncated ack bitmap")
        pos += 3 + n
        entries.append(AckEntry(msg_id=word >> 4, complete=False, base=base, bitmap=bitmap))
    return entries


def _ack_entry(msg_id: int, received: Iterable[int], max_bitmap_bytes: int) -> AckEntry:
    got = set(received)
    base = 0
    while base in got:
        base += 1
    beyond = [i - base for i in got if i > base]
    n_bytes = min(max_bitmap_bytes, (max(beyond) // 8 + 1) if beyond else 0)
    bitmap = bytearray(n_bytes)
    for i in beyond:
        if i < 8 * n_bytes:
            bitmap[i // 8] |= 1 << (i % 8)
    return AckEntry(msg_id=msg_id, complete=False, base=base, bitmap=bytes(bitmap))


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
        room = MINIFRAME_BYTES - _CRC16_BYTES
        entries: list[AckEntry] = []
        for msg_id in list(rx.ack_pending):
            if msg_id in rx.completed:
                entry = AckEntry(msg_id=msg_id, complete=True)
            elif msg_id in rx.partial and room > _ACK_ENTRY_HEADER_BYTES:
                entry = _ack_entry(msg_id, rx.partial[msg_id].parts, room - _ACK_ENTRY_HEADER_BYTES)
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


# --------------------------------------------------------------------------------------------
# Benchmark drivers
# --------------------------------------------------------------------------------------------


class Workload(_Section):
    """Periodic traffic: every vehicle sends a submap to the topside each period (staggered)."""

    topside: str = "topside"
    uplink_bytes: int = Field(1024, ge=0, le=MAX_MESSAGE_BYTES, description="0: no uplink")
    downlink_bytes: int = Field(
        0, ge=0, le=MAX_MESSAGE_BYTES, description="topside -> each vehicle per period; 0: none"
    )
    period_s: float = Field(60.0, gt=0)
    duration_s: float = Field(1800.0, gt=0, description="time during which messages are offered")
    drain_s: float = Field(3600.0, ge=0, description="extra time for the last messages to resolve")


def simulate_workload(config: LinkConfig, workload: Workload, *, seed: int = 0) -> LinkStats:
    """Run `workload` over `config` on the simulated clock; every message resolves or drains out.

    Goodput is delivered message bits over the simulated time until the last message resolved.
    """
    sim = LinkSimulator(config, rng=np.random.default_rng(seed))
    if workload.topside not in sim.nodes:
        raise ConfigError(f"workload topside {workload.topside!r} is not in tdma.slot_order")
    vehicles = [n for n in sim.nodes if n != workload.topside]
    content = np.random.default_rng([seed, 1])
    n_periods = math.ceil(workload.duration_s / workload.period_s)
    for i, vehicle in enumerate(vehicles):
        offset_s = i * workload.period_s / len(vehicles)
        for k in range(n_periods):
            t = offset_s + k * workload.period_s
            if t >= workload.duration_s:
                break
            if workload.uplink_bytes:
                sim.offer(vehicle, workload.topside, content.bytes(workload.uplink_bytes), at_s=t)
            if workload.downlink_bytes:
                sim.offer(workload.topside, vehicle, content.bytes(workload.downlink_bytes), at_s=t)
    sim.run_until(workload.duration_s)
    step_s = config.tdma.slot_s * len(config.tdma.slot_order)
    while sim.pending() and sim.now_s < workload.duration_s + workload.drain_s:
        sim.run_until(sim.now_s + step_s)
    return sim.stats


DEFAULT_SWEEP_SNR_DB: dict[ModemRate, tuple[float, ...]] = {
    ModemRate.RATE1: (-7.2, -6.8, -6.5, -6.0),
    ModemRate.RATE3: (-1.6, -0.8, 0.0, 3.0),
    ModemRate.RATE5: (4.4, 5.0, 5.5, 6.0),
}
"""SNRs spanning each rate's published curve, from heavy loss to (near) none."""


@dataclass(frozen=True)
class SweepRow:
    rate: ModemRate
    snr_db: float
    frame_error_prob: float
    messages_offered: int
    messages_delivered: int
    messages_lost: int
    delivery_ratio: float
    latency_p50_s: float
    latency_p90_s: float
    goodput_bps: float
    fragments_retransmitted: int
    bytes_on_air: int

    def as_dict(self) -> dict[str, Any]:
        return {**self.__dict__, "rate": self.rate.value}


def sweep_link(
    rates: Sequence[ModemRate] = tuple(ModemRate),
    snrs_db: Sequence[float] | None = None,
    *,
    workload: Workload | None = None,
    base_config: LinkConfig | None = None,
    seed: int = 0,
) -> list[SweepRow]:
    """`simulate_workload` for each rate x SNR (SNRs per rate from DEFAULT_SWEEP_SNR_DB if None)."""
    workload = workload or Workload()
    base = (base_config or LinkConfig()).model_dump()
    rows = []
    for rate in rates:
        rate = ModemRate(rate)
        for snr_db in DEFAULT_SWEEP_SNR_DB[rate] if snrs_db is None else snrs_db:
            channel = {
                **base["channel"],
                "rate": rate,
                "snr": {**base["channel"]["snr"], "mean_db": snr_db},
            }
            config = LinkConfig.model_validate({**base, "channel": channel})
            stats = simulate_workload(config, workload, seed=seed)
            rows.append(
                SweepRow(
                    rate=rate,
                    snr_db=float(snr_db),
                    frame_error_prob=frame_error_prob(rate, snr_db),
                    messages_offered=stats.messages_offered,
                    messages_delivered=stats.messages_delivered,
                    messages_lost=stats.messages_lost,
                    delivery_ratio=stats.delivery_ratio,
                    latency_p50_s=stats.latency_percentile_s(50),
                    latency_p90_s=stats.latency_percentile_s(90),
                    goodput_bps=stats.goodput_bps,
                    fragments_retransmitted=stats.fragments_retransmitted,
                    bytes_on_air=stats.bytes_on_air,
                )
            )
    return rows


def format_sweep_table(rows: Sequence[SweepRow]) -> str:
    """Fixed-width text table of a sweep (one line per rate x SNR)."""
    header = (
        f"{'rate':>4} {'snr_db':>7} {'FER':>6} {'offered':>7} {'deliv':>6} {'lost':>5} "
        f"{'ratio':>6} {'p50_s':>8} {'p90_s':>8} {'goodput_bps':>11} {'retx':>6} {'air_kB':>8}"
    )
    lines = [header, "-" * len(header)]
    for r in rows:
        lines.append(
            f"{r.rate.value:>4} {r.snr_db:>7.2f} {r.frame_error_prob:>6.3f} "
            f"{r.messages_offered:>7} "
            f"{r.messages_delivered:>6} {r.messages_lost:>5} {r.delivery_ratio:>6.3f} "
            f"{r.latency_p50_s:>8.1f} {r.latency_p90_s:>8.1f} {r.goodput_bps:>11.2f} "
            f"{r.fragments_retransmitted:>6} {r.bytes_on_air / 1000:>8.1f}"
        )
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# Zenoh bridge
# --------------------------------------------------------------------------------------------


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
    return None if suffix is None else f"{top_prefix}/{suffix}"


def downlink_key(key: str, *, uw_prefix: str, top_prefix: str) -> str | None:
    """Topside key -> vehicle-side key (None for keys already on the vehicle side, or foreign)."""
    if key_suffix(key, uw_prefix) is not None or key == uw_prefix:
        return None
    suffix = key_suffix(key, top_prefix)
    return None if suffix is None else f"{uw_prefix}/{suffix}"


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


def make_zenoh_config(
    *,
    config_file: str | None = None,
    mode: str | None = None,
    connect: Sequence[str] = (),
    listen: Sequence[str] = (),
    scouting: bool = True,
) -> zenoh.Config:
    """A zenoh Config from the usual `--config/--mode/--connect/--listen` flags.

    `scouting=False` turns multicast and gossip scouting off and sets `scouting/delay` to 0
    (tests and fixed topologies).
    """
    try:
        config = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
        if mode:
            config.insert_json5("mode", json.dumps(mode))
        if connect:
            config.insert_json5("connect/endpoints", json.dumps(list(connect)))
        if listen:
            config.insert_json5("listen/endpoints", json.dumps(list(listen)))
        if not scouting:
            config.insert_json5("scouting/multicast/enabled", "false")
            config.insert_json5("scouting/gossip/enabled", "false")
            config.insert_json5("scouting/delay", "0")
    except (zenoh.ZError, OSError, ValueError) as exc:
        raise ConfigError(f"invalid zenoh configuration: {exc}") from exc
    return config


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
    `k` in `downlink_keys` go from `topside` to the vehicle named in the key and are republished
    on `{uw_prefix}/<suffix>`. The key suffix travels over the link with the payload; encodings
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
        downlink_keys: Sequence[str] = ("factor/**",),
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
                self._session = zenoh.open(
                    zenoh_config if zenoh_config is not None else zenoh.Config()
                )
            remote = zenoh.Locality.REMOTE  # never re-bridge what this session republished
            self._subscribers.append(
                self._session.declare_subscriber(
                    f"{uw_prefix}/**", self._uplink_sample, allowed_origin=remote
                )
            )
            for k in downlink_keys:
                self._subscribers.append(
                    self._session.declare_subscriber(
                        f"{top_prefix}/{k}", self._downlink_sample, allowed_origin=remote
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
        logger.info(
            "acoustic bridge %s/** <-> %s/** (rate %d, time_scale %g, vehicles %s)",
            uw_prefix,
            top_prefix,
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
                logger.debug("undeclare failed: %s", exc)
        self._subscribers.clear()
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            if self._thread.is_alive():
                logger.warning("acoustic bridge worker did not stop within 5 s")
        if self._owns_session and self._session is not None:
            self._session.close()
        s = self._sim.stats
        logger.info(
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
                logger.warning("%s ingress queue full: dropped %s", direction.value, dropped_key)
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
            logger.exception("acoustic bridge worker failed; bridge stopped")

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
            logger.warning("%s sample %s names no known vehicle: not bridged", direction.value, key)
            return
        try:
            data = frame_sample(suffix, payload)
            self._sim.offer(src, dst, data)
        except LinkError as exc:
            self._stats.oversize += 1
            logger.warning("%s sample %s not bridged: %s", direction.value, key, exc)

    def _on_deliver(self, delivery: Delivery) -> None:
        suffix, payload = unframe_sample(delivery.payload)
        if delivery.dst == self.topside:
            self._outbox.append((Direction.UPLINK, f"{self.top_prefix}/{suffix}", payload))
        else:
            self._outbox.append((Direction.DOWNLINK, f"{self.uw_prefix}/{suffix}", payload))

    def _on_lost(self, event: LossEvent) -> None:
        direction = Direction.UPLINK if event.dst == self.topside else Direction.DOWNLINK
        self._stats.lost[direction.value] += 1
        try:
            suffix, _ = unframe_sample(event.payload)
        except DecodeError:
            suffix = "?"
        logger.warning(
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
        for direction, key, payload in outbox:
            try:
                assert self._session is not None
                self._session.put(key, payload)
            except zenoh.ZError as exc:
                with self._sim_lock:
                    self._stats.publish_errors += 1
                logger.warning("republishing %s failed: %s", key, exc)
                continue
            with self._sim_lock:
                self._stats.published[direction.value] += 1


__all__ = [
    "DEFAULT_SWEEP_SNR_DB",
    "FRAGMENT_HEADER_BYTES",
    "MAX_MESSAGE_BYTES",
    "MINIFRAME_BYTES",
    "RATE_SPECS",
    "AckEntry",
    "AcousticBridge",
    "AcousticChannel",
    "ArqConfig",
    "BridgeStats",
    "ChannelConfig",
    "Delivery",
    "Direction",
    "FerCurve",
    "Fragment",
    "LinkConfig",
    "LinkSimulator",
    "LinkStats",
    "LossEvent",
    "LossReason",
    "ModemRate",
    "RateSpec",
    "SnrModel",
    "SweepRow",
    "TdmaConfig",
    "Workload",
    "decode_ack",
    "decode_fragment",
    "downlink_key",
    "encode_ack",
    "encode_fragment",
    "fer_curves",
    "format_sweep_table",
    "frame_error_prob",
    "frame_sample",
    "join_fragments",
    "key_suffix",
    "make_zenoh_config",
    "route_vehicle",
    "simulate_workload",
    "split_message",
    "sweep_link",
    "unframe_sample",
    "uplink_key",
]
