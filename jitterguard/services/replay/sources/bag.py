"""ROS 2 bags (sqlite3 ``.db3`` or MCAP, a bag folder or a bare ``.mcap``) and ROS 1 ``.bag`` via rosbags.

One topic is replayed: a ``sensor_msgs/PointCloud2`` topic (``points``) or an Autoware
``autoware_perception_msgs/DetectedObjects`` topic (``detections``; also under its name before autoware_msgs 1.0,
``autoware_auto_perception_msgs``, read by its fields' names from the definitions the bag embeds). With ``--topic``
unset, the bag's only topic of either type is picked (PointCloud2 first); several candidates are an error that lists
them. A topic whose type the bag defines nowhere (and jitterguard ships no definition of) is refused at open.
Stamps come from each message's header (the sensor's time), falling back to the bag's receive time when a
driver left the header stamp at zero. The ego pose (the pose of the message's ``frame_id`` in the world)
comes from ``--pose-topic``:

- a ``tf2_msgs/TFMessage`` topic (``/tf``): the TF chain from the tree's root (``map``) down to the cloud's
  frame, with ``/tf_static`` for the fixed links, each dynamic link interpolated at the scan's stamp (a tree whose
  root is ``base_link`` puts nothing in the world, nor does a chain broken below it — its top no REP-105 fixed frame
  and ``base_link`` in another tree, or static links only: its frames are frame errors naming the missing link);
- an Odometry / PoseStamped / PoseWithCovarianceStamped topic, interpolated to each stamp, then composed
  with the ``/tf_static`` chain from the odometry's ``child_frame_id`` (e.g. ``base_link``) to the cloud's
  frame when the bag has one (otherwise the vehicle's pose is taken for the sensor's, and a note says so).

Without ``--pose-topic`` the pose is the identity.

Frame. With a pose topic, a PointCloud2 scan whose frame hangs under the vehicle's base frame by a static chain
is published in the *base frame's axes at the sensor*, as the nuScenes reader publishes LIDAR_TOP (see
:mod:`.nuscenes`): the detector was trained in a level, x-forward frame, as Autoware runs CenterPoint in
``base_link``'s axes, and a tilted LiDAR (or one with x to the right) would reach it tilted or turned. The base
frame is the odometry's ``child_frame_id`` (poses from a pose topic) or ``base_link`` when it is above the cloud's
frame (poses from TF, REP-105). With R the rotation of the cloud's frame in the base frame (the static chain's),
the points' x, y, z become R·p (other fields as they are), the ``frame_id`` the cloud's frame + ``FRAME_SUFFIX``
and the pose ``pose ∘ (no translation, Rᵀ)`` — the sensor's position with the base frame's orientation — so
pose ∘ point is the same world point. A note names the turn (the mount's tilt and yaw). Only a static chain is
used: a dynamic link between the two (as in the bags ``jitterguard record --ros2`` writes, whose per-frame
``base_link → sensor`` is the vehicle's roll and pitch, not a mount) keeps the clouds in their own frame, and a
note says so. A chain whose R is the identity within 1e-9 (a level, x-forward mount) changes nothing: the scans
go out in the cloud's own frame as they are. DetectedObjects, a pose topic without ``child_frame_id``
(PoseStamped) and bags replayed without ``--pose-topic`` are published in the message's own frame, as before.

rosbags is an optional dependency: it is imported when a bag is opened, and its absence is a one-line error.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from ..frames import FrameError, Item, SourceError, SourceInfo
from .base import Source
from .poser import ScanPoser
from .ros_types import (
    DETECTED_OBJECTS,
    DETECTION_TYPES,
    TF_MESSAGE,
    POINTCLOUD2,
    POSE_TYPES,
    typestore,
)

log = logging.getLogger("jitterguard.replay")

BAG_SUFFIXES = (".mcap", ".db3", ".bag")
MAX_CLAMP_NS = 500_000_000
"""A scan stamped further than this before the first pose sample (or after the last) is an unreadable frame, not
posed at that sample: a LiDAR stamp a sweep or an odometry period off is clamped, seconds before localization
began are not."""


def is_bag(path: Path) -> bool:
    """A bag folder (``metadata.yaml``) or a bag file by suffix."""
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    return path.suffix.lower() in BAG_SUFFIXES


def _holds_mcap(path: Path) -> bool:
    """``path`` is an MCAP file, or a bag folder holding one."""
    if path.is_dir():
        return any(p.suffix.lower() == ".mcap" for p in path.iterdir())
    return path.suffix.lower() == ".mcap"


def _open_reader(path: Path) -> Any:
    try:
        from rosbags.highlevel import AnyReader
    except ImportError:
        raise SourceError(f"{path}: reading bags needs the 'rosbags' package (pip install rosbags)") from None
    try:
        reader = AnyReader([path], default_typestore=typestore())
        reader.open()
    except FileNotFoundError:
        raise SourceError(f"{path}: no such bag") from None
    except Exception as exc:  # rosbags raises several error types (AnyReaderError, ReaderError, sqlite errors)
        cut = " (an MCAP cut short, e.g. by SIGKILL, has no footer: `mcap recover` rewrites it whole)" \
            if "magic" in str(exc).lower() and _holds_mcap(path) else ""
        raise SourceError(f"{path}: cannot open bag: {exc}{cut}") from None
    return reader


class BagSource(Source):
    """One PointCloud2 or DetectedObjects topic of a bag, posed by the TF tree or an odometry topic."""

    def __init__(self, path: Path, *, topic: str | None = None, pose_topic: str | None = None) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise SourceError(f"{self.path}: no such bag")
        self.reader = _open_reader(self.path)
        try:
            self._select(topic, pose_topic)
        except BaseException:
            self.close()
            raise

    def _select(self, topic: str | None, pose_topic: str | None) -> None:
        conns = self.reader.connections
        by_topic: dict[str, list[Any]] = {}
        for c in conns:
            by_topic.setdefault(c.topic, []).append(c)
        listing = ", ".join(f"{t} ({cs[0].msgtype})" for t, cs in sorted(by_topic.items())) or "none"
        if topic is not None:
            if topic not in by_topic:
                raise SourceError(f"{self.path}: no topic {topic!r} (topics: {listing})")
            msgtype = by_topic[topic][0].msgtype
            if msgtype not in (POINTCLOUD2, *DETECTION_TYPES):
                raise SourceError(f"{self.path}: topic {topic} is {msgtype}, not {POINTCLOUD2} or {DETECTED_OBJECTS}"
                                  f" (or its name before 2024, {DETECTION_TYPES[1]})")
            if sum(c.msgcount for c in by_topic[topic]) == 0:  # said as it is, not as "--start 0 is past the end"
                with_msgs = ", ".join(t for t, cs in sorted(by_topic.items())
                                      if cs[0].msgtype in (POINTCLOUD2, *DETECTION_TYPES)
                                      and sum(c.msgcount for c in cs) > 0) or "none"
                raise SourceError(f"{self.path}: topic {topic} holds no messages (topics of scans or detections"
                                  f" with messages: {with_msgs})")
        else:  # the scans, else the detections — of the topics that hold messages (a recording of a stack fed
            # detections has an empty scan topic beside them)
            for wanted in ((POINTCLOUD2,), DETECTION_TYPES):
                cands = sorted(t for t, cs in by_topic.items()
                               if cs[0].msgtype in wanted and sum(c.msgcount for c in cs) > 0)
                if len(cands) > 1:
                    raise SourceError(f"{self.path}: several {wanted[0]} topics ({', '.join(cands)}); pick one with"
                                      " --topic")
                if cands:
                    topic = cands[0]
                    break
            else:
                raise SourceError(f"{self.path}: no {POINTCLOUD2} or {DETECTED_OBJECTS} topic with messages (topics:"
                                  f" {listing})")
        assert topic is not None
        self.topic = topic
        self.msgtype = by_topic[topic][0].msgtype
        if self.msgtype not in self.reader.typestore.types:  # said once, not as every message undecodable
            raise SourceError(f"{self.path}: the bag carries no definition of {self.msgtype} (topic {topic}), and"
                              " jitterguard ships none under that name")
        self.connections = by_topic[topic]
        kind = "points" if self.msgtype == POINTCLOUD2 else "detections"
        count = sum(c.msgcount for c in self.connections)

        self.undecodable: dict[str, int] = {}  # pose and TF topics: messages skipped as undecodable
        self.poser = ScanPoser(use_tf=pose_topic is not None and pose_topic in by_topic
                               and by_topic[pose_topic][0].msgtype == TF_MESSAGE,
                               turn_clouds=self.msgtype == POINTCLOUD2, max_clamp_ns=MAX_CLAMP_NS)
        notes = [f"topic {topic} ({self.msgtype}), {count} messages"]
        statics = [t for t, cs in by_topic.items() if cs[0].msgtype == TF_MESSAGE and t.rstrip("/").endswith("tf_static")]
        for t in statics:
            self._read_tf(by_topic[t], static=True)
        if pose_topic is not None:
            if pose_topic not in by_topic:
                raise SourceError(f"{self.path}: no pose topic {pose_topic!r} (topics: {listing})")
            ptype = by_topic[pose_topic][0].msgtype
            if ptype == TF_MESSAGE:
                self._read_tf(by_topic[pose_topic], static=pose_topic in statics)
                notes.append(f"poses from the TF tree ({pose_topic}{' + ' + ', '.join(statics) if statics else ''})")
            elif ptype in POSE_TYPES:
                self._read_pose_topic(pose_topic, by_topic[pose_topic])
                skipped = (f"; {self.poser.poses_skipped} skipped: orientation not a unit quaternion or position not"
                           " finite" if self.poser.poses_skipped else "")
                notes.append(f"poses from {pose_topic} ({len(self.poser.poses)} samples{skipped})")
            else:
                raise SourceError(
                    f"{self.path}: pose topic {pose_topic} is {ptype}, not {TF_MESSAGE} or one of {', '.join(POSE_TYPES)}"
                )
        warnings = [f"{self.path}: {n} undecodable message(s) on {t} skipped; the scans take the poses around them"
                    for t, n in sorted(self.undecodable.items())]
        if self.poser.tf_skipped:
            warnings.append(f"{self.path}: TF transforms whose rotation is not a unit quaternion or that are not finite"
                            " skipped (as tf2 does): "
                            + ", ".join(f"{n} to {f!r}" for f, n in sorted(self.poser.tf_skipped.items())))
        if pose_topic is None and count > 1:
            warnings.append(f"{self.path}: no --pose-topic: every {topic} message is published at the identity"
                            " pose, so if the sensor moved, static objects will look dynamic")
        self.info = SourceInfo(name=f"{self.path}:{topic}", kind=kind, num_frames=count, notes=notes,
                               warnings=warnings)
        if self.msgtype == POINTCLOUD2 and pose_topic is not None:
            first = self._first_frame_id()
            if first is not None:
                self.poser.levelling(first)  # its note, before the replay starts
                notes.extend(self.poser.notes)
                self.poser.notes.clear()

    def _first_frame_id(self) -> str | None:
        """The first scan's frame (as :meth:`frames` reads it), or None when it does not decode."""
        messages = self.reader.messages(connections=self.connections)
        try:
            for conn, _, raw in messages:
                try:
                    msg = self.reader.deserialize(raw, conn.msgtype)
                except Exception:
                    return None
                return str(msg.header.frame_id).lstrip("/") or "lidar"
        finally:
            messages.close()
        return None

    def _messages(self, conns: list[Any]) -> Iterator[tuple[int, Any]]:
        """The decoded messages of a pose or TF topic; one that does not decode (torn by a recorder killed mid-write)
        is skipped and counted in ``undecodable`` as a non-finite sample is: it had refused the whole bag."""
        for conn, t_bag, raw in self.reader.messages(connections=conns):
            try:
                msg = self.reader.deserialize(raw, conn.msgtype)
            except Exception:
                self.undecodable[conn.topic] = self.undecodable.get(conn.topic, 0) + 1
                continue
            yield int(t_bag), msg

    def _read_tf(self, conns: list[Any], *, static: bool) -> None:
        for t_bag, msg in self._messages(conns):
            self.poser.add_tf(msg, t_bag, static=static)

    def _read_pose_topic(self, topic: str, conns: list[Any]) -> None:
        for t_bag, msg in self._messages(conns):
            self.poser.add_pose(msg, t_bag)
        if not self.poser.poses:
            no_heading = self.poser.poses_skipped
            raise SourceError(f"{self.path}: pose topic {topic} holds no message with a usable pose"
                              + (f" ({no_heading} without a unit quaternion or a finite position)" if no_heading
                                 else ""))

    def frames(self, start: int = 0) -> Iterator[Item]:
        index = -1
        for conn, t_bag, raw in self.reader.messages(connections=self.connections):
            index += 1
            if index < start:
                continue  # skipping costs no deserialisation
            origin = f"{self.path}:{self.topic}#{index}"
            try:
                msg = self.reader.deserialize(raw, conn.msgtype)
            except Exception as exc:
                yield FrameError(origin, f"undecodable {conn.msgtype} message: {exc}")
                continue
            if self.msgtype == POINTCLOUD2:
                yield self._said(self.poser.scan(msg, origin, int(t_bag)))
            else:
                yield self._said(self.poser.detections(msg, origin, int(t_bag)))

    def _said(self, item: Any) -> Any:
        """``item``, after logging what the poser noted meanwhile (once each)."""
        for note in self.poser.notes:
            log.info("%s: %s", self.path, note)
        self.poser.notes.clear()
        return item

    def close(self) -> None:
        reader, self.reader = getattr(self, "reader", None), None
        if reader is not None:
            try:
                reader.close()
            except Exception:
                pass
