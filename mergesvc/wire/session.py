"""Opening Zenoh sessions: a zenoh Config from the shared --config/--mode/--connect/--listen flags.

May import: zenoh, the standard library, mergesvc.errors.
"""

from __future__ import annotations

import json
from collections.abc import Sequence

import zenoh

from mergesvc.errors import ConfigError


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


__all__ = ["make_zenoh_config"]
