"""The merge service's memory per submap: what it keeps of every processed submap (objects,
factors, the fleet index, the pose graph) must stay small, or a fleet's soak grows without
bound (20 robots, 30 minutes, 6,400 submaps: 450-750 MB at 70 kB per submap before the state
was held compact, fleet/held.py).

Measured with tracemalloc (Python allocations: GTSAM's C++ and SQLite's are not seen) over a
window of a seeded cost-bench stream (4 vehicles of the pool fleet, session after session: each
submap brings about 2.7 new objects and 2.5 factors), the graph solved every 10 submaps as
the worker does under a backlog. Tracing starts after a warm-up and the growth is taken between
two points inside the window (what was made before and replaced inside it counts: a bound from
above). Caches are left out: the session maps (bounded: tests/test_held.py) are emptied before
each point, and the fleet index counts the rows it holds, not its buffers' capacity."""

from __future__ import annotations

import gc
import tracemalloc

from helpers import cost_stream

from mergesvc.core.model import Submap
from mergesvc.fleet.config import ServiceConfig
from mergesvc.fleet.service import MergeService

WARM, FROM, TO = 30, 40, 80  # submaps untraced, then traced; the growth FROM -> TO
BOUND = 28_000  # bytes per submap: about 22 kB; 110 kB when the state was pydantic models
BATCH = 10


def stream(n: int) -> list[Submap]:
    return cost_stream(n, seed=0, robots=4)


def held_bytes(svc: MergeService) -> int:
    """Bytes traced now, but for the caches (the session maps), and the fleet index's rows as
    the rows it holds: its buffers grow by half when full (the part not written yet is not
    memory), and one allocated before tracing started is not traced at all."""
    svc.sessions._maps.clear()
    gc.collect()
    snap = tracemalloc.take_snapshot().filter_traces(
        [tracemalloc.Filter(False, "*/mergesvc/core/retrieval.py")])
    return sum(s.size for s in snap.statistics("filename")) + svc.sessions.index_bytes()


def test_retained_memory_per_submap_is_bounded() -> None:
    subs = stream(TO)
    for s in subs:  # the arrays each input submap caches when encoded are the test's, not
        s.arrays()  # the service's: made before tracing (a suite that made them earlier did)
    svc = MergeService(ServiceConfig(store=":memory:"), session=None)
    try:
        def feed(lo: int, hi: int) -> None:
            for i in range(lo, hi):
                svc.ingest(subs[i], optimize=(i + 1) % BATCH == 0)

        feed(0, WARM)
        tracemalloc.start()
        try:
            feed(WARM, FROM)
            a = held_bytes(svc)
            feed(FROM, TO)
            b = held_bytes(svc)
        finally:
            tracemalloc.stop()
        per_submap = (b - a) / (TO - FROM)
        assert svc.stats.factors_accepted >= 100  # the stream matches: factors are held
        assert per_submap < BOUND, f"{per_submap / 1e3:.1f} kB retained per submap"
    finally:
        svc.close()
