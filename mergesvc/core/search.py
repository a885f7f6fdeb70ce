"""Nearest map objects by cosine, the candidate stage's shortlist: exact or indexed.

`ExactSearch`: chunked float32 products over the map's rows, a running top-k; memory per step
bounded whatever the map size, exact. `IvfSearch`: an inverted-file index (faiss-cpu, 4-bit
codes per dimension scanned with SIMD lookups, an eighth of the float32 embeddings) probed for
a wide shortlist, ranked by 8-bit codes per dimension held in memory (a quarter of the
embeddings). The map's own rows are read (`take_rows`: never kept resident) only for the rows
the 8-bit codes' error could bring into the best `exact_top`, whose rows and cosines are then
the exact top of what was probed; the rest carry the codes' cosines with a bound on their
error (`search_bounded`: 6 standard deviations of the rounding, plus what clipping cut off a
row; a statistical bound), which a caller ranking them otherwise uses to read exactly what
could change its choice (core/candidates.py). Unless told, the lists probed are chosen when the
index is built, by the recall of the exact top-k it measures on a sample of the map's own rows.
Both add rows incrementally (`add`), so a service whose map grows keeps one index. `map_search`
picks one for a map by the candidates settings and keeps it with the map's arrays, built once.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from mergesvc.core.arrays import ObjectArrays, chunks, release_rows, take_rows
from mergesvc.core.config import CandidatesConfig, SearchKind
from mergesvc.core.threads import PIN_BELOW_PAIRS
from mergesvc.errors import InputError

log = logging.getLogger(__name__)

_SEARCH_KEY = "search"  # where map_search keeps a map's index in ObjectArrays.cache
_QUERY_BLOCK = 256  # queries per product: (256 x 65,536) float32 scores, 64 MB
_MIN_INDEXED = 256  # fewer map rows are searched exactly (the codes need 16 rows to train)
# the 8-bit codes' range per dimension: this times the training sample's largest |value|
_CODE_RANGE = 1.1
# how far an 8-bit code's cosine is taken to be off: this many standard deviations of the
# rounding (a sum of d independent uniform errors; beyond 6 sigma is vanishingly rare)
_SIGMAS = 6.0


class MapSearch(Protocol):
    """Top-k map rows by cosine for unit-norm queries."""

    n: int

    def search(self, q_unit: np.ndarray, k: int, ordered: bool = True
               ) -> tuple[np.ndarray, np.ndarray]:
        """(m, d) unit queries -> ((m, k) map rows, (m, k) cosines), each row best first
        (in any order when not `ordered`)."""
        ...

    def search_bounded(self, q_unit: np.ndarray, k: int, ordered: bool = True
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`search`, and (m, k) bounds on how far each cosine may be from the exact one
        (0: exact)."""
        ...

    def add(self, embeddings_nd: np.ndarray, norms_n: np.ndarray | None = None) -> None:
        """Append rows n.. n + len - 1 (the map's new objects, in order)."""
        ...


def _unit32(e: np.ndarray, norms: np.ndarray | None = None) -> np.ndarray:
    e = np.asarray(e, dtype=np.float32)
    n = np.linalg.norm(e, axis=1) if norms is None else np.asarray(norms)
    return e / np.where(n > 0, n, 1.0).astype(np.float32)[:, None]


def _held(embeddings_nd: np.ndarray, norms_n: np.ndarray | None) -> tuple[np.ndarray,
                                                                          np.ndarray]:
    """Rows as a search holds them: float32 (no copy when they are) and their norms."""
    e = np.asarray(embeddings_nd, dtype=np.float32)
    n = np.linalg.norm(e.astype(np.float64), axis=1) if norms_n is None else norms_n
    return e, np.asarray(n)


def _grown(a: np.ndarray, used: int, need: int) -> np.ndarray:
    """`a` with room for `need` rows (an eighth more at least), its first `used` kept."""
    out = np.empty((max(need, len(a) * 9 // 8), *a.shape[1:]), dtype=a.dtype)
    out[:used] = a[:used]
    return out


def _best_first(rows: np.ndarray, score: np.ndarray, k: int, ordered: bool = True
                ) -> tuple[np.ndarray, np.ndarray]:
    """Top k of each row of (m, c) scores with their column labels rows (m, c), best first
    (in any order when not `ordered`)."""
    k = min(k, score.shape[1])
    if k < score.shape[1]:
        part = np.argpartition(-score, k - 1, axis=1)[:, :k]
        rows = np.take_along_axis(rows, part, axis=1)
        score = np.take_along_axis(score, part, axis=1)
    if not ordered:
        return rows, score
    order = np.argsort(-score, axis=1, kind="stable")
    return np.take_along_axis(rows, order, axis=1), np.take_along_axis(score, order, axis=1)


def exact_cosines(rows: np.ndarray, q: np.ndarray,
                  read: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """(p,) exact cosines of map rows (p,) with their float32 queries (p, d); `read` gives
    distinct rows' (float32 embeddings, norms), each row read once."""
    uniq, inverse = np.unique(rows, return_inverse=True)
    e, norms = read(uniq)
    return (np.einsum("pd,pd->p", e[inverse], q)
            / np.where(norms > 0, norms, 1.0)[inverse])


class ExactSearch:
    """Exact top-k by cosine over chunks of the map's rows (float32 products).

    Holds references to the map's embeddings and norms (no copy); `add` appends rows.
    release: drop each chunk's mapped pages once read (a one-off pass over a mapped map; a
    search repeated on a resident map is faster without)."""

    def __init__(self, embeddings_nd: np.ndarray, norms_n: np.ndarray,
                 chunk_rows: int = 65_536, release: bool = False) -> None:
        self._parts: list[tuple[np.ndarray, np.ndarray]] = [(embeddings_nd, norms_n)]
        self.n = len(embeddings_nd)
        self.chunk_rows = chunk_rows
        self.release = release

    def add(self, embeddings_nd: np.ndarray, norms_n: np.ndarray | None = None) -> None:
        self._parts.append(_held(embeddings_nd, norms_n))
        self.n += len(self._parts[-1][0])

    def rows(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(k,) global rows -> their (k, d) float32 embeddings and (k,) norms (sorted rows
        read a mapped map in order)."""
        if len(self._parts) == 1:
            e, n = self._parts[0]
            return np.asarray(take_rows(e, rows), dtype=np.float32), n[rows]
        starts = np.cumsum([0] + [len(e) for e, _ in self._parts])
        part = np.searchsorted(starts, rows, side="right") - 1
        out_e = np.empty((len(rows), self._parts[0][0].shape[1]), dtype=np.float32)
        out_n = np.empty(len(rows))
        for p in np.unique(part):
            sel = part == p
            e, n = self._parts[p]
            out_e[sel], out_n[sel] = take_rows(e, rows[sel] - starts[p]), n[rows[sel] - starts[p]]
        return out_e, out_n

    def drop_pages(self) -> None:
        """Drop the mapped pages reading its rows made resident (`release_rows`)."""
        for e, _ in self._parts:
            release_rows(e)

    def search(self, q_unit: np.ndarray, k: int, ordered: bool = True
               ) -> tuple[np.ndarray, np.ndarray]:
        rows, cos, _ = self.search_with_products(q_unit, k, ordered, products=False)
        return rows, cos

    def search_with_products(self, q_unit: np.ndarray, k: int, ordered: bool = True,
                             products: bool = True
                             ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """`search`, and with `products` the (m, n) float32 products of the queries with every
        row before the norms divide them, when the map is one chunk and the queries one block
        (else None): a caller that needs other rows' products (the ucos floor's sample) reads
        them there instead of multiplying again."""
        q = np.asarray(q_unit, dtype=np.float32)
        if len(q) > _QUERY_BLOCK:  # bounds the (queries x chunk) products
            parts = [self.search(q[lo:lo + _QUERY_BLOCK], k, ordered)
                     for lo in chunks(len(q), _QUERY_BLOCK)]
            return np.vstack([p[0] for p in parts]), np.vstack([p[1] for p in parts]), None
        m = len(q)
        k = max(1, min(k, self.n))
        best_rows = np.zeros((m, 0), dtype=np.int64)
        best = np.zeros((m, 0), dtype=np.float32)
        offset = 0
        left = sum(len(chunks(len(e), self.chunk_rows)) for e, _ in self._parts)
        kept = None
        for e, norms in self._parts:
            inv = (1.0 / np.where(norms > 0, norms, 1.0)).astype(np.float32)
            for lo in chunks(len(e), self.chunk_rows):
                left -= 1
                hi = min(len(e), lo + self.chunk_rows)
                s = q @ e[lo:hi].T
                if products and left == 0 and offset == lo == 0:  # the only chunk
                    kept, s = s, s * inv[lo:hi]
                else:
                    s *= inv[lo:hi]
                if self.release:
                    release_rows(e, lo, hi)
                rows = np.broadcast_to(np.arange(offset + lo, offset + hi), s.shape)
                if best.shape[1] >= k:
                    # only what beats the current k-th best can enter
                    keep = s > best[:, -1:]
                    if not keep.any():
                        continue
                    width = int(keep.sum(axis=1).max())
                    if width < s.shape[1] // 4:
                        part = np.argpartition(-s, width - 1, axis=1)[:, :width]
                        s = np.take_along_axis(s, part, axis=1)
                        rows = np.take_along_axis(rows, part, axis=1)
                if best.shape[1]:
                    rows, s = np.hstack([best_rows, rows]), np.hstack([best, s])
                # the running top-k stays sorted (its k-th best gates the next chunk)
                best_rows, best = _best_first(rows, s, k, ordered or left > 0)
            offset += len(e)
        return best_rows, best, kept

    def search_bounded(self, q_unit: np.ndarray, k: int, ordered: bool = True
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        rows, cos = self.search(q_unit, k, ordered)
        return rows, cos, np.zeros(cos.shape, dtype=np.float32)  # exact


class IvfSearch:
    """Inverted-file index over unit rows (faiss IndexIVFPQFastScan: one 4-bit code per
    dimension, inner product) probed for at least `shortlist` rows per query (rerank x k when
    more), ranked by 8-bit codes (per dimension, scaled to the training sample's range) with
    the best `exact_top` re-ranked by exact float32 cosines from the map's own rows. n_lists:
    sqrt(n), at most 1024. n_probe and shortlist: given, or measured (`_calibrate`): `margin`
    times what finds `quantile` of the exact top-`calibrate_k` of `calibrate_queries` map
    rows."""

    def __init__(self, embeddings_nd: np.ndarray, norms_n: np.ndarray, *,
                 n_lists: int | None = None, n_probe: int | None = None, rerank: int = 2,
                 shortlist: int | None = None, calibrate_k: int = 12,
                 calibrate_queries: int = 512, quantile: float = 0.999, margin: float = 1.5,
                 train_per_list: int = 32, exact_top: int = 24, seed: int = 0) -> None:
        try:
            import faiss  # a large library: imported only when an index is wanted
        except ImportError as exc:  # pragma: no cover - a declared dependency
            raise InputError("the IVF candidate index needs faiss-cpu") from exc
        self._faiss = faiss
        n, d = embeddings_nd.shape
        self.n_lists = int(n_lists or min(max(16, math.isqrt(n)), 1024, max(1, n // 8)))
        self.rerank = max(1, rerank)
        self.n_probe = min(n_probe or self.n_lists, self.n_lists)
        self.shortlist = shortlist or 0
        self.exact_top = max(1, exact_top)
        self._n_built = n  # rows when the depth was set: it grows with the lists
        e, norms = _held(embeddings_nd, norms_n)
        self._exact = ExactSearch(e, norms)  # the rows, re-ranking's and the fallback's
        self.n = n
        quantizer = faiss.IndexFlatIP(d)
        # 4-bit codes scanned 32 at a time from registers: faster than 8-bit scalar codes,
        # decoded one by one, at the same recall after re-ranking (docs/benchmarks/scale.md)
        self.index = faiss.IndexIVFPQFastScan(quantizer, d, self.n_lists, d, 4,
                                              faiss.METRIC_INNER_PRODUCT)
        rng = np.random.default_rng(seed)
        n_train = min(n, train_per_list * self.n_lists)
        rows = np.sort(rng.choice(n, size=n_train, replace=False))
        sample = _unit32(take_rows(e, rows), norms[rows])
        # the re-ranking's first pass: 8-bit codes per dimension, scaled by the sample's range
        # (a unit row's values lie in [-1, 1]: no step beyond 1/127; a dimension the sample
        # leaves at 0 gets that)
        step = _CODE_RANGE * np.abs(sample).max(axis=0) / 127
        self._step = np.where(step > 0, np.minimum(step, 1 / 127), 1 / 127).astype(np.float32)
        self._codes = np.empty((n, d), dtype=np.int8)  # filled by _encode
        self._excess = np.empty(n, dtype=np.float32)  # |what clipping cut off| per row
        self._n_codes = 0
        cores = os.cpu_count() or 1
        try:
            # the lists' centres: large products, every core
            faiss.omp_set_num_threads(cores)
            clustering = faiss.Clustering(d, self.n_lists)
            clustering.niter, clustering.seed = 10, seed
            clustering.max_points_per_centroid = train_per_list
            clustering.train(sample, quantizer)
            # then the codes (the lists are trained, so skipped): a tiny k-means per dimension,
            # where more threads only wait on each other
            faiss.omp_set_num_threads(1)
            self.index.train(sample)
            self._quantizer = quantizer  # faiss keeps a pointer only: keep the object alive
            faiss.omp_set_num_threads(cores)
            self._encode(e, norms)
        finally:
            faiss.omp_set_num_threads(1)
        self.recall = float("nan")  # measured by the calibration, on the map's own rows
        if n_probe is None or shortlist is None:  # what is not told is measured
            self._calibrate(e, norms, calibrate_k, calibrate_queries, quantile, margin, rng,
                            probe=n_probe is None, depth=shortlist is None)
        self._exact.drop_pages()  # what training and calibrating read of a mapped map
        faiss.omp_set_num_threads(1)

    def _calibrate(self, e: np.ndarray, norms: np.ndarray, k: int, queries: int,
                   quantile: float, margin: float, rng: np.random.Generator, *, probe: bool,
                   depth: bool) -> None:
        """n_probe and shortlist from a sample of the map's own rows as queries, each without
        itself: `margin` times the lists nearest a query that hold `quantile` of their exact
        top-k rows, then `margin` times the re-ranking depth at which the codes' scores rank
        as many of those first (a submap's views of an object are noisier than the map's own
        rows: they reach further); and the recall of the exact top-k the two give on the
        sample (ties count either way)."""
        rows = np.sort(rng.choice(len(e), size=min(len(e), queries), replace=False))
        q = _unit32(take_rows(e, rows), norms[rows])
        exact, cos = ExactSearch(e, norms, release=True).search(q, k + 1)
        mine = exact != rows[:, None]
        items = [r[m][:k] for r, m in zip(exact, mine)]
        kth = np.array([c[m][:k][-1] for c, m in zip(cos, mine)])
        who = np.repeat(np.arange(len(q)), [len(i) for i in items])
        flat = np.concatenate(items)
        # the rank of each top-k row's list among its query's lists, nearest first
        quantizer = self.index.quantizer
        _, order = quantizer.search(q, self.n_lists)
        rank = np.empty_like(order)
        np.put_along_axis(rank, order, np.arange(self.n_lists)[None, :], axis=1)
        _, home = quantizer.search(_unit32(*self._exact.rows(flat)), 1)
        list_rank = rank[who, home[:, 0]]
        if probe:
            lists = int(np.quantile(list_rank, quantile, method="higher")) + 1
            self.n_probe = min(self.n_lists, math.ceil(margin * lists))
        if depth:  # where the codes rank the top-k rows the probe reaches
            self.index.nprobe = self.n_probe
            deepest = min(self.n, 4096)
            pos = np.full(len(flat), deepest)
            for lo in chunks(len(q), 64):  # bounds the (items x deepest) comparison
                found = self.index.search(q[lo:lo + 64], deepest)[1]
                sel = (who >= lo) & (who < lo + 64)
                hit = found[who[sel] - lo] == flat[sel, None]
                pos[sel] = np.where(hit.any(axis=1), hit.argmax(axis=1), deepest)
            pos = pos[list_rank < self.n_probe]
            need = int(np.quantile(pos, quantile, method="higher")) + 1 if len(pos) else 1
            need = math.ceil(margin * need)
            self.shortlist = int(min(deepest, max(2 * k, -(-need // 32) * 32)))
        got = self.search(q, k + 1)[0]
        got_cos = exact_cosines(  # exact: beyond exact_top the codes' are close only
            got.ravel(), np.repeat(q, got.shape[1], axis=0), self._exact.rows).reshape(got.shape)
        held = [min(k, int(np.sum(c[r != row] >= t - 1e-5)))
                for r, c, row, t in zip(got, got_cos, rows, kth)]
        self.recall = float(np.mean(held)) / k

    def add(self, embeddings_nd: np.ndarray, norms_n: np.ndarray | None = None) -> None:
        e, n = _held(embeddings_nd, norms_n)
        self._encode(e, n)
        self._exact.add(e, n)
        self.n = self._exact.n

    def _encode(self, e: np.ndarray, n: np.ndarray) -> None:
        """Rows' codes into the index and the 8-bit codes, a chunk at a time, each chunk's
        mapped pages dropped."""
        for lo in chunks(len(e), 65_536):
            unit = _unit32(e[lo:lo + 65_536], n[lo:lo + 65_536])
            end = self._n_codes + len(unit)
            if end > len(self._codes):  # `add`: grow by an eighth (amortised appends)
                self._codes = _grown(self._codes, self._n_codes, end)
                self._excess = _grown(self._excess, self._n_codes, end)
            lim = 127 * self._step
            self._codes[self._n_codes:end] = np.rint(np.clip(unit, -lim, lim) / self._step)
            self._excess[self._n_codes:end] = np.linalg.norm(
                unit - np.clip(unit, -lim, lim), axis=1)
            self._n_codes = end
            self.index.add(unit)  # after the codes: the rows it finds have them
            release_rows(e, lo, lo + 65_536)

    def _probe(self, q: np.ndarray, depth: int, k: int) -> np.ndarray:
        """(m, depth) rows the codes score best in the lists probed, best first. A query whose
        lists hold fewer than k rows (a small probe of a small map) probes twice as many lists
        until they do; one no code scores (a zero embedding) gets the exact search's rows."""
        probe = self.n_probe
        self.index.nprobe = probe
        found = self.index.search(q, depth)[1].astype(np.int64)
        short = found[:, k - 1] < 0  # faiss pads with -1 after the rows it found
        while short.any() and probe < self.n_lists:
            probe = min(2 * probe, self.n_lists)
            self.index.nprobe = probe
            found[short] = self.index.search(q[short], depth)[1]
            short = found[:, k - 1] < 0
        if short.any():
            found[short] = self._exact.search(q[short], depth)[0]
        return found

    def search(self, q_unit: np.ndarray, k: int, ordered: bool = True
               ) -> tuple[np.ndarray, np.ndarray]:
        rows, cos, _ = self.search_bounded(q_unit, k)  # always best first
        return rows, cos

    def search_bounded(self, q_unit: np.ndarray, k: int, ordered: bool = True
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        q = np.ascontiguousarray(q_unit, dtype=np.float32)  # always best first
        block = max(1, _QUERY_BLOCK // 4)
        if len(q) > block:  # bounds the re-ranking's (queries x found x d) gather
            parts = [self.search_bounded(q[lo:lo + block], k) for lo in chunks(len(q), block)]
            return tuple(np.vstack([p[i] for p in parts]) for i in range(3))  # type: ignore
        k = max(1, min(k, self.n))
        # the lists grow with `add`: the depth measured at build grows with them
        depth = min(self.n, max(self.rerank * k, -(-self.shortlist * self.n // self._n_built)))
        # a few queries: one thread (waking more costs more); a large submap's: every core
        big = len(q) * self.n >= PIN_BELOW_PAIRS
        self._faiss.omp_set_num_threads((os.cpu_count() or 1) if big else 1)
        found = self._probe(q, depth, k)
        safe = np.maximum(found, 0)
        # the 8-bit codes' cosines of what the probe found, from memory, and how far each may
        # be off: 6 sigma of the rounding (per query) plus what clipping cut off (per row)
        cos = np.matmul(self._codes[safe].astype(np.float32),
                        (q * self._step)[:, :, None])[:, :, 0]
        cos[found < 0] = -np.inf
        err = self._excess[safe] + (_SIGMAS / math.sqrt(12)) * np.linalg.norm(
            q * self._step, axis=1)[:, None]
        # the best exact_top exactly: the map's rows of every row whose cosine could be among
        # them are read (an unread row's cosine is below the lowest the best ones may have)
        top = min(self.exact_top, k, depth)
        best = np.argpartition(-cos, top - 1, axis=1)[:, :top]
        floor = np.take_along_axis(cos - err, best, axis=1).min(axis=1)
        qi, ci = np.nonzero((cos + err >= floor[:, None]) & (found >= 0))
        cos[qi, ci] = exact_cosines(found[qi, ci], q[qi], self._exact.rows)
        err[qi, ci] = 0.0
        cols, cos = _best_first(np.broadcast_to(np.arange(found.shape[1]), found.shape), cos, k)
        return (np.take_along_axis(found, cols, axis=1), cos,
                np.take_along_axis(err, cols, axis=1).astype(np.float32))


def make_search(map_: ObjectArrays, cfg: CandidatesConfig, n_queries: int = 1) -> MapSearch:
    """The search `cfg.index` asks for over this map (auto: exact below index_min_objects
    map objects, and below index_min_pairs query x map pairs; the IVF index above)."""
    kind = SearchKind(cfg.index)
    if kind is SearchKind.AUTO:
        big = map_.n >= cfg.index_min_objects or (
            map_.n * n_queries >= cfg.index_min_pairs and map_.n >= cfg.index_min_pairs_map)
        kind = SearchKind.IVF if big else SearchKind.EXACT
    if kind is SearchKind.IVF and map_.n >= max(2 * cfg.index_min_lists, _MIN_INDEXED):
        return IvfSearch(map_.embeddings_nd, map_.norms_n, n_lists=cfg.index_lists,
                         n_probe=cfg.index_probe, exact_top=2 * cfg.top_k, seed=0)
    return ExactSearch(map_.embeddings_nd, map_.norms_n)


def map_search(map_: ObjectArrays, cfg: CandidatesConfig, n_queries: int = 1) -> MapSearch:
    """The map's search structure: one already attached (`attach_search`), else made by
    `make_search` and kept with the map (an index is built once per map). An exact search is
    cheap to make and is not kept, so a later large query may still build the index."""
    held: Any = map_.cache.get(_SEARCH_KEY)
    if held is not None and held.n == map_.n:
        return held
    search = make_search(map_, cfg, n_queries)
    if isinstance(search, IvfSearch):
        map_.cache[_SEARCH_KEY] = search
    return search


def multiplied_pairs(map_: ObjectArrays, cfg: CandidatesConfig, n_queries: int) -> int:
    """Submap x map object pairs the candidate search multiplies for n_queries, the work a
    multi-threaded BLAS may pay for: all of them for an exact search, none for the index (its
    scan runs on faiss's own threads, its re-ranking on the shortlists alone)."""
    if map_.n > cfg.prefilter and isinstance(map_search(map_, cfg, n_queries), IvfSearch):
        return 0
    return map_.n * n_queries


def attach_search(map_: ObjectArrays, search: MapSearch) -> None:
    """Use `search` (rows in the map's order, search.n == map_.n) for this map's candidate
    searches: a service keeps one index per map and `add`s the objects a map gains."""
    if search.n != map_.n:
        raise InputError(f"search holds {search.n} rows, the map {map_.n}")
    map_.cache[_SEARCH_KEY] = search


__all__ = ["ExactSearch", "IvfSearch", "MapSearch", "attach_search", "exact_cosines", "make_search",
           "map_search", "multiplied_pairs"]
