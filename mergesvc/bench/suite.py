"""Benchmark harness: latency (median and spread over repeats) and accuracy of `verified`
vs `paper` mode, measured side by side in the same run on seeded scenarios.
"""

from __future__ import annotations

import json
import platform
import time
import tracemalloc
from collections.abc import Callable
from dataclasses import dataclass, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from mergesvc.core.config import MatchConfig, load_config
from mergesvc.core.model import ObjectArrays, ObjectMap
from mergesvc.core.pipeline import MatchOutcome, match
from mergesvc.sim import Family, Scenario, make_scenario


def score_case(sc: Scenario, outcome: MatchOutcome) -> dict[str, float]:
    """The paper's node accuracy (right matches / submap objects that have a true match), and
    beyond it: precision and recall of the accepted correspondences, outliers left unmatched,
    the transform's error against the truth."""
    got = {m.submap_object: m.map_object for m in outcome.result.matches}
    matchable = [s for s, m in sc.truth.items() if m is not None]
    outliers = [s for s, m in sc.truth.items() if m is None]
    right = sum(sc.is_correct(s, got[s]) for s in got)
    accepted = bool(outcome.result.accepted)
    out = {
        "accuracy": sum(s in got and sc.is_correct(s, got[s]) for s in matchable)
        / max(len(matchable), 1),
        "accepted": float(accepted),
        "returned": float(len(got)),
        "right": float(right),
        "wrong": float(len(got) - right),
        "acc_returned": float(len(got)) if accepted else 0.0,
        "acc_right": float(right) if accepted else 0.0,
        "matchable": float(len(matchable)),
        "outliers": float(len(outliers)),
        "outliers_unmatched": float(sum(s not in got for s in outliers)),
        "rot_err_deg": float("nan"),
        "trans_err_m": float("nan"),
    }
    t = outcome.result.transform
    if accepted and t is not None:
        w, x, y, z = t.quaternion_wxyz
        R_est = Rotation.from_quat([x, y, z, w]).as_matrix()
        dR = R_est.T @ sc.R_map_submap
        out["rot_err_deg"] = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
        out["trans_err_m"] = float(np.linalg.norm(np.asarray(t.translation) - sc.t_map_submap))
    return out


def _spread(values: list[float]) -> dict[str, float]:
    a = np.asarray(values)
    q1, med, q3 = np.percentile(a, [25, 50, 75])
    return {"median": float(med), "iqr": float(q3 - q1), "min": float(a.min()),
            "max": float(a.max())}


def run_case(
    sc: Scenario, config: MatchConfig, repeats: int
) -> tuple[dict[str, float], list[float], dict[str, list[float]]]:
    """Run one scenario `repeats` times; (scores of the first run, totals ms, stage ms)."""
    totals, stages = [], {}
    scores = None
    for _ in range(repeats):
        outcome = match(sc.map, sc.submap, config)
        if scores is None:
            scores = score_case(sc, outcome)
        for k, v in outcome.result.timings_ms.items():
            stages.setdefault(k, []).append(v)
        totals.append(outcome.result.timings_ms["total"])
    assert scores is not None
    return scores, totals, stages


def _modes(paper: bool, affinity: str) -> list[tuple[str, MatchConfig, bool]]:
    """(label, settings, runs once) of the modes measured for one affinity."""
    aff = {"affinity": {"kind": affinity}}
    modes = [("verified", load_config(mode="verified", **aff), False)]
    if paper:
        modes.append(("paper", load_config(mode="paper", **aff), True))
        if affinity != "ucos":  # the authors' code: the distance fed in as the affinity
            raw = {"affinity": {"kind": affinity, "raw_distances": True}}
            modes.append(("paper-raw", load_config(mode="paper", **raw), True))
    return modes


def bench_scenario(family: Family, seed: int) -> Scenario:
    """The benchmark's scenario: underwater submaps cycle through the paper's 2-5 objects."""
    if family is Family.UNDERWATER:
        return make_scenario(family, seed, n_sub=2 + seed % 4)
    return make_scenario(family, seed)


def run_match_bench(
    repeats: int = 5,
    seeds: int = 5,
    paper: bool = True,
    echo: Callable[[str], Any] = print,
    families: tuple[Family, ...] = (Family.KITTI, Family.UNDERWATER),
    affinities: tuple[str, ...] = ("ucos",),
) -> dict[str, Any]:
    """Both modes on `seeds` scenarios per family and affinity. Paper mode runs once per
    scenario (it takes seconds); verified mode `repeats` times. Returns a JSON-ready report
    (results keyed family/mode/affinity) and echoes a table."""
    report: dict[str, Any] = {
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": f"{platform.machine()} {platform.processor() or ''} "
        f"{_cpu_count()} cores, python {platform.python_version()}",
        "settings": {},
        "results": {},
    }
    start = time.perf_counter()
    scenarios = {(f, s): bench_scenario(f, s) for f in families for s in range(seeds)}
    for family in families:
        for affinity in affinities:
            for name, cfg, once in _modes(paper, affinity):
                report["settings"][f"{name}/{affinity}"] = cfg.model_dump(mode="json")
                rows, totals, stages = [], [], {}
                for seed in range(seeds):
                    sc = scenarios[family, seed]
                    run_cfg = cfg
                    if name.startswith("paper"):  # the paper's radius for this kind of world
                        run_cfg = cfg.model_copy(deep=True)
                        run_cfg.affinity.edge_radius_m = sc.paper_radius_m
                    scores, t, st = run_case(sc, run_cfg, 1 if once else repeats)
                    rows.append(scores)
                    totals += t
                    for k, v in st.items():
                        stages.setdefault(k, []).extend(v)
                    echo(
                        f"[{time.perf_counter() - start:6.1f}s] {family.value:>10} {name:>9} "
                        f"{affinity:>13} seed {seed}: {len(sc.submap.objects)} vs "
                        f"{len(sc.map.objects)} objects, acc {scores['accuracy']:.2f}, "
                        f"wrong {scores['wrong']}, {np.median(t):.1f} ms"
                    )
                report["results"][f"{family.value}/{name}/{affinity}"] = _summary(
                    rows, totals, stages
                )
    echo("")
    echo(markdown_table(report))
    return report


def _summary(
    rows: list[dict[str, float]], totals: list[float], stages: dict[str, list[float]]
) -> dict[str, Any]:
    return {
        "node_accuracy": float(np.mean([r["accuracy"] for r in rows])),
        "wrong_matches": int(sum(r["wrong"] for r in rows)),
        "returned_matches": int(sum(r["returned"] for r in rows)),
        "wrong_in_accepted": int(sum(r["wrong"] for r in rows if r["accepted"])),
        "accepted": int(sum(r["accepted"] for r in rows)),
        "scenarios": len(rows),
        "outliers_unmatched": f"{sum(r['outliers_unmatched'] for r in rows)}/"
        f"{sum(r['outliers'] for r in rows)}",
        "latency_ms": _spread(totals),
        "stages_ms": {k: _spread(v)["median"] for k, v in stages.items()},
        "runs": len(totals),
    }


def markdown_table(report: dict[str, Any]) -> str:
    lines = [
        "| scenario / mode / affinity | node accuracy | wrong matches (in accepted) | accepted "
        "| outliers left unmatched | latency median ms (IQR) [min-max] | runs |",
        "|---|---|---|---|---|---|---|",
    ]
    for key, r in report["results"].items():
        lat = r["latency_ms"]
        lines.append(
            f"| {key} | {r['node_accuracy']:.3f} | {r['wrong_matches']} "
            f"({r['wrong_in_accepted']}) | {r['accepted']}/{r['scenarios']} | "
            f"{r['outliers_unmatched']} | "
            f"{lat['median']:.1f} ({lat['iqr']:.1f}) [{lat['min']:.1f}-{lat['max']:.1f}] | "
            f"{r['runs']} |"
        )
    return "\n".join(lines)


def _cpu_count() -> int:
    import os

    return os.cpu_count() or 0


# ============================================================================================
# The paper's tables (Singh & Leonard, Table I underwater, Table II KITTI), both modes side by
# side, on trajectory runs (scenario.underwater_run / drive_run), plus a scale sweep.
# ============================================================================================

SOLVERS = ("rrwm", "sm", "ipfp")
AFFINITIES = ("ucos", "bhattacharyya", "mahalanobis")
MODES = ("paper", "verified")


@dataclass(frozen=True)
class PaperBenchPlan:
    """What `mergesvc bench paper` runs. `quick` is a slice for the tests (under a minute)."""

    runs: tuple[int, ...] = (1, 2, 3)
    sizes: tuple[int, ...] = (2, 3, 4, 5)
    per_size: int = 5  # submaps per (run, size): the windows where drift is largest
    places: int = 4  # KITTI-like loop-closure places
    place_size: int = 20
    solvers: tuple[str, ...] = SOLVERS
    affinities: tuple[str, ...] = AFFINITIES
    modes: tuple[str, ...] = MODES
    repeats: int = 3  # verified-mode timing repeats per case (paper mode runs once)
    seed: int = 0
    kitti: bool = True
    kitti_paper: bool = True  # paper mode on KITTI is a dense 20 x ~600 K: seconds per solve
    scale_sizes: tuple[int, ...] = (600, 10_000, 100_000)
    trajectory: str | None = None

    @classmethod
    def quick(cls) -> PaperBenchPlan:
        return cls(
            runs=(1,), sizes=(3, 5), per_size=2, places=1, solvers=("rrwm",),
            affinities=("ucos",), repeats=1, kitti_paper=False, scale_sizes=(600, 2000),
        )


def _aggregate(rows: list[dict[str, float]]) -> dict[str, float]:
    acc_returned = sum(r["acc_returned"] for r in rows)
    matchable = sum(r["matchable"] for r in rows)
    rot = [r["rot_err_deg"] for r in rows if np.isfinite(r["rot_err_deg"])]
    trans = [r["trans_err_m"] for r in rows if np.isfinite(r["trans_err_m"])]
    return {
        "node_accuracy": float(np.mean([r["accuracy"] for r in rows])) if rows else float("nan"),
        "cases": len(rows),
        "accepted": int(sum(r["accepted"] for r in rows)),
        "precision": sum(r["acc_right"] for r in rows) / acc_returned if acc_returned else 1.0,
        "recall": sum(r["acc_right"] for r in rows) / matchable if matchable else float("nan"),
        "wrong_returned": int(sum(r["wrong"] for r in rows)),
        "wrong_accepted": int(sum(r["acc_returned"] - r["acc_right"] for r in rows)),
        "outliers_unmatched": f"{int(sum(r['outliers_unmatched'] for r in rows))}/"
        f"{int(sum(r['outliers'] for r in rows))}",
        "rot_err_deg_median": float(np.median(rot)) if rot else float("nan"),
        "trans_err_m_median": float(np.median(trans)) if trans else float("nan"),
    }


def _config(mode: str, solver: str, affinity: str, radius_m: float) -> MatchConfig:
    cfg = load_config(mode=mode, solver={"name": solver}, affinity={"kind": affinity})
    if mode == "paper":
        cfg.affinity.edge_radius_m = radius_m  # the paper's radius for this kind of world
    return cfg


def _run_cases(
    cases: list[tuple[str, Scenario]],
    plan: PaperBenchPlan,
    modes: tuple[str, ...],
    progress: Callable[[str], None],
) -> tuple[dict[str, list[dict[str, float]]], dict[str, dict[str, list[float]]],
           dict[str, MatchOutcome]]:
    """Every case x mode x solver x affinity. Returns per-combination case scores (key
    mode/solver/affinity/case), stage timings per mode, and the outcomes of the first case
    (for the figures)."""
    scores: dict[str, list[dict[str, float]]] = {}
    stages: dict[str, dict[str, list[float]]] = {}
    first: dict[str, MatchOutcome] = {}
    for label, sc in cases:
        for mode in modes:
            for solver in plan.solvers:
                for affinity in plan.affinities:
                    cfg = _config(mode, solver, affinity, sc.paper_radius_m)
                    reps = plan.repeats if mode == "verified" else 1
                    outcome = None
                    for _ in range(reps):
                        outcome = match(sc.map, sc.submap, cfg)
                        for k, v in outcome.result.timings_ms.items():
                            stages.setdefault(mode, {}).setdefault(k, []).append(v)
                    assert outcome is not None
                    key = f"{mode}/{solver}/{affinity}"
                    scores.setdefault(f"{key}/{label}", []).append(score_case(sc, outcome))
                    first.setdefault(f"{key}/{label}", outcome)
                    progress(f"{label} {key}")
    return scores, stages, first


def run_paper_bench(
    plan: PaperBenchPlan,
    out_dir: Path,
    echo: Callable[[str], Any] = print,
    progress_factory: Callable[[int], Callable[[str], None]] | None = None,
) -> dict[str, Any]:
    """Table I (underwater runs x submap sizes) and Table II (KITTI-like places), for the
    paper's pipeline and ours, each solver and affinity; a scale sweep; JSON, markdown and
    figures under out_dir. Returns the report."""
    from mergesvc.bench.figures import plot_accuracy_vs_size, plot_correspondences
    from mergesvc.sim import drive_run, underwater_run

    out_dir.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    uw_cases: list[tuple[str, Scenario]] = []
    uw_runs = {}
    for r in plan.runs:
        run = underwater_run(r, plan.seed)
        uw_runs[r] = run
        for size in plan.sizes:
            for k, sc in enumerate(run.windows(size, plan.per_size)):
                uw_cases.append((f"run{r}/n{size}/{k}", sc))
    kitti_cases: list[tuple[str, Scenario]] = []
    drive = None
    if plan.kitti:
        drive = drive_run(plan.seed, plan.trajectory)
        for k, sc in enumerate(drive.places(plan.places, plan.place_size)):
            kitti_cases.append((f"place{k + 1}", sc))
    echo(f"scenarios built in {time.perf_counter() - start:.1f} s: {len(uw_cases)} underwater "
         f"submaps, {len(kitti_cases)} KITTI-like places"
         + (f" ({len(drive.map.objects)}-object map)" if drive else ""))
    combos = len(plan.solvers) * len(plan.affinities)
    total = (len(uw_cases) * len(plan.modes)
             + len(kitti_cases) * (len(plan.modes) if plan.kitti_paper else 1)) * combos
    progress = progress_factory(total) if progress_factory else (lambda _msg: None)
    uw_scores, uw_stages, uw_first = _run_cases(uw_cases, plan, plan.modes, progress)
    k_modes = plan.modes if plan.kitti_paper else tuple(m for m in plan.modes if m != "paper")
    k_scores, k_stages, k_first = _run_cases(kitti_cases, plan, k_modes, progress)

    report: dict[str, Any] = {
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": f"{platform.machine()} {_cpu_count()} cores, python "
        f"{platform.python_version()}",
        "plan": {k: list(v) if isinstance(v, tuple) else v for k, v in plan.__dict__.items()},
        "settings": load_config().model_dump(mode="json"),
        "table1": _table1(uw_scores, plan, plan.modes),
        "table2": _table2(k_scores, plan, k_modes, [c[0] for c in kitti_cases]),
        "stages_ms": {
            world: {m: {k: _spread(v) for k, v in st.items()} for m, st in stages.items()}
            for world, stages in (("underwater", uw_stages), ("kitti", k_stages))
        },
    }
    report["summary"] = {
        "underwater": {
            f"{mode}/{s}/{a}": _aggregate([x for key, v in uw_scores.items()
                                           if key.startswith(f"{mode}/{s}/{a}/") for x in v])
            for mode in plan.modes for s in plan.solvers for a in plan.affinities
        },
        "kitti": {
            f"{mode}/{s}/{a}": _aggregate([x for key, v in k_scores.items()
                                           if key.startswith(f"{mode}/{s}/{a}/") for x in v])
            for mode in k_modes for s in plan.solvers for a in plan.affinities
        },
    }
    if plan.scale_sizes and drive is not None and kitti_cases:
        report["scale"] = run_scale_sweep(kitti_cases[0][1], plan.scale_sizes, plan.repeats,
                                          plan.seed, echo)
    # figures: accuracy vs size per mode (first solver, each affinity), a correspondence view
    figs = {}
    series = {}
    for mode in plan.modes:
        for a in plan.affinities:
            s0 = plan.solvers[0]
            series[f"{mode} {s0}/{a}"] = {
                size: float(np.mean([x["accuracy"] for key, v in uw_scores.items()
                                     if key.startswith(f"{mode}/{s0}/{a}/") and
                                     f"/n{size}/" in key for x in v] or [np.nan]))
                for size in plan.sizes
            }
    figs["accuracy_vs_size"] = str(plot_accuracy_vs_size(
        series, out_dir / "accuracy_vs_size.png", "underwater runs: node accuracy",
        plan.sizes).name)
    s0, a0 = plan.solvers[0], plan.affinities[0]
    if kitti_cases:
        label, sc = kitti_cases[0]
        for mode in k_modes:
            key = f"{mode}/{s0}/{a0}/{label}"
            traj = drive.poses_est[:, :2, 3] if drive is not None else None
            figs[f"kitti_{mode}"] = str(plot_correspondences(
                sc, k_first[key], out_dir / f"kitti_{label}_{mode}.png",
                f"KITTI-like {label}, {mode} ({s0}/{a0})", traj).name)
    if uw_cases:
        label, sc = max(uw_cases, key=lambda c: len(c[1].submap.objects))
        for mode in plan.modes:
            key = f"{mode}/{s0}/{a0}/{label}"
            figs[f"underwater_{mode}"] = str(plot_correspondences(
                sc, uw_first[key], out_dir / f"underwater_{label.replace('/', '_')}_{mode}.png",
                f"underwater {label}, {mode} ({s0}/{a0})").name)
    report["figures"] = figs
    report["elapsed_s"] = round(time.perf_counter() - start, 1)
    md = paper_markdown(report, plan)
    (out_dir / "paper_bench.json").write_text(json.dumps(report, indent=1, default=float))
    (out_dir / "paper_bench.md").write_text(md)
    echo(md)
    return report


def _table1(scores: dict[str, list[dict[str, float]]], plan: PaperBenchPlan,
            modes: tuple[str, ...]) -> dict[str, dict[str, float]]:
    """{mode/solver/affinity: {"run{r}/n{size}": accuracy, ..., "average": a}}."""
    out: dict[str, dict[str, float]] = {}
    for mode in modes:
        for s in plan.solvers:
            for a in plan.affinities:
                row: dict[str, float] = {}
                for r in plan.runs:
                    for size in plan.sizes:
                        xs = [x["accuracy"] for key, v in scores.items()
                              if key.startswith(f"{mode}/{s}/{a}/run{r}/n{size}/") for x in v]
                        if xs:
                            row[f"run{r}/n{size}"] = float(np.mean(xs))
                row["average"] = float(np.mean(list(row.values()))) if row else float("nan")
                out[f"{mode}/{s}/{a}"] = row
    return out


def _table2(scores: dict[str, list[dict[str, float]]], plan: PaperBenchPlan,
            modes: tuple[str, ...], places: list[str]) -> dict[str, dict[str, float]]:
    out: dict[str, dict[str, float]] = {}
    for mode in modes:
        for s in plan.solvers:
            for a in plan.affinities:
                row = {p: float(np.mean([x["accuracy"] for x in scores[f"{mode}/{s}/{a}/{p}"]]))
                       for p in places if f"{mode}/{s}/{a}/{p}" in scores}
                row["average"] = float(np.mean(list(row.values()))) if row else float("nan")
                out[f"{mode}/{s}/{a}"] = row
    return out


def _fmt(x: float) -> str:
    return "-" if x is None or not np.isfinite(x) else f"{x:.2f}"


def paper_markdown(report: dict[str, Any], plan: PaperBenchPlan) -> str:
    """The report as markdown: Table I and II layouts per mode, then the rest."""
    lines = [f"Run {report['date']} on {report['machine']}; {report.get('elapsed_s', '?')} s.", ""]
    for name, table in (("Table I: underwater runs, node accuracy", report["table1"]),
                        ("Table II: KITTI-like places, node accuracy", report["table2"])):
        if not table:
            continue
        cols = [k for k in next(iter(table.values())) if k != "average"] + ["average"]
        lines += [f"### {name}", "", "| mode | solver | affinity | " + " | ".join(cols) + " |",
                  "|---|---|---|" + "---|" * len(cols)]
        for key, row in table.items():
            mode, s, a = key.split("/")
            lines.append(f"| {mode} | {s} | {a} | "
                         + " | ".join(_fmt(row.get(c, float("nan"))) for c in cols) + " |")
        lines.append("")
    lines += ["### Beyond the paper: accepted correspondences and transforms", "",
              "| world | mode/solver/affinity | node acc. | accepted | precision | recall | "
              "wrong (accepted) | outliers unmatched | rot. err. deg | transl. err. m |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for world, summ in report["summary"].items():
        for key, r in summ.items():
            if not r["cases"]:
                continue
            lines.append(
                f"| {world} | {key} | {_fmt(r['node_accuracy'])} | {r['accepted']}/{r['cases']} "
                f"| {_fmt(r['precision'])} | {_fmt(r['recall'])} | {r['wrong_returned']} "
                f"({r['wrong_accepted']}) | {r['outliers_unmatched']} | "
                f"{_fmt(r['rot_err_deg_median'])} | {_fmt(r['trans_err_m_median'])} |")
    lines += ["", "### Per-stage time, ms: median (IQR)", "",
              "| world | mode | " + " | ".join(["stage"] * 1) + " | median | IQR |",
              "|---|---|---|---|---|"]
    for world, per_mode in report["stages_ms"].items():
        for mode, st in per_mode.items():
            for k, v in st.items():
                lines.append(f"| {world} | {mode} | {k} | {v['median']:.1f} | {v['iqr']:.1f} |")
    if "scale" in report:
        lines += ["", "### Scale: one 20-object submap against growing maps (verified mode)", "",
                  "| map objects | latency median ms (IQR) [min-max] | peak memory MB | "
                  "node accuracy | accepted |", "|---|---|---|---|---|"]
        for r in report["scale"]:
            lat = r["latency_ms"]
            lines.append(f"| {r['map_objects']} | {lat['median']:.1f} ({lat['iqr']:.1f}) "
                         f"[{lat['min']:.1f}-{lat['max']:.1f}] | {r['peak_mb']:.1f} | "
                         f"{_fmt(r['accuracy'])} | {r['accepted']} |")
    if report.get("figures"):
        lines += ["", "Figures: " + ", ".join(report["figures"].values())]
    return "\n".join(lines) + "\n"


def grow_map(sc: Scenario, n_total: int, rng: np.random.Generator) -> Scenario:
    """The scenario with its map grown to n_total objects by look-alike copies of it: each
    tile is the map turned and moved 5 km away, every object's embedding perturbed like
    another instance of its class. Harder than random fill: every object has twins."""
    arr = sc.map.arrays()
    if n_total <= arr.n:
        return sc
    ids, pos, emb, var, nobs = [arr.ids], [arr.position_xyz_m], [arr.embeddings_nd], \
        [arr.variances_nd], [arr.n_obs]
    need, tile = n_total - arr.n, 0
    d = arr.dim
    while need > 0:
        tile += 1
        k = min(need, arr.n)
        pick = rng.choice(arr.n, size=k, replace=False)
        yaw = rng.uniform(-np.pi, np.pi)
        R = Rotation.from_euler("z", yaw).as_matrix()
        off = np.array([5000.0 * tile, 5000.0 * rng.uniform(-1, 1), 0.0])
        e = arr.embeddings_nd[pick]
        norm = np.linalg.norm(e, axis=1, keepdims=True)
        e = e + rng.normal(size=e.shape) * 0.35 * norm / np.sqrt(d)
        ids.append([f"g{tile}_{arr.ids[i]}" for i in pick])
        pos.append(arr.position_xyz_m[pick] @ R.T + off)
        emb.append(e)
        var.append(arr.variances_nd[pick])
        nobs.append(arr.n_obs[pick])
        need -= k
    grown = ObjectArrays(
        [i for chunk in ids for i in chunk], np.vstack(pos), np.vstack(emb), np.vstack(var),
        np.concatenate(nobs),
    )
    big = ObjectMap(robot_id=sc.map.robot_id, session_id=sc.map.session_id,
                    objects=grown.to_nodes())
    return Scenario(big, sc.submap, sc.truth, sc.R_map_submap, sc.t_map_submap,
                    sc.paper_radius_m, sc.equivalent)


def run_scale_sweep(
    sc: Scenario, sizes: tuple[int, ...], repeats: int, seed: int, echo: Callable[[str], Any]
) -> list[dict[str, Any]]:
    """Latency (median and spread), peak traced memory and accuracy of verified mode for one
    submap against maps grown to each size."""
    rng = np.random.default_rng(seed)
    cfg = load_config()
    out = []
    for n in sizes:
        big = grow_map(sc, n, rng)
        arrays = big.map.arrays()  # built once, as the service keeps its map in memory
        match(arrays, big.submap, cfg)  # warm the per-map caches (unit embeddings, KD-tree)
        tracemalloc.start()
        outcome = match(arrays, big.submap, cfg)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        totals = [match(arrays, big.submap, cfg).result.timings_ms["total"]
                  for _ in range(max(repeats, 3))]
        row = {"map_objects": arrays.n, "latency_ms": _spread(totals),
               "peak_mb": peak / 2**20, "accuracy": score_case(big, outcome)["accuracy"],
               "accepted": bool(outcome.result.accepted)}
        echo(f"scale {arrays.n:>7} objects: {row['latency_ms']['median']:.1f} ms median, "
             f"peak {row['peak_mb']:.1f} MB, accuracy {row['accuracy']:.2f}")
        out.append(row)
    return out


def run_uncertainty_bench(
    out_dir: Path, seed: int = 0, samples: int = 20_000, echo: Callable[[str], Any] = print,
    runs: tuple[int, ...] = (1, 2, 3), sizes: tuple[int, ...] = (2, 3, 4, 5), per_size: int = 5,
    affinity_seeds: int = 5,
) -> dict[str, Any]:
    """Train the uncertainty head on the world's observations, then run the underwater runs
    three times, the vehicle reporting as each image's s: the simulator's true s, the head's
    prediction, or one constant (no uncertainty at all). Node accuracy of both modes.
    Then each node affinity with tracked and with constant variances on `affinity_seeds`
    worlds (run_affinity_uncertainty_bench; 0 skips it)."""
    from mergesvc.sim import image_s_dataset, underwater_run
    from mergesvc.sim.uncertainty import UncertaintyConfig, evaluate, fit

    n_test = max(samples // 5, 100)
    y, loss, s_true = image_s_dataset(samples + n_test, seed)
    head, _ = fit(y[:samples], loss[:samples], UncertaintyConfig(hidden_sizes=(64,)),
                  np.random.default_rng(seed))
    held = evaluate(head, y[samples:], loss[samples:])
    from scipy.stats import spearmanr

    true_rho = float(spearmanr(s_true[samples:], loss[samples:])[0])
    echo(f"uncertainty head: held-out Spearman {held['spearman']:.3f} "
         f"(the simulator's own s: {true_rho:.3f})")
    sources: dict[str, Any] = {
        "true s": None,
        "learned head": head.predict,
        "constant s": lambda e: np.full(len(e), float(np.median(s_true))),
    }
    report: dict[str, Any] = {"spearman_head": held, "spearman_true_s": true_rho, "rows": {}}
    for name, source in sources.items():
        for mode in ("paper", "verified"):
            rows = []
            for r in runs:
                run = underwater_run(r, seed, image_s=source)
                for size in sizes:
                    for sc in run.windows(size, per_size):
                        cfg = _config(mode, "rrwm", "ucos", sc.paper_radius_m)
                        rows.append(score_case(sc, match(sc.map, sc.submap, cfg)))
            agg = _aggregate(rows)
            report["rows"][f"{name}/{mode}"] = agg
            echo(f"{name:>13} {mode:>8}: node accuracy {agg['node_accuracy']:.3f}, precision "
                 f"{agg['precision']:.3f}, recall {_fmt(agg['recall'])} over {agg['cases']}")
    out_dir.mkdir(parents=True, exist_ok=True)
    if affinity_seeds > 0:
        echo("")
        plan = AffinityUncertaintyPlan(seeds=tuple(range(seed, seed + affinity_seeds)),
                                       runs=runs, sizes=sizes, per_size=per_size)
        report["affinities"] = run_affinity_uncertainty_bench(plan, echo)
        (out_dir / "uncertainty_affinities.md").write_text(report["affinities"]["markdown"] + "\n")
    (out_dir / "uncertainty_bench.json").write_text(json.dumps(report, indent=1, default=float))
    return report


# ============================================================================================
# Which node affinity makes use of the tracked uncertainty: each affinity with the objects'
# posterior variances as tracked, and with every variance replaced by the map's mean variance
# (no uncertainty at all), on worlds where view quality varies (range, light). Precision and
# recall of the accepted correspondences, per seed, then median and spread over seeds.
# ============================================================================================

VARIANCE_INPUTS = ("tracked", "constant")


@dataclass(frozen=True)
class AffinityUncertaintyPlan:
    """What the affinity x variance comparison runs; `quick` is a slice for the tests."""

    seeds: tuple[int, ...] = (0, 1, 2, 3, 4)
    runs: tuple[int, ...] = (1, 2, 3)
    sizes: tuple[int, ...] = (2, 3, 4, 5)
    per_size: int = 5
    places: int = 4
    place_size: int = 20
    affinities: tuple[str, ...] = (*AFFINITIES, "likelihood_ratio")
    variances: tuple[str, ...] = VARIANCE_INPUTS

    @classmethod
    def quick(cls) -> AffinityUncertaintyPlan:
        return cls(seeds=(0,), runs=(1,), sizes=(3,), per_size=2, places=1,
                   affinities=("ucos", "likelihood_ratio"))


def constant_variance(
    map_arr: ObjectArrays, sub_arr: ObjectArrays
) -> tuple[ObjectArrays, ObjectArrays]:
    """Map and submap with every variance replaced by the mean variance over the map: the same
    means, no uncertainty information (what an uncertainty-unaware tracker would send)."""
    v = float(map_arr.variances_nd.mean())
    return (replace(map_arr, variances_nd=np.full_like(map_arr.variances_nd, v)),
            replace(sub_arr, variances_nd=np.full_like(sub_arr.variances_nd, v)))


def candidate_separation(
    sc: Scenario, map_arr: ObjectArrays, sub_arr: ObjectArrays, config: MatchConfig
) -> dict[str, list[float]]:
    """The candidate stage alone (calibrated node scores, no geometry): for each submap object
    with a true match, its best score at a right ("right") and at a wrong ("wrong") map object;
    for each false detection, its best score ("false"). 0 where there is no such candidate."""
    from mergesvc.core.candidates import retrieve

    cands, _ = retrieve(sub_arr, map_arr, config.candidates, config.affinity,
                        np.random.default_rng(config.seed))
    out: dict[str, list[float]] = {"right": [], "wrong": [], "false": []}
    for i, sid in enumerate(sub_arr.ids):
        sel = cands.rows == i
        score = cands.score[sel]
        ok = np.array([sc.is_correct(sid, map_arr.ids[b]) for b in cands.map_nodes[sel]], bool)
        if sc.truth.get(sid) is None:
            out["false"].append(float(score.max()) if len(score) else 0.0)
            continue
        out["right"].append(float(score[ok].max()) if ok.any() else 0.0)
        out["wrong"].append(float(score[~ok].max()) if (~ok).any() else 0.0)
    return out


def _auc(pos: list[float], neg: list[float]) -> float:
    """P(a positive scores above a negative), ties counting half; NaN without both."""
    if not pos or not neg:
        return float("nan")
    from scipy.stats import mannwhitneyu

    return float(mannwhitneyu(pos, neg).statistic) / (len(pos) * len(neg))


def _affinity_worlds(seed: int, plan: AffinityUncertaintyPlan) -> dict[str, list[Scenario]]:
    from mergesvc.sim import drive_run, underwater_run

    uw = [sc for r in plan.runs for size in plan.sizes
          for sc in underwater_run(r, seed).windows(size, plan.per_size)]
    drive = drive_run(seed).places(plan.places, plan.place_size) if plan.places else []
    return {"underwater": uw, "drive": drive}


def run_affinity_uncertainty_bench(
    plan: AffinityUncertaintyPlan | None = None, echo: Callable[[str], Any] = print
) -> dict[str, Any]:
    """Verified mode, each affinity with tracked and with constant variances, on the underwater
    runs' windows and the drive's loop-closure places of every seed; and the candidate stage
    alone (candidate_separation). Returns a JSON-ready report ({"per_seed": {world/affinity/
    variances: [aggregate per seed]}, "summary": {...: spreads, pooled values, AUCs}}) with a
    markdown table under "markdown"."""
    plan = plan or AffinityUncertaintyPlan()
    start = time.perf_counter()
    per_seed: dict[str, list[dict[str, Any]]] = {}
    pooled: dict[str, list[dict[str, float]]] = {}
    separation: dict[str, dict[str, list[float]]] = {}
    for seed in plan.seeds:
        for world, cases in _affinity_worlds(seed, plan).items():
            inputs = {"tracked": [(sc.map.arrays(), sc.submap.arrays()) for sc in cases]}
            inputs["constant"] = [constant_variance(m, s) for m, s in inputs["tracked"]]
            for affinity in plan.affinities:
                cfg = load_config(affinity={"kind": affinity})
                for var in plan.variances:
                    rows = [score_case(sc, match(m, s, cfg))
                            for sc, (m, s) in zip(cases, inputs[var])]
                    if not rows:
                        continue
                    agg = _aggregate(rows)
                    per_seed.setdefault(f"{world}/{affinity}/{var}", []).append(agg)
                    pooled.setdefault(f"{world}/{affinity}/{var}", []).extend(rows)
                    sep = separation.setdefault(f"{world}/{affinity}/{var}",
                                                {"right": [], "wrong": [], "false": []})
                    for sc, (m, s) in zip(cases, inputs[var]):
                        for k, v in candidate_separation(sc, m, s, cfg).items():
                            sep[k].extend(v)
                    echo(f"[{time.perf_counter() - start:6.1f}s] seed {seed} {world:>10} "
                         f"{affinity:>16} {var:>8}: precision {agg['precision']:.3f}, recall "
                         f"{_fmt(agg['recall'])}, node accuracy {agg['node_accuracy']:.3f} "
                         f"over {agg['cases']}")
    summary: dict[str, dict[str, Any]] = {}
    for key, aggs in per_seed.items():
        summary[key] = {m: _spread([a[m] for a in aggs])
                        for m in ("precision", "recall", "node_accuracy")}
        summary[key]["wrong_accepted"] = int(sum(a["wrong_accepted"] for a in aggs))
        summary[key]["accepted"] = f"{sum(a['accepted'] for a in aggs)}/" \
                                   f"{sum(a['cases'] for a in aggs)}"
        summary[key]["seeds"] = len(aggs)
        # every case of every seed together: a seed with few accepted submaps weighs less
        summary[key]["pooled"] = {m: v for m, v in _aggregate(pooled[key]).items()
                                  if m in ("precision", "recall", "node_accuracy")}
        # how well the node score alone separates a right match from the best wrong one and
        # from a false detection's best (AUC over all submap objects of all seeds)
        sep = separation[key]
        summary[key]["candidate_auc"] = {"right_vs_wrong": _auc(sep["right"], sep["wrong"]),
                                         "right_vs_false": _auc(sep["right"], sep["false"])}
    report = {"plan": {k: list(v) if isinstance(v, tuple) else v
                       for k, v in plan.__dict__.items()},
              "per_seed": per_seed, "summary": summary,
              "elapsed_s": round(time.perf_counter() - start, 1)}
    report["markdown"] = affinity_uncertainty_markdown(summary)
    echo(report["markdown"])
    return report


def _fmt3(x: float) -> str:
    return "-" if not np.isfinite(x) else f"{x:.3f}"


def affinity_uncertainty_markdown(summary: dict[str, dict[str, Any]]) -> str:
    """One row per world / affinity / variances: median (IQR) [min-max] over seeds, then
    precision and recall over all cases of all seeds together, and how well the node score
    alone (the candidate stage) separates right matches from wrong ones."""

    def cell(s: dict[str, float]) -> str:
        return f"{s['median']:.3f} ({s['iqr']:.3f}) [{s['min']:.3f}-{s['max']:.3f}]"

    lines = ["| world | affinity | variances | precision | recall | node accuracy | "
             "pooled precision / recall | wrong accepted | accepted | seeds | "
             "node score AUC: right vs best wrong / vs false detection |",
             "|" + "---|" * 11]
    for key, r in summary.items():
        world, affinity, var = key.split("/")
        p = r["pooled"]
        lines.append(f"| {world} | {affinity} | {var} | {cell(r['precision'])} | "
                     f"{cell(r['recall'])} | {cell(r['node_accuracy'])} | "
                     f"{p['precision']:.3f} / {p['recall']:.3f} | "
                     f"{r['wrong_accepted']} | {r['accepted']} | {r['seeds']} | "
                     f"{_fmt3(r['candidate_auc']['right_vs_wrong'])} / "
                     f"{_fmt3(r['candidate_auc']['right_vs_false'])} |")
    return "\n".join(lines)


def run_link_bench(
    seeds: int = 5,
    submap_objects: int = 20,
    period_s: float = 300.0,
    duration_s: float = 3600.0,
    seed: int = 0,
    echo: Callable[[str], Any] = print,
) -> dict[str, Any]:
    """Profile x modem rate x SNR: bytes per object, bytes and airtime of one 20-object submap,
    delivery ratio and mean time to deliver (3 vehicles sharing the TDMA cycle, one submap each
    every period_s), and node accuracy after decoding (the submap decoded, the map as is)."""
    from mergesvc.link import (
        DEFAULT_SWEEP_SNR_DB,
        RATE_SPECS,
        ModemRate,
        Workload,
        frame_error_prob,
        sweep_link,
    )
    from mergesvc.wire import Profile, Projection, decode_message, encode_message

    profiles: dict[str, dict[str, float]] = {}
    for prof in Profile:
        acc, nbytes, nobj = [], 0, 0
        for s in range(seeds):
            sc = make_scenario(Family.UNDERWATER, seed + s, n_map=40, n_sub=submap_objects,
                               n_outliers=2)
            proj = Projection.fit(sc.map.arrays().embeddings_nd) if prof is Profile.COMPACT \
                else None  # the fleet's projection: learned from map data, not the submap
            data = encode_message(sc.submap, prof, sc.submap.robot_id, 0, projection=proj)
            _, decoded = decode_message(data, proj)
            nbytes += len(data)
            nobj += len(sc.submap.objects)
            acc.append(score_case(sc, match(sc.map, decoded))["accuracy"])
        profiles[prof.value] = {"bytes_per_object": nbytes / nobj,
                                "bytes_per_submap": nbytes / seeds,
                                "node_accuracy": float(np.mean(acc))}
    rows = []
    for prof, p in profiles.items():
        size = round(p["bytes_per_submap"])
        wl = Workload(uplink_bytes=size, period_s=period_s, duration_s=duration_s)
        for rate in ModemRate:
            spec = RATE_SPECS[rate]
            fragments = -(-(size + 4) // spec.fragment_payload_bytes)
            airtime = -(-fragments // spec.frames) * spec.airtime_s
            for r in sweep_link((rate,), DEFAULT_SWEEP_SNR_DB[rate], workload=wl, seed=seed):
                row = {
                    "profile": prof, "rate": rate.value, "snr_db": r.snr_db,
                    "frame_error": frame_error_prob(rate, r.snr_db),
                    "bytes_per_object": p["bytes_per_object"], "bytes_per_submap": size,
                    "airtime_s": airtime, "delivery_ratio": r.delivery_ratio,
                    "latency_p50_s": r.latency_p50_s, "node_accuracy": p["node_accuracy"],
                }
                rows.append(row)
    lines = ["| profile | rate | SNR dB | FER | B/object | B/submap | airtime s | delivered | "
             "time to deliver s (median) | node accuracy |", "|" + "---|" * 10]
    for r in rows:
        lines.append(
            f"| {r['profile']} | {r['rate']} | {r['snr_db']:.1f} | {r['frame_error']:.3f} | "
            f"{r['bytes_per_object']:.0f} | {r['bytes_per_submap']} | {r['airtime_s']:.1f} | "
            f"{r['delivery_ratio']:.2f} | {_fmt(r['latency_p50_s'])} | "
            f"{r['node_accuracy']:.3f} |")
    md = "\n".join(lines)
    echo(md)
    return {"profiles": profiles, "rows": rows, "markdown": md,
            "workload": {"vehicles": 3, "submap_objects": submap_objects, "period_s": period_s,
                         "duration_s": duration_s}}
