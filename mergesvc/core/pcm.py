"""Pairwise consistency of loop closures between two sessions (PCM: Mangelson et al., "Pairwise
Consistent Measurement Set Maximization for Robust Multi-robot Map Merging", ICRA 2018).

Two closures f = T_{A i, B j} and g = T_{A k, B l} between the same two odometry chains agree
when the loop they close with the chains is near the identity:

    e = Log(f^-1 * T_{A i,k} * g * T_{B l,j}),  C = C_f + (the chain's covariance, first order)

and e^T C^-1 e is below the chi-square quantile (6 dof). The closures that may be trusted are
the largest set that agree pairwise (a maximum clique of the consistency graph), so a wrong
closure has to agree with every trusted one to get in. The clique search is exact (branch and
bound with a greedy-colouring bound) within a node budget, then the best found. Pure.
"""

from __future__ import annotations

from collections.abc import Sequence

import gtsam
import numpy as np

from mergesvc.core.poses import compose_with_covariance, inverse_with_covariance


def loop_nees(
    f: tuple[gtsam.Pose3, np.ndarray],
    g: tuple[gtsam.Pose3, np.ndarray],
    chain_a: tuple[gtsam.Pose3, np.ndarray],
    chain_b: tuple[gtsam.Pose3, np.ndarray],
) -> float:
    """e^T C^-1 e of the loop f^-1 T_{A i,k} g T_{B l,j} (module docstring).

    f, g: closures (T, 6x6 covariance) A_i -> B_j and A_k -> B_l; chain_a: T_{A i,k} with its
    covariance, chain_b: T_{B l,j}, both GTSAM order."""
    T, S = compose_with_covariance(*compose_with_covariance(*chain_a, *g), *chain_b)
    e = np.asarray(gtsam.Pose3.Logmap(f[0].between(T)), dtype=np.float64)
    C = S + f[1]
    try:
        return float(e @ np.linalg.solve(C, e))
    except np.linalg.LinAlgError:
        return float("inf")


def reversed_chain(T: gtsam.Pose3, S: np.ndarray) -> tuple[gtsam.Pose3, np.ndarray]:
    """T^-1 with its covariance (a chain walked the other way)."""
    return inverse_with_covariance(T, S)


def max_clique(adjacent: np.ndarray, prefer: Sequence[bool] | None = None,
               budget: int = 5_000) -> list[int]:
    """Indices of a maximum clique of the undirected graph `adjacent` (n, n) bool (the diagonal
    is ignored); among cliques of one size, the one holding most `prefer`red nodes. Exact
    unless the search passes `budget` nodes (then the best found). Bitsets: Python ints."""
    A = np.asarray(adjacent, dtype=bool)
    n = len(A)
    if n == 0:
        return []
    pref = np.zeros(n, dtype=bool) if prefer is None else np.asarray(prefer, dtype=bool)
    # preferred nodes first (then the earliest): a tie keeps the set that holds more of them
    order = sorted(range(n), key=lambda v: (not pref[v], v))
    pos = {v: i for i, v in enumerate(order)}
    nbr = [0] * n  # neighbours of position i, as a bitset of positions
    for i, v in enumerate(order):
        for u in np.flatnonzero(A[v]):
            if u != v:
                nbr[i] |= 1 << pos[int(u)]
    # weight: size first, preferred members second (as a fraction below 1)
    w = [1.0 + (1.0 / (n + 1.0) if pref[v] else 0.0) for v in order]
    best: list[int] = []
    best_w = 0.0
    visited = 0

    def colour(cands: int) -> list[tuple[int, float]]:
        """Greedy colouring: (position, bound on the weight of a clique among it and the
        candidates coloured before it), in increasing bound order."""
        out: list[tuple[int, float]] = []
        left, acc = cands, 0.0
        while left:
            q, top = left, 0.0
            while q:
                low = q & -q
                i = low.bit_length() - 1
                q &= ~nbr[i] & ~low
                left &= ~low
                top = max(top, w[i])
                out.append((i, 0.0))
            acc += top
            out[-1:] = [(out[-1][0], acc)]
            k = len(out) - 2
            while k >= 0 and out[k][1] == 0.0:
                out[k] = (out[k][0], acc)
                k -= 1
        return out

    def expand(clique: list[int], weight: float, cands: int) -> None:
        nonlocal best, best_w, visited
        for i, bound in reversed(colour(cands)):
            visited += 1
            if weight + bound <= best_w + 1e-12 or visited > budget:
                return
            new, nw = [*clique, i], weight + w[i]
            rest = cands & nbr[i]
            if rest:
                expand(new, nw, rest)
            elif nw > best_w + 1e-12:
                best, best_w = new, nw
            cands &= ~(1 << i)

    expand([], 0.0, (1 << n) - 1)
    return sorted(order[i] for i in best)


__all__ = ["loop_nees", "max_clique", "reversed_chain"]
