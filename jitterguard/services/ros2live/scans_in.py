"""The live ROS 2 input's pure core: CDR messages of a LiDAR topic (or of a detector's ``DetectedObjects`` topic) and
its poses in, posed scans (or frames of detections) out.

A vehicle's ROS 2 stack reaches Zenoh through ``zenoh-bridge-ros2dds`` or runs on rmw_zenoh (the keys of either:
:mod:`.ros_keys`); each message travels as its CDR bytes, encapsulation header included. This core decodes them
(rosbags' typestore, the one the bag source reads with) and poses each scan by the bag source's rules
(:class:`~jitterguard.services.replay.sources.poser.ScanPoser`): TF (``/tf`` + ``/tf_static``) or an odometry /
pose topic, the cloud turned into ``base_link``'s axes where its mount is a static link. Live messages come in any
order, so a scan whose stamp is newer than the newest pose is *not covered* yet: the service waits a little for
the pose to catch up before it poses the scan (clamped to the newest pose after that). Pure: bytes and stamps in,
frames out; no Zenoh, no clock.
"""

from __future__ import annotations

from typing import Any

from ..replay.frames import DetectionFrame, FrameError, ScanFrame
from ..replay.sources.poser import ScanPoser
from ..replay.sources.ros_types import DETECTED_OBJECTS, POINTCLOUD2, POSE_TYPES, TF_MESSAGE, stamp_ns, typestore

INPUT_TYPES = (POINTCLOUD2, DETECTED_OBJECTS)
"""What the input topic may carry: a LiDAR's scans (for jitterguard's detector), or the boxes of the vehicle's own
detector (Autoware's ``DetectedObjects``, for jitterguard's tracker)."""

KEEP_POSES_NS = 10_000_000_000
"""Pose samples older than this behind the newest scan are forgotten: a live stream's memory stays bounded."""


class UndecodableMessage(ValueError):
    """A payload that is not a CDR message of the topic's type."""


class LiveScans:
    """One input topic of ``msgtype`` (:data:`INPUT_TYPES`: scans, or DetectedObjects), posed by TF (``pose_type``
    ``tf2_msgs/msg/TFMessage``), a pose topic (one of :data:`POSE_TYPES`) or nothing (the identity pose: a sensor
    that does not move)."""

    def __init__(self, pose_type: str | None, msgtype: str = POINTCLOUD2) -> None:
        if pose_type not in (None, TF_MESSAGE, *POSE_TYPES):
            raise ValueError(f"pose messages of type {pose_type} cannot pose a scan (use {TF_MESSAGE} or one of "
                             f"{', '.join(POSE_TYPES)})")
        if msgtype not in INPUT_TYPES:
            raise ValueError(f"an input topic carries {' or '.join(INPUT_TYPES)}, not {msgtype}")
        self.pose_type = pose_type
        self.msgtype = msgtype
        self.store = typestore()
        self.poser = ScanPoser(use_tf=pose_type == TF_MESSAGE)
        self.newest_pose_ns: int | None = None  # the newest dynamic pose sample's stamp

    def _decode(self, payload: bytes, msgtype: str) -> Any:
        try:
            return self.store.deserialize_cdr(payload, msgtype)
        except Exception as exc:  # rosbags raises several kinds for a payload that is not this type
            raise UndecodableMessage(f"not a CDR {msgtype}: {type(exc).__name__}: {exc}"[:300]) from None

    def tf(self, payload: bytes, received_ns: int, *, static: bool) -> None:
        """A ``/tf`` or ``/tf_static`` message."""
        msg = self._decode(payload, TF_MESSAGE)
        self.poser.add_tf(msg, received_ns, static=static)
        if not static:
            stamps = [stamp_ns(t.header) for t in msg.transforms]
            if stamps:
                self._saw_pose(max(stamps) or received_ns)

    def pose(self, payload: bytes, received_ns: int) -> None:
        """A message of the pose topic."""
        assert self.pose_type in POSE_TYPES
        msg = self._decode(payload, self.pose_type)
        if self.poser.add_pose(msg, received_ns):
            self._saw_pose(self.poser.pose_times[-1])

    def _saw_pose(self, stamp: int) -> None:
        if self.newest_pose_ns is None or stamp > self.newest_pose_ns:
            self.newest_pose_ns = stamp

    def stamp_of(self, payload: bytes) -> tuple[Any, int]:
        """The decoded input message and its header stamp (0 when the driver left it unset)."""
        msg = self._decode(payload, self.msgtype)
        return msg, stamp_ns(msg.header)

    def covered(self, stamp: int, frame_id: str | None = None) -> bool:
        """Whether the poses reach ``stamp`` (no pose source: always) — by TF, those of the chain from ``frame_id``
        (the message's, as :meth:`scan` reads it) to its root: every dynamic link on it (a ``/tf`` message's other
        links say nothing of this one; a faster one had let a scan be posed at once, clamped to an older vehicle
        pose)."""
        if self.pose_type is None:
            return True
        if self.pose_type == TF_MESSAGE and frame_id is not None:
            try:
                newest = self.poser.tf.newest(frame_id.lstrip("/") or "lidar")
            except KeyError:
                return False  # not in the tree yet: its transforms may be on their way
            return newest is None or newest >= stamp
        return self.newest_pose_ns is not None and self.newest_pose_ns >= stamp

    def scan(self, msg: Any, origin: str, received_ns: int) -> ScanFrame | DetectionFrame | FrameError:
        """The posed scan of a decoded PointCloud2, or the posed frame of a decoded DetectedObjects (:meth:`stamp_of`),
        or why there is none; forgets the poses :data:`KEEP_POSES_NS` older than it."""
        if self.msgtype == POINTCLOUD2:
            frame: ScanFrame | DetectionFrame | FrameError = self.poser.scan(msg, origin, received_ns)
        else:
            frame = self.poser.detections(msg, origin, received_ns)
        if not isinstance(frame, FrameError):
            self.poser.forget_before(frame.stamp_ns - KEEP_POSES_NS)
        return frame

    def notes(self) -> list[str]:
        """What the poser noted since the last call (a mount's turn, a missing extrinsic): each said once."""
        out, self.poser.notes[:] = list(self.poser.notes), []
        return out
