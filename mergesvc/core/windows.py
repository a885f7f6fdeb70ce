"""Large submaps in windows: spatial tiles matched one by one, then one transform for all.

A submap of thousands of objects cannot be one QAP (K grows with the square of its candidate
pairs, the exact search with the square of its rows). `partition` cuts it into spatial windows
of at most `size` objects (recursive median splits along the widest axis: compact tiles, each
like an ordinary submap); the pipeline matches and verifies each window on its own, and
`consensus` picks the transform most windows' matches agree with and keeps the matches that fit
it, one map object per submap object. Cost and memory grow linearly with the submap.
"""

from __future__ import annotations

import numpy as np

from mergesvc.core.verify import align, transform_points


def partition(position_xyz_m: np.ndarray, size: int) -> list[np.ndarray]:
    """Windows of at most `size` (>= 2) objects covering all n rows once, each sorted.
    position_xyz_m: (n, 3). Deterministic."""
    n = len(position_xyz_m)
    out: list[np.ndarray] = []
    stack = [np.arange(n)]
    while stack:
        idx = stack.pop()
        if len(idx) <= size:
            out.append(np.sort(idx))
            continue
        xyz = position_xyz_m[idx]
        axis = int(np.argmax(np.ptp(xyz, axis=0)))
        order = idx[np.argsort(xyz[:, axis], kind="stable")]
        half = len(order) // 2
        stack += [order[half:], order[:half]]
    return out


def consensus(
    sub_xyz: np.ndarray,
    map_xyz: np.ndarray,
    gate_m: np.ndarray,
    hypotheses: list,
    rounds: int = 3,
) -> tuple[object | None, np.ndarray]:
    """The transform most pairs fit, and which pairs fit it.

    sub_xyz, map_xyz: (k, 3) proposed pairs (every window's); gate_m: (k,) residual gate;
    hypotheses: candidate T_map_submap (gtsam.Pose3, the accepted windows' fits). The
    hypothesis with the most pairs within their gate wins; it is refitted on those pairs
    (least squares), and the pairs within the gate of the refit kept, `rounds` times.
    Returns (T or None, (k,) bool inliers)."""
    k = len(sub_xyz)
    best_T, best = None, np.zeros(k, dtype=bool)
    for T in hypotheses:
        inl = np.linalg.norm(transform_points(T, sub_xyz) - map_xyz, axis=1) <= gate_m
        if inl.sum() > best.sum():
            best_T, best = T, inl
    for _ in range(rounds):
        if best.sum() < 3:
            break
        T = align(sub_xyz[best], map_xyz[best])
        if T is None:
            break
        inl = np.linalg.norm(transform_points(T, sub_xyz) - map_xyz, axis=1) <= gate_m
        if inl.sum() < 3:
            break
        best_T, same = T, np.array_equal(inl, best)
        best = inl
        if same:
            break
    return best_T, best


def one_to_one(rows: np.ndarray, map_nodes: np.ndarray, residual: np.ndarray) -> np.ndarray:
    """(k,) bool: of pairs claiming the same map node (or the same row), the one with the
    smallest residual is kept."""
    keep = np.ones(len(rows), dtype=bool)
    order = np.argsort(residual, kind="stable")
    seen_map: set[int] = set()
    seen_row: set[int] = set()
    for p in order.tolist():
        r, b = int(rows[p]), int(map_nodes[p])
        if r in seen_row or b in seen_map:
            keep[p] = False
            continue
        seen_row.add(r)
        seen_map.add(b)
    return keep


__all__ = ["consensus", "one_to_one", "partition"]
