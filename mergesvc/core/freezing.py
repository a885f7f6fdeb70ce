"""Freezing, rule 6 of the pose graph (docs/pose_graph.md): a node placed beyond doubt freezes at
its solved pose once `max_live_nodes` nodes joined the anchor's component after it; later solves
hold it fixed and leave out the settled factors between two frozen nodes (sealed), so a long
mission's solve stays the size of its live part.

Guarantees: a frozen node never moves again, and nodes freeze only in one anchor's frame; no
node freezes on a single closure, on an arbitrary pick between closures that disagree, or in a
chain a doubtful closure still pulls. Pure: no I/O.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Sequence

import gtsam

from mergesvc.core.graph_factor import GraphFactor
from mergesvc.errors import InputError

log = logging.getLogger(__name__)


class Freezing:
    """The frozen nodes of one pose graph, its sealed factors and when its live nodes joined
    the anchor's component."""

    def __init__(self) -> None:
        # frozen node -> its pose in the anchor frame (the anchor it was solved with)
        self.frozen: dict[str, gtsam.Pose3] = {}
        self.anchor: str | None = None
        # a settled factor between two frozen nodes -> its weight in the last solve that held it
        self.sealed: dict[str, float] = {}
        # live node -> how many nodes had joined the anchor's component once it had
        self._joined: dict[str, int] = {}

    def check_anchor(self, frame: str) -> None:
        """InputError unless `frame` may be the anchor: the frozen nodes' anchor, if any."""
        if self.frozen and frame != self.anchor:
            raise InputError(f"{len(self.frozen)} nodes are frozen in the frame of "
                             f"{self.anchor!r}: the anchor cannot be {frame!r}")

    def settle_limits(self, anchor_index: int, nodes: int, step: int) -> range:
        """The prefixes (how many of the first nodes added) a restart solves in turn before the
        whole graph, `step` more each time: the first holds the anchor and `step` nodes more
        than are frozen already."""
        return range(max(len(self.frozen) + step, anchor_index + 1), nodes, step)

    def update(self, anchor: str, live: Sequence[str], poses: dict[str, gtsam.Pose3],
               facs: Iterable[GraphFactor], held: dict[str, tuple[float, str, float]],
               chain: Callable[[str], int], block: Callable[[str], int], pulled: Iterable[str],
               cap: int) -> list[GraphFactor]:
        """After a solve of `live` (the live nodes of the anchor's component; `poses`: the
        solution, `facs`: the factors solved, `held`: factor -> (weight, verdict, error)):
        the nodes placed beyond doubt freeze if `cap` nodes joined after them. `chain`: a
        node's odometry chain (the known inliers contracted), `block`: its 2-edge-connected
        block over the closures GNC kept, chains contracted (rule 3); placed: in the anchor's
        block, and not in the chain of a node in `pulled` (the ends of the ambiguous
        closures). Returns the factors sealed now: known inliers and closures GNC
        kept between two frozen nodes (ambiguous, outlying and unchecked ones are judged again)."""
        anchor_block = block(anchor)
        doubtful = {chain(n) for n in pulled}
        placed = [n for n in live if block(n) == anchor_block and chain(n) not in doubtful]
        new = [n for n in live if n not in self._joined]
        # nodes ever joined: live ones (in _joined) and frozen ones (they left _joined)
        total = len(self._joined) + len(self.frozen) + len(new)
        for n in new:
            self._joined[n] = total  # (those that join in one solve: alike)
        frozen = [n for n in placed if total - self._joined[n] >= cap]
        for n in frozen:
            self.frozen[n] = poses[n]
            del self._joined[n]  # (only live nodes need it)
        if frozen:
            self.anchor = anchor
            log.debug("pose graph: %d nodes frozen, %d live", len(self.frozen),
                      len(live) - len(frozen))
        sealed = []
        for f in facs:  # (also one added between two frozen nodes: solved, then sealed)
            if (f.frame_a in self.frozen and f.frame_b in self.frozen
                    and (f.known_inlier or held[f.factor_id][1] == "")):
                self.sealed[f.factor_id] = held[f.factor_id][0]
                sealed.append(f)
        return sealed


__all__ = ["Freezing"]
