"""Uncertainty benchmarks (`mergesvc bench uncertainty`): the image uncertainty s the vehicle
reports (true, learned head, constant) and its effect on matching; and which node affinity makes
use of the tracked variances (tracked vs constant variances, per affinity).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from mergesvc.bench.paper import AFFINITIES
from mergesvc.bench.scoring import _aggregate, _config, _fmt, _spread, score_case
from mergesvc.core.config import MatchConfig, match_config
from mergesvc.core.model import ObjectArrays
from mergesvc.core.pipeline import match
from mergesvc.sim import Scenario


def run_uncertainty_bench(
    out_dir: Path, seed: int = 0, samples: int = 20_000, echo: Callable[[str], Any] = print,
    runs: tuple[int, ...] = (1, 2, 3), sizes: tuple[int, ...] = (2, 3, 4, 5), per_size: int = 5,
    affinity_seeds: int = 5,
    base: MatchConfig | None = None,
) -> dict[str, Any]:
    """Train the uncertainty head on the world's observations, then run the underwater runs
    three times, the vehicle reporting as each image's s: the simulator's true s, the head's
    prediction, or one constant (no uncertainty at all). Node accuracy of both modes.
    Then each node affinity with tracked and with constant variances on `affinity_seeds`
    worlds (run_affinity_uncertainty_bench; 0 skips it). Matching: `base` (default: the
    defaults) with the mode and affinity set; the head's own settings are fixed."""
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
                        cfg = _config(mode, "rrwm", "ucos", sc.paper_radius_m, base)
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
        report["affinities"] = run_affinity_uncertainty_bench(plan, echo, base)
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
    plan: AffinityUncertaintyPlan | None = None, echo: Callable[[str], Any] = print,
    base: MatchConfig | None = None,
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
                cfg = match_config(base, affinity={"kind": affinity})
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


__all__ = [
    "VARIANCE_INPUTS",
    "AffinityUncertaintyPlan",
    "affinity_uncertainty_markdown",
    "candidate_separation",
    "constant_variance",
    "run_affinity_uncertainty_bench",
    "run_uncertainty_bench",
]
