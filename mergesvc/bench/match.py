"""Benchmark harness (`mergesvc bench match`): latency (median and spread over repeats) and
accuracy of `verified` vs `paper` mode, and (`peer`) KISS-Matcher run from its own package
(bench/peers.py), measured side by side in the same run on seeded scenarios.
"""

from __future__ import annotations

import dataclasses
import platform
import time
from collections.abc import Callable
from datetime import datetime, timezone
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from mergesvc.bench.fresh import markdown_fresh, run_fresh
from mergesvc.bench.peers import KISS_METHOD, KissSettings, kiss_outcome, load_kiss
from mergesvc.bench.scoring import _cpu_count, _spread, check_count, score_case
from mergesvc.core.config import MatchConfig, match_config
from mergesvc.core.pipeline import match
from mergesvc.sim import Family, Scenario, make_scenario


def run_case(
    sc: Scenario, config: MatchConfig, repeats: int, one_thread: list[float] | None = None,
    one_thread_cpu: list[float] | None = None, peer: dict[str, list] | None = None,
    peer_settings: KissSettings | None = None,
) -> tuple[dict[str, float], list[float], dict[str, list[float]]]:
    """Run one scenario `repeats` (>= 1, else InputError) times; (scores of the first run,
    totals ms, stage ms; stage "cpu": the process CPU time of each match, ms). With
    `one_thread` (a list), each run is followed by one with the BLAS held to one thread, its
    total appended there (its CPU time to `one_thread_cpu`): both under the same load. With
    `peer` (a dict), each run is also followed by KISS-Matcher's on the same files
    (`peer_settings`, default KissSettings()), one BLAS thread: its totals to peer["totals"],
    CPU times to peer["cpu"], its first run's scores to peer["scores"]."""
    check_count("repeats", repeats)
    totals: list[float] = []
    stages: dict[str, list[float]] = {}
    scores: dict[str, float] = {}
    for run in range(repeats):
        c = time.process_time()
        outcome = match(sc.map, sc.submap, config)
        stages.setdefault("cpu", []).append((time.process_time() - c) * 1e3)
        if run == 0:
            scores = score_case(sc, outcome)
        for k, v in outcome.result.timings_ms.items():
            stages.setdefault(k, []).append(v)
        totals.append(outcome.result.timings_ms["total"])
        if one_thread is not None:
            with threadpool_limits(1):
                c = time.process_time()
                one = match(sc.map, sc.submap, config)
                if one_thread_cpu is not None:
                    one_thread_cpu.append((time.process_time() - c) * 1e3)
            one_thread.append(one.result.timings_ms["total"])
        if peer is not None:
            with threadpool_limits(1):
                c = time.process_time()
                theirs = kiss_outcome(sc.map, sc.submap, peer_settings)
                peer.setdefault("cpu", []).append((time.process_time() - c) * 1e3)
            peer.setdefault("totals", []).append(theirs.result.timings_ms["total"])
            if run == 0:
                peer.setdefault("scores", []).append(score_case(sc, theirs))
    return scores, totals, stages


def _modes(
    paper: bool, affinity: str, base: MatchConfig | None = None
) -> list[tuple[str, MatchConfig, bool]]:
    """(label, settings, runs once) of the modes measured for one affinity, each `base`
    (default: the defaults) with the mode and affinity set."""
    aff = {"affinity": {"kind": affinity}}
    modes = [("verified", match_config(base, mode="verified", **aff), False)]
    if paper:
        modes.append(("paper", match_config(base, mode="paper", **aff), True))
        if affinity != "ucos":  # the authors' code: the distance fed in as the affinity
            raw = {"affinity": {"kind": affinity, "raw_distances": True}}
            modes.append(("paper-raw", match_config(base, mode="paper", **raw), True))
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
    base: MatchConfig | None = None,
    one_thread: bool = True,
    fresh: int = 0,
    peer: bool | KissSettings = False,
) -> dict[str, Any]:
    """Both modes on `seeds` scenarios per family and affinity; verified mode also with the
    BLAS held to one thread, interleaved with the default runs (`one_thread`), KISS-Matcher
    interleaved with them on the same files (`peer`: True or its settings; results
    "<family>/kiss-matcher", beside the first affinity's), and (`fresh`
    > 0) that many times per scenario as the first match of a new `mergesvc match` process
    (bench/fresh.py; report["fresh"]). Paper mode runs
    once per scenario (it takes seconds); verified mode `repeats` times. Every configuration is
    `base` (default: the defaults) with its mode and affinity set. Returns a JSON-ready report
    (results keyed family/mode/affinity) and echoes a table. InputError for repeats or seeds
    below 1."""
    check_count("repeats", repeats)
    check_count("seeds", seeds)
    peer_settings = peer if isinstance(peer, KissSettings) else KissSettings() if peer else None
    if peer_settings is not None:
        load_kiss()  # InputError now, not after the first family, when it is not installed
    report: dict[str, Any] = {
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": f"{platform.machine()} {platform.processor() or ''} "
        f"{_cpu_count()} cores, python {platform.python_version()}",
        "settings": {},
        "results": {},
        "fresh": {},
    }
    if peer_settings is not None:
        report["settings"][KISS_METHOD] = dataclasses.asdict(peer_settings)
    start = time.perf_counter()
    scenarios = {(f, s): bench_scenario(f, s) for f in families for s in range(seeds)}
    for family in families:
        for affinity in affinities:
            for name, cfg, once in _modes(paper, affinity, base):
                report["settings"][f"{name}/{affinity}"] = cfg.model_dump(mode="json")
                rows, totals, stages = [], [], {}
                single: list[float] | None = [] if (one_thread and not once) else None
                single_cpu: list[float] = []
                theirs: dict[str, list] | None = (
                    {} if peer_settings and name == "verified" and affinity == affinities[0]
                    else None)
                for seed in range(seeds):
                    sc = scenarios[family, seed]
                    run_cfg = cfg
                    if name.startswith("paper"):  # the paper's radius for this kind of world
                        run_cfg = cfg.model_copy(deep=True)
                        run_cfg.affinity.edge_radius_m = sc.paper_radius_m
                    scores, t, st = run_case(sc, run_cfg, 1 if once else repeats, single,
                                             single_cpu, theirs, peer_settings)
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
                if single:  # the same runs, interleaved, with the BLAS on one thread
                    report["results"][f"{family.value}/{name} (1 thread)/{affinity}"] = \
                        _summary(rows, single, {"cpu": single_cpu})
                if theirs:  # the peer's runs, interleaved with those
                    report["results"][f"{family.value}/{KISS_METHOD}"] = _summary(
                        theirs["scores"], theirs["totals"], {"cpu": theirs["cpu"]})
                if fresh and name == "verified":
                    cases = [(scenarios[family, s], match(scenarios[family, s].map,
                                                          scenarios[family, s].submap, cfg))
                             for s in range(seeds)]
                    echo(f"[{time.perf_counter() - start:6.1f}s] {family.value:>10} verified "
                         f"{affinity:>13}: {fresh * seeds * 2} fresh `mergesvc match` processes")
                    report["fresh"][f"{family.value}/verified/{affinity}"] = run_fresh(
                        cases, cfg, fresh)
    echo("")
    echo(markdown_table(report))
    if report["fresh"]:
        echo("")
        echo(markdown_fresh(report["fresh"]))
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
        "cpu_ms": _spread(stages["cpu"]) if stages.get("cpu") else None,
        "stages_ms": {k: _spread(v)["median"] for k, v in stages.items() if k != "cpu"},
        "runs": len(totals),
    }


def markdown_table(report: dict[str, Any]) -> str:
    lines = [
        "| scenario / mode / affinity | node accuracy | wrong matches (in accepted) | accepted "
        "| outliers left unmatched | latency median ms (IQR) [min-max] | p99 ms "
        "| CPU ms median | runs |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for key, r in report["results"].items():
        lat, cpu = r["latency_ms"], r.get("cpu_ms")
        cpu_ms = f"{cpu['median']:.1f}" if cpu else "-"
        lines.append(
            f"| {key} | {r['node_accuracy']:.3f} | {r['wrong_matches']} "
            f"({r['wrong_in_accepted']}) | {r['accepted']}/{r['scenarios']} | "
            f"{r['outliers_unmatched']} | "
            f"{lat['median']:.1f} ({lat['iqr']:.1f}) [{lat['min']:.1f}-{lat['max']:.1f}] | "
            f"{lat.get('p99', float('nan')):.1f} | {cpu_ms} | {r['runs']} |"
        )
    ratios = []
    ours: dict[str, Any] | None = None
    for key, r in report["results"].items():  # the peer's row follows those it ran beside
        family, _, method = key.partition("/")
        if method.startswith("verified"):
            ours = r  # its 1-thread row, when run, comes last: the peer runs on one thread
        elif method == KISS_METHOD and ours is not None:
            ratio = ours["latency_ms"]["median"] / r["latency_ms"]["median"]
            ratios.append(f"{family} {ratio:.1f}x")
    if ratios:
        lines.append("\nmergesvc (verified; 1 thread when run, as the peer) p50 / KISS-Matcher "
                     "p50 in this run: " + ", ".join(ratios))
    return "\n".join(lines)


__all__ = ["bench_scenario", "markdown_table", "run_case", "run_match_bench"]
