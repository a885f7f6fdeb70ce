"""How honest a set of covariances is: relative-pose errors against a reference, whitened.

For each measurement, e = Log(inv(T_true) T_est) in GTSAM's Pose3 tangent order (rotation rad,
then translation m; a right perturbation, as the pose graph models it) and its covariance C:
  - per axis, e_a / sqrt(C_aa): its RMS over the set is 1 on an axis whose sigma is honest,
    below 1 where the covariance is too loose, above where too tight;
  - the NEES e^T C^-1 e, chi-square with 6 degrees of freedom when the covariance is honest:
    the share above its 99 % quantile (16.8) should be about 1 %;
  - the lag-1 correlation of successive errors (per axis, then averaged), which a factor graph
    that treats the measurements as independent ignores.
Pure numpy and GTSAM: no I/O.
"""

from __future__ import annotations

from collections.abc import Sequence

import gtsam
import numpy as np

from mergesvc.core.chi2 import chi2_quantile

NEES_QUANTILE = 0.99
AXES = ("rx", "ry", "rz", "tx", "ty", "tz")


def tangent_error(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """e (6,) with T_est = T_true Exp(e), GTSAM order, of two (4, 4) poses."""
    return np.asarray(gtsam.Pose3.Logmap(gtsam.Pose3(np.asarray(T_true, dtype=np.float64))
                                         .between(gtsam.Pose3(np.asarray(T_est,
                                                                         dtype=np.float64)))))


def whitened_stats(errors: Sequence[np.ndarray], covariances: Sequence[np.ndarray]
                   ) -> dict[str, object]:
    """Per-axis RMS of e_a / sigma_a, the NEES median and the share over the chi-square(6) 99 %
    quantile of (n, 6) errors with (n, 6, 6) covariances; NaN fields for an empty set."""
    e = np.asarray(errors, dtype=np.float64).reshape(-1, 6)
    C = np.asarray(covariances, dtype=np.float64).reshape(-1, 6, 6)
    if not len(e):
        return {"n": 0, "whitened_rms": [float("nan")] * 6, "nees_median": float("nan"),
                "over_99_percent": float("nan")}
    sig = np.sqrt(np.einsum("nii->ni", C))
    z = e / sig
    nees = np.einsum("ni,ni->n", e, np.linalg.solve(C, e[..., None])[..., 0])
    return {"n": len(e),
            "whitened_rms": [float(x) for x in np.sqrt(np.mean(z * z, axis=0))],
            "nees_median": float(np.median(nees)),
            "over_99_percent": float(100.0 * np.mean(nees > chi2_quantile(NEES_QUANTILE, 6)))}


def lag1_correlation(errors: Sequence[np.ndarray], covariances: Sequence[np.ndarray]
                     ) -> float:
    """Mean over axes of the correlation between successive whitened errors (e_a / sigma_a of
    measurement k and k+1); NaN with fewer than 3 measurements."""
    e = np.asarray(errors, dtype=np.float64).reshape(-1, 6)
    if len(e) < 3:
        return float("nan")
    C = np.asarray(covariances, dtype=np.float64).reshape(-1, 6, 6)
    z = e / np.sqrt(np.einsum("nii->ni", C))
    out = []
    for a in range(6):
        x, y = z[:-1, a], z[1:, a]
        if np.std(x) > 0 and np.std(y) > 0:
            out.append(float(np.corrcoef(x, y)[0, 1]))
    return float(np.mean(out)) if out else float("nan")


__all__ = ["AXES", "NEES_QUANTILE", "lag1_correlation", "tangent_error", "whitened_stats"]
