"""``jitterguard ros2-in``: a live ROS 2 LiDAR topic, on Zenoh through zenoh-bridge-ros2dds or rmw_zenoh, published on
``jg/{ns}/points`` — or the vehicle's own detector's ``autoware_perception_msgs/DetectedObjects`` topic, published on
``jg/{ns}/detections`` for jitterguard's tracker (``msgtype``).

The Zenoh adapter around :class:`.scans_in.LiveScans`: the scans' key goes through a bounded inbox (the newest scans
kept; a worker that falls behind skips, counted ``dropped_queue.*``), the pose keys (``tf``, ``tf_static`` or the
pose topic) are small and fed to the core in their callbacks. The worker decodes a scan, waits up to ``tf_wait_s``
for the poses to reach its stamp (TF usually comes a few ms after the cloud it poses), poses it and puts it on
``points`` with a seq of its own and the scan's sensor stamp. A payload that is not a CDR message of its topic's
type is rejected, counted per key, and the service goes on; one that decodes but breaks the contract (a cloud
without z, a box with an impossible probability) is counted ``invalid``, logged, and dealt with; a scan that cannot
be posed (no TF path to its frame) is counted ``unposed`` and is a failure of progress (``failing`` after five in a
row, with the reason).

``/tf_static`` is latched in ROS 2 (transient local), and a bridge or node started before us has published it once.
Each keeps that history its own way (read in their sources): zenoh-bridge-ros2dds since 1.1 and rmw_zenoh in a
zenoh-ext ``AdvancedPublisher`` cache with publisher detection, which an ``AdvancedSubscriber`` with history fetches,
from publishers that come later too; the bridge's 1.0 in a publication cache answering queries on
``@/<zid>/@ros2_pub_cache/<key>``, its 0.x on ``@ros2_pub_cache/<id>/<key>``, rmw_zenoh's first Zenoh 1.0 releases
on ``<zid>/<key>``. The key is subscribed the first way, and the others are queried at start and every few seconds
until one has come.

The ROS 2 topics are on the service's own session (a bridge that is a client of jitterguard's router) or, with
``ros_connect``, on a client session of the ROS 2 system's own router (``rmw_zenohd``, or a bridge's): then only the
topics ``ros2-in`` reads cross between the two Zenoh networks. Under rmw_zenoh the service is in the ROS graph as
node ``/jitterguard/<ns>/ros2_in`` subscribing its topics (:mod:`.graph`).
"""

from __future__ import annotations

import threading
import time

import zenoh
import zenoh.ext

from ...ros2.types import POINTCLOUD2
from ...runtime import ZenohOptions
from ...runtime.progress import ProgressPolicy
from ...schemas import DecodeError, LimitExceeded, encode, keys
from ..replay.adapter import message_for
from ..replay.frames import FrameError
from ..replay.sources.ros_types import TF_MESSAGE
from .graph import RosGraphService
from .ros_keys import AUTOWARE_OBJECTS_QOS, RosEndpoint, RosNaming, RosQos
from .scans_in import LiveScans, UndecodableMessage

INBOX = 4
"""Scans held for the worker: the newest ones (a LiDAR at 10–20 Hz; a worker behind skips, never lags)."""
MAX_CLOUD_BYTES = 64 * 1024 * 1024
"""A PointCloud2 larger than this is refused from its size (a 128-beam scan with 12 fields is ~20 MB)."""
INBOX_BYTES = 2 * MAX_CLOUD_BYTES
"""... and the scans held at most this many bytes (four of 20 MB, two of the largest)."""
MAX_POSE_BYTES = 1024 * 1024
STATIC_QUERY_S = 5.0
PUB_CACHE_PREFIXES = {"bridge": ("@/*/@ros2_pub_cache", "@ros2_pub_cache/*"), "rmw_zenoh": ("*",)}
"""Where zenoh-bridge-ros2dds 1.0 and 0.x, and rmw_zenoh's first Zenoh 1.0 releases, answer queries for their
transient-local publications' history (each under its own Zenoh id); the bridge since 1.1 and later rmw_zenoh
releases serve it to an advanced subscriber's history instead."""
SCAN_QOS = RosQos(reliable=False, depth=5)
"""ROS 2's sensor-data QoS, what a LiDAR driver's subscribers use (best effort, keep the last 5)."""
TF_QOS = RosQos(depth=100)
STATIC_QOS = RosQos(transient_local=True, depth=100)
"""tf2's listener: /tf reliable keeping 100, /tf_static transient local keeping 100."""


class Ros2InService(RosGraphService):
    """Publishes the scans of one ROS 2 PointCloud2 topic on ``points`` (or the boxes of one DetectedObjects topic on
    ``detections``: ``msgtype``), posed by TF or a pose topic."""

    name = "ros2-in"

    def __init__(self, opts: ZenohOptions, *, topic: str, pose_topic: str | None, pose_type: str | None,
                 msgtype: str = POINTCLOUD2, naming: RosNaming = RosNaming(), ros_opts: ZenohOptions | None = None,
                 tf_wait_s: float = 0.1) -> None:
        self.core = LiveScans(pose_type, msgtype)  # a type it cannot use fails before the session opens
        self._lock = threading.Lock()  # the core is fed from the pose callbacks and the worker
        self.tf_wait_s = tf_wait_s
        self.topic = topic
        super().__init__(opts)
        self._seq = 0
        self.out_key = keys.points(self.ns) if msgtype == POINTCLOUD2 else keys.detections(self.ns)
        self._pub = self.publisher(self.out_key)
        self.monitor_progress(ProgressPolicy(stall_s=5.0))  # scans in -> points out
        self.naming = naming
        self.ros = self.another_session(ros_opts) if ros_opts is not None else self.session
        self.in_key = naming.subscription(topic)
        self._inbox = self.subscribe_queue(self.in_key, INBOX, max_queued_bytes=INBOX_BYTES, progress=True,
                                           max_bytes=MAX_CLOUD_BYTES, session=self.ros)
        self.static_key = naming.subscription("/tf_static")
        self._static_seen = threading.Event()
        self._sub(self.static_key, self._on_static, history=True)
        self.pose_key = None
        if pose_type == TF_MESSAGE:
            self.pose_key = naming.subscription(pose_topic or "/tf")
            self._sub(self.pose_key, self._on_tf)
        elif pose_type is not None:
            self.pose_key = naming.subscription(pose_topic or "")
            self._sub(self.pose_key, self._on_pose)
        store = self.core.store  # the type store the messages are decoded with
        endpoints = [RosEndpoint("MS", topic, msgtype, store.hash_rihs01(msgtype),
                                 SCAN_QOS if msgtype == POINTCLOUD2 else AUTOWARE_OBJECTS_QOS),
                     RosEndpoint("MS", "/tf_static", TF_MESSAGE, store.hash_rihs01(TF_MESSAGE), STATIC_QOS)]
        if pose_type is not None:
            endpoints.append(RosEndpoint("MS", pose_topic or "/tf", pose_type, store.hash_rihs01(pose_type), TF_QOS))
        self.graph = self.declare_graph(self.ros, naming, endpoints)
        self.spawn(self._worker, "worker")
        self.spawn(self._static_history, "tf-static")

    def _sub(self, key: str, handler, history: bool = False) -> None:  # type: ignore[no-untyped-def]
        """Subscribe ``handler`` to a pose key; with ``history``, also to what publishers with a cache on it hold
        (the bridge's latched topics), those that appear later included."""
        def on_sample(sample: zenoh.Sample) -> None:
            if self.oversized(sample, MAX_POSE_BYTES, "payload", key):
                return
            self.counters.inc("received")
            handler(sample.payload.to_bytes(), key)
        if history:
            self._declared.append(zenoh.ext.declare_advanced_subscriber(
                self.ros, key, on_sample, history=zenoh.ext.HistoryConfig(detect_late_publishers=True)))
        else:
            self._declared.append(self.ros.declare_subscriber(key, on_sample))

    def _refuse(self, exc: Exception, key: str, sample_key: str | None = None) -> None:
        """Count (``rejected.<ROS key>``, the subscription's: under rmw_zenoh its ``*/*`` matches any type chunk a
        sample names, and one counter per key put had grown without bound) and log (with ``sample_key``) a payload
        refused on a ROS topic's key."""
        self.reject(exc if isinstance(exc, DecodeError) else DecodeError("CDR", "", str(exc)), key, sample_key)

    def _feed(self, payload: bytes, key: str, what: str) -> bool:
        """One pose message (``tf_static``, ``tf`` or ``poses``, the counter it goes to) into the core; False when
        it is refused."""
        now = time.time_ns()
        try:
            with self._lock:
                if what == "poses":
                    self.core.pose(payload, now)
                else:
                    self.core.tf(payload, now, static=what == "tf_static")
        except UndecodableMessage as exc:
            self._refuse(exc, key)
            return False
        self.counters.inc(what)
        return True

    def _on_static(self, payload: bytes, key: str) -> None:
        if self._feed(payload, key, "tf_static"):
            self._static_seen.set()

    def _on_tf(self, payload: bytes, key: str) -> None:
        self._feed(payload, key, "tf")

    def _on_pose(self, payload: bytes, key: str) -> None:
        self._feed(payload, key, "poses")

    def _static_history(self) -> None:
        """Ask the publication caches of older bridges and rmw_zenoh releases for the latched ``/tf_static`` until one
        has come."""
        prefixes = PUB_CACHE_PREFIXES[self.naming.middleware]
        while not self._static_seen.is_set() and not self.stop_event.is_set():
            for selector in (*(f"{prefix}/{self.static_key}" for prefix in prefixes), self.static_key):
                try:
                    for reply in self.ros.get(selector, timeout=2.0):
                        if reply.ok is not None:
                            self._on_static(reply.ok.payload.to_bytes(), self.static_key)
                except Exception as exc:  # a query that fails is asked again; the live messages still count
                    self.log.debug("query %s: %s", selector, exc)
            self.stop_event.wait(STATIC_QUERY_S)

    def _worker(self) -> None:
        while not self.stop_event.is_set():
            item = self._inbox.get(0.25)
            if item is not None:
                self._handle(item[0], item[1])

    def _handle(self, payload: bytes, key: str) -> None:
        received = time.time_ns()
        try:
            msg, stamp = self.core.stamp_of(payload)
        except UndecodableMessage as exc:
            self._refuse(exc, self.in_key, key)
            self.progress.failure(time.monotonic(), str(exc)[:200])
            return
        deadline = time.monotonic() + self.tf_wait_s
        while True:  # the poses usually come a few ms after the scan they pose
            with self._lock:
                covered = self.core.covered(stamp, msg.header.frame_id)
            if covered or not stamp or time.monotonic() >= deadline or self.stop_event.is_set():
                break
            time.sleep(0.005)
        if stamp and not covered:
            self.counters.inc("pose_clamped")  # posed at the newest pose before it
        self._seq += 1
        with self._lock:
            frame = self.core.scan(msg, f"{self.topic}#{self._seq}", received)
            notes = self.core.notes()
        for note in notes:
            self.log.info("%s", note)
        if isinstance(frame, FrameError) and frame.invalid:
            # the sender's message breaks the contract: counted apart from a scan without a pose, and dealt with, not
            # a failure of progress (a restart cannot mend the sender's messages; a run of them had the watchdog
            # restart the service over and over)
            self.counters.inc("invalid")
            self._reject_log.warn(f"{frame.origin}: {frame.reason}", kind="invalid")
            self.progress.output(time.monotonic())
            return
        if isinstance(frame, FrameError):
            self.counters.inc("unposed")
            self.progress.failure(time.monotonic(), frame.reason[:200])
            self.log.warning("%s: %s", frame.origin, frame.reason)
            return
        try:
            data = encode(message_for(frame, self._seq, frame.stamp_ns))
        except (LimitExceeded, ValueError) as exc:  # beyond the wire's limits: refused here, not downstream
            self._refuse(exc, self.in_key, key)
            self.progress.failure(time.monotonic(), str(exc)[:200])
            return
        self._pub.put(data)
        self.counters.inc("published")
        self.last_seq = self._seq
        self.progress.output(time.monotonic())
