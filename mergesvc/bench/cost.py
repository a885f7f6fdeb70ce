"""`mergesvc bench cost`: the merge service's cost per submap against the factors it has
accepted (the target: flat within 2x from the first factor to 2,000 factors).

One seeded stream of submaps (the pool fleet, session after session over the same objects, so
most submaps yield inter-robot factors) is fed in-process to a real MergeService (its store in a
temporary folder, real GTSAM) twice: `per_submap` solves after every submap (the baseline);
`batched` solves once per batch of B = round(rate_hz x optimize_interval_s) submaps, as the
worker does under a backlog. The vehicles' local maps and the service factory are passed in by
the caller (bench may not import fleet). A submap's cost is the wall time of its `ingest`; its
amortized cost adds its share (1/B) of its batch's solves. The method: docs/benchmarks/cost.md.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from mergesvc.bench.scoring import check_count, fmt_median_range, median_range, peak_rss_mb
from mergesvc.core.model import Submap
from mergesvc.core.tracking import Frame
from mergesvc.errors import InputError
from mergesvc.sim.fleet import fleet_world

MODES = ("batched", "per_submap")  # run in this order: batched sets the stream's length
TARGET_RATIO = 2.0  # issue 14: last bucket's median within 2x of the first's


class CostService(Protocol):
    """What the benchmark needs of the service (fleet/service.py MergeService)."""

    stats: Any  # .factors_accepted, .optimizations, .submaps_processed, .latency_ms

    def ingest(self, sub: Submap, *, optimize: bool = True) -> int: ...

    def close(self) -> None: ...


@dataclass
class CostBenchPlan:
    """What is run: `runs` seeds (seed, seed + 1, ...), each stream fed in both modes until
    `target_factors` are accepted (at most `max_submaps` submaps)."""

    seed: int = 0
    runs: int = 3
    robots: int = 4
    laps_per_session: int = 2
    objects: int = 24
    target_factors: int = 2000
    max_submaps: int = 4000
    rate_hz: float = 5.0  # submaps per second reaching the service, the whole fleet
    optimize_interval_s: float = 2.0  # the service's setting
    batch: int | None = None  # B directly (else from rate_hz x optimize_interval_s)
    # per_submap (the baseline: its solves grow with the graph, the whole run is quadratic)
    # stops at this many factors; None: at target_factors
    baseline_factors: int | None = None
    buckets: tuple[int, ...] = (0, 100, 250, 500, 1000, 1500)  # lower edges; the last is open

    @classmethod
    def quick(cls, seed: int = 0) -> CostBenchPlan:
        """About 150 factors, one run: for tests."""
        return cls(seed=seed, runs=1, robots=3, laps_per_session=1, target_factors=150,
                   max_submaps=400, buckets=(0, 50, 100))

    def batch_size(self) -> int:
        """B: submaps per solve in `batched` mode."""
        if self.batch is not None:
            return self.batch
        return max(1, round(self.rate_hz * self.optimize_interval_s))

    def check(self) -> None:
        check_count("runs", self.runs)
        check_count("robots", self.robots, 2)
        check_count("laps per session", self.laps_per_session)
        check_count("target factors", self.target_factors)
        check_count("max submaps", self.max_submaps)
        if self.batch is None and not (self.rate_hz > 0 and self.optimize_interval_s >= 0):
            raise InputError(f"rate_hz must be > 0 and optimize_interval_s >= 0, got "
                             f"{self.rate_hz:g} and {self.optimize_interval_s:g}")
        check_count("batch", self.batch_size())
        if self.baseline_factors is not None:
            check_count("baseline factors", self.baseline_factors)
        if list(self.buckets) != sorted(set(self.buckets)) or self.buckets[0] != 0:
            raise InputError(f"buckets must rise from 0, got {list(self.buckets)}")


BuildSubmaps = Callable[[str, str, Iterable[Frame]], list[Submap]]


class SubmapStream:
    """The seeded stream: session after session of every vehicle of one pool, in time order
    within a session round; sessions are built when first needed and kept (both modes read
    the same submaps)."""

    def __init__(self, plan: CostBenchPlan, seed: int, build: BuildSubmaps) -> None:
        self.robots = tuple(f"auv{i + 1}" for i in range(plan.robots))
        self.world = fleet_world(seed, self.robots, plan.laps_per_session, plan.objects)
        self.build = build
        self.submaps: list[Submap] = []
        self.rounds = 0

    def _next_round(self) -> None:
        k = self.rounds
        subs = []
        for r in self.robots:
            subs += self.build(r, f"s{k}", self.world.frames(r, session=k))
        self.submaps += sorted(subs, key=lambda s: (s.stamp or 0.0, s.robot_id))
        self.rounds += 1

    def __iter__(self) -> Iterator[Submap]:
        i = 0
        while True:
            while i >= len(self.submaps):
                before = len(self.submaps)
                self._next_round()
                if len(self.submaps) == before and self.rounds > 3:
                    return  # the vehicles cut no submaps at all
            yield self.submaps[i]
            i += 1


def _feed(make_service: Callable[[str], CostService], subs: Iterable[Submap], mode: str,
          batch: int, stop_at_factors: int | None, max_submaps: int,
          tick: Callable[[int, int], None]) -> dict[str, Any]:
    """Feed `subs` to a fresh service in `mode`; per submap: factors accepted before it,
    processing and solve ms, and its amortized cost."""
    every = 1 if mode == "per_submap" else batch
    rows: list[dict[str, Any]] = []
    overhead: list[float] = []  # wall - service processing time of submaps that did not solve
    with tempfile.TemporaryDirectory(prefix="mergesvc-cost-") as tmp:
        svc = make_service(str(Path(tmp) / "cost.db"))
        try:
            for i, sub in enumerate(subs):
                # batched stops at a batch's end only: its last solve is counted
                if i >= max_submaps or (stop_at_factors is not None and i % every == 0
                                        and svc.stats.factors_accepted >= stop_at_factors):
                    break
                # the last submap drains the backlog: the worker solves what is left
                due = (i + 1) % every == 0 or i + 1 == max_submaps
                rows.append(_one(svc, sub, due, overhead))
                tick(len(rows), svc.stats.factors_accepted)
            stats = svc.stats
            out = {"factors_accepted": int(stats.factors_accepted),
                   "factors_retracted": int(stats.factors_retracted),
                   "solves": int(stats.optimizations),
                   "submaps": len(rows)}
        finally:
            svc.close()
    # amortized: each submap's processing plus an equal share of its batch's solves
    for start in range(0, len(rows), every):
        group = rows[start:start + every]
        share = sum(r["solve_ms"] for r in group) / len(group)
        for r in group:
            r["amortized_ms"] = r["process_ms"] + share
    # RSS, not tracemalloc: GTSAM allocates in C++, out of tracemalloc's sight
    out.update(rows=rows, peak_rss_mb=peak_rss_mb())
    return out


def _one(svc: CostService, sub: Submap, solve: bool, overhead: list[float]) -> dict[str, Any]:
    """One submap through `ingest`, timed; a solve is attributed as described in the module
    docstring."""
    factors0, solves0 = svc.stats.factors_accepted, svc.stats.optimizations
    matched0 = svc.stats.factors_matched
    n0 = svc.stats.submaps_processed
    t0 = time.perf_counter()
    svc.ingest(sub, optimize=solve)
    wall_ms = (time.perf_counter() - t0) * 1e3
    service_ms = float(svc.stats.latency_ms[-1]) if svc.stats.submaps_processed > n0 else 0.0
    solved = svc.stats.optimizations > solves0
    solve_ms = 0.0
    if solved:
        extra = float(np.median(overhead)) if overhead else 0.0
        solve_ms = max(0.0, wall_ms - service_ms - extra)
    else:
        overhead.append(wall_ms - service_ms)
    return {"factors_before": int(factors0),
            "factors_added": int(svc.stats.factors_accepted - factors0),
            "factors_matched": int(svc.stats.factors_matched - matched0),
            "process_ms": wall_ms - solve_ms, "solve_ms": solve_ms, "solved": solved,
            "robot": sub.robot_id, "session": sub.session_id, "seq": sub.seq}


def _bucket_rows(rows: list[dict[str, Any]], edges: tuple[int, ...]) -> list[dict[str, Any]]:
    """Per bucket of factors accepted before the submap: n, median and p90 of the amortized
    cost, median processing, mean solve share."""
    out = []
    for j, lo in enumerate(edges):
        hi = edges[j + 1] if j + 1 < len(edges) else None
        sel = [r for r in rows
               if r["factors_before"] >= lo and (hi is None or r["factors_before"] < hi)]
        a = np.asarray([r["amortized_ms"] for r in sel], dtype=np.float64)
        out.append({
            "bucket": _bucket_name(lo, hi), "n": len(sel),
            "median_ms": float(np.median(a)) if a.size else float("nan"),
            "p90_ms": float(np.percentile(a, 90)) if a.size else float("nan"),
            "process_median_ms": float(np.median([r["process_ms"] for r in sel]))
            if sel else float("nan"),
            "solve_share_mean_ms": float(np.mean(a) - np.mean([r["process_ms"] for r in sel]))
            if sel else float("nan"),
        })
    return out


def _bucket_name(lo: int, hi: int | None) -> str:
    return f"{lo}-{hi}" if hi is not None else f"{lo}+"


def _ratio(buckets: list[dict[str, Any]]) -> float:
    """Median of the last non-empty bucket over the first's."""
    full = [b for b in buckets if b["n"]]
    if len(full) < 2 or not full[0]["median_ms"] > 0:
        return float("nan")
    return full[-1]["median_ms"] / full[0]["median_ms"]


def run_cost_bench(
    make_service: Callable[[str], CostService],
    build_submaps: BuildSubmaps,
    plan: CostBenchPlan | None = None,
    *,
    progress: Callable[[str, float], Any] | None = None,
    echo: Callable[[str], Any] = print,
) -> dict[str, Any]:
    """Every run: its stream through `make_service(store_path)` in `batched` mode until
    plan.target_factors are accepted (or plan.max_submaps; whole batches), then the same
    submaps in `per_submap` mode (up to plan.baseline_factors, if set).
    `build_submaps(robot, session, frames)` is a vehicle's local map: the submaps it sends.
    progress(message, mode-runs done) as it goes (of plan.runs x 2). Returns {"plan",
    "batch", "runs", "summary", "verdict", "markdown", "elapsed_s"}."""
    plan = plan or CostBenchPlan()
    plan.check()
    B = plan.batch_size()
    t_start = time.monotonic()
    runs = []
    for k, seed in enumerate(range(plan.seed, plan.seed + plan.runs)):
        stream = SubmapStream(plan, seed, build_submaps)
        run: dict[str, Any] = {"seed": seed}
        n_subs = plan.max_submaps
        for m, mode in enumerate(MODES):
            first = mode == MODES[0]
            stop = plan.target_factors if first else (plan.baseline_factors
                                                      or plan.target_factors)
            tick = _ticker(progress, f"seed {seed} {mode}", 2 * k + m, stop,
                           plan.max_submaps if first else n_subs)
            t0 = time.monotonic()
            res = _feed(make_service, stream, mode, B, stop,
                        plan.max_submaps if first else n_subs, tick)
            if first:
                n_subs = res["submaps"]
            res["buckets"] = _bucket_rows(res["rows"], plan.buckets)
            res["ratio_last_first"] = _ratio(res["buckets"])
            res["elapsed_s"] = round(time.monotonic() - t0, 1)
            run[mode] = res
            echo(f"seed {seed} {mode}: {res['submaps']} submaps, {res['factors_accepted']} "
                 f"factors, {res['solves']} solves, last/first bucket "
                 f"{res['ratio_last_first']:.2f}, {res['elapsed_s']:.0f} s")
        run["sessions"] = stream.rounds * plan.robots
        runs.append(run)
    summary = _summarize(runs, plan)
    report = {"plan": asdict(plan), "batch": B, "runs": runs, "summary": summary,
              "verdict": _verdict(runs, plan), "elapsed_s": round(time.monotonic() - t_start, 1)}
    report["markdown"] = markdown(report)
    return report


def _ticker(progress: Callable[[str, float], Any] | None, label: str, done: int,
            target_factors: int | None, n_submaps: int) -> Callable[[int, int], None]:
    """progress(message, mode-runs done) every 10 submaps of one mode-run."""

    def tick(i: int, factors: int) -> None:
        if progress is not None and i % 10 == 0:
            frac = (factors / target_factors if target_factors is not None
                    else i / max(n_submaps, 1))
            progress(f"{label}: {i} submaps, {factors} factors", done + min(frac, 1.0))

    return tick


def _summarize(runs: list[dict[str, Any]], plan: CostBenchPlan) -> dict[str, Any]:
    """Per mode and bucket: median [min-max] over runs of the bucket's median and p90."""
    out: dict[str, Any] = {}
    for mode in MODES:
        rows = []
        for j in range(len(plan.buckets)):
            per = [r[mode]["buckets"][j] for r in runs]
            rows.append({"bucket": per[0]["bucket"],
                         "n": median_range([b["n"] for b in per]),
                         "median_ms": median_range([b["median_ms"] for b in per]),
                         "p90_ms": median_range([b["p90_ms"] for b in per]),
                         "process_median_ms": median_range(
                             [b["process_median_ms"] for b in per]),
                         "solve_share_mean_ms": median_range([b["solve_share_mean_ms"]
                                                         for b in per])})
        out[mode] = {"buckets": rows,
                     "ratio_last_first": median_range(
                         [r[mode]["ratio_last_first"] for r in runs]),
                     "factors_accepted": median_range(
                         [r[mode]["factors_accepted"] for r in runs]),
                     "submaps": median_range([r[mode]["submaps"] for r in runs]),
                     "solves": median_range([r[mode]["solves"] for r in runs]),
                     "peak_rss_mb": median_range([r[mode]["peak_rss_mb"] for r in runs])}
    return out


def _verdict(runs: list[dict[str, Any]], plan: CostBenchPlan) -> dict[str, Any]:
    """Issue 14's target per mode: the last bucket's median within 2x of the first's in every
    run, with the target's factor count reached."""
    out = {}
    for mode in MODES:
        ratios = [r[mode]["ratio_last_first"] for r in runs]
        goal = plan.target_factors if mode == MODES[0] else (plan.baseline_factors
                                                               or plan.target_factors)
        reached = all(r[mode]["factors_accepted"] >= goal for r in runs)
        out[mode] = {"met": reached and all(np.isfinite(x) and x <= TARGET_RATIO
                                            for x in ratios),
                     "worst_ratio": max((x for x in ratios if np.isfinite(x)),
                                        default=float("nan")),
                     "factors_goal": goal, "target_factors_reached": reached}
    return out


def markdown(report: dict[str, Any]) -> str:
    """Per bucket of accepted factors: both modes' median and p90 ms per submap (amortized),
    median [min-max] over runs; the ratios and the verdict."""
    s = report["summary"]
    lines = ["| factors accepted | submaps per run batched (per_submap) | per_submap median ms "
             "| per_submap p90 | batched median ms | batched p90 | batched solve share ms "
             "(mean) |", "|" + "---|" * 7]
    fm = fmt_median_range
    for a, b in zip(s["per_submap"]["buckets"], s["batched"]["buckets"], strict=True):
        lines.append(f"| {a['bucket']} | {fm(b['n'], 0)} ({fm(a['n'], 0)}) | "
                     f"{fm(a['median_ms'], 1)} | {fm(a['p90_ms'], 1)} | "
                     f"{fm(b['median_ms'], 1)} | {fm(b['p90_ms'], 1)} | "
                     f"{fm(b['solve_share_mean_ms'], 1)} |")
    lines.append("")
    B = report["batch"]
    for mode in MODES:
        m, v = s[mode], report["verdict"][mode]
        lines.append(
            f"- {mode}{f' (B = {B})' if mode == 'batched' else ''}: last / first bucket "
            f"{fm(m['ratio_last_first'], 2)}; {fm(m['submaps'], 0)} submaps, "
            f"{fm(m['factors_accepted'], 0)} factors, {fm(m['solves'], 0)} solves; peak "
            f"RSS {fm(m['peak_rss_mb'], 0)} MB; target (<= {TARGET_RATIO:g}x) "
            f"{'met' if v['met'] else 'NOT met'} (worst {v['worst_ratio']:.2f}"
            f"{'' if v['target_factors_reached'] else ', factor goal not reached'}; "
            f"run to {v['factors_goal']} factors)")
    return "\n".join(lines)


def plot_cost(report: dict[str, Any], path: Path, window: int = 51) -> Path:
    """Amortized ms per submap (y, log) against factors accepted (x): every submap of every
    run faint, a running median (`window` submaps) per run and mode."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mergesvc.bench.figures import save_figure

    colors = {"per_submap": "tab:red", "batched": "tab:blue"}
    fig, ax = plt.subplots(figsize=(7, 4.2), dpi=110)
    for mode in MODES:
        for k, run in enumerate(report["runs"]):
            rows = run[mode]["rows"]
            x = np.asarray([r["factors_before"] for r in rows], dtype=np.float64)
            y = np.asarray([r["amortized_ms"] for r in rows], dtype=np.float64)
            ax.scatter(x, y, s=3, alpha=0.12, color=colors[mode], lw=0)
            if len(y) >= window:
                med = np.asarray([np.median(y[max(0, i - window // 2):i + window // 2 + 1])
                                  for i in range(len(y))])
                label = (f"{mode}" + (f" (B = {report['batch']})" if mode == "batched" else "")
                         if k == 0 else None)
                ax.plot(x, med, color=colors[mode], lw=1.4, label=label)
    ax.set_yscale("log")
    ax.set_xlabel("factors accepted")
    ax.set_ylabel("ms per submap (amortized)")
    ax.grid(alpha=0.3, which="both")
    n = len(report["runs"])
    ax.set_title(f"service cost per submap, {n} run{'s' if n > 1 else ''} "
                 f"(running median of {window} submaps)")
    ax.legend(fontsize=8)
    return save_figure(fig, path)


__all__ = ["MODES", "CostBenchPlan", "CostService", "SubmapStream", "markdown", "plot_cost",
           "run_cost_bench"]
