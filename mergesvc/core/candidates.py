"""Candidate stage: for each submap object, the top-k map objects by node affinity.

Large maps: a cosine shortlist (one matrix product) first, then the chosen affinity on the
shortlist only. Scores are calibrated per submap object between a typical unrelated map object
(the median affinity, score 0) and its best map object (score 1), so one scale serves every
affinity kind and both a 10-object pool and a 100k-object map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mergesvc.core.affinity import (
    SameObjectModel,
    fit_same_object_model,
    is_isotropic,
    log_likelihood_ratio_pairs,
    node_affinity,
    reference_distance,
)
from mergesvc.core.arrays import take_rows
from mergesvc.core.config import AffinityConfig, CandidatesConfig, NodeAffinity
from mergesvc.core.model import ObjectArrays
from mergesvc.core.search import ExactSearch, exact_cosines, map_search


@dataclass(frozen=True)
class Candidates:
    """Flat list of m candidate pairs.

    rows: (m,) submap node; map_nodes: (m,) index into the map; affinity: (m,) raw node
    affinity; score: (m,) calibrated score in (0, 1].
    """

    rows: np.ndarray
    map_nodes: np.ndarray
    affinity: np.ndarray
    score: np.ndarray

    @property
    def m(self) -> int:
        return len(self.rows)


def _sample(n: int, size: int, rng: np.random.Generator) -> np.ndarray | None:
    return None if n <= size else np.sort(rng.choice(n, size=size, replace=False))


_SAMPLES_KEPT = 8  # per map: the sample rows of this many generator states


def _map_sample(map_: ObjectArrays, size: int, rng: np.random.Generator
                ) -> tuple[np.ndarray | None, dict[str, np.ndarray] | None]:
    """`_sample` of the map's rows and what the ucos floor reads of them (their embeddings,
    norms and uncertainties), kept with the map per generator state: every match with the
    same seed draws the same rows. The generator ends where drawing would leave it."""
    if map_.n <= size:
        return None, None
    before = repr(rng.bit_generator.state)
    kept = map_.cache.setdefault(("floor_sample", size), {})
    hit = kept.get(before)  # one lookup: another thread's match may clear the dict
    if hit is not None:
        idx, rows, after = hit
        rng.bit_generator.state = after
        return idx, rows
    idx = _sample(map_.n, size, rng)
    n_idx = map_.norms_n[idx]
    rows = {"embeddings": take_rows(map_.embeddings_nd, idx),
            "norms": np.where(n_idx > 0, n_idx, 1.0), "uncertainty": map_.uncertainty_s[idx]}
    if len(kept) >= _SAMPLES_KEPT:
        kept.clear()
    kept[before] = (idx, rows, rng.bit_generator.state)
    return idx, rows


@dataclass(frozen=True)
class Calibration:
    """How raw node affinities of one submap become scores: 0 at a typical unrelated map object
    (`floor_n`, per submap object), 1 at a typical submap object's best map object (`ceil`).
    same_object: the likelihood ratio's fitted constants (that kind only)."""

    kind: NodeAffinity
    normalize: bool
    D_ref: float | None
    floor_n: np.ndarray
    ceil: float
    same_object: SameObjectModel | None = None


def pair_scores(
    sub: ObjectArrays,
    map_: ObjectArrays,
    rows: np.ndarray,
    map_nodes: np.ndarray,
    calib: Calibration,
) -> tuple[np.ndarray, np.ndarray]:
    """Raw affinity and calibrated score (<= 1) of given pairs. (m,), (m,) -> (m,), (m,)."""
    union, inverse = np.unique(map_nodes, return_inverse=True)
    A = node_affinity(
        calib.kind, sub, map_, union, calib.normalize, calib.D_ref, calib.same_object
    )
    aff = A[rows, inverse]
    return aff, np.minimum((aff - calib.floor_n[rows]) / calib.ceil, 1.0)


def _ucos_pairs(sub: ObjectArrays, map_: ObjectArrays, cos: np.ndarray, nodes: np.ndarray
                ) -> np.ndarray:
    """The weighted cosine (affinity.ucos) of (n1, c) map nodes from their (n1, c) cosines."""
    s2 = map_.uncertainty_s[nodes]
    return cos.astype(np.float64) / (1.0 + (sub.uncertainty_s[:, None] + s2) / 2.0)


def _exact_where_it_decides(sub: ObjectArrays, map_: ObjectArrays, q32: np.ndarray,
                            shortlist: np.ndarray, cos: np.ndarray, err: np.ndarray,
                            k: int) -> np.ndarray:
    """The weighted cosines (`_ucos_pairs`) of a shortlist whose cosines are within err of the
    exact ones, exact wherever that could change the k best per row: the map's rows are read
    for the entries whose highest possible weighted cosine reaches the k-th highest lowest
    possible one (the k best by the exact values are then among those read or exact)."""
    w = _ucos_pairs(sub, map_, np.ones(cos.shape, dtype=np.float32), shortlist)  # > 0
    k = min(k, cos.shape[1])
    lowest = np.partition((cos - err) * w, cos.shape[1] - k, axis=1)[:, cos.shape[1] - k]
    qi, ci = np.nonzero((err > 0) & ((cos + err) * w >= lowest[:, None]))
    if len(qi):
        cos = cos.copy()
        cos[qi, ci] = exact_cosines(shortlist[qi, ci], q32[qi], lambda r: (
            take_rows(map_.embeddings_nd, r).astype(np.float32), map_.norms_n[r]))
    return _ucos_pairs(sub, map_, cos, shortlist)


def retrieve(
    sub: ObjectArrays,
    map_: ObjectArrays,
    cand_cfg: CandidatesConfig,
    aff_cfg: AffinityConfig,
    rng: np.random.Generator | int,
) -> tuple[Candidates, Calibration]:
    """Top-k candidates per submap node with calibrated scores, and the calibration.

    rng: the generator of the map sample's draws, or its seed (a map no larger than the
    sample draws nothing: no generator is made)."""
    kind = NodeAffinity(aff_cfg.kind)
    n1, n2 = sub.n, map_.n
    if n2 > cand_cfg.sample and not isinstance(rng, np.random.Generator):
        rng = np.random.default_rng(rng)
    # shortlist: every map node for small maps, else the best `prefilter` by plain cosine
    # (core/search.py: exact chunked products, or the map's index when it is large)
    cos = None
    q = sub.unit_rows()  # (n1, d) float64, and float32 for the products over the map
    q32 = q.astype(np.float32)
    products = None  # (n1, n2) float32 q32 @ embeddings.T, when the search kept them
    if n2 <= cand_cfg.prefilter:
        shortlist = np.broadcast_to(np.arange(n2), (n1, n2))
    else:
        search = map_search(map_, cand_cfg, n1)
        # best first only where the nearest is read (the likelihood ratio's model)
        ordered = kind is NodeAffinity.LIKELIHOOD_RATIO
        if isinstance(search, ExactSearch):
            shortlist, cos, products = search.search_with_products(
                q32, cand_cfg.prefilter, ordered, products=kind is NodeAffinity.UCOS)
            err = np.zeros(cos.shape, dtype=np.float32)  # exact
        else:
            shortlist, cos, err = search.search_bounded(q32, cand_cfg.prefilter, ordered)
    sample, sample_rows = _map_sample(map_, cand_cfg.sample, rng)
    D_ref = None
    same = None
    if kind is NodeAffinity.LIKELIHOOD_RATIO:
        # on unit-norm embeddings the nearest map object is the best by cosine: reuse the
        # shortlist's product instead of a second pass over the map
        nearest = None if cos is None or not aff_cfg.normalize_embeddings else shortlist[:, 0]
        same = fit_same_object_model(sub, map_, aff_cfg.normalize_embeddings, sample, nearest)
    elif kind is not NodeAffinity.UCOS:
        D_ref = reference_distance(
            kind, sub, map_, rng, cand_cfg.sample, aff_cfg.normalize_embeddings
        )
    if kind is NodeAffinity.UCOS and cos is not None:
        # (n1, shortlist), no second product; an index's approximate cosines made exact
        # where they decide the top_k
        A = (_exact_where_it_decides(sub, map_, q32, shortlist, cos, err, cand_cfg.top_k)
             if err.any() else _ucos_pairs(sub, map_, cos, shortlist))
    elif same is not None and not (
        is_isotropic(sub.variances_nd) and is_isotropic(map_.variances_nd[np.unique(shortlist)])
    ):
        # per-dimension variances: the likelihood ratio of the shortlisted pairs only, not of
        # every submap object x the shortlists' union (up to n1 times the work)
        rows = np.broadcast_to(np.arange(n1)[:, None], shortlist.shape)
        A = log_likelihood_ratio_pairs(sub, map_, same, rows.ravel(), shortlist.ravel())
        A = A.reshape(shortlist.shape)
    elif n2 <= cand_cfg.prefilter:  # the shortlist is the whole map
        A = node_affinity(kind, sub, map_, np.arange(n2), aff_cfg.normalize_embeddings, D_ref,
                          same)
    else:
        union, inverse = np.unique(shortlist, return_inverse=True)
        A_union = node_affinity(
            kind, sub, map_, union, aff_cfg.normalize_embeddings, D_ref, same
        )
        A = np.take_along_axis(A_union, inverse.reshape(shortlist.shape), axis=1)
    # typical unrelated map object: median affinity over the map (or a sample of it)
    if sample is None and n2 <= cand_cfg.prefilter:
        floor = row_medians(A)
    elif kind is NodeAffinity.UCOS:
        # the median of a sample needs no float64: one float32 product
        if sample_rows is None:
            idx = np.arange(n2)
            n_idx = map_.norms_n[idx]
            cos_s = (q32 @ map_.embeddings_nd[idx].T) / np.where(n_idx > 0, n_idx, 1.0)[None, :]
            floor = row_medians(_ucos_pairs(sub, map_, cos_s, idx[None, :]))
        else:  # the same arithmetic on the rows kept with the map (their products kept by
            # the search when it made them: the same products up to the BLAS's rounding, bit
            # for bit at the sizes measured; a small-matrix path may move the floor by ~1e-9)
            dot = (q32 @ sample_rows["embeddings"].T if products is None
                   else products[:, sample])
            cos_s = dot / sample_rows["norms"][None, :]
            s2 = sample_rows["uncertainty"][None, :]
            floor = row_medians(cos_s.astype(np.float64)
                                / (1.0 + (sub.uncertainty_s[:, None] + s2) / 2.0))
    else:
        idx = np.arange(n2) if sample is None else sample
        floor = row_medians(
            node_affinity(kind, sub, map_, idx, aff_cfg.normalize_embeddings, D_ref, same))
    k = min(cand_cfg.top_k, A.shape[1])
    top = np.argpartition(-A, k - 1, axis=1)[:, :k]
    each = np.arange(n1)[:, None]  # fancy indexing: take_along_axis's, with less overhead
    A_top = A[each, top]
    if kind is NodeAffinity.UCOS and cos is not None:
        # the chosen pairs' affinity in float64, as pair_scores (guided matching) computes it
        nodes = np.take_along_axis(shortlist, top, axis=1)
        n2 = map_.norms_n[nodes]
        exact_cos = np.empty(nodes.shape)
        for lo in range(0, n1, 512):  # (512, k, d) float64 at a time
            blk = nodes[lo:lo + 512]
            e = take_rows(map_.embeddings_nd, blk.ravel()).astype(np.float64)
            e = e.reshape(*blk.shape, -1)
            exact_cos[lo:lo + 512] = np.einsum("nkd,nd->nk", e, q[lo:lo + 512])
        exact_cos /= np.where(n2 > 0, n2, 1.0)
        A_top = _ucos_pairs(sub, map_, exact_cos, nodes)
    # scale: a typical submap object's best candidate scores 1; an object whose best candidate
    # is unusually weak (a false detection, a never-seen object) scores below 1 throughout
    lift = A_top.max(axis=1) - floor
    ceil = max(quantile(lift, cand_cfg.ceiling_quantile), 1e-12)
    calib = Calibration(kind, aff_cfg.normalize_embeddings, D_ref, floor, ceil, same)
    score = (A_top - floor[:, None]) / ceil
    keep = score > 0
    rows = np.flatnonzero(keep) // k  # row-major: each kept pair's row
    map_nodes = shortlist[each, top][keep]
    return _sorted(rows, map_nodes, A_top[keep], np.minimum(score[keep], 1.0)), calib


def row_medians(values: np.ndarray) -> np.ndarray:
    """np.median(values, axis=1) of an (n, c) array without NaN (the same arithmetic: the
    middle element, or the mean of the middle two), without its general-case overhead."""
    c = values.shape[1]
    h = c // 2
    if c % 2:
        return np.partition(values, h, axis=1)[:, h]
    part = np.partition(values, [h - 1, h], axis=1)
    return (part[:, h - 1] + part[:, h]) / 2.0


def quantile(values: np.ndarray, q: float) -> float:
    """np.quantile(values, q) (its default linear method, the same arithmetic, so the same
    float) of a 1-d array without NaN, without its general-case overhead."""
    s = np.sort(values)
    v = (len(s) - 1) * q
    lo = min(max(int(np.floor(v)), 0), len(s) - 1)
    hi = min(lo + 1, len(s) - 1)
    t = v - lo
    a, b = float(s[lo]), float(s[hi])
    return b - (b - a) * (1 - t) if t >= 0.5 else a + (b - a) * t


def _sorted(rows, map_nodes, affinity, score) -> Candidates:
    order = np.lexsort((-affinity, rows))
    return Candidates(
        rows=np.asarray(rows)[order].astype(np.int64),
        map_nodes=np.asarray(map_nodes)[order].astype(np.int64),
        affinity=np.asarray(affinity)[order],
        score=np.asarray(score)[order],
    )


def expand_near(
    cands: Candidates,
    sub: ObjectArrays,
    map_: ObjectArrays,
    predicted_xyz_m: np.ndarray,
    radius_m: np.ndarray,
    calib: Calibration,
    min_score: float = 0.0,
) -> Candidates:
    """Add map objects near each submap object's predicted map position as candidates.

    predicted_xyz_m: (n1, 3) submap centres mapped into the map frame; radius_m: (n1,) gate.
    Guided matching: once a transform is known, an object whose true match ranked below the
    top-k by appearance alone (look-alike instances of a class) is found by where it is.
    New pairs keep their calibrated appearance score, floored at `min_score`; they follow the
    given candidates, which keep their order.
    """
    near = map_.kdtree.query_ball_point(predicted_xyz_m, radius_m)
    rows = np.repeat(np.arange(sub.n), [len(v) for v in near])
    nodes = np.fromiter((b for v in near for b in v), dtype=np.int64, count=len(rows))
    # pairs not candidates yet, by a sorted lookup (np.isin costs more at these sizes)
    have = np.sort(cands.rows * map_.n + cands.map_nodes)
    keys = rows * map_.n + nodes
    new = have[np.minimum(np.searchsorted(have, keys), max(len(have) - 1, 0))] != keys \
        if len(have) else np.ones(len(keys), dtype=bool)
    if not new.any():
        return cands
    rows, nodes = rows[new], nodes[new]
    aff, score = pair_scores(sub, map_, rows, nodes, calib)
    added = _sorted(rows, nodes, aff, np.maximum(score, min_score))
    # the earlier candidates first, in their order: K over them is kept (affinity.extend_K)
    return Candidates(
        np.concatenate([cands.rows, added.rows]),
        np.concatenate([cands.map_nodes, added.map_nodes]),
        np.concatenate([cands.affinity, added.affinity]),
        np.concatenate([cands.score, added.score]),
    )
