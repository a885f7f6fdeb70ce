"""Matching settings: one pydantic model with a section per stage, and `match_config`, which
builds one from nested override dicts.

Pure: nothing here reads a file or the environment. The settings file and the `MERGESVC_*`
environment are read by `mergesvc.settings` (the whole settings tree, of which `MatchConfig` is
the `match` section), on the command line's behalf.

Distances left as None are derived from the data (the median spacing of the objects), so one
default works for a 10 m pool and a 2 km drive alike.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from enum import Enum
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from mergesvc.errors import ConfigError


class NodeAffinity(str, Enum):
    UCOS = "ucos"
    BHATTACHARYYA = "bhattacharyya"
    MAHALANOBIS = "mahalanobis"
    LIKELIHOOD_RATIO = "likelihood_ratio"  # eq. LR-3: same object vs unrelated, log-odds


class MatchMode(str, Enum):
    PAPER = "paper"
    VERIFIED = "verified"


class SolverName(str, Enum):
    RRWM = "rrwm"
    SM = "sm"
    IPFP = "ipfp"
    EXACT = "exact"
    NGM = "ngm"  # the neural solver (core/solvers/ngm.py), trained on our formulation


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
    min_matches_vertical: int = Field(
        2, ge=2, description="matches needed for the gravity-aligned 4-DoF transform (yaw + "
        "translation) when both frames' verticals are known (declared `up`, or inferred)"
    )
    vertical_sigma_deg: float = Field(
        2.0, gt=0, description="how well a frame's vertical is known: the tilt prior of a "
        "4-DoF transform's covariance"
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


class MatchConfig(_Section):
    mode: MatchMode = MatchMode.VERIFIED
    seed: int = 0
    candidates: CandidatesConfig = CandidatesConfig()
    affinity: AffinityConfig = AffinityConfig()
    solver: SolverConfig = SolverConfig()
    verify: VerifyConfig = VerifyConfig()


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
        raise ConfigError(f"invalid config: {loc}: {err['msg']}") from exc
