"""Candidate stage: top-k retrieval, its calibration, and the likelihood-ratio node score in it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mergesvc.bench import (
    AffinityUncertaintyPlan,
    constant_variance,
    run_affinity_uncertainty_bench,
    score_case,
)
from mergesvc.core.affinity import fit_same_object_model, unit_rows
from mergesvc.core.candidates import pair_scores, retrieve, row_medians
from mergesvc.core.config import NodeAffinity, match_config
from mergesvc.core.pipeline import match
from mergesvc.sim import Family, Scenario, make_scenario


def _true_index(sc: Scenario) -> dict[int, int]:
    """submap row -> map row of its true match."""
    m, s = sc.map.arrays(), sc.submap.arrays()
    where = {oid: k for k, oid in enumerate(m.ids)}
    return {i: where[sc.truth[sid]] for i, sid in enumerate(s.ids) if sc.truth[sid] is not None}


@pytest.mark.parametrize("kind", list(NodeAffinity))
def test_retrieve_ranks_true_matches_and_pair_scores_agree(
    kind: NodeAffinity, kitti_scenario: Scenario
) -> None:
    sc = kitti_scenario
    cfg = match_config(affinity={"kind": kind.value})
    m, s = sc.map.arrays(), sc.submap.arrays()
    cands, calib = retrieve(s, m, cfg.candidates, cfg.affinity, np.random.default_rng(0))
    assert np.all(cands.score > 0) and np.all(cands.score <= 1.0)
    truth = _true_index(sc)
    first = {int(r): int(cands.map_nodes[np.flatnonzero(cands.rows == r)[0]])
             for r in np.unique(cands.rows)}
    assert np.mean([first.get(i) == a for i, a in truth.items()]) >= 0.75
    # the calibration reproduces the retrieved scores (guided matching re-scores pairs with it)
    aff, score = pair_scores(s, m, cands.rows, cands.map_nodes, calib)
    np.testing.assert_allclose(aff, cands.affinity, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(score, cands.score, rtol=1e-9, atol=1e-9)
    assert (calib.same_object is not None) == (kind is NodeAffinity.LIKELIHOOD_RATIO)


def test_likelihood_ratio_per_dimension_variances(kitti_scenario: Scenario) -> None:
    # retrieve scores the shortlisted pairs one by one; pair_scores takes the dense matrix over
    # their union: both must agree, and the true matches still come first
    sc = kitti_scenario
    rng = np.random.default_rng(1)
    m, s = sc.map.arrays(), sc.submap.arrays()
    m = replace(m, variances_nd=m.variances_nd * rng.uniform(0.3, 3.0, m.variances_nd.shape))
    s = replace(s, variances_nd=s.variances_nd * rng.uniform(0.3, 3.0, s.variances_nd.shape))
    cfg = match_config(affinity={"kind": "likelihood_ratio"}, candidates={"prefilter": 64})
    cands, calib = retrieve(s, m, cfg.candidates, cfg.affinity, np.random.default_rng(0))
    aff, score = pair_scores(s, m, cands.rows, cands.map_nodes, calib)
    np.testing.assert_allclose(aff, cands.affinity, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(score, cands.score, rtol=1e-9, atol=1e-9)
    first = {int(r): int(cands.map_nodes[np.flatnonzero(cands.rows == r)[0]])
             for r in np.unique(cands.rows)}
    truth = _true_index(sc)
    assert np.mean([first.get(i) == a for i, a in truth.items()]) >= 0.9


def test_likelihood_ratio_model_from_the_cosine_shortlist_equals_its_own_search() -> None:
    # a map larger than the prefilter: retrieve hands the cosine shortlist's nearest object in
    sc = make_scenario(Family.KITTI, seed=3, n_map=400, n_sub=10, n_outliers=2)
    m, s = sc.map.arrays(), sc.submap.arrays()
    nearest = (unit_rows(s.embeddings_nd)[0] @ m.unit_embeddings_nd.T).argmax(axis=1)
    sample = np.sort(np.random.default_rng(0).choice(m.n, 128, replace=False))
    assert fit_same_object_model(s, m, True, sample, nearest) == fit_same_object_model(
        s, m, True, sample)
    cfg = match_config(affinity={"kind": "likelihood_ratio"}, candidates={"prefilter": 64})
    cands, calib = retrieve(s, m, cfg.candidates, cfg.affinity, np.random.default_rng(0))
    assert calib.same_object is not None and cands.m > 0


@pytest.mark.parametrize("mode", ["verified", "paper"])
def test_likelihood_ratio_end_to_end(mode: str, small_kitti_scenario: Scenario) -> None:
    sc = small_kitti_scenario
    cfg = match_config(mode=mode, affinity={"kind": "likelihood_ratio"})
    out = match(sc.map, sc.submap, cfg)
    accuracy = score_case(sc, out)["accuracy"]
    if mode == "verified":
        assert out.result.accepted and accuracy >= 0.9
    else:  # paper mode (eq. LR-6 distances) matches every node; ucos gets 0.75 on this case
        assert len(out.result.matches) == len(sc.submap.objects) and accuracy >= 0.75


def test_constant_variance_keeps_means_and_drops_uncertainty(
    underwater_scenario: Scenario,
) -> None:
    m, s = underwater_scenario.map.arrays(), underwater_scenario.submap.arrays()
    m2, s2 = constant_variance(m, s)
    v = m.variances_nd.mean()
    assert np.all(m2.variances_nd == v) and np.all(s2.variances_nd == v)
    assert m2.embeddings_nd is m.embeddings_nd and s2.ids == s.ids


def test_affinity_uncertainty_bench_quick() -> None:
    lines: list[str] = []
    report = run_affinity_uncertainty_bench(AffinityUncertaintyPlan.quick(), lines.append)
    keys = {f"{w}/{a}/{v}" for w in ("underwater", "drive")
            for a in ("ucos", "likelihood_ratio") for v in ("tracked", "constant")}
    assert set(report["summary"]) == keys
    for r in report["summary"].values():
        for metric in ("precision", "recall", "node_accuracy"):
            assert 0.0 <= r[metric]["min"] <= r[metric]["median"] <= r[metric]["max"] <= 1.0
        assert 0.5 < r["candidate_auc"]["right_vs_wrong"] <= 1.0
    table = report["markdown"].splitlines()
    assert len(table) == 2 + len(keys) and table[2].startswith("| underwater | ucos | tracked |")


@pytest.mark.parametrize("kind", [NodeAffinity.UCOS, NodeAffinity.LIKELIHOOD_RATIO])
def test_floor_sample_kept_with_the_map_changes_nothing(
    kind: NodeAffinity, kitti_scenario: Scenario
) -> None:
    """The floor's sample rows kept with the map (per generator state) give the candidates and
    calibration of a fresh draw, and leave the generator where a fresh draw leaves it."""
    sc = kitti_scenario
    cfg = match_config(affinity={"kind": kind.value})
    m, s = sc.map.arrays(), sc.submap.arrays()
    assert m.n > cfg.candidates.sample  # the map is sampled, not taken whole
    fresh = [replace(m) for _ in range(2)]  # new ObjectArrays: empty caches
    runs = []
    for arrays in (fresh[0], fresh[1], fresh[1]):  # a fresh map, another, then its cache
        rng = np.random.default_rng(7)
        cands, calib = retrieve(s, arrays, cfg.candidates, cfg.affinity, rng)
        runs.append((cands, calib, rng.random()))
    assert any(k[0] == "floor_sample" for k in fresh[1].cache)
    for cands, calib, after in runs[1:]:
        for name in ("rows", "map_nodes", "affinity", "score"):
            assert np.array_equal(getattr(cands, name), getattr(runs[0][0], name))
        assert np.array_equal(calib.floor_n, runs[0][1].floor_n) and calib.ceil == runs[0][1].ceil
        assert after == runs[0][2]


def test_the_floor_reads_the_searchs_products_as_the_samples_own(kitti_scenario) -> None:
    """A map above the shortlist and the sample, searched exactly in one chunk: the search
    keeps its products, whose sample columns are the sample's own product (to the BLAS's
    rounding: a small-matrix path computes some entries otherwise), and the ucos floor read
    from them is the floor of that product (the reference)."""
    from mergesvc.core.search import ExactSearch

    sc = kitti_scenario
    cfg = match_config(affinity={"kind": "ucos"})
    m, s = replace(sc.map.arrays()), sc.submap.arrays()
    assert m.n > max(cfg.candidates.sample, cfg.candidates.prefilter)
    _, calib = retrieve(s, m, cfg.candidates, cfg.affinity, 7)
    idx = np.sort(np.random.default_rng(7).choice(m.n, cfg.candidates.sample, replace=False))
    q32 = s.unit_rows().astype(np.float32)
    e = np.asarray(m.embeddings_nd[idx], dtype=np.float32)
    _, _, products = ExactSearch(m.embeddings_nd, m.norms_n).search_with_products(q32, 256)
    assert products is not None and products.shape == (s.n, m.n)
    np.testing.assert_allclose(products[:, idx], q32 @ e.T, rtol=1e-6, atol=1e-6)
    norms = np.where(m.norms_n[idx] > 0, m.norms_n[idx], 1.0)
    u = (s.uncertainty_s[:, None] + m.uncertainty_s[idx][None, :]) / 2.0
    floor = np.median(((q32 @ e.T) / norms).astype(np.float64) / (1.0 + u), axis=1)
    np.testing.assert_allclose(calib.floor_n, floor, rtol=1e-6, atol=1e-9)
    many = ExactSearch(m.embeddings_nd, m.norms_n, chunk_rows=100)  # several chunks: none kept
    assert many.search_with_products(q32, 256)[2] is None


@pytest.mark.parametrize("cols", [1, 2, 7, 512, 513])
def test_row_medians_are_numpys_medians_to_the_bit(cols: int) -> None:
    rng = np.random.default_rng(cols)
    for values in (rng.normal(size=(20, cols)), rng.integers(0, 3, (5, cols)).astype(float)):
        np.testing.assert_array_equal(row_medians(values), np.median(values, axis=1))
