"""`mergesvc view`: join a fleet and show its merged map live in Rerun (mergesvc/view/,
docs/view.md): a native viewer, the web viewer (`--serve-web`), or an .rrd file (`--save`)."""

from __future__ import annotations

import errno
import json
import os
import time
from pathlib import Path
from typing import Annotated

import typer

from mergesvc.cli.errors import exit_on_error
from mergesvc.cli.options import (
    DEFAULT_ENDPOINT,
    Connect,
    ConnectTimeout,
    FleetName,
    Listen,
    ZenohConfigFile,
    ZenohMode,
    stop_on_signals,
    zenoh_config,
    zenoh_mode,
)

__all__ = ["view"]

ViewMode = zenoh_mode("zenoh mode")


def view(
    fleet: FleetName = "fleet0",
    mode: ViewMode = ZenohMode.CLIENT,
    connect: Connect = None,
    listen: Listen = None,
    config: ZenohConfigFile = None,
    connect_timeout: ConnectTimeout = None,
    projection: Annotated[
        list[Path] | None, typer.Option(help="fleet projection(s): compact submaps need it")
    ] = None,
    save: Annotated[
        Path | None, typer.Option(help="record into this .rrd file instead of a viewer")
    ] = None,
    serve_web: Annotated[
        bool, typer.Option(help="serve the web viewer (http on --web-port, gRPC on "
                                "--grpc-port, every interface) instead of a native one")
    ] = False,
    web_port: Annotated[int, typer.Option(help="port of the web viewer's page")] = 9090,
    grpc_port: Annotated[int, typer.Option(help="port of the viewer's gRPC stream")] = 9876,
    duration: Annotated[
        float | None, typer.Option(min=0.0, help="stop after this many s (default: at Ctrl-C)")
    ] = None,
    status_period: Annotated[
        float, typer.Option(min=0.01, help="seconds between two status queries (merged poses)")
    ] = 1.0,
) -> None:
    """Show a fleet's merged map live in Rerun: trajectories (odometry and merged), objects
    coloured by robot, correspondences, factors accepted and retracted, latency. Joins as a
    Zenoh client of tcp/127.0.0.1:7447 unless told otherwise.

    Needs pip install 'mergesvc[view]'. Prints one JSON line of counts when it stops."""
    from mergesvc.view import LiveView, ViewSink, ZenohFeed
    from mergesvc.wire import Projection
    from mergesvc.wire.session import open_session

    stop = stop_on_signals()
    with exit_on_error(ValueError, OSError):
        projections = [Projection.load(p) for p in projection or []]
        zconf = zenoh_config(mode, connect, listen, config,
                             default_connect=(DEFAULT_ENDPOINT,), connect_timeout=connect_timeout)
        if save is not None:
            _check_writable(save)
        sink = ViewSink(save=save, web=serve_web, web_port=web_port, grpc_port=grpc_port)
        # the session first: a fleet that cannot be reached opens no viewer
        with open_session(zconf) as session, LiveView.open(sink) as live:
            feed = ZenohFeed(live, session, fleet, projections, status_period_s=status_period)
            with feed:
                where = (live.url if serve_web else None) or (str(save) if save else "viewer")
                typer.echo(f"viewing fleet {fleet} -> {where}")
                start = time.monotonic()
                while not stop.is_set() and (
                        duration is None or time.monotonic() - start < duration):
                    stop.wait(0.2)
                feed.poll_status()  # the recording ends with the latest merged state
            typer.echo(json.dumps({"fleet": fleet, **vars(feed.stats),
                                   "saved": str(save) if save else None}))
            if not (feed.stats.statuses or feed.stats.submaps or feed.stats.factors):
                typer.echo(f"warning: nothing of fleet {fleet} came (no status, submap or "
                           f"factor): is a service running on that fleet there?", err=True)


def _check_writable(path: Path) -> None:
    """OSError (naming `path`) unless a file can be written there: said before anything
    connects, and before Rerun, whose own refusal comes with a log line of its own."""
    folder = path.parent
    fault = (errno.EISDIR if path.is_dir() else errno.ENOENT if not folder.exists()
             else errno.ENOTDIR if not folder.is_dir()
             else errno.EACCES if not os.access(folder, os.W_OK)
             or (path.exists() and not os.access(path, os.W_OK)) else None)
    if fault is not None:
        raise OSError(fault, os.strerror(fault), str(path))
