"""Matching settings: one pydantic model with a section per stage, and `match_config`, which
builds one from nested override dicts; and the pose graph's settings (`GraphConfig`).

Pure: nothing here reads a file or the environment. The settings file and the `MERGESVC_*`
environment are read by `mergesvc.settings` (the whole settings tree, of which `MatchConfig` is
the `match` section), on the command line's behalf.

Distances left as None are derived from the data (the median spacing of the objects), so one
default works for a 10 m pool and a 2 km drive alike.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from mergesvc.core.calibration import CalibrationConfig
from mergesvc.core.names import MatchMode, NodeAffinity, SearchKind, SolverName
from mergesvc.errors import ConfigError


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class CandidatesConfig(_Section):
    top_k: int = Field(12, ge=1, le=256, description="candidate map objects per submap object")
    prefilter: int = Field(
        256, ge=1, description="cosine shortlist per submap object before the chosen affinity"
    )
    sample: int = Field(512, ge=8, description="map objects sampled for the reference distance")
    guided: bool = Field(
        True, description="after a verified match, add map objects where the transform puts "
        "each submap object and solve again"
    )
    ceiling_quantile: float = Field(
        0.5, ge=0, le=1, description="quantile of the best-candidate lifts that scores 1"
    )
    index: SearchKind = Field(
        SearchKind.AUTO, description="cosine shortlist: exact, ivf (an index built once per "
        "map), or auto (the index for maps of index_min_objects or more, or for "
        "index_min_pairs submap x map pairs on maps of index_min_pairs_map or more)"
    )
    index_min_objects: int = Field(200_000, ge=1, description="auto: the index from here on")
    index_min_pairs: int = Field(
        50_000_000, ge=1, description="auto: the index when submap x map objects reach this")
    index_min_pairs_map: int = Field(
        20_000, ge=1, description="auto: index_min_pairs counts on maps this large only")
    index_lists: int | None = Field(
        None, ge=1, description="index: inverted lists (None: sqrt(map objects), at most 1024)")
    index_probe: int | None = Field(
        None, ge=1, description="index: lists probed per query (None: measured when the index "
        "is built: 1.5 x the fewest that find 99.9 % of the exact top-k of a sample of map rows)")
    index_min_lists: int = Field(
        64, ge=1, description="index: maps with fewer than twice this many objects are searched "
        "exactly")


class AffinityConfig(_Section):
    kind: NodeAffinity = NodeAffinity.UCOS
    normalize_embeddings: bool = Field(
        True, description="Gaussian affinities on unit-norm embeddings (scale invariant)"
    )
    raw_distances: bool = Field(
        False, description="paper mode: feed Gaussian distances in as affinities (authors' code)"
    )
    edge_radius_m: float | None = Field(
        None, gt=0, description="paper-mode edge radius; None: 3 x the median object spacing"
    )
    edge_sigma_m: float | None = Field(
        None, gt=0, description="edge length tolerance; None: spacing_sigma x median spacing"
    )
    spacing_sigma: float = Field(
        0.25, gt=0, description="edge tolerance as a fraction of the median object spacing"
    )
    edge_rel_tol: float = Field(
        0.05, ge=0, description="tolerance growing with edge length (drift, range noise)"
    )
    edge_weight: float = Field(0.5, gt=0, description="verified: weight of geometry vs nodes")
    edge_threshold: float = Field(
        0.3, ge=0, lt=1, description="verified: edge affinity below which a pair counts against"
    )
    node_threshold: float = Field(
        0.6, ge=0, lt=1, description="verified: node score below which a match counts against"
    )


class SolverConfig(_Section):
    name: SolverName = SolverName.RRWM
    max_iter: int = Field(100, ge=1)
    rrwm_alpha: float = Field(0.2, gt=0, lt=1)
    rrwm_beta: float = Field(30.0, gt=0)


class VerifyConfig(_Section):
    exact: bool = Field(True, description="prove the optimum over the candidate set")
    max_nodes: int = Field(200_000, ge=1, description="branch-and-bound node budget")
    time_limit_s: float | None = Field(2.0, gt=0)
    optimality_gap: float = Field(
        0.01, ge=0, description="exact search: proven optimal within this much objective "
        "(a node score is ~1 per object); 0 = exact, slower on maps with near-duplicates"
    )
    conflict_sigmas: float | None = Field(
        6.0, gt=0, description="exact search: two matches whose edge lengths disagree by more "
        "than this many edge tolerances cannot both hold (2 x the 3-sigma residual gate: no "
        "rigid fit keeps both); the consistency graph prunes the search. None: off"
    )
    min_matches: int = Field(3, ge=3, description="matches needed for a 6-DoF transform")
    max_chance_log10: float | None = Field(
        2.0, description="refuse an answer (too_few_matches) when a submap of a place the "
        "map does not hold would give one as good more often than 10^this (log10 of the "
        "a-contrario count of core/chance.py: the matched objects' appearance ranks and how "
        "many map objects lie as close to where the transform puts them). None: off"
    )
    max_chance_log10_large: float = Field(
        0.0, description="the limit for a submap of at least chance_large_objects objects, "
        "whose right answers are far beyond chance (0: expected less than once), where it is "
        "stricter than max_chance_log10; off with it"
    )
    chance_large_objects: int = Field(8, ge=2, description="see max_chance_log10_large")
    min_matches_vertical: int = Field(
        2, ge=2, description="matches needed for the gravity-aligned 4-DoF transform (yaw + "
        "translation) when both frames' verticals are known (declared `up`, or inferred)"
    )
    vertical_sigma_deg: float = Field(
        2.0, gt=0, description="how well each frame's vertical is known (its attitude "
        "sensor's tilt error, deg): a 4-DoF transform's tilt covariance is that of the two "
        "frames' ups, sqrt(2) times this"
    )
    infer_vertical: bool = Field(
        True, description="without a declared `up`, infer a frame's vertical axis from a "
        "flat object layout (see infer_min_objects, infer_max_flatness)"
    )
    infer_min_objects: int = Field(10, ge=4, description="objects needed to infer a vertical")
    infer_max_flatness: float = Field(
        0.3, gt=0, lt=1, description="a vertical is inferred only when the layout's least "
        "spread is at most this fraction of the next (far wider than tall)"
    )
    share_vertical: bool = Field(
        True, description="a submap of fewer than infer_min_objects objects shares the map's "
        "axis (a vehicle cuts submaps from its own map frame); declare `up` where frames differ"
    )
    margin: float = Field(
        0.1, ge=0, description="objective margin a match needs over its best alternative"
    )
    margin_max_matches: int = Field(
        6, ge=0, description="margin test only for solutions with at most this many matches: "
        "more matched objects pin the geometry down by themselves"
    )
    inlier_sigmas: float = Field(3.0, gt=0, description="residual gate in edge tolerances")
    max_tilt_deg: float | None = Field(
        60.0, gt=0, le=180, description="largest angle the transform may turn the vertical by, "
        "where the verticals are known (declared or inferred): distances alone cannot tell a "
        "flat set of objects from its mirror image (a 180 deg flip). None: no tilt test"
    )
    gravity_aligned: bool = Field(
        False, description="when both files declare `up` (an IMU's gravity), fit about it: "
        "yaw + translation (4-DoF, with the tilt prior) instead of a 6-DoF fit whose roll and "
        "pitch few, nearly coplanar objects hardly fix. The service turns it on"
    )


class WindowsConfig(_Section):
    above_objects: int = Field(
        48, ge=4, description="submaps with more objects are matched in spatial windows "
        "(core/windows.py), each verified, then one transform for all"
    )
    window_objects: int = Field(
        32, ge=4, description="most objects per window (windows hold half to all of this)"
    )
    shortlist: int = Field(
        64, ge=1, description="cosine shortlist per object of a windowed submap (an ordinary "
        "one's is candidates.prefilter): its windows' geometry, not a wide shortlist, finds "
        "look-alikes"
    )
    guided: bool = Field(
        False, description="guided step in each window too (candidates.guided); off: the "
        "common transform places every object the windows left (the same node accuracy at "
        "about half the CPU, docs/benchmarks/scale.md)"
    )
    exact: bool = Field(
        False, description="exact search in each window too (verify.exact); off: the windows "
        "verify each other through the transform most of their matches fit (measured: the "
        "same node accuracy at half the time, docs/benchmarks/scale.md)"
    )
    time_limit_s: float = Field(
        0.02, gt=0, description="exact search budget per window (an unproven window's "
        "matches still count where the common transform takes them)"
    )
    margin: bool = Field(
        False, description="margin test in each window too (verify.margin, for windows "
        "proposing few matches); off: the common transform judges them (it was 87 % of a "
        "5,000-object submap's time, docs/benchmarks/scale.md)"
    )


class MatchConfig(_Section):
    mode: MatchMode = MatchMode.VERIFIED
    seed: int = 0
    candidates: CandidatesConfig = CandidatesConfig()
    affinity: AffinityConfig = AffinityConfig()
    solver: SolverConfig = SolverConfig()
    verify: VerifyConfig = VerifyConfig()
    windows: WindowsConfig = WindowsConfig()


def _merge(base: dict[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """Merge `over` into `base` (nested dicts merged, anything else replaced); returns base."""
    for k, v in over.items():
        old = base.get(k)
        base[k] = _merge(old if isinstance(old, dict) else {}, v) if isinstance(v, Mapping) else v
    return base


def match_config(
    base: MatchConfig | Mapping[str, Any] | None = None, /, **overrides: Any
) -> MatchConfig:
    """A MatchConfig: `base` (default: the defaults) with `overrides` merged in, nested dicts
    by section, e.g. `match_config(mode="paper", solver={"name": "sm"})`. No file, no
    environment. Raises ConfigError on an invalid or unknown value."""
    if base is None:
        data: dict[str, Any] = {}
    elif isinstance(base, MatchConfig):
        data = base.model_dump()
    else:
        data = copy.deepcopy(dict(base))
    _merge(data, overrides)
    try:
        return MatchConfig.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = ".".join(str(x) for x in err["loc"])
        raise ConfigError(f"invalid settings: {loc}: {err['msg']}") from exc


class GraphConfig(BaseModel):
    """Settings of the global pose graph (core/graph.py)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    inlier_probability: float = Field(
        0.999,
        gt=0,
        lt=1,
        description="TLS threshold: chi-square quantile (6 dof) a correct factor's whitened "
        "residual stays below (synthetic 8-frame graphs: 0.2 % false rejections, 0.9 % at 0.99)",
    )
    outlier_weight: float = Field(0.5, gt=0, lt=1, description="GNC weight below which to flag")
    anchor_sigma: float = Field(
        1e-6, gt=0, description="prior sigma on the anchor frame (rad and m): holds the gauge"
    )
    least_squares_gate: bool = Field(
        True, description="solve least squares first and skip GNC when every factor to judge "
        "is within the TLS threshold there (the solution GNC would keep, at a fraction of its "
        "cost); false: GNC on every solve with factors to judge"
    )
    warm_start: bool = Field(
        True, description="start each solve from the last solution's poses (new nodes chained "
        "from their neighbours); false: from the spanning-tree chain every time"
    )
    fold_hops: int = Field(
        0, ge=0, le=1000,
        description="fold a new factor into a factor of the graph that it agrees with, when "
        "both pairs of ends are at most this many known-inlier (odometry) factors apart (rule "
        "5 of docs/pose_graph.md: bounds a long mission's graph); 0: never fold",
    )
    max_live_nodes: int = Field(
        0, ge=0,
        description="bound the solve (rule 6 of docs/pose_graph.md): a node placed beyond doubt "
        "freezes at its solved pose once this many nodes joined the anchor's component after "
        "it; later solves hold it fixed and solve only the other nodes and the factors that "
        "touch them; 0: never freeze (the whole graph every time; set on a graph with frozen "
        "nodes, it freezes no more and they stay frozen)",
    )
    calibration: CalibrationConfig = Field(
        CalibrationConfig(enabled=False),
        description="scale each factor group's covariances per axis to what the residuals "
        "show (core/calibration.py: variance-component estimation after each solve); off by "
        "default in PoseGraph",
    )
    rigid_chains: str | None = Field(
        None, description="the group prefix of chain factors (a robot's odometry): a chain "
        "whose odometry's shape its other factors do not contradict is solved held to that "
        "shape (core/rigid.py: a likelihood-ratio test); None: never")
    rigid_probability: float = Field(
        0.9, gt=0, lt=1, description="a chain is bent only where that lowers its factors' "
        "summed squared whitened residuals by more than this chi-square quantile of 6 degrees "
        "of freedom (a constant drift rate)")
    rigid_shrink: float = Field(
        1e-4, gt=0.0, le=1.0, description="a rigid chain's factors' covariances are "
        "multiplied by this in its final solve")
    fold_drift: float = Field(
        0.5, gt=0,
        description="fold only where the odometry between the two factors' ends is known this "
        "well: its covariance, whitened by the factor's own, at most this (largest eigenvalue); "
        "where the odometry drifts more, the factor corrects it and is solved",
    )


