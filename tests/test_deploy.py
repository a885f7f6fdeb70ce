"""Deployment files (deploy/, docker-compose.yml): every Zenoh config loads in real zenoh, the
router's user/password authentication, mTLS and access control hold on real sessions on
127.0.0.1, and the compose files are consistent (and valid, where `docker compose` exists)."""

from __future__ import annotations

import json
import shutil
import socket
import subprocess
import threading
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

ROOT = Path(__file__).resolve().parents[1]
DEPLOY = ROOT / "deploy"
COMPOSE = ROOT / "docker-compose.yml"
COMPOSE_TLS = DEPLOY / "compose.tls.yml"
COMPOSE_ACOUSTIC = DEPLOY / "compose.acoustic.yml"
CONFIGS = sorted(DEPLOY.glob("*.json5"))
ACL_NAMES = {"auv1": "auv1", "auv2": "auv2", "service": "mergesvc", "bridge": "bridge"}

# Bounded waits: a sample that should arrive gets up to ARRIVE_S; one that must not arrive is
# given QUIET_S after a later sample of the same session has arrived (same link, FIFO).
ARRIVE_S = 10.0
QUIET_S = 0.5
_fleet_ids = count()


def _fleet() -> str:
    """A fleet name of its own per test, so that tests sharing the router never see each other."""
    return f"t{next(_fleet_ids)}"


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _set(config: zenoh.Config, key: str, value: Any) -> zenoh.Config:
    config.insert_json5(key, json.dumps(value))
    return config


def _quiet(config: zenoh.Config) -> zenoh.Config:
    """Test sessions: no multicast or gossip scouting, no scouting delay."""
    _set(config, "scouting/multicast/enabled", False)
    _set(config, "scouting/gossip/enabled", False)
    return _set(config, "scouting/delay", 0)


def _router_config(port: int) -> zenoh.Config:
    """deploy/zenohd.json5 on 127.0.0.1:<port> with the credentials file of deploy/."""
    config = zenoh.Config.from_file(str(DEPLOY / "zenohd.json5"))
    _set(config, "listen/endpoints", [f"tcp/127.0.0.1:{port}"])
    _set(config, "transport/auth/usrpwd/dictionary_file", str(DEPLOY / "credentials.txt"))
    return _quiet(config)


def _client_config(name: str, port: int, *, timeout_ms: int = 5000) -> zenoh.Config:
    """deploy/client-<name>.json5 (its user and password unchanged), connecting to the test
    router."""
    config = zenoh.Config.from_file(str(DEPLOY / f"client-{name}.json5"))
    _set(config, "connect/endpoints", [f"tcp/127.0.0.1:{port}"])
    _set(config, "connect/timeout_ms", timeout_ms)
    return _quiet(config)


def _credentials() -> dict[str, str]:
    lines = (DEPLOY / "credentials.txt").read_text().splitlines()
    return dict(line.strip().split(":", 1) for line in lines if line.strip())


class Inbox:
    """Keys of the samples a callback subscriber got, with a bounded wait."""

    def __init__(self) -> None:
        self.keys: list[str] = []
        self._cond = threading.Condition()

    def __call__(self, sample: zenoh.Sample) -> None:
        with self._cond:
            self.keys.append(str(sample.key_expr))
            self._cond.notify_all()

    def wait_for(self, key: str, timeout_s: float) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: key in self.keys, timeout_s)


def _until(attempt: Callable[[], bool], timeout_s: float = ARRIVE_S) -> bool:
    """Repeat `attempt` (which waits a little itself) until it succeeds or time is up: a
    declaration takes a moment to reach the router, so the first put may find no route."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if attempt():
            return True
    return False


Put = Callable[[str, bytes], None]


def _deliver(put: Put, inbox: Inbox, allowed: str, forged: str | None = None) -> bool:
    """Put `forged` then `allowed` through `put` (one session) until `allowed` arrives. Same
    link, in order: if the router let `forged` through, it arrives first."""

    def attempt() -> bool:
        if forged is not None:
            put(forged, b"forged")
        put(allowed, b"ok")
        return inbox.wait_for(allowed, 0.3)

    return _until(attempt)


@contextmanager
def _publishers(session: zenoh.Session, *keys: str) -> Iterator[Put]:
    """A put through declared publishers, as the service and agents publish: a declared
    publisher sends nothing until the router has told it of a matching subscriber, which the ACL
    must let through (egress `declare_subscriber`)."""
    publishers = {key: session.declare_publisher(key) for key in keys}
    try:
        yield lambda key, payload: publishers[key].put(payload)
    finally:
        for publisher in publishers.values():
            publisher.undeclare()


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
    port = _free_port()
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
    root = f"mergesvc/v1/{_fleet()}"
    inbox = Inbox()
    sub = fleet["service"].declare_subscriber(f"{root}/submap/**", inbox)
    try:
        own, forged = f"{root}/submap/auv1/s0/1", f"{root}/submap/auv2/s0/1"
        with _publishers(fleet["auv1"], own, forged) as put:
            assert _deliver(put, inbox, own, forged), "auv1's own submap never arrived"
        time.sleep(QUIET_S)
        assert forged not in inbox.keys
        # the same key from its owner does arrive: the ACL, not the key, stopped auv1
        assert _deliver(fleet["auv2"].put, inbox, forged)
    finally:
        sub.undeclare()


def test_robot_cannot_publish_factors_and_gets_only_its_own(fleet: Fleet) -> None:
    root = f"mergesvc/v1/{_fleet()}"
    auv1_inbox, service_inbox = Inbox(), Inbox()
    subs = [
        fleet["auv1"].declare_subscriber(f"{root}/factor/auv1/**", auv1_inbox),
        # declaring a wider subscription is refused by the router: nothing of auv2 comes through
        fleet["auv1"].declare_subscriber(f"{root}/factor/**", auv1_inbox),
        fleet["service"].declare_subscriber(f"{root}/submap/**", service_inbox),
    ]
    try:
        own, other = f"{root}/factor/auv1/f1", f"{root}/factor/auv2/f1"
        with _publishers(fleet["service"], own, other) as put:
            assert _deliver(put, auv1_inbox, own, other)
        time.sleep(QUIET_S)
        assert other not in auv1_inbox.keys
        # a factor forged by a robot does not reach the vehicle it names
        auv2_inbox = Inbox()
        subs.append(fleet["auv2"].declare_subscriber(f"{root}/factor/auv2/**", auv2_inbox))
        assert _deliver(fleet["service"].put, auv2_inbox, f"{root}/factor/auv2/f2")
        fleet["auv1"].put(f"{root}/factor/auv2/forged", b"forged")
        assert _deliver(fleet["auv1"].put, service_inbox, f"{root}/submap/auv1/s0/2")
        time.sleep(QUIET_S)
        assert f"{root}/factor/auv2/forged" not in auv2_inbox.keys
        # the service's error reports reach the robot they are about, and only it
        subs.append(fleet["auv1"].declare_subscriber(f"{root}/error/auv1", auv1_inbox))
        subs.append(fleet["auv1"].declare_subscriber(f"{root}/error/*", auv1_inbox))  # refused
        errors = (f"{root}/error/auv1", f"{root}/error/auv2")
        with _publishers(fleet["service"], *errors) as put:
            assert _deliver(put, auv1_inbox, errors[0], errors[1])
        time.sleep(QUIET_S)
        assert errors[1] not in auv1_inbox.keys
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
        assert _until(lambda: _replies(fleet["auv2"], f"{root}/status") == ["service"])
        assert _until(lambda: _replies(fleet["service"], f"{root}/submap/auv1/cache") == ["cache"])
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
        assert _until(lambda: f"{root}/alive/auv1" in alive())
        assert alive() == {f"{root}/alive/auv1"}
    finally:
        for token in tokens:
            token.undeclare()


def test_advanced_publisher_history_passes_the_acl(fleet: Fleet) -> None:
    """zenoh.ext advanced publisher/subscriber (cache, miss detection, late-publisher
    detection) work through the ACL: the service recovers submaps put before it subscribed,
    and none that auv1 forged for auv2."""
    root = f"mergesvc/v1/{_fleet()}"
    options: dict[str, Any] = {
        "cache": zext.CacheConfig(10),
        "sample_miss_detection": zext.MissDetectionConfig(heartbeat=0.5),
        "publisher_detection": True,
    }
    own = zext.declare_advanced_publisher(fleet["auv1"], f"{root}/submap/auv1/s0", **options)
    forged = zext.declare_advanced_publisher(fleet["auv1"], f"{root}/submap/auv2/s0", **options)
    received: list[tuple[str, str]] = []
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        with lock:
            received.append((str(sample.key_expr), sample.payload.to_string()))

    sub = None
    try:
        for i in range(3):
            forged.put(f"forged{i}")
            own.put(f"early{i}")
        sub = zext.declare_advanced_subscriber(
            fleet["service"],
            f"{root}/submap/**",
            on_sample,
            history=zext.HistoryConfig(detect_late_publishers=True),
            recovery=zext.RecoveryConfig(heartbeat=True),
        )
        expected = [(f"{root}/submap/auv1/s0", f"early{i}") for i in range(3)]

        def history_done() -> bool:
            time.sleep(0.1)
            with lock:
                return [r for r in received if r[0].endswith("auv1/s0")] == expected

        assert _until(history_done), received
        own.put("live")

        def live_done() -> bool:
            time.sleep(0.1)
            with lock:
                return (f"{root}/submap/auv1/s0", "live") in received

        assert _until(live_done), received
        time.sleep(QUIET_S)
        with lock:
            assert not [r for r in received if "auv2" in r[0]]
    finally:
        if sub is not None:
            sub.undeclare()
        own.undeclare()
        forged.undeclare()


def test_bridge_carries_the_vehicle_side(fleet: Fleet) -> None:
    fleet_name = _fleet()
    top, uw = f"mergesvc/v1/{fleet_name}", f"mergesvc/v1/uw/{fleet_name}"
    bridge_inbox, service_inbox = Inbox(), Inbox()
    subs = [
        fleet["bridge"].declare_subscriber(f"{uw}/**", bridge_inbox),
        fleet["service"].declare_subscriber(f"{top}/submap/**", service_inbox),
    ]
    try:
        own, forged = f"{uw}/submap/auv1/s0/1", f"{uw}/submap/auv2/s0/1"
        with _publishers(fleet["auv1"], own, forged) as put:
            assert _deliver(put, bridge_inbox, own, forged)
        time.sleep(QUIET_S)
        assert forged not in bridge_inbox.keys
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
    _set(wrong, "transport/auth/usrpwd/password", "not-the-password")
    assert _refused(wrong)
    unknown = _client_config("auv1", fleet.port, timeout_ms=0)
    _set(unknown, "transport/auth/usrpwd/user", "auv9")
    assert _refused(unknown)
    anonymous = _quiet(zenoh.Config())
    _set(anonymous, "mode", "client")
    _set(anonymous, "connect/endpoints", [f"tcp/127.0.0.1:{fleet.port}"])
    _set(anonymous, "connect/timeout_ms", 0)
    assert _refused(anonymous)
    # the right password does connect (same config, nothing else changed)
    assert not _refused(_client_config("auv1", fleet.port, timeout_ms=0))


def test_embedded_router_applies_the_acl_to_robots() -> None:
    """`mergesvc serve --mode router --config deploy/zenohd.json5`: the service's own session
    is the router; its local subscriber gets only what the ACL lets the robots put."""
    port = _free_port()
    sessions: list[zenoh.Session] = []
    try:
        service = zenoh.open(_router_config(port))
        sessions.append(service)
        auv1 = zenoh.open(_client_config("auv1", port))
        sessions.append(auv1)
        inbox = Inbox()
        sub = service.declare_subscriber("mergesvc/v1/embedded/submap/**", inbox)
        try:
            own = "mergesvc/v1/embedded/submap/auv1/s0/1"
            forged = "mergesvc/v1/embedded/submap/auv2/s0/1"
            with _publishers(auv1, own, forged) as put:
                assert _deliver(put, inbox, own, forged)
            time.sleep(QUIET_S)
            assert forged not in inbox.keys
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
    _set(config, "connect/endpoints", [f"tls/127.0.0.1:{port}"])
    _set(config, "connect/timeout_ms", 0)
    _set(config, "transport/link/tls/root_ca_certificate", str(ca / "ca.pem"))
    if name is None:
        config.insert_json5("transport/link/tls/connect_certificate", "null")
        config.insert_json5("transport/link/tls/connect_private_key", "null")
    else:
        _set(config, "transport/link/tls/connect_certificate", str(certs / f"{name}.pem"))
        _set(config, "transport/link/tls/connect_private_key", str(certs / f"{name}-key.pem"))
    return _quiet(config)


def test_mtls_router_acl_by_certificate_name(tmp_path: Path) -> None:
    certs = _make_certs(tmp_path / "certs")
    foreign = _make_certs(tmp_path / "foreign")  # another CA, same names
    assert (certs / ".gitignore").read_text().strip() == "*"
    port = _free_port()
    router_config = zenoh.Config.from_file(str(DEPLOY / "zenohd-tls.json5"))
    _set(router_config, "listen/endpoints", [f"tls/127.0.0.1:{port}"])
    for key, file in (
        ("root_ca_certificate", "ca.pem"),
        ("listen_certificate", "zenohd.pem"),
        ("listen_private_key", "zenohd-key.pem"),
    ):
        _set(router_config, f"transport/link/tls/{key}", str(certs / file))
    sessions: list[zenoh.Session] = []
    try:
        sessions.append(zenoh.open(_quiet(router_config)))
        service = zenoh.open(_tls_client_config(port, certs, "mergesvc", certs))
        sessions.append(service)
        auv1 = zenoh.open(_tls_client_config(port, certs, "auv1", certs))
        sessions.append(auv1)
        inbox = Inbox()
        sub = service.declare_subscriber("mergesvc/v1/tls/submap/**", inbox)
        try:
            own, forged = "mergesvc/v1/tls/submap/auv1/s0/1", "mergesvc/v1/tls/submap/auv2/s0/1"
            with _publishers(auv1, own, forged) as put:
                assert _deliver(put, inbox, own, forged)
            time.sleep(QUIET_S)
            assert forged not in inbox.keys
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
