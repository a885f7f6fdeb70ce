"""mergesvc's outputs as ROS 2 messages, CDR-serialized by rosbags (an optional extra).

Factors and relocalization answers become geometry_msgs/msg/PoseWithCovarianceStamped (and
nav_msgs/msg/Odometry, which names both frames), the merged object map a
visualization_msgs/msg/MarkerArray, a merged trajectory a nav_msgs/msg/Path. Frames and the
covariance convention: docs/ros2.md.
"""

from __future__ import annotations

import functools
import math
import zlib
from collections.abc import Mapping, Sequence
from enum import Enum
from typing import TYPE_CHECKING, Any

import numpy as np

from mergesvc.core.model import Factor, ObjectMap, Transform
from mergesvc.errors import ConfigError

if TYPE_CHECKING:
    from mergesvc.fleet.replies import RelocalizeReply


class RosType(str, Enum):
    """The ROS 2 message types mergesvc publishes."""

    POSE_WITH_COVARIANCE_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
    ODOMETRY = "nav_msgs/msg/Odometry"
    MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
    PATH = "nav_msgs/msg/Path"


#: The ROS 2 distribution whose message definitions (and so type hashes) are used. The four
#: types hash the same in Humble, Jazzy and Kilted (tests/test_ros2.py checks Jazzy and Kilted).
DEFAULT_DISTRO = "ROS2_JAZZY"

# ROS order (x, y, z, roll, pitch, yaw) <- GTSAM Pose3 tangent order (rx, ry, rz, tx, ty, tz)
_ROS_FROM_GTSAM = np.array([3, 4, 5, 0, 1, 2])

# Colours of robots in the map (tab10), picked by a stable hash of the robot name.
_PALETTE = [(0.12, 0.47, 0.71), (1.0, 0.5, 0.05), (0.17, 0.63, 0.17), (0.84, 0.15, 0.16),
            (0.58, 0.4, 0.74), (0.55, 0.34, 0.29), (0.89, 0.47, 0.76), (0.5, 0.5, 0.5),
            (0.74, 0.74, 0.13), (0.09, 0.75, 0.81)]


@functools.lru_cache(maxsize=4)
def typestore(distro: str = DEFAULT_DISTRO) -> Any:
    """rosbags' type store of `distro` (a `rosbags.typesys.Stores` name). `ConfigError` when
    rosbags is not installed (the `ros2` extra) or the distro is unknown."""
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError as exc:
        raise ConfigError(
            "ROS 2 output needs rosbags: pip install 'mergesvc[ros2]'"
        ) from exc
    try:
        return get_typestore(Stores[distro])
    except KeyError as exc:
        raise ConfigError(f"unknown ROS 2 distro {distro!r} (rosbags Stores name, e.g. "
                          f"{DEFAULT_DISTRO})") from exc


def type_hash(ros_type: str, distro: str = DEFAULT_DISTRO) -> str:
    """The REP-2016 type hash "RIHS01_<sha256 hex>" of a message type, computed by rosbags from
    the distro's message definitions."""
    return str(typestore(distro).hash_rihs01(_name(ros_type)))


def serialize(message: Any, ros_type: str, distro: str = DEFAULT_DISTRO) -> bytes:
    """`message` as CDR: the 4-byte encapsulation header (CDR_LE: 00 01 00 00), then the
    little-endian body, alignment counted from the end of the header."""
    return bytes(typestore(distro).serialize_cdr(message, _name(ros_type), little_endian=True))


def _name(ros_type: str) -> str:
    return ros_type.value if isinstance(ros_type, RosType) else ros_type


def frame_id(robot: str, session: str, keyframe: int | None = None) -> str:
    """The ROS frame of a session ("{robot}/{session}", its keyframe 0) or of one of its
    keyframes ("{robot}/{session}/kf{k}", the vehicle's body where it cut that submap)."""
    return f"{robot}/{session}" if keyframe is None else f"{robot}/{session}/kf{keyframe}"


def factor_frames(factor: Factor) -> tuple[str, str]:
    """(frame a, frame b) of a factor: keyframe frames for a pose-level factor, else the two
    session frames."""
    return (frame_id(factor.robot_a, factor.session_a, factor.keyframe_a),
            frame_id(factor.robot_b, factor.session_b, factor.keyframe_b))


def rotation_matrix(quaternion_wxyz: Sequence[float]) -> np.ndarray:
    """(3, 3) rotation of a unit quaternion (w, x, y, z); normalised first."""
    w, x, y, z = np.asarray(quaternion_wxyz, dtype=np.float64) / np.linalg.norm(quaternion_wxyz)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def covariance_ros(covariance_gtsam: Sequence[Sequence[float]] | np.ndarray,
                   R_parent_child: np.ndarray) -> list[float]:
    """A Pose3 covariance as PoseWithCovariance.covariance (36 numbers, row-major).

    GTSAM: 6x6 over the tangent (rx, ry, rz, tx, ty, tz) of T = T_parent_child, perturbed on
    the right (T Exp(xi)), so both blocks are in the child's axes. ROS: (x, y, z, roll, pitch,
    yaw), position and fixed-axis rotation errors in the parent (header.frame_id) axes. To first
    order T Exp(xi) moves the position by R v and the orientation by R w (about the parent's
    axes), so C_ros = P J C J^T P^T with J = diag(R, R) and P the reordering."""
    C = np.asarray(covariance_gtsam, dtype=np.float64)
    if C.shape != (6, 6):
        raise ConfigError(f"covariance must be 6x6, got {C.shape}")
    R = np.asarray(R_parent_child, dtype=np.float64)
    J = np.zeros((6, 6))
    J[:3, :3] = J[3:, 3:] = R
    C_parent = J @ C @ J.T
    C_ros = C_parent[np.ix_(_ROS_FROM_GTSAM, _ROS_FROM_GTSAM)]
    C_ros = (C_ros + C_ros.T) / 2  # exact symmetry after the rotation
    return [float(x) for x in C_ros.ravel()]


def stamp(t_s: float, distro: str = DEFAULT_DISTRO) -> Any:
    """builtin_interfaces/msg/Time of a time in seconds since the UNIX epoch."""
    sec = math.floor(t_s)
    nanosec = min(round((t_s - sec) * 1e9), 999_999_999)
    return typestore(distro).types["builtin_interfaces/msg/Time"](sec=int(sec), nanosec=nanosec)


def header(frame: str, t_s: float, distro: str = DEFAULT_DISTRO) -> Any:
    """std_msgs/msg/Header."""
    return typestore(distro).types["std_msgs/msg/Header"](stamp=stamp(t_s, distro), frame_id=frame)


def pose(translation: Sequence[float], quaternion_wxyz: Sequence[float],
         distro: str = DEFAULT_DISTRO) -> Any:
    """geometry_msgs/msg/Pose (ROS orders the quaternion x, y, z, w)."""
    t = typestore(distro).types
    w, x, y, z = (float(v) for v in quaternion_wxyz)
    return t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=float(translation[0]), y=float(translation[1]),
                                              z=float(translation[2])),
        orientation=t["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
    )


def pose_with_covariance(T: Transform, covariance: Sequence[Sequence[float]] | None,
                         distro: str = DEFAULT_DISTRO) -> Any:
    """geometry_msgs/msg/PoseWithCovariance of a transform and its GTSAM covariance (zeros when
    there is none)."""
    cov = ([0.0] * 36 if covariance is None
           else covariance_ros(covariance, rotation_matrix(T.quaternion_wxyz)))
    return typestore(distro).types["geometry_msgs/msg/PoseWithCovariance"](
        pose=pose(T.translation, T.quaternion_wxyz, distro),
        covariance=np.asarray(cov, dtype=np.float64),
    )


def factor_pose(factor: Factor, t_s: float, distro: str = DEFAULT_DISTRO) -> Any:
    """PoseWithCovarianceStamped of a factor: header.frame_id = frame a, the pose of frame b in
    it (T_a_b), its covariance in ROS order and frame a's axes."""
    frame_a, _ = factor_frames(factor)
    return typestore(distro).types[RosType.POSE_WITH_COVARIANCE_STAMPED.value](
        header=header(frame_a, t_s, distro),
        pose=pose_with_covariance(factor.T_a_b, factor.covariance, distro),
    )


def factor_link(factor: Factor, t_s: float, distro: str = DEFAULT_DISTRO) -> Any:
    """nav_msgs/msg/Odometry of a factor: the same pose as `factor_pose`, and child_frame_id =
    frame b, so both ends are named. The twist is unknown: zero, covariance[0] = -1 (REP-105's
    "ignore this" marker for an unknown covariance)."""
    t = typestore(distro).types
    frame_a, frame_b = factor_frames(factor)
    twist_cov = np.zeros(36)
    twist_cov[0] = -1.0
    zero = t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    return t[RosType.ODOMETRY.value](
        header=header(frame_a, t_s, distro),
        child_frame_id=frame_b,
        pose=pose_with_covariance(factor.T_a_b, factor.covariance, distro),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](
            twist=t["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=twist_cov),
    )


def relocalization_pose(reply: RelocalizeReply, t_s: float,
                        distro: str = DEFAULT_DISTRO) -> Any | None:
    """PoseWithCovarianceStamped of a relocalization answer: header.frame_id = the anchor
    session's frame, the pose of the query submap's frame in it; None when not localized."""
    if not reply.localized or reply.T_anchor_session is None or reply.anchor is None:
        return None
    robot, _, session = reply.anchor.partition("/")
    return typestore(distro).types[RosType.POSE_WITH_COVARIANCE_STAMPED.value](
        header=header(frame_id(robot, session), t_s, distro),
        pose=pose_with_covariance(reply.T_anchor_session, reply.covariance, distro),
    )


def robot_colour(robot: str) -> tuple[float, float, float]:
    """A stable colour per robot name."""
    return _PALETTE[zlib.crc32(robot.encode()) % len(_PALETTE)]


def map_markers(object_map: ObjectMap, frame: str, t_s: float, scale_m: float = 0.3,
                distro: str = DEFAULT_DISTRO) -> Any:
    """MarkerArray of a merged map: a DELETEALL first (objects fused away disappear), then one
    SPHERE per object (ns "objects", id = its index, coloured by the robot its id starts with:
    fused ids are "{robot}/{session}/{object}"), and a TEXT_VIEW_FACING label (ns "labels") for
    objects that carry one."""
    t = typestore(distro).types
    M = t["visualization_msgs/msg/Marker"]
    hdr = header(frame, t_s, distro)
    forever = t["builtin_interfaces/msg/Duration"](sec=0, nanosec=0)
    empty_image = t["sensor_msgs/msg/CompressedImage"](
        header=header("", 0.0, distro), format="", data=np.zeros(0, dtype=np.uint8))
    empty_mesh = t["visualization_msgs/msg/MeshFile"](filename="",
                                                      data=np.zeros(0, dtype=np.uint8))
    identity = (1.0, 0.0, 0.0, 0.0)

    def marker(ns: str, k: int, kind: int, action: int, position: Sequence[float],
               rgb: tuple[float, float, float], size: float, text: str = "") -> Any:
        return M(
            header=hdr, ns=ns, id=k, type=kind, action=action,
            pose=pose(position, identity, distro),
            scale=t["geometry_msgs/msg/Vector3"](x=size, y=size, z=size),
            color=t["std_msgs/msg/ColorRGBA"](r=rgb[0], g=rgb[1], b=rgb[2], a=1.0),
            lifetime=forever, frame_locked=False, points=[], colors=[], texture_resource="",
            texture=empty_image, uv_coordinates=[], text=text, mesh_resource="",
            mesh_file=empty_mesh, mesh_use_embedded_materials=False,
        )

    markers = [marker("", 0, M.SPHERE, M.DELETEALL, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 1.0)]
    for k, obj in enumerate(object_map.objects):
        rgb = robot_colour(obj.id.split("/", 1)[0])
        markers.append(marker("objects", k, M.SPHERE, M.ADD, obj.position, rgb, scale_m))
        if obj.label:
            above = (obj.position[0], obj.position[1], obj.position[2] + scale_m)
            markers.append(marker("labels", k, M.TEXT_VIEW_FACING, M.ADD, above,
                                  (1.0, 1.0, 1.0), scale_m, obj.label))
    return t[RosType.MARKER_ARRAY.value](markers=markers)


def path(poses: Mapping[int, np.ndarray], frame: str, t_s: float,
         distro: str = DEFAULT_DISTRO) -> Any:
    """nav_msgs/msg/Path of a trajectory: keyframe -> (4, 4) pose in `frame`, in keyframe order.
    Keyframes carry no time of their own here: every pose is stamped `t_s`."""
    t = typestore(distro).types
    hdr = header(frame, t_s, distro)
    out = []
    for k in sorted(poses):
        T = np.asarray(poses[k], dtype=np.float64)
        out.append(t["geometry_msgs/msg/PoseStamped"](
            header=hdr, pose=pose(T[:3, 3], quaternion_wxyz(T[:3, :3]), distro)))
    return t[RosType.PATH.value](header=hdr, poses=out)


def quaternion_wxyz(R: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (w, x, y, z) with w >= 0 of a (3, 3) rotation matrix."""
    import gtsam

    q = gtsam.Rot3(np.asarray(R, dtype=np.float64)).toQuaternion()
    wxyz = np.array([q.w(), q.x(), q.y(), q.z()])
    wxyz = wxyz if wxyz[0] >= 0 else -wxyz
    return tuple(float(v) for v in wxyz / np.linalg.norm(wxyz))


__all__ = [
    "DEFAULT_DISTRO",
    "RosType",
    "covariance_ros",
    "factor_frames",
    "factor_link",
    "factor_pose",
    "frame_id",
    "header",
    "map_markers",
    "path",
    "pose",
    "pose_with_covariance",
    "quaternion_wxyz",
    "relocalization_pose",
    "robot_colour",
    "rotation_matrix",
    "serialize",
    "stamp",
    "type_hash",
    "typestore",
]
