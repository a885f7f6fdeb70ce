"""The chi-square quantile, without scipy.stats.

scipy.stats is slow to import, and every process that matches or solves a graph imports the
modules that need these quantiles (docs/benchmarks/scale.md); scipy.special's inverse
incomplete gamma function is what scipy.stats.chi2.ppf computes, so the values are the same
floats (tests/test_chi2.py).
"""

from __future__ import annotations

from scipy.special import gammaincinv


def chi2_quantile(probability: float, dof: float) -> float:
    """The `probability` quantile of a chi-square of `dof` degrees of freedom (as
    scipy.stats.chi2.ppf)."""
    return float(2.0 * gammaincinv(0.5 * dof, probability))


__all__ = ["chi2_quantile"]
