"""Per-image uncertainty head (Singh & Leonard): a small MLP on a frozen embedding that ranks images
by the backbone's task loss, trained with the pairwise ranking loss of Yoo & Kweon ("learning
loss") / Kirchhof et al., L = max(0, -sign(l1 - l2) * (u(e(x1)) - u(e(x2))) + m). Numpy only.

Leaves: config (UncertaintyConfig), head (features, the ranking loss, UncertaintyHead and its
weight file), training (ranking metrics, evaluate, fit). Import the names from here.
"""

from mergesvc.sim.uncertainty.config import UncertaintyConfig
from mergesvc.sim.uncertainty.head import (
    FORMAT_VERSION,
    UncertaintyHead,
    embedding_features,
    ranking_loss,
)
from mergesvc.sim.uncertainty.training import FitHistory, evaluate, fit, ranking_metrics

__all__ = [
    "FORMAT_VERSION",
    "FitHistory",
    "UncertaintyConfig",
    "UncertaintyHead",
    "embedding_features",
    "evaluate",
    "fit",
    "ranking_loss",
    "ranking_metrics",
]
