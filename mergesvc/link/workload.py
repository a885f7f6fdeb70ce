"""Benchmark drivers: periodic `Workload`s run on the simulated clock, and rate x SNR sweeps.

`simulate_workload` runs one workload through a `LinkSimulator`; `sweep_link` repeats it for each
modem rate and SNR and `format_sweep_table` prints the result.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from pydantic import Field

from mergesvc.errors import ConfigError
from mergesvc.link.arq import MAX_MESSAGE_BYTES
from mergesvc.link.config import LinkConfig, _Section
from mergesvc.link.modem import ModemRate, frame_error_prob
from mergesvc.link.simulator import LinkSimulator, LinkStats


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


def _seconds(x: float) -> str:
    """A latency column: "-" where nothing was delivered to measure."""
    return f"{x:>8.1f}" if math.isfinite(x) else f"{'-':>8}"


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
            f"{_seconds(r.latency_p50_s)} {_seconds(r.latency_p90_s)} {r.goodput_bps:>11.2f} "
            f"{r.fragments_retransmitted:>6} {r.bytes_on_air / 1000:>8.1f}"
        )
    return "\n".join(lines)


__all__ = [
    "DEFAULT_SWEEP_SNR_DB",
    "SweepRow",
    "Workload",
    "format_sweep_table",
    "simulate_workload",
    "sweep_link",
]
