"""The multi-robot demo: a merge service and three vehicles as separate processes on loopback
(optionally through the acoustic-link bridge), a seeded pool mission, and a summary scored
against the ground truth (fleet/demo_score.py): submaps, bytes, factors, precision, each
robot's trajectory error and the fleet's, and a PNG of the merged map. Once the service has
stopped, its store is exported (fleet/export.py) into OUT/export: the global pose graph in g2o
and each session's TUM trajectories.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mergesvc.core.model import Factor
from mergesvc.errors import MergeError
from mergesvc.fleet.config import ServiceConfig
from mergesvc.fleet.demo_score import (
    ROBOTS,
    SESSION,
    DemoPlan,
    add_received_odometry,
    plot_merged,
    score_demo,
    score_trajectories,
    trajectory_lines,
)
from mergesvc.sim import survey_embeddings
from mergesvc.wire import Projection, decode_message, keys

log = logging.getLogger(__name__)

STORE_FILE = "merge.db"
EXPORT_DIR = "export"  # export_store's files: beside, not over, OUT/trajectories


class DemoError(RuntimeError):
    """The demo could not run: the service exited at start or did not come up."""


@dataclass
class DemoResult:
    ok: bool
    summary: dict[str, Any] = field(default_factory=dict)
    failures: list[str] = field(default_factory=list)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def fleet_projection(seed: int, path: Path, k: int | None = None) -> Projection:
    """The fleet-shared embedding projection, learned from earlier survey data of the world
    (not from this mission's submaps) and versioned by its content id."""
    proj = Projection.fit(survey_embeddings(seed), k)  # = mergesvc projection make --survey
    proj.save(path)
    return proj


def _zenoh_client(endpoint: str) -> Any:
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    return zenoh.open(conf)


def query_status(session: Any, fleet: str, timeout_s: float = 3.0) -> dict[str, Any] | None:
    for reply in session.get(keys.status_key(keys.fleet_root(fleet)), timeout=timeout_s):
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_bytes())
    return None


def run_demo(plan: DemoPlan, out_dir: Path, echo: Callable[[str], Any] = print,
             attach: Callable[[Any, str, Path], Callable[[], None]] | None = None) -> DemoResult:
    """Start everything, run the mission, score it, stop everything (always), then export the
    service's store into OUT/export (solved with `plan.service`). `attach(session, fleet,
    projection_file)` joins an observer (the live view) to the demo's session once the service
    answers, before the vehicles start; what it returns detaches it when the service is idle."""
    import zenoh

    out_dir.mkdir(parents=True, exist_ok=True)
    fleet = plan.fleet
    endpoint = plan.listen or f"tcp/127.0.0.1:{free_port()}"
    proj_path = out_dir / "projection.npz"
    fleet_projection(plan.seed, proj_path)
    store = out_dir / STORE_FILE
    for p in out_dir.glob("merge.db*"):
        p.unlink()
    cli = [sys.executable, "-m", "mergesvc.cli"]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    procs: dict[str, subprocess.Popen] = {}
    logs: dict[str, Path] = {}

    def spawn(name: str, args: list[str]) -> None:
        logs[name] = out_dir / f"{name}.log"
        fh = logs[name].open("w")
        procs[name] = subprocess.Popen([*cli, "-v", *args], stdout=fh, stderr=subprocess.STDOUT,
                                       env=env, start_new_session=True)

    result = DemoResult(ok=False)
    t_start = time.monotonic()
    session = None
    detach: Callable[[], None] | None = None
    factors: dict[str, Factor] = {}
    try:
        spawn("service", ["serve", "--fleet", fleet, "--store", str(store), "--mode", "router",
                          "--listen", endpoint, "--projection", str(proj_path)])
        session = _wait_for_service(endpoint, fleet, procs["service"], deadline_s=30.0)
        echo(view_command(endpoint, fleet, proj_path))
        if attach is not None:
            detach = attach(session, fleet, proj_path)

        def on_factor(sample: Any) -> None:
            try:
                _, f = decode_message(sample.payload.to_bytes())
                if isinstance(f, Factor):
                    factors[f.factor_id] = f
            except MergeError as exc:  # counted by the summary as missing factors
                log.warning("demo: undecodable factor: %s", exc)

        sub = session.declare_subscriber(keys.all_factors(keys.fleet_root(fleet)), on_factor)
        if plan.link == "acoustic":
            spawn("bridge", ["link", "bridge", "--fleet", fleet, "--rate", "5", "--snr-db", "5.0",
                             "--time-scale", str(plan.time_scale), "--connect", endpoint,
                             *[x for r in ROBOTS for x in ("--vehicles", r)]])
            time.sleep(1.0)
        for r in ROBOTS:
            spawn(r, ["agent", "--robot", r, "--fleet", fleet, "--session", SESSION,
                      "--seed", str(plan.seed),
                      "--laps", str(plan.laps), "--objects", str(plan.n_objects),
                      "--profile", plan.profile.value, "--projection", str(proj_path),
                      "--time-scale", str(plan.time_scale), "--connect", endpoint,
                      *(["--acoustic"] if plan.link == "acoustic" else [])])
        echo(f"service and {len(ROBOTS)} vehicles running on {endpoint} "
             f"({plan.link} link, {plan.profile.value} codec)")
        deadline = t_start + plan.timeout_s
        for r in ROBOTS:
            code = procs[r].wait(timeout=max(deadline - time.monotonic(), 1.0))
            if code != 0:
                result.failures.append(f"{r} exited with {code} (see {logs[r]})")
        status = _wait_until_idle(session, fleet, deadline, procs)
        if detach is not None:
            detach, d = None, detach
            d()
        sub.undeclare()
        if status is None:
            result.failures.append("the service did not answer its status query")
            return result
        result.summary = score_demo(plan, status, factors, logs, out_dir)
        result.summary["elapsed_s"] = round(time.monotonic() - t_start, 1)
        if result.summary["factors_accepted"] == 0:
            result.failures.append("no factor was accepted")
    except subprocess.TimeoutExpired as exc:
        result.failures.append(f"timed out: {exc}")
    # what a run can meet and still report: the service not coming up (DemoError), Zenoh
    # (ZError), files and processes (OSError), our own errors; anything else is a bug and
    # keeps its traceback (the processes are stopped below either way)
    except (DemoError, zenoh.ZError, OSError, MergeError) as exc:
        result.failures.append(f"{type(exc).__name__}: {exc}")
    finally:
        if detach is not None:
            detach()
        if session is not None:
            with contextlib.suppress(zenoh.ZError):
                session.close()
        for name, p in procs.items():
            _stop(p)
            if name == "service" and p.returncode not in (0, -signal.SIGINT, -signal.SIGTERM):
                result.failures.append(f"service exited with {p.returncode} (see {logs[name]})")
    if store.exists():
        _export(store, out_dir / EXPORT_DIR, proj_path, plan.service, result)
    if result.summary:
        # the odometry as the service received it (the export's): what the merge started from
        if result.summary.get("exports"):
            add_received_odometry(result.summary, out_dir / EXPORT_DIR)
        for line in trajectory_lines(result.summary):
            echo(line)
    result.ok = not result.failures
    (out_dir / "summary.json").write_text(json.dumps(
        {"ok": result.ok, "failures": result.failures, **result.summary}, indent=1,
        default=float))
    return result


def view_command(endpoint: str, fleet: str, projection: Path) -> str:
    """The line that attaches a live view to a running demo (docs/view.md)."""
    return (f"live view, from another terminal while the demo runs (`--view` opens one "
            f"itself): mergesvc view --connect {endpoint} --fleet {fleet} "
            f"--projection {projection}")


def _export(store: Path, out: Path, proj_path: Path, config: ServiceConfig | None,
            result: DemoResult) -> None:
    """The stopped service's store as g2o and TUM files (their paths: summary["exports"])."""
    from mergesvc.fleet.export import export_store

    try:
        res = export_store(store, out, config=config,
                           projections=[Projection.load(proj_path)])
    except (MergeError, OSError, ValueError) as exc:
        result.failures.append(f"export: {type(exc).__name__}: {exc}")
        return
    result.summary["exports"] = [str(p) for p in res.files]


def _stop(p: subprocess.Popen) -> None:
    if p.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(p.pid, signal.SIGINT)
        try:
            p.wait(timeout=8.0)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGKILL)
            p.wait(timeout=5.0)


def _wait_for_service(endpoint: str, fleet: str, proc: subprocess.Popen,
                      deadline_s: float) -> Any:
    import zenoh

    end = time.monotonic() + deadline_s
    while time.monotonic() < end:
        if proc.poll() is not None:
            raise DemoError(f"the service exited with {proc.returncode} at start")
        try:
            session = _zenoh_client(endpoint)
        except zenoh.ZError:  # its router is not listening yet
            time.sleep(0.3)
            continue
        if query_status(session, fleet, 1.0) is not None:
            return session
        session.close()
        time.sleep(0.3)
    raise DemoError("the service did not come up")


def _wait_until_idle(session: Any, fleet: str, deadline: float,
                     procs: dict[str, subprocess.Popen]) -> dict[str, Any] | None:
    """Until every received submap is processed (or the deadline)."""
    last = None
    stable = 0
    while time.monotonic() < deadline:
        if procs["service"].poll() is not None:
            return last
        st = query_status(session, fleet, 2.0)
        if st is not None:
            s = st["submaps"]
            done = s["processed"] + s["duplicate"] + s["rejected"]
            idle = s["queued"] == 0 and done >= s["received"]
            same = last is not None and last["submaps"] == s
            last = st
            stable = stable + 1 if idle and same else 0
            if stable >= 2:
                return st
        time.sleep(0.5)
    return last


__all__ = [
    "DemoError",
    "DemoPlan",
    "DemoResult",
    "fleet_projection",
    "free_port",
    "plot_merged",
    "query_status",
    "run_demo",
    "score_demo",
    "score_trajectories",
    "trajectory_lines",
    "view_command",
]
