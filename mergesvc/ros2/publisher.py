"""ROS 2 publishers inside a Zenoh session, as rmw_zenoh makes them: one node token, and per topic
a publisher on the rmw_zenoh data key, its liveliness token, CDR samples with the attachment.

A ROS 2 node on rmw_zenoh connected to the same Zenoh network sees the topics in `ros2 topic
list` and receives them with `ros2 topic echo` (docs/ros2.md). No ROS 2 install is needed here.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from mergesvc.core.model import Factor, FactorStatus, ObjectMap
from mergesvc.ros2.messages import (
    DEFAULT_DISTRO,
    RosType,
    factor_link,
    factor_pose,
    frame_id,
    map_markers,
    path,
    relocalization_pose,
    serialize,
    type_hash,
)
from mergesvc.ros2.names import (
    Durability,
    Qos,
    attachment,
    check_namespace,
    entity_gid,
    join_topic,
    name_token,
    node_token,
    publisher_token,
    topic_key,
)

if TYPE_CHECKING:
    from mergesvc.fleet.replies import RelocalizeReply

log = logging.getLogger(__name__)

# Topics below the namespace, with their type and QoS. Factors are kept for late joiners
# (transient local, the last 1000); the map and each path are latched (the last one).
FACTORS = "factors"
FACTOR_LINKS = "factor_links"
RETRACTED_FACTORS = "retracted_factors"
RELOCALIZATION = "relocalization"
MAP = "map"
PATHS = "paths"

FACTOR_QOS = Qos(durability=Durability.TRANSIENT_LOCAL, depth=1000)
RELOCALIZATION_QOS = Qos(durability=Durability.VOLATILE, depth=10)
LATCHED_QOS = Qos(durability=Durability.TRANSIENT_LOCAL, depth=1)
HEARTBEAT_S = 1.0  # sporadic heartbeat of the transient-local (cached) publishers

# rmw_zenoh numbers nodes and entities per context; one counter per process keeps the ids of
# several Ros2Publishers on one session apart.
_ids = itertools.count()


@dataclass
class _Topic:
    name: str
    ros_type: str
    qos: Qos
    key: str
    token_key: str
    gid: bytes
    publisher: Any
    token: Any
    seq: int = 1  # rmw_zenoh's publishers count from 1


class Ros2Publisher:
    """mergesvc's outputs as ROS 2 topics of node `{namespace}/{node_name}` in `session`.

    Topics (under `namespace`, default /mergesvc): factors, factor_links, retracted_factors,
    relocalization, map, paths/{robot}/{session}; docs/ros2.md gives types, frames and QoS.
    Publishers and their tokens are declared on first use; `close()` undeclares everything
    (the session stays open: it is the caller's)."""

    def __init__(
        self,
        session: Any,
        domain_id: int = 0,
        namespace: str = "/mergesvc",
        node_name: str = "merge_service",
        distro: str = DEFAULT_DISTRO,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.session = session
        self.domain_id = domain_id
        self.namespace = check_namespace(namespace)
        self.node_name = node_name
        self.distro = distro
        self.clock = clock
        self.zid = str(session.info.zid())
        self.node_id = next(_ids)
        self._lock = threading.Lock()
        self._topics: dict[str, _Topic] = {}
        self._closed = False
        self.node_token_key = node_token(domain_id, self.zid, self.node_id, self.namespace,
                                         node_name)
        type_hash(RosType.PATH.value, distro)  # fail now (no rosbags, bad distro), not later
        self._node_token = session.liveliness().declare_token(self.node_token_key)

    # ------------------------------------------------------------------ topics

    @property
    def topics(self) -> dict[str, str]:
        """Topic name -> Zenoh data key of every topic declared so far."""
        with self._lock:
            return {t.name: t.key for t in self._topics.values()}

    def _topic(self, name: str, ros_type: RosType, qos: Qos) -> _Topic:
        from zenoh import CongestionControl
        from zenoh import Reliability as ZReliability
        from zenoh.ext import CacheConfig, MissDetectionConfig, declare_advanced_publisher

        with self._lock:
            if self._closed:
                raise RuntimeError("Ros2Publisher is closed")
            topic = self._topics.get(name)
            if topic is not None:
                return topic
            h = type_hash(ros_type.value, self.distro)
            key = topic_key(self.domain_id, name, ros_type.value, h)
            token_key = publisher_token(self.domain_id, self.zid, self.node_id, next(_ids),
                                        self.namespace, self.node_name, name, ros_type.value, h,
                                        qos)
            if qos.transient_local:
                # as rmw_zenoh: a cache of `depth` samples that late transient-local
                # subscriptions query, publisher detection, sporadic heartbeats (reliable)
                pub = declare_advanced_publisher(
                    self.session, key, cache=CacheConfig(max_samples=qos.depth),
                    publisher_detection=True,
                    sample_miss_detection=MissDetectionConfig(
                        heartbeat=None, sporadic_heartbeat=HEARTBEAT_S),
                    reliability=ZReliability.RELIABLE,
                    congestion_control=CongestionControl.DROP,
                )
            else:
                pub = self.session.declare_publisher(
                    key, reliability=ZReliability.RELIABLE,
                    congestion_control=CongestionControl.DROP)
            token = self.session.liveliness().declare_token(token_key)
            topic = self._topics[name] = _Topic(name, ros_type.value, qos, key, token_key,
                                                entity_gid(token_key), pub, token)
            log.info("ROS 2 topic %s (%s) on %s", name, ros_type.value, key)
            return topic

    def _put(self, name: str, ros_type: RosType, qos: Qos, message: Any) -> str:
        topic = self._topic(name, ros_type, qos)
        payload = serialize(message, ros_type.value, self.distro)
        with self._lock:
            seq = topic.seq
            topic.seq += 1
        topic.publisher.put(payload, attachment=attachment(seq, time.time_ns(), topic.gid))
        return name

    # ------------------------------------------------------------------ outputs

    def publish_factor(self, factor: Factor) -> list[str]:
        """An inter-robot factor. Accepted (or without status): PoseWithCovarianceStamped on
        `factors` and Odometry on `factor_links`; retracted: Odometry on `retracted_factors`.
        Returns the topics published on."""
        t_s = self.clock()
        if factor.status is FactorStatus.RETRACTED:
            return [self._put(join_topic(self.namespace, RETRACTED_FACTORS), RosType.ODOMETRY,
                              FACTOR_QOS, factor_link(factor, t_s, self.distro))]
        return [
            self._put(join_topic(self.namespace, FACTORS), RosType.POSE_WITH_COVARIANCE_STAMPED,
                      FACTOR_QOS, factor_pose(factor, t_s, self.distro)),
            self._put(join_topic(self.namespace, FACTOR_LINKS), RosType.ODOMETRY, FACTOR_QOS,
                      factor_link(factor, t_s, self.distro)),
        ]

    def publish_relocalization(self, reply: RelocalizeReply) -> list[str]:
        """A relocalization answer as PoseWithCovarianceStamped on `relocalization` (frame: the
        anchor session); nothing for an answer that did not localize."""
        msg = relocalization_pose(reply, self.clock(), self.distro)
        if msg is None:
            return []
        return [self._put(join_topic(self.namespace, RELOCALIZATION),
                          RosType.POSE_WITH_COVARIANCE_STAMPED, RELOCALIZATION_QOS, msg)]

    def publish_map(self, object_map: ObjectMap, scale_m: float = 0.3) -> list[str]:
        """The merged object map (MergeService.global_map()) as a MarkerArray on `map`, in the
        frame of the map's own robot/session (the anchor)."""
        frame = frame_id(object_map.robot_id, object_map.session_id)
        msg = map_markers(object_map, frame, self.clock(), scale_m, self.distro)
        return [self._put(join_topic(self.namespace, MAP), RosType.MARKER_ARRAY, LATCHED_QOS,
                          msg)]

    def publish_paths(self, poses_by_session: Mapping[str, Mapping[int, np.ndarray]],
                      anchor: str) -> list[str]:
        """Each session's merged trajectory as a Path on `paths/{robot}/{session}` (names made
        ROS tokens: name_token), frame = the anchor session ("robot/session").
        `poses_by_session`: "robot/session" -> keyframe -> (4, 4) pose in the anchor frame, as
        MergeService.keyframe_poses() returns it."""
        a_robot, _, a_session = anchor.partition("/")
        return self._publish_paths(poses_by_session, lambda _: frame_id(a_robot, a_session))

    def publish_session_paths(self, poses_by_session: Mapping[str, Mapping[int, np.ndarray]]
                              ) -> list[str]:
        """Trajectories of sessions no factor joins to the anchor yet, each in its own frame
        (frame = the session, "robot/session": its keyframe 0), on the same `paths/{robot}/
        {session}` topic the anchor-frame path takes once it is joined (docs/ros2.md).
        `poses_by_session`: "robot/session" -> keyframe -> (4, 4) pose in that session's frame."""
        return self._publish_paths(poses_by_session, lambda name: frame_id(*name.split("/", 1)))

    def _publish_paths(self, poses_by_session: Mapping[str, Mapping[int, np.ndarray]],
                       frame_of: Callable[[str], str]) -> list[str]:
        t_s = self.clock()
        out = []
        for name, poses in sorted(poses_by_session.items()):
            if not poses:
                continue
            robot, _, session = name.partition("/")
            topic = join_topic(self.namespace, PATHS, name_token(robot), name_token(session))
            out.append(self._put(topic, RosType.PATH, LATCHED_QOS,
                                 path(poses, frame_of(name), t_s, self.distro)))
        return out

    # ------------------------------------------------------------------ lifecycle

    def close(self) -> None:
        """Undeclare every token and publisher (idempotent)."""
        import zenoh

        with self._lock:
            if self._closed:
                return
            self._closed = True
            entities = [e for t in self._topics.values() for e in (t.token, t.publisher)]
            entities.append(self._node_token)
        for ent in entities:
            with contextlib.suppress(zenoh.ZError):  # gone already, with the session
                ent.undeclare()

    def __enter__(self) -> Ros2Publisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = [
    "FACTORS",
    "FACTOR_LINKS",
    "FACTOR_QOS",
    "HEARTBEAT_S",
    "LATCHED_QOS",
    "MAP",
    "PATHS",
    "RELOCALIZATION",
    "RELOCALIZATION_QOS",
    "RETRACTED_FACTORS",
    "Ros2Publisher",
]
