"""What merging a fleet's submaps could give at best: every robot's odometry chain plus a closure
between every two keyframes of two robots whose submaps share objects, exact or as accurate as
a run's factors (`closure_bound`), solved by least squares. `bench merge` reports it beside the
service's merged trajectories (fleet/replay.py); it uses the truth, which the service never sees.
"""

from __future__ import annotations

import logging
from collections import defaultdict
from collections.abc import Callable
from typing import Any

import gtsam
import numpy as np

from mergesvc.core.connectivity import UnionFind
from mergesvc.core.model import Submap
from mergesvc.core.poses import pose3_from_model

log = logging.getLogger(__name__)

# what "exact" means for the closures of `closure_bound`: 1 mrad, 1 cm
EXACT_SIGMA = (1e-3, 1e-2)
MIN_SHARED = 3  # true objects two submaps must share for a closure between their keyframes
BOUND_DRAWS = 10  # draws of the closures' errors for the bound at the factors' accuracy
MIN_ERROR_SAMPLES = 10  # factors needed to estimate their error per axis (to about a third)
MAD_TO_SIGMA = 1.4826  # sigma of a normal distribution = 1.4826 x its median absolute value
SIGMA_FLOOR = 1e-4  # rad, m: an axis the factors got exactly right (the tilt, fitted about
# gravity) is still not held infinitely stiff



def closure_bound(
    subs: list[Submap],
    truth_T: dict[str, np.ndarray],
    truth_of: Callable[[str, str], str | None],
    *,
    anchor: str,
    exact_sigma: tuple[float, float] = EXACT_SIGMA,
    min_shared: int = MIN_SHARED,
    error_sigma: np.ndarray | None = None,
    rng: np.random.Generator | None = None,
) -> dict[str, tuple[dict[int, np.ndarray] | None, int]]:
    """What merging these submaps could give with better closures: every robot's odometry chain
    (the submaps' own odometry edges and covariances, as the service holds them) plus a closure
    between every two keyframes of two robots whose submaps hold at least `min_shared` of the
    same true objects (the service closes loops between robots only, as here), solved by least
    squares. Each closure is the truth relative pose, with sigma `exact_sigma` (rad, m);
    no closure is wrong, and there are far more of them than a matcher accepts.

    It is a bound for this odometry weighting and these closures, not a minimum of ATE: exact
    closures make two chains meet in a least-squares compromise of their odometry, which can
    place a robot a little worse than its own odometry did (measured: 0.077 against 0.077 m,
    the pool, 1 lap). Where it misses a target by a margin, better closures will not meet it;
    other information (more of the paths seen twice, better odometry) would.

    `error_sigma` (6, GTSAM tangent order: rotation rad, translation m): instead, each closure
    is off the truth by a right perturbation drawn from N(0, diag(error_sigma^2)) (from `rng`)
    and weighted by it: what closures as accurate as a matcher's factors could give were every
    co-visible pair matched, with independent errors.

    Returns per robot ({keyframe: pose (4x4) in the anchor robot's frame}, closures touching
    the robot); None for a robot with fewer than two poses to score; {} when the solve fails.
    A submap lost on the link leaves pieces of chain that only closures join to the rest, as
    in the service (the start of a delivered odometry edge whose own submap was lost is a node
    there too). The anchor's largest piece holds the gauge; a robot is scored on its nodes
    joined to it, else on its own chain from keyframe 0 (ATE aligns each robot on its own).
    Nodes start at their piece's true start composed with the odometry; a piece's start has a
    loose prior there, which places nothing the links do not.
    """
    by_robot: dict[str, list[Submap]] = defaultdict(list)
    for s in subs:
        if s.keyframe is not None and s.robot_id in truth_T:
            by_robot[s.robot_id].append(s)
    robots = sorted(by_robot)
    if not robots:
        return {}
    if anchor not in by_robot:
        anchor = robots[0]
    sym = {r: i for i, r in enumerate(robots)}

    def key(r: str, k: int) -> int:
        return gtsam.symbol("b", sym[r] * 1_000_000_000 + k)

    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    seen: dict[str, dict[int, set[str]]] = {}  # robot -> keyframe -> true objects it holds
    placed: dict[str, dict[int, np.ndarray]] = {}  # robot -> node -> initial pose
    links: list[tuple[tuple[str, int], tuple[str, int]]] = []  # odometry edges and closures
    loose = gtsam.noiseModel.Isotropic.Sigma(6, 1e3)
    for r in robots:
        T = truth_T[r]
        odo = placed[r] = {}
        seen[r] = defaultdict(set)

        def piece(k: int, T: np.ndarray = T, r: str = r) -> None:
            # a node no odometry reaches (keyframe 0, or the start of an edge whose submap was
            # lost: the service holds it too) starts a piece where it truly is, loosely: only
            # links place it relative to anything else
            placed[r][k] = T[k]
            values.insert(key(r, k), gtsam.Pose3(T[k]))
            graph.add(gtsam.PriorFactorPose3(key(r, k), gtsam.Pose3(T[k]), loose))

        piece(0)
        for s in sorted(by_robot[r], key=lambda s: s.keyframe or 0):
            k = int(s.keyframe or 0)
            if k >= len(T):
                continue
            seen[r][k] |= {t for o in s.objects if (t := truth_of(r, o.id)) is not None}
            if k in odo:
                continue
            od = s.odometry
            if od is None or od.from_keyframe >= k:
                piece(k)
                continue
            if od.from_keyframe not in odo:
                piece(od.from_keyframe)
            T_ft = pose3_from_model(od.T_from_to)
            odo[k] = odo[od.from_keyframe] @ T_ft.matrix()
            values.insert(key(r, k), gtsam.Pose3(odo[k]))
            graph.add(gtsam.BetweenFactorPose3(
                key(r, od.from_keyframe), key(r, k), T_ft,
                gtsam.noiseModel.Gaussian.Covariance(np.asarray(od.covariance, dtype=np.float64))))
            links.append(((r, od.from_keyframe), (r, k)))
    if error_sigma is None:
        sigma = np.array([exact_sigma[0]] * 3 + [exact_sigma[1]] * 3)
    else:
        sigma = np.asarray(error_sigma, dtype=np.float64).reshape(6)
        rng = rng if rng is not None else np.random.default_rng(0)
    noise = gtsam.noiseModel.Diagonal.Sigmas(sigma)
    closures: dict[str, int] = defaultdict(int)
    nodes = [(r, k) for r in robots for k in sorted(seen[r])]
    for i, (ra, ka) in enumerate(nodes):
        for rb, kb in nodes[i + 1:]:
            if ra == rb or len(seen[ra][ka] & seen[rb][kb]) < min_shared:
                continue
            T_ab = gtsam.Pose3(np.linalg.inv(truth_T[ra][ka]) @ truth_T[rb][kb])
            if error_sigma is not None:
                assert rng is not None
                T_ab = T_ab.compose(gtsam.Pose3.Expmap(rng.normal(0.0, sigma)))
            graph.add(gtsam.BetweenFactorPose3(key(ra, ka), key(rb, kb), T_ab, noise))
            links.append(((ra, ka), (rb, kb)))
            closures[ra] += 1
            closures[rb] += 1
    # groups: nodes joined by links (the loose priors join nothing). The gauge: the anchor's
    # largest group, held at its first node's true pose; each robot is scored on its nodes in
    # the gauge's group, else on its keyframe 0's group (its own odometry: ATE aligns)
    index = {n: i for i, n in enumerate((r, k) for r in robots for k in sorted(placed[r]))}
    uf = UnionFind(len(index))
    for a, b in links:
        uf.union(index[a], index[b])

    def group(r: str, g: int) -> list[int]:
        return [k for k in sorted(placed[r]) if uf.find(index[(r, k)]) == g]

    sizes: dict[int, int] = defaultdict(int)
    for k in placed[anchor]:
        sizes[uf.find(index[(anchor, k)])] += 1
    gauge = min(sizes, key=lambda g: (-sizes[g], g))
    k0 = group(anchor, gauge)[0]
    graph.add(gtsam.PriorFactorPose3(key(anchor, k0), gtsam.Pose3(truth_T[anchor][k0]),
                                     gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    try:
        est = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    except RuntimeError as exc:  # (not seen: a bench row is left empty rather than failing)
        log.warning("closure bound: the solve failed: %s", exc)
        return {}
    out: dict[str, tuple[dict[int, np.ndarray] | None, int]] = {}
    for r in robots:
        ks = group(r, gauge) or group(r, uf.find(index[(r, 0)]))
        out[r] = ({k: est.atPose3(key(r, k)).matrix() for k in ks} if len(ks) > 1 else None,
                  closures[r])
    return out


def error_sigma(factors: list[dict[str, Any]]) -> np.ndarray | None:
    """Per axis (GTSAM tangent order: rotation rad, translation m) the typical error of the
    factors whose correspondences are all right, what the objects let a factor reach: 1.4826 x
    the median absolute error, robust to the few factors far off (a second moment would be
    theirs: pool-long, 1 of 96 factors 4 m off in height). None with fewer than
    MIN_ERROR_SAMPLES such factors."""
    e = np.asarray([f["err_tangent"] for f in factors
                    if f["corr_wrong"] == 0 and f["err_tangent"] is not None], dtype=np.float64)
    if len(e) < MIN_ERROR_SAMPLES:
        return None
    return np.maximum(MAD_TO_SIGMA * np.median(np.abs(e), axis=0), SIGMA_FLOOR)


__all__ = ["BOUND_DRAWS", "closure_bound", "error_sigma"]
