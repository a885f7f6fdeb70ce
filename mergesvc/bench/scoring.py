"""Scoring shared by the benchmarks: one matched case against its truth (`score_case`), the
aggregates over cases, spreads over repeats, the settings of one mode / solver / affinity, and
small formatting helpers.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from mergesvc.core.config import MatchConfig, match_config
from mergesvc.core.pipeline import MatchOutcome
from mergesvc.errors import InputError
from mergesvc.sim import Scenario


def peak_rss_mb() -> float:
    """This process's peak resident memory, MB: Linux's VmHWM, which starts afresh when a
    process execs (ru_maxrss keeps the peak of what the process was before: a benchmark's child
    would report its parent's); ru_maxrss where /proc is missing."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def check_count(name: str, value: int, minimum: int = 1) -> None:
    """A benchmark's count argument (repeats, seeds): InputError below `minimum`."""
    if value < minimum:
        raise InputError(f"{name} must be >= {minimum}, got {value}")


def score_case(sc: Scenario, outcome: MatchOutcome) -> dict[str, float]:
    """The paper's node accuracy (right matches / submap objects that have a true match), and
    beyond it: precision and recall of the accepted correspondences, outliers left unmatched,
    the transform's error against the truth."""
    got = {m.submap_object: m.map_object for m in outcome.result.matches}
    matchable = [s for s, m in sc.truth.items() if m is not None]
    outliers = [s for s, m in sc.truth.items() if m is None]
    right = sum(sc.is_correct(s, got[s]) for s in got)
    accepted = bool(outcome.result.accepted)
    out = {
        "accuracy": sum(s in got and sc.is_correct(s, got[s]) for s in matchable)
        / max(len(matchable), 1),
        "accepted": float(accepted),
        "returned": float(len(got)),
        "right": float(right),
        "wrong": float(len(got) - right),
        "acc_returned": float(len(got)) if accepted else 0.0,
        "acc_right": float(right) if accepted else 0.0,
        "matchable": float(len(matchable)),
        "outliers": float(len(outliers)),
        "outliers_unmatched": float(sum(s not in got for s in outliers)),
        "rot_err_deg": float("nan"),
        "trans_err_m": float("nan"),
    }
    t = outcome.result.transform
    if accepted and t is not None:
        w, x, y, z = t.quaternion_wxyz
        R_est = Rotation.from_quat([x, y, z, w]).as_matrix()
        dR = R_est.T @ sc.R_map_submap
        out["rot_err_deg"] = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
        out["trans_err_m"] = float(np.linalg.norm(np.asarray(t.translation) - sc.t_map_submap))
    return out


def _spread(values: list[float]) -> dict[str, float]:
    a = np.asarray(values)
    q1, med, q3, p99 = np.percentile(a, [25, 50, 75, 99])
    return {"median": float(med), "iqr": float(q3 - q1), "min": float(a.min()),
            "max": float(a.max()), "p99": float(p99)}


def median_range(values: list[float | None]) -> dict[str, float]:
    """Median, min and max of the finite values (None and NaN left out), and how many; NaN
    when none: the "median [min-max] over runs" of the benchmark tables."""
    a = np.asarray([v for v in values if v is not None and np.isfinite(v)], dtype=np.float64)
    if not a.size:
        return {"median": float("nan"), "min": float("nan"), "max": float("nan"), "n": 0}
    return {"median": float(np.median(a)), "min": float(a.min()), "max": float(a.max()),
            "n": int(a.size)}


def fmt_median_range(s: dict[str, float], digits: int = 2) -> str:
    """`median [min-max]` (the median alone when they agree; "-" when there were none)."""
    if not s["n"]:
        return "-"
    med = f"{s['median']:.{digits}f}"
    if s["min"] == s["max"]:
        return med
    return f"{med} [{s['min']:.{digits}f}-{s['max']:.{digits}f}]"


def _aggregate(rows: list[dict[str, float]]) -> dict[str, float]:
    acc_returned = sum(r["acc_returned"] for r in rows)
    matchable = sum(r["matchable"] for r in rows)
    rot = [r["rot_err_deg"] for r in rows if np.isfinite(r["rot_err_deg"])]
    trans = [r["trans_err_m"] for r in rows if np.isfinite(r["trans_err_m"])]
    return {
        "node_accuracy": float(np.mean([r["accuracy"] for r in rows])) if rows else float("nan"),
        "cases": len(rows),
        "accepted": int(sum(r["accepted"] for r in rows)),
        "precision": sum(r["acc_right"] for r in rows) / acc_returned if acc_returned else 1.0,
        "recall": sum(r["acc_right"] for r in rows) / matchable if matchable else float("nan"),
        "wrong_returned": int(sum(r["wrong"] for r in rows)),
        "wrong_accepted": int(sum(r["acc_returned"] - r["acc_right"] for r in rows)),
        "outliers_unmatched": f"{int(sum(r['outliers_unmatched'] for r in rows))}/"
        f"{int(sum(r['outliers'] for r in rows))}",
        "rot_err_deg_median": float(np.median(rot)) if rot else float("nan"),
        "trans_err_m_median": float(np.median(trans)) if trans else float("nan"),
    }


def _config(
    mode: str, solver: str, affinity: str, radius_m: float, base: MatchConfig | None = None
) -> MatchConfig:
    """`base` (default: the defaults) with the benchmark's axes set: mode, solver, affinity,
    and in paper mode the paper's edge radius for this kind of world."""
    cfg = match_config(base, mode=mode, solver={"name": solver}, affinity={"kind": affinity})
    if mode == "paper":
        cfg.affinity.edge_radius_m = radius_m  # the paper's radius for this kind of world
    return cfg


def _fmt(x: float) -> str:
    return "-" if x is None or not np.isfinite(x) else f"{x:.2f}"


def _cpu_count() -> int:
    import os

    return os.cpu_count() or 0


__all__ = ["check_count", "fmt_median_range", "median_range", "peak_rss_mb", "score_case"]
