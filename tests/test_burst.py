"""A vehicle's burst of 1,000 submaps through the agents' advanced publisher (issue 14): a real
`mergesvc serve` process, a publisher declared by fleet/agent.py's `Agent` (cache, sample-miss
detection, BLOCK), every submap stored once; and when the service is killed mid-burst and
started again on its store, the publisher's cache gives it back everything it missed.

The service runs with `submap_burst` raised to 2,000: its token bucket (a separate admission
rule, 600 new submaps at once by default) would refuse the excess of one robot's 1,000 at once
by design (error code rate_limited), which is not what these tests measure."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import sqlite3
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh
from helpers import free_port, wait_for, zenoh_config

from mergesvc.core.model import Factor, ObjectNode, Submap
from mergesvc.fleet.agent import Agent, AgentConfig
from mergesvc.wire import Profile, encode_message, keys

FLEET = "burst"
ROOT = keys.fleet_root(FLEET)
N_BURST = 1000


def burst_payloads(robot: str, n: int = N_BURST) -> list[bytes]:
    """n distinct small submaps (seq 0..n-1, 3 objects, 8-d), coded as the agent codes them."""
    rng = np.random.default_rng(14)
    out = []
    for seq in range(n):
        objs = [ObjectNode(id=f"o{seq}-{i}",
                           position=tuple(float(x) for x in rng.uniform(-5, 5, 3)),
                           embedding=[float(x) for x in rng.normal(size=8)], variance=0.01,
                           n_obs=2) for i in range(3)]
        out.append(encode_message(Submap(robot_id=robot, session_id="s0", seq=seq, objects=objs),
                                  Profile.INT8, robot, seq))
    return out


class Service:
    """`mergesvc serve` on `store`, an embedded router on `ep` (scouting off)."""

    def __init__(self, tmp: Path, ep: str) -> None:
        self.store, self.ep = tmp / "burst.db", ep
        self.zfile = tmp / "zenoh.json5"
        self.zfile.write_text(json.dumps({"scouting": {"multicast": {"enabled": False},
                                                       "gossip": {"enabled": False}}}))
        self.log = tmp / "serve.log"
        self.proc: subprocess.Popen | None = None

    def start(self) -> None:
        env = {**os.environ, "MERGESVC_SERVICE__SUBMAP_BURST": "2000"}
        with self.log.open("ab") as out:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "mergesvc.cli", "serve", "--fleet", FLEET, "--store",
                 str(self.store), "--listen", self.ep, "--config", str(self.zfile)],
                stdout=out, stderr=subprocess.STDOUT, env=env, start_new_session=True)

    def signal(self, sig: int) -> None:
        if self.proc is not None and self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.proc.pid, sig)
            self.proc.wait(timeout=30)

    def seqs(self) -> list[int]:
        """Seqs of the stored submaps (read-only; [] before the store exists)."""
        if not self.store.exists():
            return []
        with contextlib.closing(sqlite3.connect(f"file:{self.store}?mode=ro", uri=True,
                                                timeout=10.0)) as db:
            return [int(r[0]) for r in db.execute("SELECT seq FROM submaps ORDER BY seq")]


def _answers_status(cs: zenoh.Session) -> bool:
    return any(r.ok is not None for r in cs.get(keys.status_key(ROOT), timeout=1.0))


@pytest.fixture
def service(tmp_path: Path) -> Iterator[Service]:
    svc = Service(tmp_path, f"tcp/127.0.0.1:{free_port()}")
    svc.start()
    try:
        yield svc
    finally:
        svc.signal(signal.SIGTERM)


@contextlib.contextmanager
def vehicle(service: Service, robot: str) -> Iterator[tuple[zenoh.Session, Agent]]:
    """A client session on the service's router and an `Agent` on it, as run_agent builds one."""
    assert wait_for(lambda: _connects(service.ep), 30.0, 0.3), service.log.read_text()
    with zenoh.open(zenoh_config("client", connect=service.ep)) as cs:
        assert wait_for(lambda: _answers_status(cs), 30.0)

        def decode_factor(data: bytes) -> Factor:
            raise AssertionError("no factor expected")

        with Agent(AgentConfig(robot=robot, fleet=FLEET), cs, lambda sub, seq: b"",
                   decode_factor, submap_key=keys.submap_key(ROOT, robot, "s0"),
                   factor_key=keys.robot_factors(ROOT, robot),
                   alive_key=keys.alive_key(ROOT, robot)) as ag:
            yield cs, ag


def _connects(ep: str) -> bool:
    try:
        zenoh.open(zenoh_config("client", connect=ep)).close()
        return True
    except zenoh.ZError:
        return False


def test_burst_of_1000_through_the_agents_publisher_is_stored_whole(service: Service) -> None:
    payloads = burst_payloads("b1")
    with vehicle(service, "b1") as (_, ag):
        for data in payloads:  # as fast as the publisher takes them
            ag._pub.put(data)
        assert wait_for(lambda: len(service.seqs()) == N_BURST, 60.0, 0.5)
    assert service.seqs() == list(range(N_BURST))


def test_burst_with_a_kill_mid_way_is_recovered_from_the_cache(service: Service) -> None:
    """kill -9 after 300 of 1,000 puts, the other 700 sent while the service is down; started
    again on its store, the service fetches from the publisher's cache what it never stored."""
    payloads = burst_payloads("b2")
    with vehicle(service, "b2") as (_, ag):
        for seq, data in enumerate(payloads):
            if seq == 300:
                service.signal(signal.SIGKILL)
            ag._pub.put(data)
        stored_at_kill = service.seqs()
        assert len(stored_at_kill) <= 300  # the rest went to the cache only
        service.start()
        assert wait_for(lambda: len(service.seqs()) == N_BURST, 60.0, 0.5), (
            f"{len(service.seqs())} stored; log: {service.log.read_text()[-2000:]}")
    assert service.seqs() == list(range(N_BURST))
