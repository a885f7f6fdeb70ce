"""Which frames a submap is worth matching against: one index over the whole fleet's objects.

`FleetIndex` holds the unit embeddings of every frame's (robot session's) objects, one float32
matrix per embedding size; `rank` scores each frame for a submap with one matrix product, so
the service matches only the best few (`ServiceConfig.max_candidate_frames`) and its matching
cost per submap is bounded whatever the fleet size. Frames of another embedding size are never
candidates (their objects come from another model).

Score of frame f for a submap with objects i: sum_i max(0, best_i(f) - typical_i), best_i(f)
the cosine of object i to its most similar object of f, typical_i the median of best_i over the
fleet's frames (a generic object that resembles everything adds nothing). Ties keep the frames'
order of arrival; a fleet of at most `keep` frames is returned whole (scores still computed).
Pure numpy; no frame is ever dropped (its row block is replaced when its objects change). A
large submap is scored a block of its objects at a time, so its scores' memory is bounded.
Memory layout and cost: docs/benchmarks/merge.md, "The fleet index".
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mergesvc.errors import InputError

_RANK_BLOCK = 256  # submap objects per product in `rank`: (256, N) float32 scores at a time


@dataclass(frozen=True)
class FrameScore:
    frame: str
    score: float


class FleetIndex:
    """Unit embeddings of every frame's objects, grouped by embedding size."""

    def __init__(self) -> None:
        self._frames: dict[str, tuple[int, int]] = {}  # frame -> (dim, rows), arrival order
        self._blocks: dict[int, _Rows] = {}  # dim -> the unit rows of its frames, stacked

    def __len__(self) -> int:
        return len(self._frames)

    def __contains__(self, frame: object) -> bool:
        return frame in self._frames

    def update(self, frame: str, embeddings: np.ndarray) -> None:
        """Set (or replace) a frame's objects: (n, d) embeddings, n >= 0, finite."""
        e = _unit_rows(embeddings, f"frame {frame}")
        dim = e.shape[1]
        old = self._frames.get(frame)
        if old is not None and old[0] != dim:  # another embedding size: another block
            self._blocks[old[0]].drop(frame)
        self._frames[frame] = (dim, len(e))  # a replaced frame keeps its place in the order
        rows = self._blocks.get(dim)
        if rows is None:
            rows = self._blocks[dim] = _Rows(dim)
        if frame not in rows.sizes:
            rows.enter(frame, [f for f, (d, _) in self._frames.items() if d == dim])
        rows.put(frame, e)

    def remove(self, frame: str) -> None:
        old = self._frames.pop(frame, None)
        if old is not None:
            self._blocks[old[0]].drop(frame)

    def _stack(self, dim: int) -> tuple[list[str], np.ndarray, np.ndarray]:
        """(frames of this size with objects, (N, dim) rows, (k,) start row of each frame)."""
        rows = self._blocks.get(dim)
        if rows is None:
            return [], np.zeros((0, dim)), np.zeros(0, dtype=np.int64)
        names = [f for f, n in rows.sizes.items() if n]
        sizes = [rows.sizes[f] for f in names]
        starts = np.cumsum([0, *sizes[:-1]]).astype(np.int64)
        return names, rows.view(), starts

    def nbytes(self) -> int:
        """Bytes of unit rows held (the buffers' used part)."""
        return sum(r.view().nbytes for r in self._blocks.values())

    def rank(self, embeddings: np.ndarray, *, exclude: str | None = None,
             keep: int | None = None) -> list[FrameScore]:
        """The frames of the submap's embedding size (but `exclude`, its own), best first;
        at most `keep` of them (None: all). (m, d) embeddings of the submap's objects."""
        if keep is not None and keep < 0:
            raise InputError(f"keep must be >= 0, got {keep}")
        q = _unit_rows(embeddings, "submap")
        names, rows, starts = self._stack(q.shape[1])
        pick = [i for i, f in enumerate(names) if f != exclude]
        if not pick or not len(q):
            return [FrameScore(names[i], 0.0) for i in pick][:keep]
        q32 = q.astype(np.float32)  # float32 as the rows are held
        best = np.empty((len(q), len(pick)), dtype=np.float32)  # (m, frames)
        for lo in range(0, len(q), _RANK_BLOCK):  # (block, N) products: bounded whatever m
            sim = q32[lo:lo + _RANK_BLOCK] @ rows.T
            best[lo:lo + _RANK_BLOCK] = np.maximum.reduceat(sim, starts, axis=1)[:, pick]
        typical = np.median(best, axis=1, keepdims=True)
        score = np.maximum(best - typical, 0.0).sum(axis=0, dtype=np.float64)
        order = np.argsort(-score, kind="stable")
        out = [FrameScore(names[pick[i]], float(score[i])) for i in order]
        return out if keep is None else out[:keep]


class _Rows:
    """The unit rows of the frames of one embedding size: one float32 buffer, each frame's
    rows a block, the blocks in the frames' order of arrival (`sizes`), no gaps."""

    def __init__(self, dim: int) -> None:
        self.dim = dim
        self.buf = np.empty((0, dim), dtype=np.float32)
        self.used = 0
        self.sizes: dict[str, int] = {}  # frame -> its rows, in the blocks' order

    def view(self) -> np.ndarray:
        return self.buf[:self.used]

    def enter(self, frame: str, order: list[str]) -> None:
        """A frame new to this size, without rows yet, placed by `order` (the index's order
        of arrival of this size's frames)."""
        if not self.sizes or order[-1] == frame:
            self.sizes[frame] = 0
            return
        known = self.sizes
        self.sizes = {f: known.get(f, 0) for f in order if f in known or f == frame}

    def put(self, frame: str, e: np.ndarray) -> None:
        """Replace a frame's block by the rows `e`; the blocks after it move."""
        start = 0
        for f, n in self.sizes.items():
            if f == frame:
                break
            start += n
        old, new = self.sizes[frame], len(e)
        if new != old:
            need = self.used + new - old
            if need > len(self.buf):
                grown = np.empty((max(need, len(self.buf) * 3 // 2, 64), self.dim),
                                 dtype=np.float32)
                grown[:self.used] = self.buf[:self.used]
                self.buf = grown
            self.buf[start + new:need] = self.buf[start + old:self.used]  # overlap-safe
            self.used = need
            self.sizes[frame] = new
        self.buf[start:start + new] = e

    def drop(self, frame: str) -> None:
        self.put(frame, np.empty((0, self.dim)))
        del self.sizes[frame]


def _unit_rows(e: np.ndarray, what: str) -> np.ndarray:
    a = np.asarray(e, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] < 1:
        raise InputError(f"{what}: embeddings must be (n, d) with d >= 1, got {a.shape}")
    if not np.isfinite(a).all():
        raise InputError(f"{what}: embeddings must be finite")
    norm = np.linalg.norm(a, axis=1, keepdims=True)
    return a / np.where(norm > 0, norm, 1.0)


__all__ = ["FleetIndex", "FrameScore"]
