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
    deliveries: list[int] = []
    handles = []

    def put() -> None:
        with lock:
            pub.put(str(sent[0]).encode())
            sent[0] += 1

    def record(n: int) -> None:
        got.add(n)
        deliveries.append(n)

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
            deliveries.clear()  # a restarted service has the whole cache again: once
            handles = [ZenohTransport(router).subscribe(
                "fleet/submap/**", lambda s: record(int(s.payload)), recover=True)]
            # the robot reconnects within its client backoff, puts, and everything arrives
            assert wait_for(lambda c=cycle: raced[0] > c and len(got) == sent[0], 8.0), (
                f"cycle {cycle}: never delivered {sorted(set(range(sent[0])) - got)}")
            # each once, whichever way it came (zenoh.ext's history, live, the sweep)
            assert sorted(deliveries) == sorted(set(deliveries)), sorted(deliveries)
    finally:
        seen.undeclare()
        for h in handles:
            h.close()
        client.close()
        router.close()


def test_delivered_numbers_per_publisher_are_marked_and_bounded(monkeypatch) -> None:
    from mergesvc.fleet import zenoh_transport as zt

    d = zt._Delivered()
    a, b = ("z1", "6"), ("z2", "6")
    # a live sample first (the race), then the backlog below it
    assert d.first(a, 5) and d.mark(a) == 0
    assert [d.first(a, n) for n in (0, 1, 2, 3, 4, 5, 3)] == [True] * 5 + [False, False]
    assert d.mark(a) == 6 and d.mark(b) == 0
    assert d.first(b, 0) and not d.first(b, 0) and d.mark(b) == 1
    # numbers far above a mark whose past never comes: the mark moves up to the lowest kept
    monkeypatch.setattr(zt, "AHEAD_KEPT", 3)
    for n in (100, 101, 103, 104):
        assert d.first(a, n)
    assert d.mark(a) == 102 and not d.first(a, 50) and d.first(a, 102) and d.mark(a) == 105
    # publishers beyond SOURCES_KEPT: the least recently seen is forgotten
    monkeypatch.setattr(zt, "SOURCES_KEPT", 2)
    d.first(("z3", "1"), 0)
    assert d.mark(b) == 0 and d.mark(a) == 105  # b, last seen before a's numbers, went


def test_a_token_key_names_its_publisher() -> None:
    from mergesvc.wire import keys

    tok = "fleet/submap/r00/s0/@adv/pub/ac35c9acc01aa1a81047efa1e299c2b2/6/_"
    assert keys.advanced_publisher_source(tok) == ("ac35c9acc01aa1a81047efa1e299c2b2", "6")
    assert keys.advanced_publisher_source("fleet/submap/r00/s0") is None
    assert keys.advanced_publisher_source("a/@adv/pub/zid") is None
