"""Could chance explain an answer? The a-contrario count of a verified match.

A submap of a place the map does not hold still gets an answer whose matches fit a rigid
transform when the map is large or the submap small: some of its objects look like some map
objects, and a few of those happen to sit where one transform puts them. This module counts how
many answers as good as a given one such a submap would be expected to produce (the number of
false alarms of a-contrario testing), as log10:

    log10 NFA = log10 C(n, k) + sum_i log10 r_i + s log10 N + sum_i log10(c_i / N)

n submap objects, k of them matched, N map objects; r_i the rank of the chosen map object among
submap object i's candidates by appearance (a map object unrelated to it ranks that high among
all N with probability r_i / N; a pair found by position, not among the top candidates, ranks
after them: a lower bound of its rank among all N, so the count errs towards accepting); c_i the
map objects within pair i's residual (at least the answer's RMS) of where the transform puts
submap object i (an unrelated one lies that close with probability c_i / N); s = 2 pairs fix the
transform and are no evidence of it. C(n, k) counts the subsets of the submap an answer could
have chosen.

It reads ranks and counts only: no axis convention, embedding size, unit or noise level enters.
`match` refuses an answer above verify.max_chance_log10_large (0: chance would give one less
than once) for a submap of verify.chance_large_objects or more, whose right answers match most
of it and lie far below; a smaller submap cannot prove itself this way (two objects matched of
two give 0 at best), so there only an answer chance explains well (above
verify.max_chance_log10) is refused.
"""

from __future__ import annotations

import math

import numpy as np

from mergesvc.core.candidates import Candidates
from mergesvc.core.model import ObjectArrays

_FIXING_PAIRS = 2  # s above: two matched points fix a transform up to what the fit absorbs


def log10_comb(n: int, k: int) -> float:
    """log10 of the binomial coefficient C(n, k), for any size (no big integers)."""
    return (math.lgamma(n + 1) - math.lgamma(k + 1) - math.lgamma(n - k + 1)) / math.log(10.0)


def candidate_ranks(cands: Candidates, rows: np.ndarray, nodes: np.ndarray, n_sub: int
                    ) -> np.ndarray:
    """(k,) rank (1 = best) of each chosen pair (rows[j], nodes[j]), one per row, among its
    row's candidates by raw affinity (ties share the better rank); a pair that is not a
    candidate ranks after all of its row's. Candidates hold each pair once."""
    rows = np.asarray(rows, dtype=np.int64)
    n_map = int(max(cands.map_nodes.max(initial=0), np.max(nodes, initial=0))) + 1
    keys = cands.rows.astype(np.int64) * n_map + cands.map_nodes
    order = np.argsort(keys)
    want = rows * n_map + np.asarray(nodes, dtype=np.int64)
    pos = np.minimum(np.searchsorted(keys[order], want), max(len(keys) - 1, 0))
    found = keys[order][pos] == want if len(keys) else np.zeros(len(rows), dtype=bool)
    chosen = np.full(n_sub, np.inf)  # rows not asked about: no candidate is higher
    chosen[rows] = np.where(found, cands.affinity[order[pos]] if len(keys) else 0.0, -np.inf)
    higher = cands.affinity > chosen[cands.rows]
    return 1 + np.bincount(cands.rows[higher], minlength=n_sub)[rows]


def chance_log10(
    map_: ObjectArrays, n_sub: int, ranks: np.ndarray, predicted_xyz_m: np.ndarray,
    residual_m: np.ndarray,
) -> float:
    """log10 of the expected number of answers this good from an unrelated submap (above).

    ranks: (k,) of the matched pairs; predicted_xyz_m: (k, 3) where the transform puts their
    submap objects in the map; residual_m: (k,) their distance to the chosen map objects."""
    k, N = len(ranks), map_.n
    if k == 0:
        return math.inf
    rms = float(np.sqrt(np.mean(np.square(residual_m))))
    radius = np.maximum(residual_m, max(rms, 1e-9))
    near = np.asarray(map_.kdtree.query_ball_point(predicted_xyz_m, radius, return_length=True))
    geometry = float(np.sum(np.log10(np.maximum(near, 1) / N)))
    return (log10_comb(n_sub, k) + float(np.sum(np.log10(ranks))) + _FIXING_PAIRS * math.log10(N)
            + geometry)
