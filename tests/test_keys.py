"""Zenoh key expressions: each function's exact string (the strings README.md lists; vehicles,
the service, the bridge and the router's ACL agree on them), names refused, and no key built
anywhere else in fleet/, cli/ or link/ (the acoustic bridge)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import mergesvc
from mergesvc.errors import ConfigError
from mergesvc.wire import keys

PACKAGE = Path(mergesvc.__file__).resolve().parent
TOP = keys.fleet_root("fleet0")
UW = keys.uw_root("fleet0")


def test_roots() -> None:
    assert TOP == "mergesvc/v1/fleet0"
    assert UW == "mergesvc/v1/uw/fleet0"
    assert keys.fleet_root("demo0") == "mergesvc/v1/demo0"


@pytest.mark.parametrize("root", [TOP, UW])
def test_every_key_under_either_root(root: str) -> None:
    assert keys.submap_key(root, "auv1", "s0") == f"{root}/submap/auv1/s0"
    assert keys.all_submaps(root) == f"{root}/submap/**"
    assert keys.factor_key(root, "auv2", "auv1.s0-auv2.s0-3") == (
        f"{root}/factor/auv2/auv1.s0-auv2.s0-3"
    )
    assert keys.robot_factors(root, "auv2") == f"{root}/factor/auv2/**"
    assert keys.all_factors(root) == f"{root}/factor/**"
    assert keys.error_key(root, "auv1") == f"{root}/error/auv1"
    assert keys.all_errors(root) == f"{root}/error/**"
    assert keys.result_key(root, "auv1") == f"{root}/result/auv1"
    assert keys.all_results(root) == f"{root}/result/**"
    assert keys.relocalize_key(root) == f"{root}/relocalize"
    assert keys.status_key(root) == f"{root}/status"
    assert keys.alive_key(root, "auv3") == f"{root}/alive/auv3"
    assert keys.all_alive(root) == f"{root}/alive/*"


def test_the_literal_strings() -> None:
    """Spelled out once, so a change of the key space cannot pass unnoticed."""
    assert keys.submap_key(TOP, "auv1", "s0") == "mergesvc/v1/fleet0/submap/auv1/s0"
    assert keys.factor_key(UW, "auv1", "f-1") == "mergesvc/v1/uw/fleet0/factor/auv1/f-1"
    assert keys.error_key(TOP, "auv1") == "mergesvc/v1/fleet0/error/auv1"
    assert keys.result_key(TOP, "auv1") == "mergesvc/v1/fleet0/result/auv1"
    assert (keys.MSGPACK_ENCODING, keys.JSON_ENCODING) == ("application/msgpack",
                                                           "application/json")
    assert keys.relocalize_key(TOP) == "mergesvc/v1/fleet0/relocalize"
    assert keys.status_key(TOP) == "mergesvc/v1/fleet0/status"
    assert keys.alive_key(TOP, "auv1") == "mergesvc/v1/fleet0/alive/auv1"


def test_sessions_and_factor_ids_keep_their_slashes() -> None:
    """Sessions may contain '/' (frame names split at the first one); the key does too."""
    assert keys.submap_key(TOP, "auv1", "2024/05") == f"{TOP}/submap/auv1/2024/05"
    assert keys.factor_key(TOP, "auv1", "a.2024/05-b.s0-1") == (
        f"{TOP}/factor/auv1/a.2024/05-b.s0-1"
    )


def test_the_bridge_keys() -> None:
    """The bridge moves keys between two prefixes by their suffix; what it carries down is
    every factor."""
    assert keys.under(UW, "submap/auv1/s0") == "mergesvc/v1/uw/fleet0/submap/auv1/s0"
    assert keys.under(TOP, "factor/auv1/f-1") == keys.factor_key(TOP, "auv1", "f-1")
    assert keys.all_under(UW) == "mergesvc/v1/uw/fleet0/**"
    assert keys.BRIDGE_DOWNLINK == ("factor/**",)
    for root in (TOP, UW):
        assert [keys.under(root, k) for k in keys.BRIDGE_DOWNLINK] == [keys.all_factors(root)]
    # any plain key expression is a prefix (the bridge is not tied to the fleet roots)
    assert keys.under("a/uw", "x/y") == "a/uw/x/y"
    assert keys.all_under("mergesvc/v1/f/uw") == "mergesvc/v1/f/uw/**"


@pytest.mark.parametrize("prefix", ["", "a/", "/a", "a//b", "a/*", "a/**", "a$", "a?b", "a#"])
def test_bridge_prefixes_with_wildcards_or_empty_chunks_are_refused(prefix: str) -> None:
    with pytest.raises(ConfigError):
        keys.under(prefix, "submap/auv1/s0")
    with pytest.raises(ConfigError):
        keys.all_under(prefix)


def test_parsing_keys() -> None:
    assert keys.submap_robot(TOP, f"{TOP}/submap/auv2/s0") == "auv2"
    assert keys.submap_robot(TOP, f"{TOP}/submap/auv2/s/1") == "auv2"
    assert keys.submap_robot(TOP, f"{TOP}/submap") is None
    assert keys.submap_robot(TOP, f"{TOP}/status") is None
    assert keys.submap_robot(TOP, "mergesvc/v1/other/submap/auv2/s0") is None
    assert keys.alive_robot(keys.alive_key(TOP, "auv3")) == "auv3"


@pytest.mark.parametrize("fleet", ["", "a/b", "a*", "x" * 65, "a b", "é"])
def test_invalid_fleet_names_are_refused(fleet: str) -> None:
    with pytest.raises(ConfigError):
        keys.fleet_root(fleet)
    with pytest.raises(ConfigError):
        keys.uw_root(fleet)


@pytest.mark.parametrize("robot", ["", "a/b", "a*", "**", "a$b", "a?", "a#"])
def test_invalid_robot_names_are_refused(robot: str) -> None:
    for make in (
        lambda: keys.submap_key(TOP, robot, "s0"),
        lambda: keys.factor_key(TOP, robot, "f1"),
        lambda: keys.robot_factors(TOP, robot),
        lambda: keys.error_key(TOP, robot),
        lambda: keys.result_key(TOP, robot),
        lambda: keys.alive_key(TOP, robot),
    ):
        with pytest.raises(ConfigError):
            make()


@pytest.mark.parametrize("name", ["", "/s", "s/", "a//b", "*", "s/**", "s$", "s?x", "s#"])
def test_invalid_sessions_and_factor_ids_are_refused(name: str) -> None:
    with pytest.raises(ConfigError):
        keys.submap_key(TOP, "auv1", name)
    with pytest.raises(ConfigError):
        keys.factor_key(TOP, "auv1", name)


@pytest.mark.parametrize(
    "root", ["", "fleet0", "mergesvc/v1", "mergesvc/v1/", "mergesvc/v2/fleet0",
             "mergesvc/v1/fleet0/", "mergesvc/v1/a/b", "mergesvc/v1/*", TOP + "/submap"]
)
def test_roots_of_another_shape_are_refused(root: str) -> None:
    for make in (keys.all_submaps, keys.all_factors, keys.status_key, keys.relocalize_key,
                 keys.all_alive, keys.all_errors, keys.all_results):
        with pytest.raises(ConfigError):
            make(root)


# --------------------------------------------------------------------------------------------
# Keys are built only in keys.py
# --------------------------------------------------------------------------------------------

# "/*": a wildcard subscription
KEY_PARTS = ("/submap", "/factor", "/status", "/error", "/result", "/alive", "/relocalize",
             "submap/", "factor/", "alive/", "error/", "result/", "/*")


def _docstrings(tree: ast.Module) -> set[int]:
    ids = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                ids.add(id(body[0].value))
    return ids


def key_literals(source: str) -> list[tuple[int, str]]:
    """String literals (plain, or the text of f-strings) that look like a piece of a key
    expression, docstrings left out."""
    tree = ast.parse(source)
    docs = _docstrings(tree)
    out = []
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Constant)
            and isinstance(node.value, str)
            and id(node) not in docs
            and any(part in node.value for part in KEY_PARTS)
        ):
            out.append((node.lineno, node.value))
    return out


def test_the_literal_check_sees_keys() -> None:
    src = (
        '"""Docstrings may say {root}/status."""\n'
        'a = f"{root}/status"\n'
        'b = root + "/factor/" + robot\n'
        'c = f"{root}/alive/{robot}"\n'
        'd = "--store"\n'
        'e = f"factor/{robot}/**"\n'
        'f = f"{prefix}/**"\n'
        'g = ("factor/**",)\n'
    )
    assert sorted({line for line, _ in key_literals(src)}) == [2, 3, 4, 6, 7, 8]


@pytest.mark.parametrize("folder", ["fleet", "cli", "link"])
def test_no_key_is_built_outside_keys_py(folder: str) -> None:
    found = [
        f"{path.relative_to(PACKAGE.parent)}:{line}: {text!r}"
        for path in sorted((PACKAGE / folder).rglob("*.py"))
        for line, text in key_literals(path.read_text())
    ]
    assert not found, "build keys with mergesvc.wire.keys:\n" + "\n".join(found)
