"""Using mergesvc's inter-robot factors in your own GTSAM graph: a self-contained example.

No import of mergesvc: a factor arrives as the JSON object of schemas/factor.schema.json (decode
the wire message as docs/wire.md says, or take `mergesvc export`'s factors.json). Each factor is
a BetweenFactorPose3 between keyframe `keyframe_a` of (robot_a, session_a) and keyframe
`keyframe_b` of (robot_b, session_b): T_a_b is the pose of b's keyframe in a's keyframe, its
covariance 6x6 in GTSAM's Pose3 tangent order (rotation rad, then translation m). A factor id
seen again with status "retracted" must be removed: the service's GNC found it inconsistent.

    graph = InterRobotFactors(key_of=lambda robot, session, k: my_key(robot, session, k))
    graph.apply(factor_json)            # add, replace (same id, new content) or remove
    graph.graph                         # a gtsam.NonlinearFactorGraph: add your odometry, solve

With ISAM2, pass the indices `apply` returns to `isam.update(..., removeFactorIndices)` instead
(the reference agent does that: mergesvc/fleet/agent.py, `LocalMap.add_inter_robot`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import gtsam
import numpy as np

KeyOf = Callable[[str, str, int], int]


def pose_of(p: Mapping[str, Any]) -> gtsam.Pose3:
    """A factor's T_a_b ({"quaternion_wxyz": [w, x, y, z], "translation": [x, y, z]})."""
    w, x, y, z = p["quaternion_wxyz"]
    return gtsam.Pose3(gtsam.Rot3.Quaternion(w, x, y, z), np.asarray(p["translation"], float))


def between_factor(f: Mapping[str, Any], key_of: KeyOf) -> gtsam.BetweenFactorPose3:
    """The BetweenFactorPose3 of one factor object; a factor without keyframes ties the two
    session frames, which are keyframe 0 of each session."""
    ka, kb = f.get("keyframe_a") or 0, f.get("keyframe_b") or 0
    cov = np.asarray(f["covariance"], dtype=np.float64)
    return gtsam.BetweenFactorPose3(
        key_of(f["robot_a"], f["session_a"], ka), key_of(f["robot_b"], f["session_b"], kb),
        pose_of(f["T_a_b"]), gtsam.noiseModel.Gaussian.Covariance(cov))


class InterRobotFactors:
    """The factors in force, in one NonlinearFactorGraph, by factor id."""

    def __init__(self, key_of: KeyOf) -> None:
        self.key_of = key_of
        self.graph = gtsam.NonlinearFactorGraph()
        self.index: dict[str, int] = {}  # factor id -> its slot in self.graph
        self.ends: dict[str, tuple[str, ...]] = {}  # factor id -> the sessions it ties

    def apply(self, f: Mapping[str, Any]) -> str:
        """Add a factor, replace one with the same id, or drop it when its status is
        "retracted"; returns what it did. A factor whose id was seen tying other sessions is
        refused (ids never collide, docs/wire.md §6.3: it is not from the service)."""
        fid = f["factor_id"]
        ends = tuple(f[k] for k in ("robot_a", "session_a", "robot_b", "session_b"))
        if self.ends.setdefault(fid, ends) != ends:
            return "refused: the id names another pair of sessions"
        old = self.index.pop(fid, None)
        if old is not None:
            self.graph.remove(old)  # leaves an empty slot: indices of the others stay valid
        if f.get("status") == "retracted":
            return "removed" if old is not None else "unknown, ignored"
        self.graph.add(between_factor(f, self.key_of))
        self.index[fid] = self.graph.size() - 1
        return "replaced" if old is not None else "added"
