from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize_scalar
from scipy.special import gammaln
from scipy.stats import multivariate_normal, multivariate_t

import mergesvc.core.affinity as affinity_mod
from mergesvc.core.affinity import (
    SameObjectModel,
    candidate_K,
    distance_to_similarity,
    edge_affinity,
    edge_pair_weight,
    edge_scales,
    exp_edges,
    fit_same_object_model,
    log_likelihood_ratio,
    log_likelihood_ratio_pairs,
    node_affinity,
    node_distance,
    paper_K,
    paper_node_affinity,
    weighted_cosine,
)
from mergesvc.core.config import AffinityConfig, NodeAffinity
from mergesvc.core.geometry import median_spacing, pairwise_lengths, radius_edges
from mergesvc.core.model import ObjectArrays


def _objs(rng: np.random.Generator, n: int, d: int) -> ObjectArrays:
    return ObjectArrays(
        ids=[f"o{k}" for k in range(n)],
        position_xyz_m=rng.normal(size=(n, 3)) * 5,
        embeddings_nd=rng.normal(size=(n, d)),
        variances_nd=rng.uniform(0.05, 0.5, size=(n, d)),
        n_obs=rng.integers(1, 6, size=n),
    )


def _f64(objs: ObjectArrays) -> np.ndarray:
    """The embeddings as held (float32), in float64 for the references' arithmetic."""
    return objs.embeddings_nd.astype(np.float64)


def _bhattacharyya_ref(mu1, var1, mu2, var2) -> float:
    S1, S2 = np.diag(var1), np.diag(var2)
    S = (S1 + S2) / 2
    dmu = mu1 - mu2
    return float(
        dmu @ np.linalg.inv(S) @ dmu / 8
        + 0.5 * np.log(np.linalg.det(S) / np.sqrt(np.linalg.det(S1) * np.linalg.det(S2)))
    )


def test_weighted_cosine_matches_formula() -> None:
    rng = np.random.default_rng(1)
    a, b = _objs(rng, 4, 6), _objs(rng, 5, 6)
    W = weighted_cosine(a.embeddings_nd, a.uncertainty_s, b.embeddings_nd, b.uncertainty_s)
    for i in range(4):
        for j in range(5):
            f1, f2 = _f64(a)[i], _f64(b)[j]
            cos = f1 @ f2 / np.linalg.norm(f1) / np.linalg.norm(f2)
            ref = cos / (1 + (a.uncertainty_s[i] + b.uncertainty_s[j]) / 2)
            assert W[i, j] == pytest.approx(ref, rel=1e-12)


@pytest.mark.parametrize("normalize", [False, True])
def test_gaussian_distances_match_dense_reference(normalize: bool) -> None:
    rng = np.random.default_rng(2)
    a, b = _objs(rng, 3, 5), _objs(rng, 4, 5)
    DB = node_distance(NodeAffinity.BHATTACHARYYA, a, b, normalize=normalize)
    DM = node_distance(NodeAffinity.MAHALANOBIS, a, b, normalize=normalize)
    for i in range(3):
        for j in range(4):
            mu1, var1 = _f64(a)[i], a.variances_nd[i]
            mu2, var2 = _f64(b)[j], b.variances_nd[j]
            if normalize:
                n1, n2 = np.linalg.norm(mu1), np.linalg.norm(mu2)
                mu1, var1, mu2, var2 = mu1 / n1, var1 / n1**2, mu2 / n2, var2 / n2**2
            # Bhattacharyya on appearance distributions: variance x n_obs
            ref_b = _bhattacharyya_ref(mu1, var1 * a.n_obs[i], mu2, var2 * b.n_obs[j])
            assert DB[i, j] == pytest.approx(ref_b, rel=1e-9)
            dmu = mu1 - mu2
            ref_m = dmu @ np.linalg.inv(np.diag(var1 + var2)) @ dmu
            assert DM[i, j] == pytest.approx(ref_m, rel=1e-9)


def test_chunking_gives_the_same_distances(monkeypatch: pytest.MonkeyPatch) -> None:
    import mergesvc.core.affinity as aff

    rng = np.random.default_rng(3)
    a, b = _objs(rng, 3, 7), _objs(rng, 50, 7)
    full = node_distance(NodeAffinity.BHATTACHARYYA, a, b)
    monkeypatch.setattr(aff, "_CHUNK_ELEMS", 30)  # a few map nodes per chunk
    np.testing.assert_allclose(node_distance(NodeAffinity.BHATTACHARYYA, a, b), full)


@pytest.mark.parametrize("kind", list(NodeAffinity))
def test_affinities_are_bounded_and_prefer_the_same_object(kind: NodeAffinity) -> None:
    rng = np.random.default_rng(4)
    b = _objs(rng, 30, 64)
    # re-observations of the first 10 map objects: small noise, larger variance
    a = ObjectArrays(
        ids=[f"s{k}" for k in range(10)],
        position_xyz_m=b.position_xyz_m[:10],
        embeddings_nd=b.embeddings_nd[:10] + rng.normal(size=(10, 64)) * 0.2,
        variances_nd=b.variances_nd[:10] * 2,
        n_obs=np.ones(10, dtype=int),
    )
    A = node_affinity(kind, a, b)
    assert A.shape == (10, 30)
    if kind is not NodeAffinity.LIKELIHOOD_RATIO:  # a log-odds: any real number
        lo = -1.0 if kind is NodeAffinity.UCOS else 0.0
        assert np.all(lo <= A) and np.all(A <= 1.0)
    assert np.all(np.argmax(A, axis=1) == np.arange(10)), "larger must mean more alike"


def test_distance_to_similarity() -> None:
    D = np.array([0.0, 1.0, 2.0, 10.0])
    s = distance_to_similarity(D, D_ref=2.0)
    assert s[0] == 1.0 and s[2] == pytest.approx(0.25)
    assert np.all(np.diff(s) < 0) and np.all(s > 0)


def test_radius_edges_relaxes_until_connected() -> None:
    # two clusters 10 m apart: radius 1 m is disconnected, the relaxed radius must bridge them
    rng = np.random.default_rng(5)
    pts = np.vstack([rng.uniform(0, 1, (6, 3)), rng.uniform(0, 1, (6, 3)) + np.array([10, 0, 0])])
    edges, r = radius_edges(pts, 1.0)
    assert r > 8.0
    L = pairwise_lengths(pts)
    assert np.all(L[edges[:, 0], edges[:, 1]] < r)
    assert np.all(edges[:, 0] < edges[:, 1])
    # every pair below the radius is an edge
    assert len(edges) == int((L[np.triu_indices(12, 1)] < r).sum())
    connected, r0 = radius_edges(pts[:6], 5.0)
    assert r0 == 5.0 and len(connected) == 15


def test_edge_affinity_and_spacing() -> None:
    assert edge_affinity(np.array(3.0), np.array(3.0), 1.0) == 1.0
    assert edge_affinity(np.array(3.0), np.array(4.0), 2.0) == pytest.approx(np.exp(-0.5))
    grid = np.array([[x, y, 0.0] for x in range(5) for y in range(5)]) * 2.0
    assert median_spacing(grid) == pytest.approx(2.0)


# ------------------------------------------------------------ same-object likelihood ratio


def _with(objs: ObjectArrays, **arrays: np.ndarray) -> ObjectArrays:
    fields = {"ids": objs.ids, "position_xyz_m": objs.position_xyz_m,
              "embeddings_nd": objs.embeddings_nd, "variances_nd": objs.variances_nd,
              "n_obs": objs.n_obs}
    return ObjectArrays(**{**fields, **arrays})


def _isotropic(objs: ObjectArrays) -> ObjectArrays:
    return _with(objs, variances_nd=np.repeat(objs.variances_nd[:, :1], objs.dim, axis=1))


def _lr_reference(mu1, var1, mu2, var2, c: float, D: float, nu: float) -> tuple[float, bool]:
    """Eq. LR-3 from scipy's densities, LR-5 as the minimum over the ray a * dmu, a in [0, 1],
    and C(nu, d) as the ratio's value for V -> inf (both densities at their peak).
    Returns (LLR, whether LR-5 applied)."""
    d = len(mu1)
    V = c * (var1 + var2)
    W = V + D
    t, g = multivariate_t(np.zeros(d), np.diag(V), df=nu), multivariate_normal(np.zeros(d), W)
    dmu = mu1 - mu2

    def llr(a: float) -> float:
        return float(t.logpdf(a * dmu) - g.logpdf(a * dmu))

    at_1 = llr(1.0)
    best = minimize_scalar(llr, bounds=(0.0, 1.0), method="bounded", options={"xatol": 1e-10})
    C = (gammaln((nu + d) / 2) - gammaln(nu / 2) - d / 2 * np.log(nu / 2))
    return min(at_1, float(best.fun)) - C, float(best.fun) < at_1 - 1e-9


def _fit_reference(sub: ObjectArrays, map_: ObjectArrays) -> tuple[float, float]:
    """Eqs. LR-2 and LR-4 by a direct loop: (c, D)."""
    u1 = _f64(sub) / np.linalg.norm(_f64(sub), axis=1, keepdims=True)
    u2 = _f64(map_) / np.linalg.norm(_f64(map_), axis=1, keepdims=True)
    d = sub.dim
    sq = [[float(np.sum((u1[i] - u2[a]) ** 2)) for a in range(map_.n)] for i in range(sub.n)]
    D = float(np.median(sq)) / d
    c_i = []
    for i in range(sub.n):
        a = int(np.argmin(sq[i]))
        c_i.append(np.mean((u1[i] - u2[a]) ** 2 / (sub.variances_nd[i] + map_.variances_nd[a])))
    return float(np.median(c_i)), D


@pytest.mark.parametrize("isotropic", [True, False])
@pytest.mark.parametrize("d", [3, 8])
def test_likelihood_ratio_matches_direct_reference(isotropic: bool, d: int) -> None:
    rng = np.random.default_rng(10 + d)
    a, b = _objs(rng, 4, d), _objs(rng, 7, d)
    if isotropic:
        a, b = _isotropic(a), _isotropic(b)
    model = fit_same_object_model(a, b)
    c, D = _fit_reference(a, b)
    assert model.c == pytest.approx(c, rel=1e-10) and pytest.approx(D, rel=1e-10) == model.D
    # as fitted, with vaguer variances, and with a small D that puts pairs beyond the ray
    # minimum of LR-5
    clamped = 0
    for c_scale, D_scale in ((1.0, 1.0), (30.0, 1.0), (1.0, 0.05)):
        m = SameObjectModel(c=model.c * c_scale, D=model.D * D_scale, normalize=True)
        L = log_likelihood_ratio(a, b, m)
        u1 = _f64(a) / np.linalg.norm(_f64(a), axis=1, keepdims=True)
        u2 = _f64(b) / np.linalg.norm(_f64(b), axis=1, keepdims=True)
        for i in range(a.n):
            for j in range(b.n):
                ref, beyond = _lr_reference(u1[i], a.variances_nd[i], u2[j],
                                            b.variances_nd[j], m.c, m.D, m.nu)
                assert L[i, j] == pytest.approx(ref, rel=1e-6, abs=1e-6)
                clamped += beyond
    assert 0 < clamped < 3 * a.n * b.n


def test_likelihood_ratio_isotropic_shortcut_equals_general_path(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    rng = np.random.default_rng(11)
    a, b = _isotropic(_objs(rng, 5, 32)), _isotropic(_objs(rng, 40, 32))
    fast = node_affinity(NodeAffinity.LIKELIHOOD_RATIO, a, b)
    monkeypatch.setattr(affinity_mod, "is_isotropic", lambda var: False)
    monkeypatch.setattr(affinity_mod, "_LR_CHUNK_ELEMS", 5 * 32 * 7)  # several chunks
    slow = node_affinity(NodeAffinity.LIKELIHOOD_RATIO, a, b)
    np.testing.assert_allclose(fast, slow, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("isotropic", [True, False])
def test_likelihood_ratio_invariances(isotropic: bool) -> None:
    rng = np.random.default_rng(12)
    a, b = _objs(rng, 6, 24), _objs(rng, 50, 24)
    if isotropic:
        a, b = _isotropic(a), _isotropic(b)
    kind = NodeAffinity.LIKELIHOOD_RATIO
    L = node_affinity(kind, a, b)
    # each embedding's norm (brightness) and one common unit of all variances: no effect
    # (powers of two: the float32 embeddings scale exactly)
    a2 = _with(a, embeddings_nd=a.embeddings_nd * 2.0 ** rng.integers(-3, 4, (a.n, 1)),
               variances_nd=a.variances_nd * 7.0)
    b2 = _with(b, embeddings_nd=b.embeddings_nd * 2.0 ** rng.integers(-3, 4, (b.n, 1)),
               variances_nd=b.variances_nd * 7.0)
    np.testing.assert_allclose(node_affinity(kind, a2, b2), L, rtol=1e-9, atol=1e-9)
    # without normalisation: one scale of all embeddings (and their variances with its square)
    raw = node_affinity(kind, a, b, normalize=False)
    a3 = _with(a, embeddings_nd=a.embeddings_nd * 32.0, variances_nd=a.variances_nd * 1024.0)
    b3 = _with(b, embeddings_nd=b.embeddings_nd * 32.0, variances_nd=b.variances_nd * 1024.0)
    np.testing.assert_allclose(node_affinity(kind, a3, b3, normalize=False), raw, rtol=1e-9,
                               atol=1e-9)
    # permuting either side permutes the rows / columns
    p1, p2 = rng.permutation(a.n), rng.permutation(b.n)
    perm = node_affinity(kind, a.subset(p1), b.subset(p2))
    np.testing.assert_allclose(perm, L[np.ix_(p1, p2)], rtol=1e-9, atol=1e-9)


def test_likelihood_ratio_monotone() -> None:
    d, D = 16, 0.05
    model = SameObjectModel(c=1.0, D=D, normalize=False)
    rng = np.random.default_rng(13)
    direction = rng.normal(size=d)
    direction /= np.linalg.norm(direction)

    def lr(dist: float, var: float) -> float:
        one = ObjectArrays(["s"], np.zeros((1, 3)), np.zeros((1, d)), np.full((1, d), var / 2),
                           np.ones(1, dtype=int))
        two = ObjectArrays(["m"], np.zeros((1, 3)), (dist * direction)[None, :],
                           np.full((1, d), var / 2), np.ones(1, dtype=int))
        return float(log_likelihood_ratio(one, two, model)[0, 0])

    # a closer mean is more likely the same object: strictly up to the ray minimum of LR-5
    # (|dmu|^2 = (nu + d) D + d V), then flat
    V = 0.01
    turn = np.sqrt((model.nu + d) * D + d * V)
    dists = np.linspace(0.0, 0.99 * turn, 30)
    assert np.all(np.diff([lr(x, V) for x in dists]) < 0)
    assert lr(1.5 * turn, V) == pytest.approx(lr(turn, V), rel=1e-12)
    assert lr(3.0 * turn, V) == pytest.approx(lr(turn, V), rel=1e-12)
    # the variance, as eq. LR-3 says: identical means are weaker evidence the vaguer the
    # estimates (d/2 ln(1 + D/V)); a difference far beyond what V explains is explained away
    # by a larger V; an uninformative posterior (V >> D) gives no evidence (LLR -> 0)
    assert lr(0.0, 0.001) > lr(0.0, 0.01) > lr(0.0, 0.1) > 0.0
    assert lr(0.0, 0.001) == pytest.approx(d / 2 * np.log1p(D / 0.001), rel=1e-12)
    far = 0.5 * turn
    assert far**2 > 10 * d * 0.002
    assert lr(far, 0.001) < lr(far, 0.002)
    assert abs(lr(0.1, 1e6)) < 1e-3


@pytest.mark.parametrize("isotropic", [True, False])
@pytest.mark.parametrize("d", [128, 768])
def test_likelihood_ratio_finite_on_extreme_inputs(isotropic: bool, d: int) -> None:
    rng = np.random.default_rng(14)
    n1, n2 = 5, 12
    # embeddings are held in float32: extremes of its range (beyond it they are refused)
    emb1 = rng.normal(size=(n1, d)) * np.array([1e-30, 1e30, 1.0, 1.0, 0.0])[:, None]
    emb2 = rng.normal(size=(n2, d)) * 10.0 ** rng.uniform(-30, 30, (n2, 1))
    emb2[0] = emb1[2]  # one identical pair
    var1 = 10.0 ** rng.choice([-300.0, -5.0, 0.0, 300.0], size=(n1, 1 if isotropic else d))
    var2 = 10.0 ** rng.choice([-300.0, -5.0, 0.0, 300.0], size=(n2, 1 if isotropic else d))
    a = ObjectArrays([f"s{k}" for k in range(n1)], np.zeros((n1, 3)), emb1,
                     np.broadcast_to(var1, (n1, d)).copy(), np.ones(n1, dtype=int))
    b = ObjectArrays([f"m{k}" for k in range(n2)], np.zeros((n2, 3)), emb2,
                     np.broadcast_to(var2, (n2, d)).copy(), np.ones(n2, dtype=int))
    for normalize in (True, False):
        with np.errstate(over="raise", invalid="raise"):  # no overflow or NaN on the way
            L = node_affinity(NodeAffinity.LIKELIHOOD_RATIO, a, b, normalize=normalize)
        assert np.all(np.isfinite(L))
        Dist = node_distance(NodeAffinity.LIKELIHOOD_RATIO, a, b, normalize=normalize)
        assert np.all(np.isfinite(Dist)) and np.all(Dist >= 0)
        assert np.allclose(Dist.min(axis=1), 0.0)  # eq. LR-6: 0 at each row's best


def test_likelihood_ratio_prefers_the_same_object_and_uses_the_variance() -> None:
    # two map candidates at the same distance from the submap object: the one whose variance
    # explains the difference wins; a far candidate with a tight variance loses to both
    rng = np.random.default_rng(15)
    d = 64
    b = _isotropic(_objs(rng, 200, d))
    x = rng.normal(size=d)
    x /= np.linalg.norm(x)
    step = rng.normal(size=(2, d)) * 0.03
    emb = np.vstack([b.embeddings_nd, x + step[0], x + step[1] * np.linalg.norm(step[0])
                     / np.linalg.norm(step[1])])
    var = np.vstack([b.variances_nd, np.full((1, d), 1e-3), np.full((1, d), 1e-5)])
    m = ObjectArrays([f"m{k}" for k in range(len(emb))], np.zeros((len(emb), 3)), emb, var,
                     np.ones(len(emb), dtype=int))
    s = ObjectArrays(["s"], np.zeros((1, 3)), x[None, :], np.full((1, d), 1e-5),
                     np.ones(1, dtype=int))
    L = node_affinity(NodeAffinity.LIKELIHOOD_RATIO, s, m)[0]
    assert np.argmax(L) == 200 and L[200] > L[201] > np.median(L)


@pytest.mark.parametrize("isotropic", [True, False])
def test_likelihood_ratio_of_pairs_equals_the_dense_matrix(
    isotropic: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(affinity_mod, "_LR_CHUNK_ELEMS", 20 * 7)  # 7 pairs per chunk
    rng = np.random.default_rng(16)
    a, b = _objs(rng, 4, 20), _objs(rng, 30, 20)
    if isotropic:
        a, b = _isotropic(a), _isotropic(b)
    model = fit_same_object_model(a, b)
    rows, cols = rng.integers(0, a.n, 50), rng.integers(0, b.n, 50)
    dense = log_likelihood_ratio(a, b, model)
    np.testing.assert_allclose(
        log_likelihood_ratio_pairs(a, b, model, rows, cols), dense[rows, cols], rtol=1e-9,
        atol=1e-9,
    )


# --------------------------------------------------------------------------- K


def _tiny_candidates(rng: np.random.Generator, n1: int, n2: int, per_row: int
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Candidate pairs of a tiny example: per_row distinct map nodes per submap node (map
    nodes shared between rows), a score in (0, 1) each."""
    rows = np.repeat(np.arange(n1), per_row)
    map_nodes = np.concatenate([rng.choice(n2, size=per_row, replace=False) for _ in range(n1)])
    return rows, map_nodes, rng.uniform(0.05, 1.0, size=len(rows))


@pytest.mark.parametrize("conflict_sigmas", [None, 1.5])
def test_candidate_K_matches_double_loop_reference(conflict_sigmas: float | None) -> None:
    rng = np.random.default_rng(21)
    n1, n2 = 4, 7
    sub, map_ = _objs(rng, n1, 3), _objs(rng, n2, 3)
    rows, map_nodes, score = _tiny_candidates(rng, n1, n2, per_row=3)
    aff = AffinityConfig(edge_rel_tol=0.1, edge_weight=0.7, edge_threshold=0.25,
                         node_threshold=0.4)
    sigma_m = 1.3
    signed, positive, local = candidate_K(
        sub, map_, rows, map_nodes, score, aff, sigma_m, conflict_sigmas
    )

    # reference: one entry at a time, straight from the formulas
    m = len(rows)
    w = aff.edge_weight / (n1 - 1) / 2.0
    K_pos, K_signed = np.zeros((m, m)), np.zeros((m, m))
    conflict = np.zeros((m, m), dtype=bool)
    for p in range(m):
        for q in range(m):
            i, a, j, b = rows[p], map_nodes[p], rows[q], map_nodes[q]
            if p == q:
                K_pos[p, p] = score[p]
                K_signed[p, p] = score[p] - aff.node_threshold
                continue
            if i == j or a == b:
                continue  # never both chosen: no entry
            e_ij = np.linalg.norm(sub.position_xyz_m[i] - sub.position_xyz_m[j])
            e_ab = np.linalg.norm(map_.position_xyz_m[a] - map_.position_xyz_m[b])
            tol2 = sigma_m**2 + (aff.edge_rel_tol * e_ij) ** 2
            a_e = np.exp(-((e_ij - e_ab) ** 2) / (2.0 * tol2))
            K_pos[p, q] = w * a_e
            K_signed[p, q] = w * (a_e - aff.edge_threshold)
            if conflict_sigmas is not None:
                conflict[p, q] = abs(e_ij - e_ab) > conflict_sigmas * np.sqrt(tol2)

    np.testing.assert_array_equal(local, np.unique(map_nodes))
    for problem in (signed, positive):
        assert (problem.n1, problem.n2) == (n1, len(local))
        np.testing.assert_array_equal(problem.rows, rows)
        np.testing.assert_array_equal(local[problem.cols], map_nodes)
    np.testing.assert_allclose(positive.K, K_pos, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(signed.K, K_signed, rtol=1e-12, atol=1e-15)
    assert positive.conflict is None
    if conflict_sigmas is None:
        assert signed.conflict is None
    else:
        assert conflict.any() and not conflict.all()  # the example exercises both outcomes
        np.testing.assert_array_equal(signed.conflict, conflict)
    assert w == edge_pair_weight(n1, aff)


def test_edge_scales_from_spacing_unless_set() -> None:
    rng = np.random.default_rng(22)
    map_ = _objs(rng, 9, 3)
    spacing = median_spacing(map_.position_xyz_m)
    assert edge_scales(map_, AffinityConfig(spacing_sigma=0.2)) == pytest.approx(
        (0.2 * spacing, 3.0 * spacing), rel=1e-12
    )
    assert edge_scales(map_, AffinityConfig(edge_sigma_m=0.5, edge_radius_m=4.0)) == (0.5, 4.0)


def test_paper_K_matches_double_loop_reference() -> None:
    rng = np.random.default_rng(23)
    n1, n2, sigma_m = 3, 4, 0.9
    sub, map_ = _objs(rng, n1, 3), _objs(rng, n2, 3)
    A = rng.random((n1, n2))
    K = paper_K(A, sub, map_, sigma_m, radius_m=1e6)  # every pair within the radius
    ref = np.zeros((n1 * n2, n1 * n2))  # pygmtools' column-major index a * n1 + i
    for i in range(n1):
        for a in range(n2):
            for j in range(n1):
                for b in range(n2):
                    if (i, a) == (j, b):
                        ref[a * n1 + i, a * n1 + i] = A[i, a]
                    elif i != j and a != b:
                        e_ij = np.linalg.norm(sub.position_xyz_m[i] - sub.position_xyz_m[j])
                        e_ab = np.linalg.norm(map_.position_xyz_m[a] - map_.position_xyz_m[b])
                        ref[a * n1 + i, b * n1 + j] = np.exp(-((e_ij - e_ab) ** 2)
                                                             / (2.0 * sigma_m**2))
    np.testing.assert_allclose(K, ref, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("kind", list(NodeAffinity))
def test_paper_node_affinity(kind: NodeAffinity) -> None:
    rng = np.random.default_rng(24)
    sub, map_ = _objs(rng, 3, 5), _objs(rng, 6, 5)
    A = paper_node_affinity(sub, map_, AffinityConfig(kind=kind))
    if kind is NodeAffinity.UCOS:
        np.testing.assert_array_equal(A, node_affinity(kind, sub, map_))
        return
    D = node_distance(kind, sub, map_)
    np.testing.assert_array_equal(A, distance_to_similarity(D, float(np.median(D))))
    raw = paper_node_affinity(sub, map_, AffinityConfig(kind=kind, raw_distances=True))
    np.testing.assert_array_equal(raw, D)  # the authors' code: the distance as the affinity


def test_extend_K_equals_candidate_K_over_the_enlarged_set(kitti_scenario) -> None:
    """Guided matching keeps K over the first candidates and computes only the new entries:
    the same numbers (and conflicts) as building K over all of them."""
    from mergesvc.core.affinity import edge_scales, extend_K
    from mergesvc.core.candidates import expand_near, retrieve
    from mergesvc.core.config import MatchConfig

    cfg = MatchConfig()
    m, s = kitti_scenario.map.arrays(), kitti_scenario.submap.arrays()
    cands, calib = retrieve(s, m, cfg.candidates, cfg.affinity, np.random.default_rng(0))
    sigma, _ = edge_scales(m, cfg.affinity)
    first = candidate_K(s, m, cands.rows, cands.map_nodes, cands.score, cfg.affinity, sigma,
                        6.0)
    rng = np.random.default_rng(1)
    predicted = m.position_xyz_m[rng.integers(0, m.n, s.n)]
    more = expand_near(cands, s, m, predicted, np.full(s.n, 30.0), calib)
    assert more.m > cands.m
    np.testing.assert_array_equal(more.rows[:cands.m], cands.rows)
    full = candidate_K(s, m, more.rows, more.map_nodes, more.score, cfg.affinity, sigma, 6.0)
    ext = extend_K(first, s, m, more.rows, more.map_nodes, more.score, cfg.affinity, sigma, 6.0)
    for a, b in ((full.signed, ext.signed), (full.positive, ext.positive)):
        np.testing.assert_array_equal(a.K, b.K)
        np.testing.assert_array_equal(a.cols, b.cols)
    np.testing.assert_array_equal(full.signed.conflict, ext.signed.conflict)
    np.testing.assert_array_equal(full.local, ext.local)


def test_exp_edges_is_numpy_exp_without_subnormals() -> None:
    """exp_edges gives np.exp's floats wherever they are normal, 0 where np.exp underflows
    (subnormal or 0), on either side of both limits."""
    rng = np.random.default_rng(3)
    X = -np.concatenate([rng.random(3000) * 5, rng.random(3000) * 1e5,
                         rng.uniform(700, 760, 2400)])
    rng.shuffle(X)
    X[:6] = [-708.39, -708.40, -745.13, -745.14, -746.0, 0.0]
    for shape in ((1200, 7), (2, 3)):
        x = X[: shape[0] * shape[1]].reshape(shape)
        got, want = exp_edges(x), np.exp(x)
        normal = want >= np.finfo(np.float64).tiny
        assert np.array_equal(got[normal], want[normal])
        assert not got[~normal].any()
    assert exp_edges(X.reshape(1200, 7)).any() and (np.exp(X) > 0).sum() > (exp_edges(X) > 0).sum()
