"""Test oracles for the assignment solvers: brute-force enumeration (tiny problems only) and
pygmtools' exact A* (pytorch backend, when torch happens to be installed). They live with the
tests: production code never calls them."""

from __future__ import annotations

import itertools
import math

import numpy as np

from mergesvc.core.solvers.problem import UNMATCHED, AssignmentProblem
from mergesvc.errors import SolverError

BRUTE_FORCE_LIMIT = 2_000_000


def brute_force(
    problem: AssignmentProblem, allow_unmatched: bool = True
) -> tuple[np.ndarray, float]:
    """Enumerate every feasible assignment (tiny problems only).

    Returns ((n1,) map node per row or UNMATCHED, score). Raises SolverError when the product of
    per-row option counts exceeds BRUTE_FORCE_LIMIT, or when allow_unmatched=False and no full
    assignment exists.
    """
    n1 = problem.n1
    K = np.asarray(problem.K, dtype=np.float64)
    options: list[list[tuple[int, int]]] = [[] for _ in range(n1)]
    for p, (r, c) in enumerate(zip(problem.rows.tolist(), problem.cols.tolist(), strict=True)):
        options[r].append((c, p))
    if allow_unmatched:
        for opt in options:
            opt.append((UNMATCHED, -1))
    total = math.prod(len(o) for o in options)
    if total > BRUTE_FORCE_LIMIT:
        raise SolverError(f"brute force over {total} combinations exceeds {BRUTE_FORCE_LIMIT}")
    sym = (K + K.T).tolist()
    diag = np.diag(K).tolist()
    clash: list[set[int]] = [set() for _ in range(problem.m)]
    if problem.conflict is not None:
        for p, q in zip(*np.nonzero(problem.conflict), strict=True):
            clash[int(p)].add(int(q))

    best_score = -math.inf
    best: list[int] | None = None
    chosen_p: list[int] = []
    chosen_c: list[int] = [UNMATCHED] * n1
    used: set[int] = set()

    # Depth-first enumeration with an incremental score: K[p,p] plus (K[p,q] + K[q,p]) against
    # everything chosen so far; far cheaper than re-summing a submatrix per leaf.
    def rec(i: int, score: float) -> None:
        nonlocal best_score, best
        if i == n1:
            if score > best_score:
                best_score, best = score, list(chosen_c)
            return
        for c, p in options[i]:
            if p < 0:
                chosen_c[i] = UNMATCHED
                rec(i + 1, score)
                continue
            if c in used or any(q in clash[p] for q in chosen_p):
                continue
            row = sym[p]
            delta = diag[p] + sum(row[q] for q in chosen_p)
            used.add(c)
            chosen_p.append(p)
            chosen_c[i] = c
            rec(i + 1, score + delta)
            chosen_p.pop()
            used.discard(c)
        chosen_c[i] = UNMATCHED

    rec(0, 0.0)
    if best is None:
        raise SolverError("no feasible full assignment")
    assignment = np.asarray(best, dtype=np.int64)
    return assignment, problem.score(assignment)


def astar_crosscheck(problem: AssignmentProblem) -> np.ndarray:
    """Solve a dense problem with pygmtools' exact A* (pytorch backend) as an independent oracle.

    Returns (n1,) map node per row (UNMATCHED where A* left a row unmatched). Raises SolverError
    when torch is missing or the problem is not dense (all n1*n2 pairs are candidates).
    """
    try:
        import torch
    except ImportError as exc:
        raise SolverError("pygmtools A* needs torch; install torch to use the cross-check") from exc
    import pygmtools

    n1, n2 = problem.n1, problem.n2
    if problem.m != n1 * n2:
        raise SolverError("pygmtools A* cross-check needs a dense problem (all n1*n2 pairs)")
    # pygmtools indexes the affinity matrix column-major: pair (i, a) -> a * n1 + i.
    pg = np.asarray(problem.cols) * n1 + np.asarray(problem.rows)
    Kpg = np.zeros((n1 * n2, n1 * n2))
    Kpg[np.ix_(pg, pg)] = problem.K
    X = pygmtools.astar(
        torch.from_numpy(Kpg)[None],
        n1=torch.tensor([n1]),
        n2=torch.tensor([n2]),
        backend="pytorch",
    )
    X = np.asarray(X[0].detach().cpu().numpy())
    return np.where(X.max(axis=1) > 0.5, X.argmax(axis=1), UNMATCHED).astype(np.int64)


def brute_margin(problem: AssignmentProblem, assignment: np.ndarray, i: int) -> float:
    """Objective of the solution minus the best feasible assignment giving row i another
    candidate (-inf alternatives: the margin is inf). Enumerates every assignment (all at once
    in arrays: each one's chosen candidates, feasibility and score)."""
    n1 = problem.n1
    options = [[-1, *np.flatnonzero(problem.rows == r).tolist()] for r in range(n1)]
    total = math.prod(len(o) for o in options)
    if total > BRUTE_FORCE_LIMIT:
        raise SolverError(f"brute force over {total} combinations exceeds {BRUTE_FORCE_LIMIT}")
    P = np.array(list(itertools.product(*options)), dtype=np.int64).reshape(-1, n1)
    on = P >= 0  # row matched, to candidate P
    Q = np.maximum(P, 0)
    cols = np.where(on, problem.cols[Q], -1 - np.arange(n1))  # unmatched rows never collide
    ok = np.ones(len(P), dtype=bool)
    for a in range(n1):
        for b in range(a + 1, n1):
            ok &= cols[:, a] != cols[:, b]
    both = on[:, :, None] & on[:, None, :]
    pairs = (Q[:, :, None], Q[:, None, :])
    if problem.conflict is not None:
        ok &= ~(problem.conflict[pairs] & both).any(axis=(1, 2))
    scores = np.where(both, np.asarray(problem.K, dtype=np.float64)[pairs], 0.0).sum(axis=(1, 2))
    alternative = ok & on[:, i] & (cols[:, i] != assignment[i])
    alt = scores[alternative].max() if alternative.any() else -np.inf
    return problem.score(assignment) - alt
