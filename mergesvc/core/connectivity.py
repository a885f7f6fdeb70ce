"""Small algorithms on multigraphs (parallel edges count separately): union-find, bridges and
2-edge-connected components. The pose graph's outlier rules are decided on these. Pure.
"""

from __future__ import annotations

from collections.abc import Sequence


def bridges(n: int, edges: Sequence[tuple[int, int]]) -> set[int]:
    """Indices of the bridge edges of an undirected multigraph (Tarjan, iterative)."""
    adj: list[list[tuple[int, int]]] = [[] for _ in range(n)]
    for e, (u, v) in enumerate(edges):
        adj[u].append((v, e))
        adj[v].append((u, e))
    disc = [-1] * n
    low = [0] * n
    out: set[int] = set()
    t = 0
    for root in range(n):
        if disc[root] >= 0:
            continue
        disc[root] = low[root] = t
        t += 1
        stack = [(root, -1, iter(adj[root]))]
        while stack:
            u, in_edge, it = stack[-1]
            advanced = False
            for v, e in it:
                if e == in_edge:  # the tree edge back to the parent (parallel edges still count)
                    continue
                if disc[v] < 0:
                    disc[v] = low[v] = t
                    t += 1
                    stack.append((v, e, iter(adj[v])))
                    advanced = True
                    break
                low[u] = min(low[u], disc[v])
            if advanced:
                continue
            stack.pop()
            if stack:
                p = stack[-1][0]
                low[p] = min(low[p], low[u])
                if low[u] > disc[p]:
                    out.add(in_edge)
    return out


class UnionFind:
    def __init__(self, n: int) -> None:
        self.parent = list(range(n))

    def find(self, i: int) -> int:
        root = i
        while self.parent[root] != root:
            root = self.parent[root]
        while self.parent[i] != root:  # path compression
            self.parent[i], i = root, self.parent[i]
        return root

    def union(self, i: int, j: int) -> bool:
        ri, rj = self.find(i), self.find(j)
        if ri == rj:
            return False
        # The smaller index stays the root: groups are named after their first member.
        if rj < ri:
            ri, rj = rj, ri
        self.parent[rj] = ri
        return True


def two_edge_connected(n: int, edges: list[tuple[int, int]]) -> list[int]:
    """Label of each node's 2-edge-connected component (components after removing bridges)."""
    br = bridges(n, edges)
    uf = UnionFind(n)
    for e, (u, v) in enumerate(edges):
        if e not in br:
            uf.union(u, v)
    return [uf.find(i) for i in range(n)]


__all__ = ["UnionFind", "bridges", "two_edge_connected"]
