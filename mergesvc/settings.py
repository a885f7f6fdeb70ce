"""One settings tree for every command: `Settings`, a section per part of the system, resolved
from defaults <- a JSON file <- `MERGESVC_*` environment <- command-line flags.

It nests the config models of core, wire, link, sim and fleet and is the only place that reads
the settings file and the environment; only `mergesvc.cli` imports it, and everything below
takes its config objects as arguments. `load_settings` takes the environment as a parameter (the
command line passes `os.environ`, tests `{}`): nothing reads `os.environ` behind a caller's back.

The file is JSON: the tree (`mergesvc config --dump`; any subset will do) or a bare MatchConfig
or UncertaintyConfig section; `MERGESVC_SETTINGS=FILE` names it when no `--settings` is given.
The environment: `MERGESVC_<SECTION>__<FIELD>[__<FIELD>...]=VALUE`, read as JSON when it parses,
else as a string. An unknown field under a section is a ConfigError; a name that is not a
setting is ignored with one warning. The rules in full: docs/architecture.md, "Settings".
"""

from __future__ import annotations

import copy
import difflib
import json
import logging
import types
import typing
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, create_model, field_validator

from mergesvc.core.config import MatchConfig
from mergesvc.errors import ConfigError
from mergesvc.fleet.agent import AgentConfig
from mergesvc.fleet.config import ServiceConfig
from mergesvc.link.config import LinkConfig
from mergesvc.link.workload import Workload
from mergesvc.sim.uncertainty import UncertaintyConfig
from mergesvc.wire.profiles import CodecSettings

log = logging.getLogger(__name__)

ENV_PREFIX = "MERGESVC_"
SETTINGS_ENV = "MERGESVC_SETTINGS"
FLAGS = "flags"  # the command line's layer (`load_settings` overrides)
# Variables already warned about as "not a setting" (one warning per process and name).
_WARNED: set[str] = set()

# AgentConfig without the vehicle's name: that is `mergesvc agent --robot`, one per process,
# not a setting a fleet shares. Built from AgentConfig's fields and their validators, so a field
# or a check added there is here.
AgentSettings = create_model(
    "AgentSettings",
    __config__=ConfigDict(extra="forbid"),
    __doc__="The `agent` section: AgentConfig (fleet/agent.py) without `robot` (--robot).",
    __module__=__name__,
    __validators__={
        name: field_validator(*(f for f in dec.info.fields if f != "robot"),
                              mode=dec.info.mode)(classmethod(dec.func.__func__))
        for name, dec in AgentConfig.__pydantic_decorators__.field_validators.items()
        if set(dec.info.fields) - {"robot"}
    },
    **{
        name: (info.annotation, copy.copy(info))
        for name, info in AgentConfig.model_fields.items()
        if name != "robot"
    },
)


class Settings(BaseModel):
    """Every setting of mergesvc, a section per part; the sections are the config models of the
    layers below, nested as they are (a field added to one of them is in the tree).

    Sections and the commands that use them:
      match        `mergesvc match` (MatchConfig, core/config.py); for `mergesvc bench ...` the
                   settings every benchmarked configuration starts from (each benchmark sets
                   its own axes on top: mode, solver, affinity kind, paper-mode edge radius)
      service      `mergesvc serve`, and the service `mergesvc demo` starts (ServiceConfig,
                   fleet/service.py). It holds the service's own matching settings,
                   `service.match` (an inter-robot factor needs 4 matches by default), and
                   whatever else ServiceConfig nests (e.g. the pose graph's settings)
      agent        `mergesvc agent`, and the vehicles `mergesvc demo` starts (AgentConfig,
                   fleet/agent.py, without `robot`, which is --robot)
      codec        `mergesvc codec encode` (CodecSettings, wire/profiles.py)
      link         `mergesvc link sim`, `mergesvc bench link`: the link every rate x SNR point
                   of their sweeps starts from (LinkConfig, link/config.py). `link bridge`
                   builds its link from its own flags and does not read this section
      workload     `mergesvc link sim`: the traffic it simulates (Workload, link/workload.py)
      uncertainty  `mergesvc uncertainty train` (UncertaintyConfig,
                   sim/uncertainty/config.py)

    `mergesvc config --dump [--settings FILE] [--section NAME] [--for COMMAND]` prints the
    resolved tree (--for: where the command puts a bare MatchConfig file);
    `mergesvc bench ...` and `mergesvc demo` write it beside their results (settings.json in an
    output folder, NAME.settings.json beside an output file NAME.json).
    """

    model_config = ConfigDict(extra="forbid")

    match: MatchConfig = Field(default_factory=MatchConfig, description="mergesvc match")
    service: ServiceConfig = Field(default_factory=ServiceConfig, description="mergesvc serve")
    agent: AgentSettings = Field(  # type: ignore[valid-type]
        default_factory=AgentSettings, description="mergesvc agent (without --robot)"
    )
    codec: CodecSettings = Field(default_factory=CodecSettings, description="codec encode")
    link: LinkConfig = Field(default_factory=LinkConfig, description="link sim, bench link")
    workload: Workload = Field(default_factory=Workload, description="link sim")
    uncertainty: UncertaintyConfig = Field(
        default_factory=UncertaintyConfig, description="uncertainty train"
    )

    def agent_config(self, robot: str) -> AgentConfig:
        """The AgentConfig of vehicle `robot`: the agent section plus its name."""
        fields = {name: getattr(self.agent, name) for name in type(self.agent).model_fields}
        try:
            return AgentConfig.model_validate({**fields, "robot": robot})
        except ValidationError as exc:
            # the section's own values were checked when it was loaded
            raise _config_error(exc, "--robot") from exc

    def merged(self, overrides: Mapping[str, Any]) -> Settings:
        """These settings with `overrides` (nested dicts by section) merged in and checked."""
        return _validate(_merge(self.model_dump(), overrides))

    def to_json(self) -> str:
        return json.dumps(self.model_dump(mode="json"), indent=2) + "\n"


SECTIONS: tuple[str, ...] = tuple(Settings.model_fields)
_BARE = {
    "match": frozenset(MatchConfig.model_fields),
    "uncertainty": frozenset(UncertaintyConfig.model_fields),
}


# Where a bare MatchConfig file goes: one path in the tree, or several (each gets the whole
# MatchConfig). `mergesvc serve` puts it at ("service", "match"), every other command at
# ("match",); `mergesvc config --dump` without --for shows both.
BareMatch = tuple[str, ...] | Sequence[tuple[str, ...]]


def load_settings(
    path: Path | str | None = None,
    *,
    environ: Mapping[str, str],
    overrides: Mapping[str, Any] | None = None,
    bare_match: BareMatch = ("match",),
) -> Settings:
    """Defaults <- the JSON file at `path` (else at environ[MERGESVC_SETTINGS], if set) <- the
    `MERGESVC_*` variables of `environ` <- `overrides` (the command-line flags, nested dicts
    by section). `bare_match` is where a bare MatchConfig file goes (a path such as
    ("service", "match"), or several paths). Raises ConfigError."""
    if path is None and environ.get(SETTINGS_ENV):
        path = environ[SETTINGS_ENV]
    # (where a value came from, the values), later ones win: an error names its source
    layers: list[tuple[str, Mapping[str, Any]]] = []
    if path is not None:
        layers.append((f"settings file {path}", read_settings_file(path, bare_match=bare_match)))
    found = _env_found(environ)
    layers.append(("", _env_tree(found)))
    layers.append((FLAGS, overrides or {}))
    data = Settings().model_dump()
    for _, values in layers:
        _merge(data, values)
    try:
        return Settings.model_validate(data)
    except ValidationError as exc:
        loc = exc.errors()[0]["loc"]
        setters = [(label, values) for label, values in reversed(layers) if _sets(values, loc)]
        source = None  # a whole section refused: its setter only when one layer set it
        if setters and (len(loc) > 1 or len(setters) == 1):
            label = setters[0][0]
            source = label or _env_name(found, loc)
        raise _config_error(exc, source) from exc


def read_settings_file(path: Path | str, *, bare_match: BareMatch = ("match",)) -> dict[str, Any]:
    """The settings file as nested overrides by section (a bare section nested where it goes).
    Raises ConfigError for an unreadable file or keys that are neither sections nor one bare
    section's fields."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ConfigError(f"cannot read settings file {path}: {exc}") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"settings file {path} must hold a JSON object")
    keys = set(data)
    if keys <= set(SECTIONS):
        return data
    if keys <= _BARE["match"]:  # a whole MatchConfig, as --config/--settings always read it
        try:  # validated where it goes in the tree: a refusal names the nearest key, the file
            whole = Settings.model_validate({"match": data}).match.model_dump(mode="json")
        except ValidationError as exc:
            raise _config_error(exc, f"settings file {path}") from exc
        out: dict[str, Any] = {}
        for where in _bare_paths(bare_match):
            _merge(out, _nest(where, copy.deepcopy(whole)))
        return out
    if keys <= _BARE["uncertainty"]:
        return {"uncertainty": data}
    unknown = ", ".join(sorted(keys - set(SECTIONS)))
    raise ConfigError(
        f"settings file {path}: unknown section(s) {unknown}; sections: {', '.join(SECTIONS)} "
        "(or a bare MatchConfig or UncertaintyConfig object)"
    )


def env_overrides(environ: Mapping[str, str]) -> dict[str, Any]:
    """The `MERGESVC_*` variables as nested overrides by section. A name whose first part is
    neither a section nor a MatchConfig field (the short form) is not a setting: ignored, with
    one warning per process and name. Raises ConfigError for an unknown field under a section
    (a typo), or one setting named twice (short and long form)."""
    return _env_tree(_env_found(environ))


_EnvFound = dict[tuple[str, ...], tuple[int, str, Any]]  # path -> (long form, name, value)


def _env_found(environ: Mapping[str, str]) -> _EnvFound:
    """env_overrides' settings by path, each with the variable that set it."""
    found: _EnvFound = {}
    ignored: list[str] = []
    for key, raw in environ.items():
        if not key.startswith(ENV_PREFIX) or key == SETTINGS_ENV:
            continue
        path = tuple(key[len(ENV_PREFIX):].lower().split("__"))
        short = path[0] not in SECTIONS and path[0] in MatchConfig.model_fields
        if short:
            path = ("match", *path)
        elif path[0] not in SECTIONS:
            ignored.append(key)
            continue
        leaf = _check_path(key, path)
        if path in found:
            raise ConfigError(f"{found[path][1]} and {key} both set {'.'.join(path)}")
        found[path] = (0 if short else 1, key, _env_value(raw, leaf))
    _warn_ignored(ignored)
    return found


def _env_tree(found: _EnvFound) -> dict[str, Any]:
    out: dict[str, Any] = {}
    # a section given whole (a JSON object) first, its fields after; the short form first
    for path, (_, _, value) in sorted(found.items(), key=lambda kv: (len(kv[0]), kv[1][0])):
        _merge(out, _nest(path, value))
    return out


def _env_name(found: _EnvFound, loc: Sequence[Any]) -> str:
    """The variable that set the value at `loc` (the longest path leading to it), or the
    variables that set values below it (a whole section refused)."""
    names = [(len(path), name) for path, (_, name, _) in found.items()
             if tuple(loc[:len(path)]) == path]
    if names:
        return max(names)[1]
    below = sorted(name for path, (_, name, _) in found.items()
                   if path[:len(loc)] == tuple(loc))
    return ", ".join(below) if below else "the environment"


def _sets(values: Mapping[str, Any], loc: Sequence[Any]) -> bool:
    """Whether nested `values` set the value at `loc` (or a whole list or section holding it)."""
    node: Any = values
    for part in loc:
        if not isinstance(node, Mapping):
            return True
        if part not in node:
            return False
        node = node[part]
    return True


# ------------------------------------------------------------------ helpers


def _warn_ignored(keys: Iterable[str]) -> None:
    """One warning for the variables that are not settings, each name once per process."""
    new = sorted(k for k in keys if k not in _WARNED)
    if not new:
        return
    _WARNED.update(new)
    log.warning(
        "ignoring %s: not a setting (a MERGESVC_* setting starts with a section: %s, "
        "or a match setting)", ", ".join(new), ", ".join(SECTIONS),
    )


def _bare_paths(bare_match: BareMatch) -> list[tuple[str, ...]]:
    """`bare_match` as a list of paths (one path is a tuple of strings)."""
    if all(isinstance(part, str) for part in bare_match):
        return [tuple(typing.cast("tuple[str, ...]", bare_match))]
    return [tuple(where) for where in bare_match]


def _validate(data: Mapping[str, Any]) -> Settings:
    try:
        return Settings.model_validate(data)
    except ValidationError as exc:
        raise _config_error(exc) from exc


FROM_FLAGS = "(set on the command line)"


class SettingsError(ConfigError):
    """Settings refused; `from_flag`: the value at fault came from a command-line flag (bad
    input, where a file's or a variable's is a configuration error); `loc`: where in the tree
    (its message says FROM_FLAGS where the command line can name the flag)."""

    def __init__(self, message: str, *, from_flag: bool = False,
                 loc: tuple[Any, ...] = ()) -> None:
        super().__init__(message)
        self.from_flag, self.loc = from_flag, loc


def _config_error(exc: ValidationError, source: str | None = None) -> SettingsError:
    """The first error, one line: where, what, the nearest key to a misspelt one, and
    `source` (the file, variable or flag that set the value; FLAGS: the flag named as the
    setting is) when known."""
    err = exc.errors()[0]
    loc = ".".join(str(x) for x in err["loc"])
    msg = err["msg"].removeprefix("Value error, ")
    hint = ""
    if err["type"] == "extra_forbidden":  # a misspelt key: the nearest one there is
        near = difflib.get_close_matches(str(err["loc"][-1]), _keys_at(err["loc"][:-1]), 1)
        hint = f" (did you mean {near[0]}?)" if near else " (no such setting)"
    from_flag = source == FLAGS or (source or "").startswith("--")
    if source == FLAGS:
        hint += f" {FROM_FLAGS}"
    elif source:
        hint += f" (set by {source})"
    return SettingsError(f"invalid settings: {loc}: {msg}{hint}", from_flag=from_flag,
                         loc=tuple(err["loc"]))


def _keys_at(path: Sequence[Any]) -> list[str]:
    """The setting names under `path` of the settings tree ([] where it is not a section)."""
    model: Any = Settings
    for part in path:
        field = getattr(model, "model_fields", {}).get(part)
        if field is None:
            return []
        model = field.annotation
    return list(getattr(model, "model_fields", {}))


def _merge(base: dict[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """Merge `over` into `base` (nested dicts merged, anything else replaced); returns base."""
    for k, v in over.items():
        old = base.get(k)
        base[k] = _merge(old if isinstance(old, dict) else {}, v) if isinstance(v, Mapping) else v
    return base


def _nest(path: Iterable[str], value: Any) -> dict[str, Any]:
    parts = list(path)
    out: Any = value
    for part in reversed(parts):
        out = {part: out}
    return out


def _model_of(annotation: Any) -> type[BaseModel] | None:
    """The model a field holds (also through `X | None`), or None for a plain value."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        models = [m for a in typing.get_args(annotation) if (m := _model_of(a)) is not None]
        return models[0] if len(models) == 1 else None
    return None


def _is_mapping(annotation: Any) -> bool:
    origin = typing.get_origin(annotation)
    return isinstance(origin, type) and issubclass(origin, Mapping)


def _check_path(key: str, path: tuple[str, ...]) -> Any:
    """The annotation of the field at `path` (its first part a section); ConfigError (naming
    `key`) if there is none."""
    model: type[BaseModel] = Settings
    annotation: Any = Settings
    for i, part in enumerate(path):
        fields = model.model_fields
        if part not in fields:
            raise ConfigError(
                f"unknown setting {key}: {'.'.join(path[:i])} has no {part!r} "
                f"(it has {', '.join(fields)})"
            )
        annotation = fields[part].annotation
        sub = _model_of(annotation)
        if sub is None:
            if i < len(path) - 1 and not _is_mapping(annotation):
                raise ConfigError(
                    f"unknown setting {key}: {'.'.join(path[: i + 1])} is a value, not a section"
                )
            return annotation
        model = sub
    return annotation


def _env_value(raw: str, annotation: Any) -> Any:
    """JSON if it parses, else the string; a text field keeps the text as typed ("007")."""
    if annotation is str:
        return raw
    try:
        return json.loads(raw)
    except json.JSONDecodeError:
        return raw


__all__ = [
    "ENV_PREFIX",
    "FROM_FLAGS",
    "SECTIONS",
    "SETTINGS_ENV",
    "AgentSettings",
    "BareMatch",
    "Settings",
    "SettingsError",
    "env_overrides",
    "load_settings",
    "read_settings_file",
]
