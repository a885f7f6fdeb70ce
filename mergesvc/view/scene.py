"""What the live view shows, as plain state and geometry (no rerun, no zenoh): each session's
keyframes (its odometry chain, from its submaps) and objects, the merged keyframe poses the
service publishes in its status, the inter-robot factors (accepted, retracted) and their
correspondences. view/live.py draws a FleetScene; view/feed.py fills one from the network.

Frames. Everything is drawn in the anchor frame (the service's anchor session's keyframe 0).
A session the service has aligned (its keyframes are in `status.keyframe_poses`) is placed with
those merged poses, and keyframes newer than the last status are composed along its odometry
from the nearest merged one (as the service places them: fleet/service.py SessionState). A
session not aligned (yet) is drawn in its own frame as if that were the anchor frame: its
keyframe 0 at the origin. Its odometry trajectory (the vehicle's own estimate) is drawn with the
same start as its merged one, so the two differ by the drift the merge corrected.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np

from mergesvc.core.factors import match_factor_id
from mergesvc.core.frames import FrameId
from mergesvc.core.model import Factor, FactorStatus, Submap
from mergesvc.fleet.sessions import SessionState

# Robot colours (RGB) in the order robots first appear: tab10 without its red, which marks
# retracted factors.
PALETTE: tuple[tuple[int, int, int], ...] = (
    (31, 119, 180), (255, 127, 14), (44, 160, 44), (148, 103, 189), (140, 86, 75),
    (227, 119, 194), (188, 189, 34), (23, 190, 207), (127, 127, 127),
)
RETRACTED_RGB = (214, 39, 40)


@dataclass(frozen=True)
class PlacedObjects:
    """A session's objects in the view frame: ids (n,), position_xyz_m (n, 3)."""

    ids: list[str]
    position_xyz_m: np.ndarray


@dataclass(frozen=True)
class Segments:
    """Line segments in the view frame: start_xyz_m, end_xyz_m (n, 3), one label each."""

    start_xyz_m: np.ndarray
    end_xyz_m: np.ndarray
    labels: list[str]

    def __len__(self) -> int:
        return len(self.labels)


def _segments(rows: list[tuple[np.ndarray, np.ndarray, str]]) -> Segments:
    if not rows:
        return Segments(np.zeros((0, 3)), np.zeros((0, 3)), [])
    return Segments(np.stack([a for a, _, _ in rows]), np.stack([b for _, b, _ in rows]),
                    [lab for _, _, lab in rows])


def _pose(T: Any) -> gtsam.Pose3:
    return gtsam.Pose3(np.asarray(T, dtype=np.float64))


def _submap_seq(factor: Factor) -> int | None:
    """The seq of the submap a factor came from, when its id is match_factor_id's."""
    try:
        seq = int(factor.factor_id.rsplit("-", 1)[1])
    except (IndexError, ValueError):
        return None
    fid = match_factor_id(FrameId(factor.robot_a, factor.session_a),
                          FrameId(factor.robot_b, factor.session_b), seq)
    return seq if fid == factor.factor_id else None


@dataclass
class FleetScene:
    """The fleet as the view knows it. Thread-safe: feeds call it from Zenoh callbacks."""

    sessions: dict[str, SessionState] = field(default_factory=dict)
    robots: list[str] = field(default_factory=list)  # order of first appearance: colours
    factors: dict[str, Factor] = field(default_factory=dict)  # latest message per factor id
    merged: dict[str, dict[int, gtsam.Pose3]] = field(default_factory=dict)  # T_anchor_k
    anchor: str | None = None
    submaps_seen: int = 0
    _arrival_s: dict[tuple[str, int], float] = field(default_factory=dict, repr=False)
    lock: threading.RLock = field(default_factory=threading.RLock, repr=False)

    # ------------------------------------------------------------------ input

    def add_submap(self, sub: Submap, arrived_s: float | None = None) -> str:
        """Take a submap in; returns its session name "{robot}/{session}"."""
        frame = FrameId(sub.robot_id, sub.session_id)
        name = str(frame)
        with self.lock:
            st = self.sessions.get(name)
            if st is None:
                st = self.sessions[name] = SessionState(frame)
            if sub.robot_id not in self.robots:
                self.robots.append(sub.robot_id)
            st.add(sub)
            self.submaps_seen += 1
            if arrived_s is not None and sub.seq is not None:
                self._arrival_s.setdefault((name, sub.seq), arrived_s)
        return name

    def add_factor(self, factor: Factor, arrived_s: float | None = None) -> float | None:
        """Take a factor message in (the service sends each to both robots: the second copy
        changes nothing). Returns, for the first copy of a factor whose submap this scene saw
        arrive, the delay from that submap to its factor in seconds, else None."""
        with self.lock:
            old = self.factors.get(factor.factor_id)
            if old is not None and old.status == factor.status:
                return None
            self.factors[factor.factor_id] = factor
            if old is not None or arrived_s is None:
                return None
            seq = _submap_seq(factor)
            name = str(FrameId(factor.robot_b, factor.session_b))
            t0 = self._arrival_s.get((name, seq)) if seq is not None else None
            return None if t0 is None else arrived_s - t0

    def set_merged(self, keyframe_poses: Mapping[str, Mapping[Any, Any]],
                   anchor: str | None) -> None:
        """The service's merged keyframe poses: {"robot/session": {k: (4, 4) T_anchor_k}}, as
        its status (keys as strings) or MergeService.keyframe_poses() (keys as ints) give
        them."""
        merged = {name: {int(k): _pose(T) for k, T in poses.items()}
                  for name, poses in keyframe_poses.items()}
        with self.lock:
            self.merged = merged
            self.anchor = anchor

    # ------------------------------------------------------------------ what is drawn

    def color(self, robot: str) -> tuple[int, int, int]:
        with self.lock:
            i = self.robots.index(robot) if robot in self.robots else len(self.robots)
        return PALETTE[i % len(PALETTE)]

    def is_retracted(self, factor: Factor) -> bool:
        return factor.status is FactorStatus.RETRACTED

    def aligned(self, name: str) -> bool:
        """Whether the service has placed this session in the anchor frame."""
        with self.lock:
            return bool(self.merged.get(name))

    def placed_poses(self, name: str) -> dict[int, gtsam.Pose3]:
        """Every keyframe of a session that can be placed, in the view frame (module doc)."""
        with self.lock:
            st = self.sessions[name]
            seeds = {k: T for k, T in self.merged.get(name, {}).items() if k in st.keyframes}
            return st.propagate(seeds or {0: gtsam.Pose3()})

    def odometry_poses(self, name: str) -> dict[int, gtsam.Pose3]:
        """The session's keyframes by its odometry alone, started where the merge put the
        earliest keyframe it placed (the session's own frame when not aligned)."""
        with self.lock:
            st = self.sessions[name]
            odo = st.propagate({0: gtsam.Pose3()})
            merged = self.merged.get(name, {})
            common = sorted(set(odo) & set(merged))
            if not common:
                return odo
            k = common[0]
            T_view_session = merged[k].compose(odo[k].inverse())
            return {j: T_view_session.compose(T) for j, T in odo.items()}

    @staticmethod
    def path_xyz_m(poses: Mapping[int, gtsam.Pose3]) -> np.ndarray:
        """(n, 3) positions of keyframe poses in keyframe order."""
        if not poses:
            return np.zeros((0, 3))
        return np.stack([np.asarray(poses[k].translation(), dtype=np.float64)
                         for k in sorted(poses)])

    def merged_poses(self, name: str) -> dict[int, gtsam.Pose3]:
        """The service's merged keyframe poses of a session ({} when not aligned)."""
        with self.lock:
            return dict(self.merged.get(name, {}))

    def objects(self, name: str, placed: Mapping[int, gtsam.Pose3] | None = None
                ) -> PlacedObjects:
        """A session's objects, each from the latest submap holding it, placed with the pose
        of that submap's keyframe (objects of keyframes that cannot be placed are left out)."""
        with self.lock:
            st = self.sessions[name]
            placed = self.placed_poses(name) if placed is None else placed
            ids, xyz = [], []
            for oid, held in st.objects.items():
                T = placed.get(held.keyframe)
                if T is None:
                    continue
                ids.append(oid)
                xyz.append(T.transformFrom(np.asarray(held.position, dtype=np.float64)))
        return PlacedObjects(ids, np.asarray(xyz, dtype=np.float64).reshape(-1, 3))

    def active_factors(self) -> list[Factor]:
        with self.lock:
            return [f for f in self.factors.values() if not self.is_retracted(f)]

    def retracted_factors(self) -> list[Factor]:
        with self.lock:
            return [f for f in self.factors.values() if self.is_retracted(f)]

    def correspondences(self) -> Segments:
        """One segment per correspondence of every factor in force: object_a of session a to
        object_b of session b, both as placed (pairs with an object not seen are left out)."""
        with self.lock:
            where: dict[str, dict[str, np.ndarray]] = {}
            for name in self.sessions:
                objs = self.objects(name)
                where[name] = dict(zip(objs.ids, objs.position_xyz_m))
            rows = []
            for f in self.active_factors():
                a = where.get(str(FrameId(f.robot_a, f.session_a)), {})
                b = where.get(str(FrameId(f.robot_b, f.session_b)), {})
                for c in f.correspondences:
                    if c.object_a in a and c.object_b in b:
                        rows.append((a[c.object_a], b[c.object_b],
                                     f"{c.object_a}={c.object_b}"))
        return _segments(rows)

    def factor_segments(self, retracted: bool) -> Segments:
        """One segment per factor (in force, or retracted), keyframe_a of session a to
        keyframe_b of session b as placed (keyframes 0 for a frame-level factor)."""
        with self.lock:
            placed = {name: self.placed_poses(name) for name in self.sessions}
            rows = []
            for f in self.retracted_factors() if retracted else self.active_factors():
                Ta = placed.get(str(FrameId(f.robot_a, f.session_a)), {}).get(f.keyframe_a or 0)
                Tb = placed.get(str(FrameId(f.robot_b, f.session_b)), {}).get(f.keyframe_b or 0)
                if Ta is not None and Tb is not None:
                    rows.append((np.asarray(Ta.translation(), dtype=np.float64),
                                 np.asarray(Tb.translation(), dtype=np.float64), f.factor_id))
        return _segments(rows)


__all__ = ["PALETTE", "RETRACTED_RGB", "FleetScene", "PlacedObjects", "Segments"]
