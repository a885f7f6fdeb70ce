"""mergesvc.ros2: rmw_zenoh keys and tokens against rmw_zenoh's design doc, CDR bytes against a
CDR reader written here from the OMG CDR rules (not rosbags'), type hashes against published
RIHS01 values, and the topics end to end over real Zenoh sessions on loopback."""

from __future__ import annotations

import json
import struct
import threading
from typing import Any

import gtsam
import numpy as np
import pytest
import zenoh
from helpers import free_port, wait_for, zenoh_config

from mergesvc.core.model import Factor, FactorStatus, ObjectMap, ObjectNode, Submap, Transform
from mergesvc.errors import ConfigError
from mergesvc.fleet.config import ServiceConfig
from mergesvc.fleet.replies import RelocalizeReply
from mergesvc.fleet.service import MergeService
from mergesvc.fleet.transport import Query
from mergesvc.ros2 import Ros2Bridge, Ros2Publisher
from mergesvc.ros2.messages import (
    RosType,
    covariance_ros,
    factor_link,
    factor_pose,
    map_markers,
    path,
    quaternion_wxyz,
    serialize,
    type_hash,
)
from mergesvc.ros2.names import (
    Durability,
    Qos,
    attachment,
    dds_type_name,
    join_topic,
    name_token,
    node_token,
    parse_attachment,
    publisher_token,
    qos_keyexpr,
    topic_key,
)
from mergesvc.wire import Profile, encode_message, keys

pytest.importorskip("rosbags")

# ---------------------------------------------------------------- rmw_zenoh's documented format
# Source: ros2/rmw_zenoh docs/design.md at commit 99a6a2bd10b949052f4f12c5854825dc005e95a5,
# "Topic and Service name mapping to Zenoh key expressions": the format
# `<domain_id>/<fully_qualified_name>/<type_name>/<type_hash>` and these examples (demo_nodes_cpp):
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
DOC_CHATTER = f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
DOC_CHATTER_NS = f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
ADD_TWO_INTS_HASH = "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"
DOC_SERVICE = f"2/add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/{ADD_TWO_INTS_HASH}"
# ... and "Graph Cache": node and publisher liveliness tokens.
DOC_NODE_TOKEN = "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
DOC_PUB_TOKEN = ("@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
                 f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,")


def test_data_keys_are_rmw_zenohs_documented_keys() -> None:
    assert topic_key(0, "/chatter", "std_msgs/msg/String", STRING_HASH) == DOC_CHATTER
    assert topic_key(0, "/robot1/chatter", "std_msgs/msg/String", STRING_HASH) == DOC_CHATTER_NS
    assert topic_key(2, "/add_two_ints", "example_interfaces/srv/AddTwoInts",
                     ADD_TWO_INTS_HASH) == DOC_SERVICE
    assert dds_type_name("geometry_msgs/msg/PoseWithCovarianceStamped") == (
        "geometry_msgs::msg::dds_::PoseWithCovarianceStamped_")
    for bad in ["chatter", "/a//b", "/1abc", "/a/", "/a b"]:
        with pytest.raises(ConfigError):
            topic_key(0, bad, "std_msgs/msg/String", STRING_HASH)
    with pytest.raises(ConfigError):
        topic_key(0, "/a", "std_msgs/msg/String", "RIHS01_xyz")


def test_liveliness_tokens_are_rmw_zenohs_documented_tokens() -> None:
    assert node_token(2, "aac3178e146ba6f1fc6e6a4085e77f21", 0, "/", "listener") == (
        DOC_NODE_TOKEN)
    assert publisher_token(2, "8b20917502ee955ac4476e0266340d5c", 0, 10, "/", "talker",
                           "/chatter", "std_msgs/msg/String", STRING_HASH,
                           Qos(depth=7)) == DOC_PUB_TOKEN
    # a namespace is mangled in the token ("/" -> "%"), the data key keeps its slashes
    tok = publisher_token(0, "ab", 3, 4, "/mergesvc", "merge_service", "/mergesvc/factors",
                          "std_msgs/msg/String", STRING_HASH, Qos())
    assert tok.split("/")[5:10] == ["MP", "%", "%mergesvc", "merge_service", "%mergesvc%factors"]


def test_qos_chunk_leaves_rmw_zenohs_defaults_empty() -> None:
    # defaults (qos.cpp): reliable, volatile, keep_last, depth 42 -> every field empty
    assert qos_keyexpr(Qos(depth=42)) == "::,:,:,:,,"
    assert qos_keyexpr(Qos(depth=10)) == "::,10:,:,:,,"  # design.md's listener example
    # rmw_qos_durability_policy_e: TRANSIENT_LOCAL = 1
    assert qos_keyexpr(Qos(durability=Durability.TRANSIENT_LOCAL, depth=1)) == ":1:,1:,:,:,,"


def test_attachment_is_what_zenoh_ext_serializes_for_int64_int64_and_16_bytes() -> None:
    from zenoh.ext import Int64, z_deserialize

    gid = bytes(range(16))
    att = attachment(7, 1_700_000_000_123_456_789, gid)
    assert len(att) == 33  # 8 + 8 + 1 (length 16) + 16, as design.md's "Publishers" lists
    assert parse_attachment(att) == (7, 1_700_000_000_123_456_789, gid)
    # zenoh's own deserializer (Rust zenoh-ext) reads it as (int64, int64, bytes)
    seq, stamp, raw = z_deserialize(tuple[Int64, Int64, bytes], zenoh.ZBytes(att))
    assert (int(seq), int(stamp), raw) == (7, 1_700_000_000_123_456_789, gid)


def test_ros_names_from_mergesvc_names() -> None:
    assert name_token("auv-1") == "auv_1"
    assert name_token("0s") == "_0s"
    assert name_token("a..b") == "a_b"
    assert join_topic("/mergesvc", "paths", "auv_1", "s0") == "/mergesvc/paths/auv_1/s0"
    assert join_topic("/", "map") == "/map"


# ---------------------------------------------------------------- type hashes
# Published RIHS01 values (REP-2016, as rosidl computes them):
# - std_msgs/msg/String: rmw_zenoh docs/design.md (above), computed by rosidl;
# - std_msgs/msg/Header, geometry_msgs/msg/PoseStamped, nav_msgs/msg/Odometry: ZettaScaleLabs/ros-z
#   crates/ros-z-codegen/tests/hash_regression.rs (commit 9bb63050), "verified against
#   rmw_zenoh_cpp interop tests";
# - geometry_msgs/msg/PoseWithCovarianceStamped, nav_msgs/msg/Path: ZettaScaleLabs/ros-z
#   crates/ros-z-msgs/python/ros_z_msgs_py/types/{geometry,nav}_msgs.py (commit 59d2ce8e);
# - visualization_msgs/msg/MarkerArray: the same value appears in independent public ROS 2
#   clients (an Elixir client's MarkerArray module and a C generated_types.h); no ros2/ or ros-z
#   file with it was found. Its parts (Header, Pose, ...) are covered by the rows above.
PUBLISHED_HASHES = {
    "std_msgs/msg/String": STRING_HASH,
    "std_msgs/msg/Header":
        "RIHS01_f49fb3ae2cf070f793645ff749683ac6b06203e41c891e17701b1cb597ce6a01",
    "geometry_msgs/msg/PoseStamped":
        "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8",
    "nav_msgs/msg/Odometry":
        "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0",
    "geometry_msgs/msg/PoseWithCovarianceStamped":
        "RIHS01_26432f9803e43727d3c8f668d1fdb3c630f548af631e2f4e31382371bfea3b6e",
    "nav_msgs/msg/Path":
        "RIHS01_1957a5bb3cee5da65c4e52e52b65a93df227efce4c20f8458b36e73066ca334b",
    "visualization_msgs/msg/MarkerArray":
        "RIHS01_86cb8800b6fb05b5eff1abd7a56f62a5641d3ae9a1c29e78e67e704f1d067dcf",
}


@pytest.mark.parametrize("distro", ["ROS2_JAZZY", "ROS2_KILTED"])
@pytest.mark.parametrize("ros_type", sorted(PUBLISHED_HASHES))
def test_type_hashes_are_the_published_values(ros_type: str, distro: str) -> None:
    assert type_hash(ros_type, distro) == PUBLISHED_HASHES[ros_type]


def test_every_published_type_has_a_checked_hash() -> None:
    assert {t.value for t in RosType} <= set(PUBLISHED_HASHES)


def test_an_unknown_distro_is_a_config_error() -> None:
    with pytest.raises(ConfigError):
        type_hash("std_msgs/msg/String", "ROS2_NOPE")


# ---------------------------------------------------------------- an independent CDR reader
class CdrReader:
    """XCDR1 little endian as ROS 2 writes it: a 4-byte encapsulation header (00 01 = CDR_LE),
    then each primitive aligned to its size counted from the end of that header; strings are a
    uint32 length including the NUL, the bytes, the NUL; sequences a uint32 count first."""

    def __init__(self, data: bytes) -> None:
        assert data[:4] == b"\x00\x01\x00\x00", data[:4]
        self.body, self.pos = data[4:], 0

    def _prim(self, fmt: str, size: int) -> Any:
        self.pos += -self.pos % size
        (v,) = struct.unpack_from("<" + fmt, self.body, self.pos)
        self.pos += size
        return v

    def i32(self) -> int:
        return self._prim("i", 4)

    def u32(self) -> int:
        return self._prim("I", 4)

    def f32(self) -> float:
        return self._prim("f", 4)

    def f64(self) -> float:
        return self._prim("d", 8)

    def u8(self) -> int:
        return self._prim("B", 1)

    def string(self) -> str:
        n = self.u32()
        raw = self.body[self.pos:self.pos + n]
        self.pos += n
        assert raw[-1:] == b"\x00"
        return raw[:-1].decode()

    def f64s(self, n: int) -> list[float]:
        return [self.f64() for _ in range(n)]

    def header(self) -> tuple[int, int, str]:
        return self.i32(), self.u32(), self.string()

    def pose(self) -> tuple[list[float], list[float]]:
        return self.f64s(3), self.f64s(4)  # position xyz, orientation xyzw

    def done(self) -> bool:
        return self.pos == len(self.body)


def _factor(**update: Any) -> Factor:
    q = gtsam.Rot3.RzRyRx(0.3, -0.2, 1.1).toQuaternion()
    A = np.random.default_rng(3).normal(size=(6, 6))
    fields = dict(
        factor_id="a-s0-b-s1-7", robot_a="auv1", session_a="s0", robot_b="auv2",
        session_b="s1",
        T_a_b=Transform(translation=(1.5, -2.0, 0.25),
                        quaternion_wxyz=(q.w(), q.x(), q.y(), q.z())),
        covariance=(A @ A.T + 6 * np.eye(6)).tolist(), keyframe_a=3, keyframe_b=12,
        status=FactorStatus.ACCEPTED,
    )
    fields.update(update)
    return Factor(**fields)


def _check_pose_with_covariance(r: CdrReader, factor: Factor) -> None:
    position, xyzw = r.pose()
    assert position == list(factor.T_a_b.translation)
    w, x, y, z = factor.T_a_b.quaternion_wxyz
    assert xyzw == [x, y, z, w]
    cov = np.array(r.f64s(36)).reshape(6, 6)
    R = gtsam.Rot3.Quaternion(w, x, y, z).matrix()
    assert np.allclose(cov, np.array(covariance_ros(factor.covariance, R)).reshape(6, 6))


def test_pose_with_covariance_stamped_cdr_reads_back_independently() -> None:
    f = _factor()
    data = serialize(factor_pose(f, 1_700_000_000.25), RosType.POSE_WITH_COVARIANCE_STAMPED.value)
    r = CdrReader(data)
    assert r.header() == (1_700_000_000, 250_000_000, "auv1/s0/kf3")
    _check_pose_with_covariance(r, f)
    assert r.done()


def test_odometry_cdr_names_both_frames() -> None:
    f = _factor(keyframe_a=None, keyframe_b=None)  # a frame-level factor: the session frames
    r = CdrReader(serialize(factor_link(f, 5.0), RosType.ODOMETRY.value))
    assert r.header() == (5, 0, "auv1/s0")
    assert r.string() == "auv2/s1"
    _check_pose_with_covariance(r, f)
    assert r.f64s(6) == [0.0] * 6  # twist unknown
    assert r.f64s(36) == [-1.0] + [0.0] * 35
    assert r.done()


def test_path_cdr_reads_back_independently() -> None:
    rng = np.random.default_rng(1)
    poses = {}
    for k in (0, 2, 5):
        T = np.eye(4)
        T[:3, :3] = gtsam.Rot3.Expmap(rng.normal(size=3)).matrix()
        T[:3, 3] = rng.normal(size=3)
        poses[k] = T
    r = CdrReader(serialize(path(poses, "auv1/s0", 3.5), RosType.PATH.value))
    assert r.header() == (3, 500_000_000, "auv1/s0")
    assert r.u32() == 3
    for k in (0, 2, 5):
        assert r.header() == (3, 500_000_000, "auv1/s0")
        position, (x, y, z, w) = r.pose()
        assert np.allclose(position, poses[k][:3, 3])
        assert np.allclose(gtsam.Rot3.Quaternion(w, x, y, z).matrix(), poses[k][:3, :3])
    assert r.done()


def _read_marker(r: CdrReader) -> dict[str, Any]:
    m: dict[str, Any] = {"header": r.header(), "ns": r.string(), "id": r.i32(),
                         "type": r.i32(), "action": r.i32(), "pose": r.pose(),
                         "scale": r.f64s(3), "color": [r.f32() for _ in range(4)],
                         "lifetime": (r.i32(), r.u32()), "frame_locked": r.u8()}
    m["points"] = [r.f64s(3) for _ in range(r.u32())]
    m["colors"] = [[r.f32() for _ in range(4)] for _ in range(r.u32())]
    m["texture_resource"] = r.string()
    m["texture"] = (r.header(), r.string(), [r.u8() for _ in range(r.u32())])
    m["uv"] = [(r.f32(), r.f32()) for _ in range(r.u32())]
    m["text"] = r.string()
    m["mesh_resource"] = r.string()
    m["mesh_file"] = (r.string(), [r.u8() for _ in range(r.u32())])
    m["mesh_use_embedded_materials"] = r.u8()
    return m


def test_marker_array_cdr_reads_back_independently() -> None:
    objs = [ObjectNode(id="auv1/s0/o1", position=(1.0, 2.0, 3.0), embedding=[1.0, 0.0],
                       variance=0.1, label="rock"),
            ObjectNode(id="auv2/s1/o9", position=(-1.0, 0.5, 2.0), embedding=[0.0, 1.0],
                       variance=0.1)]
    gmap = ObjectMap(robot_id="auv1", session_id="s0", objects=objs)
    r = CdrReader(serialize(map_markers(gmap, "auv1/s0", 2.0, scale_m=0.4),
                            RosType.MARKER_ARRAY.value))
    markers = [_read_marker(r) for _ in range(r.u32())]
    assert r.done()
    assert [(m["ns"], m["id"], m["type"], m["action"]) for m in markers] == [
        ("", 0, 2, 3),  # DELETEALL
        ("objects", 0, 2, 0), ("labels", 0, 9, 0),  # SPHERE, TEXT_VIEW_FACING
        ("objects", 1, 2, 0),
    ]
    assert markers[1]["pose"][0] == [1.0, 2.0, 3.0]
    assert markers[3]["pose"][0] == [-1.0, 0.5, 2.0]
    assert markers[1]["scale"] == [0.4] * 3 and markers[2]["text"] == "rock"
    assert markers[1]["color"] != markers[3]["color"]  # coloured by robot
    assert all(m["header"] == (2, 0, "auv1/s0") for m in markers)


def test_covariance_in_ros_order_and_parent_axes_matches_a_numerical_jacobian() -> None:
    """C_ros = J C J^T with J the derivative of (position, fixed-axis rotation) in the parent
    frame with respect to GTSAM's tangent (rot, trans), taken by central differences."""
    rng = np.random.default_rng(7)
    T = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3)), rng.normal(size=3))
    A = rng.normal(size=(6, 6))
    C = A @ A.T + np.eye(6)
    eps = 1e-6
    J = np.zeros((6, 6))
    for i in range(6):
        d = np.zeros(6)
        d[i] = eps
        Tp, Tm = T.retract(d), T.retract(-d)
        J[:3, i] = (Tp.translation() - Tm.translation()) / (2 * eps)
        J[3:, i] = gtsam.Rot3.Logmap(Tp.rotation().compose(Tm.rotation().inverse())) / (2 * eps)
    expected = J @ C @ J.T
    got = np.array(covariance_ros(C, T.rotation().matrix())).reshape(6, 6)
    assert np.allclose(got, expected, rtol=1e-5, atol=1e-6)
    # with the identity rotation it is the plain reordering: trans block first
    got_identity = np.array(covariance_ros(np.diag([1.0, 2, 3, 4, 5, 6]), np.eye(3)))
    assert got_identity.reshape(6, 6).diagonal().tolist() == [4, 5, 6, 1, 2, 3]


def test_quaternion_round_trip() -> None:
    R = gtsam.Rot3.RzRyRx(0.4, 0.1, -2.0).matrix()
    w, x, y, z = quaternion_wxyz(R)
    assert w >= 0 and np.allclose(gtsam.Rot3.Quaternion(w, x, y, z).matrix(), R)


# ---------------------------------------------------------------- end to end over Zenoh
class Samples:
    """(key, payload, attachment) of every sample a subscriber got."""

    def __init__(self) -> None:
        self.items: list[tuple[str, bytes, bytes | None]] = []
        self._lock = threading.Lock()

    def __call__(self, sample: zenoh.Sample) -> None:
        att = sample.attachment.to_bytes() if sample.attachment is not None else None
        with self._lock:
            self.items.append((str(sample.key_expr), sample.payload.to_bytes(), att))

    def on(self, key: str) -> list[tuple[bytes, bytes | None]]:
        with self._lock:
            return [(p, a) for k, p, a in self.items if k == key]


@pytest.fixture
def two_sessions():
    """A peer listening on loopback (mergesvc's side) and one connected to it (the ROS side)."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    with zenoh.open(zenoh_config("peer", listen=ep)) as ours, \
            zenoh.open(zenoh_config("peer", connect=ep)) as ros:
        yield ours, ros


def _tokens(session: zenoh.Session) -> set[str]:
    return {str(r.ok.key_expr) for r in session.liveliness().get("@ros2_lv/0/**", timeout=2.0)
            if r.ok is not None}


def test_a_factor_arrives_as_cdr_on_the_rmw_zenoh_key_with_tokens(two_sessions) -> None:
    ours, ros = two_sessions
    got = Samples()
    sub = ros.declare_subscriber("0/**", got)
    factors_key = topic_key(0, "/mergesvc/factors", RosType.POSE_WITH_COVARIANCE_STAMPED.value,
                            PUBLISHED_HASHES["geometry_msgs/msg/PoseWithCovarianceStamped"])
    try:
        with Ros2Publisher(ours, clock=lambda: 42.0) as pub:
            n = [0]

            def publish_and_check() -> bool:  # until the subscription has reached our side
                n[0] += 1
                pub.publish_factor(_factor(factor_id=f"f{n[0]}"))
                return bool(got.on(factors_key))

            assert wait_for(publish_and_check, timeout_s=10.0, step_s=0.1)
            payload, att = got.on(factors_key)[0]
            r = CdrReader(payload)
            assert r.header() == (42, 0, "auv1/s0/kf3")
            _check_pose_with_covariance(r, _factor())
            _, stamp_ns, gid = parse_attachment(att)
            assert stamp_ns > 0 and len(gid) == 16
            seqs = [parse_attachment(a)[0] for _, a in got.on(factors_key)]
            assert seqs == sorted(set(seqs)) and seqs[0] >= 1  # per publisher, increasing
            assert {parse_attachment(a)[2] for _, a in got.on(factors_key)} == {gid}
            assert pub.topics["/mergesvc/factors"] == factors_key

            zid = str(ours.info.zid())
            node = f"@ros2_lv/0/{zid}/{pub.node_id}/{pub.node_id}/NN/%/%mergesvc/merge_service"
            pose_topic = ("/%mergesvc%factors/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/"
                          + PUBLISHED_HASHES["geometry_msgs/msg/PoseWithCovarianceStamped"]
                          + "/:1:,1000:,:,:,,")
            links = "%mergesvc%factor_links/nav_msgs::msg::dds_::Odometry_/"

            def declared(tokens: set[str]) -> bool:
                pub_tokens = [t for t in tokens if "/MP/" in t]
                return (node in tokens and any(t.endswith(pose_topic) for t in pub_tokens)
                        and any(links in t for t in pub_tokens))

            # the tokens reach a late reader (liveliness propagation is asynchronous)
            assert wait_for(lambda: declared(_tokens(ros)), timeout_s=10.0), _tokens(ros)
        # closed: the tokens are gone (ros2 topic list forgets the topics)
        assert wait_for(lambda: not _tokens(ros), timeout_s=10.0)
    finally:
        sub.undeclare()


def _submap(rng: np.random.Generator, robot: str = "auv1", session: str = "s0") -> Submap:
    objects = [ObjectNode(id=f"o{i}", position=tuple(rng.uniform(-6, 6, size=3).tolist()),
                          embedding=rng.normal(size=16).tolist(), variance=0.01)
               for i in range(10)]
    return Submap(robot_id=robot, session_id=session, objects=objects, seq=0,
                  up=(0.0, 0.0, 1.0))


def test_the_bridge_republishes_service_factors_once_the_map_and_relocalization(
        two_sessions) -> None:
    ours, ros = two_sessions
    got = Samples()
    sub = ros.declare_subscriber("0/**", got)
    service = MergeService(ServiceConfig(store=":memory:", fleet="f1"), None)
    root = keys.fleet_root("f1")
    sub_a = _submap(np.random.default_rng(0))
    service.ingest(sub_a)
    bridge = Ros2Bridge(ours, fleet="f1", service=service, period_s=0.2, node_name="svc")
    try:
        bridge.start()
        factor = _factor(robot_a="auv1", robot_b="auv2")
        blob = encode_message(factor, Profile.FULL, "mergesvc", 0)

        def send_and_check() -> bool:  # as the service sends it: to both robots
            for robot in ("auv1", "auv2"):
                ours.put(keys.factor_key(root, robot, factor.factor_id), blob)
            return bridge.factors_published > 0

        assert wait_for(send_and_check, timeout_s=10.0)
        assert wait_for(lambda: "/mergesvc/map" in bridge.publisher.topics, timeout_s=10.0)
        map_key = bridge.publisher.topics["/mergesvc/map"]
        assert wait_for(lambda: bool(got.on(map_key)), timeout_s=10.0)
        r = CdrReader(got.on(map_key)[-1][0])
        markers = [_read_marker(r) for _ in range(r.u32())]
        assert len([m for m in markers if m["ns"] == "objects"]) == len(sub_a.objects)
        assert markers[1]["header"][2] == "auv1/s0"  # the anchor's frame

        # every sample for one (id, status) was republished once
        for robot in ("auv1", "auv2"):
            ours.put(keys.factor_key(root, robot, factor.factor_id), blob)
        retracted = factor.model_copy(update={"status": FactorStatus.RETRACTED})
        ours.put(keys.factor_key(root, "auv1", factor.factor_id),
                 encode_message(retracted, Profile.FULL, "mergesvc", 1))
        # one session's puts arrive in order: once the retraction is through, so are the copies
        assert wait_for(lambda: "/mergesvc/retracted_factors" in bridge.publisher.topics,
                        timeout_s=10.0)
        assert bridge.factors_published == 2  # the accepted factor once, its retraction once

        # a relocalization answer given by the service is published too
        reply = service.relocalize(sub_a.model_copy(update={"session_id": "s9"}))
        assert isinstance(reply, RelocalizeReply) and reply.localized, reply
        reloc_key = bridge.publisher.topics["/mergesvc/relocalization"]
        assert wait_for(lambda: bool(got.on(reloc_key)), timeout_s=10.0)
        r = CdrReader(got.on(reloc_key)[-1][0])
        assert r.header()[2] == "auv1/s0"
        position, _ = r.pose()
        assert np.allclose(position, reply.T_anchor_session.translation)
        # and one asked over Zenoh (the relocalize queryable's handler) as well
        before = len(got.on(reloc_key))
        asked = Query(keys.relocalize_key(root), payload=encode_message(
            sub_a.model_copy(update={"session_id": "s8"}), Profile.FULL, "auv1", 1))
        answer = json.loads(service._on_relocalize(asked).payload)
        assert answer["localized"], answer
        assert wait_for(lambda: len(got.on(reloc_key)) > before, timeout_s=10.0)
    finally:
        bridge.close()
        sub.undeclare()
        service.close()
    assert "relocalize" not in vars(service)  # unwrapped


def test_paths_are_published_per_session(two_sessions) -> None:
    ours, ros = two_sessions
    got = Samples()
    sub = ros.declare_subscriber("0/**", got)
    try:
        with Ros2Publisher(ours, namespace="/fleet") as pub:
            poses = {"auv-1/s0": {0: np.eye(4), 1: np.eye(4)}, "auv2/s1": {0: np.eye(4)}}

            def publish_and_check() -> bool:
                pub.publish_paths(poses, anchor="auv-1/s0")
                return all(got.on(k) for k in pub.topics.values())

            assert wait_for(publish_and_check, timeout_s=10.0)
            assert set(pub.topics) == {"/fleet/paths/auv_1/s0", "/fleet/paths/auv2/s1"}
            r = CdrReader(got.on(pub.topics["/fleet/paths/auv2/s1"])[0][0])
            assert r.header()[2] == "auv-1/s0" and r.u32() == 1
    finally:
        sub.undeclare()


def test_a_late_transient_local_subscriber_gets_the_latched_map(two_sessions) -> None:
    """The map topic is TRANSIENT_LOCAL (depth 1) like a latched ROS topic: a subscription made
    after the publication still receives it, the way rmw_zenoh's transient-local subscriptions
    query the publisher's cache (zenoh.ext advanced subscriber with history)."""
    from zenoh.ext import HistoryConfig, declare_advanced_subscriber

    ours, ros = two_sessions
    gmap = ObjectMap(robot_id="auv1", session_id="s0", objects=[
        ObjectNode(id="auv1/s0/o1", position=(1.0, 2.0, 3.0), embedding=[1.0], variance=0.1)])
    with Ros2Publisher(ours) as pub:
        pub.publish_map(gmap)
        got = Samples()
        late = declare_advanced_subscriber(
            ros, "0/mergesvc/map/**", got,
            history=HistoryConfig(detect_late_publishers=True))
        try:
            key = pub.topics["/mergesvc/map"]
            assert wait_for(lambda: bool(got.on(key)), timeout_s=10.0)
            r = CdrReader(got.on(key)[0][0])
            assert r.u32() == 2  # DELETEALL + one sphere
        finally:
            late.undeclare()


def test_a_vehicle_side_bridge_uses_the_status_queryable_and_its_own_factors(
        two_sessions) -> None:
    """Without a service object (`agent --ros2`): paths from the status queryable's
    keyframe_poses (its JSON as README documents it), factors of the given robots only."""
    ours, ros = two_sessions
    root = keys.fleet_root("f1")
    T1 = np.eye(4)
    T1[:3, 3] = (1.0, 2.0, 0.5)
    status = {"fleet": "f1", "anchor": "auv1/s0",
              "keyframe_poses": {"auv1/s0": {"0": np.eye(4).tolist(), "1": T1.tolist()}}}

    def answer(query: zenoh.Query) -> None:
        with query:
            query.reply(query.key_expr, json.dumps(status).encode())

    queryable = ours.declare_queryable(keys.status_key(root), answer)
    got = Samples()
    sub = ours.declare_subscriber("0/**", got)
    bridge = Ros2Bridge(ros, fleet="f1", robots=["auv1"], period_s=0.2, node_name="agent",
                        namespace="/mergesvc/auv1")
    try:
        bridge.start()
        assert wait_for(lambda: "/mergesvc/auv1/paths/auv1/s0" in bridge.publisher.topics,
                        timeout_s=10.0)
        key = bridge.publisher.topics["/mergesvc/auv1/paths/auv1/s0"]
        assert wait_for(lambda: bool(got.on(key)), timeout_s=10.0)
        r = CdrReader(got.on(key)[-1][0])
        assert r.header()[2] == "auv1/s0" and r.u32() == 2
        r.header()
        r.pose()
        r.header()
        assert r.pose()[0] == [1.0, 2.0, 0.5]

        mine = _factor(factor_id="mine", robot_a="auv1", robot_b="auv2")
        other = _factor(factor_id="other", robot_a="auv3", robot_b="auv2")
        ours.put(keys.factor_key(root, "auv3", "other"),
                 encode_message(other, Profile.FULL, "mergesvc", 0))
        ours.put(keys.factor_key(root, "auv1", "mine"),
                 encode_message(mine, Profile.FULL, "mergesvc", 1))
        assert wait_for(lambda: "/mergesvc/auv1/factors" in bridge.publisher.topics,
                        timeout_s=10.0)
        factors_key = bridge.publisher.topics["/mergesvc/auv1/factors"]

        def frames() -> list[str]:
            return [CdrReader(p).header()[2] for p, _ in got.on(factors_key)]

        # in order: had auv3's factor been taken, its sample would come before auv1's
        assert wait_for(lambda: "auv1/s0/kf3" in frames(), timeout_s=10.0)
        assert frames() == ["auv1/s0/kf3"] and bridge.factors_published == 1
    finally:
        bridge.close()
        sub.undeclare()
        queryable.undeclare()


def test_a_session_not_joined_to_the_anchor_has_its_path_in_its_own_frame(two_sessions) -> None:
    """serve --ros2: auv1 and auv2 joined by a factor (paths in the anchor frame), auv3 seen by
    nobody else: its path is published too, in its own frame (docs/ros2.md)."""
    ours, ros = two_sessions
    got = Samples()
    sub = ros.declare_subscriber("0/**", got)
    service = MergeService(ServiceConfig(store=":memory:", fleet="f2"), None)
    sub_a = _submap(np.random.default_rng(0))
    service.ingest(sub_a)
    service.ingest(sub_a.model_copy(update={"robot_id": "auv2"}))
    service.ingest(_submap(np.random.default_rng(7), robot="auv3"))
    assert service.factors and set(service.keyframe_poses()) == {"auv1/s0", "auv2/s0"}
    bridge = Ros2Bridge(ours, fleet="f2", service=service, period_s=0.2, node_name="svc")
    try:
        bridge.start()
        topics = {f"/mergesvc/paths/{r}/s0" for r in ("auv1", "auv2", "auv3")}
        assert wait_for(lambda: topics <= set(bridge.publisher.topics), timeout_s=10.0)
        frames = {}
        for t in topics:
            key = bridge.publisher.topics[t]
            assert wait_for(lambda key=key: bool(got.on(key)), timeout_s=10.0)
            frames[t.split("/")[3]] = CdrReader(got.on(key)[-1][0]).header()[2]
        assert frames == {"auv1": "auv1/s0", "auv2": "auv1/s0", "auv3": "auv3/s0"}
    finally:
        bridge.close()
        sub.undeclare()
        service.close()


def test_a_vehicle_side_bridge_says_once_why_an_unjoined_session_has_no_path(
        two_sessions, caplog: pytest.LogCaptureFixture) -> None:
    ours, ros = two_sessions
    root = keys.fleet_root("f3")
    status = {"fleet": "f3", "anchor": "auv1/s0", "frames": {"auv1/s0": 4, "auv3/s0": 5},
              "keyframe_poses": {"auv1/s0": {"0": np.eye(4).tolist()}}}

    def answer(query: zenoh.Query) -> None:
        with query:
            query.reply(query.key_expr, json.dumps(status).encode())

    queryable = ours.declare_queryable(keys.status_key(root), answer)
    bridge = Ros2Bridge(ros, fleet="f3", robots=["auv1"], period_s=0.1, node_name="agent")
    try:
        def notes() -> list[str]:
            return [r.getMessage() for r in caplog.records if "not joined" in r.getMessage()]

        with caplog.at_level("WARNING", logger="mergesvc.ros2.bridge"):
            # the queryable reaches the bridge's session asynchronously: refresh until it answers
            assert wait_for(lambda: bridge.refresh() is not None and bool(notes()), timeout_s=10.0)
            for _ in range(3):
                bridge.refresh()
        assert len(notes()) == 1 and "auv3/s0" in notes()[0]
        assert set(bridge.publisher.topics) >= {"/mergesvc/paths/auv1/s0"}
        assert "/mergesvc/paths/auv3/s0" not in bridge.publisher.topics
    finally:
        bridge.close()
        queryable.undeclare()
