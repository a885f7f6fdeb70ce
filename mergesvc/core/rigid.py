"""Rigid before bent: a robot's trajectory keeps the shape of its own odometry unless its
inter-robot factors show that the odometry is wrong.

A chain is the nodes one robot's odometry factors join. Its rigid placement is the one pose that
puts the chain's odometry shape (composed along the chain) best against the factors from the
chain to nodes outside it, those held where the solve put them. The chain is kept rigid unless
bending it as the solve did lowers those factors' summed squared whitened residuals, and those
of its loops (factors, not known inliers, between two of its own nodes: the shape fixes their
residual), by more than the chi-square quantile of DRIFT_DOF degrees of freedom: a
likelihood-ratio test of "the odometry's shape is right" against "it drifted at a constant
rate". Pure.
"""

from __future__ import annotations

from collections import defaultdict, deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import gtsam
import numpy as np

from mergesvc.core.chi2 import chi2_quantile
from mergesvc.core.connectivity import UnionFind
from mergesvc.core.graph_factor import GraphFactor, levenberg_marquardt

# The freedom the test charges a bent chain with: a drift at a constant rate along it (a
# twist). The solve bends freely, which fits at least as well: the test errs toward bending.
DRIFT_DOF = 6

Measured = Callable[[GraphFactor], tuple[gtsam.Pose3, np.ndarray]]
IsChain = Callable[[str | None], bool]


@dataclass(frozen=True)
class RigidTest:
    """One chain's test: its factors to outside nodes and its loops (`factors`), their
    summed squared whitened residuals with the chain placed rigidly (`rigid_cost`) and as
    solved (`bent_cost`), the degrees of freedom charged (`dof`) and the verdict (`rigid`)."""

    nodes: int
    factors: int
    rigid_cost: float
    bent_cost: float
    dof: int
    rigid: bool


def chains(facs: Sequence[GraphFactor], is_chain: IsChain) -> list[list[str]]:
    """The nodes the chain factors (`is_chain(group)`) join, one list per chain of 2+ nodes."""
    nodes = sorted({n for f in facs if is_chain(f.group) for n in (f.frame_a, f.frame_b)})
    index = {n: i for i, n in enumerate(nodes)}
    uf = UnionFind(len(nodes))
    for f in facs:
        if is_chain(f.group):
            uf.union(index[f.frame_a], index[f.frame_b])
    out: dict[int, list[str]] = defaultdict(list)
    for n in nodes:
        out[uf.find(index[n])].append(n)
    return [c for c in out.values() if len(c) > 1]


def chain_shape(chain: Sequence[str], facs: Sequence[GraphFactor], measured: Measured,
                is_chain: IsChain) -> dict[str, gtsam.Pose3]:
    """Each chain node's pose relative to the chain's first node, composed along a spanning
    tree (breadth first) of its chain factors."""
    members = set(chain)
    adj: dict[str, list[tuple[str, gtsam.Pose3]]] = defaultdict(list)
    for f in facs:
        if is_chain(f.group) and f.frame_a in members and f.frame_b in members:
            T = measured(f)[0]
            adj[f.frame_a].append((f.frame_b, T))
            adj[f.frame_b].append((f.frame_a, T.inverse()))
    shape = {chain[0]: gtsam.Pose3()}
    todo = deque([chain[0]])
    while todo:
        a = todo.popleft()
        for b, T in adj[a]:
            if b not in shape:
                shape[b] = shape[a].compose(T)
                todo.append(b)
    return shape


def _whitened_cost(T: gtsam.Pose3, C: np.ndarray, T_est: gtsam.Pose3) -> float:
    e = np.asarray(gtsam.Pose3.Logmap(T.between(T_est)))
    return float(e @ np.linalg.solve(C, e))


def rigid_test(shape: Mapping[str, gtsam.Pose3], facs: Sequence[GraphFactor],
               measured: Measured, placed: Mapping[str, gtsam.Pose3],
               probability: float) -> RigidTest:
    """The test of one chain (`shape`: its nodes' poses relative to one of them) against the
    factors from it to nodes `placed` outside it; its own nodes are `placed` as the solve bent
    them."""
    graph = gtsam.NonlinearFactorGraph()
    first: gtsam.Pose3 | None = None
    bent = loops = 0.0  # loops: the shape's own residual of the chain's loops
    n_loops = 0
    for f in facs:
        a_in, b_in = f.frame_a in shape, f.frame_b in shape
        if a_in and b_in and not f.known_inlier and f.frame_a in placed \
                and f.frame_b in placed:
            T, C = measured(f)
            loops += _whitened_cost(T, C, shape[f.frame_a].between(shape[f.frame_b]))
            bent += _whitened_cost(T, C, placed[f.frame_a].between(placed[f.frame_b]))
            n_loops += 1
            continue
        if a_in == b_in or (f.frame_b if a_in else f.frame_a) not in placed:
            continue
        T, C = measured(f)
        bent += _whitened_cost(T, C, placed[f.frame_a].between(placed[f.frame_b]))
        i, j = (f.frame_a, f.frame_b) if a_in else (f.frame_b, f.frame_a)
        Z = T if a_in else T.inverse()  # T_i_j
        if not a_in:  # the inverse's covariance: moved by the adjoint of T
            A = np.asarray(T.AdjointMap())
            C = A @ C @ A.T
        OZ = shape[i].compose(Z)
        P = placed[j].compose(OZ.inverse())  # the chain's placement this factor says
        A = np.asarray(OZ.AdjointMap())
        S = A @ C @ A.T
        graph.add(gtsam.PriorFactorPose3(0, P, gtsam.noiseModel.Gaussian.Covariance(
            0.5 * (S + S.T), False)))
        if first is None:
            first = P
    n = graph.size()
    if n_loops == 0 and (n < 2 or first is None):  # a rigid placement explains one factor
        return RigidTest(len(shape), n, bent, bent, 0, True)
    cost = loops
    if n >= 2 and first is not None:  # (one factor out: placed on it exactly, cost 0)
        values = gtsam.Values()
        values.insert(0, first)
        cost += 2.0 * float(graph.error(levenberg_marquardt(graph, values, "rigid placement")))
    return RigidTest(len(shape), n + n_loops, cost, bent, DRIFT_DOF,
                     cost - bent <= chi2_quantile(probability, DRIFT_DOF))


__all__ = ["DRIFT_DOF", "RigidTest", "chain_shape", "chains", "rigid_test"]
