"""`mergesvc bench soak`: a real `mergesvc serve` process (its own store, an embedded router on
a free loopback port) under N robots publishing keyframe submaps at their own seeded rates
through the agents' advanced publisher, K robots of another embedding model (the service pins
its model: they must be refused), an attacker sending hostile payloads, and SIGKILL restarts at
seeded moments; then a drain, SIGTERM, and the judgement (bench/soak_report.py). Traffic:
bench/soak_world.py. Targets: no valid submap lost, failed, pending or duplicated; every
hostile payload refused and answered; the other model refused and nobody else; RSS growth
without the clients' shared memory under 100 MB (docs/benchmarks/soak.md says why).
`SoakPlan.quick()` is the test's variant.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import resource
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mergesvc.bench.soak_report import Ledger, build_report, plot_soak, soak_summary
from mergesvc.bench.soak_world import (
    CACHE_SAMPLES,
    FLOOD_ROBOT,
    HEARTBEAT_S,
    HOSTILE_ROBOTS,
    HOSTILE_SEQ0,
    LARGE_ROBOT,
    HostileKind,
    RobotWalk,
    SoakPlan,
    SoakWorld,
    agent_publisher,
    flood_payloads,
    hostile_payload,
    hostile_schedule,
    large_submap,
)
from mergesvc.errors import MergeError, StoreError
from mergesvc.store import StoreReader
from mergesvc.wire import Profile, encode_message, keys
from mergesvc.wire.session import make_zenoh_config

log = logging.getLogger(__name__)

#: How long the attacker may take, once the run's time is up, to send the payloads its schedule
#: had left (held back by a kill near the end): back to back, so a few seconds are plenty.
HOSTILE_OVERTIME_S = 10.0


def _proc_status_bytes(pid: int, field: str) -> int | None:
    """A kB field of /proc/<pid>/status in bytes; None when the process is gone or the kernel
    does not say."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(f"{field}:"):
                return int(line.split()[1]) * 1024
    except OSError:
        return None
    return None


def shmem_bytes(pid: int) -> int | None:
    """The part of process `pid`'s RSS in shared memory (RssShmem: the Zenoh shared memory
    pools of same-host clients it maps); None when it is gone or the kernel does not say."""
    return _proc_status_bytes(pid, "RssShmem")


def rss_bytes(pid: int) -> int | None:
    """Resident set size of process `pid` (None when it is gone)."""
    try:
        import psutil
    except ImportError:
        psutil = None
    if psutil is not None:
        try:
            return int(psutil.Process(pid).memory_info().rss)
        except psutil.Error:
            return None
    return _proc_status_bytes(pid, "VmRSS")


def family_rss_bytes(pid: int) -> int | None:
    """RSS of process `pid` and of its children (the service's solver process)."""
    own = rss_bytes(pid)
    if own is None:
        return None
    kids = []  # Linux files a child under the thread that started it: read every thread's
    for task in Path(f"/proc/{pid}/task").glob("*/children"):
        with contextlib.suppress(OSError):
            kids += task.read_text().split()
    return own + sum(rss_bytes(int(k)) or 0 for k in kids)


class ServiceProcess:
    """`mergesvc serve` as a subprocess on one store and one endpoint, started again after
    each kill; its output appended to `log_path`."""

    def __init__(self, command: Sequence[str], fleet: str, store: Path, endpoint: str,
                 zenoh_file: Path, log_path: Path, env: dict[str, str],
                 extra_args: Sequence[str] = ()) -> None:
        self.args = [*command, "serve", "--fleet", fleet, "--store", str(store), "--listen",
                     endpoint, "--config", str(zenoh_file), *extra_args]
        self.env, self.log_path = env, log_path
        self.proc: subprocess.Popen | None = None
        self.starts = 0

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc is not None and self.proc.poll() is None else None

    def start(self, file_limit_bytes: int | None = None, log_path: Path | None = None) -> None:
        """Start it; with `file_limit_bytes` its files may not grow past that size (the
        kernel's RLIMIT_FSIZE: a write beyond it fails with EFBIG, SIGXFSZ ignored), as on a
        full disk, its output then going to `log_path` (the run's log may be larger)."""
        def limit() -> None:
            if file_limit_bytes is not None:
                signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
                resource.setrlimit(resource.RLIMIT_FSIZE, (file_limit_bytes, file_limit_bytes))

        with (log_path or self.log_path).open("ab") as out:
            self.proc = subprocess.Popen(self.args, stdout=out, stderr=subprocess.STDOUT,
                                         env=self.env, start_new_session=True,
                                         preexec_fn=limit if file_limit_bytes else None)
        self.starts += 1

    def kill(self) -> None:
        """SIGKILL: no clean shutdown."""
        if self.proc is not None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.proc.pid, signal.SIGKILL)
            self.proc.wait(timeout=30)

    def stop(self, timeout_s: float = 60.0) -> int | None:
        """SIGTERM, then SIGKILL after `timeout_s`; the exit code."""
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.kill()
        return self.proc.returncode


# ------------------------------------------------------------------------------ the run


def _seeds(seed: int, n: int) -> list[np.random.Generator]:
    return [np.random.default_rng(s) for s in np.random.SeedSequence([seed, 7]).spawn(n)]


class _Gate:
    """Pauses the attacker: `hold()` blocks new hostile sends until released."""

    def __init__(self) -> None:
        self._open = threading.Event()
        self._open.set()
        self.busy = threading.Lock()  # held by the attacker while it sends one payload
        self.calm = threading.Event()  # cleared while the disk is full: the flood waits
        self.calm.set()

    def wait_open(self, stop: threading.Event) -> bool:
        while not self._open.wait(0.2):
            if stop.is_set():
                return False
        return True

    @contextlib.contextmanager
    def hold(self) -> Iterator[None]:
        self._open.clear()
        with self.busy:  # a send under way finishes first
            pass
        try:
            yield
        finally:
            self._open.set()


def _robot_loop(walk: RobotWalk, session: Any, plan: SoakPlan, rate_hz: float,
                switch_at_s: float | None, t_start: float, stop: threading.Event,
                ledger: Ledger, book: dict, publishers: list) -> None:
    """One robot: Poisson submaps at `rate_hz` until `stop`; a second session at `switch_at_s`.
    Its publishers stay declared (their caches) until the driver closes the session."""
    root = keys.fleet_root(plan.fleet)
    publishers.append(session.liveliness().declare_token(keys.alive_key(root, walk.robot)))
    pub = agent_publisher(session, keys.submap_key(root, walk.robot, walk.session))
    publishers.append(pub)
    seq, t_next = 0, t_start + float(walk.rng.exponential(1.0 / rate_hz))
    while not stop.wait(max(0.0, t_next - time.monotonic())):
        if switch_at_s is not None and time.monotonic() - t_start >= switch_at_s:
            switch_at_s = None
            walk.new_session("s1")
            pub = agent_publisher(session, keys.submap_key(root, walk.robot, walk.session))
            publishers.append(pub)
        sub = walk.next_submap(seq)
        data = encode_message(sub, plan.profile, walk.robot, seq)
        with ledger.lock:
            book[(walk.robot, walk.session, seq)] = time.time()
            ledger.bytes_valid += len(data)
            if plan.disk_full_at and book is ledger.valid:  # kept for a retry
                ledger.payloads[(walk.robot, walk.session, seq)] = (
                    keys.submap_key(root, walk.robot, walk.session), data)
        pub.put(data)
        seq += 1
        t_next += float(walk.rng.exponential(1.0 / rate_hz))


def _attacker_loop(session: Any, plan: SoakPlan, at_s: np.ndarray, world: SoakWorld,
                   rng: np.random.Generator, t_start: float, stop: threading.Event,
                   abort: threading.Event, gate: _Gate, ledger: Ledger) -> None:
    """One hostile payload at each of `at_s` (N,) s after `t_start`, none while the gate is
    held (those due meanwhile go as soon as it opens); once `stop` is set (the run's time is
    up), those left back to back; `abort` ends it wherever it is."""
    import zenoh

    root = keys.fleet_root(plan.fleet)
    kinds = list(HostileKind)
    victim = RobotWalk(world, "r00", plan.dim, plan.objects_per_submap, plan.step_m,
                       np.random.default_rng([plan.seed, 99]))
    for n, at in enumerate(at_s):
        stop.wait(max(0.0, t_start + float(at) - time.monotonic()))
        if abort.is_set() or not gate.wait_open(abort):
            return
        with gate.busy:
            robot = HOSTILE_ROBOTS[n % len(HOSTILE_ROBOTS)]
            kind = kinds[int(rng.integers(len(kinds)))]
            walk = RobotWalk(world, robot, plan.dim, plan.objects_per_submap, plan.step_m,
                             np.random.default_rng([plan.seed, 100 + n]))
            seq = HOSTILE_SEQ0 + n
            suffix, data = hostile_payload(kind, robot, seq, walk.next_submap(seq),
                                           victim.next_submap(HOSTILE_SEQ0 + n),
                                           plan.max_payload_bytes, rng)
            with ledger.lock:
                ledger.hostile.append((time.time(), kind.value))
            session.put(f"{root}/{suffix}", data,
                        congestion_control=zenoh.CongestionControl.BLOCK)


def _flood_loop(session: Any, plan: SoakPlan, world: SoakWorld, t_start: float,
                store: Path, stop: threading.Event, gate: _Gate, ledger: Ledger) -> None:
    """At `plan.flood_at` of the run: FLOOD_ROBOT's one valid submap, and once it is stored,
    `plan.flood_variants` byte-variants of it as fast as they go (between kills)."""
    import zenoh

    if stop.wait(max(0.0, t_start + plan.flood_at * plan.duration_s - time.monotonic())):
        return
    walk = RobotWalk(world, FLOOD_ROBOT, plan.dim, plan.objects_per_submap, plan.step_m,
                     np.random.default_rng([plan.seed, 98]))
    first, *variants = flood_payloads(walk.next_submap(0), plan.flood_variants, Profile.FULL)
    key = f"{keys.fleet_root(plan.fleet)}/submap/{FLOOD_ROBOT}/{walk.session}"
    if not _put_until_stored(session, key, first, (FLOOD_ROBOT, walk.session, 0), store, stop,
                             gate):
        return
    while not gate.calm.wait(0.2):
        if stop.is_set():
            return
    if not gate.wait_open(stop):
        return
    with gate.busy:
        t0 = time.monotonic()
        with ledger.lock:
            ledger.flood_at = time.time()
        for data in variants:
            session.put(key, data, congestion_control=zenoh.CongestionControl.BLOCK)
        with ledger.lock:
            ledger.flood_sent = len(variants)
            ledger.flood_s = time.monotonic() - t0


def _put_until_stored(session: Any, key: str, data: bytes, k: tuple[str, str, int],
                      store: Path, stop: threading.Event, gate: _Gate,
                      sent: Callable[[], Any] = lambda: None) -> bool:
    """`data` put on `key` (not during the disk-full episode, between kills), again while
    the store has no row `k` (a kill may have lost it), 10 times at most; `sent` called
    before each put. Whether it was stored."""
    import zenoh

    while not gate.calm.wait(0.2):
        if stop.is_set():
            return False
    for _ in range(10):
        if not gate.wait_open(stop):
            return False
        sent()
        session.put(key, data, congestion_control=zenoh.CongestionControl.BLOCK)
        if _wait(lambda: k in _stored_keys(store)[0], 3.0):
            return True
    return False


def _large_loop(session: Any, plan: SoakPlan, world: SoakWorld, t_start: float,
                store: Path, stop: threading.Event, gate: _Gate, ledger: Ledger) -> None:
    """At `plan.large_at` of the run: LARGE_ROBOT's one large submap, until it is stored."""
    if stop.wait(max(0.0, t_start + plan.large_at * plan.duration_s - time.monotonic())):
        return
    sub = large_submap(world, plan)
    data = encode_message(sub, plan.profile, LARGE_ROBOT, 0)
    key = f"{keys.fleet_root(plan.fleet)}/submap/{LARGE_ROBOT}/{sub.session_id}"

    def sent() -> None:
        with ledger.lock:
            ledger.large_at = time.time()

    _put_until_stored(session, key, data, (LARGE_ROBOT, sub.session_id, 0), store, stop, gate,
                      sent)


def _status(session: Any, fleet: str, timeout_s: float = 2.0) -> tuple[dict | None, int]:
    """The status reply (None without one) and its size in bytes."""
    # the counts only: the merged poses grow with every keyframe (MergeService.status)
    selector = keys.status_key(keys.fleet_root(fleet)) + "?poses=false"
    for reply in session.get(selector, timeout=timeout_s):
        if reply.ok is not None:
            data = reply.ok.payload.to_bytes()
            return json.loads(data), len(data)
    return None, 0


def _wait(predicate: Callable[[], bool], timeout_s: float, step_s: float = 0.25) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(step_s)
    return predicate()


def _stored_keys(path: Path) -> tuple[set[tuple[str, str, int]], int]:
    """Keys of the stored submaps and how many are pending (empty before the store exists)."""
    if not path.exists():
        return set(), 0
    try:
        with StoreReader(path) as db:
            rows = db.submap_rows()
    except StoreError:
        return set(), -1
    return {(r, s, q) for r, s, q, *_ in rows}, sum(1 for r in rows if r[3] == "pending")


def run_soak(plan: SoakPlan, serve_command: Sequence[str] | None = None,
             serve_args: Sequence[str] = (), echo: Callable[[str], Any] = print,
             log_path: Path | None = None) -> dict[str, Any]:
    """Run the soak (see the module docstring) and return its report. `serve_command` starts
    the CLI (`[python, -m, mergesvc.cli]` by default), `serve_args` are added to `serve`
    (e.g. `--settings FILE`); the service's output goes to `log_path` (else a temporary
    file). Raises InputError for a bad plan, MergeError when the service does not come up."""
    import zenoh

    plan.check()
    command = list(serve_command or [sys.executable, "-m", "mergesvc.cli"])
    world = SoakWorld.make(plan)
    rngs = _seeds(plan.seed, plan.robots + plan.mismatch_robots + 3)
    ctl_rng, att_rng = rngs[-1], rngs[-2]
    with tempfile.TemporaryDirectory(prefix="mergesvc-soak-") as tmp:
        tmpdir = Path(tmp)
        store = tmpdir / "soak.db"
        port = _free_port()
        endpoint = f"tcp/127.0.0.1:{port}"
        zfile = tmpdir / "zenoh.json5"
        zfile.write_text(json.dumps({"scouting": {"multicast": {"enabled": False},
                                                  "gossip": {"enabled": False}, "delay": 0}}))
        env = {**os.environ, "PYTHONUNBUFFERED": "1",
               "MERGESVC_SERVICE__EMBEDDING_DIM": str(plan.dim)}
        svc = ServiceProcess(command, plan.fleet, store, endpoint, zfile,
                             log_path or tmpdir / "serve.log", env, serve_args)
        if log_path is not None:
            log_path.parent.mkdir(parents=True, exist_ok=True)
            log_path.write_bytes(b"")
        client = make_zenoh_config(mode="client", connect=[endpoint], scouting=False)
        ledger = Ledger()
        stop = threading.Event()
        abort = threading.Event()  # the attacker's stop: `stop` only makes it hurry
        sampler_stop = threading.Event()
        gate = _Gate()
        sessions: list[Any] = []
        publishers: list[list[Any]] = []
        threads: list[threading.Thread] = []
        samples: list[dict[str, Any]] = []
        probed: list[dict[str, Any]] = []  # the status probe's round trips (soak_probe.py)
        probes: list[subprocess.Popen] = []
        rss: list[tuple[float, float, int, float]] = []  # (t, MB, incarnation, shmem MB)
        restarts: list[dict[str, float]] = []
        svc.start()
        try:
            monitor = zenoh.open(client) if _wait_router(client, plan.start_timeout_s) else None
            if monitor is None:
                raise MergeError(f"the service did not come up on {endpoint} (log: "
                                 f"{svc.log_path})")
            sessions.append(monitor)
            root = keys.fleet_root(plan.fleet)
            subs = [monitor.declare_subscriber(keys.all_errors(root), ledger.on_error),
                    monitor.declare_subscriber(keys.all_factors(root), ledger.on_factor),
                    monitor.declare_subscriber(f"{root}/result/**", ledger.on_result)]
            if not _wait(lambda: _status(monitor, plan.fleet)[0] is not None,
                         plan.start_timeout_s):
                raise MergeError(f"the service does not answer status (log: {svc.log_path})")
            t_start = time.monotonic()
            ledger.t0 = time.time()

            def sample_loop() -> None:
                next_status = 0.0
                while not sampler_stop.wait(plan.rss_period_s):
                    t = time.time() - ledger.t0
                    pid = svc.pid
                    b = family_rss_bytes(pid) if pid is not None else None
                    if b is not None:
                        shm = shmem_bytes(pid) if pid is not None else None
                        rss.append((t, b / 2**20, svc.starts, (shm or 0) / 2**20))
                    if time.monotonic() >= next_status:
                        next_status = time.monotonic() + plan.status_period_s
                        t_q = time.monotonic()
                        st, size = _status(monitor, plan.fleet)
                        if st is not None:
                            samples.append({
                                "t_s": t, "bytes": size, "incarnation": svc.starts,
                                "status_ms": (time.monotonic() - t_q) * 1e3,
                                "latency_ms": st.get("latency_ms"),
                                "delay_ms": st.get("delay_ms"),
                                "queued": st["submaps"]["queued"],
                                "stored": st["submaps"]["stored"],
                                "factors_active": st["factors"]["active"]})

            threads.append(threading.Thread(target=sample_loop, name="soak-sampler",
                                            daemon=True))
            probe = subprocess.Popen(
                [sys.executable, "-m", "mergesvc.bench.soak_probe", endpoint, plan.fleet,
                 str(plan.status_period_s)], stdout=subprocess.PIPE, env=env, text=True)
            probes.append(probe)

            probe_up = threading.Event()

            def read_probe() -> None:
                for line in probe.stdout or ():
                    probe_up.set()
                    with contextlib.suppress(ValueError, KeyError):
                        doc = json.loads(line)
                        if doc["ms"] is not None:
                            probed.append({"t_s": doc["t"] - ledger.t0, "status_ms": doc["ms"]})

            threading.Thread(target=read_probe, name="soak-probe", daemon=True).start()
            # the robots start once the probe asks (its start-up, a loaded machine's seconds,
            # is not the service's): the status figures then cover the whole run
            probe_up.wait(timeout=30.0)
            # the robots: valid ones, then the mismatching ones
            rates = []
            for i in range(plan.robots + plan.mismatch_robots):
                mismatch = i >= plan.robots
                robot = f"m{i - plan.robots}" if mismatch else f"r{i:02d}"
                rng = rngs[i]
                rate = float(rng.uniform(*plan.rate_hz))
                rates.append(rate)
                switch = (float(rng.uniform(0.2, 0.8)) * plan.duration_s
                          if rng.random() < plan.second_session_p else None)
                walk = RobotWalk(world, robot, plan.mismatch_dim if mismatch else plan.dim,
                                 plan.objects_per_submap, plan.step_m, rng)
                s = zenoh.open(client)
                sessions.append(s)
                held: list[Any] = []
                publishers.append(held)
                book = ledger.mismatch if mismatch else ledger.valid
                threads.append(threading.Thread(
                    target=_robot_loop, name=f"soak-{robot}", daemon=True,
                    args=(walk, s, plan, rate, switch, t_start, stop, ledger, book, held)))
            valid_rate = sum(rates[: plan.robots])
            hostile_rate = valid_rate * plan.hostile_fraction / (1.0 - plan.hostile_fraction)
            hostile_at_s = hostile_schedule(hostile_rate, plan.duration_s, att_rng)
            ledger.hostile_planned = len(hostile_at_s)
            attacker_thread = None
            if len(hostile_at_s):
                attacker = zenoh.open(client)
                sessions.append(attacker)
                attacker_thread = threading.Thread(
                    target=_attacker_loop, name="soak-attacker", daemon=True,
                    args=(attacker, plan, hostile_at_s, world, att_rng, t_start, stop, abort,
                          gate, ledger))
                threads.append(attacker_thread)
            # the episodes of one robot each, on a session of its own
            for on, loop, name in ((plan.flood_variants, _flood_loop, "soak-flood"),
                                   (plan.large_objects, _large_loop, "soak-large")):
                if on:
                    own = zenoh.open(client)
                    sessions.append(own)
                    threads.append(threading.Thread(
                        target=loop, name=name, daemon=True,
                        args=(own, plan, world, t_start, store, stop, gate, ledger)))
            kill_at = sorted(float(x) for x in ctl_rng.uniform(0.15, 0.85, plan.restarts)
                             * plan.duration_s)
            echo(f"soak: {plan.robots} robots ({valid_rate:.1f} submaps/s), "
                 f"{plan.mismatch_robots} of another model, {len(hostile_at_s)} hostile "
                 f"({hostile_rate:.2f}/s), "
                 f"{plan.restarts} kill -9 at {', '.join(f'{t:.0f}' for t in kill_at) or '-'} "
                 f"s of {plan.duration_s:.0f} s; service on {endpoint}")
            for th in threads:
                th.start()
            ledger.resend = lambda key, data: monitor.put(key, data)
            events = sorted([(t, "kill") for t in kill_at]
                            + ([(plan.disk_full_at * plan.duration_s, "disk_full")]
                               if plan.disk_full_at else []))
            for at, what in events:
                while time.monotonic() - t_start < at:
                    time.sleep(min(0.2, max(0.0, at - (time.monotonic() - t_start))))
                if what == "kill":
                    restarts.append(_restart(svc, monitor, plan, gate, ledger, ctl_rng, echo))
                else:
                    _disk_full(svc, store, monitor, plan, gate, ledger, echo)
            while time.monotonic() - t_start < plan.duration_s:
                time.sleep(0.2)
            stop.set()
            # the attacker's quota is the plan's, whatever the load: what a kill near the end
            # held back goes now, before the answers to it are awaited
            if attacker_thread is not None:
                attacker_thread.join(timeout=HOSTILE_OVERTIME_S)
            abort.set()
            for th in threads[1:]:
                th.join(timeout=30.0)
            sent_at_end = len(ledger.valid)
            echo(f"soak: publishing stopped ({sent_at_end} valid submaps sent); draining")
            t_drain = time.monotonic()

            def drained() -> bool:
                stored, pending = _stored_keys(store)
                return pending == 0 and set(ledger.valid) <= stored

            is_drained = _wait(drained, plan.drain_timeout_s, 0.5)
            _wait(lambda: not ledger.unanswered(), 10.0)
            drain_s = time.monotonic() - t_drain
            drain_end = time.time()
            sampler_stop.set()
            threads[0].join(timeout=10.0)
            for sub in subs:
                sub.undeclare()
            exit_code = svc.stop()
        finally:
            stop.set()
            abort.set()
            sampler_stop.set()
            for held in publishers:
                for ent in held:
                    with contextlib.suppress(Exception):
                        ent.undeclare()
            for s in sessions:
                with contextlib.suppress(Exception):
                    s.close()
            svc.stop(timeout_s=10.0)
            for p in probes:
                p.kill()
                p.wait()
        log_text = svc.log_path.read_text(errors="replace")
        report = build_report(plan, store, ledger, samples, rss, restarts, rates,
                         drained=is_drained, drain_s=drain_s, exit_code=exit_code,
                         log_text=log_text, probed=[p for p in probed
                                                    if p["t_s"] <= drain_end - ledger.t0])
    return report


def _free_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _wait_router(config: Any, timeout_s: float) -> bool:
    """Whether a client session can open on the service's router within `timeout_s`."""
    import zenoh

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            zenoh.open(config).close()
            return True
        except zenoh.ZError:
            time.sleep(0.3)
    return False


def _restart(svc: ServiceProcess, monitor: Any, plan: SoakPlan, gate: _Gate, ledger: Ledger,
             rng: np.random.Generator, echo: Callable[[str], Any]) -> dict[str, float]:
    """kill -9 the service and start it again on the same store; the attacker and the flood
    wait (their payloads sent so far answered first, at most 10 s)."""
    with gate.hold():
        _wait(lambda: not ledger.unanswered(), 10.0, 0.1)
        t_kill = time.time()
        svc.kill()
        time.sleep(float(rng.uniform(*plan.restart_pause_s)))
        svc.start()
        up = _wait(lambda: _status(monitor, plan.fleet, 1.0)[0] is not None,
                   plan.start_timeout_s)
        t_up = time.time()
    if not up:
        raise MergeError(f"the service did not come back after a kill (log: {svc.log_path})")
    echo(f"soak: kill -9 at {t_kill - ledger.t0:.1f} s, answering again after "
         f"{t_up - t_kill:.1f} s")
    return {"killed_at_s": t_kill - ledger.t0, "down_s": t_up - t_kill}


def _disk_full(svc: ServiceProcess, store: Path, monitor: Any, plan: SoakPlan, gate: _Gate,
               ledger: Ledger, echo: Callable[[str], Any]) -> None:
    """The service stopped (SIGTERM: its WAL checkpointed and removed) and started again with
    its files limited to `disk_full_margin_bytes` above the largest of them that it appends
    to (the WAL starts empty, the acks file; the database takes writes only at a checkpoint),
    so its writes soon fail with a real EFBIG; held `disk_full_s`, then restarted without it.
    The robots go on publishing and send again what is answered `store`."""
    def up() -> bool:
        return _wait(lambda: _status(monitor, plan.fleet, 1.0)[0] is not None,
                     plan.start_timeout_s)

    episode_log = svc.log_path.with_name(svc.log_path.name + ".disk_full")
    gate.calm.clear()
    with gate.hold():
        _wait(lambda: not ledger.unanswered(), 10.0, 0.1)
        svc.stop()
        appended = [p for p in (store.with_name(store.name + "-wal"),
                                store.with_name(store.name + ".acks")) if p.exists()]
        largest = max([p.stat().st_size for p in appended] + [0])
        limit = largest + plan.disk_full_margin_bytes
        svc.start(file_limit_bytes=limit, log_path=episode_log)
        t_from = time.time()
        if not up():
            raise MergeError(f"the service did not start with a full disk (log: {episode_log})")
    time.sleep(plan.disk_full_s)
    with gate.hold():  # (failing writes slow the service's ingress: a longer wait)
        _wait(lambda: not ledger.unanswered(), 60.0, 0.1)
        svc.stop()
        t_to = time.time()
        with svc.log_path.open("ab") as out:
            out.write(episode_log.read_bytes())
        svc.start()
        if not up():
            raise MergeError(f"the service did not come back after the disk was full (log: "
                             f"{svc.log_path})")
    gate.calm.set()
    with ledger.lock:
        ledger.episode = {"from_t": t_from, "to_t": t_to, "limit_bytes": limit,
                          "largest_bytes": largest}
        n = sum(len(ts) for ts in ledger.store_answers.values())
    echo(f"soak: disk full from {t_from - ledger.t0:.1f} to {t_to - ledger.t0:.1f} s (files "
         f"limited to {limit} bytes): {n} `store` answers")


__all__ = [
    "CACHE_SAMPLES",
    "HEARTBEAT_S",
    "HOSTILE_ROBOTS",
    "HOSTILE_SEQ0",
    "HostileKind",
    "Ledger",
    "RobotWalk",
    "ServiceProcess",
    "SoakPlan",
    "SoakWorld",
    "agent_publisher",
    "family_rss_bytes",
    "hostile_payload",
    "plot_soak",
    "rss_bytes",
    "run_soak",
    "shmem_bytes",
    "soak_summary",
]
