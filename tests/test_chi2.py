"""core/chi2.py: the chi-square quantile without scipy.stats, and the processes that match or
solve graphs starting without scipy.stats."""

from __future__ import annotations

import subprocess
import sys

import pytest
from scipy.stats import chi2

from mergesvc.core.chi2 import chi2_quantile


@pytest.mark.parametrize("dof", [1, 2, 3, 4, 6, 7.5, 12, 60])
def test_the_quantile_is_scipy_stats_own(dof: float) -> None:
    for p in (1e-6, 0.01, 0.25, 0.5, 0.9, 0.95, 0.99, 0.995, 0.999, 0.9999, 1 - 1e-9):
        assert chi2_quantile(p, dof) == float(chi2.ppf(p, dof)), (p, dof)


def test_the_quantile_at_the_ends() -> None:
    assert chi2_quantile(0.0, 6) == 0.0
    assert chi2_quantile(1.0, 6) == float("inf")


@pytest.mark.parametrize("module", ["mergesvc.core.pipeline", "mergesvc.fleet.service",
                                    "mergesvc.fleet.demo", "mergesvc.core.graph"])
def test_matching_and_solving_start_without_scipy_stats(module: str) -> None:
    code = f"import sys, {module}; print('scipy.stats' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=120)
    assert out.stdout.strip() == "False"
