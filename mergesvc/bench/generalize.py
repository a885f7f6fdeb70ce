"""Generalization benchmark: a matrix of worlds that do not share the generator's
assumptions (axis conventions, embedding dimension, map size, look-alikes, duplicates, range
noise, declared vertical), with verified mode, paper mode and cosine + Hungarian side by side,
the neural solver (NGM) in both modes beside the default solver (RRWM), and a peer from its own
code when it is installed (KISS-Matcher, bench/peers.py); per cell, how
often each method accepts a submap of a place the map lacks (another world of the cell's kind).

The worlds are simulation (mergesvc.sim: worlds.py builds them gravity-aligned from real data
in `../shared/data` where it exists and from the project's own generators, conventions.py
writes them as `match` files in a cell's frame conventions); this module holds the methods, the
matrix of cells, the scoring and the run.
"""

from __future__ import annotations

import logging
import platform
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, field, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from mergesvc.bench.peers import KISS_METHOD, kiss_outcome, load_kiss
from mergesvc.bench.scoring import check_count, score_case
from mergesvc.core.config import MatchConfig, match_config
from mergesvc.core.model import (
    Match,
    MatchResult,
    ObjectArrays,
    ObjectMap,
    RejectReason,
    Submap,
)
from mergesvc.core.pipeline import MatchOutcome, match
from mergesvc.errors import InputError
from mergesvc.sim import (
    DEFAULT_DATA_DIR,
    DINO_CENTROIDS,
    KITTI_GT,
    KITTI_ORB,
    Scenario,
    World,
    WorldSpec,
    convention_rotation,
    express,
    generator_world,
    kitti_world,
    load_dino_centroids,
    load_kitti_poses_34,
    pool_world,
    supports_up,
)

log = logging.getLogger(__name__)


# ============================================================================================
# Methods
# ============================================================================================


def cosine_hungarian(map_: ObjectArrays, sub: ObjectArrays) -> np.ndarray:
    """The plain baseline: cosine similarity of the embeddings (n_sub, n_map), Hungarian
    assignment maximising it; every submap object matched (while map objects last).
    Returns (n_sub,) map index per submap object, -1 where none is left."""
    S = sub.unit_embeddings_nd @ map_.unit_embeddings_nd.T
    rows, cols = linear_sum_assignment(S, maximize=True)
    out = np.full(sub.n, -1, dtype=np.int64)
    out[rows] = cols
    return out


def cosine_hungarian_outcome(
    map_: ObjectMap | ObjectArrays, sub: ObjectMap | ObjectArrays,
    clock: Callable[[], float] = time.perf_counter,
) -> MatchOutcome:
    """`cosine_hungarian` wrapped as a pipeline outcome (accepted, nothing verified)."""
    t0 = clock()
    m = map_ if isinstance(map_, ObjectArrays) else map_.arrays()
    s = sub if isinstance(sub, ObjectArrays) else sub.arrays()
    assignment = cosine_hungarian(m, s)
    S = s.unit_embeddings_nd @ m.unit_embeddings_nd.T
    matches = [Match(submap_object=s.ids[i], map_object=m.ids[int(a)],
                     score=round(float(S[i, a]), 6)) for i, a in enumerate(assignment) if a >= 0]
    result = MatchResult(accepted=bool(matches), reason=RejectReason.NOT_VERIFIED,
                         matches=matches, transform=None, covariance=None,
                         timings_ms={"total": round((clock() - t0) * 1e3, 3)})
    return MatchOutcome(result=result, assignment=assignment, proposed=assignment)


METHODS = ("verified", "paper", "cos-hungarian")
# the neural solver in each mode, beside the default solver (`<mode>-<solver>`)
NGM_METHODS = ("verified-ngm", "paper-ngm")


def method_config(method: str, base: MatchConfig | None) -> MatchConfig:
    """`base` with the method's mode set, and its solver when the method names one."""
    mode, _, solver = method.partition("-")
    return match_config(base, mode=mode, **({"solver": {"name": solver}} if solver else {}))


# ============================================================================================
# The matrix
# ============================================================================================


@dataclass(frozen=True)
class Cell:
    """One combination of the matrix. frame: `conv` or `map_conv>sub_conv`."""

    name: str
    family: str  # kitti00 | pool | gen-kitti | gen-pool
    frame: str = "enu"
    vertical: bool = False  # declare `up` in both files
    dim: int = 384
    n_map: int = 600
    lookalike: str = "base"
    duplicates: float = 0.0
    noise: str = "base"
    n_cases: int = 8
    sub_size: int = 20
    n_false: int = 2
    paper_cases: int = 2
    varies: str = "base"  # which factor this cell varies around its family's base

    def conventions(self) -> tuple[str, str]:
        a, _, b = self.frame.partition(">")
        return a, b or a

    def spec(self) -> WorldSpec:
        return WorldSpec(self.family, self.n_map, self.dim, self.lookalike, self.duplicates,
                         self.noise, self.n_cases, self.sub_size, self.n_false)

    def needs(self) -> tuple[str, ...]:
        return {"kitti00": (KITTI_GT, KITTI_ORB, DINO_CENTROIDS),
                "pool": (DINO_CENTROIDS,)}.get(self.family, ())


def full_plan() -> list[Cell]:
    """A base cell per world family, one-factor variations around it, a few combined hard
    cells. Bases use each world's native convention without a declared vertical (what outside
    data looks like); `+up` cells declare it."""
    kb = Cell("kitti00", "kitti00", frame="camera", n_map=600, n_cases=8, sub_size=20,
              n_false=2, paper_cases=2)
    pb = Cell("pool", "pool", frame="ned", n_map=30, n_cases=16, sub_size=0, n_false=1,
              paper_cases=16)
    gk = Cell("gen-kitti", "gen-kitti", frame="enu", n_map=605, n_cases=6, paper_cases=1)
    gp = Cell("gen-pool", "gen-pool", frame="enu", n_map=0, n_cases=12, sub_size=0,
              paper_cases=12)
    cells = [kb]
    for fr in ("enu", "ned", "random", "camera>enu"):
        cells.append(replace(kb, name=f"kitti00/{fr}", frame=fr, varies="frame", paper_cases=1))
    for fr in ("camera", "random", "camera>enu"):
        cells.append(replace(kb, name=f"kitti00/{fr}+up", frame=fr, vertical=True,
                             varies="frame+up", paper_cases=1))
    for d in (128, 768):
        cells.append(replace(kb, name=f"kitti00/d{d}", dim=d, varies="dim", paper_cases=1))
    for n in (2000, 5000):
        cells.append(replace(kb, name=f"kitti00/map{n}", n_map=n, varies="map size",
                             n_cases=6, paper_cases=0))
    cells += [
        replace(kb, name="kitti00/lookalike-high", lookalike="high", varies="look-alikes",
                paper_cases=1),
        replace(kb, name="kitti00/dup15%", duplicates=0.15, varies="duplicates", paper_cases=1),
        replace(kb, name="kitti00/noise-high", noise="high", varies="range noise",
                paper_cases=1),
        replace(kb, name="kitti00/sub8", sub_size=8, n_false=1, varies="submap size",
                paper_cases=1),
    ]
    cells.append(pb)
    for fr in ("enu", "camera", "random", "ned>enu", "ned>camera"):
        cells.append(replace(pb, name=f"pool/{fr}", frame=fr, varies="frame"))
    for fr in ("ned", "random", "ned>camera"):
        cells.append(replace(pb, name=f"pool/{fr}+up", frame=fr, vertical=True,
                             varies="frame+up"))
    for d in (128, 768):
        cells.append(replace(pb, name=f"pool/d{d}", dim=d, varies="dim"))
    cells += [
        replace(pb, name="pool/map300", n_map=300, varies="map size", paper_cases=8),
        replace(pb, name="pool/lookalike-high", lookalike="high", varies="look-alikes"),
        replace(pb, name="pool/lookalike-low", lookalike="low", varies="look-alikes"),
        replace(pb, name="pool/dup15%", duplicates=0.15, varies="duplicates"),
        replace(pb, name="pool/noise-high", noise="high", varies="range noise"),
    ]
    cells.append(gk)
    for fr in ("camera", "ned", "random", "enu>camera"):
        cells.append(replace(gk, name=f"gen-kitti/{fr}", frame=fr, varies="frame"))
    cells.append(replace(gk, name="gen-kitti/camera+up", frame="camera", vertical=True,
                         varies="frame+up"))
    cells.append(gp)
    for fr in ("camera", "ned", "random", "enu>ned"):
        cells.append(replace(gp, name=f"gen-pool/{fr}", frame=fr, varies="frame"))
    cells.append(replace(gp, name="gen-pool/enu>ned+up", frame="enu>ned", vertical=True,
                         varies="frame+up"))
    # combined hard cells
    cells += [
        replace(kb, name="hard/kitti00-random-d768-lookalike-dup", frame="random", dim=768,
                lookalike="high", duplicates=0.15, varies="combined", paper_cases=1),
        replace(kb, name="hard/kitti00-map5000-camera>ned-d128-noise", frame="camera>ned",
                n_map=5000, dim=128, noise="high", varies="combined", n_cases=6,
                paper_cases=0),
        replace(kb, name="hard/kitti00-map5000-camera>ned-d128-noise+up", frame="camera>ned",
                vertical=True, n_map=5000, dim=128, noise="high", varies="combined",
                n_cases=6, paper_cases=0),
        replace(pb, name="hard/pool-ned>camera-noise-dup-lookalike", frame="ned>camera",
                noise="high", duplicates=0.15, lookalike="high", varies="combined"),
        replace(pb, name="hard/pool-ned>camera-noise-dup-lookalike+up", frame="ned>camera",
                vertical=True, noise="high", duplicates=0.15, lookalike="high",
                varies="combined"),
    ]
    return cells


def quick_plan() -> list[Cell]:
    """A few small cells for CI (well under a minute): the pool in its native and two foreign
    frames, with and without `up`, a small KITTI-00 map, the project's pool generator rotated."""
    pb = Cell("pool", "pool", frame="ned", n_map=30, n_cases=6, sub_size=0, n_false=1,
              paper_cases=3)
    kb = Cell("kitti00/map200", "kitti00", frame="camera", n_map=200, n_cases=3, sub_size=12,
              n_false=2, paper_cases=1, varies="map size")
    return [
        pb,
        replace(pb, name="pool/ned>camera", frame="ned>camera", varies="frame"),
        replace(pb, name="pool/ned>camera+up", frame="ned>camera", vertical=True,
                varies="frame+up"),
        replace(pb, name="pool/random/d128", frame="random", dim=128, varies="frame+dim"),
        kb,
        replace(kb, name="kitti00/map200/enu+up", frame="enu", vertical=True,
                varies="frame+up"),
        Cell("gen-pool/camera", "gen-pool", frame="camera", n_map=0, n_cases=4, sub_size=0,
             paper_cases=2, varies="frame"),
    ]


@dataclass
class _Data:
    data_dir: Path
    gt: np.ndarray | None = None
    est: np.ndarray | None = None
    dino: np.ndarray | None = None

    def load(self, names: Iterable[str]) -> None:
        for n in names:
            if n == KITTI_GT and self.gt is None:
                self.gt = load_kitti_poses_34(self.data_dir / n)
            elif n == KITTI_ORB and self.est is None:
                self.est = load_kitti_poses_34(self.data_dir / n)
            elif n == DINO_CENTROIDS and self.dino is None:
                self.dino = load_dino_centroids(self.data_dir / n)


def build_world(cell: Cell, seed: int, data: _Data) -> World:
    """The cell's world (gravity-aligned), for one seed."""
    spec = cell.spec()
    data.load(cell.needs())
    if cell.family == "kitti00":
        if data.gt is None or data.est is None:  # cell.needs() names both: loaded above
            raise InputError(f"{cell.name} needs {KITTI_GT} and {KITTI_ORB} in {data.data_dir}")
        return kitti_world(spec, seed, data.gt, data.est, data.dino)
    if cell.family == "pool":
        return pool_world(spec, seed, data.dino)
    return generator_world(spec, seed)


def _expressed(cell: Cell, seed: int, data: _Data) -> list[Scenario]:
    """`cell_scenarios` with the data already loaded (shared across the cells)."""
    world = build_world(cell, seed, data)
    rng = np.random.default_rng([seed, 9, 3])
    a, b = cell.conventions()
    C_map = convention_rotation(a, rng)
    C_sub = C_map if b == a else convention_rotation(b, rng)
    return express(world, C_map, C_sub, cell.vertical)


def cell_scenarios(cell: Cell, seed: int, data_dir: Path | None = None) -> list[Scenario]:
    """The cell's cases as parsed `match` files in its conventions, with their truth."""
    return _expressed(cell, seed, _Data(Path(data_dir or DEFAULT_DATA_DIR)))


UNRELATED_CASES = 4  # per cell and seed
UNRELATED_SEED = 100_000  # the other world's seed: this seed plus this


def unrelated_pairs(cell: Cell, seed: int, data: _Data, scenarios: Sequence[Scenario]
                    ) -> list[tuple[ObjectMap, Submap]]:
    """(map, submap) pairs whose submap is of a place the map does not hold: the same cell's
    world for another seed (its own objects and layout; their embeddings as unlike this map's
    as two unrelated objects') against this seed's maps. Every match an answer returns on them
    is wrong."""
    others = _expressed(cell, seed + UNRELATED_SEED, data)
    n = min(UNRELATED_CASES, len(scenarios), len(others))
    return [(scenarios[j].map, others[j].submap) for j in range(n)]


def lacking_pairs(scenarios: Sequence[Scenario]) -> list[tuple[ObjectMap, Submap]]:
    """(map, submap) pairs whose map lacks the submap's place, the harder probe: each of the
    first scenarios' maps without the submap's own objects (and their duplicates). The same
    kinds of objects in the same layout remain, as at an unmapped corner of a mapped site."""
    out = []
    for sc in scenarios[:UNRELATED_CASES]:
        gone = {t for t in sc.truth.values() if t}
        gone.update(x for v in sc.equivalent.values() for x in v)
        kept = [o for o in sc.map.objects if o.id not in gone]
        out.append((sc.map.model_copy(update={"objects": kept}), sc.submap))
    return out


# ------------------------------------------------------------------ scoring


def confusers(sc: Scenario) -> float:
    """Look-alike density seen by a case: per matchable submap object, how many map objects
    (not the same physical object) are closer by cosine than its true match; the mean."""
    m, s = sc.map.arrays(), sc.submap.arrays()
    index = {oid: k for k, oid in enumerate(m.ids)}
    counts = []
    for j, sid in enumerate(s.ids):
        true = sc.truth.get(sid)
        if true is None:
            continue
        same = {index[x] for x in sc.equivalent.get(sid, (true,))}
        cos = m.unit_embeddings_nd @ s.unit_embeddings_nd[j]
        best_true = max(cos[k] for k in same)
        closer = cos > best_true
        closer[list(same)] = False
        counts.append(int(closer.sum()))
    return float(np.mean(counts)) if counts else float("nan")


def score(sc: Scenario, outcome: MatchOutcome) -> dict[str, Any]:
    """score_case (scoring.py) plus node accuracy over every submap object (a false detection is
    right when left unmatched), the reason and the exact stage's budget state."""
    base = score_case(sc, outcome)
    n = base["matchable"] + base["outliers"]
    right_matchable = base["accuracy"] * base["matchable"]
    exact = outcome.exact
    return {
        **base,
        "node_accuracy": (right_matchable + base["outliers_unmatched"]) / max(n, 1.0),
        "reason": outcome.result.reason.value,
        "latency_ms": float(outcome.result.timings_ms.get("total", float("nan"))),
        "exact_ms": float(outcome.result.timings_ms.get("exact", float("nan"))),
        "exact_budget_hit": bool(exact is not None and not exact.optimal),
        "search_incomplete": outcome.result.reason is RejectReason.SEARCH_INCOMPLETE,
    }


def _run_method(method: str, map_: ObjectMap, sub: Submap, configs: dict[str, MatchConfig]
                ) -> MatchOutcome:
    if method == "cos-hungarian":
        return cosine_hungarian_outcome(map_, sub)
    if method == KISS_METHOD:
        return kiss_outcome(map_, sub)
    return match(map_, sub, configs[method])


def _probe(pairs: Sequence[tuple[ObjectMap, Submap]], methods: Sequence[str],
           configs: dict[str, MatchConfig]) -> dict[str, dict[str, int]]:
    """Per method (paper mode excluded: it accepts nothing): the pairs, the answers accepted
    and the matches they return (every one wrong: the map lacks the submap's place)."""
    out = {m: {"cases": 0, "accepted": 0, "matches": 0}
           for m in methods if not m.startswith("paper")}
    for mp, sub in pairs:
        for m, u in out.items():
            res = _run_method(m, mp, sub, configs).result
            u["cases"] += 1
            u["accepted"] += int(res.accepted)
            u["matches"] += len(res.matches) if res.accepted else 0
    return out


def _percentile(values: list[float], q: float) -> float:
    """Percentile of the finite values (the exact stage runs only in verified mode)."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    return float(np.percentile(v, q)) if len(v) else float("nan")


def summarize(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """One method on one cell and seed: rates over its cases."""
    if not rows:
        return {"cases": 0}
    acc_returned = sum(r["acc_returned"] for r in rows)
    matchable = sum(r["matchable"] for r in rows)
    lat = np.array([r["latency_ms"] for r in rows])
    rot = [r["rot_err_deg"] for r in rows if np.isfinite(r["rot_err_deg"])]
    reasons: dict[str, int] = {}
    for r in rows:
        reasons[r["reason"]] = reasons.get(r["reason"], 0) + 1
    return {
        "cases": len(rows),
        "node_accuracy": float(np.mean([r["node_accuracy"] for r in rows])),
        "paper_accuracy": float(np.mean([r["accuracy"] for r in rows])),
        "precision": sum(r["acc_right"] for r in rows) / acc_returned if acc_returned else
        float("nan"),
        "recall": sum(r["acc_right"] for r in rows) / matchable if matchable else float("nan"),
        "accepted": int(sum(r["accepted"] for r in rows)),
        "accepted_fraction": float(np.mean([r["accepted"] for r in rows])),
        "wrong_accepted": int(sum(r["acc_returned"] - r["acc_right"] for r in rows)),
        "latency_p50_ms": float(np.percentile(lat, 50)),
        "latency_p99_ms": float(np.percentile(lat, 99)),
        "exact_p50_ms": _percentile([r.get("exact_ms", np.nan) for r in rows], 50),
        "exact_p99_ms": _percentile([r.get("exact_ms", np.nan) for r in rows], 99),
        "exact_budget_hits": int(sum(r["exact_budget_hit"] for r in rows)),
        "search_incomplete": int(sum(r["search_incomplete"] for r in rows)),
        "rot_err_deg_median": float(np.median(rot)) if rot else float("nan"),
        "reasons": reasons,
    }


SPREAD_KEYS = ("node_accuracy", "paper_accuracy", "precision", "recall", "accepted_fraction",
               "latency_p50_ms", "latency_p99_ms", "exact_p50_ms", "exact_p99_ms",
               "exact_budget_hits", "rot_err_deg_median")


def _spread(values: list[float]) -> dict[str, float]:
    a = np.asarray([v for v in values if np.isfinite(v)], dtype=np.float64)
    if len(a) == 0:
        return {"median": float("nan"), "min": float("nan"), "max": float("nan")}
    return {"median": float(np.median(a)), "min": float(a.min()), "max": float(a.max())}


def over_seeds(per_seed: list[dict[str, Any]]) -> dict[str, Any]:
    """Median and [min, max] over seeds of each rate; counts summed."""
    per_seed = [p for p in per_seed if p.get("cases")]
    if not per_seed:
        return {"cases": 0}
    reasons: dict[str, int] = {}
    for p in per_seed:
        for k, v in p["reasons"].items():
            reasons[k] = reasons.get(k, 0) + v
    out: dict[str, Any] = {k: _spread([p[k] for p in per_seed]) for k in SPREAD_KEYS}
    for probe in ("unrelated", "lacking"):
        if all(probe in p for p in per_seed):
            out[probe] = {k: sum(p[probe][k] for p in per_seed)
                          for k in ("cases", "accepted", "matches")}
    out.update(cases=sum(p["cases"] for p in per_seed),
               accepted=sum(p["accepted"] for p in per_seed),
               wrong_accepted=sum(p["wrong_accepted"] for p in per_seed),
               search_incomplete=sum(p["search_incomplete"] for p in per_seed),
               exact_budget_hits_total=sum(p["exact_budget_hits"] for p in per_seed),
               seeds=len(per_seed), reasons=reasons)
    return out


# ------------------------------------------------------------------ the run


@dataclass
class GeneralizePlan:
    """What `mergesvc bench generalize` runs."""

    cells: list[Cell]
    seed: int = 0
    seeds: int = 1
    methods: tuple[str, ...] = METHODS + NGM_METHODS
    paper_max_map: int = 700  # paper mode's dense K: only maps up to this size
    data_dir: Path = field(default_factory=lambda: DEFAULT_DATA_DIR)

    @classmethod
    def quick(cls, seed: int = 0, seeds: int = 1, data_dir: Path | None = None
              ) -> GeneralizePlan:
        return cls(quick_plan(), seed, seeds, data_dir=Path(data_dir or DEFAULT_DATA_DIR))

    @classmethod
    def full(cls, seed: int = 0, seeds: int = 1, data_dir: Path | None = None
             ) -> GeneralizePlan:
        return cls(full_plan(), seed, seeds, data_dir=Path(data_dir or DEFAULT_DATA_DIR))

    def steps(self) -> int:
        """Number of (cell, seed, case) units, for a progress bar."""
        return sum(c.n_cases for c in self.cells) * self.seeds


def run_generalize(
    plan: GeneralizePlan,
    progress: Callable[[str, int], Any] | None = None,
    base: MatchConfig | None = None,
) -> dict[str, Any]:
    """Run the matrix. progress(message, cases done) after each case. Verified and paper mode
    are `base` (default: the defaults) with the mode set. Returns a JSON-ready report: per
    cell its settings, skip note (missing data, no `up` field), and per method the rates over
    seeds (median, min, max) and per seed; plus every case's record. InputError for
    plan.seeds below 1."""
    check_count("seeds", plan.seeds)
    t_start = time.perf_counter()
    configs = {m: method_config(m, base) for m in plan.methods
               if m not in ("cos-hungarian", KISS_METHOD)}
    if KISS_METHOD in plan.methods:
        load_kiss()  # InputError, before any world is built, when the peer is not installed
    data = _Data(Path(plan.data_dir))
    has_up = supports_up()
    report: dict[str, Any] = {
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": f"{platform.machine()} {platform.python_version()}",
        "data_dir": str(plan.data_dir),
        "seed": plan.seed,
        "seeds": plan.seeds,
        "methods": list(plan.methods),
        "settings": {k: v.model_dump(mode="json") for k, v in configs.items()},
        "paper_max_map": plan.paper_max_map,
        "cells": {},
        "cases": [],
    }
    done = 0
    for cell in plan.cells:
        entry: dict[str, Any] = {"cell": asdict(cell), "skipped": None, "methods": {}}
        report["cells"][cell.name] = entry
        missing = [n for n in cell.needs() if not (Path(plan.data_dir) / n).is_file()]
        if missing:
            entry["skipped"] = f"data absent: {', '.join(missing)}"
        elif cell.vertical and not has_up:
            entry["skipped"] = "this build's files have no `up` field"
        if entry["skipped"]:
            log.info("%s skipped: %s", cell.name, entry["skipped"])
            done += cell.n_cases * plan.seeds
            if progress:
                progress(f"{cell.name}: skipped", done)
            continue
        per_seed: dict[str, list[dict[str, Any]]] = {m: [] for m in plan.methods}
        notes: list[str] = []
        confusion: list[float] = []
        n_map = 0
        for s in range(plan.seeds):
            seed = plan.seed + s
            scenarios = _expressed(cell, seed, data)
            rows: dict[str, list[dict[str, Any]]] = {m: [] for m in plan.methods}
            for k, sc in enumerate(scenarios):
                n_map = len(sc.map.objects)
                confusion.append(confusers(sc))
                for method in plan.methods:
                    if method.startswith("paper") and (k >= cell.paper_cases
                                              or n_map > plan.paper_max_map):
                        continue
                    outcome = _run_method(method, sc.map, sc.submap, configs)
                    rec = score(sc, outcome)
                    rec.update(cell=cell.name, seed=seed, case=k, method=method,
                               n_sub=len(sc.submap.objects), n_map=n_map)
                    rows[method].append(rec)
                    report["cases"].append(rec)
                done += 1
                if progress:
                    progress(f"{cell.name} seed {seed} case {k}", done)
            # how often each method accepts a place the map lacks: a submap of another world,
            # and the map without the submap's own objects
            probes = {"unrelated": unrelated_pairs(cell, seed, data, scenarios),
                      "lacking": lacking_pairs(scenarios)}
            counts = {p: _probe(pairs, plan.methods, configs) for p, pairs in probes.items()}
            if progress:
                progress(f"{cell.name} seed {seed}: places the map lacks", done)
            for m in plan.methods:
                per_seed[m].append(summarize(rows[m]))
                for p, c in counts.items():
                    if m in c and per_seed[m][-1].get("cases"):
                        per_seed[m][-1][p] = c[m]
        if any(m.startswith("paper") for m in plan.methods) and (
                cell.paper_cases == 0 or n_map > plan.paper_max_map):
            notes.append(f"paper skipped (map {n_map} objects > {plan.paper_max_map} or capped)")
        entry["notes"] = notes
        entry["n_map"] = n_map
        entry["confusers_mean"] = float(np.nanmean(confusion)) if confusion else float("nan")
        for m in plan.methods:
            entry["methods"][m] = {"over_seeds": over_seeds(per_seed[m]),
                                   "per_seed": per_seed[m]}
    report["ngm_vs_default"] = ngm_comparison(report)
    report["elapsed_s"] = round(time.perf_counter() - t_start, 1)
    report["markdown"] = markdown(report)
    return report


# the neural solver's target in verified mode (issue 28): node accuracy within this much of the
# default solver's, at a p50 latency at most this many times its
NGM_ACC_TOLERANCE = 0.02
NGM_P50_RATIO = 2.0


def ngm_comparison(report: dict[str, Any]) -> dict[str, dict[str, dict[str, Any]]]:
    """Per cell and mode, NGM against the default solver on the same cases: node accuracy,
    precision and p50 latency (medians over seeds), and in verified mode whether NGM meets the
    target (NGM_ACC_TOLERANCE, NGM_P50_RATIO)."""
    out: dict[str, dict[str, dict[str, Any]]] = {}
    for name, e in report["cells"].items():
        for mode in ("verified", "paper"):
            base = e["methods"].get(mode, {}).get("over_seeds", {})
            ngm = e["methods"].get(f"{mode}-ngm", {}).get("over_seeds", {})
            if not (base.get("cases") and ngm.get("cases")):
                continue
            row = {k: {"default": base[k]["median"], "ngm": ngm[k]["median"]}
                   for k in ("node_accuracy", "precision", "latency_p50_ms")}
            row["node_accuracy_diff"] = ngm["node_accuracy"]["median"] - \
                base["node_accuracy"]["median"]
            row["p50_ratio"] = ngm["latency_p50_ms"]["median"] / \
                max(base["latency_p50_ms"]["median"], 1e-9)
            if mode == "verified":
                row["meets_target"] = bool(row["node_accuracy_diff"] >= -NGM_ACC_TOLERANCE
                                           and row["p50_ratio"] <= NGM_P50_RATIO)
            out.setdefault(name, {})[mode] = row
    return out


def ngm_markdown(comparison: dict[str, dict[str, dict[str, Any]]]) -> str:
    """NGM against the default solver, one row per cell and mode (empty without NGM)."""
    if not comparison:
        return ""
    lines = ["| cell | mode | node acc default / NGM | diff | precision default / NGM "
             "| p50 ms default / NGM | p50 ratio | target met |",
             "|---|---|---|---|---|---|---|---|"]
    met = total = 0
    for name, modes in comparison.items():
        for mode, r in modes.items():
            target = "-"
            if "meets_target" in r:
                total += 1
                met += r["meets_target"]
                target = "yes" if r["meets_target"] else "no"
            na, pr, lat = r["node_accuracy"], r["precision"], r["latency_p50_ms"]
            lines.append(
                f"| {name} | {mode} | {na['default']:.2f} / {na['ngm']:.2f} "
                f"| {r['node_accuracy_diff']:+.2f} | {_num(pr['default'])} / {_num(pr['ngm'])} "
                f"| {lat['default']:.1f} / {lat['ngm']:.1f} | {r['p50_ratio']:.2f} | {target} |")
    lines.append("")
    lines.append(f"NGM in verified mode within {NGM_ACC_TOLERANCE} node accuracy of the default "
                 f"solver at a p50 at most {NGM_P50_RATIO:g}x: {met} of {total} cells.")
    return "\n".join(lines)


def _num(x: float) -> str:
    return f"{x:.2f}" if np.isfinite(x) else "-"


def _fmt(s: dict[str, float] | None, digits: int = 2, seeds: int = 1) -> str:
    if not s or not np.isfinite(s.get("median", float("nan"))):
        return "-"
    med = f"{s['median']:.{digits}f}"
    if seeds > 1 and s["max"] > s["min"]:
        return f"{med} [{s['min']:.{digits}f}-{s['max']:.{digits}f}]"
    return med


def _probed(o: dict[str, Any], probe: str) -> str:
    u = o.get(probe)
    return f"{u['accepted']}/{u['cases']} ({u['matches']})" if u and u["cases"] else "-"


def markdown(report: dict[str, Any]) -> str:
    """The report as a markdown table: one row per cell and method."""
    seeds = int(report.get("seeds", 1))
    lines = [
        "| cell | varies | map | method | node acc | precision | recall | accepted "
        "| unrelated accepted | lacking accepted | p50 ms | p99 ms | exact p50/p99 ms "
        "| budget hits | look-alikes | reasons |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    skipped = []
    for name, e in report["cells"].items():
        if e["skipped"]:
            skipped.append(f"- {name}: skipped ({e['skipped']})")
            continue
        for m, r in e["methods"].items():
            o = r["over_seeds"]
            if not o.get("cases"):
                continue
            reasons = ", ".join(f"{k} {v}" for k, v in sorted(o["reasons"].items(),
                                                              key=lambda kv: -kv[1]))
            hits = o.get("exact_budget_hits_total", "-") if m.startswith("verified") else "-"
            exact = (f"{_fmt(o.get('exact_p50_ms'), 1, 1)} / {_fmt(o.get('exact_p99_ms'), 1, 1)}"
                     if m.startswith("verified") else "-")
            lines.append(
                f"| {name} | {e['cell']['varies']} | {e['n_map']} | {m} "
                f"| {_fmt(o['node_accuracy'], 2, seeds)} | {_fmt(o['precision'], 2, seeds)} "
                f"| {_fmt(o['recall'], 2, seeds)} | {o['accepted']}/{o['cases']} "
                f"| {_probed(o, 'unrelated')} | {_probed(o, 'lacking')} "
                f"| {_fmt(o['latency_p50_ms'], 1, seeds)} "
                f"| {_fmt(o['latency_p99_ms'], 1, seeds)} "
                f"| {exact} | {hits} | {e['confusers_mean']:.1f} | {reasons} |"
            )
        for note in e.get("notes", []):
            skipped.append(f"- {name}: {note}")
    text = "\n".join(lines)
    if skipped:
        text += "\n\n" + "\n".join(skipped)
    text += (
        "\n\nnode acc: right submap objects / all submap objects (a false detection or an "
        "object not in the map is right when left unmatched), on every returned answer; "
        "precision / recall: matches of accepted answers only; budget hits: cases whose exact "
        "stage stopped at its budget unproven (search_incomplete among the reasons when that "
        "rejected an answer); unrelated accepted: submaps of the cell's world for another "
        "seed (other objects, another layout) accepted against this one's maps, and the "
        "matches they returned (all wrong); lacking accepted: the same for each of those maps "
        "without the submap's own objects (the same kinds, the same layout); look-alikes: mean map "
        "objects closer by cosine than the true match, per matchable submap object."
    )
    if report.get("ngm_vs_default"):
        text += "\n\n### NGM against the default solver\n\n" + ngm_markdown(
            report["ngm_vs_default"])
    return text


__all__ = [
    "METHODS",
    "NGM_METHODS",
    "Cell",
    "GeneralizePlan",
    "build_world",
    "cell_scenarios",
    "confusers",
    "cosine_hungarian",
    "cosine_hungarian_outcome",
    "full_plan",
    "lacking_pairs",
    "markdown",
    "method_config",
    "ngm_comparison",
    "ngm_markdown",
    "over_seeds",
    "quick_plan",
    "run_generalize",
    "score",
    "summarize",
    "unrelated_pairs",
]
