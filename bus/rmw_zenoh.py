"""ROS 2 over Zenoh in rmw_zenoh's format: key expressions, liveliness tokens, GIDs and attachments, so a
followbus process is a ROS 2 node to ``ros2 topic echo`` / ``ros2 node list`` on a machine running rmw_zenoh,
with no bridge process between them.

From ros2/rmw_zenoh (docs/design.md; rmw_zenoh_cpp/src/detail/liveliness_utils.cpp, attachment_helpers.cpp,
rmw_publisher_data.cpp, qos.cpp), checked against the examples of its design document in tests/test_ros2.py:

- a topic's key: ``<domain_id>/<fully qualified name without its leading and trailing '/'>/<DDS type name>/
  <RIHS01 type hash>``, e.g. ``0/cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_9c45...``;
- liveliness tokens: ``@ros2_lv/<domain>/<session zid>/<node id>/<node id>/NN/<enclave>/<namespace>/<node>`` for a
  node, ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/MP|MS/<enclave>/<namespace>/<node>/<topic>/<type>/
  <hash>/<qos>`` for a publisher or subscription; names mangled (``/`` -> ``%``), the QoS written field by field
  where it differs from rmw_zenoh's default (reliable, volatile, keep last 42, infinite times);
- an entity's GID: XXH3-128 of its liveliness key, low 64 bits then high 64 bits, little-endian;
- each put's attachment, zenoh's own serialisation (zenoh.ext): sequence number (int64, from 1), source
  timestamp (int64 ns since the epoch), GID (16 bytes, length-prefixed): 33 bytes;
- payloads: CDR (bus/ros2.py).
"""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import xxhash
import zenoh
from zenoh import ext as zext

from . import ros2

ADMIN_SPACE = "@ros2_lv"
NODE, PUBLISHER, SUBSCRIPTION = "NN", "MP", "MS"
# rmw/types.h enums
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2


@dataclass(frozen=True)
class Qos:
    """The QoS parts a token carries (deadline, lifespan and liveliness stay rmw_zenoh's defaults here)."""

    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST
    depth: int = 10  # rclcpp's usual depth (rmw_zenoh's own default is 42)


RMW_ZENOH_DEFAULT_QOS = Qos(depth=42)
SENSOR_QOS = Qos(reliability=BEST_EFFORT, depth=5)  # rclcpp's SensorDataQoS


def qos_keyexpr(qos: Qos) -> str:
    """rmw_zenoh's compact QoS: ``<rel>:<dur>:<hist>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:<liveliness>,<s>,
    <ns>``, each field empty where it equals the default (so the defaults give ``::,:,:,:,,``)."""
    d = RMW_ZENOH_DEFAULT_QOS

    def field(value: int, default: int) -> str:
        return "" if value == default else str(value)

    return (f"{field(qos.reliability, d.reliability)}:{field(qos.durability, d.durability)}:"
            f"{field(qos.history, d.history)},{field(qos.depth, d.depth)}:,:,:,,")


def mangle(name: str) -> str:
    return name.replace("/", "%")


def fully_qualified(topic: str, namespace: str = "/") -> str:
    """``cmd_vel`` in ``/robot`` -> ``/robot/cmd_vel``; an absolute topic stays as it is."""
    if topic.startswith("/"):
        return topic
    return f"{namespace.rstrip('/')}/{topic}"


def topic_keyexpr(domain_id: int, topic: str, type_name: str) -> str:
    return f"{domain_id}/{topic.strip('/')}/{ros2.dds_type_name(type_name)}/{ros2.type_hash(type_name)}"


def node_token(domain_id: int, zid: str, node_id: int, node_name: str, namespace: str = "/",
               enclave: str = "/") -> str:
    node = f"{mangle(enclave)}/{mangle(namespace)}/{node_name}"
    return f"{ADMIN_SPACE}/{domain_id}/{zid}/{node_id}/{node_id}/{NODE}/{node}"


def entity_token(domain_id: int, zid: str, node_id: int, entity_id: int, kind: str, node_name: str, topic: str,
                 type_name: str, qos: Qos, namespace: str = "/", enclave: str = "/") -> str:
    node = f"{mangle(enclave)}/{mangle(namespace)}/{node_name}"
    return (f"{ADMIN_SPACE}/{domain_id}/{zid}/{node_id}/{entity_id}/{kind}/{node}/{mangle(topic)}/"
            f"{ros2.dds_type_name(type_name)}/{ros2.type_hash(type_name)}/{qos_keyexpr(qos)}")


def gid(token: str) -> bytes:
    """The entity's 16-byte GID: XXH3-128 of its liveliness key, low then high 64 bits, little-endian."""
    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(16, "little")


def attachment(sequence_number: int, source_timestamp_ns: int, source_gid: bytes) -> bytes:
    return zext.z_serialize((zext.Int64(sequence_number), zext.Int64(source_timestamp_ns),
                             bytes(source_gid))).to_bytes()


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp ns, GID); ValueError for anything else."""
    try:
        seq, stamp, source = zext.z_deserialize(tuple[zext.Int64, zext.Int64, bytes], zenoh.ZBytes(data))
    except zext.ZDeserializeError as exc:
        raise ValueError(f"not an rmw_zenoh attachment: {exc}") from None
    if len(source) != 16:
        raise ValueError(f"not an rmw_zenoh attachment: a GID of {len(source)} bytes")
    return int(seq), int(stamp), bytes(source)


# --- a ROS 2 node on a Zenoh session -------------------------------------------------------------------

class Ros2Node:
    """A ROS 2 node (its NN token) on a Zenoh session, making publishers and subscriptions that ROS 2 nodes on
    rmw_zenoh see and talk to. Entity ids count from the node's, as an rmw_zenoh context numbers them."""

    def __init__(self, session: zenoh.Session, name: str, namespace: str = "/", domain_id: int = 0):
        self.session, self.name, self.namespace, self.domain_id = session, name, namespace, domain_id
        self.zid = str(session.info.zid())
        self._ids = itertools.count()
        self.node_id = next(self._ids)
        self._entities: list[Any] = []
        self._token = session.liveliness().declare_token(node_token(domain_id, self.zid, self.node_id, name,
                                                                    namespace))

    def _entity_token(self, kind: str, topic: str, type_name: str, qos: Qos) -> str:
        return entity_token(self.domain_id, self.zid, self.node_id, next(self._ids), kind, self.name,
                            fully_qualified(topic, self.namespace), type_name, qos, self.namespace)

    def publisher(self, topic: str, type_name: str, qos: Qos = Qos()) -> Ros2Publisher:
        pub = Ros2Publisher(self, fully_qualified(topic, self.namespace), type_name, qos)
        self._entities.append(pub)
        return pub

    def subscription(self, topic: str, type_name: str, callback: Callable[[Any, int], None],
                     qos: Qos = Qos()) -> Ros2Subscription:
        sub = Ros2Subscription(self, fully_qualified(topic, self.namespace), type_name, callback, qos)
        self._entities.append(sub)
        return sub

    def close(self) -> None:
        for entity in self._entities:
            entity.close()
        self._token.undeclare()


class Ros2Publisher:
    """Puts CDR on the topic's key with rmw_zenoh's attachment; its MP token makes it discoverable."""

    def __init__(self, node: Ros2Node, topic: str, type_name: str, qos: Qos):
        self.topic, self.type_name = topic, type_name
        self.key = topic_keyexpr(node.domain_id, topic, type_name)
        self.token_key = node._entity_token(PUBLISHER, topic, type_name, qos)
        self.gid = gid(self.token_key)
        self._sequence = itertools.count(1)
        self._lock = threading.Lock()
        reliable = qos.reliability == RELIABLE
        block = reliable and qos.history == KEEP_ALL  # as rmw_zenoh: only reliable keep-all blocks
        self._pub = node.session.declare_publisher(
            self.key, encoding=zenoh.Encoding.ZENOH_BYTES,
            reliability=zenoh.Reliability.RELIABLE if reliable else zenoh.Reliability.BEST_EFFORT,
            congestion_control=zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP)
        self._token = node.session.liveliness().declare_token(self.token_key)

    @property
    def matched(self) -> bool:
        """Whether a subscriber on this topic's key is known to the session now."""
        return bool(self._pub.matching_status.matching)

    def publish(self, msg: Any) -> None:
        payload = ros2.serialize(msg, self.type_name)
        with self._lock:
            seq = next(self._sequence)
        self._pub.put(payload, attachment=attachment(seq, time.time_ns(), self.gid))

    def close(self) -> None:
        self._token.undeclare()
        self._pub.undeclare()


class Ros2Subscription:
    """Calls ``callback(message, source_timestamp_ns)`` for each CDR sample on the topic's key (0 without an
    attachment); a sample that does not decode is counted in ``errors`` and dropped."""

    def __init__(self, node: Ros2Node, topic: str, type_name: str, callback: Callable[[Any, int], None],
                 qos: Qos):
        self.topic, self.type_name, self.callback = topic, type_name, callback
        self.key = topic_keyexpr(node.domain_id, topic, type_name)
        self.token_key = node._entity_token(SUBSCRIPTION, topic, type_name, qos)
        self.received = self.errors = 0
        self._sub = node.session.declare_subscriber(self.key, self._on_sample)
        self._token = node.session.liveliness().declare_token(self.token_key)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            msg = ros2.deserialize(sample.payload.to_bytes(), self.type_name)
            stamp = parse_attachment(sample.attachment.to_bytes())[1] if sample.attachment is not None else 0
        except Exception:  # a malformed sample is counted and dropped, never raised into zenoh's thread
            self.errors += 1
            return
        self.received += 1
        self.callback(msg, stamp)

    def close(self) -> None:
        self._token.undeclare()
        self._sub.undeclare()
