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

import logging
import re
import sys
from typing import Annotated

import typer

from mergesvc.cli import bench, files, fleet, projection, solver, view
from mergesvc.cli.errors import show_tracebacks

__all__ = ["app", "hoist_verbose", "main"]

class _PlainTopHelp(typer.core.TyperGroup):
    """`mergesvc --help` in plain text: rich's help renderer alone costs ~0.3 s of start-up
    (every command's own --help keeps it)."""

    def format_help(self, ctx, formatter) -> None:  # type: ignore[no-untyped-def]
        super(typer.core.TyperGroup, self).format_help(ctx, formatter)


app = typer.Typer(
    cls=_PlainTopHelp,
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    help="mergesvc: merge multi-robot object maps by semantic graph matching.",
)


@app.callback()
def _main(
    verbose: Annotated[int, typer.Option(
        "--verbose", "-v", count=True, help="more logs; -vv: debug, and tracebacks of errors")] = 0,
) -> None:
    logging.basicConfig(
        level=logging.WARNING - 10 * min(verbose, 2),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    show_tracebacks(verbose >= 2)


for _command in (
    files.match, files.convert, files.example, files.schemas, files.config, fleet.serve,
    fleet.agent, fleet.demo, fleet.export, view.view,
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
