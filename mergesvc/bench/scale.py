"""Scale benchmark (`mergesvc bench scale`): latency, memory, node accuracy and candidate recall
from small to a million-object map and from 2-object to 10,000-object submaps, with the BLAS at
its default thread count and at one thread, interleaved in the same run.

The parent builds each world (sim/scale.py) and writes its map and submaps as binary map files;
one child process per map size loads them as `match` does (a map from 32 MB memory-mapped) and
matches, so its peak RSS is the map's and the matching's alone. Each map is prepared first,
untimed and reported apart (what a map keeps: the KD-tree, its index).
"""

from __future__ import annotations

import contextlib
import json
import multiprocessing
import os
import platform
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from mergesvc.bench.scoring import check_count, peak_rss_mb
from mergesvc.core.config import MatchConfig, match_config
from mergesvc.core.pipeline import match
from mergesvc.core.search import ExactSearch, map_search
from mergesvc.errors import InputError
from mergesvc.sim import DEFAULT_DATA_DIR, DINO_CENTROIDS, load_dino_centroids
from mergesvc.sim.scale import cut_submap, scale_world
from mergesvc.wire.mapfile import load_arrays, release_pages, save_arrays

THREAD_MODES = ("default", "1")
RECALL_QUERIES = 200  # submap objects per case whose shortlist is checked against exact


@dataclass
class ScalePlan:
    """What `mergesvc bench scale` runs: per map size, the submap sizes matched against it."""

    cells: dict[int, tuple[int, ...]]
    cases: int = 5  # submaps per (map, submap size) of up to 100 objects
    large_cases: int = 1  # submaps per size above 100 objects
    repeats: int = 5  # matches per submap and thread mode (1 above 100 objects)
    dim: int = 384
    seed: int = 0
    data_dir: Path = field(default_factory=lambda: DEFAULT_DATA_DIR)
    config: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def full(cls, **kw: Any) -> ScalePlan:
        cells = {900: (3, 20), 1_000: (3, 20, 200), 10_000: (3, 20, 1_000),
                 100_000: (3, 20, 1_000, 5_000, 10_000), 1_000_000: (3, 20)}
        return cls(cells, **kw)

    @classmethod
    def quick(cls, **kw: Any) -> ScalePlan:
        return cls({900: (3, 20), 5_000: (3, 20, 200)}, **kw)


def _rss_mb(shared: bool = False) -> float:
    """Resident memory now (Linux /proc), MB; nan elsewhere. shared: only its pages of mapped
    files (a memory-mapped map's, the libraries'), which the page cache holds and may reclaim."""
    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[2 if shared else 1])
        return pages * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return float("nan")


def _node_accuracy(assignment: np.ndarray, truth: np.ndarray) -> float:
    """Right matches plus false detections left unmatched, over all submap objects."""
    right = np.where(truth >= 0, assignment == truth, assignment < 0)
    return float(right.mean())


def _recall(map_, sub, truth: np.ndarray, twins: np.ndarray, cfg: MatchConfig
            ) -> dict[str, float]:
    """Of the exact top-k (k = candidates.top_k) by cosine, the share the map's search (the
    index where it has one) returns; over all checked objects and over look-alikes (objects
    with a twin in the map); and how often the true object is in the exact top-prefilter."""
    rows = np.flatnonzero(truth >= 0)[:RECALL_QUERIES]
    if len(rows) == 0 or map_.n <= cfg.candidates.prefilter:
        return {}
    q = sub.unit_rows(rows).astype(np.float32)
    k = cfg.candidates.top_k
    got = map_search(map_, cfg.candidates, sub.n).search(q, k)[0]
    # the reference pass reads the whole map: its pages are dropped as it goes (the
    # benchmark's own reading is not the matcher's memory)
    exact = ExactSearch(map_.embeddings_nd, map_.norms_n, release=True).search(
        q, cfg.candidates.prefilter)[0]
    share = np.array([len(set(g) & set(e[:k])) / k for g, e in zip(got, exact)])
    look = twins[truth[rows]]
    true_in = np.array([t in set(e) for t, e in zip(truth[rows], exact)])
    return {"recall_at_k": float(share.mean()),
            "recall_at_k_lookalikes": float(share[look].mean()) if look.any() else float("nan"),
            "lookalike_queries": int(look.sum()),
            "true_in_shortlist": float(true_in.mean())}


def _child(job: dict[str, Any]) -> dict[str, Any]:
    """One map size in a fresh process: load, match every case in both thread modes."""
    from threadpoolctl import threadpool_limits

    out: dict[str, Any] = {"rss_start_mb": _rss_mb()}
    cfg = match_config(job["config"])
    t0 = time.perf_counter()
    map_, _, _ = load_arrays(job["map"])
    out["load_s"] = time.perf_counter() - t0
    twins = np.load(job["twins"])
    out["rss_loaded_mb"] = _rss_mb()
    first = True
    cells = {}
    largest = max(int(k) for k in job["subs"]) if job["subs"] else 1
    for n_sub, paths in job["subs"].items():
        subs = [(load_arrays(p, mmap_large=False)[0], np.load(t)) for p, t in paths]
        if first:
            # what a map keeps (KD-tree, the index its largest submaps want) is built once,
            # before the timed matches, as a service or `match` does when it loads a map
            t = time.perf_counter()
            map_search(map_, cfg.candidates, largest)
            match(map_, subs[0][0], cfg)
            out["prepare_s"] = time.perf_counter() - t
            release_pages(map_)  # what building them read of the mapped map
            out["rss_prepared_mb"] = _rss_mb()
            first = False
        lat: dict[str, list[float]] = {m: [] for m in THREAD_MODES}
        cpu: dict[str, list[float]] = {m: [] for m in THREAD_MODES}  # process CPU time:
        # less moved by the machine's load than wall time
        acc, accepted, recall = [], [], []
        repeats = job["repeats"] if int(n_sub) <= 100 else 1
        for sub, truth in subs:
            for r in range(repeats):
                for mode in THREAD_MODES:  # interleaved: both see the same machine load
                    # timed inside threadpoolctl's block: entering it lists the loaded
                    # libraries (about a millisecond), which is the benchmark's, not match's
                    with threadpool_limits(1) if mode == "1" else contextlib.nullcontext():
                        t, c = time.perf_counter(), time.process_time()
                        o = match(map_, sub, cfg)
                        lat[mode].append((time.perf_counter() - t) * 1e3)
                        cpu[mode].append((time.process_time() - c) * 1e3)
                    if r == 0 and mode == "default":
                        acc.append(_node_accuracy(o.assignment, truth))
                        accepted.append(bool(o.result.accepted))
            recall.append(_recall(map_, sub, truth, twins, cfg))
        cells[n_sub] = {
            "latency_ms": {m: {"p50": float(np.percentile(v, 50)),
                               "p99": float(np.percentile(v, 99)), "runs": len(v)}
                           for m, v in lat.items()},
            "cpu_ms_p50": float(np.percentile(cpu["default"], 50)),
            "cpu_ms_p50_1thread": float(np.percentile(cpu["1"], 50)),
            "node_accuracy": float(np.mean(acc)),
            "accepted": f"{sum(accepted)}/{len(accepted)}",
            "submaps": len(subs),
            "recall": {k: float(np.nanmean([r[k] for r in recall if k in r]))
                       for k in ("recall_at_k", "recall_at_k_lookalikes", "true_in_shortlist")
                       if any(k in r for r in recall)},
            "peak_rss_mb": peak_rss_mb(),
        }
    out["cells"] = cells
    out["peak_rss_mb"] = peak_rss_mb()
    out["rss_end_mb"], out["rss_end_shared_mb"] = _rss_mb(), _rss_mb(shared=True)
    out["index"] = type(map_.cache.get("search")).__name__ if "search" in map_.cache else \
        "ExactSearch"
    return out


def _write_world(n_map: int, subs: tuple[int, ...], plan: ScalePlan, folder: Path,
                 dino: np.ndarray | None) -> dict[str, Any]:
    world = scale_world(n_map, plan.dim, plan.seed, dino)
    job: dict[str, Any] = {"map": str(folder / f"map{n_map}.npz"),
                           "twins": str(folder / f"twins{n_map}.npy"), "subs": {},
                           "repeats": plan.repeats, "config": plan.config}
    save_arrays(job["map"], world.map, {"kind": "map", "robot_id": "a", "session_id": "s"})
    twin = np.zeros(n_map, dtype=bool)
    twin[world.twin_of[world.twin_of >= 0]] = True
    twin[world.twin_of >= 0] = True
    np.save(job["twins"], twin)
    for n_sub in subs:
        if n_sub > n_map:
            continue
        cases = plan.cases if n_sub <= 100 else plan.large_cases
        paths = []
        for c in range(cases):
            size = n_sub if n_sub != 3 else 2 + c % 4  # "3": the paper's 2-5 objects
            case = cut_submap(world, size, plan.seed * 1000 + c)
            p = folder / f"sub{n_map}_{n_sub}_{c}.npz"
            save_arrays(p, case.submap, {"kind": "submap", "robot_id": "b", "session_id": "s"})
            np.save(folder / f"truth{n_map}_{n_sub}_{c}.npy", case.truth)
            paths.append((str(p), str(folder / f"truth{n_map}_{n_sub}_{c}.npy")))
        job["subs"][str(n_sub)] = paths
    return job


def run_scale(plan: ScalePlan, echo: Callable[[str], Any] = print,
              work_dir: Path | None = None, partial: Path | None = None) -> dict[str, Any]:
    """Run the plan; returns a JSON-ready report and echoes a table (and writes the report
    so far to `partial` after each map)."""
    check_count("repeats", plan.repeats)
    check_count("cases", plan.cases)
    dino_path = Path(plan.data_dir) / DINO_CENTROIDS
    dino = load_dino_centroids(dino_path) if dino_path.exists() else None
    report: dict[str, Any] = {
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": f"{platform.machine()} {os.cpu_count()} cores, python "
        f"{platform.python_version()}",
        "load_avg": os.getloadavg(),
        "plan": {**asdict(plan), "data_dir": str(plan.data_dir),
                 "cells": {str(k): v for k, v in plan.cells.items()}},
        "appearance": "DINO centroids" if dino is not None else "generated centroids",
        "maps": {},
    }
    ctx = multiprocessing.get_context("spawn")
    start = time.perf_counter()
    if work_dir is not None:
        try:
            Path(work_dir).mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise InputError(f"cannot make the work folder {work_dir}: "
                             f"{exc.strerror or exc}") from exc
    with tempfile.TemporaryDirectory(dir=work_dir) as tmp:
        for n_map, subs in plan.cells.items():
            t = time.perf_counter()
            job = _write_world(n_map, subs, plan, Path(tmp), dino)
            built = time.perf_counter() - t
            with ctx.Pool(1) as pool:
                res = pool.apply(_child, (job,))
            res["world_build_s"] = built
            res["load_avg_after"] = os.getloadavg()
            report["maps"][str(n_map)] = res
            echo(f"[{time.perf_counter() - start:7.1f}s] map {n_map}: load "
                 f"{res['load_s']:.2f} s, prepare {res['prepare_s']:.2f} s, RSS loaded "
                 f"{res['rss_loaded_mb']:.0f} MB, prepared {res['rss_prepared_mb']:.0f} MB, "
                 f"peak {res['peak_rss_mb']:.0f} MB, after matching {res['rss_end_mb']:.0f} MB "
                 f"({res['rss_end_shared_mb']:.0f} MB of it mapped files), search "
                 f"{res['index']}")
            if partial is not None:  # what is done so far survives an interrupted run
                write_report(report, partial)
            for f in Path(tmp).iterdir():
                f.unlink()
    echo("")
    echo(markdown_table(report))
    return report


def markdown_table(report: dict[str, Any]) -> str:
    lines = [
        "| map objects | submap objects | p50 ms (default threads) | p99 ms | p50 ms (1 thread) "
        "| p99 ms | CPU ms p50 (default / 1 thread) | node accuracy | accepted "
        "| recall@k (look-alikes) | true in shortlist | peak RSS MB |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for n_map, res in report["maps"].items():
        for n_sub, c in res["cells"].items():
            d, one = c["latency_ms"]["default"], c["latency_ms"]["1"]
            rec = c["recall"]
            r = (f"{rec['recall_at_k']:.3f} ({rec.get('recall_at_k_lookalikes', float('nan')):.3f})"
                 if "recall_at_k" in rec else "-")
            t = f"{rec['true_in_shortlist']:.3f}" if "true_in_shortlist" in rec else "-"
            size = "2-5" if n_sub == "3" else n_sub
            lines.append(f"| {n_map} | {size} | {d['p50']:.1f} | {d['p99']:.1f} | "
                         f"{one['p50']:.1f} | {one['p99']:.1f} | "
                         f"{c.get('cpu_ms_p50', float('nan')):.1f} / "
                         f"{c.get('cpu_ms_p50_1thread', float('nan')):.1f} | "
                         f"{c['node_accuracy']:.3f} | "
                         f"{c['accepted']} | {r} | {t} | {c['peak_rss_mb']:.0f} |")
    return "\n".join(lines)


def write_report(report: dict[str, Any], out: Path) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=1))
    out.with_suffix(".md").write_text(markdown_table(report) + "\n")


__all__ = ["THREAD_MODES", "ScalePlan", "markdown_table", "run_scale", "write_report"]
