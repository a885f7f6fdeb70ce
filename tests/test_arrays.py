"""ObjectArrays' memory layout: float32 embeddings held once, one variance per object kept as
one number, derived arrays cached, nothing written into memory-mapped inputs."""

from __future__ import annotations

import numpy as np
import pytest

from mergesvc.core.arrays import ObjectArrays
from mergesvc.errors import SchemaError


def _arrays(n: int = 50, d: int = 16, iso: bool = True, seed: int = 0) -> ObjectArrays:
    rng = np.random.default_rng(seed)
    var = rng.uniform(0.1, 1.0, n) if iso else rng.uniform(0.1, 1.0, (n, d))
    return ObjectArrays([f"o{i}" for i in range(n)], rng.normal(size=(n, 3)),
                        rng.normal(size=(n, d)), var, np.ones(n, dtype=np.int64))


def test_embeddings_are_float32_and_not_copied_when_they_are() -> None:
    a = _arrays()
    assert a.embeddings_nd.dtype == np.float32
    e = np.ascontiguousarray(a.embeddings_nd)
    b = ObjectArrays(a.ids, a.position_xyz_m, e, a.variances_nd, a.n_obs)
    assert b.embeddings_nd is e  # float32 given: held as given, no copy


@pytest.mark.parametrize("shape", ["n", "n1", "nd"])
def test_scalar_variance_stays_one_number_per_object(shape: str) -> None:
    n, d = 40, 32
    v = np.linspace(0.1, 0.5, n)
    given = {"n": v, "n1": v[:, None], "nd": np.repeat(v[:, None], d, axis=1)}[shape]
    a = ObjectArrays([f"o{i}" for i in range(n)], np.zeros((n, 3)), np.ones((n, d)), given,
                     np.ones(n, dtype=np.int64))
    assert a.isotropic and a.variances_nd.shape == (n, d)
    assert a.variances_nd.strides[1] == 0  # a view of one column: n numbers held, not n x d
    assert a.variances_nd.base is not None and a.variances_nd.base.size == n
    np.testing.assert_array_equal(a.uncertainty_s, v)
    np.testing.assert_array_equal(a.variances_nd[3], np.full(d, v[3]))
    sub = a.subset(np.array([5, 1]))
    assert sub.isotropic and sub.variances_nd.strides[1] == 0
    np.testing.assert_array_equal(sub.uncertainty_s, v[[5, 1]])
    with pytest.raises(ValueError):
        a.variances_nd[0, 0] = 1.0  # read-only: nothing writes through the shared column


def test_per_dimension_variances_are_kept_and_averaged() -> None:
    a = _arrays(iso=False)
    assert not a.isotropic and a.variances_nd.strides[1] != 0
    np.testing.assert_allclose(a.uncertainty_s, a.variances_nd.mean(axis=1))


def test_norms_and_unit_rows_match_a_reference_and_no_copy_is_kept() -> None:
    a = _arrays(n=30, d=12)
    e = a.embeddings_nd.astype(np.float64)
    np.testing.assert_allclose(a.norms_n, np.linalg.norm(e, axis=1), rtol=1e-12)
    np.testing.assert_allclose(a.unit_rows(np.array([2, 7])),
                               e[[2, 7]] / np.linalg.norm(e[[2, 7]], axis=1, keepdims=True),
                               rtol=1e-12)
    a.unit_rows()
    assert "norms_n" in vars(a) and not any(
        isinstance(v, np.ndarray) and v.shape == a.embeddings_nd.shape for v in vars(a).values()
        if v is not a.embeddings_nd and v is not a.variances_nd)


def test_values_beyond_float32_are_refused_in_one_line() -> None:
    a = _arrays(n=3, d=4)
    big = np.ones((3, 4))
    big[1, 2] = 1e300
    with pytest.raises(SchemaError, match="float32"):
        ObjectArrays(a.ids, a.position_xyz_m, big, a.variances_nd, a.n_obs)
    with pytest.raises(SchemaError, match="positive"):
        ObjectArrays(a.ids, a.position_xyz_m, a.embeddings_nd, np.zeros(3), a.n_obs)


def test_read_only_inputs_are_accepted_unchanged() -> None:
    a = _arrays(n=20, d=8)
    e = np.array(a.embeddings_nd)
    e.setflags(write=False)
    b = ObjectArrays(a.ids, a.position_xyz_m, e, a.variances_nd, a.n_obs)
    assert b.embeddings_nd is e
    assert np.isfinite(b.norms_n).all() and b.uncertainty_s.shape == (20,)


def _rss_file_mb() -> float:
    """Mapped file pages resident in this process, MB (Linux; a tmpfs file's count as shared
    memory)."""
    with open("/proc/self/status") as f:
        kb = [int(line.split()[1]) for line in f if line.startswith(("RssFile:", "RssShmem:"))]
    if not kb:
        pytest.skip("no RssFile in /proc/self/status")
    return sum(kb) / 1024.0


def test_a_pass_over_a_mapped_map_does_not_keep_the_file_resident(tmp_path) -> None:
    """release_rows drops the pages of the rows given (whole pages only); validation, norms
    and building an index over a mapped map leave little of the file resident."""
    from mergesvc.core.arrays import release_rows
    from mergesvc.core.search import IvfSearch

    n, d = 40_000, 384  # 61 MB of float32
    rng = np.random.default_rng(0)
    IvfSearch(rng.normal(size=(200, 4)).astype(np.float32), np.ones(200))  # faiss mapped
    path = tmp_path / "e.f32"
    rng.normal(size=(n, d)).astype(np.float32).tofile(path)
    e = np.memmap(path, dtype=np.float32, mode="r", shape=(n, d))
    base = _rss_file_mb()
    assert float(e.sum(dtype=np.float64)) != 0 and _rss_file_mb() - base > 50  # all read
    release_rows(e, 0, n // 2)
    assert 20 < _rss_file_mb() - base < 40  # the first half dropped
    release_rows(e)
    assert _rss_file_mb() - base < 2
    release_rows(np.ones((10, 3)))  # ordinary memory: nothing to do
    cow = np.memmap(path, dtype=np.float32, mode="c", shape=(n, d))
    cow[:] = 1.0  # a copy-on-write map's edits live only in this process's pages
    release_rows(cow)
    assert float(cow[-1, -1]) == 1.0  # kept: a writable mapping is never released
    del cow
    # the checks and the norms of a mapped map, then an index built over it
    a = ObjectArrays([f"o{i}" for i in range(n)], rng.normal(size=(n, 3)), e, np.ones(n),
                     np.ones(n, dtype=np.int64))
    norms = a.norms_n
    index = IvfSearch(a.embeddings_nd, norms)
    assert index.n == n and _rss_file_mb() - base < 10, _rss_file_mb() - base


def _resident_mb(path) -> float:
    """This process's resident pages of the file at `path`, MB (Linux /proc/self/smaps)."""
    kb, inside = 0, False
    with open("/proc/self/smaps") as f:
        for line in f:
            head = line.split()
            if len(head) > 5 and "-" in head[0] and ":" in head[3]:  # a mapping's first line
                inside = line.rstrip("\n").endswith(str(path))
            elif inside and line.startswith("Rss:"):
                kb += int(head[1])
    return kb / 1024.0


@pytest.mark.parametrize("noted", [True, False], ids=["pread", "mapped-then-dropped"])
def test_scattered_rows_of_a_mapped_map_are_copied_without_making_it_resident(
        tmp_path, noted: bool) -> None:
    """take_rows returns a[rows] (any order, repeats) and leaves none of the file resident:
    a file noted by map_file is read with pread, another read-only mapping drops what each
    batch mapped; indexing the mapping directly keeps the 64 KB around every row read."""
    import mmap

    from mergesvc.core.arrays import map_file, take_rows

    n, d = 40_000, 384  # 61 MB of float32, 1.5 KB a row
    rng = np.random.default_rng(1)
    ref = rng.normal(size=(n, d)).astype(np.float32)
    path = tmp_path / "e.f32"
    with open(path, "wb") as f:
        f.write(b"\0" * 128)  # rows start past a header, as in a map file
        ref.tofile(f)
    with open(path, "rb") as f:
        mm = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        if noted:
            map_file(mm, f.fileno())
    e = np.ndarray((n, d), dtype=np.float32, buffer=mm, offset=128)
    rows = rng.choice(n, 6_000, replace=True)  # repeats, unsorted: > one batch
    base = _resident_mb(path)  # (what mapping it made resident, if anything)
    got = take_rows(e, rows)
    assert _resident_mb(path) - base < 1, _resident_mb(path) - base
    np.testing.assert_array_equal(got, ref[rows])
    for far_or_dense in (np.arange(n - 1, 0, -97), np.arange(n)[::-1]):  # a call a row; spans
        np.testing.assert_array_equal(take_rows(e, far_or_dense), ref[far_or_dense])
    assert _resident_mb(path) - base < 1, _resident_mb(path) - base
    np.testing.assert_array_equal(take_rows(e, -1 - rows[:3]), ref[-1 - rows[:3]])  # as numpy
    mask = np.zeros(n, dtype=bool)
    mask[rows[:4]] = True
    np.testing.assert_array_equal(take_rows(e, mask), ref[mask])
    for bad in (np.array([n]), np.array([-n - 1]), np.array([0.5])):
        with pytest.raises(IndexError):
            take_rows(e, bad)
    np.testing.assert_array_equal(take_rows(e[:, :7], rows[:5]), ref[rows[:5], :7])  # a view
    assert float(e[rows].sum()) != 0 and _resident_mb(path) - base > 30  # what indexing maps
    del e
    mm.close()
