"""Deployment files (deploy/, docker-compose.yml): every Zenoh config loads in real zenoh, the
router's user/password authentication, mTLS and access control hold on real sessions on
127.0.0.1, and the compose files are consistent (and valid, where `docker compose` exists)."""

from __future__ import annotations

import json
import shutil
import subprocess
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from itertools import count
from pathlib import Path
from typing import Any

import pytest
import zenoh
import zenoh.ext as zext
from helpers import Inbox, free_port, quiet, set_json, wait_for, zenoh_config

ROOT = Path(__file__).resolve().parents[1]
DEPLOY = ROOT / "deploy"
COMPOSE = ROOT / "docker-compose.yml"
COMPOSE_TLS = DEPLOY / "compose.tls.yml"
COMPOSE_ACOUSTIC = DEPLOY / "compose.acoustic.yml"
CONFIGS = sorted(DEPLOY.glob("*.json5"))
ACL_NAMES = {"auv1": "auv1", "auv2": "auv2", "service": "mergesvc", "bridge": "bridge"}

# Bounded waits: a sample that should arrive gets up to ARRIVE_S. That one must not arrive is
# never shown by a pause: a permitted sentinel put after it on the same path arrives, and it did
# not arrive before (see `_stopped`).
ARRIVE_S = 10.0
# Test puts block rather than being dropped when a queue is full (zenoh's default for puts is
# to drop): a forged sample lost to congestion would pass for one the ACL stopped.
BLOCK = zenoh.CongestionControl.BLOCK
_fleet_ids = count()
_sentinel_ids = count()


def _fleet() -> str:
    """A fleet name of its own per test, so that tests sharing the router never see each other."""
    return f"t{next(_fleet_ids)}"


def _router_config(port: int) -> zenoh.Config:
    """deploy/zenohd.json5 on 127.0.0.1:<port> with the credentials file of deploy/."""
    config = zenoh.Config.from_file(str(DEPLOY / "zenohd.json5"))
    set_json(config, "listen/endpoints", [f"tcp/127.0.0.1:{port}"])
    set_json(config, "transport/auth/usrpwd/dictionary_file", str(DEPLOY / "credentials.txt"))
    return quiet(config)


def _client_config(name: str, port: int, *, timeout_ms: int = 5000) -> zenoh.Config:
    """deploy/client-<name>.json5 (its user and password unchanged), connecting to the test
    router."""
    config = zenoh.Config.from_file(str(DEPLOY / f"client-{name}.json5"))
    set_json(config, "connect/endpoints", [f"tcp/127.0.0.1:{port}"])
    set_json(config, "connect/timeout_ms", timeout_ms)
    return quiet(config)


def _credentials() -> dict[str, str]:
    lines = (DEPLOY / "credentials.txt").read_text().splitlines()
    return dict(line.strip().split(":", 1) for line in lines if line.strip())


Put = Callable[[str, bytes], None]


def _session_put(session: zenoh.Session) -> Put:
    """Undeclared puts of `session`. Unlike a declared publisher's, they go to the router
    whether or not the session knows of a subscriber."""
    return lambda key, payload: session.put(key, payload, congestion_control=BLOCK)


def _deliver(put: Put, inbox: Inbox, allowed: str, forged: str | None = None) -> bool:
    """Put `forged` then `allowed` through `put` (one session) until `allowed` arrives: a
    declaration takes a moment to reach the router, so the first put may find no route."""

    def attempt() -> bool:
        if forged is not None:
            put(forged, b"forged")
        put(allowed, b"ok")
        return inbox.wait_for(allowed, 0.3)

    return wait_for(attempt, ARRIVE_S, step_s=0)


def _sentinel(put: Put, inbox: Inbox, key: str) -> None:
    """Put a payload of its own on the permitted `key` and wait (bounded) until it arrives."""
    token = f"sentinel-{next(_sentinel_ids)}".encode()
    put(key, token)
    assert inbox.wait_for(key, ARRIVE_S, token), f"the sentinel on {key} never arrived"


def _stopped(
    put: Put, inbox: Inbox, forged: str, sentinel: str, *, session: zenoh.Session | None = None
) -> bool:
    """Whether `forged` never reached `inbox`, shown by a sentinel, not by a pause.

    Puts `forged`, then a payload of its own on the permitted key `sentinel`, through `put`,
    and waits for that sentinel. Both go from one session over its one link to the router, with
    the same priority and reliability, and zenoh keeps them in order on each link (hop by hop)
    and through the router, which handles one link's messages in turn, the ACL check included
    (it is applied there, at ingress or egress, to each message as the router routes it). So a
    forged put that got through would be in `inbox` before the sentinel: once the sentinel is
    in, absence is final, on a slow machine too. `inbox` must be fed through `Inbox.handler`
    when it listens with more than one subscriber (one receiving thread, so one order).
    With `session`, the forged key is also put by the session itself: a declared publisher sends
    nothing while it knows of no subscriber, the session's own put always reaches the router."""
    put(forged, b"forged")
    if session is not None:
        _session_put(session)(forged, b"forged")
    _sentinel(put, inbox, sentinel)
    return forged not in inbox.keys


class Publishers:
    """Declared publishers on one session, as the service and agents publish: a declared
    publisher sends nothing until the router has told it of a matching subscriber, which the
    ACL must let through (egress `declare_subscriber`)."""

    def __init__(self, session: zenoh.Session, keys: tuple[str, ...]) -> None:
        # declared in the order given: a forged key first, so that if the router ever told the
        # session of a subscriber for it, the session would know before it learnt of the one
        # for the permitted key
        self._publishers = {
            key: session.declare_publisher(key, congestion_control=BLOCK) for key in keys
        }

    def __call__(self, key: str, payload: bytes) -> None:
        self._publishers[key].put(payload)

    def matching(self, key: str) -> bool:
        return self._publishers[key].matching_status.matching

    def undeclare(self) -> None:
        for publisher in self._publishers.values():
            publisher.undeclare()


@contextmanager
def _publishers(session: zenoh.Session, *keys: str) -> Iterator[Publishers]:
    publishers = Publishers(session, keys)
    try:
        yield publishers
    finally:
        publishers.undeclare()


# --- every config loads ----------------------------------------------------------------------


def test_deploy_has_the_expected_configs() -> None:
    names = {p.name for p in CONFIGS}
    assert {
        "zenohd.json5",
        "zenohd-tls.json5",
        "client-auv1.json5",
        "client-auv2.json5",
        "client-service.json5",
        "client-bridge.json5",
        "client-tls.json5",
    } <= names


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.name)
def test_config_loads_in_zenoh(path: Path) -> None:
    zenoh.Config.from_file(str(path))


def test_zenoh_rejects_a_bad_config(tmp_path: Path) -> None:
    """Guards the test above: Config.from_file does reject a misspelt or 0.11-style key."""
    bad = tmp_path / "bad.json5"
    bad.write_text('{ access_control: { enabled: true, rules: [{ id: "r", actions: ["put"] }] } }')
    with pytest.raises(zenoh.ZError):
        zenoh.Config.from_file(str(bad))


def test_tls_router_has_the_same_acl_with_certificate_names() -> None:
    plain = zenoh.Config.from_file(str(DEPLOY / "zenohd.json5"))
    tls = zenoh.Config.from_file(str(DEPLOY / "zenohd-tls.json5"))
    for key in ("access_control/enabled", "access_control/default_permission"):
        assert json.loads(tls.get_json(key)) == json.loads(plain.get_json(key))
    for key in ("access_control/rules", "access_control/policies"):
        assert json.loads(tls.get_json(key)) == json.loads(plain.get_json(key))
    by_user = {
        s["id"]: s["usernames"] for s in json.loads(plain.get_json("access_control/subjects"))
    }
    by_cert = {
        s["id"]: s["cert_common_names"] for s in json.loads(tls.get_json("access_control/subjects"))
    }
    assert by_user == by_cert == {k: [v] for k, v in ACL_NAMES.items()}
    assert json.loads(tls.get_json("transport/link/tls/enable_mtls")) is True
    assert json.loads(tls.get_json("listen/endpoints")) == ["tls/0.0.0.0:7447"]


def test_credentials_match_the_client_configs() -> None:
    credentials = _credentials()
    assert set(credentials) == set(ACL_NAMES.values())
    for name, user in ACL_NAMES.items():
        config = zenoh.Config.from_file(str(DEPLOY / f"client-{name}.json5"))
        assert json.loads(config.get_json("mode")) == "client"
        assert json.loads(config.get_json("transport/auth/usrpwd/user")) == user
        assert json.loads(config.get_json("transport/auth/usrpwd/password")) == credentials[user]
        assert "CHANGE-ME" in credentials[user]


# --- the router's authentication and ACL on real sessions -------------------------------------


@dataclass
class Fleet:
    """A router from deploy/zenohd.json5 and clients from deploy/client-*.json5."""

    port: int
    router: zenoh.Session
    clients: dict[str, zenoh.Session] = field(default_factory=dict)

    def __getitem__(self, name: str) -> zenoh.Session:
        return self.clients[name]


@pytest.fixture(scope="module")
def fleet() -> Iterator[Fleet]:
    port = free_port()
    sessions: list[zenoh.Session] = []
    try:
        router = zenoh.open(_router_config(port))
        sessions.append(router)
        running = Fleet(port, router)
        for name in ("service", "auv1", "auv2", "bridge"):
            running.clients[name] = zenoh.open(_client_config(name, port))
            sessions.append(running.clients[name])
        yield running
    finally:
        for session in reversed(sessions):
            session.close()


def test_robot_puts_only_its_own_submaps(fleet: Fleet) -> None:
    """auv1's submap forged under auv2's key never reaches the service. Shown by a sentinel
    (`_stopped`): auv1 puts the forged submap, then one of its own on the same session, to the
    same subscriber; the router would have passed the forged one first. auv1 does send it (its
    publisher knows of the service's subscriber), so it is the router's ACL that stops it."""
    root = f"mergesvc/v1/{_fleet()}"
    inbox = Inbox()
    sub = fleet["service"].declare_subscriber(f"{root}/submap/**", inbox.handler)
    try:
        own, forged = f"{root}/submap/auv1/s0/1", f"{root}/submap/auv2/s0/1"
        with _publishers(fleet["auv1"], forged, own) as put:
            assert _deliver(put, inbox, own, forged), "auv1's own submap never arrived"
            assert wait_for(lambda: put.matching(forged), ARRIVE_S)
            assert _stopped(put, inbox, forged, own, session=fleet["auv1"])
        # the same key from its owner does arrive: the ACL, not the key, stopped auv1
        assert _deliver(_session_put(fleet["auv2"]), inbox, forged)
    finally:
        sub.undeclare()


def test_robot_cannot_publish_factors_and_gets_only_its_own(fleet: Fleet) -> None:
    """What a robot must not get is shown absent by sentinels (`_stopped`), not by pauses:

    - auv2's factor and error report: the service puts them (declared publisher and plain put)
      and then auv1's own, from one session to auv1's one session; auv1's refused wider
      subscription is declared before its own one, and both feed one inbox through one thread;
    - the factor auv1 forges for auv2: no key goes from auv1 to auv2, so the sentinel takes two
      hops, each over one link in order: auv1's own submap after the forged factor reaching the
      service shows that the router has handled (and, if let through, already queued for auv2)
      the forged factor; a factor the service puts for auv2 after that reaches auv2 behind it."""
    root = f"mergesvc/v1/{_fleet()}"
    auv1_inbox, service_inbox = Inbox(), Inbox()
    subs = [
        # declaring a wider subscription is refused by the router: nothing of auv2 comes through
        fleet["auv1"].declare_subscriber(f"{root}/factor/**", auv1_inbox.handler),
        fleet["auv1"].declare_subscriber(f"{root}/factor/auv1/**", auv1_inbox.handler),
        fleet["service"].declare_subscriber(f"{root}/submap/**", service_inbox.handler),
    ]
    try:
        own, other = f"{root}/factor/auv1/f1", f"{root}/factor/auv2/f1"
        with _publishers(fleet["service"], other, own) as put:
            assert _deliver(put, auv1_inbox, own, other)
            assert _stopped(put, auv1_inbox, other, own, session=fleet["service"])
        # a factor forged by a robot does not reach the vehicle it names
        auv2_inbox = Inbox()
        subs.append(fleet["auv2"].declare_subscriber(f"{root}/factor/auv2/**", auv2_inbox.handler))
        assert _deliver(_session_put(fleet["service"]), auv2_inbox, f"{root}/factor/auv2/f2")
        forged = f"{root}/factor/auv2/forged"
        _session_put(fleet["auv1"])(forged, b"forged")
        assert _deliver(_session_put(fleet["auv1"]), service_inbox, f"{root}/submap/auv1/s0/2")
        assert _deliver(_session_put(fleet["service"]), auv2_inbox, f"{root}/factor/auv2/f3")
        assert forged not in auv2_inbox.keys
        # the service's error reports and submap results reach the robot they are about, and
        # only it; the wider subscription refused, and declared before the permitted one, like
        # factor/** above
        for kind in ("error", "result"):
            subs.append(fleet["auv1"].declare_subscriber(f"{root}/{kind}/*", auv1_inbox.handler))
            subs.append(fleet["auv1"].declare_subscriber(f"{root}/{kind}/auv1",
                                                         auv1_inbox.handler))
            mine, theirs = f"{root}/{kind}/auv1", f"{root}/{kind}/auv2"
            with _publishers(fleet["service"], theirs, mine) as put:
                assert _deliver(put, auv1_inbox, mine, theirs), kind
                assert _stopped(put, auv1_inbox, theirs, mine, session=fleet["service"]), kind
    finally:
        for sub in subs:
            sub.undeclare()


def _replies(session: zenoh.Session, key: str, timeout_s: float = 1.0) -> list[str]:
    return [
        reply.ok.payload.to_string()
        for reply in session.get(key, timeout=timeout_s)
        if reply.ok is not None
    ]


def test_only_the_service_answers_relocalize_and_status(fleet: Fleet) -> None:
    root = f"mergesvc/v1/{_fleet()}"

    def answer(text: str) -> Callable[[zenoh.Query], None]:
        return lambda query: query.reply(query.key_expr, text.encode())

    queryables = [
        fleet["service"].declare_queryable(f"{root}/status", answer("service")),
        # a robot posing as the service: refused
        fleet["auv1"].declare_queryable(f"{root}/relocalize", answer("impostor")),
        # a queryable the ACL allows (its own submap cache): shows robot queryables are reachable
        fleet["auv1"].declare_queryable(f"{root}/submap/auv1/cache", answer("cache")),
    ]
    try:
        assert wait_for(
            lambda: _replies(fleet["auv2"], f"{root}/status") == ["service"], ARRIVE_S, step_s=0
        )
        assert wait_for(
            lambda: _replies(fleet["service"], f"{root}/submap/auv1/cache") == ["cache"],
            ARRIVE_S,
            step_s=0,
        )
        assert _replies(fleet["service"], f"{root}/relocalize") == []
        assert _replies(fleet["auv2"], f"{root}/relocalize") == []
    finally:
        for queryable in queryables:
            queryable.undeclare()


def test_robot_declares_only_its_own_liveliness_token(fleet: Fleet) -> None:
    root = f"mergesvc/v1/{_fleet()}"
    tokens = [
        fleet["auv1"].liveliness().declare_token(f"{root}/alive/auv2"),  # refused
        fleet["auv1"].liveliness().declare_token(f"{root}/alive/auv1"),
    ]

    def alive() -> set[str]:
        replies = fleet["service"].liveliness().get(f"{root}/alive/*", timeout=0.5)
        return {str(r.ok.key_expr) for r in replies if r.ok is not None}

    try:
        assert wait_for(lambda: f"{root}/alive/auv1" in alive(), ARRIVE_S, step_s=0)
        assert alive() == {f"{root}/alive/auv1"}
    finally:
        for token in tokens:
            token.undeclare()


def test_advanced_publisher_history_passes_the_acl(fleet: Fleet) -> None:
    """zenoh.ext advanced publisher/subscriber (cache, miss detection, late-publisher
    detection) work through the ACL: the service recovers submaps put before it subscribed,
    and none that auv1 forged for auv2.

    Absence is shown without a pause. Live: auv1 puts a forged sample, then a sentinel of its
    own (one session, one link, in order, `_stopped`); the advanced subscriber hands a sample on
    as it comes once its initial history query is done (which the early samples show), and its
    callback runs in one thread, so a forged sample let through would be there before the
    sentinel. History: a query of every cache the service can reach is complete when it
    returns (the router answers it once every queryable it routed it to has), and holds auv1's
    own cache only."""
    root = f"mergesvc/v1/{_fleet()}"
    options: dict[str, Any] = {
        "cache": zext.CacheConfig(10),
        "sample_miss_detection": zext.MissDetectionConfig(heartbeat=0.5),
        "publisher_detection": True,
        "congestion_control": BLOCK,
    }
    own_key = f"{root}/submap/auv1/s0"
    own = zext.declare_advanced_publisher(fleet["auv1"], own_key, **options)
    forged = zext.declare_advanced_publisher(fleet["auv1"], f"{root}/submap/auv2/s0", **options)
    inbox = Inbox()
    sub = None
    try:
        for i in range(3):
            forged.put(f"forged{i}")
            own.put(f"early{i}")
        sub = zext.declare_advanced_subscriber(
            fleet["service"],
            f"{root}/submap/**",
            inbox,
            history=zext.HistoryConfig(detect_late_publishers=True),
            recovery=zext.RecoveryConfig(heartbeat=True),
        )
        expected = [(own_key, f"early{i}".encode()) for i in range(3)]

        def history_done() -> bool:
            return [item for item in inbox.snapshot() if item[0] == own_key] == expected

        assert wait_for(history_done, ARRIVE_S), inbox.snapshot()
        own.put("live")
        assert inbox.wait_for(own_key, ARRIVE_S, b"live"), inbox.snapshot()
        forged.put("forged-live")
        _sentinel(lambda _key, payload: own.put(payload), inbox, own_key)
        assert {key for key, _ in inbox.snapshot()} == {own_key}
        replies = fleet["service"].get(
            f"{root}/submap/**/@adv/**",
            accept_replies=zenoh.ReplyKeyExpr.ANY,
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=ARRIVE_S,
        )
        assert {str(reply.ok.key_expr) for reply in replies if reply.ok is not None} == {own_key}
    finally:
        if sub is not None:
            sub.undeclare()
        own.undeclare()
        forged.undeclare()


def test_bridge_carries_the_vehicle_side(fleet: Fleet) -> None:
    """auv1's vehicle-side submap forged for auv2 never reaches the bridge: shown by auv1's own
    submap put after it on the same session (`_stopped`), not by a pause."""
    fleet_name = _fleet()
    top, uw = f"mergesvc/v1/{fleet_name}", f"mergesvc/v1/uw/{fleet_name}"
    bridge_inbox, service_inbox = Inbox(), Inbox()
    subs = [
        fleet["bridge"].declare_subscriber(f"{uw}/**", bridge_inbox.handler),
        fleet["service"].declare_subscriber(f"{top}/submap/**", service_inbox.handler),
    ]
    try:
        own, forged = f"{uw}/submap/auv1/s0/1", f"{uw}/submap/auv2/s0/1"
        with _publishers(fleet["auv1"], forged, own) as put:
            assert _deliver(put, bridge_inbox, own, forged)
            assert wait_for(lambda: put.matching(forged), ARRIVE_S)
            assert _stopped(put, bridge_inbox, forged, own, session=fleet["auv1"])
        # the bridge republishes topside, where the service gets it
        republished = f"{top}/submap/auv1/s0/1"
        with _publishers(fleet["bridge"], republished) as put:
            assert _deliver(put, service_inbox, republished)
    finally:
        for sub in subs:
            sub.undeclare()


def _refused(config: zenoh.Config) -> bool:
    start = time.monotonic()
    try:
        session = zenoh.open(config)
    except zenoh.ZError:
        assert time.monotonic() - start < 15.0
        return True
    session.close()
    return False


def test_wrong_password_unknown_user_and_no_credentials_are_refused(fleet: Fleet) -> None:
    wrong = _client_config("auv1", fleet.port, timeout_ms=0)
    set_json(wrong, "transport/auth/usrpwd/password", "not-the-password")
    assert _refused(wrong)
    unknown = _client_config("auv1", fleet.port, timeout_ms=0)
    set_json(unknown, "transport/auth/usrpwd/user", "auv9")
    assert _refused(unknown)
    anonymous = zenoh_config("client", connect=f"tcp/127.0.0.1:{fleet.port}")
    set_json(anonymous, "connect/timeout_ms", 0)
    assert _refused(anonymous)
    # the right password does connect (same config, nothing else changed)
    assert not _refused(_client_config("auv1", fleet.port, timeout_ms=0))


def test_embedded_router_applies_the_acl_to_robots() -> None:
    """`mergesvc serve --mode router --config deploy/zenohd.json5`: the service's own session
    is the router; its local subscriber gets only what the ACL lets the robots put. The forged
    submap's absence is shown by auv1's own put after it on the same session (`_stopped`)."""
    port = free_port()
    sessions: list[zenoh.Session] = []
    try:
        service = zenoh.open(_router_config(port))
        sessions.append(service)
        auv1 = zenoh.open(_client_config("auv1", port))
        sessions.append(auv1)
        inbox = Inbox()
        sub = service.declare_subscriber("mergesvc/v1/embedded/submap/**", inbox.handler)
        try:
            own = "mergesvc/v1/embedded/submap/auv1/s0/1"
            forged = "mergesvc/v1/embedded/submap/auv2/s0/1"
            with _publishers(auv1, forged, own) as put:
                assert _deliver(put, inbox, own, forged)
                assert wait_for(lambda: put.matching(forged), ARRIVE_S)
                assert _stopped(put, inbox, forged, own, session=auv1)
        finally:
            sub.undeclare()
    finally:
        for session in reversed(sessions):
            session.close()


# --- TLS with mutual authentication, clients named by certificate -----------------------------


def _make_certs(out: Path) -> Path:
    if shutil.which("openssl") is None or shutil.which("bash") is None:
        pytest.skip("openssl and bash are needed to make test certificates")
    subprocess.run(
        ["bash", str(DEPLOY / "make-certs.sh"), str(out)],
        check=True,
        capture_output=True,
        timeout=60,
    )
    return out


def _tls_client_config(port: int, certs: Path, name: str | None, ca: Path) -> zenoh.Config:
    config = zenoh.Config.from_file(str(DEPLOY / "client-tls.json5"))
    set_json(config, "connect/endpoints", [f"tls/127.0.0.1:{port}"])
    set_json(config, "connect/timeout_ms", 0)
    set_json(config, "transport/link/tls/root_ca_certificate", str(ca / "ca.pem"))
    if name is None:
        config.insert_json5("transport/link/tls/connect_certificate", "null")
        config.insert_json5("transport/link/tls/connect_private_key", "null")
    else:
        set_json(config, "transport/link/tls/connect_certificate", str(certs / f"{name}.pem"))
        set_json(config, "transport/link/tls/connect_private_key", str(certs / f"{name}-key.pem"))
    return quiet(config)


def test_mtls_router_acl_by_certificate_name(tmp_path: Path) -> None:
    """Over mTLS the ACL names clients by certificate: auv1's submap forged for auv2 never
    reaches the service, shown by auv1's own put after it on the same session (`_stopped`)."""
    certs = _make_certs(tmp_path / "certs")
    foreign = _make_certs(tmp_path / "foreign")  # another CA, same names
    assert (certs / ".gitignore").read_text().strip() == "*"
    port = free_port()
    router_config = zenoh.Config.from_file(str(DEPLOY / "zenohd-tls.json5"))
    set_json(router_config, "listen/endpoints", [f"tls/127.0.0.1:{port}"])
    for key, file in (
        ("root_ca_certificate", "ca.pem"),
        ("listen_certificate", "zenohd.pem"),
        ("listen_private_key", "zenohd-key.pem"),
    ):
        set_json(router_config, f"transport/link/tls/{key}", str(certs / file))
    sessions: list[zenoh.Session] = []
    try:
        sessions.append(zenoh.open(quiet(router_config)))
        service = zenoh.open(_tls_client_config(port, certs, "mergesvc", certs))
        sessions.append(service)
        auv1 = zenoh.open(_tls_client_config(port, certs, "auv1", certs))
        sessions.append(auv1)
        inbox = Inbox()
        sub = service.declare_subscriber("mergesvc/v1/tls/submap/**", inbox.handler)
        try:
            own, forged = "mergesvc/v1/tls/submap/auv1/s0/1", "mergesvc/v1/tls/submap/auv2/s0/1"
            with _publishers(auv1, forged, own) as put:
                assert _deliver(put, inbox, own, forged)
                assert wait_for(lambda: put.matching(forged), ARRIVE_S)
                assert _stopped(put, inbox, forged, own, session=auv1)
        finally:
            sub.undeclare()
        # no client certificate, or one from another CA: no connection
        assert _refused(_tls_client_config(port, certs, None, certs))
        assert _refused(_tls_client_config(port, foreign, "auv1", certs))
    finally:
        for session in reversed(sessions):
            session.close()


# --- docker-compose.yml ------------------------------------------------------------------------


def _compose(*files: Path) -> dict[str, Any]:
    """The services of compose files merged as compose does it for what is checked here: later
    files replace keys, and volumes by container path."""
    yaml = pytest.importorskip("yaml")
    merged: dict[str, Any] = {}
    for file in files:
        for name, service in (yaml.safe_load(file.read_text()).get("services") or {}).items():
            into = merged.setdefault(name, {})
            volumes = {v.split(":")[1]: v for v in into.get("volumes", [])}
            volumes |= {v.split(":")[1]: v for v in service.get("volumes", [])}
            into.update(service)
            if volumes:
                into["volumes"] = list(volumes.values())
    return merged


def _mounts(service: dict[str, Any]) -> dict[str, str]:
    """Container path -> host path of the bind mounts (named volumes left out)."""
    mounts = {}
    for volume in service.get("volumes", []):
        source, target = volume.split(":")[:2]
        if source.startswith("./"):
            mounts[target] = source
    return mounts


def _option(command: list[str], flag: str) -> str:
    return command[command.index(flag) + 1]


def test_compose_services_commands_and_mounts() -> None:
    services = _compose(COMPOSE)
    assert set(services) == {"zenohd", "service", "auv1", "auv2", "bridge"}
    zenohd = services["zenohd"]
    assert zenohd["image"].startswith("eclipse/zenoh:")
    assert zenohd["command"] == ["-c", "/etc/zenoh/zenohd.json5"]
    assert _mounts(zenohd) == {
        "/etc/zenoh/zenohd.json5": "./deploy/zenohd.json5",
        "/etc/zenoh/credentials.txt": "./deploy/credentials.txt",
    }
    serve = services["service"]["command"]
    assert serve[0] == "serve"
    assert _option(serve, "--mode") == "client"
    assert _option(serve, "--connect") == "tcp/zenohd:7447"
    assert _option(serve, "--store") == "/data/mergesvc.db"
    assert "mergesvc-data:/data" in services["service"]["volumes"]
    for name in ("auv1", "auv2"):
        command = services[name]["command"]
        assert command[0] == "agent"
        assert _option(command, "--robot") == name
        assert _option(command, "--connect") == "tcp/zenohd:7447"
        # one shared simulated world; the compact profile would need a --projection file
        assert _option(command, "--seed") == _option(services["auv1"]["command"], "--seed")
        assert _option(command, "--profile") in {"full", "f16", "int8"}
        assert set(services[name]["depends_on"]) == {"zenohd", "service"}
        assert services[name]["restart"] == "on-failure"
    assert services["bridge"]["command"][:2] == ["link", "bridge"]
    assert services["bridge"]["profiles"] == ["acoustic"]
    for name, service in services.items():
        assert service.get("restart"), name
        for host in _mounts(service).values():
            assert (ROOT / host).is_file(), host
        if name != "zenohd":
            assert service["build"]["dockerfile"] == "deploy/Dockerfile"
            assert set(service["depends_on"]) <= set(services)
            # each client authenticates as its own ACL name
            config = _mounts(service)[_option(service["command"], "--config")]
            user = zenoh.Config.from_file(str(ROOT / config)).get_json("transport/auth/usrpwd/user")
            assert json.loads(user) == ACL_NAMES[name]


def test_compose_tls_override_mounts_each_clients_own_certificate() -> None:
    services = _compose(COMPOSE, COMPOSE_TLS)
    assert _mounts(services["zenohd"])["/etc/zenoh/zenohd.json5"] == "./deploy/zenohd-tls.json5"
    written_by_make_certs = {"ca", "zenohd", *ACL_NAMES.values()}
    for name, service in services.items():
        mounts = _mounts(service)
        for host in mounts.values():
            if host.startswith("./deploy/certs/"):
                stem = Path(host).name.removesuffix(".pem").removesuffix("-key")
                assert stem in written_by_make_certs, host
            else:
                assert (ROOT / host).is_file(), host
        if name != "zenohd":
            assert _option(service["command"], "--connect") == "tls/zenohd:7447"
            assert mounts["/etc/mergesvc/zenoh.json5"] == "./deploy/client-tls.json5"
            assert mounts["/certs/client.pem"] == f"./deploy/certs/{ACL_NAMES[name]}.pem"
            assert mounts["/certs/client-key.pem"] == f"./deploy/certs/{ACL_NAMES[name]}-key.pem"


def test_compose_acoustic_override_puts_the_vehicles_behind_the_bridge() -> None:
    plain, acoustic = _compose(COMPOSE), _compose(COMPOSE, COMPOSE_ACOUSTIC)
    for name in ("auv1", "auv2"):
        command = acoustic[name]["command"]
        assert "--acoustic" in command
        # the rest of the command and the mounts are those of docker-compose.yml
        assert [arg for arg in command if arg != "--acoustic"] == plain[name]["command"]
        assert _mounts(acoustic[name]) == _mounts(plain[name])
    bridge = acoustic["bridge"]["command"]
    vehicles = [bridge[i + 1] for i, arg in enumerate(bridge) if arg == "--vehicles"]
    assert vehicles == ["auv1", "auv2"]
    assert _option(bridge, "--fleet") == _option(acoustic["auv1"]["command"], "--fleet")


def _docker_compose_available() -> bool:
    if shutil.which("docker") is None:
        return False
    try:
        probe = subprocess.run(
            ["docker", "compose", "version"], capture_output=True, timeout=30, check=False
        )
    except (OSError, subprocess.TimeoutExpired):
        return False
    return probe.returncode == 0


@pytest.mark.parametrize(
    "files",
    [(COMPOSE,), (COMPOSE, COMPOSE_TLS), (COMPOSE, COMPOSE_ACOUSTIC)],
    ids=["plain", "tls", "acoustic"],
)
def test_docker_compose_config_is_valid(files: tuple[Path, ...]) -> None:
    if not _docker_compose_available():
        pytest.skip("`docker compose` (the compose plugin) is not available here")
    args = [arg for file in files for arg in ("-f", str(file))]
    result = subprocess.run(
        ["docker", "compose", "--project-directory", str(ROOT), *args, "config", "-q"],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert result.returncode == 0, result.stderr
