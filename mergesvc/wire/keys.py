"""Every Zenoh key expression of mergesvc, versioned under one root; built only here."""

from __future__ import annotations

import re

from mergesvc.errors import ConfigError

ROOT = "mergesvc/v1"
_NAME = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")


def _name(value: str, what: str) -> str:
    if not _NAME.match(value):
        raise ConfigError(f"invalid {what} {value!r}: use 1-64 of A-Z a-z 0-9 _ . -")
    return value


def fleet_root(fleet: str) -> str:
    """Topside root of a fleet: mergesvc/v1/{fleet}."""
    return f"{ROOT}/{_name(fleet, 'fleet')}"


def uw_root(fleet: str) -> str:
    """Vehicle side of an acoustic link: what the bridge carries to fleet_root(fleet)."""
    return f"{ROOT}/uw/{_name(fleet, 'fleet')}"
