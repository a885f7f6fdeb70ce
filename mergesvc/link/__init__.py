"""The acoustic link: modem channel model, ARQ framing, event simulator, Zenoh bridge.

May import: mergesvc.wire, mergesvc.core, mergesvc.errors.
"""

from mergesvc.link.acoustic import (
    DEFAULT_SWEEP_SNR_DB,
    RATE_SPECS,
    AcousticBridge,
    ArqConfig,
    ChannelConfig,
    LinkConfig,
    ModemRate,
    SnrModel,
    TdmaConfig,
    Workload,
    format_sweep_table,
    frame_error_prob,
    make_zenoh_config,
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
    "make_zenoh_config",
    "sweep_link",
]
