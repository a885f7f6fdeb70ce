"""Benchmarks (`mergesvc bench ...`) and their figures.

Leaves: scoring (score_case and helpers shared by the benchmarks), match (`bench match`), paper
(`bench paper`: the paper's tables, the scale sweep), uncertainty (`bench uncertainty`: image
uncertainty, affinity x variances), link (`bench link`), generalize (`bench generalize`),
merge (`bench merge`: its plan, seeds and tables; the in-process fleet it scores is
fleet/replay.py, passed in by cli), soak (`bench soak`: a real `mergesvc serve` process under a
fleet with hostile payloads and kill -9 restarts), qaplib (`bench qaplib`: the exact solver
against QAPLIB's optima), figures.

May import: mergesvc.core, mergesvc.wire, mergesvc.link, mergesvc.sim, mergesvc.errors.
"""

from mergesvc.bench.generalize import METHODS, GeneralizePlan, run_generalize
from mergesvc.bench.link import run_link_bench
from mergesvc.bench.match import run_match_bench
from mergesvc.bench.merge import MergeBenchPlan, run_merge_bench, run_scale_bench
from mergesvc.bench.paper import PaperBenchPlan, run_paper_bench
from mergesvc.bench.scoring import score_case
from mergesvc.bench.soak import SoakPlan, plot_soak, run_soak, soak_summary
from mergesvc.bench.uncertainty import (
    AffinityUncertaintyPlan,
    constant_variance,
    run_affinity_uncertainty_bench,
    run_uncertainty_bench,
)

__all__ = [
    "METHODS",
    "AffinityUncertaintyPlan",
    "GeneralizePlan",
    "MergeBenchPlan",
    "PaperBenchPlan",
    "SoakPlan",
    "constant_variance",
    "plot_soak",
    "run_affinity_uncertainty_bench",
    "run_generalize",
    "run_link_bench",
    "run_match_bench",
    "run_merge_bench",
    "run_paper_bench",
    "run_scale_bench",
    "run_soak",
    "run_uncertainty_bench",
    "score_case",
    "soak_summary",
]
