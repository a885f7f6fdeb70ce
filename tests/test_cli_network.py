"""Network errors at the command line: a busy port, a dead or silent endpoint, a malformed
endpoint, a bad Zenoh config file. Each ends in one line on stderr naming the endpoint (or file)
and what to do, with the exit code of cli/errors.py's table, and a traceback only with -vv.
Real processes and real Zenoh sessions on 127.0.0.1; every wait is bounded."""

from __future__ import annotations

import itertools
import json
import os
import re
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh
from helpers import free_port, zenoh_config
from typer.testing import CliRunner

from mergesvc.cli import app
from mergesvc.cli.errors import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_NETWORK, exit_code, message
from mergesvc.errors import ConfigError, InputError, TransportError, TransportFault
from mergesvc.wire.session import check_endpoint, make_zenoh_config, open_session

CLI = [sys.executable, "-m", "mergesvc.cli"]


@pytest.fixture(scope="module")
def busy() -> Iterator[str]:
    """An endpoint a first Zenoh router listens on."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    with zenoh.open(zenoh_config("router", listen=ep)):
        yield ep


@pytest.fixture(scope="module")
def silent() -> Iterator[str]:
    """An endpoint that accepts TCP connections and never speaks Zenoh."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(16)
        yield f"tcp/127.0.0.1:{s.getsockname()[1]}"


@pytest.fixture(scope="module")
def runs(busy: str, silent: str, tmp_path_factory) -> dict[str, subprocess.CompletedProcess]:
    """Every command below started at once (they are slow to import, not to fail), each bounded:
    a command that hangs fails the test by its timeout."""
    tmp = tmp_path_factory.mktemp("net")
    dead = f"tcp/127.0.0.1:{free_port()}"  # nothing listens there
    bad_config = tmp / "bad.json5"
    bad_config.write_text('{ mode: "client", connect: { endpoints: ["tcp/127.0.0.1:1"] ')
    # a service without the fleet's projection: it refuses every compact submap for good
    proj = tmp / "proj.npz"
    made = CliRunner().invoke(app, ["projection", "make", str(proj), "--survey", "underwater",
                                    "--samples", "300"])
    assert made.exit_code == 0, made.output
    refusing = f"tcp/127.0.0.1:{free_port()}"
    clean = {k: v for k, v in os.environ.items() if not k.startswith("MERGESVC_")}
    service_log = tmp / "service.err"
    with service_log.open("w") as err:
        service = subprocess.Popen([*CLI, "serve", "--store", ":memory:", "--listen", refusing,
                                    "--seconds", "120", "--progress", "0.5"],
                                   stdout=subprocess.DEVNULL, stderr=err, env=clean)
    commands = {
        "agent_refused": ["agent", "--robot", "auv1", "--laps", "1", "--profile", "compact",
                          "--projection", str(proj), "--connect", refusing,
                          "--connect-timeout", "60", "--time-scale", "0", "--linger", "3"],
        # a router and no service: nobody answers the agent's submaps
        "agent_unanswered": ["agent", "--robot", "auv2", "--laps", "1", "--connect", busy,
                             "--time-scale", "0", "--linger", "1"],
        "serve_busy": ["serve", "--store", ":memory:", "--listen", busy, "--seconds", "30"],
        "agent_dead": ["agent", "--robot", "auv1", "--laps", "1", "--connect", dead,
                       "--connect-timeout", "1"],
        # the default connect timeout bounds an endpoint that accepts and never answers
        "view_silent": ["view", "--connect", silent, "--save", str(tmp / "v.rrd"),
                        "--duration", "30"],
        "bridge_dead_vv": ["-vv", "link", "bridge", "--connect", dead, "--connect-timeout", "0",
                           "--seconds", "30"],
        "bridge_malformed": ["link", "bridge", "--connect", "127.0.0.1:7447", "--seconds", "30"],
        "bridge_malformed_listen": ["link", "bridge", "--mode", "peer", "--listen",
                                    "tcp/127.0.0.1:99999", "--seconds", "30"],
        "bridge_bad_config": ["link", "bridge", "--config", str(bad_config), "--seconds", "30"],
    }
    procs = {name: subprocess.Popen([*CLI, *args], stdout=subprocess.PIPE,
                                    stderr=subprocess.PIPE, text=True, env=clean)
             for name, args in commands.items()}
    out = {}
    try:
        for name, p in procs.items():
            stdout, stderr = p.communicate(timeout=180)
            out[name] = subprocess.CompletedProcess(commands[name], p.returncode, stdout, stderr)
    finally:
        for p in (*procs.values(), service):
            if p.poll() is None:
                p.kill()
                p.wait(timeout=10)
    out["dead"] = dead  # type: ignore[assignment]
    out["service_log"] = service_log  # type: ignore[assignment]
    return out


def _one_line(r: subprocess.CompletedProcess, code: int) -> str:
    assert r.returncode == code, r.stderr
    assert "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), r.stderr
    return lines[0]


def test_serve_on_a_busy_port_says_pick_another_listen(runs, busy: str) -> None:
    line = _one_line(runs["serve_busy"], EXIT_NETWORK)
    assert f"{busy} is in use" in line and "pick another --listen" in line


def test_demo_on_a_busy_port_fails_before_starting_anything(busy: str, tmp_path: Path) -> None:
    r = CliRunner().invoke(app, ["demo", "--quick", "--out", str(tmp_path), "--listen", busy])
    assert r.exit_code == EXIT_NETWORK, r.output
    assert r.stdout == "" and r.stderr.strip() == (
        f"error: {busy} is in use: pick another --listen, or stop the process that holds it")
    assert not (tmp_path / "settings.json").exists()


def test_an_agent_whose_every_submap_is_refused_says_so_and_fails(runs) -> None:
    """Refused for good (here: coded with a projection the service lacks) is said on stderr
    the first time, counted in the summary, and fails the run when it was every submap."""
    r = runs["agent_refused"]
    assert r.returncode == EXIT_FAILED, r.stderr
    summary = json.loads(r.stdout)
    assert summary["submaps_sent"] > 0 and summary["results"] == {
        "refused": summary["submaps_sent"]} == {"refused": summary["submaps_refused"]}
    warned, error = r.stderr.strip().splitlines()[-2:]
    assert "WARNING" in warned and "refused for good, not sent again; the service said: " \
        "bad_submap" in warned
    assert error.startswith(f"error: the service held none of the {summary['submaps_sent']} "
                            "submaps sent; it said: bad_submap") and \
        "give the command that decodes it that projection file (--projection)" in error


def test_a_service_says_how_it_is_going(runs) -> None:
    """Progress at the default verbosity: a line on stderr when the counts change."""
    lines = runs["service_log"].read_text().splitlines()
    sent = json.loads(runs["agent_refused"].stdout)["submaps_sent"]
    assert any(re.fullmatch(rf"\[ +\d+ s\] submaps {sent} received, 0 merged, 0 without a "
                            rf"match, {sent} refused, 0 queued; factors 0 in force, 0 "
                            r"retracted; robots alive: .*", line) for line in lines), lines
    texts = [line.split("] ", 1)[1] for line in lines if line.startswith("[")]
    assert all(a != b for a, b in itertools.pairwise(texts))  # a line only on a change


def test_an_agent_nobody_answers_says_so(runs) -> None:
    r = runs["agent_unanswered"]
    assert r.returncode == 0, r.stderr
    sent = json.loads(r.stdout)["submaps_sent"]
    assert sent > 0 and r.stderr.strip().splitlines()[-1] == (
        f"warning: none of the {sent} submaps sent got an answer from a service within "
        "--linger 1 s: is one running on fleet fleet0?")


def test_agent_gives_up_on_a_dead_endpoint(runs) -> None:
    line = _one_line(runs["agent_dead"], EXIT_NETWORK)
    assert f"nothing answered at {runs['dead']} within 1 s" in line and "--connect" in line


def test_view_gives_up_on_a_silent_endpoint_by_default(runs, silent: str) -> None:
    line = _one_line(runs["view_silent"], EXIT_NETWORK)
    assert f"nothing answered at {silent} within 5 s" in line


def test_vv_prints_the_traceback_above_the_same_line(runs) -> None:
    r = runs["bridge_dead_vv"]
    assert r.returncode == EXIT_NETWORK, r.stderr
    assert "Traceback" in r.stderr and "TransportError" in r.stderr
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith(f"error: nothing answered at {runs['dead']}") and "--connect" in last


def test_malformed_endpoints_are_bad_input(runs) -> None:
    line = _one_line(runs["bridge_malformed"], EXIT_BAD_INPUT)
    assert "'127.0.0.1:7447'" in line and "<protocol>/<host>:<port>" in line
    line = _one_line(runs["bridge_malformed_listen"], EXIT_BAD_INPUT)
    assert "listen endpoint 'tcp/127.0.0.1:99999'" in line


def test_a_bad_zenoh_config_file_is_named_with_its_line(runs) -> None:
    line = _one_line(runs["bridge_bad_config"], EXIT_FAILED)
    assert "bad.json5: line 1, column" in line and ".rs:" not in line


# --------------------------------------------------------------------------------------------
# the library side: wire/session.py raises typed errors, cli/errors.py maps them
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("ep", ["tcp/127.0.0.1:7447", "tcp/[::1]:7447", "udp/zenohd:7447",
                                "tls/host.example:7447?x=1#iface=eth0", "unixsock-stream//s"])
def test_check_endpoint_accepts_endpoints(ep: str) -> None:
    assert check_endpoint(ep, "connect") == ep


@pytest.mark.parametrize("ep", ["127.0.0.1:7447", "tcp/127.0.0.1", "tcp/127.0.0.1:99999",
                                "tcp/127.0.0.1:port", "tcp/127.0.0.1:0", "", "tcp/ a:1"])
def test_check_endpoint_refuses_what_is_no_endpoint(ep: str) -> None:
    with pytest.raises(InputError, match="is not a Zenoh endpoint"):
        check_endpoint(ep, "connect")
    assert check_endpoint("tcp/127.0.0.1:0", "listen")  # port 0: any free port, to listen


def test_open_session_names_the_busy_endpoint(busy: str) -> None:
    conf = make_zenoh_config(mode="router", listen=[busy], scouting=False)
    with pytest.raises(TransportError) as info:
        open_session(conf)
    assert info.value.fault is TransportFault.IN_USE and info.value.endpoint == busy
    assert exit_code(info.value) == EXIT_NETWORK
    assert message(info.value) == f"{busy} is in use: pick another --listen, or stop the " \
                                  "process that holds it"


def test_connect_timeout_gives_up_and_waits_for_a_late_router() -> None:
    ep = f"tcp/127.0.0.1:{free_port()}"
    conf = make_zenoh_config(mode="client", connect=[ep], scouting=False, connect_timeout_s=0)
    with pytest.raises(TransportError) as info:
        open_session(conf)
    assert info.value.fault is TransportFault.NO_ANSWER and info.value.endpoint == ep
    # a client that keeps trying meets a router that starts after it
    started, stop = threading.Event(), threading.Event()

    def router() -> None:
        time.sleep(0.5)
        with zenoh.open(zenoh_config("router", listen=ep)):
            started.set()
            stop.wait(30)

    t = threading.Thread(target=router)
    t.start()
    try:
        conf = make_zenoh_config(mode="client", connect=[ep], scouting=False,
                                 connect_timeout_s=20)
        with open_session(conf):
            assert started.is_set()
    finally:
        stop.set()
        t.join(timeout=30)


def test_a_config_file_zenoh_cannot_read_is_a_config_error(tmp_path: Path) -> None:
    bad = tmp_path / "z.json5"
    bad.write_text('{ mode: "clint" }')
    with pytest.raises(ConfigError, match=r"z\.json5: unknown variant `clint`.*\(line 1, column"):
        make_zenoh_config(config_file=str(bad))
    with pytest.raises(ConfigError, match="No such file"):
        make_zenoh_config(config_file=str(tmp_path / "missing.json5"))


def test_a_listening_peer_needs_no_default_router() -> None:
    """`view --mode peer --listen E` is reached at E; a client, or a command without
    --listen, tries the default router."""
    from mergesvc.cli.options import DEFAULT_ENDPOINT, ZenohMode, zenoh_config

    def connect(**kw) -> list[str]:
        conf = zenoh_config(kw.get("mode", ZenohMode.PEER), kw.get("connect"), kw.get("listen"),
                            None, default_connect=(DEFAULT_ENDPOINT,))
        return json.loads(conf.get_json("connect/endpoints"))

    assert connect(listen=["tcp/127.0.0.1:7500"]) == []
    assert connect(mode=ZenohMode.ROUTER, listen=["tcp/127.0.0.1:7500"]) == []
    assert connect(mode=ZenohMode.CLIENT, listen=["tcp/127.0.0.1:7500"]) == [DEFAULT_ENDPOINT]
    assert connect() == [DEFAULT_ENDPOINT]
    assert connect(connect=["tcp/127.0.0.1:7501"], listen=["tcp/127.0.0.1:7500"]) == [
        "tcp/127.0.0.1:7501"]


def test_an_agent_stopped_by_ctrl_c_says_what_it_did(busy: str, tmp_path: Path
                                                                ) -> None:
    """Stopped mid-mission, a vehicle prints its summary (what it sent, `stopped`), exit 0."""
    import signal

    clean = {k: v for k, v in os.environ.items() if not k.startswith("MERGESVC_")}
    for sig in (signal.SIGINT,):  # Ctrl-C; SIGTERM takes the same handler
        log = tmp_path / f"agent{sig}.log"
        with log.open("w") as err:
            p = subprocess.Popen([*CLI, "-v", "agent", "--robot", "auv3", "--connect", busy,
                                  "--time-scale", "0.2", "--linger", "30", "--progress", "0.2"],
                                 stdout=subprocess.PIPE, stderr=err, text=True, env=clean)
        try:
            deadline = time.monotonic() + 90
            # its progress lines (at -v as at the default) count the submaps as they go out
            sent = re.compile(r"\[ +\d+ s\] \d+ frames, [1-9]\d* submaps sent \(\d+ "
                              r"bytes\), answers: none yet, factors in: 0")
            while not sent.search(log.read_text()) and time.monotonic() < deadline:
                assert p.poll() is None, log.read_text()
                time.sleep(0.2)
            assert sent.search(log.read_text()), log.read_text()
            p.send_signal(sig)
            out, _ = p.communicate(timeout=30)
        finally:
            if p.poll() is None:
                p.kill()
                p.wait(timeout=10)
        assert p.returncode == 0, log.read_text()
        summary = json.loads(out)
        assert summary["stopped"] and summary["submaps_sent"] >= 1
