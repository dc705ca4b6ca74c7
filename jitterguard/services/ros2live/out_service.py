"""``jitterguard ros2-out``: the classifier's ``objects`` back into ROS 2, live, as Autoware's prediction reads them.

Each ``objects`` message becomes an ``autoware_perception_msgs/msg/TrackedObjects`` (the conversion of the ROS 2 bag
recorder, :class:`~jitterguard.ros2.autoware.RosBuilder`: twists in the object's frame, ``is_stationary`` from the
z-test, static objects with zero velocity and their window-mean pose), serialised as CDR and put on the Zenoh key of
``/perception/object_recognition/tracking/objects`` — the topic ``map_based_prediction`` subscribes to — as the
ROS 2 system names it (:mod:`.ros_keys`): for zenoh-bridge-ros2dds to hand to ROS 2 (it writes a topic into ROS 2
once a ROS 2 node subscribes to it), or for rmw_zenoh's subscribers directly, on the key with the message type's
REP 2011 hash and with the attachment they require (a sequence number, the time of publication, this publisher's
GID), and in rmw_zenoh's ROS graph as node ``/jitterguard/<ns>/ros2_out`` publishing the topic (:mod:`.graph`). One
read and one write per message; a payload that does not validate is refused and counted per key, as every
service does.
"""

from __future__ import annotations

import time

from ...ros2.autoware import RosBuilder
from ...ros2.types import TRACKED_OBJECTS, typestore
from ...runtime import ZenohOptions
from ...runtime.progress import ProgressPolicy
from ...schemas import keys
from ...schemas.models import TrackedObjects
from ...schemas.wire import LIMITS
from ..bridge.service import BOUNDS
from .graph import RosGraphService
from .ros_keys import AUTOWARE_OBJECTS_QOS, RosEndpoint, RosNaming, entity_gid, rmw_attachment


class Ros2OutService(RosGraphService):
    """Puts the classifier's ``objects`` as CDR ``TrackedObjects`` on one ROS 2 topic's Zenoh key."""

    name = "ros2-out"

    def __init__(self, opts: ZenohOptions, *, topic: str, naming: RosNaming = RosNaming(),
                 ros_opts: ZenohOptions | None = None) -> None:
        self.store = typestore()
        self.builder = RosBuilder(self.store)
        super().__init__(opts)
        self.naming = naming
        type_hash = self.store.hash_rihs01(TRACKED_OBJECTS)
        self.key = naming.publication(topic, TRACKED_OBJECTS, type_hash)
        ros = self.another_session(ros_opts) if ros_opts is not None else self.session
        self._pub = self.publisher(self.key, session=ros)
        self.graph = self.declare_graph(ros, naming, [RosEndpoint("MP", topic, TRACKED_OBJECTS, type_hash,
                                                                  AUTOWARE_OBJECTS_QOS)])
        self._gid = entity_gid(self.graph[-1]) if self.graph else bytes(16)
        self._sent = 0
        self.monitor_progress(ProgressPolicy(stall_s=5.0))  # objects in -> TrackedObjects out
        self.subscribe(keys.objects(self.ns), TrackedObjects, self._on_objects, max_bytes=LIMITS.max_payload_bytes,
                       **BOUNDS)

    def _on_objects(self, msg: TrackedObjects, _key: str) -> None:
        self.progress.input(time.monotonic())
        try:
            cdr = bytes(self.store.serialize_cdr(self.builder.tracked_objects(msg), TRACKED_OBJECTS))
        except Exception as exc:  # a message the wire allows and ROS cannot hold: counted, the next one goes on
            self.counters.inc("convert_errors")
            self.progress.failure(time.monotonic(), f"{type(exc).__name__}: {exc}"[:200])
            self.log.warning("objects seq %d not converted: %s: %s", msg.header.seq, type(exc).__name__, exc)
            return
        self._sent += 1
        self._pub.put(cdr, attachment=rmw_attachment(self._sent, time.time_ns(), self._gid)
                      if self.naming.attaches else None)
        self.counters.inc("published")
        self.last_seq = msg.header.seq
        self.progress.output(time.monotonic())
