"""The pose graph's calibrated noise scales kept across restarts: written to the store's meta
when a solve changes them, read back before the first solve of a restart (so a restarted
service weighs its factors as the stopped one did, docs/uncertainty.md)."""

from __future__ import annotations

import contextlib
import json
import logging
from typing import Any

import numpy as np

from mergesvc.errors import MergeError, one_line
from mergesvc.store import META_NOISE_SCALES

log = logging.getLogger(__name__)


class NoiseScaleMemory:
    """The last scales stored for `graph` in `store`."""

    def __init__(self, store: Any, graph: Any) -> None:
        self.store = store
        self.graph = graph
        self._saved: dict[str, np.ndarray] = {}

    def restore(self) -> None:
        stored = self.store.meta(META_NOISE_SCALES)
        try:
            for group, s in (json.loads(stored) if stored else {}).items():
                self.graph.set_noise_scale(group, s)
        except (ValueError, TypeError, AttributeError, MergeError) as exc:
            log.warning("stored noise scales unreadable, calibrating afresh: %s", one_line(exc))
        self._saved = self.graph.noise_scales

    def save(self) -> None:
        """The last solve's scales, when they changed."""
        now = self.graph.solved_noise_scales
        if now.keys() == self._saved.keys() and all(
                np.array_equal(now[g], self._saved[g]) for g in now):
            return
        self._saved = now
        with contextlib.suppress(MergeError):  # a read-only copy (export) keeps none
            if not self.store.closed:
                self.store.set_meta(META_NOISE_SCALES, json.dumps(
                    {g: [float(x) for x in v] for g, v in now.items()}))


__all__ = ["NoiseScaleMemory"]
