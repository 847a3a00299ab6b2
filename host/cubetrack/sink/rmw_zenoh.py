"""rmw_zenoh's wire conventions: what a ROS 2 node using ``rmw_zenoh_cpp`` puts on Zenoh.

From ros2/rmw_zenoh (``docs/design.md``; ``liveliness_utils.cpp``, ``attachment_helpers.cpp``,
``qos.cpp``, ``rmw_publisher_data.cpp``); docs/ros2.md lists the commits read.

- **Data key**: ``<domain>/<topic without leading/trailing '/'>/<DDS type name>/<type hash>``,
  e.g. ``0/robot/pose/geometry_msgs::msg::dds_::PoseStamped_/RIHS01_10f3...``. Humble builds
  write the constant ``TypeHashNotSupported`` for the hash.
- **Attachment** (mandatory: subscribers drop samples without one), zenoh-ext serialisation of
  (int64 sequence number, int64 source timestamp in ns since the epoch, uint8[16] GID): two
  little-endian int64, the LEB128 length of the array (one byte, 16), the 16 bytes = 33 bytes.
  Sequence numbers start at 1. Humble's rmw_zenoh also uses 16-byte GIDs.
- **GID** of an entity: XXH3-128 of its liveliness key expression, low 64 bits then high 64
  bits, each little-endian (``Entity::Entity``).
- **Liveliness tokens** (the ROS graph: ``ros2 node list``, ``ros2 topic list``...):
  ``@ros2_lv/<domain>/<zid>/<node id>/<node id>/NN/<enclave>/<namespace>/<node name>`` for a
  node, ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/MP/<enclave>/<namespace>/<node
  name>/<topic>/<DDS type>/<hash>/<qos>`` for a publisher; names "mangled" (every ``/`` ->
  ``%``), so the root namespace and enclave are ``%`` and ``/robot/pose`` is ``%robot%pose``.
- **QoS** in a token: ``reliability:durability:history,depth:deadline s,ns:lifespan s,ns:
  liveliness,lease s,lease ns``, each field empty when it equals rmw_zenoh's default
  (reliable, volatile, keep-last, depth 42, infinite durations, automatic liveliness), e.g.
  ``::,10:,:,:,,`` for a reliable volatile keep-last-10 publisher.
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass

from cubetrack.sink.cdr import RosType

ADMIN_SPACE = "@ros2_lv"
GID_SIZE = 16
HUMBLE_TYPE_HASH = "TypeHashNotSupported"


class Distro(enum.Enum):
    """ROS 2 distributions whose rmw_zenoh cubetrack can talk to."""

    HUMBLE = "humble"
    IRON = "iron"
    JAZZY = "jazzy"
    KILTED = "kilted"
    ROLLING = "rolling"

    def type_hash(self, ros_type: RosType) -> str:
        """The hash segment of keys and tokens: Humble has no type hashes."""
        return HUMBLE_TYPE_HASH if self is Distro.HUMBLE else ros_type.rihs01


# rmw's enum values (rmw/types.h), as they appear in tokens
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2


@dataclass(frozen=True, slots=True)
class Qos:
    """The QoS policies a publisher here can differ in (durations are always infinite)."""

    depth: int
    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST

    def keyexpr(self) -> str:
        """The compact form in liveliness tokens (fields equal to rmw_zenoh's defaults empty)."""

        def diff(value: int, default: int) -> str:
            return "" if value == default else str(value)

        return (f"{diff(self.reliability, RELIABLE)}:{diff(self.durability, VOLATILE)}:"
                f"{diff(self.history, KEEP_LAST)},{diff(self.depth, 42)}:,:,:,,")


def mangle(name: str) -> str:
    """A ROS name as one key chunk: every ``/`` -> ``%``."""
    return name.replace("/", "%")


def topic_key(domain_id: int, topic: str, ros_type: RosType, distro: Distro) -> str:
    """The data key expression of ``topic`` (a fully qualified name such as ``/robot/pose``)."""
    return f"{domain_id}/{topic.strip('/')}/{ros_type.dds_name}/{distro.type_hash(ros_type)}"


def node_token(domain_id: int, zid: str, node_id: int, namespace: str, node: str, enclave: str = "/") -> str:
    """Liveliness key expression announcing a node."""
    return (f"{ADMIN_SPACE}/{domain_id}/{zid}/{node_id}/{node_id}/NN/"
            f"{mangle(enclave)}/{mangle(namespace)}/{mangle(node)}")


def publisher_token(domain_id: int, zid: str, node_id: int, entity_id: int, namespace: str, node: str,
                    topic: str, ros_type: RosType, distro: Distro, qos: Qos, enclave: str = "/") -> str:
    """Liveliness key expression announcing a publisher of ``topic`` in a node."""
    return (f"{ADMIN_SPACE}/{domain_id}/{zid}/{node_id}/{entity_id}/MP/"
            f"{mangle(enclave)}/{mangle(namespace)}/{mangle(node)}/"
            f"{mangle(topic)}/{ros_type.dds_name}/{distro.type_hash(ros_type)}/{qos.keyexpr()}")


def gid(token: str) -> bytes:
    """The entity's 16-byte GID, derived from its liveliness key expression as rmw_zenoh does."""
    import xxhash

    return xxhash.xxh3_128_intdigest(token.encode("utf-8")).to_bytes(GID_SIZE, "little")


def attachment(sequence_number: int, source_time_ns: int, publisher_gid: bytes) -> bytes:
    """The 33-byte attachment every rmw_zenoh sample carries."""
    if len(publisher_gid) != GID_SIZE:
        raise ValueError(f"a GID has {GID_SIZE} bytes, got {len(publisher_gid)}")
    return struct.pack("<qqB16s", sequence_number, source_time_ns, GID_SIZE, publisher_gid)
