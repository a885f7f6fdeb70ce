"""Affinity stage: node affinities between objects, object-graph edges, and the QAP matrix K.

Node affinities follow the paper (uncertainty-weighted cosine, Bhattacharyya and Mahalanobis on
diagonal Gaussians); edge affinity exp(-(e_ij - e_ab)^2 / sigma) on centre distances.
"""

from __future__ import annotations

import logging
from enum import Enum

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from mergesvc.model import ObjectArrays

log = logging.getLogger(__name__)

# Chunk of map nodes per vectorised step of the per-dimension Gaussian distances; bounds the
# (n1, chunk, d) temporaries to a few tens of MB.
_CHUNK_ELEMS = 4_000_000


class NodeAffinity(str, Enum):
    UCOS = "ucos"
    BHATTACHARYYA = "bhattacharyya"
    MAHALANOBIS = "mahalanobis"


def unit_rows(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows scaled to unit norm. Returns (X / |X|, |X|); zero rows stay zero."""
    norms = np.linalg.norm(X, axis=1)
    return X / np.where(norms > 0, norms, 1.0)[:, None], norms


def cosine(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """(n1, d), (n2, d) -> (n1, n2) cosine similarity."""
    return unit_rows(A)[0] @ unit_rows(B)[0].T


def weighted_cosine(
    emb1_nd: np.ndarray, s1_n: np.ndarray, emb2_nd: np.ndarray, s2_n: np.ndarray
) -> np.ndarray:
    """Paper's uncertainty-weighted cosine: cos(F1, F2) / (1 + (s1 + s2) / 2). (n1, n2)."""
    return cosine(emb1_nd, emb2_nd) / (1.0 + (s1_n[:, None] + s2_n[None, :]) / 2.0)


def _gaussian_inputs(
    objs: ObjectArrays, index: np.ndarray | None, normalize: bool, appearance: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    mu = objs.embeddings_nd if index is None else objs.embeddings_nd[index]
    var = objs.variances_nd if index is None else objs.variances_nd[index]
    if appearance:
        # The fused variance shrinks as 1/n_obs; times n_obs it is the spread of single views
        # of the object (its appearance distribution), which does not depend on how often the
        # object was seen. Used by Bhattacharyya, whose log-det term would otherwise rank map
        # objects by how closely their observation count matches the submap object's.
        n = objs.n_obs if index is None else objs.n_obs[index]
        var = var * n[:, None]
    if normalize:
        # Scale-free comparison (like the cosine): the embedding on the unit sphere, its variance
        # scaled by the same factor, so a brighter view of an object is not a different object.
        mu, norms = unit_rows(mu)
        var = var / np.where(norms > 0, norms, 1.0)[:, None] ** 2
    return mu, var


def _pairwise_diag(
    mu1: np.ndarray, var1: np.ndarray, mu2: np.ndarray, var2: np.ndarray, kind: NodeAffinity
) -> np.ndarray:
    """Gaussian distance between every pair of diagonal Gaussians. (n1, n2)."""
    n1, d = mu1.shape
    out = np.empty((n1, len(mu2)))
    logdet1 = np.log(var1).sum(axis=1)
    logdet2 = np.log(var2).sum(axis=1)
    step = max(1, _CHUNK_ELEMS // max(1, n1 * d))
    for lo in range(0, len(mu2), step):
        hi = min(len(mu2), lo + step)
        dmu2 = (mu1[:, None, :] - mu2[None, lo:hi, :]) ** 2
        if kind is NodeAffinity.MAHALANOBIS:
            # squared Mahalanobis distance of the difference: S = S1 + S2
            out[:, lo:hi] = (dmu2 / (var1[:, None, :] + var2[None, lo:hi, :])).sum(axis=2)
        else:
            # Bhattacharyya: 1/8 dmu^T S^-1 dmu + 1/2 ln(det S / sqrt(det S1 det S2)), S = mean
            S = (var1[:, None, :] + var2[None, lo:hi, :]) / 2.0
            out[:, lo:hi] = (dmu2 / S).sum(axis=2) / 8.0 + 0.5 * (
                np.log(S).sum(axis=2) - 0.5 * (logdet1[:, None] + logdet2[None, lo:hi])
            )
    return out


def node_distance(
    kind: NodeAffinity,
    sub: ObjectArrays,
    map_: ObjectArrays,
    map_index: np.ndarray | None = None,
    normalize: bool = True,
) -> np.ndarray:
    """Bhattacharyya or squared Mahalanobis distance, submap x map nodes. (n1, n2) >= 0.

    Mahalanobis uses the estimates' covariances (S = S1 + S2: is the difference of the two
    means explained by their uncertainty?); Bhattacharyya compares the objects' appearance
    distributions (see _gaussian_inputs).
    """
    appearance = NodeAffinity(kind) is NodeAffinity.BHATTACHARYYA
    mu1, var1 = _gaussian_inputs(sub, None, normalize, appearance)
    mu2, var2 = _gaussian_inputs(map_, map_index, normalize, appearance)
    return np.maximum(_pairwise_diag(mu1, var1, mu2, var2, kind), 0.0)


def distance_to_similarity(D: np.ndarray, D_ref: float) -> np.ndarray:
    """Map a distance to a bounded similarity in (0, 1], larger = more alike.

    exp(-ln 4 * D / D_ref): identical distributions give 1, a pair at the reference distance
    (the median over submap x map, i.e. a typical unrelated pair) gives 1/4. The authors' code
    fed the raw distances in as affinities, which rewards the *least* alike pairs; and the raw
    Bhattacharyya coefficient exp(-D) underflows to 0 in 384 dimensions. A data-derived scale
    keeps the mapping usable when the stated variances are off by a constant factor.
    """
    return np.exp(-np.log(4.0) * D / max(D_ref, 1e-12))


def node_affinity(
    kind: NodeAffinity,
    sub: ObjectArrays,
    map_: ObjectArrays,
    map_index: np.ndarray | None = None,
    normalize: bool = True,
    D_ref: float | None = None,
) -> np.ndarray:
    """Node affinity of every submap node to every (or the indexed) map node. (n1, n2).

    ucos lies in [-1, 1]; the Gaussian ones in (0, 1]. D_ref is the distance that maps to 1/4;
    by default the median of the computed distances.
    """
    kind = NodeAffinity(kind)
    if kind is NodeAffinity.UCOS:
        emb2 = map_.embeddings_nd if map_index is None else map_.embeddings_nd[map_index]
        s2 = map_.uncertainty_s if map_index is None else map_.uncertainty_s[map_index]
        return weighted_cosine(sub.embeddings_nd, sub.uncertainty_s, emb2, s2)
    D = node_distance(kind, sub, map_, map_index, normalize)
    return distance_to_similarity(D, float(np.median(D)) if D_ref is None else D_ref)


def reference_distance(
    kind: NodeAffinity,
    sub: ObjectArrays,
    map_: ObjectArrays,
    rng: np.random.Generator,
    sample: int = 512,
    normalize: bool = True,
) -> float:
    """Median Gaussian distance from the submap to a random sample of map nodes."""
    idx = None if map_.n <= sample else rng.choice(map_.n, size=sample, replace=False)
    return float(np.median(node_distance(kind, sub, map_, idx, normalize)))


# --------------------------------------------------------------------------- edges


def pairwise_lengths(position_xyz_m: np.ndarray) -> np.ndarray:
    """(n, 3) -> (n, n) Euclidean distances between object centres."""
    return cdist(position_xyz_m, position_xyz_m)


def median_spacing(position_xyz_m: np.ndarray, tree: cKDTree | None = None) -> float:
    """Median nearest-neighbour distance between object centres (metres); 1.0 for one object.

    tree: a KD-tree already built over position_xyz_m (a map's cached one), else built here."""
    if len(position_xyz_m) < 2:
        return 1.0
    tree = cKDTree(position_xyz_m) if tree is None else tree
    dist, _ = tree.query(position_xyz_m, k=2)
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


def edge_affinity(e1: np.ndarray, e2: np.ndarray, sigma: np.ndarray | float) -> np.ndarray:
    """Paper's edge affinity exp(-(e_ij - e_ab)^2 / sigma); arrays broadcast."""
    return np.exp(-((e1 - e2) ** 2) / sigma)
