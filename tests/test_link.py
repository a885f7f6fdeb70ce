"""Acoustic link: FER model, channel, wire format, ARQ simulator, sweep, and the Zenoh bridge."""

from __future__ import annotations

import json
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

import numpy as np
import pytest
import zenoh
from helpers import Inbox, free_port, wait_for
from pydantic import ValidationError

from mergesvc.errors import ConfigError, DecodeError, InputError, LinkError
from mergesvc.link.arq import (
    FRAGMENT_HEADER_BYTES,
    MAX_MESSAGE_BYTES,
    MINIFRAME_BYTES,
    AckEntry,
    Fragment,
    decode_ack,
    decode_fragment,
    encode_ack,
    encode_fragment,
    join_fragments,
    split_message,
)
from mergesvc.link.bridge import (
    AcousticBridge,
    Direction,
    downlink_key,
    frame_sample,
    key_suffix,
    route_vehicle,
    unframe_sample,
    uplink_key,
)
from mergesvc.link.channel import AcousticChannel
from mergesvc.link.config import ChannelConfig, LinkConfig
from mergesvc.link.modem import RATE_SPECS, ModemRate, fer_curves, frame_error_prob
from mergesvc.link.simulator import Delivery, LinkSimulator, LossEvent, LossReason
from mergesvc.link.workload import Workload, format_sweep_table, simulate_workload, sweep_link
from mergesvc.wire.session import make_zenoh_config

SHARED_TABLE = (
    Path(__file__).resolve().parents[2] / "shared" / "data" / "acomms_micromodem_per_table.json"
)


# ---------------------------------------------------------------------------------------------
# FER model
# ---------------------------------------------------------------------------------------------


def test_fer_matches_table_points_and_is_monotone() -> None:
    for rate, curve in fer_curves().items():
        for snr_db, prob in zip(curve.snr_db, curve.frame_error_prob):
            assert frame_error_prob(rate, snr_db) == pytest.approx(prob, abs=1e-12)
        grid = np.linspace(curve.snr_db[0] - 3.0, curve.snr_db[-1] + 3.0, 2001)
        values = np.array([frame_error_prob(rate, s) for s in grid])
        assert np.all(np.diff(values) <= 1e-15)  # never rises with SNR
        assert values[0] == 1.0  # clamped below the table
        assert values[-1] == curve.frame_error_prob[-1]  # clamped above it
    # Linear in dB between points: half way between rate-5 anchors.
    mid = (3.09699410930214 + 4.44256115246717) / 2
    assert frame_error_prob(ModemRate.RATE5, mid) == pytest.approx((1 + 0.135) / 2)


@pytest.mark.skipif(not SHARED_TABLE.exists(), reason="../shared/data not present")
def test_package_table_equals_published_table() -> None:
    published = json.loads(SHARED_TABLE.read_text())
    for rate, curve in fer_curves().items():
        entry = published[f"rate{rate.value}"]
        assert curve.snr_db.tolist() == entry["snr_db"]
        assert curve.frame_error_prob.tolist() == entry["frame_error_prob"]


ANCHORS = [
    (ModemRate.RATE1, -7.96, 1.0),
    (ModemRate.RATE1, -6.01, 0.0),
    (ModemRate.RATE3, -2.92, 1.0),
    (ModemRate.RATE3, -1.59, 0.57),
    (ModemRate.RATE3, 0.0, 0.025),
    (ModemRate.RATE5, 3.10, 1.0),
    (ModemRate.RATE5, 4.44, 0.135),
    (ModemRate.RATE5, 6.02, 0.0),
]


@pytest.mark.parametrize(("rate", "snr_db", "published"), ANCHORS)
def test_published_anchor_points_come_out_of_the_channel(
    rate: ModemRate, snr_db: float, published: float
) -> None:
    n_packets = 20_000
    channel = AcousticChannel(
        ChannelConfig(rate=rate, snr={"mean_db": snr_db}), np.random.default_rng(7)
    )
    frames = [bytes([i]) * 8 for i in range(RATE_SPECS[rate].frames)]
    received = [len(channel.transmit_packet("a", "b", frames)) for _ in range(n_packets)]
    first_frame_lost = np.mean([n == 0 for n in received])
    # The anchors are the table points rounded to 0.01 dB (-2.92 lies just above -2.9215, where
    # the FER is 0.9998): 0.005 covers that; the binomial std is <= 0.0035 at n = 20000, so 0.02
    # is > 5 sigma for the intermediate points.
    tolerance = 0.005 if published in (0.0, 1.0) else 0.02
    assert first_frame_lost == pytest.approx(published, abs=tolerance)
    if rate is ModemRate.RATE5 and published == 0.135:
        whole = np.mean([n == 7 for n in received])
        assert whole == pytest.approx((1 - 0.135) ** 7, abs=0.02)  # all 7 frames good


class _ScriptedRng:
    """Stands in for numpy's Generator with scripted uniforms (channel draws one per frame)."""

    def __init__(self, uniforms: list[float]) -> None:
        self.uniforms = np.asarray(uniforms)

    def random(self, size: int | None = None) -> np.ndarray | float:
        return self.uniforms[:size] if size is not None else 0.99

    def standard_normal(self) -> float:
        return 0.0


def test_packet_is_cut_at_first_bad_frame() -> None:
    config = ChannelConfig(rate=ModemRate.RATE5, fixed_fer=0.5)
    frames = [bytes([i]) * 10 for i in range(7)]
    # frame 2 is bad (0.1 < 0.5); frames 3.. are lost even though their draws are good
    rng = _ScriptedRng([0.9, 0.9, 0.1, 0.9, 0.9, 0.9, 0.9])
    channel = AcousticChannel(config, rng)  # type: ignore[arg-type]
    assert channel.transmit_packet("a", "b", frames) == frames[:2]
    rng.uniforms = np.array([0.1] + [0.9] * 6)
    assert channel.transmit_packet("a", "b", frames) == []
    rng.uniforms = np.full(7, 0.9)
    assert channel.transmit_packet("a", "b", frames) == frames


def test_cut_statistics_are_geometric_and_prefixes_only() -> None:
    p = 0.3
    channel = AcousticChannel(
        ChannelConfig(rate=ModemRate.RATE5, fixed_fer=p), np.random.default_rng(3)
    )
    frames = [bytes([i]) * 4 for i in range(7)]
    lengths = []
    for _ in range(10_000):
        got = channel.transmit_packet("a", "b", frames)
        assert got == frames[: len(got)]
        lengths.append(len(got))
    expected = sum((1 - p) ** k for k in range(1, 8))  # E[prefix] = sum_k P(first k good)
    assert np.mean(lengths) == pytest.approx(expected, abs=0.05)


def test_snr_spread_draws_per_packet() -> None:
    frames = [b"x" * 8, b"y" * 8]
    fixed = AcousticChannel(
        ChannelConfig(rate=ModemRate.RATE1, snr={"mean_db": -6.0}), np.random.default_rng(0)
    )
    spread = AcousticChannel(
        ChannelConfig(rate=ModemRate.RATE1, snr={"mean_db": -6.0, "spread_db": 1.0}),
        np.random.default_rng(0),
    )
    assert all(len(fixed.transmit_packet("a", "b", frames)) == 2 for _ in range(2000))
    lost = sum(len(spread.transmit_packet("a", "b", frames)) < 2 for _ in range(2000))
    assert 100 < lost < 1500  # SNR below -6.01 dB about half the time, FER rising from 0


# ---------------------------------------------------------------------------------------------
# Wire format
# ---------------------------------------------------------------------------------------------


def test_fragment_round_trip_and_every_byte_error_detected() -> None:
    frag = Fragment(msg_id=4095, index=1022, count=1024, payload=bytes(range(90)))
    frame = encode_fragment(frag)
    assert len(frame) == 90 + FRAGMENT_HEADER_BYTES
    assert decode_fragment(frame) == frag
    for pos in range(len(frame)):
        for flip in (0x01, 0x80, 0xFF):
            bad = bytearray(frame)
            bad[pos] ^= flip
            with pytest.raises(DecodeError):
                decode_fragment(bytes(bad))
    with pytest.raises(DecodeError):
        decode_fragment(frame[:3])


def test_split_and_join_message() -> None:
    message = np.random.default_rng(0).bytes(1000)
    fragments = split_message(5, message, 90)
    assert len(fragments) == 12  # 1000 + 4 CRC bytes in 90-byte pieces
    assert join_fragments([f.payload for f in fragments]) == message
    assert join_fragments([f.payload for f in split_message(0, b"", 90)]) == b""
    payloads = [f.payload for f in fragments]
    payloads[3] = payloads[3][:-1] + bytes([payloads[3][-1] ^ 1])
    with pytest.raises(DecodeError):
        join_fragments(payloads)
    with pytest.raises(LinkError):
        split_message(0, bytes(1024 * 90), 90)


def test_ack_round_trip_and_bitmap() -> None:
    entries = [
        AckEntry(msg_id=7, complete=True),
        AckEntry(msg_id=8, complete=False, base=3, bitmap=bytes([0b00000110])),
    ]
    frame = encode_ack(entries)
    assert len(frame) <= MINIFRAME_BYTES
    assert decode_ack(frame) == entries
    assert list(entries[1].received(10)) == [0, 1, 2, 4, 5]
    assert list(entries[0].received(3)) == [0, 1, 2]
    with pytest.raises(DecodeError):
        decode_ack(frame[:-1] + bytes([frame[-1] ^ 1]))
    with pytest.raises(ValueError, match="mini-frame"):
        encode_ack([AckEntry(msg_id=1, complete=False, base=0, bitmap=bytes(95))])


# ---------------------------------------------------------------------------------------------
# Configuration
# ---------------------------------------------------------------------------------------------


def test_config_validation() -> None:
    config = LinkConfig.model_validate({"channel": {"rate": 5}})
    assert config.channel.rate is ModemRate.RATE5
    with pytest.raises(ValidationError):
        LinkConfig.model_validate({"channel": {"rate": 2}})
    with pytest.raises(ValidationError):
        LinkConfig.model_validate({"channel": {"bogus": 1}})
    with pytest.raises(ValidationError, match="slot_s"):
        LinkConfig.model_validate({"tdma": {"slot_s": 3.5}})
    with pytest.raises(ValidationError, match="slot_order"):
        LinkConfig.model_validate({"channel": {"link_snr": {"v9->topside": {"mean_db": 0}}}})


# ---------------------------------------------------------------------------------------------
# Simulator: timing, ARQ
# ---------------------------------------------------------------------------------------------


def _two_node_config(**channel: object) -> LinkConfig:
    return LinkConfig.model_validate(
        {
            "channel": {"range_m": 1500.0, "fixed_fer": 0.0, "miniframe_fer": 0.0, **channel},
            "tdma": {"slot_order": ["a", "b"], "slot_s": 6.0},
        }
    )


def _collect(
    config: LinkConfig, seed: int = 0
) -> tuple[LinkSimulator, list[Delivery], list[LossEvent]]:
    deliveries: list[Delivery] = []
    losses: list[LossEvent] = []
    sim = LinkSimulator(
        config,
        rng=np.random.default_rng(seed),
        on_deliver=deliveries.append,
        on_lost=losses.append,
    )
    return sim, deliveries, losses


def _drain(sim: LinkSimulator, limit_s: float = 1e6) -> None:
    step_s = sim.config.tdma.slot_s * len(sim.config.tdma.slot_order)
    while sim.pending() and sim.now_s < limit_s:
        sim.run_until(sim.now_s + step_s)
    assert sim.pending() == 0


def test_airtime_and_propagation_exact() -> None:
    sim, deliveries, _ = _collect(_two_node_config())
    sim.offer("a", "b", b"hello", at_s=0.0)  # a owns the slot starting at 0
    sim.offer("a", "b", b"later", at_s=1.0)  # mid-slot: waits for a's next slot at 12
    sim.run_until(100.0)
    assert [d.payload for d in deliveries] == [b"hello", b"later"]
    assert deliveries[0].delivered_s == pytest.approx(0.0 + 3.07 + 1500 / 1500, abs=1e-9)
    assert deliveries[1].delivered_s == pytest.approx(12.0 + 3.07 + 1.0, abs=1e-9)
    assert deliveries[1].latency_s == pytest.approx(15.07, abs=1e-9)
    assert sim.stats.packets_sent == 2 and sim.stats.fragments_retransmitted == 0

    # b's slot (6 s) opens with its ack mini-frame (0.5 s), then its data packet.
    sim, deliveries, _ = _collect(_two_node_config(link_range_m={"a->b": 3000.0}))
    sim.offer("a", "b", b"ping", at_s=0.0)
    sim.offer("b", "a", b"pong", at_s=0.0)
    sim.run_until(50.0)
    times = {d.payload: d.delivered_s for d in deliveries}
    assert times[b"ping"] == pytest.approx(3.07 + 2.0, abs=1e-9)
    assert times[b"pong"] == pytest.approx(6.0 + 0.5 + 3.07 + 2.0, abs=1e-9)


def test_arq_under_loss_delivers_byte_identical_messages() -> None:
    config = LinkConfig.model_validate(
        {
            "channel": {
                "rate": 1,
                "fixed_fer": 0.25,
                "miniframe_fer": 0.2,
                "corrupt_bad_frame_prob": 0.5,
            },
            "tdma": {"slot_order": ["topside", "v1", "v2"]},
            "arq": {"max_tx_per_fragment": 30, "message_timeout_s": 1e6, "max_queue_messages": 64},
        }
    )
    sim, deliveries, losses = _collect(config, seed=11)
    rng = np.random.default_rng(5)
    sent: dict[int, bytes] = {}
    sizes = [0, 1, 85, 86, 87, 500, 3000]
    for k in range(21):
        src, dst = [("v1", "topside"), ("v2", "topside"), ("topside", "v1")][k % 3]
        payload = rng.bytes(sizes[k % len(sizes)])
        sent[sim.offer(src, dst, payload, at_s=30.0 * k)] = payload
    _drain(sim)
    handles = [d.handle for d in deliveries]
    assert len(handles) == len(set(handles))  # each message delivered once
    assert all(d.payload == sent[d.handle] for d in deliveries)
    assert not losses and sim.stats.messages_lost == 0
    assert sorted(handles) == sorted(sent)
    s = sim.stats
    assert s.corrupt_deliveries == 0
    assert s.frames_crc_failed > 0  # corrupted frames were passed up and caught by the CRC
    assert s.fragments_retransmitted > 0 and s.duplicates_dropped > 0
    assert s.bytes_delivered == sum(len(p) for p in sent.values())


def test_lost_acks_give_duplicates_that_are_dropped() -> None:
    config = _two_node_config(miniframe_fer=1.0)  # every ack is lost
    config.arq.max_tx_per_fragment = 4
    sim, deliveries, losses = _collect(config)
    sim.offer("a", "b", bytes(100), at_s=0.0)  # 2 fragments, one packet
    sim.run_until(200.0)
    assert [d.payload for d in deliveries] == [bytes(100)]
    assert sim.stats.packets_sent == 4
    assert sim.stats.duplicates_dropped == 2 * 3
    # The sender gives up, but the receiver has the message: not reported lost.
    assert not losses and sim.stats.give_ups_after_delivery == 1


def test_retry_budget_reports_loss() -> None:
    config = _two_node_config(fixed_fer=1.0)
    config.arq.max_tx_per_fragment = 3
    sim, deliveries, losses = _collect(config)
    handle = sim.offer("a", "b", b"doomed", at_s=0.0)
    _drain(sim)
    assert not deliveries
    assert [(e.handle, e.reason, e.payload) for e in losses] == [
        (handle, LossReason.RETRIES, b"doomed")
    ]
    assert losses[0].lost_s == pytest.approx(36.0)  # a's 4th slot: 0, 12, 24 were used
    assert sim.stats.packets_sent == 3 and sim.stats.messages_lost == 1


def test_timeout_and_queue_overflow_report_loss() -> None:
    config = _two_node_config(fixed_fer=1.0)
    config.arq.max_tx_per_fragment = 100
    config.arq.message_timeout_s = 20.0
    sim, _, losses = _collect(config)
    sim.offer("a", "b", b"stale", at_s=0.0)
    _drain(sim)
    assert [(e.reason, e.lost_s) for e in losses] == [(LossReason.TIMEOUT, 24.0)]

    config = _two_node_config()
    config.arq.max_queue_messages = 2
    config.arq.max_in_flight = 1
    sim, deliveries, losses = _collect(config)
    handles = [sim.offer("a", "b", bytes([i]), at_s=0.0) for i in range(6)]
    _drain(sim)
    assert [e.handle for e in losses] == handles[:4]  # oldest dropped first
    assert all(e.reason is LossReason.QUEUE_OVERFLOW for e in losses)
    assert [d.handle for d in deliveries] == handles[4:]
    assert sim.stats.lost_by_reason["queue_overflow"] == 4


def test_no_retransmissions_without_errors() -> None:
    config = LinkConfig.model_validate(
        {"channel": {"rate": 5, "fixed_fer": 0.0, "miniframe_fer": 0.0}}
    )
    workload = Workload(uplink_bytes=1024, downlink_bytes=300, duration_s=600.0)
    stats = simulate_workload(config, workload, seed=0)
    assert stats.messages_offered == 2 * 3 * 10
    assert stats.messages_delivered == stats.messages_offered
    assert stats.fragments_retransmitted == 0 and stats.duplicates_dropped == 0
    assert stats.acks_lost == 0 and stats.messages_lost == 0


def test_simulation_is_deterministic_for_a_seed() -> None:
    config = LinkConfig.model_validate({"channel": {"rate": 1, "snr": {"mean_db": -6.9}}})
    workload = Workload(duration_s=900.0)
    a = simulate_workload(config, workload, seed=3).summary()
    b = simulate_workload(config, workload, seed=3).summary()
    c = simulate_workload(config, workload, seed=4).summary()
    assert a == b
    assert a != c


def test_offer_rejects_bad_input() -> None:
    sim, _, _ = _collect(_two_node_config())
    with pytest.raises(LinkError):
        sim.offer("a", "b", bytes(MAX_MESSAGE_BYTES + 1))
    with pytest.raises(ConfigError):
        sim.offer("a", "zz", b"x")
    big = bytes(MAX_MESSAGE_BYTES)
    sim.offer("a", "b", big)
    sim.run_until(1.0)  # 729 fragments at rate 1: accepted and being sent


def test_sweep_table() -> None:
    rows = sweep_link(
        rates=[ModemRate.RATE1, ModemRate.RATE5],
        workload=Workload(duration_s=600.0),
        seed=0,
    )
    assert len(rows) == 8
    for row in rows:
        assert row.messages_offered == 30
        assert row.messages_delivered + row.messages_lost == row.messages_offered
        assert 0.0 <= row.delivery_ratio <= 1.0
    best = {r.rate: r for r in rows if r.snr_db in (-6.0, 6.0)}
    assert best[ModemRate.RATE5].delivery_ratio == 1.0
    assert best[ModemRate.RATE1].fragments_retransmitted == 0  # FER is 0 at -6.0 dB
    table = format_sweep_table(rows)
    assert len(table.splitlines()) == 2 + len(rows)
    assert json.dumps([r.as_dict() for r in rows])


# ---------------------------------------------------------------------------------------------
# Bridge helpers (pure)
# ---------------------------------------------------------------------------------------------


def test_key_mapping() -> None:
    uw, top = "mergesvc/v1/f/uw", "mergesvc/v1/f"
    assert uplink_key(f"{uw}/submap/v1/s0/3", uw_prefix=uw, top_prefix=top) == (
        f"{top}/submap/v1/s0/3"
    )
    assert uplink_key(f"{top}/submap/v1/s0/3", uw_prefix=uw, top_prefix=top) is None
    assert downlink_key(f"{top}/factor/v2/9", uw_prefix=uw, top_prefix=top) == f"{uw}/factor/v2/9"
    assert downlink_key(f"{uw}/factor/v2/9", uw_prefix=uw, top_prefix=top) is None
    assert downlink_key("other/factor/v2", uw_prefix=uw, top_prefix=top) is None
    assert key_suffix("a/bc", "a/b") is None and key_suffix("a/b", "a/b") is None
    assert route_vehicle("submap/v2/s0/1", ["v1", "v2"]) == "v2"
    assert route_vehicle("status/all", ["v1", "v2"]) is None
    assert unframe_sample(frame_sample("submap/v1/1", b"\x00\xff")) == ("submap/v1/1", b"\x00\xff")
    with pytest.raises(DecodeError):
        unframe_sample(b"\x09abc")
    with pytest.raises(LinkError):
        frame_sample("x" * 256, b"")


# ---------------------------------------------------------------------------------------------
# Zenoh bridge on loopback
# ---------------------------------------------------------------------------------------------

UW, TOP = "mergesvc/v1/test/uw", "mergesvc/v1/test"


@contextmanager
def _bridge_network(
    config: LinkConfig, **bridge_kwargs: object
) -> Iterator[tuple[AcousticBridge, zenoh.Session, zenoh.Session]]:
    """A bridge listening on a free loopback port, plus a vehicle-side and a topside session."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with ExitStack() as stack:
        bridge = stack.enter_context(
            AcousticBridge(
                config,
                uw_prefix=UW,
                top_prefix=TOP,
                zenoh_config=make_zenoh_config(mode="peer", listen=[endpoint], scouting=False),
                time_scale=0.002,
                seed=1,
                **bridge_kwargs,  # type: ignore[arg-type]
            )
        )
        side_config = make_zenoh_config(mode="peer", connect=[endpoint], scouting=False)
        vehicle = stack.enter_context(zenoh.open(side_config))
        topside = stack.enter_context(zenoh.open(side_config))
        yield bridge, vehicle, topside


def _matched_publisher(session: zenoh.Session, key: str) -> zenoh.Publisher:
    pub = session.declare_publisher(key)
    assert wait_for(lambda: pub.matching_status.matching, 10.0), f"no subscriber for {key}"
    return pub


def test_bridge_carries_both_directions() -> None:
    config = LinkConfig.model_validate(
        {
            "channel": {"rate": 3, "snr": {"mean_db": 0.0}},
            "tdma": {"slot_order": ["topside", "v1", "v2"]},
        }
    )
    up_inbox, down_inbox = Inbox(), Inbox()
    with _bridge_network(config) as (bridge, vehicle, topside):
        up_sub = topside.declare_subscriber(f"{TOP}/submap/**", up_inbox)
        down_sub = vehicle.declare_subscriber(f"{UW}/factor/**", down_inbox)
        try:
            submap = np.random.default_rng(0).bytes(700)  # two rate-3 frames
            pub = _matched_publisher(vehicle, f"{UW}/submap/v1/s0/1")
            pub.put(submap)
            assert wait_for(lambda: len(up_inbox.snapshot()) == 1)
            assert up_inbox.snapshot() == [(f"{TOP}/submap/v1/s0/1", submap)]

            factor_pub = _matched_publisher(topside, f"{TOP}/factor/v2/7")
            factor_pub.put(b"factor-for-v2")
            assert wait_for(lambda: len(down_inbox.snapshot()) == 1)
            assert down_inbox.snapshot() == [(f"{UW}/factor/v2/7", b"factor-for-v2")]
            pub.undeclare()
            factor_pub.undeclare()
        finally:
            up_sub.undeclare()
            down_sub.undeclare()
        stats = bridge.stats()
    assert stats.published == {"uplink": 1, "downlink": 1}
    assert stats.link["messages_delivered"] == 2
    # The bridge's own republications were not bridged back (no loop).
    assert stats.received == {"uplink": 1, "downlink": 1}


def test_bridge_loses_but_never_corrupts() -> None:
    config = LinkConfig.model_validate(
        {
            "channel": {
                "rate": 1,
                "corrupt_bad_frame_prob": 1.0,
                "snr": {"mean_db": 0.0},
                "link_snr": {
                    "v1->topside": {"mean_db": -6.9, "spread_db": 0.3},  # lossy
                    "v2->topside": {"mean_db": -20.0},  # nothing gets through
                },
            },
            "tdma": {"slot_order": ["topside", "v1", "v2"]},
            "arq": {"max_tx_per_fragment": 3, "max_queue_messages": 32},
        }
    )
    inbox = Inbox()
    losses: list[tuple[Direction, str, LossEvent]] = []
    with _bridge_network(config, on_lost=lambda *a: losses.append(a)) as (bridge, vehicle, topside):
        sub = topside.declare_subscriber(f"{TOP}/submap/**", inbox)
        try:
            sent: dict[str, bytes] = {}
            rng = np.random.default_rng(2)
            pub = _matched_publisher(vehicle, f"{UW}/submap/v1/s0/0")
            for k in range(8):
                robot = "v1" if k < 6 else "v2"
                key = f"{UW}/submap/{robot}/s0/{k}"
                sent[key.replace(UW, TOP)] = payload = rng.bytes(150)
                vehicle.put(key, payload)

            def resolved() -> bool:
                link = bridge.stats().link
                done = link["messages_delivered"] + link["messages_lost"] == len(sent)
                return done and len(inbox.snapshot()) == link["messages_delivered"]

            assert wait_for(resolved, 30.0)
            pub.undeclare()
        finally:
            sub.undeclare()
        stats = bridge.stats()
    received = inbox.snapshot()
    assert all(sent[key] == payload for key, payload in received)
    assert not any("/v2/" in key for key, _ in received)
    assert len(received) == stats.link["messages_delivered"] == stats.published["uplink"]
    assert stats.link["corrupt_deliveries"] == 0
    assert stats.link["frames_crc_failed"] > 0  # corrupted frames reached the receiver
    lost_suffixes = {suffix for _, suffix, _ in losses}
    assert {"submap/v2/s0/6", "submap/v2/s0/7"} <= lost_suffixes
    assert stats.lost["uplink"] == len(losses) == stats.link["messages_lost"]


def test_bridge_rejects_bad_arguments() -> None:
    config = LinkConfig()
    with pytest.raises(ConfigError):
        AcousticBridge(config, uw_prefix="a/uw/", top_prefix="a", time_scale=0.1)
    with pytest.raises(ConfigError):
        AcousticBridge(config, uw_prefix="a/uw", top_prefix="a", time_scale=0.0)
    with pytest.raises(ConfigError):
        AcousticBridge(config, uw_prefix="a/uw", top_prefix="a", topside="ship")


def test_make_zenoh_config_maps_errors() -> None:
    with pytest.raises(ConfigError):
        make_zenoh_config(mode="bogus")
    with pytest.raises(InputError):  # a malformed endpoint is bad input, before zenoh sees it
        make_zenoh_config(connect=["not-an-endpoint"])
    config = make_zenoh_config(mode="client", connect=["tcp/127.0.0.1:7447"], scouting=False)
    assert json.loads(config.get_json("scouting/multicast/enabled")) is False


def test_public_names_are_exported() -> None:
    import mergesvc.link as link

    assert all(hasattr(link, name) for name in link.__all__)
    public = {
        name
        for name, obj in vars(link).items()
        if not name.startswith("_")
        and getattr(obj, "__module__", None) == link.__name__
        and name != "log"
    }
    assert public <= set(link.__all__)


def test_the_sweep_table_says_dash_where_nothing_was_delivered() -> None:
    """No delivered message, no latency to print: '-', not nan."""
    from mergesvc.link.workload import SweepRow

    row = SweepRow(ModemRate(5), 2.0, 1.0, 10, 0, 10, 0.0, float("nan"), float("nan"), 0.0, 0, 0)
    line = format_sweep_table([row]).splitlines()[-1]
    assert "nan" not in line and line.split()[7:9] == ["-", "-"]
