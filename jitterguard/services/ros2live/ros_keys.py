"""How a ROS 2 topic is named on Zenoh, by the two ways a ROS 2 system reaches it (pure; no Zenoh, no clock).

- ``bridge``: zenoh-bridge-ros2dds (or zenoh-plugin-ros2dds in a router) carries a DDS-based ROS 2 system: topic
  ``/a/b`` is the key ``a/b``, behind the bridge's namespace if it has one; messages are their CDR bytes.
- ``rmw_zenoh``: ROS 2 nodes running on rmw_zenoh (ROS 2's own Zenoh middleware, with its router ``rmw_zenohd``)
  put topic ``/a/b`` of type ``pkg/msg/T`` in ROS domain ``d`` on ``d/a/b/pkg::msg::dds_::T_/RIHS01_<hash>``
  (``TopicInfo`` in rmw_zenoh_cpp's ``liveliness_utils.cpp``: slashes inside the name kept, the type hash of
  REP 2011 last; ROS 2 Humble, which has no type hashes, writes ``TypeHashNotSupported`` there). Payloads are the
  same CDR bytes, encapsulation header included. Its subscriptions declare the exact key and drop a sample without
  the attachment its publishers send (:func:`rmw_attachment`), so a publication must carry both; a subscription of
  ours takes any type and hash (``*/*``) and decodes by the type it expects, refusing what does not decode.

Both keep a latched (transient-local) topic's history in a zenoh-ext advanced publisher's cache (the bridge since
1.1; older bridges in a publication cache, queried by the service): see ``in_service``.

rmw_zenoh's ROS graph (``ros2 topic list``, ``ros2 node list``, ``ros2 topic info -v``, rviz's topic lists) is made
of Zenoh liveliness tokens, one per node and one per publisher or subscription (:func:`graph_tokens`, the key
layout of ``Entity`` in ``liveliness_utils.cpp`` since rmw_zenoh moved to Zenoh 1.0: Jazzy's and Humble's binary
releases). Data flows without them; they make jitterguard's endpoints visible to ROS 2's tools, which also need
them to learn a topic's type. Behind a bridge the bridge announces DDS endpoints itself: no tokens.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import xxhash

Middleware = Literal["bridge", "rmw_zenoh"]
MIDDLEWARES: tuple[str, ...] = ("bridge", "rmw_zenoh")
MAX_DOMAIN_ID = 232
"""ROS 2 domain IDs run 0–232 (DDS' port arithmetic; rmw_zenoh keeps the range)."""
NO_TYPE_HASH = "TypeHashNotSupported"
"""The hash chunk of rmw_zenoh's keys on ROS 2 distributions before type hashes (REP 2011 came with Iron)."""
DISTROS_WITHOUT_TYPE_HASHES = ("foxy", "galactic", "humble")


def ros_key(prefix: str, topic: str) -> str:
    """The Zenoh key of a ROS 2 topic as zenoh-bridge-ros2dds maps it: the topic without its leading ``/``, under
    the bridge's namespace ``prefix`` (``''`` by default)."""
    return prefix.strip("/") + "/" + topic.strip("/") if prefix.strip("/") else topic.strip("/")


TOPIC_NAME = re.compile(r"(/[A-Za-z_][A-Za-z0-9_]*)+")
"""A fully qualified ROS 2 topic name (rcl's rules): ``/``-separated tokens, none empty, of letters, digits and
underscores, none starting with a digit."""
KEY_PREFIX = re.compile(r"[A-Za-z0-9_\-.]+(/[A-Za-z0-9_\-.]+)*")
"""A bridge's namespace as a Zenoh key prefix: chunks that are neither empty nor wildcards."""


def check_topic(flag: str, topic: str) -> str:
    """A ROS 2 topic name as a flag gives it (``/sensing/lidar/top/pointcloud``); ValueError naming ``flag``. An
    empty token (``/a//b``) had passed and failed later as a Zenoh key, in a traceback."""
    name = topic.strip()
    if not TOPIC_NAME.fullmatch(name):
        raise ValueError(f"{flag}: {topic!r} is not a ROS 2 topic name (e.g. /sensing/lidar/top/pointcloud)")
    return name


def check_key_prefix(flag: str, prefix: str) -> str:
    """A bridge namespace (``--key-prefix``; ``''`` for none), its ``/`` at either end dropped; ValueError naming
    ``flag`` for an empty chunk (``a//b``) or a wildcard (``a/*``, ``**``), which had been taken and published on."""
    name = prefix.strip().strip("/")
    if name and not KEY_PREFIX.fullmatch(name):
        raise ValueError(f"{flag}: {prefix!r} is not a Zenoh key prefix (chunks of letters, digits, '_', '-', '.', "
                         f"split by single '/'; no wildcards)")
    return name


def dds_type_name(msgtype: str) -> str:
    """``pkg/msg/Name`` as ROS 2 names it on the wire (DDS, and rmw_zenoh's keys): ``pkg::msg::dds_::Name_``."""
    package, kind, name = msgtype.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def rmw_attachment(seq: int, stamp_ns: int, gid: bytes) -> bytes:
    """What rmw_zenoh's publishers attach to every sample, and its subscriptions require: the sequence number and
    the source timestamp (int64, little-endian) and the publisher's 16-byte GID with its length, in zenoh-ext's
    serialization (33 bytes; rmw_zenoh's design notes, ``attachment_helpers.cpp``)."""
    if len(gid) != 16:
        raise ValueError(f"a GID is 16 bytes, got {len(gid)}")
    return struct.pack("<qqB16s", seq, stamp_ns, 16, gid)


def entity_gid(token: str) -> bytes:
    """An endpoint's 16-byte GID as rmw_zenoh derives it: XXH3-128 of its liveliness token, the low 64 bits first
    (``Entity``'s constructor) — what ``ros2 topic info -v`` shows and what its attachments carry."""
    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(16, "little")


GRAPH_PREFIX = "@ros2_lv"
"""Where rmw_zenoh's liveliness tokens live: ``@ros2_lv/<domain>/...``."""
RMW_BEST_EFFORT = 2  # rmw_qos_reliability_policy_e (RELIABLE = 1, the default)
RMW_TRANSIENT_LOCAL = 1  # rmw_qos_durability_policy_e (VOLATILE = 2, the default)
RMW_ZENOH_DEFAULT_DEPTH = 42
"""rmw_zenoh's default history depth (``qos.cpp``); a token leaves out every QoS field equal to its default."""


@dataclass(frozen=True)
class RosQos:
    """The QoS an endpoint announces in its graph token (keep-last history; deadline, lifespan and liveliness at
    rmw_zenoh's defaults, as every jitterguard endpoint has them)."""

    reliable: bool = True
    transient_local: bool = False
    depth: int = RMW_ZENOH_DEFAULT_DEPTH

    def chunk(self) -> str:
        """``reliability:durability:history,depth:deadline s,ns:lifespan s,ns:liveliness,lease s,ns`` with the
        defaults left empty (``qos_to_keyexpr``): e.g. ``::,1:,:,:,,`` for reliable, volatile, depth 1."""
        rel = "" if self.reliable else str(RMW_BEST_EFFORT)
        dur = str(RMW_TRANSIENT_LOCAL) if self.transient_local else ""
        depth = "" if self.depth == RMW_ZENOH_DEFAULT_DEPTH else str(self.depth)
        return f"{rel}:{dur}:,{depth}:,:,:,,"


AUTOWARE_OBJECTS_QOS = RosQos(depth=1)
"""Autoware's detection and tracking outputs (and their subscribers): reliable, volatile, keeping the last one
(``rclcpp::QoS{1}``)."""


@dataclass(frozen=True)
class RosEndpoint:
    """One publisher (``MP``) or subscription (``MS``) of a node, as the ROS graph lists it."""

    kind: Literal["MP", "MS"]
    topic: str
    msgtype: str  # pkg/msg/Name
    type_hash: str  # RIHS01_…, or NO_TYPE_HASH where the distribution has none
    qos: RosQos = RosQos()


def ros_node(service: str, ns: str) -> tuple[str, str]:
    """The ROS namespace and node name a jitterguard service appears under in the ROS graph: ``/jitterguard/<ns>``
    and ``ros2_out`` for ``ros2-out`` of namespace ``ns`` (ROS names take no ``-``: it becomes ``_``)."""
    return f"/jitterguard/{ns.replace('-', '_')}", service.replace("-", "_")


def _mangle(name: str) -> str:
    """A ROS name as one key chunk: ``/`` becomes ``%`` (``mangle_name``)."""
    return name.replace("/", "%")


@dataclass(frozen=True)
class RosNaming:
    """The keys of a ROS 2 system's topics on Zenoh: ``middleware`` ``bridge`` (under the bridge's namespace
    ``prefix``) or ``rmw_zenoh`` (in ROS domain ``domain_id``)."""

    middleware: Middleware = "bridge"
    prefix: str = ""
    domain_id: int = 0
    type_hashes: bool = True  # False on ROS 2 Humble (rmw_zenoh then puts NO_TYPE_HASH in its keys)

    def __post_init__(self) -> None:
        if self.middleware not in MIDDLEWARES:
            raise ValueError(f"middleware {self.middleware!r} is not one of {', '.join(MIDDLEWARES)}")
        if not 0 <= self.domain_id <= MAX_DOMAIN_ID:
            raise ValueError(f"ROS domain ID {self.domain_id} is outside 0-{MAX_DOMAIN_ID}")

    def subscription(self, topic: str) -> str:
        """The key expression that receives ``topic`` (under rmw_zenoh whatever its type and type hash)."""
        if self.middleware == "bridge":
            return ros_key(self.prefix, topic)
        return f"{self.domain_id}/{topic.strip('/')}/*/*"

    def publication(self, topic: str, msgtype: str, type_hash: str) -> str:
        """The key a ROS 2 subscriber of ``topic`` (messages of ``msgtype``, whose REP 2011 hash is ``type_hash``,
        ``RIHS01_…``) listens on."""
        if self.middleware == "bridge":
            return ros_key(self.prefix, topic)
        chunk = type_hash if self.type_hashes else NO_TYPE_HASH
        return f"{self.domain_id}/{topic.strip('/')}/{dds_type_name(msgtype)}/{chunk}"

    def graph_tokens(self, zid: str, node: str, namespace: str,
                     endpoints: Sequence[RosEndpoint]) -> list[str]:
        """The liveliness tokens that put node ``namespace/node`` and its ``endpoints`` in rmw_zenoh's ROS graph,
        node first (``@ros2_lv/<domain>/<session zid>/<node id>/<entity id>/<NN|MP|MS>/<enclave>/<namespace>/<node>
        [/<topic>/<type>/<type hash>/<qos>]``, names with ``/`` as ``%``, the default enclave ``/``); none behind a
        bridge."""
        if self.middleware != "rmw_zenoh":
            return []
        head = f"{GRAPH_PREFIX}/{self.domain_id}/{zid}/0"
        tail = f"{_mangle('/')}/{_mangle(namespace)}/{node}"
        tokens = [f"{head}/0/NN/{tail}"]
        for i, e in enumerate(endpoints, start=1):
            chunk = e.type_hash if self.type_hashes else NO_TYPE_HASH
            tokens.append(f"{head}/{i}/{e.kind}/{tail}/{_mangle(e.topic)}/{dds_type_name(e.msgtype)}/{chunk}/"
                          f"{e.qos.chunk()}")
        return tokens

    @property
    def attaches(self) -> bool:
        """Whether a publication carries rmw_zenoh's attachment (:func:`rmw_attachment`)."""
        return self.middleware == "rmw_zenoh"
