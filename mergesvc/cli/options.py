"""Options shared by several commands, defined once.

The Zenoh flags follow the zenoh-python examples: every program that opens a session takes
`--mode/--connect/--listen/--config` (and `--connect-timeout`), and `zenoh_config` turns them
into a `zenoh.Config`. `serve`, `agent`, `view` and `link bridge` take them. The factories
keep the help text each command has always shown; the plain aliases carry the usual one.

The settings tree (mergesvc/settings.py): every command that has settings takes
`--settings FILE` (`settings_file(...)`, its help naming what that command reads) and resolves
them with `resolve_settings`, the one place the command line hands `os.environ` to the loader.
Where a bare MatchConfig file goes is `bare_match_for(command)`: `service.match` for `serve`,
`match` for every other command (`config --dump --for COMMAND` shows it). `--config` is the
Zenoh file and nothing else; `match --config` and `uncertainty train --config` survive as
hidden, deprecated aliases of `--settings` (`deprecated_config`).
"""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from mergesvc.cli.errors import EXIT_BAD_INPUT, fail
from mergesvc.errors import InputError

if TYPE_CHECKING:
    import zenoh

    from mergesvc.settings import Settings

__all__ = [
    "Connect",
    "ConnectTimeout",
    "DeprecatedConfig",
    "Flags",
    "FleetName",
    "LinkKind",
    "Listen",
    "Mode",
    "Progress",
    "SettingsCommand",
    "TrajectoryFile",
    "ZenohConfigFile",
    "ZenohMode",
    "bare_match_for",
    "check_trajectory",
    "command_group",
    "deprecated_config",
    "given",
    "key_names",
    "progress_lines",
    "resolve_settings",
    "settings_env",
    "settings_file",
    "stop_on_signals",
    "write_settings_beside",
    "zenoh_config",
    "zenoh_connect",
    "zenoh_mode",
]

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
# how long a client or peer keeps trying its --connect endpoints before it gives up (exit 3)
DEFAULT_CONNECT_TIMEOUT_S = 5.0


class ZenohMode(str, Enum):
    """Zenoh session mode."""

    ROUTER = "router"
    PEER = "peer"
    CLIENT = "client"


class LinkKind(str, Enum):
    """How the demo's vehicles reach the service."""

    ZENOH = "zenoh"
    ACOUSTIC = "acoustic"  # through the simulated modem


class SettingsCommand(str, Enum):
    """The commands that read `--settings` (`config --dump --for`)."""

    MATCH = "match"
    SERVE = "serve"
    AGENT = "agent"
    DEMO = "demo"
    CODEC = "codec"
    LINK = "link"
    UNCERTAINTY = "uncertainty"
    BENCH = "bench"


# Where a command puts a bare MatchConfig settings file: `serve` matches with the service's
# own settings, every other command with the `match` section.
_BARE_MATCH: dict[SettingsCommand, tuple[str, ...]] = {SettingsCommand.SERVE: ("service", "match")}


def command_group(help: str) -> typer.Typer:
    """A group of subcommands (`mergesvc bench ...`): its help when called bare; help texts
    plain, not rich markup (so "pip install 'mergesvc[view]'" and "[default: ...]" stay)."""
    return typer.Typer(no_args_is_help=True, rich_markup_mode=None, help=help)


def stop_on_signals() -> threading.Event:
    """An event SIGTERM or Ctrl-C sets: a long-running command stops and says what it did."""
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    return stop


Progress = Annotated[float, typer.Option(
    min=0.0, help="seconds between two progress lines on stderr (a line only when something "
    "changed); 0: none")]


@contextmanager
def progress_lines(every_s: float, line: Callable[[], str]) -> Iterator[None]:
    """While the block runs, `line()` on stderr every `every_s` seconds (after the elapsed
    time), when it differs from the last one printed; none for `every_s` 0. A `line()` that
    fails is skipped: progress never stops the work."""
    if every_s <= 0:
        yield
        return
    done = threading.Event()
    start = time.monotonic()

    def loop() -> None:
        last = ""
        while not done.wait(every_s):
            try:
                text = line()
            except Exception:  # a progress line is never worth the work's failure
                continue
            if text != last:
                typer.echo(f"[{time.monotonic() - start:6.0f} s] {text}", err=True)
                last = text

    thread = threading.Thread(target=loop, name="progress", daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join()


def key_names(what: str) -> Callable[[Any], Any]:
    """A typer callback refusing a name (or each of a list) that no key can hold as a `what`
    (fleet, robot: wire/keys.py check_name): bad input, before anything connects."""
    from mergesvc.errors import ConfigError
    from mergesvc.wire.keys import check_name

    def check(value: Any) -> Any:
        try:
            for name in value if isinstance(value, list) else [value] if value else []:
                check_name(what, name)
        except ConfigError as exc:
            raise typer.BadParameter(str(exc)) from exc
        return value

    return check


FleetName = Annotated[str, typer.Option(help="fleet name in the key space",
                                        callback=key_names("fleet"))]


def bare_match_for(command: SettingsCommand | None) -> tuple[tuple[str, ...], ...]:
    """Where `command` puts a bare MatchConfig file (`None`: every place a command may put it,
    `match` and `service.match`)."""
    if command is None:
        return (("match",), ("service", "match"))
    return (_BARE_MATCH.get(command, ("match",)),)


def zenoh_mode(help_text: str = "zenoh mode: router, peer or client") -> Any:
    """`--mode`, typed so typer checks and lists router|peer|client."""
    return Annotated[ZenohMode, typer.Option("--mode", help=help_text)]


def zenoh_connect(help_text: str = "zenoh endpoint(s)") -> Any:
    """`--connect EP`, repeatable."""
    return Annotated[list[str] | None, typer.Option("--connect", help=help_text)]


Mode = zenoh_mode()
Connect = zenoh_connect()
Listen = Annotated[list[str] | None, typer.Option("--listen", help="zenoh listen endpoint(s)")]
ZenohConfigFile = Annotated[Path | None, typer.Option("--config", help="zenoh JSON5 config file")]
ConnectTimeout = Annotated[float | None, typer.Option(
    "--connect-timeout",
    help="seconds to keep trying the --connect endpoints before giving up (exit 3); negative: "
         f"forever [default: {DEFAULT_CONNECT_TIMEOUT_S:g} for a client or peer; with --config, "
         "its connect/timeout_ms; a router keeps trying in the background]")]


def settings_file(reads: str, *, bare: str | None = None) -> Any:
    """`--settings FILE`, its help saying what the command reads (`reads`: its sections) and
    which bare section object it also takes as a whole file (`bare`), if any."""
    also = f", or a bare {bare}" if bare else ""
    return Annotated[
        Path | None,
        typer.Option(
            "--settings",
            help="settings file (JSON): the tree `mergesvc config --dump` prints or any part "
            f"of it{also}; this command reads {reads}. MERGESVC_* variables override it, "
            "flags override both",
        ),
    ]

DeprecatedConfig = Annotated[
    Path | None, typer.Option("--config", hidden=True, help="deprecated: use --settings")
]
TrajectoryFile = Annotated[
    Path | None, typer.Option(help="KITTI pose file to drive instead of the street loop")
]


def check_trajectory(path: Path | None) -> None:
    """A `--trajectory` that names no file: one line on stderr, exit 2."""
    if path is not None and not path.is_file():
        fail(InputError(f"trajectory file not found: {path}"), EXIT_BAD_INPUT)


def zenoh_config(
    mode: ZenohMode | None,
    connect: Sequence[str] | None,
    listen: Sequence[str] | None,
    config: Path | None,
    *,
    default_connect: Sequence[str] = (),
    scouting: bool | None = None,
    connect_timeout: float | None = None,
) -> zenoh.Config:
    """The Zenoh flags as a `zenoh.Config` (raises ConfigError, InputError for a malformed
    endpoint). `default_connect` applies without --connect, unless a peer or router is
    given --listen (it is reached there: a peer viewer needs no router);
    `scouting=None` means scouting stays on unless a --config file is given (what serve and
    agent have always done);
    `connect_timeout=None` (not typed) means DEFAULT_CONNECT_TIMEOUT_S for a client or peer
    without a --config file, else the file's (or Zenoh's) own."""
    from mergesvc.wire.session import make_zenoh_config

    if connect_timeout is None and config is None and mode is not ZenohMode.ROUTER:
        connect_timeout = DEFAULT_CONNECT_TIMEOUT_S
    return make_zenoh_config(
        config_file=str(config) if config else None,
        mode=mode.value if mode is not None else None,
        connect=tuple(connect or (() if listen and mode in (ZenohMode.PEER, ZenohMode.ROUTER)
                                  else default_connect)),
        listen=tuple(listen or ()),
        scouting=config is None if scouting is None else scouting,
        connect_timeout_s=connect_timeout,
    )


def deprecated_config(settings: Path | None, config: Path | None, command: str) -> Path | None:
    """The settings file of a command that used to call it `--config`: a one-line warning on
    stderr when the old name is used, exit 2 when both are."""
    if config is None:
        return settings
    if settings is not None:
        fail(InputError("--config is the deprecated name of --settings: give one"), EXIT_BAD_INPUT)
    typer.echo(f"warning: `mergesvc {command} --config` is deprecated, use --settings "
               "(--config names a Zenoh config file)", err=True)
    return config


def given(ctx: typer.Context, **flags: Any) -> Flags:
    """The flags typed on the command line (named by their parameter), enums as their values:
    the flags' layer of the settings. A flag left at its default is left out, so the value
    from the file or the environment stands (a flag's default is the setting's default)."""
    out = Flags()
    out.options = {p.name: list(p.opts) for p in ctx.command.params if p.name and p.opts}
    for name, value in flags.items():
        source = ctx.get_parameter_source(name)
        if source is not None and source.name not in ("DEFAULT", "DEFAULT_MAP"):
            out[name] = value.value if isinstance(value, Enum) else value
    return out


def resolve_settings(
    path: Path | None,
    flags: Mapping[str, Any] | None = None,
    *,
    bare_match: tuple[tuple[str, ...], ...] = bare_match_for(SettingsCommand.MATCH),
) -> Settings:
    """Defaults <- `path` (else $MERGESVC_SETTINGS) <- MERGESVC_* <- `flags` (nested by section).
    `bare_match`: where a bare MatchConfig file goes (`bare_match_for(command)`). A bad file or
    variable is a ConfigError (exit 1 under exit_on_error); a flag the settings refuse is bad
    input (exit 2), as when the command checked it itself."""
    from mergesvc.settings import FROM_FLAGS, SettingsError, load_settings

    try:
        return load_settings(path, environ=os.environ, overrides=flags, bare_match=bare_match)
    except SettingsError as exc:
        if not exc.from_flag:
            raise
        flag = _flag_of(flags or {}, exc.loc)
        text = str(exc).replace(FROM_FLAGS, f"(set by {flag})") if flag else str(exc)
        fail(SettingsError(text, from_flag=True, loc=exc.loc), EXIT_BAD_INPUT)


def _flag_of(flags: Mapping[str, Any], loc: tuple[Any, ...]) -> str | None:
    """The flag (`given`'s options) that set the setting at `loc` (section, setting, ...):
    the parameter named as the setting or spelt so; None when no flag is known for it."""
    if len(loc) < 2 or not isinstance(loc[1], str):
        return None
    options = getattr(flags.get(loc[0]), "options", {})
    spelt = "--" + loc[1].replace("_", "-")
    return next((opts[0] for name, opts in options.items()
                 if name == loc[1] or spelt in opts), None)


class Flags(dict[str, Any]):
    """The flags typed (`given`), with every parameter's option names (`options`: parameter
    -> its flags) to name the flag a refused setting came from."""

    options: dict[str, list[str]]


def write_settings_beside(settings: Settings, out: Path, *, folder: bool) -> Path:
    """Write the resolved settings with a command's results, as kiss-icp does: `settings.json`
    in an output folder, `NAME.settings.json` beside an output file `NAME.json`."""
    path = out / "settings.json" if folder else out.with_suffix(".settings.json")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(settings.to_json())
    return path


@contextmanager
def settings_env(path: Path) -> Iterator[None]:
    """$MERGESVC_SETTINGS set to `path` inside the block (and restored after), so processes
    started inside it read these settings."""
    from mergesvc.settings import SETTINGS_ENV

    old = os.environ.get(SETTINGS_ENV)
    os.environ[SETTINGS_ENV] = str(path.resolve())
    try:
        yield
    finally:
        if old is None:
            os.environ.pop(SETTINGS_ENV, None)
        else:
            os.environ[SETTINGS_ENV] = old
