"""Command line: `mergesvc match`, `example`, `schemas`, `bench`. Only this module exits."""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path
from typing import Annotated

import typer

from mergesvc.affinity import NodeAffinity
from mergesvc.config import MatchMode, SolverName, load_config
from mergesvc.errors import InputError, MergeError

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    help="mergesvc: merge multi-robot object maps by semantic graph matching.",
)
log = logging.getLogger("mergesvc")


def _fail(exc: MergeError) -> None:
    """Known errors: one line on stderr, exit 2 for bad input, 1 otherwise."""
    msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    typer.echo(f"error: {msg}", err=True)
    raise typer.Exit(2 if isinstance(exc, InputError) else 1)


@app.callback()
def _main(
    verbose: Annotated[int, typer.Option("--verbose", "-v", count=True, help="more logs")] = 0,
) -> None:
    logging.basicConfig(
        level=logging.WARNING - 10 * min(verbose, 2),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )


@app.command()
def match(
    map_path: Annotated[Path, typer.Option("--map", help="map JSON file")],
    submap_path: Annotated[Path, typer.Option("--submap", help="submap JSON file")],
    mode: Annotated[MatchMode, typer.Option(help="verified (ours) or paper (baseline)")] = (
        MatchMode.VERIFIED
    ),
    solver: Annotated[SolverName, typer.Option(help="graph-matching solver")] = SolverName.RRWM,
    affinity: Annotated[NodeAffinity, typer.Option(help="node affinity")] = NodeAffinity.UCOS,
    config: Annotated[
        Path | None, typer.Option(help="JSON settings file (see mergesvc.config)")
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="print one JSON object")] = False,
) -> None:
    """Match a submap against a map; print the correspondences and the transform."""
    from mergesvc.model import ObjectMap, Submap, load_model
    from mergesvc.pipeline import match as run_match

    try:
        cfg = load_config(
            config, mode=mode.value, solver={"name": solver.value},
            affinity={"kind": affinity.value},
        )
        map_ = load_model(ObjectMap, map_path)
        sub = load_model(Submap, submap_path)
        outcome = run_match(map_, sub, cfg)
    except MergeError as exc:
        _fail(exc)
        return
    result = outcome.result
    if as_json:
        typer.echo(json.dumps(result.cli_dict()))
        return
    state = "accepted" if result.accepted else "rejected"
    typer.echo(f"{state} ({result.reason.value}): {len(result.matches)} matches")
    for m in result.matches:
        typer.echo(f"  {m.submap_object:>12} -> {m.map_object:<12} score {m.score:.3f}")
    if result.transform is not None:
        t, q = result.transform.translation, result.transform.quaternion_wxyz
        typer.echo(f"  T_map_submap: t = [{t[0]:.3f}, {t[1]:.3f}, {t[2]:.3f}] m, "
                   f"q_wxyz = [{q[0]:.4f}, {q[1]:.4f}, {q[2]:.4f}, {q[3]:.4f}]")
    typer.echo("  timings (ms): " + ", ".join(f"{k} {v:.1f}" for k, v in result.timings_ms.items()))


@app.command()
def example(
    out_dir: Annotated[Path, typer.Argument(help="folder for map.json, submap.json, truth.json")],
    family: Annotated[str, typer.Option(help="underwater or kitti")] = "kitti",
    seed: Annotated[int, typer.Option(help="scenario seed")] = 0,
) -> None:
    """Write a seeded example map, submap and their ground truth."""
    from mergesvc.scenario import Family, make_scenario

    try:
        sc = make_scenario(Family(family), seed)
    except ValueError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "map.json").write_text(sc.map.model_dump_json())
    (out_dir / "submap.json").write_text(sc.submap.model_dump_json())
    (out_dir / "truth.json").write_text(json.dumps(sc.truth_dict(), indent=1))
    typer.echo(
        f"wrote {out_dir}/map.json ({len(sc.map.objects)} objects), submap.json "
        f"({len(sc.submap.objects)} objects), truth.json"
    )


@app.command()
def schemas(
    out_dir: Annotated[Path, typer.Argument(help="folder for the JSON Schema files")] = Path(
        "schemas"
    ),
    check: Annotated[bool, typer.Option(help="fail if the files differ from the models")] = False,
) -> None:
    """Write (or --check) the JSON Schema files generated from the models."""
    from mergesvc.model import json_schemas

    stale = []
    for name, schema in json_schemas().items():
        text = json.dumps(schema, indent=2, sort_keys=True) + "\n"
        path = out_dir / name
        if check:
            if not path.exists() or path.read_text() != text:
                stale.append(name)
        else:
            out_dir.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
    if stale:
        typer.echo(f"error: schemas out of date: {', '.join(stale)}", err=True)
        raise typer.Exit(1)
    typer.echo(f"schemas {'up to date' if check else 'written'} in {out_dir}")


bench_app = typer.Typer(no_args_is_help=True, help="benchmarks")
app.add_typer(bench_app, name="bench")


@bench_app.command("match")
def bench_match(
    repeats: Annotated[int, typer.Option(help="runs per scenario")] = 5,
    seeds: Annotated[int, typer.Option(help="scenarios per family")] = 5,
    paper: Annotated[bool, typer.Option(help="also run paper mode (slow: dense K)")] = True,
    affinity: Annotated[
        list[NodeAffinity] | None,
        typer.Option(help="node affinities to measure (repeat the option); default: all"),
    ] = None,
    out: Annotated[Path | None, typer.Option(help="write the results as JSON here")] = None,
) -> None:
    """Latency and accuracy of verified vs paper mode on seeded scenarios."""
    from mergesvc.bench import run_match_bench

    kinds = tuple(a.value for a in (affinity or list(NodeAffinity)))
    try:
        report = run_match_bench(
            repeats=repeats, seeds=seeds, paper=paper, echo=typer.echo, affinities=kinds
        )
    except MergeError as exc:
        _fail(exc)
        return
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(report, indent=1))
        typer.echo(f"wrote {out}")


def main() -> None:
    app()


if __name__ == "__main__":
    main()
