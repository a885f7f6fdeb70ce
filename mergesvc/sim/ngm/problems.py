"""Training problems for the NGM solver, drawn from the project's own generators only (never
the real trajectories or embeddings in ../shared/data that evaluate it).

Each problem is one map / submap pair in one of the two formulations the pipeline hands a
solver: `paper` (the dense K over all pairs, paper_K, on a spatial crop of a large map) or
`verified` (K over the top-k candidates, candidate_K, its edge entries rescaled to [0, 1] as
pipeline.py does for NGM), with the truth as a 0/1 target per pair. Worlds: the pool runs of
Table I and the drive of Table II at other seeds, directly drawn scenarios (2-40 objects
against maps of 20-1,000, outliers, look-alikes) and harbour pools in several axis conventions.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from mergesvc.core.affinity import (
    candidate_K,
    edge_pair_weight,
    edge_scales,
    paper_K,
    paper_node_affinity,
)
from mergesvc.core.candidates import retrieve
from mergesvc.core.config import MatchConfig, match_config
from mergesvc.core.model import ObjectArrays
from mergesvc.sim.conventions import convention_rotation
from mergesvc.sim.runs import drive_run, underwater_run
from mergesvc.sim.scenario import Family, Scenario, make_scenario
from mergesvc.sim.worlds import WorldSpec, express, pool_world

# Seeds of the evaluated worlds are small (bench paper: 0; bench generalize: 0, 1, 2, ...):
# training worlds start far above them.
SEED_BASE = 100_000
SOURCES = ("uw-run", "drive", "uw-scenario", "kitti-scenario", "pool")
AFFINITIES = ("ucos", "bhattacharyya", "mahalanobis")
CONVENTIONS = ("enu", "ned", "camera", "random")


@dataclass(frozen=True)
class NGMProblem:
    """One training problem: NGM's input over m pairs and the truth.

    K: (m, m) float32, node affinity on the diagonal, edge affinity in [0, 1] off it;
    rows, cols: (m,) int, the pair's submap and map (or local candidate) index;
    target: (m,) float32, 1 where the pair is a true match (any duplicate of it counts)."""

    K: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    n1: int
    n2: int
    target: np.ndarray
    kind: str  # paper | verified
    source: str

    @property
    def m(self) -> int:
        return len(self.rows)

    @property
    def matchable(self) -> int:
        """Submap objects whose true match is among the pairs."""
        return len(np.unique(self.rows[self.target > 0]))


def _targets(sc: Scenario, sub: ObjectArrays, map_ids: list[str], rows: np.ndarray,
             cols: np.ndarray) -> np.ndarray:
    return np.array([sc.is_correct(sub.ids[r], map_ids[c]) for r, c in zip(rows, cols)],
                    dtype=np.float32)


def _crop(sc: Scenario, map_: ObjectArrays, keep: int, rng: np.random.Generator
          ) -> np.ndarray:
    """Indices of `keep` map objects: those nearest the true matches and a few random places
    (whole neighbourhoods, so the radius graph inside the crop looks like the full map's)."""
    if map_.n <= keep:
        return np.arange(map_.n)
    index = {oid: k for k, oid in enumerate(map_.ids)}
    true = [index[m] for m in sc.truth.values() if m is not None and m in index]
    centres = list(true[:1]) + list(rng.choice(map_.n, size=3, replace=False))
    d = np.min(np.linalg.norm(map_.position_xyz_m[:, None, :]
                              - map_.position_xyz_m[centres][None, :, :], axis=2), axis=1)
    return np.sort(np.argsort(d, kind="stable")[:keep])


def paper_problem(sc: Scenario, cfg: MatchConfig, rng: np.random.Generator,
                  max_pairs: int, source: str) -> NGMProblem:
    """Paper mode's dense K (pygmtools' column-major order) on the scenario, the map cropped
    to at most max_pairs pairs; scales (sigma, radius) from the whole map, as paper mode does."""
    sub, full = sc.submap.arrays(), sc.map.arrays()
    sigma_m, radius_m = edge_scales(full, cfg.affinity)
    pick = _crop(sc, full, max(max_pairs // sub.n, 2), rng)
    map_ = full.subset(pick) if len(pick) < full.n else full
    A = paper_node_affinity(sub, map_, cfg.affinity)
    K = paper_K(A, sub, map_, sigma_m, radius_m)
    n1, n2 = sub.n, map_.n
    cols, rows = np.divmod(np.arange(n1 * n2), n1)
    return NGMProblem(K.astype(np.float32), rows, cols, n1, n2,
                      _targets(sc, sub, map_.ids, rows, cols), "paper", source)


def verified_problem(sc: Scenario, cfg: MatchConfig, rng: np.random.Generator, source: str
                     ) -> NGMProblem:
    """Verified mode's K over the top-k candidates (the positive problem RRWM gets), its edge
    entries divided by their weight (what pipeline.py hands NGM)."""
    sub, map_ = sc.submap.arrays(), sc.map.arrays()
    cands, _ = retrieve(sub, map_, cfg.candidates, cfg.affinity, rng)
    sigma_m, _ = edge_scales(map_, cfg.affinity)
    ck = candidate_K(sub, map_, cands.rows, cands.map_nodes, cands.score, cfg.affinity,
                     sigma_m)
    p = ck.positive
    K = p.K / edge_pair_weight(sub.n, cfg.affinity)
    np.fill_diagonal(K, np.diag(p.K))
    ids = [map_.ids[k] for k in ck.local]
    return NGMProblem(K.astype(np.float32), p.rows, p.cols, p.n1, p.n2,
                      _targets(sc, sub, ids, p.rows, p.cols), "verified", source)


# ------------------------------------------------------------------ worlds


def _uw_runs(seed: int, rng: np.random.Generator) -> list[Scenario]:
    run = underwater_run(int(rng.integers(1, 4)), seed)
    return [sc for size in (2, 3, 4, 5) for sc in run.windows(size, 2)]


def _drive(seed: int, rng: np.random.Generator) -> list[Scenario]:
    run = drive_run(seed)
    return run.places(4, int(rng.integers(8, 31)))


def _uw_scenario(seed: int, rng: np.random.Generator) -> list[Scenario]:
    n_sub = int(rng.integers(2, 11))
    return [make_scenario(Family.UNDERWATER, seed, n_map=int(rng.integers(20, 61)),
                          n_sub=n_sub, n_outliers=int(rng.integers(0, 3)),
                          instance_scale=float(rng.uniform(0.25, 0.9)))]


def _kitti_scenario(seed: int, rng: np.random.Generator) -> list[Scenario]:
    n_map = int(np.exp(rng.uniform(np.log(20), np.log(1000))))
    return [make_scenario(Family.KITTI, seed, n_map=n_map,
                          n_sub=int(rng.integers(2, min(40, n_map) + 1)),
                          n_outliers=int(rng.integers(0, 6)),
                          instance_scale=float(rng.uniform(0.15, 0.9)))]


def _pool(seed: int, rng: np.random.Generator) -> list[Scenario]:
    spec = WorldSpec("pool", n_map=int(rng.integers(20, 301)),
                     lookalike=str(rng.choice(["low", "base", "high"])),
                     duplicates=float(rng.choice([0.0, 0.15])),
                     noise=str(rng.choice(["base", "high"])), n_cases=4,
                     sub_size=int(rng.choice([0, 0, 8, 15])), n_false=int(rng.integers(0, 3)))
    world = pool_world(spec, seed, None)  # generated class centroids: no real DINO data
    a, b = rng.choice(CONVENTIONS, size=2)
    conv = np.random.default_rng([seed, 5])
    C_map = convention_rotation(str(a), conv)
    return express(world, C_map, convention_rotation(str(b), conv), bool(rng.random() < 0.5))


WORLDS: dict[str, Callable[[int, np.random.Generator], list[Scenario]]] = {
    "uw-run": _uw_runs, "drive": _drive, "uw-scenario": _uw_scenario,
    "kitti-scenario": _kitti_scenario, "pool": _pool,
}


def problems(
    seed: int, weights: dict[str, float], p_paper: float = 0.5, max_pairs: int = 1600,
    base: MatchConfig | None = None, stream: int = 0,
) -> Iterator[NGMProblem]:
    """An endless seeded stream of training problems: a world from `weights` (source ->
    relative frequency), each of its scenarios in the paper or the verified formulation with a
    random node affinity; paper-mode edge radius the paper's for the world, or derived.
    Streams of one seed (training 0, validation 1) draw disjoint worlds."""
    rng = np.random.default_rng([seed, 28, stream])
    names = sorted(weights)
    p = np.array([weights[k] for k in names], dtype=float)
    p /= p.sum()
    k = 0
    while True:
        source = names[int(rng.choice(len(names), p=p))]
        world_seed = SEED_BASE + 1_000_000 * stream + 10_000 * seed + k % 10_000
        k += 1
        for sc in WORLDS[source](world_seed, rng):
            if not any(m is not None for m in sc.truth.values()):
                continue
            affinity = str(rng.choice(AFFINITIES))
            if rng.random() < p_paper:
                radius = sc.paper_radius_m if rng.random() < 0.7 else None
                cfg = match_config(base, mode="paper", affinity={"kind": affinity,
                                                                  "edge_radius_m": radius})
                yield paper_problem(sc, cfg, rng, max_pairs, source)
            else:
                cfg = match_config(base, affinity={"kind": affinity})
                yield verified_problem(sc, cfg, rng, source)


__all__ = ["SEED_BASE", "SOURCES", "WORLDS", "NGMProblem", "paper_problem", "problems",
           "verified_problem"]
