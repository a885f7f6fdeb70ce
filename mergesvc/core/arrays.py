"""Objects as arrays (`ObjectArrays`), the representation every core stage computes on.

Memory layout, held once per map: embeddings in float32 (the wire's `full` precision); a
variance given as one number per object kept as one number per object (a read-only (n, d)
broadcast view, no (n, d) copy); no normalised copy of the embeddings (cosines divide by the
cached row norms). Any array may be a read-only memory map (wire/mapfile.py): nothing here
writes into the arrays it is given, and whole-map passes (validation, norms) run in chunks,
dropping the mapped pages each chunk read (`release_rows`): a pass over a mapped map does not
make the whole file this process's resident memory.
"""

from __future__ import annotations

import functools
import mmap
import os
import weakref
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from mergesvc.core.geometry import median_spacing
from mergesvc.errors import SchemaError

# |coordinate| of an object, metres (see model.py: the file models refuse beyond it too)
MAX_COORDINATE_M = 1e9
FLOAT32_MAX = float(np.finfo(np.float32).max)
# rows per step of a whole-map pass: bounds its temporaries to a few tens of MB
_CHUNK_ROWS = 16_384
# the bytes around a page read that the kernel maps with it (fault-around: 16 pages of 4 KB,
# aligned), and the rows `take_rows` reads before dropping what they mapped
_FAULT_AROUND = 65_536
_TAKE_BATCH = 512
# rows of a file closer than this are read in one call (cheaper than a call per row)
_SPAN_GAP = 32_768
_SPAN_MAX = 8 << 20


def chunks(n: int, step: int = _CHUNK_ROWS) -> range:
    """Start rows of the chunks of a whole-map pass over n rows."""
    return range(0, n, step)


def _read_only_map(a: np.ndarray) -> mmap.mmap | None:
    """The read-only mmap an array views, or None (ordinary memory, a writable mapping)."""
    base: Any = a
    while isinstance(base, np.ndarray) and base.base is not None:
        base = base.base
    if isinstance(base, mmap.mmap) and hasattr(base, "madvise") and memoryview(base).readonly:
        return base
    return None


def release_rows(a: np.ndarray, lo: int = 0, hi: int | None = None) -> None:
    """Drop the pages that lie wholly within rows lo..hi of a read-only memory-mapped array
    from this process's resident memory; they stay in the page cache and come back on the next
    read. Nothing for an array in ordinary memory, a writable mapping (a copy-on-write map
    would lose its edits) or rows that are not contiguous."""
    base = _read_only_map(a)
    hi = len(a) if hi is None else min(hi, len(a))
    if base is None or hi <= lo or not a[lo:hi].flags.c_contiguous:
        return
    rows = a[lo:hi]
    start = rows.ctypes.data - np.frombuffer(base, dtype=np.uint8).ctypes.data
    end = start + rows.nbytes
    first, last = -(-start // mmap.PAGESIZE) * mmap.PAGESIZE, end // mmap.PAGESIZE * mmap.PAGESIZE
    if last > first:
        base.madvise(mmap.MADV_DONTNEED, first, last - first)


# the files behind read-only maps (`map_file`), open while their map lives: rows are read
# from them instead of through the mapping
_MAPPED_FILES: weakref.WeakKeyDictionary[mmap.mmap, int] = weakref.WeakKeyDictionary()


def map_file(mm: mmap.mmap, fileno: int) -> None:
    """Note that `mm` maps the whole file open as `fileno` from its start, read-only: the file
    is kept open (a descriptor of its own, closed with the map) and `take_rows` reads
    scattered rows of arrays over the map from it with pread instead of through the mapping."""
    fd = os.dup(fileno)
    _MAPPED_FILES[mm] = fd
    weakref.finalize(mm, os.close, fd)


def _pread_rows(fd: int, start: int, stride: int, rows: np.ndarray, order: np.ndarray,
                out: np.ndarray) -> None:
    """out[i] = the row rows[i] of the rows at byte `start` of file `fd`, `stride` bytes apart:
    rows in file order, those closer than `_SPAN_GAP` bytes read in one call of at most
    `_SPAN_MAX` bytes."""
    srt = rows[order]
    flat = out.reshape(len(rows), -1).view(np.uint8)
    size = flat.shape[1]
    breaks = np.flatnonzero(np.diff(srt) * stride > _SPAN_GAP + size) + 1
    first_row, first_at = srt.tolist(), order.tolist()
    for lo, hi in zip(np.r_[0, breaks].tolist(), np.r_[breaks, len(srt)].tolist()):
        if hi - lo == 1:  # a row alone (most, when few rows of a large file are asked)
            if os.preadv(fd, [flat[first_at[lo]]], start + first_row[lo] * stride) != size:
                raise OSError("a memory-mapped file was truncated while in use")
            continue
        while lo < hi:
            first = first_row[lo]
            cut = hi if (first_row[hi - 1] - first) * stride + size <= _SPAN_MAX else \
                lo + int(np.searchsorted(srt[lo:hi], first + max(1, _SPAN_MAX // stride)))
            last = first_row[cut - 1]
            length = (last - first) * stride + size
            span = os.pread(fd, length, start + first * stride)
            if len(span) != length:
                raise OSError("a memory-mapped file was truncated while in use")
            block = np.ndarray((last - first + 1, size), dtype=np.uint8, buffer=span,
                               strides=(stride, 1))
            if cut - lo <= 16:  # a few rows: cheaper one by one than by an index array
                for i in range(lo, cut):
                    flat[first_at[i]] = block[first_row[i] - first]
            else:
                flat[order[lo:cut]] = block[srt[lo:cut] - first]
            lo = cut


def take_rows(a: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """a[rows] (integer rows, negative ones counted from the end, or a boolean mask), a copy
    that leaves no page of a read-only memory-mapped array resident. The kernel maps the
    `_FAULT_AROUND` bytes around any page read, so scattered reads through the mapping would
    make most of a large file resident: rows of a file noted by `map_file` are read with pread
    (a few microseconds a row); of another read-only mapping, read `_TAKE_BATCH` at a time in
    file order, each batch's pages dropped again (tens of microseconds a row)."""
    rows = np.asarray(rows)
    if rows.dtype == bool:
        rows = np.flatnonzero(rows)
    base = _read_only_map(a)
    if base is None or rows.ndim != 1 or len(rows) == 0 or not a.flags.c_contiguous:
        return a[rows]
    if rows.dtype.kind not in "iu":
        raise IndexError(f"rows must be integers or a mask, got {rows.dtype}")
    if rows.min() < -len(a) or rows.max() >= len(a):
        raise IndexError(f"rows out of range for {len(a)} rows")
    rows = np.where(rows < 0, rows + len(a), rows).astype(np.int64)
    out = np.empty((len(rows), *a.shape[1:]), dtype=a.dtype)
    origin = np.frombuffer(base, dtype=np.uint8).ctypes.data
    fd = _MAPPED_FILES.get(base)
    order = np.argsort(rows, kind="stable")
    if fd is not None:
        _pread_rows(fd, a.ctypes.data - origin, a.strides[0], rows, order, out)
        return out
    for lo in range(0, len(rows), _TAKE_BATCH):
        sel = order[lo:lo + _TAKE_BATCH]
        out[sel] = a[rows[sel]]
        # the windows (aligned in the address space) each row lies in, merged into runs (rows
        # in order: both ends ascend), dropped within the mapping
        at = a.ctypes.data + rows[sel] * a.strides[0]
        first, last = at // _FAULT_AROUND, (at + out[0].nbytes - 1) // _FAULT_AROUND
        new_run = np.flatnonzero(first[1:] > last[:-1] + 1) + 1
        for a_w, b_w in zip(first[np.r_[0, new_run]].tolist(),
                            last[np.r_[new_run - 1, len(sel) - 1]].tolist()):
            lo_b = max(a_w * _FAULT_AROUND - origin, 0)
            lo_b -= lo_b % mmap.PAGESIZE
            hi_b = min((b_w + 1) * _FAULT_AROUND - origin, len(base))
            if hi_b > lo_b:
                base.madvise(mmap.MADV_DONTNEED, lo_b, hi_b - lo_b)
    return out


class _BadRowError(SchemaError):
    """One object's `what` (its row) refused (`problem`: it has NaN or inf, ...);
    ObjectArrays names the object."""

    def __init__(self, what: str, row: int, problem: str = "has NaN or inf") -> None:
        super().__init__(f"object {row}: its {what} {problem}")
        self.what, self.row, self.problem = what, row, problem


def _check_finite(a: np.ndarray, what: str) -> None:
    """_BadRowError for the first row of `a` holding a NaN or inf."""
    for lo in chunks(len(a)):
        block = np.isfinite(a[lo:lo + _CHUNK_ROWS])
        if not block.all():
            bad = block.reshape(len(block), -1).all(axis=1)
            raise _BadRowError(what, lo + int(np.argmin(bad)))
        release_rows(a, lo, lo + _CHUNK_ROWS)


def _as_float32(e: Any) -> np.ndarray:
    """(n, d) embeddings as float32 (no copy when they already are); SchemaError when a value
    is not finite or lies beyond float32's range."""
    a = e if isinstance(e, np.ndarray) else np.asarray(e)
    if a.dtype == np.float32:
        _check_finite(a, "embedding")
        return a
    a = np.asarray(a, dtype=np.float64)
    _check_finite(a, "embedding")
    if a.size and float(np.abs(a).max()) > FLOAT32_MAX:
        raise SchemaError(f"embedding values beyond +-{FLOAT32_MAX:.3g} (float32) are not "
                          "supported")
    return a.astype(np.float32)


def _compact_variances(v: Any, n: int, d: int) -> np.ndarray:
    """(n, d) variances as given ((n,), (n, 1) or (n, d)); a read-only broadcast of one column
    when each object has one number (isotropic), else the (n, d) array itself."""
    a = np.asarray(v, dtype=np.float64)
    if a.ndim == 1 and a.shape == (n,):
        a = a[:, None]
    if a.ndim != 2 or a.shape[0] != n or a.shape[1] not in (1, d):
        raise SchemaError(f"variances_nd must be ({n}, {d}), ({n}, 1) or ({n},), got {a.shape}")
    if a.shape[1] == d and d > 1:
        if a.strides[1] == 0:
            a = a[:, :1]
        elif all(bool((a[lo:lo + _CHUNK_ROWS] == a[lo:lo + _CHUNK_ROWS, :1]).all())
                 for lo in chunks(n)):
            a = np.ascontiguousarray(a[:, :1])
    _check_finite(a, "variance")
    if n and not float(a.min()) > 0:
        k = int(np.flatnonzero(~(a.min(axis=1) > 0))[0])
        raise _BadRowError("variance", k, f"must be positive, not {float(a[k].min()):g}")
    return np.broadcast_to(a, (n, d)) if a.shape[1] == 1 else a


@dataclass(frozen=True)
class ObjectArrays:
    """Objects as arrays, the representation the core stages compute on.

    ids: n object ids; position_xyz_m: (n, 3) float64; embeddings_nd: (n, d) float32 (given
    any float, stored as float32); variances_nd: (n, d) per-dimension variance (given (n, d),
    (n, 1) or (n,): one number per object is kept as one, seen through a read-only (n, d)
    view); n_obs: (n,); up_xyz: (3,) unit vector opposite to gravity when the frame declares
    it, else None (see `mergesvc.core.vertical`).
    """

    ids: Sequence[str]
    position_xyz_m: np.ndarray
    embeddings_nd: np.ndarray
    variances_nd: np.ndarray
    n_obs: np.ndarray
    up_xyz: np.ndarray | None = None
    # what the stages derive from a map once and keep with it (core/search.py: its index)
    cache: dict[Any, Any] = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        n = len(self.ids)
        if n == 0:
            raise SchemaError("no objects")
        pos = np.asarray(self.position_xyz_m, dtype=np.float64)
        if pos.shape != (n, 3):
            raise SchemaError(f"position_xyz_m must be ({n}, 3), got {pos.shape}")
        emb = self.embeddings_nd
        if getattr(emb, "ndim", np.ndim(emb)) != 2 or len(emb) != n:
            raise SchemaError(f"embeddings_nd must be ({n}, d), got {np.shape(emb)}")
        try:
            emb = _as_float32(emb)
            var = _compact_variances(self.variances_nd, n, emb.shape[1])
            _check_finite(pos, "position")
        except _BadRowError as exc:
            raise SchemaError(f"object {exc.row} (id {self.ids[exc.row]!r}): its {exc.what} "
                              f"{exc.problem}") from exc
        if np.any(np.abs(pos) > MAX_COORDINATE_M):
            raise SchemaError(f"position_xyz_m beyond +-{MAX_COORDINATE_M:g} m")
        for name, value in (("position_xyz_m", pos), ("embeddings_nd", emb),
                            ("variances_nd", var), ("n_obs", np.asarray(self.n_obs))):
            object.__setattr__(self, name, value)
        if self.up_xyz is not None:
            up = np.asarray(self.up_xyz, dtype=np.float64)
            peak = float(np.abs(up).max()) if up.shape == (3,) else 0.0
            if not (np.isfinite(peak) and peak > 0.0):
                raise SchemaError("up_xyz must be a finite non-zero 3-vector")
            up = up / peak  # scaled first: no overflow for huge components
            object.__setattr__(self, "up_xyz", up / np.linalg.norm(up))

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        """Pickled as its arrays alone (memory maps read into memory, one variance column
        when isotropic); what the stages derived (`cache`, norms, KD-tree) is made again."""
        return ObjectArrays, (list(self.ids), np.asarray(self.position_xyz_m),
                              np.asarray(self.embeddings_nd), np.asarray(self.variance_column),
                              np.asarray(self.n_obs), self.up_xyz)

    @property
    def n(self) -> int:
        return len(self.ids)

    @property
    def dim(self) -> int:
        return self.embeddings_nd.shape[1]

    @property
    def isotropic(self) -> bool:
        """Whether every object's variance is one number (held as one column)."""
        return self.variances_nd.strides[1] == 0 or self.dim == 1

    @property
    def variance_column(self) -> np.ndarray:
        """(n, 1) per-object variance when isotropic, else the (n, d) variances."""
        return self.variances_nd[:, :1] if self.isotropic else self.variances_nd

    @functools.cached_property
    def norms_n(self) -> np.ndarray:
        """(n,) float64 embedding norms; computed once per map, in chunks."""
        e = self.embeddings_nd
        out = np.empty(self.n)
        for lo in chunks(self.n):
            blk = e[lo:lo + _CHUNK_ROWS].astype(np.float64)
            out[lo:lo + len(blk)] = np.sqrt(np.einsum("ij,ij->i", blk, blk))
            release_rows(e, lo, lo + _CHUNK_ROWS)
        return out

    @functools.cached_property
    def uncertainty_s(self) -> np.ndarray:
        """(n,) scalar uncertainty s: mean of the per-dimension variances (see ObjectNode);
        computed once per map."""
        if self.isotropic:
            return np.ascontiguousarray(self.variances_nd[:, 0])
        return self.variances_nd.mean(axis=1)

    def unit_rows(self, index: np.ndarray | None = None) -> np.ndarray:
        """(k, d) float64 unit-norm embeddings of the indexed objects (all when None); a new
        array each call (no normalised copy of the map is kept)."""
        e = self.embeddings_nd if index is None else take_rows(self.embeddings_nd, index)
        norms = self.norms_n if index is None else self.norms_n[index]
        return e.astype(np.float64) / np.where(norms > 0, norms, 1.0)[:, None]

    @property
    def unit_embeddings_nd(self) -> np.ndarray:
        """(n, d) embeddings scaled to unit norm (`unit_rows()`; computed on each call)."""
        return self.unit_rows()

    @functools.cached_property
    def kdtree(self) -> cKDTree:
        """KD-tree over the object centres; built once per map."""
        return cKDTree(self.position_xyz_m)

    @functools.cached_property
    def median_spacing_m(self) -> float:
        """Median nearest-neighbour distance between object centres; 1.0 if undefined."""
        return median_spacing(self.position_xyz_m, self.kdtree)

    @classmethod
    def from_objects(
        cls, objects: Sequence[Any], up: tuple[float, float, float] | None = None
    ) -> ObjectArrays:
        """From the file models' objects (model.ObjectNode: id, position, embedding, variance,
        n_obs)."""
        d = len(objects[0].embedding)
        if all(not isinstance(o.variance, list) for o in objects):
            var = np.array([o.variance for o in objects], dtype=np.float64)
        else:
            var = np.empty((len(objects), d))
            for k, o in enumerate(objects):
                var[k] = o.variance  # a scalar broadcasts: isotropic
        return cls(
            ids=[o.id for o in objects],
            position_xyz_m=np.array([o.position for o in objects], dtype=np.float64),
            embeddings_nd=_as_float32(np.array([o.embedding for o in objects],
                                               dtype=np.float64)),
            variances_nd=var,
            n_obs=np.array([o.n_obs for o in objects], dtype=np.int64),
            up_xyz=None if up is None else np.asarray(up, dtype=np.float64),
        )

    def subset(self, index: np.ndarray) -> ObjectArrays:
        index = np.asarray(index, dtype=np.int64)
        return ObjectArrays(
            ids=[self.ids[k] for k in index],
            position_xyz_m=self.position_xyz_m[index],
            embeddings_nd=self.embeddings_nd[index],
            variances_nd=self.variance_column[index],
            n_obs=self.n_obs[index],
            up_xyz=self.up_xyz,
        )


__all__ = ["FLOAT32_MAX", "MAX_COORDINATE_M", "ObjectArrays", "chunks", "map_file",
           "release_rows", "take_rows"]
