"""Opening Zenoh sessions: a config from the shared --config/--mode/--connect/--listen flags, and
`open_session`, which turns Zenoh's refusals into errors that name the endpoint.

Guarantees: a malformed connect or listen endpoint is an InputError before any socket opens; a
config file Zenoh cannot read is a ConfigError naming the file; a session that cannot open (a
port in use, nothing answering within the connect timeout) is a TransportError with the endpoint
and its `TransportFault`. Zenoh's messages reach the user without their Rust source locations.

May import: zenoh, the standard library, mergesvc.errors.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Sequence

import zenoh

from mergesvc.errors import ConfigError, InputError, TransportError, TransportFault

# links whose address is host:port (the others, unixsock-stream, serial, ..., are left to zenoh)
_HOST_PORT_LINKS = frozenset({"tcp", "udp", "tls", "quic", "ws"})
_ENDPOINT = re.compile(r"(?P<proto>[a-z][a-z0-9_-]*)/(?P<address>[^?#\s]+)(?:\?[^#\s]*)?(?:#\S*)?")
_HOST_PORT = re.compile(r"(?:\[[0-9A-Za-z:.%]+\]|[^:\[\]/]+):(?P<port>[0-9]{1,5})")
_RUST_LOCATION = re.compile(r"\s*\bat /\S+\.rs:\d+\.?")
_JSON_MESSAGE = re.compile(r'msg: "(?P<msg>(?:[^"\\]|\\.)*)", location: Some\(Location \{ '
                           r"line: (?P<line>\d+), column: (?P<col>\d+) \}\)")
_PEST_POSITION = re.compile(r"-->\s*(?P<line>\d+):(?P<col>\d+)")
_BOUND_TO = re.compile(r"\bbound to (?P<ep>\S+?): \[")
_CONNECT_TARGET = re.compile(r"Single\((?P<ep>[^)]+)\)")
_OS_REASON = re.compile(r"(?P<reason>[A-Z][^:\[\]]*?) \(os error \d+\)")


def check_endpoint(endpoint: str, role: str) -> str:
    """`endpoint` if it is a Zenoh endpoint (`<protocol>/<address>`; host:port for IP links,
    port 1-65535 to connect, 0-65535 to listen), else InputError. `role`: connect or listen."""
    m = _ENDPOINT.fullmatch(endpoint)
    ok = m is not None
    if m is not None and m["proto"] in _HOST_PORT_LINKS:
        hp = _HOST_PORT.fullmatch(m["address"])
        low = 1 if role == "connect" else 0
        ok = hp is not None and low <= int(hp["port"]) <= 65535
    if not ok:
        raise InputError(f"{role} endpoint {endpoint!r} is not a Zenoh endpoint: write "
                         "<protocol>/<host>:<port>, e.g. tcp/127.0.0.1:7447")
    return endpoint


def make_zenoh_config(
    *,
    config_file: str | None = None,
    mode: str | None = None,
    connect: Sequence[str] = (),
    listen: Sequence[str] = (),
    scouting: bool = True,
    connect_timeout_s: float | None = None,
) -> zenoh.Config:
    """A zenoh Config from the usual `--config/--mode/--connect/--listen` flags.

    `scouting=False` turns multicast and gossip scouting off and sets `scouting/delay` to 0
    (tests and fixed topologies). `connect_timeout_s`: how long the session keeps trying its
    connect endpoints before `open_session` gives up (0: one try; negative: forever, never
    giving up); None leaves it to the file (or Zenoh: a client tries once, a peer or router
    keeps trying in the background).
    """
    for ep in connect:
        check_endpoint(ep, "connect")
    for ep in listen:
        check_endpoint(ep, "listen")
    if connect_timeout_s is not None and math.isnan(connect_timeout_s):
        raise InputError("the connect timeout must be a number of seconds")
    try:
        config = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    except (zenoh.ZError, OSError, ValueError) as exc:
        raise ConfigError(f"cannot read the Zenoh config {config_file}: {zenoh_message(exc)}"
                          ) from exc
    try:
        if mode:
            config.insert_json5("mode", json.dumps(mode))
        if connect:
            config.insert_json5("connect/endpoints", json.dumps(list(connect)))
        if listen:
            config.insert_json5("listen/endpoints", json.dumps(list(listen)))
        if not scouting:
            config.insert_json5("scouting/multicast/enabled", "false")
            config.insert_json5("scouting/gossip/enabled", "false")
            config.insert_json5("scouting/delay", "0")
        if connect_timeout_s is not None:
            forever = connect_timeout_s < 0 or math.isinf(connect_timeout_s)
            timeout_ms = -1 if forever else round(connect_timeout_s * 1000)
            config.insert_json5("connect/timeout_ms", json.dumps(timeout_ms))
            config.insert_json5("connect/exit_on_failure", json.dumps(not forever))
    except (zenoh.ZError, OSError, ValueError) as exc:
        raise ConfigError(f"invalid zenoh configuration: {zenoh_message(exc)}") from exc
    return config


def open_session(config: zenoh.Config) -> zenoh.Session:
    """`zenoh.open(config)`; a session Zenoh refuses to open is a TransportError."""
    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        raise transport_error(exc, config) from exc


def transport_error(exc: Exception, config: zenoh.Config) -> TransportError:
    """The TransportError for Zenoh's refusal `exc` to open a session with `config`."""
    text = zenoh_message(exc)
    raw = str(exc)
    if "listener" in raw or "Address already in use" in raw:
        m = _BOUND_TO.search(raw)
        ep = m["ep"] if m else _first(_endpoints(config, "listen"))
        if "Address already in use" in raw:
            return TransportError(f"{ep} is in use", fault=TransportFault.IN_USE, endpoint=ep)
        reason = _OS_REASON.search(raw)
        why = reason["reason"] if reason else text
        return TransportError(f"cannot listen on {ep}: {why}", fault=TransportFault.CANNOT_LISTEN,
                              endpoint=ep)
    if "Unable to connect to any of" in raw:
        eps = _CONNECT_TARGET.findall(raw) or _endpoints(config, "connect")
        timeout_ms = _connect_timeout_ms(config)
        within = f" within {timeout_ms / 1000:g} s" if timeout_ms and timeout_ms > 0 else ""
        return TransportError(f"nothing answered at {', '.join(eps)}{within}",
                              fault=TransportFault.NO_ANSWER, endpoint=_first(eps))
    if _get(config, "mode") == "client" and not _endpoints(config, "connect"):
        return TransportError(f"no Zenoh router answered scouting (a client with no connect "
                              f"endpoint): {text}")
    eps = _endpoints(config, "listen") + _endpoints(config, "connect")
    where = f" ({', '.join(eps)})" if eps else ""
    return TransportError(f"cannot open a Zenoh session{where}: {text}", endpoint=_first(eps))


def zenoh_message(exc: BaseException) -> str:
    """Zenoh's error text on one line, without Rust source locations; a JSON5 or parse error
    as its message and `line L, column C`."""
    raw = str(exc)
    m = _JSON_MESSAGE.search(raw)
    if m:
        msg = _RUST_LOCATION.sub("", m["msg"].replace('\\"', '"'))
        return f"{msg} (line {m['line']}, column {m['col']})"
    pest = _PEST_POSITION.search(raw)
    if pest:  # the pest parser's picture of the line: keep its last line, "= expected ..."
        tail = _RUST_LOCATION.sub("", raw).strip().splitlines()[-1].strip().lstrip("= ")
        return f"line {pest['line']}, column {pest['col']}: {tail}"
    return " ".join(_RUST_LOCATION.sub("", raw).split()) or type(exc).__name__


def _first(items: Sequence[str]) -> str | None:
    return items[0] if items else None


def _get(config: zenoh.Config, key: str) -> object:
    try:
        return json.loads(config.get_json(key))
    except (zenoh.ZError, ValueError):
        return None


def _for_mode(config: zenoh.Config, value: object) -> object:
    """A setting given per mode (`{router: ..., peer: ..., client: ...}`): this config's."""
    if isinstance(value, dict):
        return value.get(_get(config, "mode") or "peer")
    return value


def _endpoints(config: zenoh.Config, which: str) -> list[str]:
    value = _for_mode(config, _get(config, f"{which}/endpoints"))
    return [str(v) for v in value] if isinstance(value, list) else []


def _connect_timeout_ms(config: zenoh.Config) -> int | None:
    value = _for_mode(config, _get(config, "connect/timeout_ms"))
    return value if isinstance(value, int) else None


__all__ = ["check_endpoint", "make_zenoh_config", "open_session", "transport_error",
           "zenoh_message"]
