"""`mergesvc bench match|paper|uncertainty|link|generalize|scale|merge|soak|cost|fuzz|qaplib` (see
docs/benchmarks.md).

Every benchmark takes `--settings FILE`: the `match` section is the matching settings each
benchmarked configuration starts from (the benchmark sets its own axes on top), `bench link`
also starts its sweep from the `link` section. The resolved tree is written with the results:
settings.json in an output folder, NAME.settings.json beside an output file NAME.json.
Counts (--repeats, --seeds, --samples) are checked here (at least 1) and again by the
benchmark functions (InputError), so a bad count is one line and exit 2, never a traceback."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from mergesvc.cli.errors import exit_on_error
from mergesvc.cli.options import (
    TrajectoryFile,
    check_trajectory,
    command_group,
    resolve_settings,
    settings_file,
    write_settings_beside,
)
from mergesvc.core.names import NodeAffinity

if TYPE_CHECKING:
    from mergesvc.settings import Settings

app = command_group("benchmarks")

# --settings of each benchmark: what it reads (a bare MatchConfig file is `match` here too)
BenchSettings = settings_file(
    "`match` (every benchmarked configuration starts from it)", bare="MatchConfig"
)
LinkBenchSettings = settings_file(
    "`match` (the base of every configuration) and `link` (the base of the sweep)",
    bare="MatchConfig",
)


@app.command("match")
def bench_match(
    repeats: Annotated[int, typer.Option(min=1, help="runs per scenario")] = 5,
    seeds: Annotated[int, typer.Option(min=1, help="scenarios per family")] = 5,
    paper: Annotated[bool, typer.Option(help="also run paper mode (slow: dense K)")] = True,
    one_thread: Annotated[bool, typer.Option(
        help="verified mode also with the BLAS on one thread, interleaved")] = True,
    fresh: Annotated[int, typer.Option(
        min=0, help="also run verified mode this many times per scenario as the first match "
        "of a new `mergesvc match --json` process (default and one-thread BLAS; 0: not)")] = 1,
    affinity: Annotated[
        list[NodeAffinity] | None,
        typer.Option(help="node affinities to measure (repeat the option); default: all"),
    ] = None,
    peer: Annotated[bool, typer.Option(
        help="also run KISS-Matcher from its own package on the same files, interleaved (the "
        "`peers` extra)")] = False,
    peer_top_k: Annotated[int | None, typer.Option(
        min=1, help="the peer's candidate pairs per submap object, by cosine [default: 1]")
    ] = None,
    peer_noise_m: Annotated[float | None, typer.Option(
        min=1e-3, help="the peer's voxel size, which scales its noise bounds, m [default: 2]")
    ] = None,
    peer_gate_m: Annotated[float | None, typer.Option(
        min=0.0, help="how far from where the peer's transform puts an object its match may "
        "lie, m [default: 6]")] = None,
    out: Annotated[Path | None, typer.Option(help="write the results as JSON here")] = None,
    settings: BenchSettings = None,
) -> None:
    """Latency and accuracy of verified vs paper mode on seeded scenarios."""
    from mergesvc.bench import run_match_bench

    kinds = tuple(a.value for a in (affinity or list(NodeAffinity)))
    with exit_on_error():
        tree = resolve_settings(settings)
        report = run_match_bench(
            repeats=repeats, seeds=seeds, paper=paper, echo=typer.echo, affinities=kinds,
            one_thread=one_thread, fresh=fresh,
            peer=_peer_settings(peer, peer_top_k, peer_noise_m, peer_gate_m),
            base=tree.match,
        )
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(report, indent=1))
        write_settings_beside(tree, out, folder=False)
        typer.echo(f"wrote {out}")


def _peer_settings(peer: bool, top_k: int | None, noise_m: float | None,
                   gate_m: float | None) -> Any:
    """KissSettings with the options given (False without --peer; an option without it is an
    error)."""
    from mergesvc.bench.peers import KissSettings

    given = {k: v for k, v in (("top_k", top_k), ("noise_m", noise_m), ("gate_m", gate_m))
             if v is not None}
    if not peer:
        if given:
            raise typer.BadParameter("the peer's settings need --peer", param_hint="--peer")
        return False
    return dataclasses.replace(KissSettings(), **given)


@app.command("paper")
def bench_paper(
    out: Annotated[Path, typer.Option(help="folder for JSON, markdown and figures")] = Path(
        "results/paper"
    ),
    quick: Annotated[bool, typer.Option(help="a small slice (under a minute)")] = False,
    seed: Annotated[int, typer.Option(help="world seed")] = 0,
    repeats: Annotated[
        int | None, typer.Option(min=1, help="verified-mode timing repeats")
    ] = None,
    kitti_paper: Annotated[
        bool, typer.Option(help="paper mode on the KITTI-like map too (dense K: minutes)")
    ] = True,
    trajectory: TrajectoryFile = None,
    settings: BenchSettings = None,
) -> None:
    """The paper's Table I and II for its pipeline and ours, side by side, plus precision,
    recall, transform errors, stage timings and a scale sweep; figures under --out."""
    from rich.progress import Progress

    from mergesvc.bench import PaperBenchPlan, run_paper_bench

    plan = PaperBenchPlan.quick() if quick else PaperBenchPlan()
    changes: dict[str, object] = {"seed": seed, "kitti_paper": kitti_paper and plan.kitti_paper}
    if repeats is not None:
        changes["repeats"] = repeats
    check_trajectory(trajectory)
    if trajectory is not None:
        changes["trajectory"] = str(trajectory)
    plan = dataclasses.replace(plan, **changes)
    with exit_on_error():
        tree = resolve_settings(settings)
    with Progress(transient=True) as bar:

        def factory(total: int):
            task = bar.add_task("matching", total=total)
            return lambda msg: bar.update(task, advance=1, description=msg[:60])

        with exit_on_error():
            run_paper_bench(plan, out, echo=typer.echo, progress_factory=factory,
                            base=tree.match)
    write_settings_beside(tree, out, folder=True)
    typer.echo(f"wrote {out}/paper_bench.json, paper_bench.md and figures")


@app.command("uncertainty")
def bench_uncertainty(
    out: Annotated[Path, typer.Option(help="folder for the report")] = Path("results"),
    seed: Annotated[int, typer.Option(help="world seed")] = 0,
    samples: Annotated[int, typer.Option(min=1, help="training observations")] = 20_000,
    settings: BenchSettings = None,
) -> None:
    """What the learned uncertainty head changes: Table I accuracy with the simulator's true
    image uncertainty, the head's prediction, and a constant (uncertainty-unaware)."""
    from mergesvc.bench import run_uncertainty_bench

    with exit_on_error():
        tree = resolve_settings(settings)
        run_uncertainty_bench(out, seed=seed, samples=samples, echo=typer.echo,
                              base=tree.match)
    write_settings_beside(tree, out, folder=True)


@app.command("link")
def bench_link(
    out: Annotated[Path | None, typer.Option(help="write the table as JSON here")] = None,
    seeds: Annotated[int, typer.Option(min=1, help="scenarios per profile")] = 5,
    seed: Annotated[int, typer.Option(help="first seed")] = 0,
    period_s: Annotated[float, typer.Option(help="one submap per vehicle every ...")] = 300.0,
    duration_s: Annotated[float, typer.Option(help="simulated mission time")] = 3600.0,
    settings: LinkBenchSettings = None,
) -> None:
    """Codec profile x modem rate x SNR: bytes, airtime, delivery, time to deliver, accuracy."""
    from mergesvc.bench import run_link_bench

    with exit_on_error():
        tree = resolve_settings(settings)
        report = run_link_bench(seeds=seeds, period_s=period_s, duration_s=duration_s,
                                seed=seed, echo=typer.echo, base=tree.match,
                                link_config=tree.link)
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(report, indent=1, default=float))
        write_settings_beside(tree, out, folder=False)
        typer.echo(f"wrote {out}")


@app.command("generalize")
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
    peer: Annotated[bool | None, typer.Option(
        help="also run KISS-Matcher from its own package (the `peers` extra); default: when "
        "it is installed")] = None,
    settings: BenchSettings = None,
) -> None:
    """Generalization matrix: real KITTI-00 / DINO-based worlds and the project's generators
    in camera / ENU / NED / random / mixed frames, embedding dims, map sizes, look-alikes,
    duplicates, range noise, with and without a declared vertical; verified, paper,
    cosine + Hungarian and KISS-Matcher (when installed) side by side; and how often each
    accepts a submap of a place the map lacks (another world's)."""
    from rich.progress import Progress

    from mergesvc.bench import GeneralizePlan, run_generalize

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
        plan.methods = tuple(m for m in plan.methods if not m.startswith("paper"))
    from mergesvc.bench.peers import KISS_METHOD, kiss_available

    if peer or (peer is None and kiss_available()):
        plan.methods = (*plan.methods, KISS_METHOD)
    with exit_on_error():
        tree = resolve_settings(settings)
    with Progress(transient=True) as bar:
        task = bar.add_task("generalize", total=plan.steps())
        with exit_on_error():
            report = run_generalize(
                plan, progress=lambda msg, done: bar.update(task, completed=done,
                                                            description=msg[:60]),
                base=tree.match)
    typer.echo(report["markdown"])
    typer.echo(f"\n{len(plan.cells)} cells x {seeds} seed(s) in {report['elapsed_s']:.0f} s")
    if out is not None:
        _write_report(report, out, tree)


@app.command("scale")
def bench_scale(
    quick: Annotated[bool, typer.Option(help="900- and 5,000-object maps (under a minute)")] = (
        False),
    repeats: Annotated[int, typer.Option(min=1, help="matches per submap and thread mode")] = 5,
    cases: Annotated[int, typer.Option(min=1, help="submaps per size (up to 100 objects)")] = 5,
    seed: Annotated[int, typer.Option(min=0, help="world seed")] = 0,
    map_size: Annotated[list[int] | None, typer.Option(
        "--map-size", min=2, help="only these map sizes of the plan (repeat)")] = None,
    out: Annotated[
        Path | None, typer.Option(help="write the report as JSON here (and .md beside it)")
    ] = None,
    data: Annotated[
        Path | None, typer.Option(help="the shared data folder (default: ../shared/data)")
    ] = None,
    work_dir: Annotated[Path | None, typer.Option(
        help="where the worlds' binary map files are written while they are matched")] = None,
    settings: BenchSettings = None,
) -> None:
    """Cost against map size (1k-1M objects) and submap size (2-10,000 objects): p50/p99
    latency with default BLAS threads and with one, peak RSS, node accuracy, candidate recall
    of the exact top-k (look-alikes apart)."""
    from mergesvc.bench.scale import ScalePlan, run_scale, write_report

    with exit_on_error():
        tree = resolve_settings(settings)
        kw: dict[str, Any] = {"repeats": repeats, "cases": cases, "seed": seed,
                              "config": tree.match.model_dump(mode="json")}
        if data is not None:
            kw["data_dir"] = data
        plan = ScalePlan.quick(**kw) if quick else ScalePlan.full(**kw)
        if map_size:
            unknown = set(map_size) - set(plan.cells)
            if unknown:
                raise typer.BadParameter(f"not in the plan: {sorted(unknown)} (plan: "
                                         f"{sorted(plan.cells)})", param_hint="--map-size")
            plan.cells = {k: v for k, v in plan.cells.items() if k in map_size}
        report = run_scale(plan, echo=typer.echo, work_dir=work_dir, partial=out)
    if out is not None:
        write_report(report, out)
        write_settings_beside(tree, out, folder=False)
        typer.echo(f"wrote {out} and {out.with_suffix('.md')}")


MergeBenchSettings = settings_file(
    "`service` (the merge service), `agent` (the vehicles) and `link` (the base of the "
    "acoustic world's link)"
)


def _write_report(report: dict, out: Path, tree: Settings) -> None:
    """The report as JSON at `out`, its markdown table beside it, and the settings used."""
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=1, default=float))
    out.with_suffix(".md").write_text(report["markdown"] + "\n")
    write_settings_beside(tree, out, folder=False)
    typer.echo(f"wrote {out} and {out.with_suffix('.md')}")


@app.command("merge")
def bench_merge(
    quick: Annotated[bool, typer.Option(help="pool (1 lap) + a short KITTI-00 stretch")] = False,
    seed: Annotated[int, typer.Option(min=0, help="first world seed")] = 0,
    seeds: Annotated[int | None, typer.Option(min=1, help="seeds per world (default 3, quick 1)")
                     ] = None,
    out: Annotated[
        Path | None, typer.Option(help="write the report as JSON here (and .md beside it)")
    ] = None,
    data: Annotated[
        Path | None, typer.Option(help="the shared data folder (default: ../shared/data)")
    ] = None,
    acoustic: Annotated[bool, typer.Option(help="also the pool through the acoustic link")
                        ] = True,
    world: Annotated[list[str] | None, typer.Option(
        help="only these worlds (pool, pool-long, kitti00, kitti00-vo, pool+acoustic, "
             "pool-calib)")] = None,
    scale: Annotated[str | None, typer.Option(
        help="instead: the service's cost per submap at these fleet sizes, e.g. 2,3,5,10,20 "
             "(the pool world, in-process)")] = None,
    figure: Annotated[Path | None, typer.Option(
        help="also plot every robot's merged ATE and its bounds over its odometry ATE here "
             "(.png)")] = None,
    settings: MergeBenchSettings = None,
) -> None:
    """Merged trajectories in-process against the truth: the pool fleet, 3 cars on real
    KITTI-00 stretches, the pool through the acoustic link; per robot ATE odometry vs merged,
    final rotation error, object RMSE; factors accepted, retracted, correct; precision;
    service ms per submap."""
    from mergesvc.bench import MergeBenchPlan, run_merge_bench, run_scale_bench
    from mergesvc.fleet.replay import replay_world

    if data is not None and not data.is_dir():
        raise typer.BadParameter(f"{data} is not a folder", param_hint="--data")
    if scale is not None:
        if figure is not None:
            raise typer.BadParameter("the figure is the merge bench's: leave out --scale",
                                     param_hint="--figure")
        try:
            sizes = [int(x) for x in scale.split(",")]
        except ValueError:
            raise typer.BadParameter(f"{scale!r}: fleet sizes like 2,3,5,10,20",
                                     param_hint="--scale") from None
        with exit_on_error():
            tree = resolve_settings(settings)
            report = run_scale_bench(sizes, replay=replay_world, service=tree.service,
                                     agent=tree.agent_config, seed=seed,
                                     seeds=seeds or (1 if quick else 3),
                                     laps=1 if quick else 2, echo=typer.echo)
        typer.echo(report["markdown"])
        if out is not None:
            _write_report(report, out, tree)
        return
    if quick:
        plan = MergeBenchPlan.quick(seed, seeds or 1, data)
    else:
        plan = MergeBenchPlan(seed=seed, seeds=seeds or 3, data_dir=data)
    plan.acoustic = acoustic
    if world:
        plan.worlds = list(world)
    with exit_on_error():
        tree = resolve_settings(settings)
        report = run_merge_bench(plan, replay=replay_world, service=tree.service,
                                 agent=tree.agent_config, link_config=tree.link,
                                 echo=typer.echo)
    typer.echo(report["markdown"])
    typer.echo(f"{report['elapsed_s']:.0f} s")
    if out is not None:
        _write_report(report, out, tree)
    if figure is not None:
        from mergesvc.bench.merge import plot_merge

        typer.echo(f"wrote {plot_merge(report, figure)}")


SoakSettings = settings_file(
    "`service` (its limits: max_payload_bytes sizes the oversize payloads, submap_rate_hz caps "
    "the robots' rates; the file is passed to the `serve` process)"
)


@app.command("soak")
def bench_soak(
    robots: Annotated[int, typer.Option(min=1, help="robots publishing valid submaps")] = 5,
    minutes: Annotated[float | None, typer.Option(
        min=0.0, help="how long the robots publish (default 2)")] = None,
    seconds: Annotated[float | None, typer.Option(min=0.0, help="... in seconds instead")
                       ] = None,
    hostile: Annotated[float, typer.Option(min=0.0, max=0.95,
                                           help="fraction of all traffic that is hostile")
                       ] = 0.1,
    mismatch_robots: Annotated[int, typer.Option(
        min=0, help="robots whose submaps use another embedding size")] = 1,
    restarts: Annotated[int, typer.Option(min=0, help="kill -9 restarts at random moments")
                        ] = 2,
    seed: Annotated[int, typer.Option(help="seed of the world, rates, payloads and kills")] = 0,
    rate_hz: Annotated[str | None, typer.Option(
        help="each robot's submap rate is drawn uniformly in LO,HI Hz (default 0.2,2); keep "
             "the fleet's sum within what the service processes (20 robots: e.g. 0.05,0.3)")
                       ] = None,
    out: Annotated[Path | None, typer.Option(
        help="write the report as JSON here (the figure as .png beside it, the service's log "
             "as .service.log)")] = None,
    quick: Annotated[bool, typer.Option(
        help="3 robots, 10 s, 1 restart, 1 robot of another model, 20 % hostile (for tests)")
                     ] = False,
    large_objects: Annotated[int | None, typer.Option(
        min=0, help="objects of the one large submap sent at 70 % of the run (a whole map "
                    "relocalized; default 5000, quick 400; 0: none)")] = None,
    settings: SoakSettings = None,
) -> None:
    """A real `mergesvc serve` under N robots publishing at their own rates, hostile payloads,
    robots of another embedding model and kill -9 restarts: throughput, latency and RSS over
    time; valid submaps lost, duplicated, failed and pending at the end. Exit 1 when a target
    is missed."""
    import sys

    from mergesvc.bench import SoakPlan, plot_soak, run_soak, soak_summary

    if minutes is not None and seconds is not None:
        raise typer.BadParameter("give --minutes or --seconds, not both", param_hint="--seconds")
    if quick:
        plan = SoakPlan.quick(seed)
    else:
        plan = SoakPlan(robots=robots, hostile_fraction=hostile,
                        mismatch_robots=mismatch_robots, restarts=restarts, seed=seed)
    if rate_hz is not None:
        try:
            lo, hi = (float(x) for x in rate_hz.split(","))
        except ValueError:
            raise typer.BadParameter(f"{rate_hz!r}: two rates like 0.2,2",
                                     param_hint="--rate-hz") from None
        plan.rate_hz = (lo, hi)
    if large_objects is not None:
        plan.large_objects = large_objects
    if minutes is not None:
        plan.duration_s = minutes * 60.0
    if seconds is not None:
        plan.duration_s = seconds
    with exit_on_error():
        tree = resolve_settings(settings)
        plan.max_payload_bytes = tree.service.max_payload_bytes
        plan.max_rate_hz = tree.service.submap_rate_hz
        log_path = out.with_suffix(".service.log") if out is not None else None
        report = run_soak(plan, serve_command=[sys.executable, "-m", "mergesvc.cli"],
                          serve_args=["--settings", str(settings)] if settings else (),
                          echo=typer.echo, log_path=log_path)
    typer.echo(soak_summary(report))
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(report, indent=1, default=float))
        write_settings_beside(tree, out, folder=False)
        fig = plot_soak(report, out.with_suffix(".png"))
        typer.echo(f"wrote {out}, {fig} and {log_path}")
    if not report["ok"]:
        raise typer.Exit(1)


CostBenchSettings = settings_file(
    "`service` (the merge service: its optimize_interval_s sets the batch) and `agent` (the "
    "vehicles)"
)


@app.command("cost")
def bench_cost(
    quick: Annotated[bool, typer.Option(help="about 150 factors, one run (for tests)")] = False,
    seed: Annotated[int, typer.Option(min=0, help="first world seed")] = 0,
    runs: Annotated[int, typer.Option(min=1, help="seeds (median and spread over runs)")] = 3,
    factors: Annotated[int, typer.Option(
        min=1, help="feed each stream until this many factors are accepted")] = 2000,
    baseline_factors: Annotated[int | None, typer.Option(
        min=1, help="the per_submap baseline (a solve after every submap: quadratic in all) "
                    "only up to this many factors; default: --factors")] = None,
    rate_hz: Annotated[float, typer.Option(
        min=0.0, help="submaps per second reaching the service (the whole fleet): batch = "
                      "rate x service.optimize_interval_s")] = 5.0,
    batch: Annotated[int | None, typer.Option(min=1, help="the batch size directly")] = None,
    robots: Annotated[int, typer.Option(min=2, help="vehicles in the pool")] = 4,
    max_submaps: Annotated[int, typer.Option(min=1, help="at most this many per stream")
                           ] = 4000,
    out: Annotated[Path | None, typer.Option(
        help="write the report as JSON here (and .md beside it)")] = None,
    figure: Annotated[Path | None, typer.Option(
        help="write cost against factors accepted as a PNG here")] = None,
    settings: CostBenchSettings = None,
) -> None:
    """The service's cost per submap against the factors it has accepted (target: flat
    within 2x to 2,000 factors): one seeded pool fleet, session after session, in-process
    through a real MergeService twice: the graph solved once per batch (the worker under a
    backlog) and after every submap (the baseline); median and p90 ms per submap per
    bucket of factors, median [min-max] over runs."""
    from rich.progress import Progress

    from mergesvc.bench.cost import CostBenchPlan, plot_cost, run_cost_bench
    from mergesvc.fleet.agent import build_submaps
    from mergesvc.fleet.service import MergeService

    with exit_on_error():
        tree = resolve_settings(settings)
    if quick:
        plan = CostBenchPlan.quick(seed)
    else:
        plan = CostBenchPlan(seed=seed, runs=runs, robots=robots, target_factors=factors,
                             max_submaps=max_submaps, baseline_factors=baseline_factors,
                             rate_hz=rate_hz, batch=batch)
    plan.optimize_interval_s = tree.service.optimize_interval_s

    def make_service(store: str) -> MergeService:
        # offline: `ingest` in the calling thread, no Zenoh session; the store in the
        # benchmark's temporary folder
        return MergeService(tree.service.model_copy(update={"store": store}), session=None)

    def vehicle(robot: str, session: str, frames: Any) -> list[Any]:
        cfg = tree.agent_config(robot).model_copy(update={"session": session})
        if cfg.up is None:  # the pool's vehicles know gravity (an AHRS): z up
            cfg = cfg.model_copy(update={"up": (0.0, 0.0, 1.0)})
        return build_submaps(cfg, frames)[1]

    with Progress(transient=True) as bar:
        task = bar.add_task("cost", total=2 * plan.runs)
        with exit_on_error():
            report = run_cost_bench(
                make_service, vehicle, plan, echo=typer.echo,
                progress=lambda msg, done: bar.update(task, completed=done,
                                                      description=msg[:60]))
    typer.echo(report["markdown"])
    typer.echo(f"{report['elapsed_s']:.0f} s")
    if out is not None:
        _write_report(report, out, tree)
    if figure is not None:
        typer.echo(f"wrote {plot_cost(report, figure)}")


@app.command("fuzz")
def bench_fuzz(
    inputs: Annotated[int, typer.Option(min=1, help="inputs per target")] = 100_000,
    seed: Annotated[int, typer.Option(help="seed of every mutation")] = 0,
    target: Annotated[str, typer.Option(
        help="wire, link, match, other (codec JSON, TUM, observation log, projection) or all")
                      ] = "all",
    out: Annotated[Path | None, typer.Option(
        help="write the report as JSON here (.md beside it; reproducers in NAME.findings/)")
                   ] = None,
    cli_samples: Annotated[int, typer.Option(
        min=0, help="malformed files (the nastiest first) run through a real `mergesvc match`")
                           ] = 20,
) -> None:
    """Fuzz every decoder of outside input with seeded mutations of valid inputs: each input
    must decode or be refused with an error the CLI prints as one line (exit 2); anything else
    or a hang is a finding. Exit 1 when there is a finding."""
    import sys

    from rich.progress import Progress

    from mergesvc.bench.fuzz import FuzzTarget, run_fuzz

    try:
        kind = FuzzTarget(target)
    except ValueError:
        raise typer.BadParameter(f"{target!r}: one of {', '.join(t.value for t in FuzzTarget)}",
                                 param_hint="--target") from None
    with exit_on_error():
        tree = resolve_settings(None)
    with Progress(transient=True) as bar:

        def factory(name: str, total: int):
            task = bar.add_task(name, total=total)
            return lambda n: bar.update(task, advance=n)

        with exit_on_error():
            report = run_fuzz(inputs, seed, kind, out, cli=[sys.executable, "-m", "mergesvc.cli"],
                              cli_samples=cli_samples,
                              echo=lambda m: bar.console.print(m, soft_wrap=True, highlight=False),
                              progress_factory=factory)
    typer.echo(report["markdown"])
    if out is not None:
        _write_report(report, out, tree)
    if report["findings"] or not all(r["ok"] for r in report.get("cli_check", {}).get(
            "results", [])):
        raise typer.Exit(1)


@app.command("qaplib")
def bench_qaplib(
    instance: Annotated[list[str] | None, typer.Option(
        help="only these instances (repeat the option); default: the 19 proven ones")] = None,
    repeats: Annotated[int, typer.Option(min=1, help="solves per instance")] = 3,
    time_limit: Annotated[float, typer.Option(min=0.0, help="seconds per solve")] = 120.0,
    data: Annotated[
        Path | None, typer.Option(help="the shared data folder (default: ../shared/data)")
    ] = None,
    out: Annotated[Path | None, typer.Option(
        help="write the report as JSON here (and .md beside it)")] = None,
) -> None:
    """The exact solver on QAPLIB instances against their proven optima: score, proof, nodes
    and CPU seconds per instance. Exit 1 when an instance was not solved to its optimum."""
    from mergesvc.bench.qaplib import PROVEN_S, QAPLIB_DIR, run_qaplib_bench

    folder = QAPLIB_DIR if data is None else data / "qaplib"
    with exit_on_error(OSError, ValueError):  # a missing or malformed instance file
        tree = resolve_settings(None)
        report = run_qaplib_bench(instance or tuple(PROVEN_S), repeats=repeats,
                                  time_limit_s=time_limit, folder=folder, echo=typer.echo)
    typer.echo(report["markdown"])
    if out is not None:
        _write_report(report, out, tree)
    if report["failed"]:
        typer.echo(f"not solved to the optimum: {', '.join(report['failed'])}", err=True)
        raise typer.Exit(1)
