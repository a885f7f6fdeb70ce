"""The matching settings' fixed vocabularies (plain Enums, no pydantic): what the command line
names. core/config.py uses and re-exports them."""

from __future__ import annotations

from enum import Enum


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


class SearchKind(str, Enum):
    """How the candidate stage finds a submap object's nearest map objects (core/search.py)."""

    AUTO = "auto"  # exact below index_min_objects (and index_min_pairs), the index above
    EXACT = "exact"  # chunked float32 products over every map object
    IVF = "ivf"  # inverted-file index (faiss), re-ranked exactly


__all__ = ["MatchMode", "NodeAffinity", "SearchKind", "SolverName"]
