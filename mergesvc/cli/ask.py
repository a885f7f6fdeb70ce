"""`mergesvc status` and `mergesvc relocalize`: a running service's two queries from a shell
(docs/wire.md §11.3), one line or the reply as JSON; when no service answers, one line that
says what to do and exit 3."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any

import typer

from mergesvc.cli.errors import EXIT_BAD_INPUT, EXIT_FAILED, exit_on_error, fail
from mergesvc.cli.options import (
    DEFAULT_ENDPOINT,
    Connect,
    ConnectTimeout,
    FleetName,
    ZenohConfigFile,
    ZenohMode,
    zenoh_config,
    zenoh_mode,
)
from mergesvc.errors import MergeError
from mergesvc.wire.names import Profile

QueryMode = zenoh_mode("zenoh mode")

QueryTimeout = Annotated[float, typer.Option(min=0.1, help="seconds to wait for the answer")]


def _ask(mode: ZenohMode, connect: list[str] | None, config: Path | None,
         connect_timeout: float | None, fleet: str, what: str, payload: bytes | None,
         timeout: float) -> tuple[bool, dict[str, Any]]:
    """One query to a running service's `what` queryable (status?poses=..., relocalize):
    (ok, its JSON reply); a TransportError, saying what to do, when no service answers."""
    from mergesvc.errors import TransportError, TransportFault
    from mergesvc.wire import keys
    from mergesvc.wire.session import open_session

    zconf = zenoh_config(mode, connect, None, config, default_connect=(DEFAULT_ENDPOINT,),
                         connect_timeout=connect_timeout)
    with open_session(zconf) as session:
        for reply in session.get(f"{keys.fleet_root(fleet)}/{what}", payload=payload,
                                 timeout=timeout):
            sample = reply.ok if reply.ok is not None else reply.err
            return reply.ok is not None, json.loads(sample.payload.to_bytes())
    raise TransportError(f"no service of fleet {fleet} answered within {timeout:g} s (is "
                         f"`mergesvc serve --fleet {fleet}` running there?)",
                         fault=TransportFault.NO_ANSWER)


def status(
    fleet: FleetName = "fleet0",
    mode: QueryMode = ZenohMode.CLIENT,
    connect: Connect = None,
    config: ZenohConfigFile = None,
    connect_timeout: ConnectTimeout = None,
    poses: Annotated[bool, typer.Option(help="with every keyframe's pose (--json)")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="the whole reply as JSON")] = False,
    timeout: QueryTimeout = 5.0,
) -> None:
    """Ask a running service how it is: one line (submaps, factors, robots alive), or with
    --json its whole status reply (docs/wire.md §11.3)."""
    from mergesvc.fleet.replies import status_line

    with exit_on_error(ValueError):  # (a reply that is not JSON)
        _, doc = _ask(mode, connect, config, connect_timeout, fleet,
                      f"status?poses={str(poses).lower()}", None, timeout)
    typer.echo(json.dumps(doc) if as_json else f"fleet {fleet}: {status_line(doc)}")


def relocalize(
    submap: Annotated[Path, typer.Option(help="a submap JSON file of the new session (its "
                                              "robot_id, session_id and objects)")],
    fleet: FleetName = "fleet0",
    mode: QueryMode = ZenohMode.CLIENT,
    connect: Connect = None,
    config: ZenohConfigFile = None,
    connect_timeout: ConnectTimeout = None,
    timeout: QueryTimeout = 10.0,
) -> None:
    """Ask a running service where a submap of a new session lies in its map: the reply as
    JSON (docs/wire.md §11.3); exit 1 when it is not localized."""
    from mergesvc.core.model import Submap
    from mergesvc.wire import encode_message
    from mergesvc.wire.files import load_model

    with exit_on_error(ValueError, OSError):
        sub = load_model(Submap, submap)
        blob = encode_message(sub, Profile.FULL, sub.robot_id, sub.seq or 0)
        ok, doc = _ask(mode, connect, config, connect_timeout, fleet, "relocalize", blob,
                       timeout)
    if not ok:  # the service's error reply (docs/wire.md §7)
        fail(MergeError(f"the service refused the query: {doc.get('detail') or doc}"),
             EXIT_BAD_INPUT)
    typer.echo(json.dumps(doc))
    if not doc.get("localized"):
        raise typer.Exit(EXIT_FAILED)


__all__ = ["relocalize", "status"]
