"""Where a pose-graph solve starts (core/graph.py): the seeds (the anchor, the frozen nodes the
factors touch) at their poses, every other node chained from them along a spanning tree of the
factors, or where the last solution put it (warm start; docs/pose_graph.md says what it saves
and what it may change).

Guarantees: every node the factors join to a seed gets a pose; a single gross factor beside
correct parallel ones does not spoil the start. Pure: no I/O.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Mapping, Sequence

import gtsam
import numpy as np

from mergesvc.core.connectivity import UnionFind
from mergesvc.core.graph_factor import GraphFactor


def initial_poses(seeds: Mapping[str, gtsam.Pose3], live: Sequence[str],
                  facs: Sequence[GraphFactor],
                  prev: Mapping[str, gtsam.Pose3]) -> dict[str, gtsam.Pose3]:
    """The seeds at their poses and every node of `live` chained from them along a spanning
    tree of `facs`, in that order; a node in `prev` (the last solution) starts there instead,
    only new nodes are chained from their tree parent.

    Node pairs are ranked: known inliers first, then pairs with more parallel factors, then the
    smaller covariance; within a pair the medoid measurement is used."""
    by_pair: dict[tuple[str, str], list[tuple[GraphFactor, gtsam.Pose3]]] = defaultdict(list)
    for f in facs:
        a, b = sorted((f.frame_a, f.frame_b))
        T = f.T_a_b if (a, b) == (f.frame_a, f.frame_b) else f.T_a_b.inverse()
        by_pair[(a, b)].append((f, T))
    ranked = []
    for pair, items in by_pair.items():
        dist = [
            sum(np.linalg.norm(gtsam.Pose3.Logmap(T.between(U))) for _, U in items)
            for _, T in items
        ]
        k = int(np.argmin(dist))
        f, T = items[k]
        known = any(g.known_inlier for g, _ in items)
        ranked.append(((not known, -len(items), float(np.trace(f.covariance_66))), pair, T))
    ranked.sort(key=lambda r: r[0])
    adj: dict[str, list[tuple[str, gtsam.Pose3]]] = defaultdict(list)
    nodes = [*seeds, *(n for n in live if n not in seeds)]
    uf = UnionFind(len(nodes))
    index = {f: i for i, f in enumerate(nodes)}
    for i in range(1, len(seeds)):  # the seeds are placed: one tree joins them all
        uf.union(0, i)
    for _, (a, b), T in ranked:  # Kruskal: best pairs first
        if uf.union(index[a], index[b]):
            adj[a].append((b, T))
            adj[b].append((a, T.inverse()))
    poses = dict(seeds)
    todo = list(seeds)
    while todo:
        a = todo.pop()
        for b, T_a_b in adj[a]:
            if b not in poses:
                poses[b] = prev[b] if b in prev else poses[a].compose(T_a_b)
                todo.append(b)
    return {n: poses[n] for n in nodes}


__all__ = ["initial_poses"]
