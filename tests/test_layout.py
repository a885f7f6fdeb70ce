"""The package's layout is its architecture: which layer may import which, no import cycles, no
side effects in the core, and the public API at the package top (see mergesvc/__init__.py)."""

from __future__ import annotations

import ast
import importlib
from collections import defaultdict
from collections.abc import Iterable
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
    "store": {"store", "core", "errors"},
    "fleet": {"fleet", "store", "link", "wire", "sim", "core", "errors"},
    "bench": {"bench", "store", "link", "wire", "sim", "core", "errors"},
    "settings": {"settings", "fleet", "store", "link", "wire", "sim", "core", "errors"},
    "ros2": {"ros2", "fleet", "store", "link", "wire", "sim", "core", "errors"},
    "view": {"view", "fleet", "store", "link", "wire", "sim", "core", "errors"},
    "cli": {"cli", "settings", "ros2", "view", "fleet", "bench", "store", "link", "wire", "sim",
            "core", "errors", "api"},
    "api": {"core", "wire", "errors"},
}
# Third-party and stdlib modules that mean I/O beyond computation, forbidden in these layers.
SIDE_EFFECT_MODULES = {"zenoh", "socket", "sqlite3", "subprocess", "multiprocessing", "msgpack"}
PURE_LAYERS = {"core", "sim"}
# File access in core, with the reason it is still there (none: mergesvc/settings.py reads the
# settings file and the environment).
CORE_FILE_ACCESS: dict[str, str] = {}
# Calls that read or write files: methods of paths and file objects, and module functions.
FILE_METHODS = {"read_text", "read_bytes", "write_text", "write_bytes", "open", "mkdir", "unlink",
                "tofile"}
FILE_FUNCTIONS = {
    "np": {"load", "save", "savez", "savez_compressed", "loadtxt", "savetxt", "genfromtxt",
           "fromfile", "memmap"},
    "json": {"load", "dump"},
    "pickle": None,  # any use of pickle: it only exists to read and write bytes
}
FILE_FUNCTIONS["numpy"] = FILE_FUNCTIONS["np"]
FILE_MODULES = {"pickle", "shelve", "marshal"}

# Module-level rules beyond the layers: (importer, imported) -> why it may not. `imported`
# counts with everything under it (a package and its leaves), lazy imports included.
MODULE_RULES: dict[tuple[str, str], str] = {
    ("mergesvc.fleet.agent", "mergesvc.sim"): "a vehicle runs on its sensors' data; a simulated "
    "run or a recorded log is turned into frames by whoever starts it (the CLI, the demo)",
    ("mergesvc.store", "mergesvc.core.graph"): "the store persists records; the pose "
    "graph is the service's",
    ("mergesvc.core.config", "mergesvc.core.affinity"): "the config describes the stages; "
    "the stages import it, not the other way round",
}
# Rules still broken, with the reason and the plan; the lead removes an entry when its import
# is gone (test_temporary_allowances_are_still_needed says when).
TEMPORARY: dict[tuple[str, str], str] = {}


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


def _string_import(node: ast.Call) -> str | None:
    """The module `importlib.import_module("x")`, `import_module("x")` or `__import__("x")`
    names when it is a string literal (absolute), else None."""
    f = node.func
    named = (isinstance(f, ast.Attribute) and f.attr == "import_module") or (
        isinstance(f, ast.Name) and f.id in {"import_module", "__import__"})
    if not named or not node.args:
        return None
    arg = node.args[0]
    if isinstance(arg, ast.Constant) and isinstance(arg.value, str) and arg.value:
        return arg.value if not arg.value.startswith(".") else None
    return None


def _imports(module: str, tree: ast.Module) -> list[tuple[str, int]]:
    """Every module this one imports (at any depth: lazy imports count), as absolute names.

    `from pkg import name` counts as importing pkg.name when that is a module, else pkg.
    `importlib.import_module("pkg.mod")` and `__import__("pkg.mod")` with a string literal count
    as `import pkg.mod`."""
    out: list[tuple[str, int]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and (target := _string_import(node)) is not None:
            out.append((target, node.lineno))
        elif isinstance(node, ast.Import):
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


def _packages_run_first(importer: str, target: str, modules: Iterable[str]) -> list[str]:
    """The package `__init__`s Python runs before `target` when `importer` imports it: every
    package on the way down to the target (the target itself when it is a package), except
    those that hold the importer (already imported: the importer runs inside them)."""
    parts = target.split(".")
    chain = [".".join(parts[:i]) for i in range(1, len(parts))]
    return [p for p in chain if p in modules and not importer.startswith(p + ".")]


def _internal_edges(modules: dict[str, ast.Module] | None = None) -> dict[str, set[str]]:
    """Import graph between our modules. Importing a leaf runs its package `__init__` first, so
    an import of `pkg.leaf` is an edge to `pkg` as well (to every package on the way that does
    not hold the importer). Not an edge from the leaf to its own package: when a leaf is
    imported its package is already in sys.modules, and a package that imports its leaves (a
    facade) would otherwise look like a cycle with each of them."""
    modules = MODULES if modules is None else modules
    edges: dict[str, set[str]] = defaultdict(set)
    for module, tree in modules.items():
        for target, _ in _imports(module, tree):
            if target in modules and target != module:
                edges[module].add(target)
            for package in _packages_run_first(module, target, modules):
                if package != module:
                    edges[module].add(package)
    return edges


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
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

    for m in sorted(set(edges) | {t for ts in edges.values() for t in ts}):
        if m not in state:
            visit(m)
    return cycles


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
    cycles = _cycles(_internal_edges())
    assert not cycles, "\n".join(" -> ".join(c) for c in cycles)


def _fake_modules(sources: dict[str, str]) -> dict[str, ast.Module]:
    return {name: ast.parse(src) for name, src in sources.items()}


def test_the_cycle_check_sees_a_cycle_through_a_package_init() -> None:
    """`a.x` imports `b.y`; that runs `b/__init__`, which imports `a.x`: a cycle the flat
    graph (a.x -> b.y only) misses."""
    fake = _fake_modules({
        "mergesvc.a": "", "mergesvc.a.x": "from mergesvc.b.y import f\n",
        "mergesvc.b": "from mergesvc.a.x import g\n", "mergesvc.b.y": "",
    })
    assert "mergesvc.b" in _internal_edges(fake)["mergesvc.a.x"]
    assert _cycles(_internal_edges(fake))
    # a facade importing its own leaves, and leaves importing each other, is no cycle
    facade = _fake_modules({
        "mergesvc.b": "from mergesvc.b.y import f\nfrom mergesvc.b.z import h\n",
        "mergesvc.b.y": "from mergesvc.b.z import h\n", "mergesvc.b.z": "",
        "mergesvc.c": "from mergesvc.b import f\n",
        "mergesvc.c.w": "from mergesvc.b.z import h\n",
    })
    assert not _cycles(_internal_edges(facade))
    assert _packages_run_first("mergesvc.c.w", "mergesvc.b.z", facade) == ["mergesvc.b"]


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
    """Lines that read or write files: open(), path and file methods, numpy's and json's file
    functions (np.load, np.savez, json.dump, ...), pickle, and imports of file functions or
    modules (`from numpy import load`, `import pickle`)."""
    lines = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            f = node.func
            if isinstance(f, ast.Name) and f.id == "open":
                lines.append(node.lineno)
            elif isinstance(f, ast.Attribute):
                owner = f.value.id if isinstance(f.value, ast.Name) else ""
                banned = FILE_FUNCTIONS.get(owner, set())
                if f.attr in FILE_METHODS or banned is None or f.attr in banned:
                    lines.append(node.lineno)
        elif isinstance(node, ast.Import):
            if any(a.name.split(".")[0] in FILE_MODULES for a in node.names):
                lines.append(node.lineno)
        elif isinstance(node, ast.ImportFrom) and node.module:
            top = node.module.split(".")[0]
            names = FILE_FUNCTIONS.get(node.module) or set()
            if top in FILE_MODULES or any(a.name in names for a in node.names):
                lines.append(node.lineno)
    return sorted(set(lines))


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
    src = "\n".join([
        "import numpy as np", "import json", "import pickle",        # 1-3 (3: pickle)
        "a = np.load('a.npy')", "np.save('b', a)", "np.savez('c', a=a)",  # 4-6
        "np.loadtxt('d')", "np.savetxt('e', a)", "json.load(f)",      # 7-9
        "json.dump({}, f)", "pickle.dumps(a)", "a.tofile('g')",        # 10-12
        "from numpy import load", "json.loads('{}')", "np.asarray(a)",  # 13 (14, 15: no files)
        "json.dumps({})", "from json import dumps",                    # 16, 17: no files
    ])
    assert _file_access(ast.parse(src)) == [3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13]


def test_the_import_rules_catch_a_violation() -> None:
    """The checks above are only worth something if they can fail."""
    tree = ast.parse("from mergesvc.fleet.service import MergeService\nimport zenoh\n")
    targets = [t for t, _ in _imports("mergesvc.core.fake", tree)]
    assert "mergesvc.fleet.service" in targets
    assert _layer("mergesvc.fleet.service") not in ALLOWED["core"]
    assert "zenoh" in targets
    rel = ast.parse("from ..wire import codec\n")
    assert _imports("mergesvc.core.fake", rel)[0][0].startswith("mergesvc.wire")


def test_the_import_rules_see_imports_by_name() -> None:
    """importlib.import_module / __import__ with a literal name are imports like any other."""
    tree = ast.parse(
        "import importlib\n"
        "def f():\n"
        "    m = importlib.import_module('mergesvc.fleet.service')\n"
        "    return __import__('mergesvc.cli'), import_module('zenoh')\n"
        "importlib.import_module(name)\n"  # not a literal: cannot be checked, not counted
    )
    found = _imports("mergesvc.core.fake", tree)
    assert ("mergesvc.fleet.service", 3) in found and ("mergesvc.cli", 4) in found
    assert ("zenoh", 4) in found
    assert [t for t, _ in found] == ["importlib", "mergesvc.fleet.service", "mergesvc.cli", "zenoh"]


def _rule_violations(modules: dict[str, ast.Module]) -> dict[tuple[str, str], list[str]]:
    """MODULE_RULES broken in `modules`: rule -> "module:line imports target"."""
    out: dict[tuple[str, str], list[str]] = defaultdict(list)
    for (importer, banned), _why in MODULE_RULES.items():
        # the importer with everything under it (a package and its leaves)
        for name, tree in modules.items():
            if name != importer and not name.startswith(importer + "."):
                continue
            for target, line in _imports(name, tree):
                if target == banned or target.startswith(banned + "."):
                    out[importer, banned].append(f"{name}:{line} imports {target}")
    return dict(out)


def test_module_rules() -> None:
    """Rules between single modules the layers do not express (MODULE_RULES, with their
    reasons); TEMPORARY lists the ones still broken."""
    bad = {rule: where for rule, where in _rule_violations(MODULES).items()
           if rule not in TEMPORARY}
    assert not bad, "\n".join(f"{w} ({MODULE_RULES[r]})" for r, ws in bad.items() for w in ws)


def test_temporary_allowances_are_still_needed() -> None:
    """An allowance whose import is gone is removed (so the rule holds from then on)."""
    assert set(TEMPORARY) <= set(MODULE_RULES)
    broken = _rule_violations(MODULES)
    stale = [rule for rule in TEMPORARY if rule not in broken]
    assert not stale, f"remove from TEMPORARY (the rule holds now): {stale}"


def test_the_module_rules_catch_a_violation() -> None:
    fake = _fake_modules({
        "mergesvc.store.database": "def f():\n    from mergesvc.core.graph import PoseGraph\n",
        "mergesvc.core.config": "import importlib\n"
                                "importlib.import_module('mergesvc.core.affinity')\n",
        "mergesvc.fleet.agent": "from mergesvc.sim.logs import read_observation_log\n",
    })
    assert set(_rule_violations(fake)) == set(MODULE_RULES)
    clean = _fake_modules({"mergesvc.store.database": "from mergesvc.core.frames import "
                                                        "FrameId\n"})
    assert _rule_violations(clean) == {}


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


def _name_column(line: str) -> list[str]:
    """The file names a Layout line starts with (`a.py, b.py   description`): the leading
    words that are .py names, so a .py word inside the description does not count."""
    names = []
    for word in line.split():
        word = word.rstrip(",")
        if not word.endswith(".py"):
            break
        names.append(word)
    return names


def _readme_layout(text: str | None = None) -> dict[str, set[str]]:
    """Package folder -> the .py files README.md's Layout block lists under it (in its name
    column)."""
    text = (PACKAGE.parent / "README.md").read_text() if text is None else text
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
        for word in _name_column(line):
            listed[word.rsplit("/", 1)[0] + "/" if "/" in word else folder].add(
                word.rsplit("/", 1)[-1]
            )
    return listed


def test_the_readme_check_reads_only_the_name_column() -> None:
    text = "## Layout\n```\nmergesvc/x/   a folder\n  a.py, b.py  the a and b, unlike c.py\n" \
        "  d.py        d (see e.py)\nmergesvc/top.py   the top\n```\n"
    assert _readme_layout(text) == {"mergesvc/x/": {"a.py", "b.py", "d.py"},
                                    "mergesvc/": {"top.py"}}


def test_readme_layout_matches_the_tree() -> None:
    listed = _readme_layout()
    actual: dict[str, set[str]] = defaultdict(set)
    for p in PACKAGE.rglob("*.py"):
        if p.name in {"__init__.py", "__main__.py"}:
            continue
        actual[str(p.parent.relative_to(PACKAGE.parent)) + "/"].add(p.name)
    assert dict(listed) == dict(actual)
