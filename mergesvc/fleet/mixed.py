"""Matching across wire profiles: where either side of a match holds compact-coded objects,
both sides' embeddings are compared as that compact code gives them.

A compact embedding is its quantised PCA coefficients decoded (docs/wire.md §5): alike objects
quantise alike, so compact-to-compact similarities run higher than full-to-compact ones of the
same object. A map whose objects came in several profiles (a map sent in parts, a fleet of
mixed profiles) would favour look-alikes of the query's own profile over the true objects of
the other (docs/wire.md §5.4). `ProfileViews` remembers which sessions hold compact-coded
objects (and the code: projection, budget, step) and gives the matcher both sides in that
code; a pair with no compact side is matched as it is. Idempotent on compact embeddings, so
all-compact fleets match as before.
"""

from __future__ import annotations

import dataclasses
import threading
from collections import OrderedDict
from collections.abc import Mapping

from mergesvc.core.model import ObjectArrays, Submap
from mergesvc.wire.envelope import peek_compact_code
from mergesvc.wire.projection import CompactCode, Projection, compact_view

VIEWS_CACHED = 8  # compact views of session maps kept (a submap tries at most a few sessions)


class ProfileViews:
    """Which sessions hold compact-coded objects, and the compact views of a match's sides."""

    def __init__(self, projections: Mapping[str, Projection]) -> None:
        self._projections = projections
        self._frames: dict[str, CompactCode] = {}  # session -> the code of its compact objects
        self._cache: OrderedDict[tuple[str, CompactCode], tuple[ObjectArrays, ObjectArrays]] = (
            OrderedDict())
        self._lock = threading.Lock()

    def note(self, frame: str, payload: bytes) -> CompactCode | None:
        """A stored submap of session `frame`: its compact code (None: not compact), which
        marks the session as holding compact objects from now on."""
        code = peek_compact_code(payload)
        if code is not None and code.projection_id in self._projections:
            with self._lock:
                self._frames.setdefault(frame, code)
            return code
        return None

    def frame_code(self, frame: str) -> CompactCode | None:
        with self._lock:
            return self._frames.get(frame)

    def pair(
        self, frame: str, map_arrays: ObjectArrays, sub: Submap, code: CompactCode | None
    ) -> tuple[ObjectArrays, ObjectArrays | Submap]:
        """(map, submap) to match: session `frame`'s objects and a submap coded with `code`
        (None: not compact), both in the compact code of either side when one has one (the
        submap's first), else as they are."""
        use = code or self.frame_code(frame)
        proj = None if use is None else self._projections.get(use.projection_id)
        if use is None or proj is None or proj.dim != map_arrays.dim:
            return map_arrays, sub
        with self._lock:
            hit = self._cache.get((frame, use))
            if hit is not None and hit[0] is map_arrays:
                self._cache.move_to_end((frame, use))
                view = hit[1]
            else:
                view = _view(map_arrays, proj, use)
                self._cache[(frame, use)] = (map_arrays, view)
                while len(self._cache) > VIEWS_CACHED:
                    self._cache.popitem(last=False)
        return view, _view(sub.arrays(), proj, use)


def _view(arrays: ObjectArrays, proj: Projection, code: CompactCode) -> ObjectArrays:
    return dataclasses.replace(arrays, embeddings_nd=compact_view(arrays.embeddings_nd, proj, code))


__all__ = ["VIEWS_CACHED", "ProfileViews"]
