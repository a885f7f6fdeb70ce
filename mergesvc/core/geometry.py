"""Geometry of an object graph: centre distances, the median spacing that scales every default
distance, and the radius graph the paper's edges live on. Plain numpy/scipy; the lowest layer of
core (model.py's ObjectArrays and affinity.py both build on it).
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

log = logging.getLogger(__name__)


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b over the last axis, (..., 3) each: the same products and differences as np.cross
    (bit for bit) without its axis handling, which costs tens of microseconds per call."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def pairwise_lengths(position_xyz_m: np.ndarray) -> np.ndarray:
    """(n, 3) -> (n, n) Euclidean distances between object centres."""
    return cdist(position_xyz_m, position_xyz_m)


# Objects whose nearest neighbour the median spacing looks up: all of a map up to this size,
# an evenly spread subset of a larger one (its median is the map's within a fraction of a
# percent, at a tenth of the cost for 100k objects)
SPACING_SAMPLE = 20_000


def median_spacing(position_xyz_m: np.ndarray, tree: cKDTree | None = None) -> float:
    """Median nearest-neighbour distance between object centres (metres); 1.0 for one object.

    tree: a KD-tree already built over position_xyz_m (a map's cached one), else built here.
    Above SPACING_SAMPLE objects, the median over an evenly spread SPACING_SAMPLE of them."""
    n = len(position_xyz_m)
    if n < 2:
        return 1.0
    tree = cKDTree(position_xyz_m) if tree is None else tree
    rows = np.linspace(0, n - 1, SPACING_SAMPLE).astype(np.int64) if n > SPACING_SAMPLE else \
        slice(None)
    dist, _ = tree.query(position_xyz_m[rows], k=2)
    spacing = float(np.median(dist[:, 1]))
    return spacing if spacing > 0 else 1.0


def radius_edges(
    position_xyz_m: np.ndarray, radius_m: float, grow: float = 1.25, max_steps: int = 200
) -> tuple[np.ndarray, float]:
    """Edges between centres closer than the radius, relaxed until the graph is connected.

    Returns ((ne, 2) int array of i < j pairs, the radius used). The radius grows by `grow` per
    step (paper: relaxed until connected).
    """
    n = len(position_xyz_m)
    tree = cKDTree(position_xyz_m)
    r = float(radius_m)
    for _ in range(max_steps):
        pairs = tree.query_pairs(r, output_type="ndarray")
        if n <= 1:
            return pairs.reshape(-1, 2), r
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
        if connected_components(graph, directed=False)[0] == 1:
            return pairs, r
        r *= grow
    log.warning("graph still disconnected at radius %.3g m; using it anyway", r)
    return pairs, r
