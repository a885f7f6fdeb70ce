"""The acoustic link: modem channel model, ARQ framing, event simulator, Zenoh bridge.

A WHOI Micro-Modem channel, selective-repeat ARQ over TDMA, and a Zenoh bridge. Layers, bottom
up: `AcousticChannel` (rates, airtime, propagation, frame losses; `channel`, `modem`) ->
fragment/ack wire format (`encode_fragment`, `encode_ack`; `arq`) -> `LinkSimulator` (TDMA slots,
selective-repeat ARQ, discrete events on a simulated clock; `simulator`) -> `AcousticBridge` (the
simulator run in scaled real time between two Zenoh key spaces; `bridge`). `simulate_workload`
and `sweep_link` are the benchmark drivers (`workload`); `config` holds the pydantic settings.

May import: mergesvc.wire, mergesvc.core, mergesvc.errors.
"""

from mergesvc.link.bridge import AcousticBridge
from mergesvc.link.config import ArqConfig, ChannelConfig, LinkConfig, SnrModel, TdmaConfig
from mergesvc.link.modem import RATE_SPECS, ModemRate, frame_error_prob
from mergesvc.link.workload import (
    DEFAULT_SWEEP_SNR_DB,
    Workload,
    format_sweep_table,
    sweep_link,
)

__all__ = [
    "DEFAULT_SWEEP_SNR_DB",
    "RATE_SPECS",
    "AcousticBridge",
    "ArqConfig",
    "ChannelConfig",
    "LinkConfig",
    "ModemRate",
    "SnrModel",
    "TdmaConfig",
    "Workload",
    "format_sweep_table",
    "frame_error_prob",
    "sweep_link",
]
