"""Link configuration: channel (rate, SNR, ranges), TDMA slots and ARQ limits (pydantic models).

`LinkConfig` checks the sections against each other: per-link tables name known nodes, a slot
fits its acks + one packet + propagation, and the largest message fits the fragment count.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, model_validator

from mergesvc.link.arq import MAX_FRAGMENTS, MAX_MESSAGE_BYTES, MESSAGE_TRAILER_BYTES
from mergesvc.link.modem import RATE_SPECS, ModemRate

SOUND_SPEED_MPS = 1500.0


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


__all__ = [
    "SOUND_SPEED_MPS",
    "ArqConfig",
    "ChannelConfig",
    "LinkConfig",
    "SnrModel",
    "TdmaConfig",
]
