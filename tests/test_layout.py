"""The package's layout is its architecture: which layer may import which, no import cycles, no
side effects in the core, and the public API at the package top (see mergesvc/__init__.py)."""

from __future__ import annotations

import ast
import importlib
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

import mergesvc

PACKAGE = Path(mergesvc.__file__).resolve().parent

# Layer -> the layers it may import (itself included). "api" is mergesvc/__init__.py.
ALLOWED: dict[str, set[str]] = {
    "errors": {"errors"},
    "core": {"core", "errors"},
    "wire": {"wire", "core", "errors"},
    "link": {"link", "wire", "core", "errors"},
    "sim": {"sim", "core", "errors"},
    "fleet": {"fleet", "link", "wire", "sim", "core", "errors"},
    "bench": {"bench", "link", "wire", "sim", "core", "errors"},
    "settings": {"settings", "fleet", "link", "wire", "sim", "core", "errors"},
    "cli": {"cli", "settings", "fleet", "bench", "link", "wire", "sim", "core", "errors", "api"},
    "api": {"core", "wire", "errors"},
}
# Third-party and stdlib modules that mean I/O beyond computation, forbidden in these layers.
SIDE_EFFECT_MODULES = {"zenoh", "socket", "sqlite3", "subprocess", "multiprocessing", "msgpack"}
PURE_LAYERS = {"core", "sim"}
# File access in core, with the reason it is still there (none: mergesvc/settings.py reads the
# settings file and the environment).
CORE_FILE_ACCESS: dict[str, str] = {}


def _module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _layer(module: str) -> str:
    parts = module.split(".")
    if len(parts) == 1:
        return "api"
    return parts[1]


def _modules() -> dict[str, ast.Module]:
    return {
        _module_name(p): ast.parse(p.read_text(), filename=str(p))
        for p in sorted(PACKAGE.rglob("*.py"))
    }


MODULES = _modules()


def _is_package(module: str) -> bool:
    return (PACKAGE.parent / module.replace(".", "/") / "__init__.py").exists()


def _imports(module: str, tree: ast.Module) -> list[tuple[str, int]]:
    """Every module this one imports (at any depth: lazy imports count), as absolute names.

    `from pkg import name` counts as importing pkg.name when that is a module, else pkg."""
    out: list[tuple[str, int]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.extend((a.name, node.lineno) for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")
                base = base[: len(base) - node.level + (1 if _is_package(module) else 0)]
                target = ".".join([*base, node.module] if node.module else base)
            else:
                target = node.module or ""
            for a in node.names:
                sub = f"{target}.{a.name}"
                out.append((sub if sub in MODULES else target, node.lineno))
    return out


def _internal_edges() -> dict[str, set[str]]:
    edges: dict[str, set[str]] = defaultdict(set)
    for module, tree in MODULES.items():
        for target, _ in _imports(module, tree):
            if target in MODULES and target != module:
                edges[module].add(target)
    return edges


def test_the_tree_has_the_documented_layers() -> None:
    layers = {_layer(m) for m in MODULES}
    assert layers == set(ALLOWED), layers ^ set(ALLOWED)


def test_each_layer_imports_only_the_layers_below_it() -> None:
    bad = []
    for module, tree in MODULES.items():
        layer = _layer(module)
        for target, line in _imports(module, tree):
            is_ours = target == "mergesvc" or target.startswith("mergesvc.")
            if is_ours and _layer(target) not in ALLOWED[layer]:
                bad.append(f"{module}:{line} ({layer}) imports {target}")
    assert not bad, "\n".join(bad)


def test_nothing_imports_the_cli() -> None:
    bad = [
        f"{module}:{line}"
        for module, tree in MODULES.items()
        if _layer(module) != "cli"
        for target, line in _imports(module, tree)
        if target.startswith("mergesvc.cli")
    ]
    assert not bad


def test_no_import_cycles() -> None:
    edges = _internal_edges()
    state: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for t in sorted(edges.get(m, ())):
            if state.get(t) == 1:
                cycles.append([*stack[stack.index(t) :], t])
            elif t not in state:
                visit(t)
        stack.pop()
        state[m] = 2

    for m in sorted(MODULES):
        if m not in state:
            visit(m)
    assert not cycles, "\n".join(" -> ".join(c) for c in cycles)


def test_modules_inside_a_package_do_not_import_its_facade() -> None:
    """Inside wire/, link/, sim/, ... modules import leaves; the package __init__ is for the
    layers above (importing it from inside is how cycles start)."""
    bad = []
    for module, tree in MODULES.items():
        if _is_package(module) or module.endswith(".__main__"):  # `python -m pkg` runs pkg
            continue
        package = module.rsplit(".", 1)[0]
        if package == "mergesvc":
            continue
        for target, line in _imports(module, tree):
            if target == package:
                bad.append(f"{module}:{line} imports its own package {package}")
    assert not bad, "\n".join(bad)


def test_core_and_sim_have_no_side_effect_imports() -> None:
    bad = []
    for module, tree in MODULES.items():
        if _layer(module) not in PURE_LAYERS:
            continue
        for target, line in _imports(module, tree):
            if target.split(".")[0] in SIDE_EFFECT_MODULES:
                bad.append(f"{module}:{line} imports {target}")
    assert not bad, "\n".join(bad)


def _file_access(tree: ast.Module) -> list[int]:
    lines = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            f = node.func
            if isinstance(f, ast.Name) and f.id == "open":
                lines.append(node.lineno)
            if isinstance(f, ast.Attribute) and f.attr in {
                "read_text", "read_bytes", "write_text", "write_bytes", "open", "mkdir", "unlink",
            }:
                lines.append(node.lineno)
    return lines


def test_core_does_not_touch_files() -> None:
    bad = {
        module: lines
        for module, tree in MODULES.items()
        if _layer(module) == "core" and (lines := _file_access(tree))
    }
    assert set(bad) == set(CORE_FILE_ACCESS), bad


def test_the_file_access_check_sees_file_access() -> None:
    tree = ast.parse("from pathlib import Path\nPath('x').read_text()\nopen('y')\n")
    assert _file_access(tree) == [2, 3]
    assert _file_access(ast.parse("x = 1\n")) == []


def test_the_import_rules_catch_a_violation() -> None:
    """The checks above are only worth something if they can fail."""
    tree = ast.parse("from mergesvc.fleet.service import MergeService\nimport zenoh\n")
    targets = [t for t, _ in _imports("mergesvc.core.fake", tree)]
    assert "mergesvc.fleet.service" in targets
    assert _layer("mergesvc.fleet.service") not in ALLOWED["core"]
    assert "zenoh" in targets
    rel = ast.parse("from ..wire import codec\n")
    assert _imports("mergesvc.core.fake", rel)[0][0].startswith("mergesvc.wire")


def test_public_api_at_the_package_top() -> None:
    public = set(mergesvc.__all__)
    for name in public:
        assert hasattr(mergesvc, name), name
    expected = {
        "match", "MatchConfig", "MatchOutcome", "MatchResult", "ObjectNode", "ObjectMap",
        "Submap", "Factor", "Correspondence", "RejectReason", "Transform", "ObjectArrays",
        "encode_message", "decode_message", "encode_file", "decode_file", "Profile",
        "Projection", "MergeError", "InputError", "__version__",
    }
    assert expected <= public, expected - public
    assert len(public) == len(mergesvc.__all__)
    # defined names that look public are exported, so __all__ is the whole story
    missing = {
        n for n, v in vars(mergesvc).items()
        if not n.startswith("_") and not isinstance(v, type(mergesvc))
    } - public
    assert not missing, missing


@pytest.mark.parametrize(
    "package", ["mergesvc.wire", "mergesvc.link", "mergesvc.sim", "mergesvc.bench"]
)
def test_facades_export_what_they_list(package: str) -> None:
    mod = importlib.import_module(package)
    assert mod.__all__, package
    for name in mod.__all__:
        assert getattr(mod, name) is not None, f"{package}.{name}"


def test_the_package_top_works_as_a_user_would_call_it() -> None:
    rng = np.random.default_rng(0)
    objs = [
        mergesvc.ObjectNode(
            id=f"o{i}",
            embedding=rng.normal(size=8).tolist(),
            variance=0.01,
            position=tuple(rng.uniform(-5, 5, size=3).tolist()),
        )
        for i in range(6)
    ]
    m = mergesvc.ObjectMap(robot_id="a", session_id="s0", objects=objs)
    sub = mergesvc.Submap(robot_id="b", session_id="s0", objects=objs)
    out = mergesvc.match(m, sub)
    assert out.result.accepted
    assert all(x.submap_object == x.map_object for x in out.result.matches)
    blob = mergesvc.encode_message(sub, mergesvc.Profile.FULL, "b", 0)
    _, decoded = mergesvc.decode_message(blob)
    assert decoded.objects[0].id == "o0"


MODULES_WITH_ALL = sorted(m for m, tree in MODULES.items() if any(
    isinstance(n, ast.Assign) and any(getattr(t, "id", None) == "__all__" for t in n.targets)
    for n in tree.body
))


@pytest.mark.parametrize("module", MODULES_WITH_ALL)
def test_every_all_lists_real_names_and_every_public_definition(module: str) -> None:
    """Where a module has an `__all__`, it names only what exists and every public class,
    function or constant the module defines itself (so moving code cannot drop a name)."""
    mod = importlib.import_module(module)
    listed = list(mod.__all__)
    assert len(set(listed)) == len(listed), module
    missing = [n for n in listed if not hasattr(mod, n)]
    assert not missing, f"{module}.__all__ names what does not exist: {missing}"
    defined = {
        n
        for n, v in vars(mod).items()
        if not n.startswith("_")
        and getattr(v, "__module__", None) == module
        and (isinstance(v, type) or callable(v))
    }
    assert defined <= set(listed), f"{module} defines but does not export {defined - set(listed)}"


def _readme_layout() -> dict[str, set[str]]:
    """Package folder -> the .py files README.md's Layout block lists under it."""
    text = (PACKAGE.parent / "README.md").read_text()
    block = text.split("## Layout", 1)[1].split("```", 2)[1]
    listed: dict[str, set[str]] = defaultdict(set)
    stack: list[tuple[int, str]] = []
    for line in block.splitlines():
        if not line.strip():
            continue
        indent = len(line) - len(line.lstrip())
        head = line.strip().split("  ")[0]
        if head.endswith("/") and " " not in head:  # a folder line
            stack = [(i, f) for i, f in stack if i < indent]
            parent = stack[-1][1] if stack else ""
            stack.append((indent, head if head.startswith("mergesvc/") else parent + head))
            continue
        stack = [(i, f) for i, f in stack if i < indent]
        folder = stack[-1][1] if stack else ""
        for word in line.replace(",", " ").split():
            if word.endswith(".py"):
                listed[word.rsplit("/", 1)[0] + "/" if "/" in word else folder].add(
                    word.rsplit("/", 1)[-1]
                )
    return listed


def test_readme_layout_matches_the_tree() -> None:
    listed = _readme_layout()
    actual: dict[str, set[str]] = defaultdict(set)
    for p in PACKAGE.rglob("*.py"):
        if p.name in {"__init__.py", "__main__.py"}:
            continue
        actual[str(p.parent.relative_to(PACKAGE.parent)) + "/"].add(p.name)
    assert dict(listed) == dict(actual)
