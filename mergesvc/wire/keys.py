"""Every Zenoh key expression of mergesvc, versioned under one root; built only here.

A fleet has two roots: the topside `fleet_root(fleet)` (the service, and vehicles on Zenoh) and
the vehicle side of an acoustic link `uw_root(fleet)`; under either the key space is the same
(submap, factor, error, result, relocalize, status, alive: docs/wire.md §11). The service sends
coded messages as MSGPACK_ENCODING and JSON documents as JSON_ENCODING.

Every function takes the root first and refuses a root of another shape, and a name that would
not be one key chunk (a robot) or that Zenoh refuses in a key (`*`, `$`, `?`, `#`, empty
chunks): `ConfigError`. Names are otherwise taken as they come: the key of a name that worked
before must not change. `under`, `all_under` and BRIDGE_DOWNLINK address keys by their suffix
below a prefix for the acoustic bridge (link/bridge.py); they refuse a prefix with wildcards,
`$?#` or empty chunks. Which function builds which key: docs/wire.md §11.4.
"""

from __future__ import annotations

import re

from mergesvc.errors import ConfigError

ROOT = "mergesvc/v1"
_NAME = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
_ROOT = re.compile(r"^mergesvc/v1/(uw/)?[A-Za-z0-9_.-]{1,64}$")
_RESERVED = set("*$?#")

#: Zenoh encoding of the coded (msgpack) messages of docs/wire.md. Zenoh 1.x predefines no
#: msgpack encoding: this string travels as a custom encoding and reads back as itself.
MSGPACK_ENCODING = "application/msgpack"
#: Zenoh encoding of JSON documents (zenoh.Encoding.APPLICATION_JSON).
JSON_ENCODING = "application/json"


class KeyNameError(ConfigError, ValueError):
    """A name that cannot be a key's (a ValueError too, so a settings validator reports it)."""


def _name(value: str, what: str) -> str:
    if not isinstance(value, str) or not _NAME.match(value):
        raise KeyNameError(f"invalid {what} {value!r}: use 1-64 of A-Z a-z 0-9 _ . -")
    return value


def _root(root: str) -> str:
    if not isinstance(root, str) or not _ROOT.match(root):
        raise ConfigError(f"invalid key root {root!r}: use fleet_root(fleet) or uw_root(fleet)")
    return root


def _chunks(value: str, what: str, *, one: bool) -> str:
    """`value` as one key chunk (`one`), or as chunks joined by '/' (sessions, factor ids)."""
    if not isinstance(value, str) or not value:
        raise KeyNameError(f"invalid {what} {value!r}: must be a non-empty string")
    if one and "/" in value:
        raise KeyNameError(f"invalid {what} {value!r}: may not contain '/'")
    if "" in value.split("/"):
        raise KeyNameError(f"invalid {what} {value!r}: empty key chunk")
    if _RESERVED & set(value):
        raise KeyNameError(f"invalid {what} {value!r}: may not contain * $ ? #")
    return value


def _robot(robot: str) -> str:
    return _chunks(robot, "robot", one=True)


def check_name(what: str, value: str) -> str:
    """`value` if it can be the fleet, robot or session (`what`) of a key, else KeyNameError:
    the rule every key built here applies, for settings to apply before anything connects."""
    if what == "fleet":
        return _name(value, what)
    if what in ("robot", "session"):
        return _chunks(value, what, one=what == "robot")
    raise ValueError(f"not a key name: {what!r}")


def fleet_root(fleet: str) -> str:
    """Topside root of a fleet: mergesvc/v1/{fleet}."""
    return f"{ROOT}/{_name(fleet, 'fleet')}"


def uw_root(fleet: str) -> str:
    """Vehicle side of an acoustic link: what the bridge carries to fleet_root(fleet)."""
    return f"{ROOT}/uw/{_name(fleet, 'fleet')}"


def submap_key(root: str, robot: str, session: str) -> str:
    """Where a vehicle publishes the submaps of one session: {root}/submap/{robot}/{session}."""
    return f"{_root(root)}/submap/{_robot(robot)}/{_chunks(session, 'session', one=False)}"


def all_submaps(root: str) -> str:
    """Every submap of the fleet (what the service subscribes to): {root}/submap/**."""
    return f"{_root(root)}/submap/**"


def submap_robot(root: str, key: str) -> str | None:
    """The robot a submap key names ({root}/submap/{robot}/...), None for another key."""
    prefix = f"{_root(root)}/submap/"
    if not key.startswith(prefix):
        return None
    robot = key[len(prefix):].split("/", 1)[0]
    return robot or None


def factor_key(root: str, robot: str, factor_id: str) -> str:
    """Where the service sends one factor to one of its robots:
    {root}/factor/{robot}/{factor_id}."""
    return f"{_root(root)}/factor/{_robot(robot)}/{_chunks(factor_id, 'factor id', one=False)}"


def robot_factors(root: str, robot: str) -> str:
    """Every factor for one robot (what a vehicle subscribes to): {root}/factor/{robot}/**."""
    return f"{_root(root)}/factor/{_robot(robot)}/**"


def all_factors(root: str) -> str:
    """Every factor of the fleet: {root}/factor/**."""
    return f"{_root(root)}/factor/**"


def error_key(root: str, robot: str) -> str:
    """Where the service answers a robot's bad submaps: {root}/error/{robot}."""
    return f"{_root(root)}/error/{_robot(robot)}"


def all_errors(root: str) -> str:
    """Every error answer of the fleet: {root}/error/**."""
    return f"{_root(root)}/error/**"


def result_key(root: str, robot: str) -> str:
    """Where the service says what became of each of a robot's submaps (processed, no match,
    refused): {root}/result/{robot}."""
    return f"{_root(root)}/result/{_robot(robot)}"


def all_results(root: str) -> str:
    """Every submap result of the fleet: {root}/result/**."""
    return f"{_root(root)}/result/**"


def relocalize_key(root: str) -> str:
    """The relocalize queryable: {root}/relocalize."""
    return f"{_root(root)}/relocalize"


def status_key(root: str) -> str:
    """The status queryable: {root}/status."""
    return f"{_root(root)}/status"


def alive_key(root: str, robot: str) -> str:
    """A robot's liveliness token: {root}/alive/{robot}."""
    return f"{_root(root)}/alive/{_robot(robot)}"


def all_alive(root: str) -> str:
    """Every robot's liveliness token (what the service watches): {root}/alive/*."""
    return f"{_root(root)}/alive/*"


def alive_robot(key: str) -> str:
    """The robot an alive/{robot} key names: its last chunk."""
    return key.rsplit("/", 1)[-1]


#: What the acoustic bridge carries from the topside down to the vehicles, as key expressions
#: below a root (under(root, s) for s in BRIDGE_DOWNLINK): every factor, all_factors(root).
BRIDGE_DOWNLINK: tuple[str, ...] = ("factor/**",)


def _prefix(prefix: str) -> str:
    return _chunks(prefix, "key prefix", one=False)


def under(prefix: str, suffix: str) -> str:
    """`suffix` below a plain key expression `prefix`: {prefix}/{suffix} (the bridge's
    republished keys and its downlink subscriptions)."""
    return f"{_prefix(prefix)}/{suffix}"


def all_under(prefix: str) -> str:
    """Every key below a plain key expression `prefix`: {prefix}/** (what the bridge carries
    up from the vehicle side)."""
    return f"{_prefix(prefix)}/**"


def advanced_publishers(key_expr: str) -> str:
    """The liveliness tokens of zenoh-ext's advanced publishers on a key expression (wildcards
    allowed), in zenoh-ext's own layout: {key_expr}/@adv/pub/**. A token's key less that
    suffix's chunks is the publication key, and a query on the token's key reaches its cache."""
    return f"{key_expr}/@adv/pub/**"


def advanced_publisher_source(token_key: str) -> tuple[str, str] | None:
    """(zid, eid) of the advanced publisher whose liveliness token is `token_key`
    ({key}/@adv/pub/{zid}/{eid}/...), as its samples' source id prints them; None if the key
    is not such a token."""
    _, sep, rest = token_key.partition("/@adv/pub/")
    parts = rest.split("/")
    if not sep or len(parts) < 2 or not parts[0] or not parts[1]:
        return None
    return parts[0], parts[1]


__all__ = [
    "BRIDGE_DOWNLINK",
    "JSON_ENCODING",
    "MSGPACK_ENCODING",
    "ROOT",
    "KeyNameError",
    "advanced_publisher_source",
    "advanced_publishers",
    "alive_key",
    "alive_robot",
    "all_alive",
    "all_errors",
    "all_factors",
    "all_results",
    "all_submaps",
    "all_under",
    "check_name",
    "error_key",
    "factor_key",
    "fleet_root",
    "relocalize_key",
    "result_key",
    "robot_factors",
    "status_key",
    "submap_key",
    "submap_robot",
    "under",
    "uw_root",
]
