"""Benchmarks (`mergesvc bench ...`) and their figures.

May import: mergesvc.core, mergesvc.wire, mergesvc.link, mergesvc.sim, mergesvc.errors.
"""

from mergesvc.bench.generalize import METHODS, GeneralizePlan, run_generalize
from mergesvc.bench.suite import (
    AffinityUncertaintyPlan,
    PaperBenchPlan,
    constant_variance,
    run_affinity_uncertainty_bench,
    run_link_bench,
    run_match_bench,
    run_paper_bench,
    run_uncertainty_bench,
    score_case,
)

__all__ = [
    "METHODS",
    "AffinityUncertaintyPlan",
    "GeneralizePlan",
    "PaperBenchPlan",
    "constant_variance",
    "run_affinity_uncertainty_bench",
    "run_generalize",
    "run_link_bench",
    "run_match_bench",
    "run_paper_bench",
    "run_uncertainty_bench",
    "score_case",
]
