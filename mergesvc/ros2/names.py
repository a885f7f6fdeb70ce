"""rmw_zenoh's names on the wire: data keys, liveliness tokens, QoS strings, sample attachments.

Written from rmw_zenoh's docs/design.md (ros2/rmw_zenoh, rolling, commit 99a6a2bd), sections
"Topic and Service name mapping to Zenoh key expressions", "Graph Cache" and "Publishers", and its
liveliness_utils.cpp (`qos_to_keyexpr`). Pure string and byte work: no Zenoh, no rosbags.
"""

from __future__ import annotations

import hashlib
import re
import struct
from dataclasses import dataclass
from enum import Enum, IntEnum

from mergesvc.errors import ConfigError

#: Prefix of every rmw_zenoh liveliness token (a Zenoh hermetic namespace: `**` never matches it).
ADMIN_SPACE = "@ros2_lv"
#: rmw_zenoh replaces each "/" of a name inside a liveliness token by this character.
SLASH_REPLACEMENT = "%"
GID_SIZE = 16
ATTACHMENT_SIZE = 8 + 8 + 1 + GID_SIZE

_TOKEN = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_TYPE = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)/(msg|srv)/([A-Za-z][A-Za-z0-9_]*)$")
_HASH = re.compile(r"^RIHS01_[0-9a-f]{64}$")


class EntityKind(str, Enum):
    """The entity field of a liveliness token."""

    NODE = "NN"
    PUBLISHER = "MP"
    SUBSCRIPTION = "MS"
    SERVICE = "SS"
    CLIENT = "SC"


class Reliability(IntEnum):
    """rmw_qos_reliability_policy_e."""

    SYSTEM_DEFAULT = 0
    RELIABLE = 1
    BEST_EFFORT = 2


class Durability(IntEnum):
    """rmw_qos_durability_policy_e."""

    SYSTEM_DEFAULT = 0
    TRANSIENT_LOCAL = 1
    VOLATILE = 2


class History(IntEnum):
    """rmw_qos_history_policy_e."""

    SYSTEM_DEFAULT = 0
    KEEP_LAST = 1
    KEEP_ALL = 2


@dataclass(frozen=True)
class Qos:
    """The QoS of a publisher, as far as mergesvc sets it (deadline, lifespan and liveliness
    stay at rmw_zenoh's defaults: infinite, infinite, automatic)."""

    reliability: Reliability = Reliability.RELIABLE
    durability: Durability = Durability.VOLATILE
    history: History = History.KEEP_LAST
    depth: int = 10

    @property
    def transient_local(self) -> bool:
        return self.durability is Durability.TRANSIENT_LOCAL


# rmw_zenoh's default QoS (qos.cpp): a field equal to it is left empty in the token.
_DEFAULT_QOS = Qos(Reliability.RELIABLE, Durability.VOLATILE, History.KEEP_LAST, 42)


def qos_keyexpr(qos: Qos) -> str:
    """The QoS chunk of a publisher's liveliness token, as rmw_zenoh's `qos_to_keyexpr` writes it:
    `reliability:durability:history,depth:deadline_s,deadline_ns:lifespan_s,lifespan_ns:
    liveliness,lease_s,lease_ns`, each field empty when it equals rmw_zenoh's default."""
    if qos.depth < 1:
        raise ConfigError(f"QoS depth must be >= 1, got {qos.depth}")

    def field(value: int, default: int) -> str:
        return "" if value == default else str(int(value))

    d = _DEFAULT_QOS
    return (f"{field(qos.reliability, d.reliability)}:{field(qos.durability, d.durability)}:"
            f"{field(qos.history, d.history)},{field(qos.depth, d.depth)}:,:,:,,")


def check_topic(name: str) -> str:
    """A fully qualified ROS 2 topic name ("/a/b"): tokens of [A-Za-z0-9_], none starting with a
    digit, no "__"; returned as is. `ConfigError` otherwise."""
    if not isinstance(name, str) or not name.startswith("/") or name.endswith("/"):
        raise ConfigError(f"invalid ROS 2 topic {name!r}: must be absolute, e.g. /mergesvc/map")
    for tok in name[1:].split("/"):
        if not _TOKEN.match(tok) or "__" in tok:
            raise ConfigError(f"invalid ROS 2 topic {name!r}: bad token {tok!r}")
    return name


def check_namespace(ns: str) -> str:
    """A ROS 2 namespace: "/" or an absolute name without a trailing "/"."""
    return ns if ns == "/" else check_topic(ns)


def name_token(value: str) -> str:
    """`value` made into one ROS 2 name token: characters outside [A-Za-z0-9_] become "_",
    runs of "_" collapse, a leading digit gets a "_" before it ("auv-1" -> "auv_1")."""
    tok = re.sub(r"_+", "_", re.sub(r"[^A-Za-z0-9_]", "_", value)) or "_"
    return "_" + tok if tok[0].isdigit() else tok


def join_topic(namespace: str, *tokens: str) -> str:
    """`namespace` + "/" + tokens, checked: join_topic("/mergesvc", "map") -> "/mergesvc/map"."""
    base = check_namespace(namespace).rstrip("/")
    return check_topic("/".join([base, *tokens]))


def dds_type_name(ros_type: str) -> str:
    """The DDS type name rmw_zenoh puts in keys: "geometry_msgs/msg/Pose" ->
    "geometry_msgs::msg::dds_::Pose_"."""
    m = _TYPE.match(ros_type)
    if not m:
        raise ConfigError(f"invalid ROS 2 type {ros_type!r}: expected pkg/msg/Name")
    pkg, kind, name = m.groups()
    return f"{pkg}::{kind}::dds_::{name}_"


def mangle(name: str) -> str:
    """A name as one liveliness-token chunk: every "/" becomes "%" ("/" alone -> "%")."""
    return name.replace("/", SLASH_REPLACEMENT)


def topic_key(domain_id: int, topic: str, ros_type: str, type_hash: str) -> str:
    """The Zenoh key of a topic's samples: `<domain_id>/<fully qualified name without its
    leading "/">/<DDS type name>/<type hash>` (design.md; the topic's inner "/" stay "/")."""
    _check_domain(domain_id)
    if not _HASH.match(type_hash):
        raise ConfigError(f"invalid type hash {type_hash!r}: expected RIHS01_ + 64 hex digits")
    return f"{domain_id}/{check_topic(topic)[1:]}/{dds_type_name(ros_type)}/{type_hash}"


def node_token(domain_id: int, zid: str, node_id: int, namespace: str, node_name: str,
               enclave: str = "/") -> str:
    """A node's liveliness token:
    `@ros2_lv/<domain>/<session id>/<node id>/<node id>/NN/<enclave>/<namespace>/<node>`."""
    _check_domain(domain_id)
    if not _TOKEN.match(node_name):
        raise ConfigError(f"invalid ROS 2 node name {node_name!r}")
    return "/".join([ADMIN_SPACE, str(domain_id), zid, str(node_id), str(node_id),
                     EntityKind.NODE.value, mangle(enclave), mangle(check_namespace(namespace)),
                     node_name])


def publisher_token(domain_id: int, zid: str, node_id: int, entity_id: int, namespace: str,
                    node_name: str, topic: str, ros_type: str, type_hash: str, qos: Qos,
                    enclave: str = "/") -> str:
    """A publisher's liveliness token: the node's chunks with `<entity id>` and `MP`, then
    `<mangled topic>/<DDS type name>/<type hash>/<qos>`."""
    node = node_token(domain_id, zid, node_id, namespace, node_name, enclave).split("/")
    node[4], node[5] = str(entity_id), EntityKind.PUBLISHER.value
    topic_key(domain_id, topic, ros_type, type_hash)  # checks topic, type and hash
    return "/".join([*node, mangle(topic), dds_type_name(ros_type), type_hash, qos_keyexpr(qos)])


def entity_gid(token: str) -> bytes:
    """16 bytes naming an entity, derived from its liveliness token. rmw_zenoh uses XXH3-128 of
    the token; receivers only compare gids for equality, so a different 128-bit hash of the same
    unique token serves (BLAKE2b, in the standard library)."""
    return hashlib.blake2b(token.encode(), digest_size=GID_SIZE).digest()


def attachment(sequence_number: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """The attachment of every sample (design.md, "Publishers"): sequence number (int64 LE),
    source timestamp in ns since the UNIX epoch (int64 LE), the gid length as one byte (16),
    the 16-byte gid: zenoh-ext's serialization of (int64, int64, uint8[16])."""
    if len(gid) != GID_SIZE:
        raise ConfigError(f"a gid has {GID_SIZE} bytes, got {len(gid)}")
    return struct.pack("<qqB", sequence_number, source_timestamp_ns, GID_SIZE) + bytes(gid)


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp ns, gid) of an attachment; `ConfigError` if it is not
    one."""
    if len(data) != ATTACHMENT_SIZE or data[16] != GID_SIZE:
        raise ConfigError(f"not an rmw_zenoh attachment ({len(data)} bytes)")
    seq, stamp = struct.unpack_from("<qq", data, 0)
    return seq, stamp, bytes(data[17:])


def _check_domain(domain_id: int) -> None:
    # ROS 2 domain ids: 0-232 are usable with DDS; rmw_zenoh takes any size_t. Keep to DDS's.
    if isinstance(domain_id, bool) or not isinstance(domain_id, int) or not 0 <= domain_id <= 232:
        raise ConfigError(f"invalid ROS_DOMAIN_ID {domain_id!r}: use 0-232")


__all__ = [
    "ADMIN_SPACE",
    "ATTACHMENT_SIZE",
    "GID_SIZE",
    "SLASH_REPLACEMENT",
    "Durability",
    "EntityKind",
    "History",
    "Qos",
    "Reliability",
    "attachment",
    "check_namespace",
    "check_topic",
    "dds_type_name",
    "entity_gid",
    "join_topic",
    "mangle",
    "name_token",
    "node_token",
    "parse_attachment",
    "publisher_token",
    "qos_keyexpr",
    "topic_key",
]
