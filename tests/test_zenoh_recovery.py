"""The service's subscriber (fleet/zenoh_transport.py) against the robots' publisher
(bench/soak_world.agent_publisher) across restarts: what a robot cached while the service was
down reaches the service after it comes back, even when the robot publishes again the moment it
sees the service (a live sample racing the recovery of its backlog)."""

from __future__ import annotations

import threading

import zenoh
from helpers import free_port, wait_for, zenoh_config

from mergesvc.bench.soak_world import agent_publisher
from mergesvc.fleet.zenoh_transport import ZenohTransport

CYCLES = 5  # zenoh.ext's own late-publisher recovery lost the backlog in 11 of 25 cycles


def test_a_backlog_survives_a_put_racing_the_reconnection() -> None:
    ep = f"tcp/127.0.0.1:{free_port()}"
    key = "fleet/submap/r00/s0"
    router = zenoh.open(zenoh_config("router", listen=ep))
    client = zenoh.open(zenoh_config("client", connect=ep))
    pub = agent_publisher(client, key)
    lock = threading.Lock()
    sent = [0]
    raced = [0]  # puts made on seeing the service
    got: set[int] = set()
    handles = []

    def put() -> None:
        with lock:
            pub.put(str(sent[0]).encode())
            sent[0] += 1

    def race(token: zenoh.Sample) -> None:
        if token.kind == zenoh.SampleKind.PUT:
            put()
            raced[0] += 1

    # the robot publishes as soon as it sees the service's subscriber again
    seen = client.liveliness().declare_subscriber("fleet/submap/**/@adv/sub/**", race)
    try:
        for cycle in range(CYCLES):
            for _ in range(5):  # while the service is down (or before it): cached
                put()
            for h in handles:
                h.close()
            router.close()  # the service's process dies with its session
            router = zenoh.open(zenoh_config("router", listen=ep))  # restarted
            handles = [ZenohTransport(router).subscribe(
                "fleet/submap/**", lambda s: got.add(int(s.payload)), recover=True)]
            # the robot reconnects within its client backoff, puts, and everything arrives
            assert wait_for(lambda c=cycle: raced[0] > c and len(got) == sent[0], 8.0), (
                f"cycle {cycle}: never delivered {sorted(set(range(sent[0])) - got)}")
    finally:
        seen.undeclare()
        for h in handles:
            h.close()
        client.close()
        router.close()
