"""The candidate stage's shortlist: exact chunked search against brute force, the IVF index's
recall of the exact top-k (look-alikes included), incremental adds."""

from __future__ import annotations

import numpy as np
import pytest

from mergesvc.core.arrays import ObjectArrays
from mergesvc.core.config import CandidatesConfig
from mergesvc.core.search import (
    ExactSearch,
    IvfSearch,
    attach_search,
    make_search,
    map_search,
    multiplied_pairs,
)
from mergesvc.errors import InputError


def _clustered(n: int, d: int, seed: int, twins: float = 0.2) -> tuple[np.ndarray, np.ndarray]:
    """Unit-ish rows around 8 class centres; a share of them near-copies (look-alikes) of
    others. Returns (rows (n, d) float32, twin source (n,), -1 for originals)."""
    rng = np.random.default_rng(seed)
    C = rng.normal(size=(8, d))
    C /= np.linalg.norm(C, axis=1, keepdims=True)
    X = C[rng.integers(0, 8, n)] + 0.6 * rng.normal(size=(n, d)) / np.sqrt(d)
    src = np.full(n, -1)
    k = int(twins * n)
    copies = rng.choice(n, k, replace=False)
    src[copies] = rng.choice(n, k)
    X[copies] = X[src[copies]] + 0.2 * rng.normal(size=(k, d)) / np.sqrt(d)
    X *= rng.uniform(2.0, 6.0, (n, 1))
    return X.astype(np.float32), src


def _brute(X: np.ndarray, q: np.ndarray, k: int) -> np.ndarray:
    cos = (q.astype(np.float64) @ X.T.astype(np.float64)) / np.linalg.norm(
        X.astype(np.float64), axis=1)
    return np.argsort(-cos, axis=1, kind="stable")[:, :k]


def test_exact_search_equals_brute_force_across_chunks_and_adds() -> None:
    X, _ = _clustered(3000, 24, 0)
    rng = np.random.default_rng(1)
    q = rng.normal(size=(300, 24)).astype(np.float32)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    norms = np.linalg.norm(X.astype(np.float64), axis=1)
    s = ExactSearch(X[:2000], norms[:2000], chunk_rows=333)  # several chunks
    s.add(X[2000:])  # the map grows: rows 2000..2999
    rows, cos = s.search(q, 10)  # 300 queries: more than one query block
    ref = _brute(X, q, 10)
    assert s.n == 3000
    np.testing.assert_array_equal(rows, ref)
    assert np.all(np.diff(cos, axis=1) <= 1e-6)  # best first
    np.testing.assert_allclose(
        cos[:, 0], np.einsum("md,md->m", q, X[ref[:, 0]]) / norms[ref[:, 0]], rtol=1e-5)


def test_exact_search_in_any_order_finds_the_same_rows_and_cosines() -> None:
    """ordered=False (the last top-k left unsorted) on a map of one chunk: the ordered answer's rows
    and cosines, row by row, in some order."""
    X, _ = _clustered(900, 24, 2)
    q = np.random.default_rng(3).normal(size=(20, 24)).astype(np.float32)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    s = ExactSearch(X, np.linalg.norm(X.astype(np.float64), axis=1))
    rows, cos = s.search(q, 256)
    any_rows, any_cos = s.search(q, 256, ordered=False)
    assert any_rows.shape == (20, 256)
    assert not np.array_equal(any_rows, rows)  # not sorted: the last sort was skipped
    order = np.argsort(-any_cos, axis=1, kind="stable")
    np.testing.assert_array_equal(np.sort(any_rows, axis=1), np.sort(rows, axis=1))
    np.testing.assert_allclose(np.take_along_axis(any_cos, order, axis=1), cos, rtol=1e-6)


def test_ivf_recall_of_the_exact_top_k_including_look_alikes() -> None:
    X, src = _clustered(20_000, 32, 2)
    norms = np.linalg.norm(X.astype(np.float64), axis=1)
    rng = np.random.default_rng(3)
    # queries: noisy views of map objects, half of them objects that have a look-alike
    look = np.flatnonzero(src >= 0)[:100]
    plain = rng.choice(np.flatnonzero(src < 0), 100, replace=False)
    who = np.concatenate([look, plain])
    q = X[who] + 0.1 * rng.normal(size=(len(who), 32)) * norms[who, None] / np.sqrt(32)
    q = (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32)
    index = IvfSearch(X, norms)
    got = index.search(q, 12)[0]
    ref = _brute(X, q, 12)
    recall = np.array([len(set(g) & set(r)) / 12 for g, r in zip(got, ref)])
    assert recall.mean() >= 0.99 and recall[:100].mean() >= 0.99, recall.mean()
    assert index.n_probe < index.n_lists  # an index, not a scan in disguise


def test_ivf_best_rows_are_exact_and_the_rest_within_the_codes_error() -> None:
    """The index ranks what it probes by 8-bit codes held in memory and reads the map's rows
    only where the codes' error could change the best exact_top: those rows and cosines are
    the exact search's (look-alikes, near ties and rows whose codes clipped included), the
    rest are the codes' cosines, within their stated error."""
    X, _ = _clustered(6_000, 32, 4, twins=0.4)
    norms = np.linalg.norm(X.astype(np.float64), axis=1)
    index = IvfSearch(X, norms, n_probe=10**6, shortlist=6_000, exact_top=10)
    # rows beyond the codes' range (fit on the training sample): clipped, still found exactly
    rng = np.random.default_rng(5)
    far = X[:50] + 0.0
    far[:, 3] += 40 * np.abs(X[:, 3]).max()
    index.add(far)
    Y = np.vstack([X, far])
    assert (index._excess[6_000:6_050] > 0).all() and (index._excess[:6_000] == 0).mean() > 0.99
    who = np.concatenate([rng.choice(6_000, 150, replace=False), np.arange(6_000, 6_050)])
    q = Y[who] + 0.05 * rng.normal(size=(len(who), 32)) * np.linalg.norm(Y[who], axis=1,
                                                                       keepdims=True) / 6
    q = (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32)
    rows, cos = index.search(q, 40)
    ref_rows, ref_cos = ExactSearch(Y, np.linalg.norm(Y.astype(np.float64), axis=1)).search(q, 40)
    np.testing.assert_array_equal(rows[:, :10], ref_rows[:, :10])
    np.testing.assert_allclose(cos[:, :10], ref_cos[:, :10], atol=1e-6)
    exact = np.einsum("mkd,md->mk", Y[rows].astype(np.float64), q) / np.linalg.norm(
        Y[rows].astype(np.float64), axis=2)
    bound = 6 / np.sqrt(12) * np.linalg.norm(q * index._step, axis=1)
    assert (np.abs(cos - exact) <= bound[:, None] + 1e-6).all()
    assert (np.abs(cos - exact)[:, 10:] > 1e-5).mean() > 0.2  # not all read: the codes
    assert np.mean([len(set(a) & set(b)) / 40 for a, b in zip(rows, ref_rows)]) > 0.95


def test_candidates_through_the_index_are_those_of_the_exact_search() -> None:
    """The candidate stage on an indexed map keeps, per submap object, the same candidates
    with the same affinities as on the exact search: the index's shortlist carries the 8-bit
    codes' cosines beyond its best rows, and wide uncertainties lift candidates from far below
    them into the top_k, so those that could are read exactly."""
    from mergesvc.core.candidates import retrieve
    from mergesvc.core.config import match_config

    X, _ = _clustered(20_000, 48, 7, twins=0.4)
    rng = np.random.default_rng(8)
    n, m = len(X), 60
    pos, var = rng.normal(size=(n, 3)), rng.uniform(0.01, 0.6, n)
    who = rng.choice(n, m, replace=False)
    Q = X[who] + 0.3 * rng.normal(size=(m, 48)) * np.linalg.norm(X[who], axis=1,
                                                                keepdims=True) / np.sqrt(48)
    sub = ObjectArrays([f"s{i}" for i in range(m)], pos[who], Q, rng.uniform(0.01, 0.6, m),
                       np.ones(m, dtype=np.int64))
    cfg = match_config(None)
    got = {}
    for kind in ("exact", "ivf"):
        map_ = ObjectArrays([f"m{i}" for i in range(n)], pos, X, var, np.ones(n, dtype=np.int64))
        cand_cfg = cfg.candidates.model_copy(update={"index": kind})
        c, _ = retrieve(sub, map_, cand_cfg, cfg.affinity, np.random.default_rng(0))
        got[kind] = dict(zip(zip(c.rows.tolist(), c.map_nodes.tolist()), c.affinity.tolist()))
        assert kind == "exact" or isinstance(map_.cache.get("search"), IvfSearch)
    assert got["ivf"].keys() == got["exact"].keys()
    np.testing.assert_allclose([got["ivf"][p] for p in got["exact"]], list(got["exact"].values()),
                               rtol=1e-6)


def test_ivf_probes_as_many_lists_as_the_map_needs() -> None:
    """The lists probed are measured on the map, not fixed: tight separate clusters need a few,
    diffuse overlapping ones many; the recall it reports is what brute force finds."""
    rng = np.random.default_rng(6)
    C = rng.normal(size=(200, 32))
    C /= np.linalg.norm(C, axis=1, keepdims=True)
    tight = (C[rng.integers(0, 200, 20_000)]
             + 0.02 * rng.normal(size=(20_000, 32)) / np.sqrt(32)).astype(np.float32)
    diffuse, _ = _clustered(20_000, 32, 2)
    found = {}
    for name, X in (("tight", tight), ("diffuse", diffuse)):
        norms = np.linalg.norm(X.astype(np.float64), axis=1)
        index = IvfSearch(X, norms, seed=1)
        assert index.recall >= 0.995 and index.n_probe < index.n_lists
        # other map rows than the calibration's: the exact top-12 without the row itself
        who = np.random.default_rng(7).choice(len(X), 100, replace=False)
        q = (X[who] / norms[who, None]).astype(np.float32)
        got, ref = index.search(q, 13)[0], _brute(X, q, 13)
        recall = [len((set(g) - {w}) & (set(r) - {w})) / len(set(r) - {w})
                  for g, r, w in zip(got, ref, who)]
        assert np.mean(recall) >= 0.99, (name, np.mean(recall))
        found[name] = index.n_probe
    assert found["tight"] < found["diffuse"], found
    X, _ = _clustered(2000, 8, 8)
    norms = np.linalg.norm(X.astype(np.float64), axis=1)
    fixed = IvfSearch(X, norms, n_probe=3)
    assert fixed.n_probe == 3 and 0 < fixed.recall <= 1  # told: kept, the rest measured
    told = IvfSearch(X, norms, n_probe=3, shortlist=64)
    assert (told.n_probe, told.shortlist) == (3, 64) and np.isnan(told.recall)


def test_ivf_add_makes_new_rows_findable() -> None:
    X, _ = _clustered(4000, 16, 4)
    norms = np.linalg.norm(X.astype(np.float64), axis=1)
    index = IvfSearch(X[:3000], norms[:3000])
    index.add(X[3000:])
    assert index.n == 4000
    q = X[3500:3510] / norms[3500:3510, None]
    rows, cos = index.search(q.astype(np.float32), 1)
    np.testing.assert_array_equal(rows[:, 0], np.arange(3500, 3510))
    np.testing.assert_allclose(cos[:, 0], 1.0, atol=1e-5)


def test_map_search_picks_and_keeps_the_index_by_size() -> None:
    X, _ = _clustered(2000, 8, 5)
    m = ObjectArrays([f"m{i}" for i in range(2000)], np.zeros((2000, 3)), X, np.ones(2000),
                     np.ones(2000, dtype=np.int64))
    auto = CandidatesConfig()
    assert isinstance(map_search(m, auto), ExactSearch) and "search" not in m.cache
    small = CandidatesConfig(index_min_objects=1000)
    ivf = map_search(m, small)
    assert isinstance(ivf, IvfSearch) and map_search(m, small) is ivf  # built once, kept
    assert isinstance(make_search(m, CandidatesConfig(index="exact")), ExactSearch)
    exact = ExactSearch(m.embeddings_nd, m.norms_n)
    attach_search(m, exact)
    assert map_search(m, small) is exact
    with pytest.raises(InputError):
        attach_search(m, ExactSearch(X[:10], m.norms_n[:10]))


def test_ivf_never_returns_a_missing_row() -> None:
    """A small calibrated probe whose lists hold fewer rows than asked probes more lists; a
    query no code scores (a zero embedding) gets the exact search's rows."""
    rng = np.random.default_rng(9)
    C = rng.normal(size=(200, 32))
    X = (C[rng.integers(0, 200, 20_000)] + 0.02 * rng.normal(size=(20_000, 32))).astype(
        np.float32)
    index = IvfSearch(X, np.linalg.norm(X.astype(np.float64), axis=1))
    assert index.n_probe * 20_000 / index.n_lists < 512  # its lists hold fewer than asked
    q = np.vstack([X[:40] / np.linalg.norm(X[:40], axis=1, keepdims=True),
                   np.zeros((1, 32))]).astype(np.float32)
    rows, cos = index.search(q, 512)
    assert rows.min() >= 0 and all(len(set(r)) == 512 for r in rows)
    assert np.all(cos[-1] == 0)  # the zero query: every row alike, none missing


def test_ivf_keeps_its_recall_as_the_map_grows() -> None:
    """The re-ranking depth measured at build scales with the rows added since."""
    X, _ = _clustered(20_000, 32, 10)
    norms = np.linalg.norm(X.astype(np.float64), axis=1)
    index = IvfSearch(X[:2000], norms[:2000])
    index.add(X[2000:], norms[2000:])
    rng = np.random.default_rng(11)
    who = rng.choice(20_000, 200, replace=False)
    q = X[who] + 0.1 * rng.normal(size=(200, 32)) * norms[who, None] / np.sqrt(32)
    q = (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32)
    got, ref = index.search(q, 12)[0], _brute(X, q, 12)
    recall = np.mean([len(set(g) & set(r)) / 12 for g, r in zip(got, ref)])
    assert recall >= 0.99, recall


def test_the_blas_counts_whole_map_products_only_and_tiny_maps_are_searched_exactly() -> None:
    X, _ = _clustered(3000, 8, 12)
    m = ObjectArrays([f"m{i}" for i in range(3000)], np.zeros((3000, 3)), X, np.ones(3000),
                     np.ones(3000, dtype=np.int64))
    assert multiplied_pairs(m, CandidatesConfig(), 20) == 3000 * 20  # exact: all of them
    assert multiplied_pairs(m, CandidatesConfig(index="ivf"), 20) == 0  # the index's own
    tiny = ObjectArrays([f"t{i}" for i in range(100)], np.zeros((100, 3)), X[:100],
                        np.ones(100), np.ones(100, dtype=np.int64))
    assert isinstance(make_search(tiny, CandidatesConfig(index="ivf", index_min_lists=4)),
                      ExactSearch)
