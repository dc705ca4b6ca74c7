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
"""

from __future__ import annotations

import hashlib
import struct
from dataclasses import dataclass
from typing import Literal

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


def check_topic(flag: str, topic: str) -> str:
    """A ROS 2 topic name as a flag gives it (``/sensing/lidar/top/pointcloud``); ValueError naming ``flag``."""
    name = topic.strip()
    if not name.startswith("/") or len(name) < 2 or any(c in name for c in "*?#$ @"):
        raise ValueError(f"{flag}: {topic!r} is not a ROS 2 topic name (e.g. /sensing/lidar/top/pointcloud)")
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


def publisher_gid(*parts: str) -> bytes:
    """A stable 16-byte GID for a publisher of ours, from what names it (rmw_zenoh hashes its liveliness key)."""
    return hashlib.sha256("/".join(parts).encode()).digest()[:16]


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

    @property
    def attaches(self) -> bool:
        """Whether a publication carries rmw_zenoh's attachment (:func:`rmw_attachment`)."""
        return self.middleware == "rmw_zenoh"
