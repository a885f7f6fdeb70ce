"""Which way is up in a frame (verification stage): declared by the file, inferred from the
object layout where that is reliable, or unknown; and how the verticals of a map and a submap
relate. No axis convention is assumed: KITTI's camera frames have y down, ROS frames z up,
marine frames often z down, and two robots of one fleet may differ.

Used by the tilt test (a flat group of objects matched to its mirror image turns the vertical
over) and by the gravity-aligned 4-DoF fit (yaw about the vertical + translation, as ROMAN does
with its gravity prior) that lets 2 matches, or matches on a line, fix a transform.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np

from mergesvc.core.geometry import cross
from mergesvc.core.model import ObjectArrays


class VerticalSource(str, Enum):
    DECLARED = "declared"  # the file's `up` field: a signed direction
    INFERRED = "inferred"  # the axis of least spread of a flat layout: sign unknown
    SHARED = "shared"  # too few objects to tell: taken to be the map's axis (same frame kind)


@dataclass(frozen=True)
class FrameVertical:
    """up_xyz: (3,) unit vector; for an inferred axis, its sign is arbitrary."""

    up_xyz: np.ndarray
    source: VerticalSource


@dataclass(frozen=True)
class VerticalRelation:
    """The verticals of both frames of one match.

    up_map, up_sub: (3,) unit vectors in map and submap coordinates. signed: the relative sign is
    known (both declared, or one axis shared by both frames), so a transform must take up_sub to
    +up_map; otherwise only the axis is known. declared: both files declared their vertical.
    """

    up_map: np.ndarray
    up_sub: np.ndarray
    signed: bool
    declared: bool

    def tilt_deg(self, R: np.ndarray) -> float:
        """Angle (deg) by which rotation R (3, 3), map <- submap, turns the submap's vertical
        away from the map's; modulo the sign when the relation is unsigned."""
        c = float(np.dot(R @ self.up_sub, self.up_map))
        return float(np.degrees(np.arccos(np.clip(c if self.signed else abs(c), -1.0, 1.0))))


# A layout must be at least this wide across as it is long for its least spread to be the
# vertical: a narrow strip (a row of objects along a wall or a kerb) may be thinner sideways
# than it is tall.
_MIN_WIDTH_RATIO = 0.1


def infer_up_axis(
    position_xyz_m: np.ndarray, min_objects: int = 10, max_flatness: float = 0.3
) -> np.ndarray | None:
    """The axis of least spread of a layout that is clearly flat, else None.

    position_xyz_m: (n, 3). Most object maps are far wider than they are tall (a street, a
    harbour floor, a pool): the smallest principal axis is then the vertical. Reliable only when
    its spread is at most `max_flatness` times the second smallest, the layout is not a narrow
    strip (the second at least a tenth of the largest), and there are enough objects for the
    principal axes to mean something; otherwise nothing is inferred. Sign: arbitrary (the
    component of largest magnitude made positive, so the result is reproducible).
    """
    xyz = np.asarray(position_xyz_m, dtype=np.float64)
    if len(xyz) < min_objects:
        return None
    centred = xyz - xyz.mean(axis=0)
    _, sv, Vt = np.linalg.svd(centred, full_matrices=False)
    if len(sv) < 3 or sv[1] <= 0 or sv[2] > max_flatness * sv[1]:
        return None
    if sv[1] < _MIN_WIDTH_RATIO * sv[0]:
        return None
    axis = Vt[2]
    return axis if axis[np.argmax(np.abs(axis))] > 0 else -axis


def frame_vertical(
    arr: ObjectArrays, min_objects: int = 10, max_flatness: float = 0.3
) -> FrameVertical | None:
    """The frame's declared vertical, else the inferred axis of a flat layout, else None."""
    if arr.up_xyz is not None:
        return FrameVertical(np.asarray(arr.up_xyz, dtype=np.float64), VerticalSource.DECLARED)
    axis = infer_up_axis(arr.position_xyz_m, min_objects, max_flatness)
    return None if axis is None else FrameVertical(axis, VerticalSource.INFERRED)


# Two axes closer than this are taken to be the same axis of the two frames' coordinates.
_SAME_AXIS_COS = float(np.cos(np.radians(30.0)))


def relate(
    map_v: FrameVertical | None, sub_v: FrameVertical | None, share: bool = True
) -> VerticalRelation | None:
    """How the verticals of map and submap relate, or None when either is unknown.

    A submap without a vertical shares the map's axis when `share` is set (the pipeline sets it
    only for submaps too small to show one: a submap is cut from a vehicle's own map, in the
    same kind of frame); its sign relation is then known. Two axes that coincide in coordinates
    are taken to be the same axis with the same sign (ENU and ENU, camera and camera); axes that
    differ (camera and ENU) give only an unsigned relation unless both files declared theirs.
    """
    if map_v is None:
        return None
    if sub_v is None:
        if not share:
            return None
        sub_v = FrameVertical(map_v.up_xyz, VerticalSource.SHARED)
    declared = map_v.source is VerticalSource.DECLARED and sub_v.source is VerticalSource.DECLARED
    up_map, up_sub = map_v.up_xyz, sub_v.up_xyz
    if declared:
        return VerticalRelation(up_map, up_sub, signed=True, declared=True)
    c = float(np.dot(up_map, up_sub))
    if abs(c) < _SAME_AXIS_COS:
        return VerticalRelation(up_map, up_sub, signed=False, declared=False)
    # the same axis of both frames: give the inferred one the sign of the other
    if c < 0:
        if sub_v.source is VerticalSource.DECLARED:
            up_map = -up_map
        else:
            up_sub = -up_sub
    return VerticalRelation(up_map, up_sub, signed=True, declared=False)


_ROTATIONS: dict[bytes, np.ndarray] = {}  # rotation_between's answers (a few verticals)


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(3, 3) smallest rotation taking the direction of a to that of b (Rodrigues); a, b (3,)
    non-zero, normalised here. Read-only: the answer for the same a and b is kept (a fleet
    has a few verticals, and every 4-DoF fit asks again)."""
    a = np.asarray(a, dtype=np.float64).reshape(3)
    b = np.asarray(b, dtype=np.float64).reshape(3)
    key = a.tobytes() + b.tobytes()
    out = _ROTATIONS.get(key)
    if out is None:
        if len(_ROTATIONS) >= 1024:
            _ROTATIONS.clear()
        out = _ROTATIONS[key] = _rotation_between(a, b)
        out.flags.writeable = False
    return out


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64) / np.linalg.norm(a)
    b = np.asarray(b, dtype=np.float64) / np.linalg.norm(b)
    c = float(np.dot(a, b))
    if c < -1.0 + 1e-8:
        # (nearly) opposite, where the cross product loses its direction: half a turn about
        # the axis perpendicular to a closest to bisecting a and b, then the small rest
        perp = cross(a, np.eye(3)[int(np.argmin(np.abs(a)))])
        perp /= np.linalg.norm(perp)
        half = 2.0 * np.outer(perp, perp) - np.eye(3)
        return _rotation_between(half @ a, b) @ half
    v = cross(a, b)
    s = float(np.linalg.norm(v))
    if s < 1e-15:
        return np.eye(3)
    k = v / s
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * Kx + (1.0 - c) * Kx @ Kx


__all__ = [
    "FrameVertical",
    "VerticalRelation",
    "VerticalSource",
    "frame_vertical",
    "infer_up_axis",
    "relate",
    "rotation_between",
]
