"""Helpers shared by the tests that open real Zenoh sessions on 127.0.0.1 (test_service,
test_link, test_deploy): bounded waits, free loopback ports, quiet session configs and a sample
inbox. Imported as `from helpers import ...` (pytest puts tests/ on sys.path)."""

from __future__ import annotations

import io
import json
import logging
import socket
import subprocess
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh
import zenoh.handlers


def wait_for(predicate: Callable[[], bool], timeout_s: float = 20.0, step_s: float = 0.1) -> bool:
    """Poll `predicate` every `step_s` until it holds or `timeout_s` is up; one last try at the
    deadline. `step_s=0` for a predicate that waits a little itself."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(step_s)
    return predicate()


def free_port() -> int:
    """A TCP port free on 127.0.0.1 right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def set_json(config: zenoh.Config, key: str, value: Any) -> zenoh.Config:
    """`config[key] = value` (value as JSON); returns the config."""
    config.insert_json5(key, json.dumps(value))
    return config


def quiet(config: zenoh.Config) -> zenoh.Config:
    """Test sessions: no multicast or gossip scouting, no scouting delay."""
    set_json(config, "scouting/multicast/enabled", False)
    set_json(config, "scouting/gossip/enabled", False)
    return set_json(config, "scouting/delay", 0)


def zenoh_config(mode: str, listen: str | None = None, connect: str | None = None) -> zenoh.Config:
    """A quiet session config: `mode`, listening on / connecting to one endpoint."""
    config = set_json(zenoh.Config(), "mode", mode)
    if listen:
        set_json(config, "listen/endpoints", [listen])
    if connect:
        set_json(config, "connect/endpoints", [connect])
    return quiet(config)


class Inbox:
    """(key, payload) of the samples a subscriber got, in arrival order, with bounded waits.

    Pass `inbox.handler` (or the inbox itself) to `declare_subscriber`. `handler` runs the
    callback in Zenoh's network thread: a plain Python callable gets a thread of its own per
    subscriber, so samples reaching one session through two subscribers can be recorded out of
    order; through `handler` they are recorded in the order the session received them."""

    def __init__(self) -> None:
        self.items: list[tuple[str, bytes]] = []
        self._cond = threading.Condition()

    def __call__(self, sample: zenoh.Sample) -> None:
        with self._cond:
            self.items.append((str(sample.key_expr), sample.payload.to_bytes()))
            self._cond.notify_all()

    @property
    def handler(self) -> zenoh.handlers.Callback:
        return zenoh.handlers.Callback(self, indirect=False)

    @property
    def keys(self) -> list[str]:
        with self._cond:
            return [key for key, _ in self.items]

    def snapshot(self) -> list[tuple[str, bytes]]:
        with self._cond:
            return list(self.items)

    def wait_for(self, key: str, timeout_s: float, payload: bytes | None = None) -> bool:
        """Whether a sample on `key` (with `payload`, if given) came within `timeout_s`."""

        def arrived() -> bool:
            return any(k == key and payload in (None, p) for k, p in self.items)

        with self._cond:
            return self._cond.wait_for(arrived, timeout_s)


_STREAMS: dict[tuple[int, int], tuple[Any, list[Any]]] = {}


def cost_stream(n: int, seed: int, robots: int) -> list[Any]:
    """The first n submaps of `mergesvc bench cost`'s seeded pool stream (z-up vehicles). Built
    once per test process and stream: a longer request extends what was built (the stream is
    seeded, so its first n never change); callers must not change the submaps."""
    from mergesvc.bench.cost import CostBenchPlan, SubmapStream
    from mergesvc.fleet.agent import AgentConfig, build_submaps

    def vehicle(robot: str, session: str, frames: Any) -> list[Any]:
        cfg = AgentConfig(robot=robot, session=session, up=(0.0, 0.0, 1.0))
        return build_submaps(cfg, frames)[1]

    if (seed, robots) not in _STREAMS:
        stream = SubmapStream(CostBenchPlan(seed=seed, robots=robots), seed, vehicle)
        _STREAMS[seed, robots] = (iter(stream), [])
    it, built = _STREAMS[seed, robots]
    while len(built) < n:
        try:
            built.append(next(it))
        except StopIteration:
            break
    return list(built[:n])


def run_cli(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """`mergesvc ARGS` in this process (typer's runner: what `main` does, without a process's
    start-up), with `env` added to the environment for its duration; stdout apart from stderr,
    which also gets the log lines the process would print. Tests of what only a process shows
    (the entry point, signals, imports) start one instead."""
    from typer.testing import CliRunner

    from mergesvc.cli import app, hoist_verbose

    argv = hoist_verbose(list(args))
    verbose = sum(2 if a == "-vv" else 1 for a in argv if a in ("-v", "-vv", "--verbose"))
    level = logging.WARNING - 10 * min(verbose, 2)
    logs = io.StringIO()  # what the process would print on stderr through logging
    handler = logging.StreamHandler(logs)
    handler.setLevel(level)
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    old_level = root.level
    root.addHandler(handler)
    root.setLevel(min(level, old_level))
    try:
        r = CliRunner().invoke(app, argv, env=env)
    finally:
        root.removeHandler(handler)
        root.setLevel(old_level)
    if r.exception is not None and not isinstance(r.exception, SystemExit):
        raise r.exception
    return subprocess.CompletedProcess(list(args), r.exit_code, r.stdout,
                                       logs.getvalue() + r.stderr)
