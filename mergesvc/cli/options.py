"""Options shared by several commands, defined once.

The Zenoh flags follow the zenoh-python examples: every program that opens a session takes
`--mode/--connect/--listen/--config`, and `zenoh_config` turns them into a `zenoh.Config`.
`serve`, `agent` and `link bridge` take them. The factories keep the help text each command
has always shown; the plain aliases carry the usual one.
"""

from __future__ import annotations

from collections.abc import Sequence
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

if TYPE_CHECKING:
    import zenoh

__all__ = [
    "Connect",
    "LinkKind",
    "Listen",
    "Mode",
    "ZenohConfigFile",
    "ZenohMode",
    "zenoh_config",
    "zenoh_connect",
    "zenoh_mode",
]

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"


class ZenohMode(str, Enum):
    """Zenoh session mode."""

    ROUTER = "router"
    PEER = "peer"
    CLIENT = "client"


class LinkKind(str, Enum):
    """How the demo's vehicles reach the service."""

    ZENOH = "zenoh"
    ACOUSTIC = "acoustic"  # through the simulated modem


def zenoh_mode(help_text: str = "zenoh mode: router, peer or client") -> Any:
    """`--mode`, typed so typer checks and lists router|peer|client."""
    return Annotated[ZenohMode, typer.Option("--mode", help=help_text)]


def zenoh_connect(help_text: str = "zenoh endpoint(s)") -> Any:
    """`--connect EP`, repeatable."""
    return Annotated[list[str] | None, typer.Option("--connect", help=help_text)]


Mode = zenoh_mode()
Connect = zenoh_connect()
Listen = Annotated[list[str] | None, typer.Option("--listen", help="zenoh listen endpoint(s)")]
ZenohConfigFile = Annotated[Path | None, typer.Option("--config", help="zenoh JSON5 config file")]


def zenoh_config(
    mode: ZenohMode | None,
    connect: Sequence[str] | None,
    listen: Sequence[str] | None,
    config: Path | None,
    *,
    default_connect: Sequence[str] = (),
    scouting: bool | None = None,
) -> zenoh.Config:
    """The Zenoh flags as a `zenoh.Config` (raises ConfigError). `default_connect` applies when
    no --connect is given; `scouting=None` means scouting stays on unless a --config file is
    given (what serve and agent have always done)."""
    from mergesvc.wire.session import make_zenoh_config

    return make_zenoh_config(
        config_file=str(config) if config else None,
        mode=mode.value if mode is not None else None,
        connect=tuple(connect or default_connect),
        listen=tuple(listen or ()),
        scouting=config is None if scouting is None else scouting,
    )
