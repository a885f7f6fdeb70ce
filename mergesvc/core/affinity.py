"""Affinity stage: node affinities between objects, object-graph edges, and the QAP matrix K.

Node affinities follow the paper (uncertainty-weighted cosine, Bhattacharyya and Mahalanobis on
diagonal Gaussians), plus a same-object likelihood ratio (eqs. LR-1..LR-6 below) that weighs the
tracked posterior variances against the spread of unrelated objects; edge affinity
exp(-(e_ij - e_ab)^2 / sigma) on centre distances.

K is built here (the last section), for both modes of pipeline.py: candidate_K over the
candidate pairs (verified mode: calibrated node scores on the diagonal, weighted edge affinities
off it, as the signed and the non-negative AssignmentProblem), and paper_node_affinity +
paper_K over all n1 x n2 pairs (paper mode; pygmtools assembles the dense K, solvers/dense.py).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from mergesvc.core.arrays import take_rows
from mergesvc.core.config import AffinityConfig, NodeAffinity
from mergesvc.core.geometry import pairwise_lengths, radius_edges
from mergesvc.core.model import ObjectArrays
from mergesvc.core.solvers import dense
from mergesvc.core.solvers.problem import AssignmentProblem, block

# Chunk of map nodes per vectorised step of the per-dimension Gaussian distances; bounds the
# (n1, chunk, d) temporaries to a few tens of MB.
_CHUNK_ELEMS = 4_000_000


def unit_rows(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows scaled to unit norm, in float64. Returns (X / |X|, |X|); zero rows stay zero."""
    X = np.asarray(X, dtype=np.float64)
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


def ucos(sub: ObjectArrays, map_: ObjectArrays, map_index: np.ndarray | None = None
         ) -> np.ndarray:
    """`weighted_cosine` of every submap object to every (or the indexed) map object, from the
    arrays' cached norms and uncertainties (no normalised copy of the map). (n1, n2)."""
    idx = slice(None) if map_index is None else map_index
    e2 = (map_.embeddings_nd if map_index is None
          else take_rows(map_.embeddings_nd, map_index)).astype(np.float64)
    n2 = map_.norms_n[idx]
    cos = (sub.unit_rows() @ e2.T) / np.where(n2 > 0, n2, 1.0)[None, :]
    s1, s2 = sub.uncertainty_s, map_.uncertainty_s[idx]
    return cos / (1.0 + (s1[:, None] + s2[None, :]) / 2.0)


def _gaussian_inputs(
    objs: ObjectArrays, index: np.ndarray | None, normalize: bool, appearance: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    mu = (objs.embeddings_nd if index is None else take_rows(objs.embeddings_nd, index)
          ).astype(np.float64)
    var = objs.variances_nd if index is None else take_rows(objs.variances_nd, index)
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
    distributions (see _gaussian_inputs). likelihood_ratio: the evidence deficit of eq. LR-6,
    its model fitted on the whole map.
    """
    if NodeAffinity(kind) is NodeAffinity.LIKELIHOOD_RATIO:
        L = log_likelihood_ratio(sub, map_, fit_same_object_model(sub, map_, normalize), map_index)
        return L.max(axis=1, keepdims=True) - L  # eq. LR-6
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
    same_object: SameObjectModel | None = None,
) -> np.ndarray:
    """Node affinity of every submap node to every (or the indexed) map node. (n1, n2).

    ucos lies in [-1, 1]; Bhattacharyya and Mahalanobis in (0, 1] (D_ref is the distance that
    maps to 1/4; by default the median of the computed distances); likelihood_ratio is the
    log-odds of eq. LR-3, any real number (same_object: its fitted constants; by default fitted
    here against the whole map).
    """
    kind = NodeAffinity(kind)
    if kind is NodeAffinity.LIKELIHOOD_RATIO:
        model = same_object or fit_same_object_model(sub, map_, normalize)
        return log_likelihood_ratio(sub, map_, model, map_index)
    if kind is NodeAffinity.UCOS:
        return ucos(sub, map_, map_index)
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


# --------------------------------------------------------------- same-object likelihood ratio
#
# Is the difference of two posterior means explained by their uncertainty (the same object seen
# twice) or by the spread between unrelated objects? With dmu = mu1 - mu2 (unit-norm embeddings,
# variances as stated, see _lr_inputs), d dimensions, t_nu the multivariate Student t:
#   (LR-1) same object: dmu ~ t_nu(0, V),       V_k = c (S1_k + S2_k)
#   (LR-2) unrelated:   dmu ~ N(0, W),          W_k = V_k + D,
#                       D = median_{i,a} |mu1_i - mu2_a|^2 / d  (submap x map, a typical
#                       unrelated pair)
#   (LR-3) LLR = ln t_nu(dmu; 0, V) - ln N(dmu; 0, W) - C(nu, d)
#              = -(nu + d)/2 ln(1 + M_V / nu) + M_W / 2 + 1/2 sum_k ln(W_k / V_k),
#          M_V = sum_k dmu_k^2 / V_k,  M_W = sum_k dmu_k^2 / W_k,
#          C(nu, d) = ln G((nu + d)/2) - ln G(nu/2) - d/2 ln(nu/2)  (G: the gamma function)
#          is the ratio's limit for uninformative posteriors (V >> D): subtracted, LLR = 0 means
#          no evidence either way.
#   (LR-4) c = median_i  (1/d) sum_k dmu_k^2 / (S1_k + S2_k)   at each submap object's nearest
#          map object (the MLE of c for that pair; the median ignores submap objects whose
#          nearest object is not theirs)
#   (LR-5) the t tail is heavier than the Gaussian's, so far beyond a typical unrelated pair
#          LR-3 would rise again; along each ray dmu -> a dmu it is evaluated at most at its
#          minimum a^2 = (nu + d) / M_W - nu / M_V (isotropic: |dmu|^2 = (nu + d) D + d V):
#          farther than that says nothing more. LLR is then non-increasing in |dmu|.
#   (LR-6) paper mode needs a distance >= 0: max_b LLR_ib - LLR_ia, the log-evidence a map
#          object falls short of submap object i's best explanation.
# Why: S1 + S2 is the covariance of the difference of two independent Kalman posteriors
# (tracking.py), but the stated variances are right only up to a factor (per-image s is a rank
# score, not a calibrated variance): c fixes their unit, and t_nu is a Gaussian N(0, V / lam)
# whose scale lam ~ Gamma(nu/2, nu/2) is itself uncertain; nu = 9 gives ln(lam) a spread of
# 0.5, the spread of ln(|dmu|^2 / (c tr(S1 + S2))) over true pairs of the underwater and drive
# worlds (0.48, 0.50). D, a median over many pairs, is well determined: a Gaussian. Unrelated
# objects are seen through the same noise, hence W = V + D: a posterior much wider than the
# population carries no evidence (LLR -> 0). A Gaussian LR-1 (nu -> inf) trusts the variances
# exactly: in 384 dimensions its log-det term then outweighs the distance and its lift over
# unrelated objects grows as 1/V, so no single score scale fits confident and vague objects
# (measured: worse than the cosine).

_LR_NU = 9.0  # Student-t degrees of freedom of LR-1 (see above)
_LR_EPS = 1e-6  # V kept within [eps D, D / eps]: only keeps the score finite at extremes
# Per-dimension variances: elements per vectorised step. Small enough for the temporaries to
# stay in cache (measured 2-3x faster than the 4M-element steps of _pairwise_diag).
_LR_CHUNK_ELEMS = 1 << 16


@dataclass(frozen=True)
class SameObjectModel:
    """Constants of the likelihood ratio (eqs. LR-1, LR-2, LR-4), fitted once per submap.

    c: stated posterior variance -> variance of a same-object difference; D: per-dimension
    variance of the difference of unrelated objects; normalize: on unit-norm embeddings (scale
    invariant per object); nu: Student-t degrees of freedom."""

    c: float
    D: float
    normalize: bool
    nu: float = _LR_NU


def _lr_inputs(objs: ObjectArrays, index: np.ndarray | None, normalize: bool
               ) -> tuple[np.ndarray, np.ndarray]:
    """Means (unit norm if normalize) and variances as stated, (n, d) each.

    Unlike _gaussian_inputs the variance is not divided by the mean's squared norm: the image
    uncertainty s is relative (the head predicts |y - x| / |x|), so dividing it by |mu|^2 would
    make an object look surer for being bright. One common unit is absorbed by c (eq. LR-4)."""
    if normalize:
        mu = objs.unit_rows(index)
    else:
        mu = (objs.embeddings_nd if index is None else take_rows(objs.embeddings_nd, index)
              ).astype(float)
    return mu, objs.variances_nd if index is None else take_rows(objs.variances_nd, index)


def _sqdist(mu1: np.ndarray, mu2: np.ndarray) -> np.ndarray:
    """(n1, d), (n2, d) -> (n1, n2) squared Euclidean distances, one matrix product."""
    sq = (mu1**2).sum(axis=1)[:, None] + (mu2**2).sum(axis=1)[None, :] - 2.0 * (mu1 @ mu2.T)
    return np.maximum(sq, 0.0)


def is_isotropic(var_nd: np.ndarray) -> bool:
    """Whether every row of (n, d) variances is one number (the likelihood ratio's fast path)."""
    if var_nd.ndim == 2 and var_nd.strides[1] == 0:  # ObjectArrays holds it as one column
        return True
    return bool(np.all(var_nd == var_nd[:, :1]))


def fit_same_object_model(
    sub: ObjectArrays,
    map_: ObjectArrays,
    normalize: bool = True,
    sample_index: np.ndarray | None = None,
    nearest_n: np.ndarray | None = None,
) -> SameObjectModel:
    """Fit c (eq. LR-4) and D (eq. LR-2) of one submap against one map.

    sample_index: map objects that stand for the map in D (None: all); nearest_n: (n1,) each
    submap object's nearest map object (None: found here by one matrix product)."""
    mu1, var1 = _lr_inputs(sub, None, normalize)
    mu_s, _ = _lr_inputs(map_, sample_index, normalize)
    d = mu1.shape[1]
    D = float(np.median(_sqdist(mu1, mu_s))) / d
    # floor: identical objects everywhere would make D = 0 (no scale at all)
    scale2 = float(np.median((mu1**2).sum(axis=1))) / d
    D = max(D, 1e-12 * scale2, np.finfo(float).tiny)
    if nearest_n is None:
        mu_all, _ = _lr_inputs(map_, None, normalize)
        nearest_n = np.argmin(_sqdist(mu1, mu_all), axis=1)
    mu2, var2 = _lr_inputs(map_, np.asarray(nearest_n), normalize)
    # the mean of the two variances, not their sum: no overflow for variances near float max
    Sbar = var1 / 2.0 + var2 / 2.0
    with np.errstate(over="ignore"):
        c_n = ((mu1 - mu2) ** 2 / Sbar).mean(axis=1) / 2.0
    c = float(np.median(c_n))
    return SameObjectModel(c=c if np.isfinite(c) else np.finfo(float).max, D=D,
                           normalize=normalize)


def _same_object_V(c: float, var1: np.ndarray, var2: np.ndarray, D: float) -> np.ndarray:
    """V = c (S1 + S2) (eq. LR-1) kept within [eps D, D / eps], arrays broadcast; finite.

    S1 + S2 may overflow to inf (both near float max): V is then clipped to D / eps, the
    uninformative end, where such a posterior belongs anyway."""
    lo, hi = _LR_EPS * D, D / _LR_EPS
    with np.errstate(over="ignore"):
        V = np.add(var1, var2)
        if c <= 0.0:  # every nearest pair identical: no spread to explain, V at its floor
            V[...] = lo
        V *= c  # c > 0 and V > 0: inf at worst, never NaN
    return np.clip(V, lo, hi, out=V)


def _mahalanobis_terms(dmu2: np.ndarray, var1: np.ndarray, var2: np.ndarray, c: float, D: float
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """M_V, M_W and sum_k ln(W_k / V_k) of eq. LR-3 over the last axis; dmu2 = dmu^2.

    In place on two temporaries: per-dimension variances make these the stage's largest
    arrays, and fresh ones cost more than the arithmetic."""
    V = _same_object_V(c, var1, var2, D)
    inv = np.reciprocal(V)
    M_V = np.einsum("...k,...k->...", dmu2, inv)
    V += D
    np.reciprocal(V, out=V)  # 1 / W
    M_W = np.einsum("...k,...k->...", dmu2, V)
    inv *= D
    np.log1p(inv, out=inv)  # ln(W / V) = ln(1 + D / V)
    return M_V, M_W, inv.sum(axis=-1)


def _lr_from_mahalanobis(
    M_V: np.ndarray, M_W: np.ndarray, logdet_WV: np.ndarray, nu: float, d: int
) -> np.ndarray:
    """Eq. LR-3 with the clamp of LR-5, from M_V, M_W and sum_k ln(W_k / V_k); broadcast."""
    with np.errstate(divide="ignore", invalid="ignore"):
        a2 = (nu + d) / M_W - nu / M_V  # LR-5: the minimum along the ray
    a2 = np.where(np.isfinite(a2), np.clip(a2, 0.0, 1.0), 1.0)
    M_V, M_W = a2 * M_V, a2 * M_W
    return -(nu + d) / 2.0 * np.log1p(M_V / nu) + M_W / 2.0 + 0.5 * logdet_WV


def log_likelihood_ratio(
    sub: ObjectArrays,
    map_: ObjectArrays,
    model: SameObjectModel,
    map_index: np.ndarray | None = None,
) -> np.ndarray:
    """Same-object log-likelihood ratio (eq. LR-3) of every submap x (indexed) map node. (n1, n2).

    Larger = more likely the same object; 0 = no evidence either way. Isotropic variances (one
    number per object, as the tracker makes them from a scalar s) take one matrix product;
    per-dimension variances a chunked (n1, chunk, d) loop."""
    mu1, var1 = _lr_inputs(sub, None, model.normalize)
    mu2, var2 = _lr_inputs(map_, map_index, model.normalize)
    c, D, nu = model.c, model.D, model.nu
    n1, d = mu1.shape
    if is_isotropic(var1) and is_isotropic(var2):
        V = _same_object_V(c, var1[:, :1], var2[:, 0][None, :], D)  # (n1, n2)
        W = V + D
        sq = _sqdist(mu1, mu2)
        return _lr_from_mahalanobis(sq / V, sq / W, d * np.log1p(D / V), nu, d)
    out = np.empty((n1, len(mu2)))
    step = max(1, _LR_CHUNK_ELEMS // max(1, n1 * d))
    for lo in range(0, len(mu2), step):
        hi = min(len(mu2), lo + step)
        dmu2 = mu1[:, None, :] - mu2[None, lo:hi, :]
        np.square(dmu2, out=dmu2)
        terms = _mahalanobis_terms(dmu2, var1[:, None, :], var2[None, lo:hi, :], c, D)
        out[:, lo:hi] = _lr_from_mahalanobis(*terms, nu, d)
    return out


def log_likelihood_ratio_pairs(
    sub: ObjectArrays,
    map_: ObjectArrays,
    model: SameObjectModel,
    rows: np.ndarray,
    map_nodes: np.ndarray,
) -> np.ndarray:
    """Eq. LR-3 of given pairs only: (m,), (m,) -> (m,). Per-dimension variances cost O(m d)
    here instead of O(n1 n2 d) for the dense matrix (the candidate stage's cosine shortlist)."""
    mu1, var1 = _lr_inputs(sub, None, model.normalize)
    c, D, nu = model.c, model.D, model.nu
    d = mu1.shape[1]
    rows, map_nodes = np.asarray(rows, dtype=np.int64), np.asarray(map_nodes, dtype=np.int64)
    out = np.empty(len(rows))
    step = max(1, _LR_CHUNK_ELEMS // max(1, d))
    for lo in range(0, len(rows), step):
        r, b = rows[lo : lo + step], map_nodes[lo : lo + step]
        mu2, var2 = _lr_inputs(map_, b, model.normalize)
        dmu2 = mu1[r] - mu2
        np.square(dmu2, out=dmu2)
        terms = _mahalanobis_terms(dmu2, var1[r], var2, c, D)
        out[lo : lo + step] = _lr_from_mahalanobis(*terms, nu, d)
    return out


# --------------------------------------------------------------------------- edges


def edge_affinity(e1: np.ndarray, e2: np.ndarray, sigma: np.ndarray | float) -> np.ndarray:
    """Paper's edge affinity exp(-(e_ij - e_ab)^2 / sigma); arrays broadcast."""
    return np.exp(-((e1 - e2) ** 2) / sigma)


def edge_scales(map_: ObjectArrays, aff: AffinityConfig) -> tuple[float, float]:
    """(edge length tolerance sigma_m, paper-mode edge radius_m), derived from data if unset."""
    need = aff.edge_sigma_m is None or aff.edge_radius_m is None
    spacing = map_.median_spacing_m if need else 1.0
    sigma = aff.edge_sigma_m or aff.spacing_sigma * spacing
    radius = aff.edge_radius_m or 3.0 * spacing
    return sigma, radius


# --------------------------------------------------------------------------- K


def edge_pair_weight(n1: int, aff: AffinityConfig) -> float:
    """Weight of one K entry of a submap edge: w_e / (n1 - 1), half on (p, q), half on (q, p)."""
    return aff.edge_weight / max(n1 - 1, 1) / 2.0


# below this, exp is subnormal (under 2.2e-308) or 0 in float64
_EXP_NORMAL_FROM = float(np.log(np.finfo(np.float64).tiny))


def exp_edges(X: np.ndarray) -> np.ndarray:
    """np.exp(X) with every result below the smallest normal float (2.2e-308) set to 0, and
    computed only where it is not: numpy's exp is several times slower on arguments whose
    result underflows (most candidate pairs disagree by far: X of -1e3 and below), and
    arithmetic on subnormal K entries (RRWM's products) is slower again. No sum of K entries
    moves by that much (tests/test_affinity.py)."""
    flat = X.ravel()
    live = np.flatnonzero(flat > _EXP_NORMAL_FROM)
    if len(live) == len(flat):
        return np.exp(X)
    out = np.zeros(X.shape)
    out.ravel()[live] = np.exp(flat[live])
    return out


class CandidateK(NamedTuple):
    """K over one candidate set, as the two problems the solvers take (see candidate_K)."""

    signed: AssignmentProblem  # node and edge terms less their thresholds; conflicts
    positive: AssignmentProblem  # thresholds 0, every entry >= 0 (RRWM / SM)
    local: np.ndarray  # (n2_local,) local col -> map index


def candidate_K(
    sub: ObjectArrays,
    map_: ObjectArrays,
    rows: np.ndarray,
    map_nodes: np.ndarray,
    node_score: np.ndarray,
    aff: AffinityConfig,
    sigma_m: float,
    conflict_sigmas: float | None = None,
) -> CandidateK:
    """K over the m candidate pairs (rows[p], map_nodes[p]), node_score[p] on its diagonal.

    Signed objective: sum of calibrated node scores less node_threshold + for every pair of
    matched submap nodes w_e / (n1 - 1) * (a_e - edge_threshold), a_e = exp(-(e_ij - e_ab)^2 /
    (2 tol_ij^2)), tol_ij^2 = sigma_m^2 + (edge_rel_tol * e_ij)^2, half of it on K[p, q] and
    half on K[q, p] (edge_pair_weight). A pair inconsistent with the others costs, so a false
    detection is better left unmatched. The non-negative one (thresholds 0) feeds RRWM / SM.
    Entries of two candidates sharing a row or a map node are 0. The signed problem also
    forbids pairs whose lengths disagree by more than conflict_sigmas tolerances (no rigid fit
    keeps both; None: no conflicts): the exact search prunes on that. The problems' columns
    are local (indices into `local`, the sorted distinct map_nodes).
    """
    local, cols = np.unique(map_nodes, return_inverse=True)
    R = np.asarray(rows, dtype=np.int64)
    m = len(R)
    e_sub = pairwise_lengths(sub.position_xyz_m)
    # -1 / (2 tol_ij^2) per submap pair, gathered once with the lengths; the map lengths of
    # the candidates directly (no map-wide matrix)
    neg_inv = -0.5 / (sigma_m**2 + (aff.edge_rel_tol * e_sub) ** 2)
    grouped = m > 0 and bool(np.all(R[1:] >= R[:-1]))
    if grouped:  # candidates sorted by row (retrieve's order): repeats instead of a gather
        counts = np.bincount(R, minlength=sub.n)
        E1 = np.repeat(np.repeat(e_sub, counts, axis=0), counts, axis=1)
        X = np.repeat(np.repeat(neg_inv, counts, axis=0), counts, axis=1)
    else:
        E1 = block(e_sub, R)
        X = block(neg_inv, R)
    xyz = map_.position_xyz_m[local[cols]]
    D = pairwise_lengths(xyz)  # e_ab of every candidate pair
    D -= E1
    np.square(D, out=D)
    X *= D  # -(e_ij - e_ab)^2 / (2 tol_ij^2)
    w = edge_pair_weight(sub.n, aff)
    K_pos = exp_edges(X)
    K_pos *= w
    invalid = cols[:, None] == cols[None, :]
    invalid |= R[:, None] == R[None, :]
    K_pos[invalid] = 0.0
    K_signed = K_pos - w * aff.edge_threshold
    K_signed[invalid] = 0.0
    np.fill_diagonal(K_pos, node_score)
    np.fill_diagonal(K_signed, node_score - aff.node_threshold)
    n2 = len(local)
    conflict = None
    if conflict_sigmas is not None:
        # |e_ij - e_ab| > k tol_ij  <=>  (e_ij - e_ab)^2 / (2 tol_ij^2) > k^2 / 2: symmetric
        # by construction (both length matrices are), pairs sharing a row or a col left out
        conflict = -0.5 * conflict_sigmas**2 > X
        conflict[invalid] = False
    return CandidateK(
        AssignmentProblem.trusted(sub.n, n2, R, cols, K_signed, conflict, invalid_zero=True),
        AssignmentProblem.trusted(sub.n, n2, R, cols, K_pos, invalid_zero=True),
        local,
    )


def extend_K(
    prev: CandidateK,
    sub: ObjectArrays,
    map_: ObjectArrays,
    rows: np.ndarray,
    map_nodes: np.ndarray,
    node_score: np.ndarray,
    aff: AffinityConfig,
    sigma_m: float,
    conflict_sigmas: float | None = None,
) -> CandidateK:
    """candidate_K over candidates whose first m are those of `prev` (same order, same
    scores): prev's K is copied and only the entries of the new candidates computed, to the
    same numbers candidate_K gives. rows, map_nodes, node_score: (M,), M >= m."""
    m, M = prev.signed.m, len(rows)
    R = np.asarray(rows, dtype=np.int64)
    local, cols = np.unique(map_nodes, return_inverse=True)
    e_sub = pairwise_lengths(sub.position_xyz_m)
    neg_inv = -0.5 / (sigma_m**2 + (aff.edge_rel_tol * e_sub) ** 2)
    xyz = map_.position_xyz_m[map_nodes]
    new = np.arange(m, M)
    # entries (p, q) with q new: every row against the new columns, one (M, M - m) block
    D = _cross_lengths(xyz, xyz[new])
    D -= block(e_sub, R, R[new])
    np.square(D, out=D)
    X = block(neg_inv, R, R[new]) * D
    invalid = (R[:, None] == R[new][None, :]) | (cols[:, None] == cols[new][None, :])
    w = edge_pair_weight(sub.n, aff)
    pos = exp_edges(X)
    pos *= w
    pos[invalid] = 0.0
    signed = pos - w * aff.edge_threshold
    signed[invalid] = 0.0
    K_pos = np.empty((M, M))
    K_signed = np.empty((M, M))
    for K, old, blk in ((K_pos, prev.positive.K, pos), (K_signed, prev.signed.K, signed)):
        K[:m, :m] = old
        K[:, m:] = blk
        K[m:, :m] = blk[:m].T
    np.fill_diagonal(K_pos, node_score)
    np.fill_diagonal(K_signed, node_score - aff.node_threshold)
    conflict = None
    if conflict_sigmas is not None and prev.signed.conflict is not None:
        c = -0.5 * conflict_sigmas**2 > X
        c[invalid] = False
        conflict = np.empty((M, M), dtype=bool)
        conflict[:m, :m] = prev.signed.conflict
        conflict[:, m:] = c
        conflict[m:, :m] = c[:m].T
        np.fill_diagonal(conflict, False)
    n2 = len(local)
    return CandidateK(
        AssignmentProblem.trusted(sub.n, n2, R, cols, K_signed, conflict, invalid_zero=True),
        AssignmentProblem.trusted(sub.n, n2, R, cols, K_pos, invalid_zero=True),
        local,
    )


def _cross_lengths(a_xyz: np.ndarray, b_xyz: np.ndarray) -> np.ndarray:
    """(k, 3), (l, 3) -> (k, l) distances between the two sets' points."""
    from scipy.spatial.distance import cdist

    return cdist(a_xyz, b_xyz)


def paper_node_affinity(sub: ObjectArrays, map_: ObjectArrays, aff: AffinityConfig
                        ) -> np.ndarray:
    """Paper mode's node affinity of every submap x map node, the diagonal of its K. (n1, n2).

    ucos as it is; a Gaussian distance mapped to a similarity (distance_to_similarity at the
    median), or with raw_distances the distance itself (the authors' code)."""
    kind = NodeAffinity(aff.kind)
    if kind is not NodeAffinity.UCOS and aff.raw_distances:
        # the authors' code: the distance itself used as the affinity
        return node_distance(kind, sub, map_, None, aff.normalize_embeddings)
    if kind is NodeAffinity.UCOS:
        return node_affinity(kind, sub, map_)
    D = node_distance(kind, sub, map_, None, aff.normalize_embeddings)
    return distance_to_similarity(D, float(np.median(D)))


def paper_K(
    A: np.ndarray, sub: ObjectArrays, map_: ObjectArrays, sigma_m: float, radius_m: float
) -> np.ndarray:
    """Paper mode's dense K over all n1 x n2 pairs, column-major (pygmtools' order).

    Diagonal: the node affinity A (n1, n2); off it: the edge affinity exp(-(e_ij - e_ab)^2 /
    (2 sigma_m^2)) between the edges of each graph within radius_m (relaxed until connected,
    geometry.radius_edges). pygmtools assembles it (solvers/dense.build_dense_K)."""
    e1, _ = radius_edges(sub.position_xyz_m, radius_m)
    e2, _ = radius_edges(map_.position_xyz_m, radius_m)
    len1 = np.linalg.norm(sub.position_xyz_m[e1[:, 0]] - sub.position_xyz_m[e1[:, 1]], axis=1)
    len2 = np.linalg.norm(map_.position_xyz_m[e2[:, 0]] - map_.position_xyz_m[e2[:, 1]], axis=1)
    return dense.build_dense_K(A, e1, len1, e2, len2, sigma=2.0 * sigma_m**2)
