"""Command line: `mergesvc match`, `convert`, `example`, `schemas`, `config`, `serve`, `agent`,
`demo`, `export`, `view`, `bench`, `codec`, `projection`, `scenario`, `uncertainty`, `solver`,
`link`. Only this package exits.

The command tree is assembled here; the commands live in `files` (commands on files, and
`config --dump`), `projection` (the fleet's projection), `bench` (benchmarks), `fleet` (the
service, vehicles, the demo and the acoustic link) and `view` (the live view in Rerun). Known
errors become exit codes in `errors`; shared options (the Zenoh flags, `--settings` and how the
settings tree is resolved) are in `options`.
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import re
import sys
from collections.abc import Iterator
from typing import Annotated

import typer

from mergesvc.cli import ask, bench, files, fleet, projection, solver, view
from mergesvc.cli.errors import EXIT_BAD_INPUT, fail, show_tracebacks
from mergesvc.errors import InputError

__all__ = ["app", "hoist_verbose", "main"]

class _Tree(typer.core.TyperGroup):
    """The command tree, its help in plain text (as every command's: rich's renderer alone
    costs ~0.3 s of start-up). A usage error (a missing or unknown option, an unknown
    command, a bad choice) is one line and exit 2, and so is a file or folder a command could
    not use and did not name in a message of its own (one that exists in a folder's place, a
    folder missing or not writable); a group called bare prints its help (exit 2)."""

    def format_help(self, ctx, formatter) -> None:  # type: ignore[no-untyped-def]
        super(typer.core.TyperGroup, self).format_help(ctx, formatter)

    def parse_args(self, ctx, args):  # type: ignore[no-untyped-def]
        with _one_line_errors():
            return super().parse_args(ctx, args)

    def invoke(self, ctx):  # type: ignore[no-untyped-def]
        with _one_line_errors():
            return super().invoke(ctx)


# what a user's file or folder can do to a command (not a full disk, not a broken pipe)
_PATH_ERRORS = (FileExistsError, FileNotFoundError, IsADirectoryError, NotADirectoryError,
                PermissionError)


@contextlib.contextmanager
def _one_line_errors() -> Iterator[None]:
    try:
        yield
    except _USAGE_ERROR as exc:
        if type(exc).__name__ == "NoArgsIsHelpError":  # a group called bare: its help
            typer.echo(exc.ctx.get_help())
            raise typer.Exit(EXIT_BAD_INPUT) from None
        where = exc.ctx.command_path if exc.ctx is not None else "mergesvc"
        # an option's own check (a pydantic validator behind a choice) speaks without its
        # library's prefix
        message = exc.format_message().replace(": Value error, ", ": ")
        fail(InputError(f"{message} (see {where} --help)"), EXIT_BAD_INPUT)
    except _PATH_ERRORS as exc:
        if exc.filename is None:
            raise
        fail(exc, EXIT_BAD_INPUT)


# the click typer builds on (its own copy in recent typer, the click package before)
_CLICK = typer.core.TyperGroup.__mro__[1].__module__.rsplit(".", 1)[0]
_USAGE_ERROR = importlib.import_module(f"{_CLICK}.exceptions").UsageError

app = typer.Typer(
    cls=_Tree,
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,  # help texts are plain: "pip install 'mergesvc[view]'" stays
    help="mergesvc: merge multi-robot object maps by semantic graph matching.",
)


def _version(value: bool) -> None:
    if value:
        from importlib.metadata import PackageNotFoundError, version

        try:
            typer.echo(f"mergesvc {version('mergesvc')}")
        except PackageNotFoundError:  # run from a source tree that was never installed
            typer.echo("mergesvc (not installed: no version)")
        raise typer.Exit()


@app.callback()
def _main(
    verbose: Annotated[int, typer.Option(
        "--verbose", "-v", count=True, help="more logs; -vv: debug, and tracebacks of errors")] = 0,
    _: Annotated[bool, typer.Option("--version", is_eager=True, callback=_version,
                                    help="print the version and exit")] = False,
) -> None:
    logging.basicConfig(
        level=logging.WARNING - 10 * min(verbose, 2),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    show_tracebacks(verbose >= 2)


for _command in (
    files.match, files.convert, files.example, files.schemas, files.config, fleet.serve,
    fleet.agent, fleet.demo, fleet.export, ask.status, ask.relocalize, view.view,
):
    app.command()(_command)
app.add_typer(bench.app, name="bench")
app.add_typer(files.codec_app, name="codec")
app.add_typer(projection.projection_app, name="projection")
app.add_typer(files.scenario_app, name="scenario")
app.add_typer(files.uncertainty_app, name="uncertainty")
app.add_typer(solver.solver_app, name="solver")
app.add_typer(fleet.link_app, name="link")


def hoist_verbose(argv: list[str]) -> list[str]:
    """`-v`, `-vv` and `--verbose` anywhere before `--` moved to the front, so that
    `mergesvc serve -v` works as `mergesvc -v serve` does (the flag is the tree's, not each
    command's). No command has an option of its own spelled so."""
    end = argv.index("--") if "--" in argv else len(argv)
    verbose = [a for a in argv[:end] if a == "--verbose" or _VERBOSE.fullmatch(a)]
    rest = [a for a in argv[:end] if not (a == "--verbose" or _VERBOSE.fullmatch(a))]
    return verbose + rest + argv[end:]


_VERBOSE = re.compile(r"-v+")


def main() -> None:
    app(args=hoist_verbose(sys.argv[1:]))
