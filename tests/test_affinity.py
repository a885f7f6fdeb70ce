from __future__ import annotations

import numpy as np
import pytest

from mergesvc.affinity import (
    NodeAffinity,
    distance_to_similarity,
    edge_affinity,
    median_spacing,
    node_affinity,
    node_distance,
    pairwise_lengths,
    radius_edges,
    weighted_cosine,
)
from mergesvc.model import ObjectArrays


def _objs(rng: np.random.Generator, n: int, d: int) -> ObjectArrays:
    return ObjectArrays(
        ids=[f"o{k}" for k in range(n)],
        position_xyz_m=rng.normal(size=(n, 3)) * 5,
        embeddings_nd=rng.normal(size=(n, d)),
        variances_nd=rng.uniform(0.05, 0.5, size=(n, d)),
        n_obs=rng.integers(1, 6, size=n),
    )


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
            f1, f2 = a.embeddings_nd[i], b.embeddings_nd[j]
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
            mu1, var1 = a.embeddings_nd[i], a.variances_nd[i]
            mu2, var2 = b.embeddings_nd[j], b.variances_nd[j]
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
    import mergesvc.affinity as aff

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
