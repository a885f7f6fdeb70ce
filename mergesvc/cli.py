"""Command line: `mergesvc match`, `example`, `scenario`, `schemas`, `bench`, `uncertainty`,
`link`, `codec`. Only this module exits."""

from __future__ import annotations

import dataclasses
import json
import logging
import sys
import time
from pathlib import Path
from typing import Annotated

import typer

from mergesvc.core.affinity import NodeAffinity
from mergesvc.core.config import MatchMode, SolverName, load_config
from mergesvc.errors import InputError, MergeError
from mergesvc.wire import keys

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
        Path | None, typer.Option(help="JSON settings file (see mergesvc.core.config)")
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="print one JSON object")] = False,
) -> None:
    """Match a submap against a map; print the correspondences and the transform."""
    from mergesvc.core.model import ObjectMap, Submap, load_model
    from mergesvc.core.pipeline import match as run_match

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
    from mergesvc.sim import Family, make_scenario

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
    from mergesvc.core.model import json_schemas

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


@bench_app.command("paper")
def bench_paper(
    out: Annotated[Path, typer.Option(help="folder for JSON, markdown and figures")] = Path(
        "results/paper"
    ),
    quick: Annotated[bool, typer.Option(help="a small slice (under a minute)")] = False,
    seed: Annotated[int, typer.Option(help="world seed")] = 0,
    repeats: Annotated[int | None, typer.Option(help="verified-mode timing repeats")] = None,
    kitti_paper: Annotated[
        bool, typer.Option(help="paper mode on the KITTI-like map too (dense K: minutes)")
    ] = True,
    trajectory: Annotated[
        Path | None, typer.Option(help="KITTI pose file to drive instead of the street loop")
    ] = None,
) -> None:
    """The paper's Table I and II for its pipeline and ours, side by side, plus precision,
    recall, transform errors, stage timings and a scale sweep; figures under --out."""
    from rich.progress import Progress

    from mergesvc.bench import PaperBenchPlan, run_paper_bench

    plan = PaperBenchPlan.quick() if quick else PaperBenchPlan()
    changes: dict[str, object] = {"seed": seed, "kitti_paper": kitti_paper and plan.kitti_paper}
    if repeats is not None:
        changes["repeats"] = repeats
    if trajectory is not None:
        if not trajectory.is_file():
            typer.echo(f"error: trajectory file not found: {trajectory}", err=True)
            raise typer.Exit(2)
        changes["trajectory"] = str(trajectory)
    plan = dataclasses.replace(plan, **changes)
    with Progress(transient=True) as bar:

        def factory(total: int):
            task = bar.add_task("matching", total=total)
            return lambda msg: bar.update(task, advance=1, description=msg[:60])

        try:
            run_paper_bench(plan, out, echo=typer.echo, progress_factory=factory)
        except MergeError as exc:
            _fail(exc)
    typer.echo(f"wrote {out}/paper_bench.json, paper_bench.md and figures")


@bench_app.command("uncertainty")
def bench_uncertainty(
    out: Annotated[Path, typer.Option(help="folder for the report")] = Path("results"),
    seed: Annotated[int, typer.Option(help="world seed")] = 0,
    samples: Annotated[int, typer.Option(help="training observations")] = 20_000,
) -> None:
    """What the learned uncertainty head changes: Table I accuracy with the simulator's true
    image uncertainty, the head's prediction, and a constant (uncertainty-unaware)."""
    from mergesvc.bench import run_uncertainty_bench

    try:
        run_uncertainty_bench(out, seed=seed, samples=samples, echo=typer.echo)
    except MergeError as exc:
        _fail(exc)


@bench_app.command("link")
def bench_link(
    out: Annotated[Path | None, typer.Option(help="write the table as JSON here")] = None,
    seeds: Annotated[int, typer.Option(help="scenarios per profile")] = 5,
    seed: Annotated[int, typer.Option(help="first seed")] = 0,
    period_s: Annotated[float, typer.Option(help="one submap per vehicle every ...")] = 300.0,
    duration_s: Annotated[float, typer.Option(help="simulated mission time")] = 3600.0,
) -> None:
    """Codec profile x modem rate x SNR: bytes, airtime, delivery, time to deliver, accuracy."""
    from mergesvc.bench import run_link_bench

    try:
        report = run_link_bench(seeds=seeds, period_s=period_s, duration_s=duration_s,
                                seed=seed, echo=typer.echo)
    except MergeError as exc:
        _fail(exc)
        return
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(report, indent=1, default=float))
        typer.echo(f"wrote {out}")


@bench_app.command("generalize")
def bench_generalize(
    quick: Annotated[bool, typer.Option(help="a few small cells for CI (under a minute)")] = False,
    seed: Annotated[int, typer.Option(min=0, help="first world seed")] = 0,
    seeds: Annotated[int, typer.Option(min=1, help="seeds per cell (median and spread)")] = 1,
    out: Annotated[
        Path | None, typer.Option(help="write the report as JSON here (and .md beside it)")
    ] = None,
    data: Annotated[
        Path | None, typer.Option(help="the shared data folder (default: ../shared/data)")
    ] = None,
    cell: Annotated[
        list[str] | None, typer.Option(help="run only cells whose name contains this (repeat)")
    ] = None,
    paper: Annotated[bool, typer.Option(help="also run paper mode (dense K: slow)")] = True,
) -> None:
    """Generalization matrix: real KITTI-00 / DINO-based worlds and the project's generators
    in camera / ENU / NED / random / mixed frames, embedding dims, map sizes, look-alikes,
    duplicates, range noise, with and without a declared vertical; verified, paper and
    cosine + Hungarian side by side."""
    from rich.progress import Progress

    from mergesvc.bench import METHODS, GeneralizePlan, run_generalize

    if data is not None and not data.is_dir():
        raise typer.BadParameter(f"{data} is not a folder", param_hint="--data")
    plan = (GeneralizePlan.quick if quick else GeneralizePlan.full)(seed, seeds, data)
    if cell:
        names = [c.name for c in plan.cells]
        plan.cells = [c for c in plan.cells if any(k in c.name for k in cell)]
        if not plan.cells:
            raise typer.BadParameter(
                f"no cell matches {', '.join(cell)}; cells: {', '.join(names)}",
                param_hint="--cell")
    if not paper:
        plan.methods = tuple(m for m in METHODS if m != "paper")
    with Progress(transient=True) as bar:
        task = bar.add_task("generalize", total=plan.steps())
        try:
            report = run_generalize(
                plan, progress=lambda msg, done: bar.update(task, completed=done,
                                                            description=msg[:60]))
        except MergeError as exc:
            _fail(exc)
            return
    typer.echo(report["markdown"])
    typer.echo(f"\n{len(plan.cells)} cells x {seeds} seed(s) in {report['elapsed_s']:.0f} s")
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(report, indent=1, default=float))
        out.with_suffix(".md").write_text(report["markdown"] + "\n")
        typer.echo(f"wrote {out} and {out.with_suffix('.md')}")


codec_app = typer.Typer(no_args_is_help=True, help="the wire codec")
app.add_typer(codec_app, name="codec")


@codec_app.command("encode")
def codec_encode(
    in_path: Annotated[Path, typer.Argument(help="map or submap JSON (the match format)")],
    out_path: Annotated[Path, typer.Argument(help="binary message to write")],
    profile: Annotated[str, typer.Option(help="full, f16, int8 or compact")] = "compact",
    projection: Annotated[
        Path | None, typer.Option(help="fleet projection (.npz); compact fits one if absent")
    ] = None,
) -> None:
    """Encode a map or submap file as one wire message; print bytes per object."""
    from mergesvc.wire import Profile, encode_file

    try:
        stats = encode_file(in_path, out_path, Profile(profile), projection=projection)
    except MergeError as exc:
        _fail(exc)
        return
    except ValueError as exc:
        typer.echo(f"error: {str(exc).splitlines()[0]}", err=True)
        raise typer.Exit(2) from exc
    typer.echo(f"wrote {out_path}: {stats.n_bytes} bytes, {stats.n_objects} objects, "
               f"{stats.bytes_per_object:.1f} bytes/object ({profile})"
               + (f"; projection {stats.projection_path}" if stats.projection_path else ""))


@codec_app.command("decode")
def codec_decode(
    in_path: Annotated[Path, typer.Argument(help="binary message")],
    out_path: Annotated[Path, typer.Argument(help="JSON file to write (the match format)")],
    projection: Annotated[Path | None, typer.Option(help="fleet projection (.npz)")] = None,
) -> None:
    """Decode a wire message back to the JSON file format `mergesvc match` reads."""
    from mergesvc.wire import decode_file

    try:
        env, model = decode_file(in_path, out_path, projection=projection)
    except MergeError as exc:
        _fail(exc)
        return
    n = len(getattr(model, "objects", []) or [])
    typer.echo(f"wrote {out_path}: {env.msg_type.value} from {env.sender}, {env.n_bytes} bytes"
               + (f", {n} objects, {env.n_bytes / n:.1f} bytes/object" if n else ""))


scenario_app = typer.Typer(no_args_is_help=True, help="seeded worlds with ground truth")
app.add_typer(scenario_app, name="scenario")


def _write_scenarios(out_dir: Path, run, cases) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "map.json").write_text(run.map.model_dump_json())
    for name, sc in cases:
        (out_dir / f"{name}.json").write_text(sc.submap.model_dump_json())
        (out_dir / f"{name}.truth.json").write_text(json.dumps(sc.truth_dict(), indent=1))
    typer.echo(
        f"wrote {out_dir}/map.json ({len(run.map.objects)} objects) and {len(cases)} submaps "
        f"with a .truth.json beside each; try: mergesvc match --map {out_dir}/map.json "
        f"--submap {out_dir}/{cases[0][0]}.json" if cases else f"wrote {out_dir}/map.json"
    )


@scenario_app.command("underwater")
def scenario_underwater(
    out_dir: Annotated[Path, typer.Argument(help="folder for map.json and the submaps")],
    run: Annotated[int, typer.Option(help="pool run 1, 2 or 3 (the paper's runs)")] = 1,
    seed: Annotated[int, typer.Option(help="world seed")] = 0,
    size: Annotated[list[int] | None, typer.Option(help="submap sizes (repeat)")] = None,
    per_size: Annotated[int, typer.Option(help="submaps per size")] = 5,
) -> None:
    """A pool run through the tracker: the first half's map, submaps from the second half."""
    from mergesvc.sim import underwater_run

    if run not in (1, 2, 3) or per_size < 1 or any(k < 1 for k in size or []):
        typer.echo("error: --run must be 1, 2 or 3; sizes and --per-size >= 1", err=True)
        raise typer.Exit(2)
    r = underwater_run(run, seed)
    cases = [(f"submap_n{k}_{j}", sc) for k in (size or [2, 3, 4, 5])
             for j, sc in enumerate(r.windows(k, per_size))]
    _write_scenarios(out_dir, r, cases)


@scenario_app.command("drive")
def scenario_drive(
    out_dir: Annotated[Path, typer.Argument(help="folder for map.json and the submaps")],
    seed: Annotated[int, typer.Option(help="world seed")] = 0,
    places: Annotated[int, typer.Option(help="loop-closure places")] = 4,
    size: Annotated[int, typer.Option(help="objects per submap")] = 20,
    trajectory: Annotated[
        Path | None, typer.Option(help="KITTI pose file to drive instead of the street loop")
    ] = None,
) -> None:
    """A KITTI-like drive through the tracker: the map, submaps at loop-closure places."""
    from mergesvc.sim import drive_run

    if trajectory is not None and not trajectory.is_file():
        typer.echo(f"error: trajectory file not found: {trajectory}", err=True)
        raise typer.Exit(2)
    try:
        r = drive_run(seed, trajectory)
    except ValueError as exc:
        typer.echo(f"error: cannot read trajectory {trajectory}: {exc}", err=True)
        raise typer.Exit(2) from exc
    cases = [(f"place{j + 1}", sc) for j, sc in enumerate(r.places(places, size))]
    _write_scenarios(out_dir, r, cases)


unc_app = typer.Typer(no_args_is_help=True, help="the learned image-uncertainty head")
app.add_typer(unc_app, name="uncertainty")


@unc_app.command("train")
def uncertainty_train(
    out: Annotated[Path, typer.Argument(help="weights file to write (.npz)")],
    samples: Annotated[int, typer.Option(help="training observations")] = 20_000,
    seed: Annotated[int, typer.Option(help="world and optimiser seed")] = 0,
    family: Annotated[str, typer.Option(help="underwater or kitti")] = "underwater",
    config: Annotated[Path | None, typer.Option(help="UncertaintyConfig as JSON")] = None,
) -> None:
    """Train the head with the ranking loss on generated observations; report held-out
    Spearman correlation of predicted and true error."""
    import numpy as np

    from mergesvc.sim import Family, image_s_dataset
    from mergesvc.sim.uncertainty import UncertaintyConfig, evaluate, fit

    try:
        cfg = UncertaintyConfig.model_validate_json(config.read_text()) if config else None
        fam = Family(family)
    except (OSError, ValueError) as exc:
        typer.echo(f"error: {str(exc).splitlines()[0]}", err=True)
        raise typer.Exit(2) from exc
    n_test = max(samples // 5, 100)
    y, loss, _ = image_s_dataset(samples + n_test, seed, fam)
    try:
        head, _ = fit(
            y[:samples], loss[:samples], cfg, np.random.default_rng(seed),
            on_epoch=lambda e, m: typer.echo(
                f"epoch {e}: " + ", ".join(f"{k} {v:.4f}" for k, v in m.items()), err=True),
        )
        head.save(out)
    except MergeError as exc:
        _fail(exc)
        return
    res = evaluate(head, y[samples:], loss[samples:])
    typer.echo(f"wrote {out}; held-out ({n_test}): Spearman {res['spearman']:.3f}, "
               f"Kendall {res['kendall']:.3f}, pairwise accuracy {res['accuracy']:.3f}")


@unc_app.command("eval")
def uncertainty_eval(
    weights: Annotated[Path, typer.Argument(help="weights file (.npz)")],
    samples: Annotated[int, typer.Option(help="test observations")] = 5000,
    seed: Annotated[int, typer.Option(help="world seed the head was trained for")] = 0,
    family: Annotated[str, typer.Option(help="underwater or kitti")] = "underwater",
) -> None:
    """Spearman / Kendall / pairwise accuracy of a trained head on fresh observations."""
    from mergesvc.sim import Family, image_s_dataset
    from mergesvc.sim.uncertainty import UncertaintyHead, evaluate

    try:
        head = UncertaintyHead.load(weights)
        # fresh objects of the same world: a new draw, not the training one
        y, loss, _ = image_s_dataset(samples, seed, Family(family))
        res = evaluate(head, y, loss)
    except MergeError as exc:
        _fail(exc)
        return
    except ValueError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    typer.echo(json.dumps(res))


link_app = typer.Typer(no_args_is_help=True, help="the acoustic link simulator")
app.add_typer(link_app, name="link")


@link_app.command("sim")
def link_sim(
    rate: Annotated[list[int] | None, typer.Option(help="modem rate 1, 3 or 5 (repeat)")] = None,
    snr_db: Annotated[list[float] | None, typer.Option(help="SNR in dB (repeat)")] = None,
    bytes_per_submap: Annotated[int, typer.Option(help="uplink message size")] = 1024,
    period_s: Annotated[float, typer.Option(help="one submap per vehicle every ...")] = 60.0,
    duration_s: Annotated[float, typer.Option(help="simulated mission time")] = 1800.0,
    seed: Annotated[int, typer.Option(help="channel seed")] = 0,
) -> None:
    """Simulate 3 vehicles and a topside on a TDMA acoustic link (no network, no waiting)."""
    from mergesvc.link import ModemRate, Workload, format_sweep_table, sweep_link

    try:
        rates = tuple(ModemRate(r) for r in (rate or [1, 3, 5]))
    except ValueError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    wl = Workload(uplink_bytes=bytes_per_submap, period_s=period_s, duration_s=duration_s)
    try:
        rows = sweep_link(rates, snr_db or None, workload=wl, seed=seed)
    except MergeError as exc:
        _fail(exc)
        return
    typer.echo(format_sweep_table(rows))


@link_app.command("bridge")
def link_bridge(
    fleet: Annotated[str, typer.Option(help="fleet name in the key space")] = "fleet0",
    rate: Annotated[int, typer.Option(help="modem rate 1, 3 or 5")] = 5,
    snr_db: Annotated[float, typer.Option(help="mean SNR in dB")] = 6.0,
    time_scale: Annotated[float, typer.Option(help="simulated s per wall s, inverted")] = 1.0,
    vehicles: Annotated[list[str] | None, typer.Option(help="vehicle names (repeat)")] = None,
    mode: Annotated[str | None, typer.Option(help="zenoh mode: peer or client")] = "client",
    connect: Annotated[list[str] | None, typer.Option(help="zenoh endpoint(s)")] = None,
    listen: Annotated[list[str] | None, typer.Option(help="zenoh listen endpoint(s)")] = None,
    config: Annotated[Path | None, typer.Option(help="zenoh JSON5 config file")] = None,
    seconds: Annotated[float | None, typer.Option(help="stop after this long")] = None,
) -> None:
    """Bridge the vehicle side of the key space to the topside through the simulated modem."""

    from mergesvc.link import (
        AcousticBridge,
        ArqConfig,
        ChannelConfig,
        LinkConfig,
        ModemRate,
        SnrModel,
        TdmaConfig,
        make_zenoh_config,
    )
    from mergesvc.wire.keys import fleet_root, uw_root

    names = vehicles or ["auv1", "auv2", "auv3"]
    try:
        cfg = LinkConfig(
            channel=ChannelConfig(rate=ModemRate(rate), snr=SnrModel(mean_db=snr_db)),
            tdma=TdmaConfig(slot_order=["topside", *names]),
            # the topside sends every factor to both robots: room for a burst of them
            arq=ArqConfig(max_queue_messages=64),
        )
        zconf = make_zenoh_config(
            config_file=str(config) if config else None, mode=mode,
            connect=tuple(connect or ("tcp/127.0.0.1:7447",)), listen=tuple(listen or ()),
        )
        with AcousticBridge(cfg, uw_prefix=uw_root(fleet), top_prefix=fleet_root(fleet),
                            zenoh_config=zconf, time_scale=time_scale) as bridge:
            typer.echo(f"bridging {uw_root(fleet)}/** <-> {fleet_root(fleet)}/** "
                       f"(rate {rate}, {snr_db} dB, time scale {time_scale})")
            start = time.monotonic()
            try:
                while seconds is None or time.monotonic() - start < seconds:
                    time.sleep(0.2)
            except KeyboardInterrupt:
                pass
            typer.echo(json.dumps(dataclasses.asdict(bridge.stats()), default=str))
    except MergeError as exc:
        _fail(exc)
    except ValueError as exc:
        typer.echo(f"error: {str(exc).splitlines()[0]}", err=True)
        raise typer.Exit(2) from exc


def _zenoh_conf(mode: str | None, connect: list[str] | None, listen: list[str] | None,
                config: Path | None):
    from mergesvc.link import make_zenoh_config

    return make_zenoh_config(
        config_file=str(config) if config else None, mode=mode, connect=tuple(connect or ()),
        listen=tuple(listen or ()), scouting=config is None,
    )


def _projections(paths: list[Path] | None):
    from mergesvc.wire import Projection

    return [Projection.load(p) for p in paths or []]


@app.command()
def serve(
    fleet: Annotated[str, typer.Option(help="fleet name in the key space")] = "fleet0",
    store: Annotated[Path, typer.Option(help="SQLite file (WAL mode)")] = Path("mergesvc.db"),
    mode: Annotated[str, typer.Option(help="zenoh mode: router, peer or client")] = "router",
    listen: Annotated[list[str] | None, typer.Option(help="zenoh listen endpoint(s)")] = None,
    connect: Annotated[list[str] | None, typer.Option(help="zenoh endpoint(s) to connect")] = None,
    config: Annotated[Path | None, typer.Option(help="zenoh JSON5 config file")] = None,
    projection: Annotated[
        list[Path] | None, typer.Option(help="fleet projection(s) for compact submaps")
    ] = None,
    settings: Annotated[Path | None, typer.Option(help="matching settings JSON")] = None,
    seconds: Annotated[float | None, typer.Option(help="stop after this long")] = None,
) -> None:
    """The merge service: embedded Zenoh router on tcp/127.0.0.1:7447 by default."""
    import signal
    import threading

    import zenoh

    from mergesvc.fleet.service import MergeService, ServiceConfig

    if mode == "router" and not listen and not config:
        listen = ["tcp/127.0.0.1:7447"]
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    try:
        cfg = ServiceConfig(fleet=fleet, store=str(store))
        if settings is not None:
            cfg = cfg.model_copy(update={"match": load_config(settings)})
        zconf = _zenoh_conf(mode, connect, listen, config)
        projections = _projections(projection)
        with zenoh.open(zconf) as session, MergeService(cfg, session, projections) as svc:
            typer.echo(f"merge service for fleet {fleet} on {listen or connect}, store {store}")
            start = time.monotonic()
            while not stop.is_set() and (seconds is None or time.monotonic() - start < seconds):
                stop.wait(0.2)
            typer.echo(json.dumps(svc.status()["submaps"]))
    except MergeError as exc:
        _fail(exc)
    except (ValueError, OSError) as exc:
        typer.echo(f"error: {str(exc).splitlines()[0]}", err=True)
        raise typer.Exit(2) from exc


@app.command()
def agent(
    robot: Annotated[str, typer.Option(help="this vehicle's name")],
    fleet: Annotated[str, typer.Option(help="fleet name in the key space")] = "fleet0",
    session_id: Annotated[str, typer.Option("--session", help="this session's name")] = "s0",
    seed: Annotated[int, typer.Option(help="fleet world seed (scenario input)")] = 0,
    laps: Annotated[int, typer.Option(help="laps of the robot's pattern")] = 2,
    objects: Annotated[int, typer.Option(help="objects in the pool")] = 24,
    log_file: Annotated[
        Path | None, typer.Option("--log", help="replay a recorded observation log instead")
    ] = None,
    profile: Annotated[str, typer.Option(help="codec: full, f16, int8 or compact")] = "int8",
    projection: Annotated[Path | None, typer.Option(help="fleet projection (compact)")] = None,
    time_scale: Annotated[float, typer.Option(help="wall s per simulated s; 0: no pacing")] = 0.0,
    acoustic: Annotated[bool, typer.Option(help="publish on the acoustic vehicle side")] = False,
    mode: Annotated[str, typer.Option(help="zenoh mode")] = "client",
    connect: Annotated[list[str] | None, typer.Option(help="zenoh endpoint(s)")] = None,
    config: Annotated[Path | None, typer.Option(help="zenoh JSON5 config file")] = None,
    linger: Annotated[float, typer.Option(help="s to stay up after the run (factors)")] = 2.0,
) -> None:
    """A vehicle: local map (tracker + ISAM2), submaps out, factors in."""
    import zenoh

    from mergesvc.core.model import Factor
    from mergesvc.fleet.agent import Agent, AgentConfig
    from mergesvc.sim import fleet_world, read_observation_log
    from mergesvc.wire import Profile, decode_message, encode_message

    try:
        prof = Profile(profile)
        proj = _projections([projection] if projection else None)
        if prof is Profile.COMPACT and not proj:
            raise typer.BadParameter("--profile compact needs --projection")
        if log_file is not None:
            frames = read_observation_log(log_file)
        else:
            frames = fleet_world(seed, laps=laps, n_objects=objects).frames(
                robot, int(session_id.lstrip("s") or 0) if session_id[1:].isdigit() else 0)
        acfg = AgentConfig(robot=robot, session=session_id, fleet=fleet)
        root = keys.uw_root(fleet) if acoustic else keys.fleet_root(fleet)
        zconf = _zenoh_conf(mode, connect or ["tcp/127.0.0.1:7447"], None, config)

        def encode(sub, seq):
            return encode_message(sub, prof, robot, seq, projection=proj[0] if proj else None)

        def decode_factor(data: bytes) -> Factor:
            _, f = decode_message(data)
            if not isinstance(f, Factor):
                raise MergeError("not a factor")
            return f

        with zenoh.open(zconf) as session, Agent(
            acfg, session, encode, decode_factor,
            submap_key=f"{root}/submap/{robot}/{session_id}",
            factor_key=f"{root}/factor/{robot}/**", alive_key=f"{root}/alive/{robot}",
        ) as ag:
            stats = ag.run(frames, time_scale=time_scale)
            time.sleep(linger)
            typer.echo(json.dumps({"robot": robot, "frames": stats.frames,
                                   "submaps_sent": stats.submaps_sent,
                                   "bytes_sent": stats.bytes_sent,
                                   "factors_received": stats.factors_received}))
    except MergeError as exc:
        _fail(exc)
    except (ValueError, OSError) as exc:
        typer.echo(f"error: {str(exc).splitlines()[0]}", err=True)
        raise typer.Exit(2) from exc


@app.command()
def demo(
    out: Annotated[Path, typer.Option(help="folder for logs, summary and the figure")] = Path(
        "results/demo"
    ),
    quick: Annotated[bool, typer.Option(help="a smaller mission (under 30 s)")] = False,
    link: Annotated[str, typer.Option(help="zenoh, or acoustic (simulated modem)")] = "zenoh",
    seed: Annotated[int, typer.Option(help="mission seed")] = 0,
    profile: Annotated[str, typer.Option(help="codec profile of the submaps")] = "compact",
) -> None:
    """Service + 3 vehicles as processes on loopback; summary against the ground truth."""
    from mergesvc.fleet.demo import DemoPlan, run_demo
    from mergesvc.wire import Profile

    if link not in ("zenoh", "acoustic"):
        typer.echo("error: --link must be zenoh or acoustic", err=True)
        raise typer.Exit(2)
    try:
        prof = Profile(profile)
    except ValueError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    plan = (DemoPlan.quick if quick else DemoPlan)(seed=seed, link=link, profile=prof)
    res = run_demo(plan, out, echo=typer.echo)
    s = res.summary
    if s:
        typer.echo(f"submaps sent {s['submaps_sent']} ({s['bytes_on_wire']} bytes, "
                   f"{s['bytes_per_submap']:.0f} per submap); processed {s['submaps_processed']}")
        typer.echo(f"factors accepted {s['factors_accepted']}, retracted "
                   f"{s['factors_retracted']}; correspondences right {s['correspondences_right']},"
                   f" wrong {s['correspondences_wrong']} (precision "
                   f"{s['precision'] if s['precision'] is None else round(s['precision'], 3)})")
        for r, a in s["alignment"].items():
            after = ("not aligned" if a["after_m"] is None else
                     f"{a['after_m']:.2f} m / {a['after_deg']:.1f} deg")
            typer.echo(f"  {r} frame in {s['anchor']}: before {a['before_m']:.2f} m / "
                       f"{a['before_deg']:.1f} deg, after {after}")
        typer.echo(f"service latency per submap ms: {s['latency_ms']}; figure {s['figure']}; "
                   f"{s['elapsed_s']} s")
    for f in res.failures:
        typer.echo(f"FAILED: {f}", err=True)
    if not res.ok:
        raise typer.Exit(1)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
