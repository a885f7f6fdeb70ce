"""`mergesvc bench qaplib`: the exact branch and bound against QAPLIB's proven optima.

Reads QAPLIB instances (../shared/data/qaplib: NAME.dat, NAME.sln, MANIFEST.txt), states each
as the candidate-restricted Lawler problem the solver takes (score = -cost), solves it with
`solve_exact` (every row matched) `repeats` times, and reports per instance the proven optimum
beside the solver's score, whether the search proved it, the nodes and the seconds (median
[min-max] over the runs). An instance whose score is not the optimum, or that was not proven,
is a failure the report says.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mergesvc.bench.scoring import check_count, fmt_median_range, median_range
from mergesvc.core.solvers.exact import solve_exact
from mergesvc.core.solvers.problem import AssignmentProblem
from mergesvc.errors import InputError
from mergesvc.sim.real_data import DEFAULT_DATA_DIR

QAPLIB_DIR = DEFAULT_DATA_DIR / "qaplib"
# Instances the solver proves optimal within 25 s each on the 2-core dev machine (with other
# work running), seconds measured then (docs/benchmarks/match.md); the others do not finish.
PROVEN_S = {
    "chr12a": 0.2, "chr12b": 0.05, "chr12c": 1.1, "chr15a": 1.0, "chr15b": 2.1, "chr15c": 0.9,
    "chr18a": 8.6, "chr18b": 0.03, "chr20a": 1.4, "chr20b": 1.4, "els19": 1.3, "esc16f": 0.0,
    "had12": 3.3, "had14": 11.4, "lipa20a": 0.2, "lipa20b": 0.02, "scr12": 1.2, "scr15": 12.7,
    "tai12a": 2.0,
}


def read_instance(name: str, folder: Path = QAPLIB_DIR
                  ) -> tuple[np.ndarray, np.ndarray, int, np.ndarray]:
    """(A, B, opt, 0-based optimal permutation as stored) of QAPLIB instance `name`."""
    tokens = (folder / f"{name}.dat").read_text().split()
    n = int(tokens[0])
    vals = np.array(tokens[1 : 1 + 2 * n * n], dtype=np.int64)
    A, B = vals[: n * n].reshape(n, n), vals[n * n :].reshape(n, n)
    sln = (folder / f"{name}.sln").read_text().split()
    if int(sln[0]) != n:
        raise InputError(f"{name}.sln is for n={sln[0]}, {name}.dat for n={n}")
    return A, B, int(sln[1]), np.array(sln[2 : 2 + n], dtype=np.int64) - 1


def manifest(folder: Path = QAPLIB_DIR) -> dict[str, bool]:
    """name -> True when the stored permutation must be inverted (MANIFEST 'ok_inv' only)."""
    out = {}
    for line in (folder / "MANIFEST.txt").read_text().splitlines():
        parts = line.split()
        if len(parts) == 5 and parts[3] in ("True", "False"):
            out[parts[0]] = parts[3] == "False"
    return out


def qaplib_problem(A: np.ndarray, B: np.ndarray) -> AssignmentProblem:
    """Lawler form with score(p) = -cost(p), p = i * n + a row-major.

    K[(i, a), (j, b)] = -A[i, j] * B[a, b]; symmetrised (score sums both orders, so unchanged;
    halves of integers are exact in float64).
    """
    n = len(A)
    K = -(A[:, None, :, None] * B[None, :, None, :]).reshape(n * n, n * n).astype(np.float64)
    return AssignmentProblem.dense((K + K.T) / 2, n, n)


def run_qaplib_bench(
    names: Sequence[str] = tuple(PROVEN_S),
    *,
    repeats: int = 3,
    time_limit_s: float = 120.0,
    folder: Path = QAPLIB_DIR,
    echo: Callable[[str], Any] = print,
) -> dict[str, Any]:
    """Each instance solved `repeats` times; {"rows": [...], "failed": [names], "markdown"}."""
    check_count("repeats", repeats)
    if not (folder / "MANIFEST.txt").is_file():
        raise InputError(f"QAPLIB not found at {folder} (MANIFEST.txt)")
    known = manifest(folder)
    unknown = [n for n in names if n not in known]
    if unknown:
        raise InputError(f"not QAPLIB instances in {folder}: {', '.join(unknown)}")
    rows = []
    for name in names:
        A, B, opt, _ = read_instance(name, folder)
        problem = qaplib_problem(A, B)
        runs = []
        for _ in range(repeats):
            t0 = time.process_time()
            res = solve_exact(problem, allow_unmatched=False, time_limit_s=time_limit_s)
            runs.append((time.process_time() - t0, res))
        res = runs[-1][1]
        row = {"name": name, "n": len(A), "opt": opt, "score": 0.0 - res.score,  # not -0.0
               "optimal": all(r.optimal for _, r in runs),
               "reached": all(0.0 - r.score == opt for _, r in runs),
               "feasible": problem.is_feasible(res.assignment, allow_unmatched=False),
               "nodes": median_range([r.nodes_expanded for _, r in runs]),
               "cpu_s": median_range([s for s, _ in runs])}
        rows.append(row)
        echo(f"{name}: opt {opt}, exact {row['score']:.0f}, proven {row['optimal']}, "
             f"{fmt_median_range(row['cpu_s'])} s")
    failed = [r["name"] for r in rows if not (r["optimal"] and r["reached"] and r["feasible"])]
    lines = ["| instance | n | QAPLIB optimum | exact search | proven | nodes | CPU s |",
             "|" + "---|" * 7]
    lines += [f"| {r['name']} | {r['n']} | {r['opt']} | {r['score']:.0f} | "
              f"{'yes' if r['optimal'] else 'NO'} | {fmt_median_range(r['nodes'], 0)} | "
              f"{fmt_median_range(r['cpu_s'])} |" for r in rows]
    return {"repeats": repeats, "time_limit_s": time_limit_s, "rows": rows, "failed": failed,
            "markdown": "\n".join(lines)}


__all__ = ["PROVEN_S", "QAPLIB_DIR", "manifest", "qaplib_problem", "read_instance",
           "run_qaplib_bench"]
