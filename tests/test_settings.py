"""The settings tree (mergesvc/settings.py): every field of every section, changed through the
file, the environment and the flags' layer, arrives in the config object the command that
uses it passes on, with the precedence defaults <- file <- MERGESVC_* <- flags.

The fields are found by walking the pydantic models, so a field added to any section is tested
without touching this file; a non-default value is made from the field's type and constraints
(validated against the whole tree, so cross-field checks count), or taken from EXPLICIT where a
type gives no value by itself (maps keyed by link). Commands run in-process (typer's CliRunner)
with the object that receives the settings replaced by a stub that records what it was given:
`mergesvc match` -> core.pipeline.match, `serve` -> MergeService (and a real MergeService built
from what serve passed: its PoseGraph's config), `agent` -> fleet.agent.run_agent, `codec
encode` -> wire.encode_file, `link sim` -> link.sweep_link, `uncertainty train` ->
sim.uncertainty.fit, and each benchmark -> the bench function it calls (`bench match` ->
run_match_bench, `paper` -> run_paper_bench, `uncertainty` -> run_uncertainty_bench, `link` ->
run_link_bench with its `link` section too, `generalize` -> run_generalize).

The environment every test runs in has no MERGESVC_* variable (tests/conftest.py).
"""

from __future__ import annotations

import enum
import inspect
import json
import os
import signal
import subprocess
import sys
import types
import typing
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pydantic import BaseModel
from pydantic.fields import FieldInfo
from typer.testing import CliRunner

import mergesvc.bench
import mergesvc.core.pipeline
import mergesvc.fleet.agent
import mergesvc.fleet.demo
import mergesvc.fleet.replay  # binds the real MergeService before any test patches it
import mergesvc.fleet.service
import mergesvc.link
import mergesvc.sim
import mergesvc.sim.uncertainty
import mergesvc.wire
from mergesvc.bench.match import _modes
from mergesvc.bench.scoring import _config
from mergesvc.cli import app
from mergesvc.core.config import MatchConfig, match_config
from mergesvc.errors import ConfigError
from mergesvc.fleet.agent import AgentConfig
from mergesvc.fleet.config import ServiceConfig
from mergesvc.fleet.service import MergeService
from mergesvc.link import LinkConfig, Workload
from mergesvc.settings import (
    SECTIONS,
    SETTINGS_ENV,
    AgentSettings,
    Settings,
    SettingsError,
    _model_of,
    env_overrides,
    load_settings,
    read_settings_file,
)
from mergesvc.sim.uncertainty import UncertaintyConfig
from mergesvc.wire import CodecSettings

runner = CliRunner()

# ------------------------------------------------------------------ walking the tree

Path_ = tuple[str, ...]


def _leaves(model: type[BaseModel], prefix: Path_ = ()) -> Iterator[tuple[Path_, FieldInfo]]:
    for name, info in model.model_fields.items():
        sub = _model_of(info.annotation)
        if sub is None:
            yield (*prefix, name), info
        else:
            yield from _leaves(sub, (*prefix, name))


def _get(obj: Any, path: Path_) -> Any:
    for part in path:
        obj = obj[part] if isinstance(obj, dict) else getattr(obj, part)
    return obj


def _nest(path: Path_, value: Any) -> dict[str, Any]:
    for part in reversed(path):
        value = {part: value}
    return value


def _jsonable(value: Any) -> Any:
    if isinstance(value, BaseModel):
        return value.model_dump(mode="json")
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, (tuple, list)):
        return [_jsonable(v) for v in value]
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    return value


def _contains(got: Any, want: Any) -> bool:
    """`got` holds `want` (for maps: every key of want, recursively; else equal as JSON)."""
    got, want = _jsonable(got), _jsonable(want)
    if isinstance(want, dict):
        return isinstance(got, dict) and all(
            k in got and _contains(got[k], v) for k, v in want.items())
    return got == want


def _candidates(annotation: Any, default: Any) -> list[Any]:
    """Values of this type other than `default`, from the type alone (constraints are checked
    by validating the tree, which drops the candidates they refuse)."""
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin in (typing.Union, types.UnionType):
        out = [c for a in args if a is not type(None) for c in _candidates(a, default)]
        return out + ([None] if type(None) in args and default is not None else [])
    if annotation is bool:
        return [not default]
    if isinstance(annotation, type) and issubclass(annotation, enum.Enum):
        return [m.value for m in annotation if m != default]
    if origin is typing.Literal:
        return [a for a in args if a != default]
    if annotation is int:
        d = default if isinstance(default, int) else 1
        return [d + 1, d - 1, 2 * d, d + 10]
    if annotation is float:
        d = default if isinstance(default, (int, float)) else 1.0
        return [d * 1.5, d * 0.5, d + 0.5, d - 0.5, 0.5, 0.25, 0.1] if d else [0.5, 0.1, 1.0]
    if annotation is str:
        return [f"{default or ''}x", "x"]
    if origin is tuple and isinstance(default, tuple) and default:
        elem = (lambda i: args[0]) if args[-1] is Ellipsis else (lambda i: args[i])
        firsts = [_candidates(elem(i), d)[:1] for i, d in enumerate(default)]
        if all(firsts):
            return [tuple(f[0] for f in firsts)]
        return []
    if origin is list and isinstance(default, list) and default:
        return [list(reversed(default)), default[:-1], [*default, f"{default[-1]}x"]]
    return []


# Fields whose type gives no value by itself: path -> a valid non-default value.
EXPLICIT: dict[Path_, Any] = {
    ("link", "channel", "link_snr"): {"topside->v1": {"mean_db": 3.0, "spread_db": 1.0}},
    ("link", "channel", "link_range_m"): {"topside->v2": 500.0},
    ("agent", "up"): (0.0, -1.0, 0.0),
    ("service", "embedding_dims"): [384, 768],
    ("service", "odometry_bounds"): {"car1": [0.01, 0.01, 0.01, 2.0, 3.0, 2.0]},
}

DEFAULTS = Settings()
DEFAULT_DUMP = DEFAULTS.model_dump(mode="json")


def _valid_change(path: Path_, value: Any) -> bool:
    try:
        got = Settings().merged(_nest(path, value))
    except ConfigError:
        return False
    return not _contains(_get(DEFAULTS, path), _get(got, path)) and _contains(
        _get(got, path), value)


def _changed_value(path: Path_, info: FieldInfo) -> Any:
    if path in EXPLICIT:
        return EXPLICIT[path]
    for value in _candidates(info.annotation, _get(DEFAULTS, path)):
        if _valid_change(path, value):
            return value
    raise AssertionError(f"no non-default value for {'.'.join(path)}: add it to EXPLICIT")


LEAVES = [(path, _changed_value(path, info)) for path, info in _leaves(Settings)]
IDS = [".".join(p) for p, _ in LEAVES]


def _env_name(path: Path_) -> str:
    return "MERGESVC_" + "__".join(path).upper()


def _env_value(value: Any) -> str:
    return value if isinstance(value, str) else json.dumps(_jsonable(value))


def test_the_walk_finds_every_section_and_the_nested_models() -> None:
    paths = {p for p, _ in LEAVES}
    assert {p[0] for p in paths} == set(SECTIONS)
    for must in [("match", "candidates", "top_k"), ("service", "match", "verify", "min_matches"),
                 ("service", "graph", "inlier_probability"), ("agent", "tracking", "cos_min"),
                 ("link", "channel", "snr", "mean_db"), ("uncertainty", "hidden_sizes"),
                 ("codec", "embedding_bits"), ("workload", "period_s")]:
        assert must in paths, must
    assert len(paths) > 120


def test_the_sections_are_the_layers_own_models() -> None:
    """Nested as they are: a field added to one of them is in the tree."""
    fields = Settings.model_fields
    assert fields["match"].annotation is MatchConfig
    assert fields["service"].annotation is ServiceConfig
    assert fields["codec"].annotation is CodecSettings
    assert fields["link"].annotation is LinkConfig
    assert fields["workload"].annotation is Workload
    assert fields["uncertainty"].annotation is UncertaintyConfig
    assert set(AgentSettings.model_fields) == set(AgentConfig.model_fields) - {"robot"}
    # the service keeps its own matching defaults inside the tree
    assert DEFAULTS.service == ServiceConfig()
    assert DEFAULTS.service.match.verify.min_matches == 4
    assert DEFAULTS.agent_config("auv1") == AgentConfig(robot="auv1")


# ------------------------------------------------------------------ every field, every source


@pytest.mark.parametrize(("path", "value"), LEAVES, ids=IDS)
def test_each_field_through_file_env_and_flags_with_precedence(
    path: Path_, value: Any, tmp_path: Path
) -> None:
    default = _jsonable(_get(DEFAULT_DUMP, path))
    f = tmp_path / "settings.json"
    f.write_text(json.dumps(_nest(path, _jsonable(value))))
    name = _env_name(path)

    def got(s: Settings) -> Any:
        return _get(s, path)

    # each source alone
    assert _contains(got(load_settings(f, environ={})), value)
    assert _contains(got(load_settings(environ={name: _env_value(value)})), value)
    assert _contains(got(load_settings(environ={}, overrides=_nest(path, value))), value)
    assert _contains(got(load_settings(environ={SETTINGS_ENV: str(f)})), value)
    # precedence: the environment beats the file, the flags beat both
    assert _contains(got(load_settings(f, environ={name: _env_value(default)})), default)
    assert _contains(got(load_settings(environ={name: _env_value(value)},
                                       overrides=_nest(path, default))), default)
    assert _contains(got(load_settings(f, environ={}, overrides=_nest(path, default))), default)
    # --settings beats $MERGESVC_SETTINGS
    empty = tmp_path / "empty.json"
    empty.write_text("{}")
    assert _contains(got(load_settings(empty, environ={SETTINGS_ENV: str(f)})), default)
    # nothing else moved
    out = load_settings(f, environ={}).model_dump(mode="json")
    assert [p for p, _ in LEAVES if _get(out, p) != _get(DEFAULT_DUMP, p)] == [path]


# ------------------------------------------------------------------ the objects that use them


class Reached(Exception):  # noqa: N818 - not an error: the stub's report
    """Raised by a stub in place of the object that receives the settings."""

    def __init__(self, got: Any) -> None:
        super().__init__("reached")
        self.got = got


def _reach(got: Any) -> None:
    raise Reached(got)


@contextmanager
def _nothing(*_a: Any, **_k: Any) -> Iterator[None]:
    yield None


@pytest.fixture(scope="module")
def pair(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    from mergesvc.sim import Family, make_scenario

    out = tmp_path_factory.mktemp("pair")
    sc = make_scenario(Family.UNDERWATER, 4, n_map=12, n_sub=4, n_outliers=0)
    (out / "map.json").write_text(sc.map.model_dump_json())
    (out / "sub.json").write_text(sc.submap.model_dump_json())
    return out / "map.json", out / "sub.json"


def _invoke(args: list[str], env: dict[str, str] | None = None) -> Any:
    result = runner.invoke(app, args, env=env)
    if isinstance(result.exception, Reached):
        return result.exception.got
    raise AssertionError(f"exit {result.exit_code}: {result.output}\n{result.exception!r}")


def via_match(monkeypatch, tmp, pair, settings: list[str]) -> MatchConfig:
    monkeypatch.setattr(mergesvc.core.pipeline, "match", lambda m, s, cfg: _reach(cfg))
    return _invoke(["match", "--map", str(pair[0]), "--submap", str(pair[1]), *settings])


def via_bench(monkeypatch, tmp, pair, settings: list[str]) -> MatchConfig:
    monkeypatch.setattr(mergesvc.bench, "run_match_bench", lambda **kw: _reach(kw["base"]))
    return _invoke(["bench", "match", "--no-paper", *settings])


def via_bench_paper(monkeypatch, tmp, pair, settings: list[str]) -> MatchConfig:
    monkeypatch.setattr(mergesvc.bench, "run_paper_bench", lambda *a, **kw: _reach(kw["base"]))
    return _invoke(["bench", "paper", "--quick", "--out", str(tmp / "paper"), *settings])


def via_bench_uncertainty(monkeypatch, tmp, pair, settings: list[str]) -> MatchConfig:
    monkeypatch.setattr(mergesvc.bench, "run_uncertainty_bench",
                        lambda *a, **kw: _reach(kw["base"]))
    return _invoke(["bench", "uncertainty", "--out", str(tmp / "unc"), *settings])


def via_bench_link(monkeypatch, tmp, pair, settings: list[str]) -> tuple[MatchConfig, LinkConfig]:
    monkeypatch.setattr(mergesvc.bench, "run_link_bench",
                        lambda **kw: _reach((kw["base"], kw["link_config"])))
    return _invoke(["bench", "link", *settings])


def via_bench_generalize(monkeypatch, tmp, pair, settings: list[str]) -> MatchConfig:
    monkeypatch.setattr(mergesvc.bench, "run_generalize", lambda *a, **kw: _reach(kw["base"]))
    return _invoke(["bench", "generalize", "--quick", *settings])


def via_bench_scale(monkeypatch, tmp, pair, settings: list[str]) -> MatchConfig:
    import mergesvc.bench.scale

    monkeypatch.setattr(mergesvc.bench.scale, "run_scale",
                        lambda plan, **kw: _reach(MatchConfig.model_validate(plan.config)))
    return _invoke(["bench", "scale", "--quick", *settings])


def via_bench_merge(monkeypatch, tmp, pair, settings: list[str]) -> tuple[Any, LinkConfig]:
    monkeypatch.setattr(mergesvc.bench, "run_merge_bench",
                        lambda *a, **kw: _reach((kw["service"], kw["link_config"])))
    return _invoke(["bench", "merge", "--quick", *settings])


def via_bench_soak(monkeypatch, tmp, pair, settings: list[str]) -> ServiceConfig:
    """The service settings the soak's `serve` subprocess resolves: its --settings file (what
    the soak passes on) and the environment it inherits."""
    from mergesvc.cli.options import SettingsCommand, bare_match_for

    def fake(plan, serve_command=None, serve_args=(), **_kw):
        args = list(serve_args)
        path = args[args.index("--settings") + 1] if "--settings" in args else None
        _reach(load_settings(path, environ=dict(os.environ),
                             bare_match=bare_match_for(SettingsCommand.SERVE)).service)

    monkeypatch.setattr(mergesvc.bench, "run_soak", fake)
    return _invoke(["bench", "soak", "--quick", *settings])


def via_bench_cost(monkeypatch, tmp, pair, settings: list[str]) -> ServiceConfig:
    """The service settings `bench cost` builds its in-process services with."""
    import mergesvc.bench.cost

    def fake(make_service, vehicle, plan, **_kw):
        make_service(str(tmp / "cost.db"))

    monkeypatch.setattr(mergesvc.fleet.service, "MergeService",
                        lambda cfg, *_a, **_k: _reach(cfg))
    monkeypatch.setattr(mergesvc.bench.cost, "run_cost_bench", fake)
    return _invoke(["bench", "cost", "--quick", *settings])


def via_serve(monkeypatch, tmp, pair, settings: list[str]) -> ServiceConfig:
    import zenoh

    monkeypatch.setattr(zenoh, "open", _nothing)
    monkeypatch.setattr(signal, "signal", lambda *_a: None)
    monkeypatch.setattr(mergesvc.fleet.service, "MergeService", lambda cfg, *_a: _reach(cfg))
    monkeypatch.chdir(tmp)  # the default store (and its lock) of each case its own
    return _invoke(["serve", "--seconds", "0", *settings])


def via_agent(monkeypatch, tmp, pair, settings: list[str]) -> Any:
    monkeypatch.setattr(signal, "signal", lambda *_a: None)
    monkeypatch.setattr(mergesvc.fleet.agent, "run_agent", lambda run, *_a: _reach(run))
    return _invoke(["agent", "--robot", "auv1", *settings])


def via_codec(monkeypatch, tmp, pair, settings: list[str]) -> CodecSettings:
    monkeypatch.setattr(mergesvc.wire, "encode_file", lambda *a, **kw: _reach(kw["settings"]))
    return _invoke(["codec", "encode", str(pair[1]), str(tmp / "out.bin"), *settings])


def via_link_sim(monkeypatch, tmp, pair, settings: list[str]) -> tuple[LinkConfig, Workload]:
    monkeypatch.setattr(mergesvc.link, "sweep_link", lambda rates, snrs, *, workload,
                        base_config, seed: _reach((base_config, workload)))
    return _invoke(["link", "sim", "--rate", "1", "--snr-db", "0", *settings])


def via_uncertainty(monkeypatch, tmp, pair, settings: list[str]) -> UncertaintyConfig:
    monkeypatch.setattr(mergesvc.sim, "image_s_dataset",
                        lambda n, *_a: (np.zeros((n, 4)), np.zeros(n), np.zeros(n)))
    monkeypatch.setattr(mergesvc.sim.uncertainty, "fit", lambda y, loss, cfg, *a, **k: _reach(cfg))
    return _invoke(["uncertainty", "train", str(tmp / "head.npz"), "--samples", "100",
                    *settings])


# section -> (how to run the command, the part of the tree the object it reached holds)
Consumer = Callable[..., Any]
CONSUMERS: dict[str, list[tuple[Consumer, Callable[[Any], Any]]]] = {
    "match": [
        (via_match, lambda got: got),
        (via_bench, lambda got: got),
        (via_bench_paper, lambda got: got),
        (via_bench_uncertainty, lambda got: got),
        (via_bench_link, lambda got: got[0]),
        (via_bench_generalize, lambda got: got),
        (via_bench_scale, lambda got: got),
    ],
    "service": [(via_serve, lambda got: got), (via_bench_merge, lambda got: got[0]),
                (via_bench_soak, lambda got: got), (via_bench_cost, lambda got: got)],
    "agent": [],  # see test_each_agent_field_reaches_the_vehicle_or_is_refused
    "codec": [(via_codec, lambda got: got)],
    "link": [(via_link_sim, lambda got: got[0]), (via_bench_link, lambda got: got[1]),
             (via_bench_merge, lambda got: got[1])],
    "workload": [(via_link_sim, lambda got: got[1])],
    "uncertainty": [(via_uncertainty, lambda got: got)],
}
BENCH_COMMANDS = {"match", "paper", "uncertainty", "link", "generalize", "merge", "soak", "cost",
                  "fuzz", "scale", "qaplib"}
# fields a command sets itself, whatever the settings say
SET_BY_THE_COMMAND = {"via_bench_cost": {("service", "store")}}  # a fresh store per run
# the decoders at their built-in limits (what a service without a settings file refuses); the
# exact solver on QAPLIB with its own arguments (no setting reaches it)
SETTINGS_FREE = {"fuzz", "qaplib"}


def test_every_section_has_a_consumer_here() -> None:
    assert set(CONSUMERS) == set(SECTIONS)


def test_every_benchmark_is_a_consumer_here() -> None:
    """Each `bench` command but the fuzzer and QAPLIB's reads --settings, so each is checked
    above."""
    from mergesvc.cli import bench

    commands = {c.name for c in bench.app.registered_commands}
    assert commands == BENCH_COMMANDS
    consumers = {run.__name__ for runs in CONSUMERS.values() for run, _ in runs}
    assert {"via_bench" if c == "match" else f"via_bench_{c}"
            for c in commands - SETTINGS_FREE} <= consumers


@pytest.mark.parametrize(("path", "value"), LEAVES, ids=IDS)
def test_each_field_arrives_where_the_command_passes_it(
    path: Path_, value: Any, tmp_path: Path, pair: tuple[Path, Path],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    f = tmp_path / "settings.json"
    f.write_text(json.dumps(_nest(path, _jsonable(value))))
    for run, part in CONSUMERS[path[0]]:
        if path in SET_BY_THE_COMMAND.get(run.__name__, ()):
            continue
        got = part(run(monkeypatch, tmp_path, pair, ["--settings", str(f)]))
        assert _contains(_get(got, path[1:]), value), (run.__name__, got)
        # and through the environment, the way a deployment sets it
        monkeypatch.setenv(_env_name(path), _env_value(value))
        got = part(run(monkeypatch, tmp_path, pair, []))
        monkeypatch.delenv(_env_name(path))
        assert _contains(_get(got, path[1:]), value), (run.__name__, "env", got)
    if path[0] == "service":
        # the real service built from what serve passed: its config, its pose graph's config
        cfg = via_serve(monkeypatch, tmp_path, pair, ["--settings", str(f)])
        if path != ("service", "store"):
            cfg = cfg.model_copy(update={"store": ":memory:"})
        else:
            monkeypatch.chdir(tmp_path)  # the store file is made here
        svc = MergeService(cfg, session=None)
        try:
            assert _contains(_get(svc.config, path[1:]), value)
            if path[1] == "graph":
                assert _contains(_get(svc.graph.config, path[2:]), value)
        finally:
            svc.close()


AGENT_LEAVES = [(p, v) for p, v in LEAVES if p[0] == "agent"]


@pytest.mark.parametrize(("path", "value"), AGENT_LEAVES,
                         ids=[".".join(p) for p, _ in AGENT_LEAVES])
def test_each_agent_field_reaches_the_vehicle(
    path: Path_, value: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The tree gives the vehicle's AgentConfig every field, and `mergesvc agent` hands that
    AgentConfig to fleet.agent.run_agent, which builds the vehicle with it."""
    f = tmp_path / "settings.json"
    f.write_text(json.dumps(_nest(path, _jsonable(value))))
    tree = load_settings(f, environ={})
    assert _contains(_get(tree.agent_config("auv1"), path[1:]), value)
    assert tree.agent_config("auv1").robot == "auv1"
    run = via_agent(monkeypatch, tmp_path, None, ["--settings", str(f)])
    assert run.config is not None and run.config.robot == "auv1"
    assert _contains(_get(run.config, path[1:]), value)
    if path[1] in ("session", "fleet"):
        assert getattr(run, path[1]) == value


def test_run_agent_refuses_settings_for_another_vehicle() -> None:
    from mergesvc.fleet.agent import AgentConfig, AgentRun, run_agent

    run = AgentRun(robot="auv1", config=AgentConfig(robot="auv2"))
    with pytest.raises(ConfigError, match="auv2"):
        run_agent(run, None, [])


# ------------------------------------------------------------------ flags


@pytest.mark.parametrize(
    ("run", "flag", "path", "values"),
    [
        (via_match, "--mode", ("match", "mode"), ("paper", "paper", "verified")),
        (via_match, "--solver", ("match", "solver", "name"), ("sm", "ipfp", "exact")),
        (via_match, "--affinity", ("match", "affinity", "kind"),
         ("mahalanobis", "bhattacharyya", "likelihood_ratio")),
        (via_serve, "--fleet", ("service", "fleet"), ("ff", "fe", "fflag")),
        (via_serve, "--store", ("service", "store"), ("a.db", "b.db", "c.db")),
        (via_agent, "--fleet", ("agent", "fleet"), ("ff", "fe", "fflag")),
        (via_agent, "--session", ("agent", "session"), ("s1", "s2", "s3")),
        (via_link_sim, "--bytes-per-submap", ("workload", "uplink_bytes"), (100, 200, 300)),
        (via_link_sim, "--period-s", ("workload", "period_s"), (10.0, 20.0, 30.0)),
        (via_link_sim, "--duration-s", ("workload", "duration_s"), (100.0, 200.0, 300.0)),
    ],
)
def test_a_flag_beats_the_environment_beats_the_file(
    run: Consumer, flag: str, path: Path_, values: tuple[Any, Any, Any], tmp_path: Path,
    pair: tuple[Path, Path], monkeypatch: pytest.MonkeyPatch,
) -> None:
    file_v, env_v, flag_v = values
    f = tmp_path / "settings.json"
    f.write_text(json.dumps(_nest(path, file_v)))

    def value(got: Any) -> Any:
        if run is via_link_sim:
            got = got[1]
        elif run is via_agent:
            return getattr(got, path[-1])
        return _jsonable(_get(got, path[1:]))

    args = ["--settings", str(f)]
    assert value(run(monkeypatch, tmp_path, pair, args)) == file_v
    monkeypatch.setenv(_env_name(path), str(env_v))
    assert value(run(monkeypatch, tmp_path, pair, args)) == env_v
    assert value(run(monkeypatch, tmp_path, pair, [*args, flag, str(flag_v)])) == flag_v
    # a flag left at its default does not override (its default is the setting's default)
    monkeypatch.delenv(_env_name(path))
    assert value(run(monkeypatch, tmp_path, pair, [*args])) == file_v


def test_a_bad_flag_value_is_bad_input_as_before(monkeypatch: pytest.MonkeyPatch) -> None:
    import zenoh

    monkeypatch.setattr(zenoh, "open", _nothing)
    monkeypatch.setattr(signal, "signal", lambda *_a: None)
    r = runner.invoke(app, ["serve", "--fleet", "", "--seconds", "0"])
    assert r.exit_code == 2 and "fleet" in r.output
    r = runner.invoke(app, ["agent", "--robot", ""])
    assert r.exit_code == 2 and "robot" in r.output


@pytest.mark.parametrize(("args", "message"), [
    (["agent", "--robot", "auv/1"], "invalid robot 'auv/1': may not contain '/' (set by --robot)"),
    (["agent", "--robot", "a", "--session", "s//1"], "empty key chunk (set by --session)"),
    (["agent", "--robot", "a", "--fleet", "f*"], "Invalid value for '--fleet': invalid fleet"),
    (["serve", "--fleet", "a b", "--store", ":memory:"], "invalid fleet 'a b'"),
    (["view", "--fleet", "a b", "--duration", "1"], "invalid fleet 'a b'"),
    (["link", "bridge", "--fleet", "a/b", "--seconds", "1"], "invalid fleet 'a/b'"),
    (["link", "bridge", "--vehicles", "auv1", "--vehicles", "a*"], "invalid robot 'a*'"),
    (["link", "sim", "--bytes-per-submap", "999999999"],
     "workload.uplink_bytes: Input should be less than or equal to 65536 (set on the command "
     "line)"),
    (["serve", "--seconds", "-1", "--store", ":memory:"], "--seconds"),
    (["agent", "--robot", "a", "--linger", "-1"], "--linger"),
])
def test_a_name_no_key_can_hold_is_refused_before_connecting(
    monkeypatch: pytest.MonkeyPatch, args: list[str], message: str
) -> None:
    """One rule for robot, session and fleet names (the keys'), applied to the settings: a
    vehicle named 'auv/1' is told so at once (exit 2), not after it connects."""
    import zenoh

    monkeypatch.setattr(zenoh, "open", _nothing)  # connecting would fail the test
    r = runner.invoke(app, args)
    assert r.exit_code == 2, r.output
    assert message in r.output and len(r.output.strip().splitlines()) == 1, r.output


def test_names_are_checked_as_keys_check_them() -> None:
    from mergesvc.wire.keys import KeyNameError, check_name, submap_key

    for robot in ("auv/1", "a*", "", "x?y"):
        with pytest.raises(ValueError, match="robot"):
            AgentConfig(robot=robot)
        with pytest.raises(KeyNameError):
            submap_key("mergesvc/v1/f", robot, "s0")
    for fleet in ("a b", "a/b", "", "x" * 65):
        with pytest.raises(ValueError, match="fleet"):
            ServiceConfig(fleet=fleet)
        with pytest.raises(ValueError, match="fleet"):
            AgentSettings(fleet=fleet)
        with pytest.raises(KeyNameError):
            check_name("fleet", fleet)
    from mergesvc.fleet.agent import AgentRun, run_agent

    with pytest.raises(ConfigError, match="invalid agent settings: robot: invalid robot 'a/b'"):
        run_agent(AgentRun(robot="a/b"), None, [])  # before any session opens
    # what the keys take, the settings take: a key that worked before still works
    assert AgentConfig(robot="auv 1", session="day1/dive2").session == "day1/dive2"
    with pytest.raises(ValueError, match="up must be"):  # every check of AgentConfig's
        AgentSettings(up=(0.0, 0.0, 0.0))
    assert submap_key("mergesvc/v1/f", "auv 1", "day1/dive2").endswith("auv 1/day1/dive2")


# ------------------------------------------------------------------ the file


def test_a_bare_match_config_file_is_the_match_section(tmp_path: Path) -> None:
    f = tmp_path / "m.json"
    f.write_text(json.dumps({"mode": "paper", "candidates": {"top_k": 5}}))
    s = load_settings(f, environ={})
    assert s.match == match_config(mode="paper", candidates={"top_k": 5})
    assert s.service == ServiceConfig()
    # for serve, as `serve --settings` always read it: a whole MatchConfig for the service
    s = load_settings(f, environ={}, bare_match=("service", "match"))
    assert s.service.match == match_config(mode="paper", candidates={"top_k": 5})
    assert s.match == MatchConfig()


def test_a_bare_uncertainty_config_file_is_the_uncertainty_section(tmp_path: Path) -> None:
    f = tmp_path / "u.json"
    f.write_text(json.dumps({"hidden_sizes": [32], "epochs": 8}))
    s = load_settings(f, environ={})
    assert s.uncertainty == UncertaintyConfig(hidden_sizes=(32,), epochs=8)


def test_bare_keys_never_name_a_section() -> None:
    assert not set(MatchConfig.model_fields) & set(SECTIONS)
    assert not set(UncertaintyConfig.model_fields) & set(SECTIONS)
    assert not set(MatchConfig.model_fields) & set(UncertaintyConfig.model_fields)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ('{"match": {}, "mode": "paper"}', "unknown section(s) mode"),
        ('{"matching": {}}', "unknown section(s) matching"),
        ('{"service": {"fleeet": "x"}}', "service.fleeet: Extra inputs are not permitted "
         "(did you mean fleet"),
        ('{"match": {"candidates": {"topk": 3}}}', "match.candidates.topk: .* (did you mean "
         "top_k"),
        ('{"service": {"zzz": 1}}', "service.zzz: .* (no such setting)"),
        # a bare MatchConfig: refused as the tree would refuse it, where it goes
        ('{"candidates": {"top_k": 0}}', "invalid settings: match.candidates.top_k: .* "
         "(set by settings file"),
        ('{"verify": {"min_matchs": 4}}', "invalid settings: match.verify.min_matchs: .* (did "
         "you mean min_matches"),
        ('{"match": {"candidates": {"top_k": 0}}}', "invalid settings: match.candidates.top_k"),
        ("[]", "must hold a JSON object"),
        ("{nope", "cannot read settings file"),
    ],
)
def test_a_bad_file_is_a_config_error(tmp_path: Path, content: str, message: str) -> None:
    f = tmp_path / "bad.json"
    f.write_text(content)
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        load_settings(f, environ={})
    with pytest.raises(ConfigError, match="cannot read settings file"):
        read_settings_file(tmp_path / "absent.json")


# ------------------------------------------------------------------ the environment


def test_the_short_form_is_the_match_section() -> None:
    for name in MatchConfig.model_fields:
        path = ("match", name)
        leaf = next(v for p, v in LEAVES if p[:2] == path)
        leaf_path = next(p for p, v in LEAVES if p[:2] == path)
        short = _env_name(leaf_path[1:])
        s = load_settings(environ={short: _env_value(leaf)})
        assert _contains(_get(s, leaf_path), leaf)
        assert s.service == ServiceConfig()  # the short form is `match` only
    assert load_settings(environ={"MERGESVC_CANDIDATES__TOP_K": "16"}).match.candidates.top_k == 16


@pytest.mark.parametrize(
    ("environ", "message"),
    [
        ({"MERGESVC_SERVICE__FOO": "1"}, "MERGESVC_SERVICE__FOO: service has no 'foo'"),
        ({"MERGESVC_SERVICE__MATCH__VERIFYY__X": "1"}, "service.match has no 'verifyy'"),
        ({"MERGESVC_MATCH__SOLVER__NAME__X": "1"}, "match.solver.name is a value"),
        ({"MERGESVC_CANDIDATES__TOPK": "1"}, "match.candidates has no 'topk'"),
        ({"MERGESVC_CANDIDATES__TOP_K": "3", "MERGESVC_MATCH__CANDIDATES__TOP_K": "4"},
         "both set match.candidates.top_k"),
        ({"MERGESVC_MATCH__SOLVER__NAME": "nope"}, "invalid settings: match.solver.name"),
    ],
)
def test_an_unknown_or_bad_variable_is_a_config_error(
    environ: dict[str, str], message: str
) -> None:
    with pytest.raises(ConfigError, match=message):
        load_settings(environ=environ)


def test_a_refused_value_names_where_it_was_set(tmp_path: Path) -> None:
    """The file, the variable (a field's or a whole section's) or the flag: the one whose value
    stood. A flag that replaces a file's bad value is no error."""
    f = tmp_path / "s.json"
    f.write_text(json.dumps({"service": {"fleet": "x y"}}))
    with pytest.raises(ConfigError, match=rf"fleet 'x y'.* \(set by settings file {f}\)$"):
        load_settings(f, environ={})
    for name, value in (("MERGESVC_SERVICE__FLEET", "a b"),
                        ("MERGESVC_SERVICE", '{"fleet": "a b"}')):
        with pytest.raises(ConfigError, match=rf"fleet 'a b'.* \(set by {name}\)$"):
            load_settings(f, environ={name: value})
    with pytest.raises(ConfigError, match=r"top_k: .* \(set by MERGESVC_CANDIDATES__TOP_K\)$"):
        load_settings(environ={"MERGESVC_CANDIDATES__TOP_K": "0"})
    with pytest.raises(SettingsError, match=r"fleet 'q r'.* \(set on the command line\)$") as err:
        load_settings(f, environ={}, overrides={"service": {"fleet": "q r"}})
    assert err.value.from_flag and err.value.loc == ("service", "fleet")  # the CLI names it
    # a whole section refused: its setter named when one layer set values in it, else none
    u = tmp_path / "u.json"
    u.write_text(json.dumps({"uncertainty": {"output_range": [2, 1]}}))
    with pytest.raises(ConfigError, match=rf"output_range .* \(set by settings file {u}\)$"):
        load_settings(u, environ={})
    with pytest.raises(ConfigError, match=r"output_range must satisfy [^(]*$"):
        load_settings(u, environ={"MERGESVC_UNCERTAINTY__PATIENCE": "3"})
    fixed = load_settings(f, environ={}, overrides={"service": {"fleet": "qr"}})
    assert fixed.service.fleet == "qr"
    with pytest.raises(SettingsError) as err:
        load_settings(f, environ={"MERGESVC_SERVICE__FLEET": "a b"})
    assert not err.value.from_flag


def test_other_variables_are_not_settings() -> None:
    assert env_overrides({"HOME": "/x", "mergesvc_lower": "1", SETTINGS_ENV: "f"}) == {}


@pytest.fixture
def fresh_warnings(monkeypatch: pytest.MonkeyPatch) -> None:
    """No variable warned about yet in this process (the loader warns once per name)."""
    monkeypatch.setattr(mergesvc.settings, "_WARNED", set())


def test_a_variable_that_names_no_section_is_ignored_with_one_warning(
    fresh_warnings: None, caplog: pytest.LogCaptureFixture
) -> None:
    """MERGESVC_HOME (another tool's variable) is no setting: ignored, warned about once."""
    environ = {"MERGESVC_HOME": "/x", "MERGESVC_FOO__BAR": "1", "MERGESVC_CANDIDATES__TOP_K": "5"}
    with caplog.at_level("WARNING", logger="mergesvc.settings"):
        s = load_settings(environ=environ)
        assert load_settings(environ=environ) == s  # the second load warns no more
    assert s.match.candidates.top_k == 5  # the settings beside them still count
    assert s.model_dump() == Settings().merged(
        {"match": {"candidates": {"top_k": 5}}}).model_dump()
    warnings = [r for r in caplog.records if r.name == "mergesvc.settings"]
    assert len(warnings) == 1 and warnings[0].levelname == "WARNING"
    text = warnings[0].getMessage()
    assert "MERGESVC_HOME" in text and "MERGESVC_FOO__BAR" in text and "\n" not in text
    assert "MERGESVC_CANDIDATES__TOP_K" not in text


def test_an_unknown_field_under_a_section_is_still_an_error(fresh_warnings: None) -> None:
    """Typo protection: the section (or the short form) is known, the field is not."""
    for name in ("MERGESVC_MATCH__CANDIDATES__TOPK", "MERGESVC_CANDIDATES__TOPK",
                 "MERGESVC_LINK__CHANEL", "MERGESVC_AGENT__ROBOT"):
        with pytest.raises(ConfigError, match=f"unknown setting {name}"):
            load_settings(environ={name: "1"})


def test_a_foreign_variable_breaks_no_command(pair: tuple[Path, Path]) -> None:
    """`MERGESVC_HOME=/x mergesvc ...` runs, with one warning line on stderr; a typo under a
    section is still exit 1."""
    env = {"MERGESVC_HOME": "/x"}
    r = subprocess.run([sys.executable, "-m", "mergesvc.cli", "link", "sim", "--rate", "5",
                        "--snr-db", "10", "--duration-s", "120"],
                       capture_output=True, text=True, env=os.environ | env, timeout=120)
    assert r.returncode == 0, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "MERGESVC_HOME" in lines[0] and "WARNING" in lines[0], lines
    r = subprocess.run([sys.executable, "-m", "mergesvc.cli", "match", "--map", str(pair[0]),
                        "--submap", str(pair[1])], capture_output=True, text=True,
                       env=os.environ | env | {"MERGESVC_MATCH__SOLVR__NAME": "sm"}, timeout=120)
    assert r.returncode == 1
    assert r.stderr.strip().splitlines()[-1].startswith("error: unknown setting")


def test_text_fields_keep_the_text_as_typed() -> None:
    s = load_settings(environ={"MERGESVC_SERVICE__FLEET": "007", "MERGESVC_AGENT__SESSION": "1"})
    assert s.service.fleet == "007" and s.agent.session == "1"


def test_a_whole_section_from_one_variable_and_a_field_on_top() -> None:
    s = load_settings(environ={"MERGESVC_MATCH__CANDIDATES": '{"top_k": 3, "sample": 9}',
                               "MERGESVC_MATCH__CANDIDATES__TOP_K": "5"})
    assert (s.match.candidates.top_k, s.match.candidates.sample) == (5, 9)


def test_the_loader_takes_the_environment_it_is_given(monkeypatch: pytest.MonkeyPatch) -> None:
    """No default: a caller says which environment (the command line passes os.environ)."""
    assert inspect.signature(load_settings).parameters["environ"].default is inspect.Parameter.empty
    monkeypatch.setenv("MERGESVC_CANDIDATES__TOP_K", "3")
    assert load_settings(environ={}).match.candidates.top_k == 12


def test_matching_outside_the_command_line_ignores_the_environment(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """core's match_config and the benchmarks' configurations read no MERGESVC_* variable."""
    monkeypatch.setenv("MERGESVC_CANDIDATES__TOP_K", "3")
    monkeypatch.setenv("MERGESVC_MATCH__VERIFY__MARGIN", "0.5")
    assert match_config() == MatchConfig()
    assert _config("paper", "sm", "ucos", 4.0).candidates.top_k == 12
    assert all(cfg.candidates.top_k == 12 for _, cfg, _ in _modes(True, "mahalanobis"))


def test_the_benchmarks_start_from_the_base_and_set_their_axes() -> None:
    base = match_config(candidates={"top_k": 7}, verify={"margin": 0.2}, mode="paper")
    for label, cfg, _ in _modes(True, "mahalanobis", base):
        assert cfg.candidates.top_k == 7 and cfg.verify.margin == 0.2
        assert cfg.mode.value == ("verified" if label == "verified" else "paper")
        assert cfg.affinity.kind.value == "mahalanobis"
    cfg = _config("paper", "sm", "ucos", 4.0, base)
    assert (cfg.candidates.top_k, cfg.solver.name.value, cfg.affinity.edge_radius_m) == (
        7, "sm", 4.0)


# ------------------------------------------------------------------ written with the results


def test_demo_hands_its_settings_to_the_processes_it_starts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    f = tmp_path / "s.json"
    f.write_text(json.dumps({"service": {"match": {"verify": {"min_matches": 5}}}}))
    seen = {}

    def fake_run_demo(plan, out, echo, attach=None):
        seen["file"] = os.environ[SETTINGS_ENV]
        seen["child"] = load_settings(environ=dict(os.environ))  # what a child resolves
        raise Reached(plan)

    monkeypatch.setattr(mergesvc.fleet.demo, "run_demo", fake_run_demo)
    monkeypatch.setenv("MERGESVC_SERVICE__QUEUE_SIZE", "9")
    out = tmp_path / "demo"
    _invoke(["demo", "--quick", "--out", str(out), "--settings", str(f)])
    written = json.loads((out / "settings.json").read_text())
    assert Path(seen["file"]) == (out / "settings.json").resolve()
    assert written["service"]["match"]["verify"]["min_matches"] == 5
    assert written["service"]["queue_size"] == 9
    assert seen["child"].service.match.verify.min_matches == 5
    assert seen["child"] == Settings.model_validate(written)
    assert SETTINGS_ENV not in os.environ  # restored after the demo


def test_demo_scores_with_the_vehicles_settings(tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """The score rebuilds the vehicles' maps to know which object each track is: with the
    settings the vehicles ran with (a tracker set otherwise scored 0.13 precision on right
    factors), not the defaults."""
    f = tmp_path / "s.json"
    f.write_text(json.dumps({"agent": {"tracking": {"semantic_ratio": 2.0},
                                       "window_objects": 6}}))
    seen = {}

    def fake_run_demo(plan, out, echo, attach=None):
        seen["plan"] = plan
        raise Reached(plan)

    monkeypatch.setattr(mergesvc.fleet.demo, "run_demo", fake_run_demo)
    _invoke(["demo", "--quick", "--out", str(tmp_path / "demo"), "--settings", str(f)])
    agents = seen["plan"].agents
    assert sorted(agents) == ["auv1", "auv2", "auv3"]
    for r, a in agents.items():
        assert a.robot == r and a.tracking.semantic_ratio == 2.0 and a.window_objects == 6
        assert a.tracking.cos_min == AgentConfig(robot=r).tracking.cos_min  # the rest kept
        assert a.up == (0.0, 0.0, 1.0)  # as the demo's vehicles run


def test_bench_writes_the_settings_it_used_beside_its_results(tmp_path: Path) -> None:
    f = tmp_path / "s.json"
    f.write_text(json.dumps({"match": {"candidates": {"top_k": 7}}}))
    out = tmp_path / "bench.json"
    r = runner.invoke(app, ["bench", "match", "--repeats", "1", "--seeds", "1", "--no-paper",
                            "--affinity", "ucos", "--out", str(out), "--settings", str(f)])
    assert r.exit_code == 0, r.output
    report = json.loads(out.read_text())
    assert report["settings"]["verified/ucos"]["candidates"]["top_k"] == 7
    written = json.loads((tmp_path / "bench.settings.json").read_text())
    assert written == load_settings(f, environ={}).model_dump(mode="json")


def test_config_dump_in_a_process_of_its_own(tmp_path: Path) -> None:
    """As a user (or a process the demo starts) runs it: $MERGESVC_SETTINGS, the variables."""
    f = tmp_path / "s.json"
    f.write_text(json.dumps({"service": {"graph": {"outlier_weight": 0.25}}}))
    env = {k: v for k, v in os.environ.items() if not k.startswith("MERGESVC_")}
    env |= {SETTINGS_ENV: str(f), "MERGESVC_MATCH__SOLVER__NAME": "sm"}
    r = subprocess.run([sys.executable, "-m", "mergesvc.cli", "config", "--dump"],
                       capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    tree = json.loads(r.stdout)
    assert set(tree) == set(SECTIONS)
    assert tree["service"]["graph"]["outlier_weight"] == 0.25
    assert tree["match"]["solver"]["name"] == "sm"
    r = subprocess.run([sys.executable, "-m", "mergesvc.cli", "config", "--dump", "--section",
                        "service.graph"], capture_output=True, text=True, env=env, timeout=120)
    assert json.loads(r.stdout)["outlier_weight"] == 0.25


# ------------------------------------------------------------------ config --dump --for


@pytest.mark.parametrize(
    ("for_", "in_match", "in_service"),
    [(None, True, True), ("serve", False, True), ("match", True, False),
     ("bench", True, False), ("agent", True, False)],
)
def test_config_dump_places_a_bare_match_config_as_the_command_does(
    for_: str | None, in_match: bool, in_service: bool, tmp_path: Path
) -> None:
    f = tmp_path / "bare.json"
    f.write_text(json.dumps({"mode": "paper", "candidates": {"top_k": 5}}))
    r = runner.invoke(app, ["config", "--dump", "--settings", str(f),
                            *(["--for", for_] if for_ else [])])
    assert r.exit_code == 0, r.output
    tree = json.loads(r.output)
    bare = match_config(mode="paper", candidates={"top_k": 5}).model_dump(mode="json")
    assert (tree["match"] == bare) is in_match
    assert (tree["service"]["match"] == bare) is in_service
    if not in_match:
        assert tree["match"] == MatchConfig().model_dump(mode="json")
    if not in_service:
        assert tree["service"]["match"] == ServiceConfig().match.model_dump(mode="json")


def test_config_dump_for_serve_is_what_serve_uses(
    tmp_path: Path, pair: tuple[Path, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    f = tmp_path / "bare.json"
    f.write_text(json.dumps({"verify": {"min_matches": 6}, "solver": {"name": "sm"}}))
    served = via_serve(monkeypatch, tmp_path, pair, ["--settings", str(f)])
    r = runner.invoke(app, ["config", "--dump", "--settings", str(f), "--for", "serve",
                            "--section", "service"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.output) == served.model_dump(mode="json")
    matched = via_match(monkeypatch, tmp_path, pair, ["--settings", str(f)])
    r = runner.invoke(app, ["config", "--dump", "--settings", str(f), "--for", "match",
                            "--section", "match"])
    assert json.loads(r.output) == matched.model_dump(mode="json")


# ------------------------------------------------------------------ bad counts, help texts


@pytest.mark.parametrize("command", [["bench", "match", "--repeats", "0"],
                                     ["bench", "match", "--seeds", "0"],
                                     ["bench", "paper", "--quick", "--repeats", "0"]])
def test_a_bad_count_is_exit_2_without_a_traceback(command: list[str]) -> None:
    """typer refuses the count (min=1) with its usage block, the message on one line."""
    r = subprocess.run([sys.executable, "-m", "mergesvc.cli", *command],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stdout == ""
    assert "Traceback" not in r.stderr and "AssertionError" not in r.stderr
    flag = command[-2]
    assert len([line for line in r.stderr.splitlines() if flag in line
                and ">= 1" in line.replace("greater than or equal to", ">=")]) == 1, r.stderr


def test_the_benchmark_functions_refuse_a_bad_count_themselves() -> None:
    """Called from Python (no typer in front): InputError, which the CLI maps to exit 2."""
    from mergesvc.bench import PaperBenchPlan, run_link_bench, run_match_bench, run_paper_bench
    from mergesvc.bench.match import run_case
    from mergesvc.errors import InputError
    from mergesvc.sim import Family, make_scenario

    with pytest.raises(InputError, match="repeats must be >= 1, got 0"):
        run_match_bench(repeats=0, seeds=1)
    with pytest.raises(InputError, match="seeds must be >= 1"):
        run_match_bench(seeds=0)
    with pytest.raises(InputError, match="repeats must be >= 1"):
        run_case(make_scenario(Family.KITTI, 0), MatchConfig(), 0)
    with pytest.raises(InputError, match="repeats must be >= 1"):
        run_paper_bench(PaperBenchPlan(repeats=0), Path("unused"))
    with pytest.raises(InputError, match="seeds must be >= 1"):
        run_link_bench(seeds=0)


def test_the_bench_package_has_no_runtime_asserts() -> None:
    import ast

    bench = Path(mergesvc.bench.__file__).parent
    found = [f"{p.name}:{n.lineno}" for p in sorted(bench.glob("*.py"))
             for n in ast.walk(ast.parse(p.read_text())) if isinstance(n, ast.Assert)]
    assert not found, found


SETTINGS_HELP = {
    ("match",): ["`match`", "bare MatchConfig"],
    ("serve",): ["`service`", "service.match"],
    ("agent",): ["`agent`"],
    ("demo",): ["`service` and `agent`"],
    ("codec", "encode"): ["`codec`"],
    ("link", "sim"): ["`link` and `workload`"],
    ("uncertainty", "train"): ["`uncertainty`", "UncertaintyConfig"],
    ("bench", "match"): ["`match`"],
    ("bench", "link"): ["`match`", "`link`"],
    ("config",): ["whole tree", "--for"],
}


@pytest.mark.parametrize("command", list(SETTINGS_HELP), ids=" ".join)
def test_settings_help_says_what_the_command_reads(command: tuple[str, ...]) -> None:
    r = runner.invoke(app, [*command, "--help"], env={"COLUMNS": "400"})
    assert r.exit_code == 0, r.output
    lines = r.output.splitlines()
    at = next(i for i, x in enumerate(lines) if x.lstrip().startswith("--settings"))
    # the option's help, however it is wrapped: up to the next option
    end = next((i for i in range(at + 1, len(lines))
                if lines[i].startswith("  -") or not lines[i].startswith("   ")), len(lines))
    line = " ".join(x.strip() for x in lines[at:end])
    for words in SETTINGS_HELP[command]:
        assert words in line, (command, line)
    # only the commands that take a bare MatchConfig file say so
    takes_bare = command in {("match",), ("serve",), ("config",), ("bench", "match"),
                             ("bench", "link")}
    assert ("bare MatchConfig" in line) is takes_bare, line


def test_help_paragraphs_do_not_break_mid_sentence() -> None:
    """typer keeps the line breaks of a docstring's later paragraphs: each is one line."""
    from mergesvc.cli import bench, files, fleet

    bad = []
    for typer_app in (app, bench.app, files.codec_app, files.scenario_app,
                      files.uncertainty_app, fleet.link_app):
        for info in typer_app.registered_commands:
            doc = inspect.cleandoc(info.callback.__doc__ or "")
            for paragraph in doc.split("\n\n")[1:]:
                if "\n" in paragraph.strip():
                    bad.append(f"{info.callback.__name__}: {paragraph[:60]!r}")
    assert not bad, bad


# ------------------------------------------------------------------ the tests' environment


def test_no_settings_variable_reaches_a_test_or_a_process_it_starts(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """tests/conftest.py strips MERGESVC_* for every test (autouse), and the processes a test
    starts inherit the stripped os.environ."""
    from conftest import strip_settings_env

    child = [sys.executable, "-c",
             "import os; print(sorted(k for k in os.environ if k.startswith('MERGESVC_')))"]
    assert not [k for k in os.environ if k.startswith("MERGESVC_")]
    monkeypatch.setenv("MERGESVC_HOME", "/x")  # as a developer's shell would have it
    monkeypatch.setenv("MERGESVC_MATCH__MODE", "paper")
    with pytest.MonkeyPatch.context() as mp:
        strip_settings_env(mp)
        assert not [k for k in os.environ if k.startswith("MERGESVC_")]
        r = subprocess.run(child, capture_output=True, text=True, timeout=60)
        assert r.stdout.strip() == "[]"
    assert os.environ["MERGESVC_HOME"] == "/x"  # the check itself can fail:
    r = subprocess.run(child, capture_output=True, text=True, timeout=60)
    assert r.stdout.strip() == "['MERGESVC_HOME', 'MERGESVC_MATCH__MODE']"
