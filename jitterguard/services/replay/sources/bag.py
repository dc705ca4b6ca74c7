"""ROS 2 bags (sqlite3 ``.db3`` or MCAP, a bag folder or a bare ``.mcap``) and ROS 1 ``.bag`` via rosbags.

One topic is replayed: a ``sensor_msgs/PointCloud2`` topic (``points``) or an Autoware
``autoware_perception_msgs/DetectedObjects`` topic (``detections``). With ``--topic`` unset, the bag's only
topic of either type is picked (PointCloud2 first); several candidates are an error that lists them.
Stamps come from each message's header (the sensor's time), falling back to the bag's receive time when a
driver left the header stamp at zero. The ego pose (the pose of the message's ``frame_id`` in the world)
comes from ``--pose-topic``:

- a ``tf2_msgs/TFMessage`` topic (``/tf``): the TF chain from the tree's root (``map``) down to the cloud's
  frame, with ``/tf_static`` for the fixed links, each dynamic link interpolated at the scan's stamp;
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
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import ValidationError

from ....geometry import rotation_from_quaternion

from ....schemas.wire import LIMITS

from ..frames import (
    IDENTITY,
    DetectionFrame,
    EgoPose,
    FrameError,
    Item,
    ScanFrame,
    SourceError,
    SourceInfo,
    compose,
    finite_rows,
)
from .base import Source
from .nuscenes import FRAME_SUFFIX, turn_points
from .ros_types import (
    DETECTED_OBJECTS,
    TF_MESSAGE,
    POINTCLOUD2,
    POSE_TYPES,
    detected_object_from_ros,
    interpolate_pose,
    pointcloud2_to_array,
    pose_of,
    stamp_ns,
    typestore,
)
from .tf import TfTree

log = logging.getLogger("jitterguard.replay")

BAG_SUFFIXES = (".mcap", ".db3", ".bag")
LEVEL_TOLERANCE = 1e-9
"""A mount whose rotation matrix is the identity within this (each entry) is level and x-forward: not turned."""
TF_BASE_FRAME = "base_link"
"""The vehicle's frame in a TF tree (REP-105): clouds under it are turned into its axes (module doc)."""


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
        self._warned_extrinsic = False
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
            if msgtype not in (POINTCLOUD2, DETECTED_OBJECTS):
                raise SourceError(f"{self.path}: topic {topic} is {msgtype}, not {POINTCLOUD2} or {DETECTED_OBJECTS}")
            if sum(c.msgcount for c in by_topic[topic]) == 0:  # said as it is, not as "--start 0 is past the end"
                with_msgs = ", ".join(t for t, cs in sorted(by_topic.items())
                                      if cs[0].msgtype in (POINTCLOUD2, DETECTED_OBJECTS)
                                      and sum(c.msgcount for c in cs) > 0) or "none"
                raise SourceError(f"{self.path}: topic {topic} holds no messages (topics of scans or detections"
                                  f" with messages: {with_msgs})")
        else:  # the scans, else the detections — of the topics that hold messages (a recording of a stack fed
            # detections has an empty scan topic beside them)
            for wanted in (POINTCLOUD2, DETECTED_OBJECTS):
                cands = sorted(t for t, cs in by_topic.items()
                               if cs[0].msgtype == wanted and sum(c.msgcount for c in cs) > 0)
                if len(cands) > 1:
                    raise SourceError(f"{self.path}: several {wanted} topics ({', '.join(cands)}); pick one with --topic")
                if cands:
                    topic = cands[0]
                    break
            else:
                raise SourceError(f"{self.path}: no {POINTCLOUD2} or {DETECTED_OBJECTS} topic with messages (topics:"
                                  f" {listing})")
        assert topic is not None
        self.topic = topic
        self.msgtype = by_topic[topic][0].msgtype
        self.connections = by_topic[topic]
        kind = "points" if self.msgtype == POINTCLOUD2 else "detections"
        count = sum(c.msgcount for c in self.connections)

        self.pose_times: list[int] = []
        self.poses: list[EgoPose] = []
        self.tf = TfTree()
        self.tf_skipped: dict[str, int] = {}  # child frame → transforms skipped: rotation not a unit quaternion
        self.use_tf = False
        self.base_frame: str | None = None
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
                self.use_tf = True
                notes.append(f"poses from the TF tree ({pose_topic}{' + ' + ', '.join(statics) if statics else ''})")
            elif ptype in POSE_TYPES:
                self._read_pose_topic(pose_topic, by_topic[pose_topic])
                skipped = (f"; {self.poses_skipped} skipped: orientation not a unit quaternion"
                           if self.poses_skipped else "")
                notes.append(f"poses from {pose_topic} ({len(self.poses)} samples{skipped})")
            else:
                raise SourceError(
                    f"{self.path}: pose topic {pose_topic} is {ptype}, not {TF_MESSAGE} or one of {', '.join(POSE_TYPES)}"
                )
        warnings = []
        if self.tf_skipped:
            warnings.append(f"{self.path}: TF transforms whose rotation is not a unit quaternion skipped (as tf2 does): "
                            + ", ".join(f"{n} to {f!r}" for f, n in sorted(self.tf_skipped.items())))
        if pose_topic is None and count > 1:
            warnings.append(f"{self.path}: no --pose-topic: every {topic} message is published at the identity"
                            " pose, so if the sensor moved, static objects will look dynamic")
        self.info = SourceInfo(name=f"{self.path}:{topic}", kind=kind, num_frames=count, notes=notes,
                               warnings=warnings)
        self._levels: dict[str, tuple[NDArray[np.float64], EgoPose] | None] = {}
        if self.msgtype == POINTCLOUD2 and pose_topic is not None:
            first = self._first_frame_id()
            if first is not None:
                self._levelling(first)  # its note, before the replay starts

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

    def _base_of(self) -> str | None:
        """The vehicle's frame the scans are turned into, when the poses name one (module doc)."""
        if self.msgtype != POINTCLOUD2:
            return None
        if self.use_tf:
            return TF_BASE_FRAME
        if self.poses and self.base_frame:
            return self.base_frame.lstrip("/")
        return None

    def _levelling(self, frame_id: str) -> tuple[NDArray[np.float64], EgoPose] | None:
        """For a scan in ``frame_id``: R, the frame's rotation in the base frame by the static chain (p' = R p),
        and the turn (no translation, Rᵀ) to compose onto its pose — or None when the scan goes out as it is (no
        base frame, no static chain from it, or a level x-forward mount). Cached; adds its note once."""
        if frame_id in self._levels:
            return self._levels[frame_id]
        found: tuple[NDArray[np.float64], EgoPose] | None = None
        note = None
        base = self._base_of()
        if base is not None:
            try:
                mount = self.tf.static_lookup(frame_id, base)
            except KeyError:
                pass  # no chain from the base frame: the pose is what it was (for a pose topic, the vehicle's)
            except ValueError as exc:
                note = (f"clouds kept in {frame_id}'s own axes: {exc} (only a static mount is turned into "
                        f"{base}'s axes)")
            else:
                rot = rotation_from_quaternion(mount.qx, mount.qy, mount.qz, mount.qw)
                if np.abs(rot - np.eye(3)).max() > LEVEL_TOLERANCE:
                    n = math.hypot(mount.qx, mount.qy, mount.qz, mount.qw)  # R's own (unit) quaternion, inverted
                    found = rot, EgoPose(qx=-mount.qx / n, qy=-mount.qy / n, qz=-mount.qz / n, qw=mount.qw / n)
                    tilt = math.degrees(math.acos(min(1.0, max(-1.0, float(rot[2, 2])))))
                    yaw = math.degrees(math.atan2(rot[1, 0], rot[0, 0]))
                    note = (f"clouds turned into {base}'s axes at the sensor, frame {frame_id}{FRAME_SUFFIX} "
                            f"(mount tilt {tilt:.1f}°, yaw {yaw:.1f}°)")
        self._levels[frame_id] = found
        if note is not None:
            self.info.notes.append(note)
        return found

    def _messages(self, conns: list[Any], what: str) -> Iterator[tuple[int, Any]]:
        for conn, t_bag, raw in self.reader.messages(connections=conns):
            try:
                yield int(t_bag), self.reader.deserialize(raw, conn.msgtype)
            except Exception as exc:
                raise SourceError(f"{self.path}: {what} {conn.topic}: undecodable message: {exc}") from None

    def _read_tf(self, conns: list[Any], *, static: bool) -> None:
        for t_bag, msg in self._messages(conns, "TF topic"):
            for tr in msg.transforms:
                r, q = tr.transform.translation, tr.transform.rotation
                pose = EgoPose(float(r.x), float(r.y), float(r.z), float(q.x), float(q.y), float(q.z), float(q.w))
                if not abs(math.hypot(pose.qx, pose.qy, pose.qz, pose.qw) - 1.0) <= LIMITS.max_quaternion_error:
                    # e.g. an all-zero rotation from a hand-written static transform: composed into the scan's
                    # pose it went out as an ego pose every consumer refuses (and as "0 unreadable"); tf2 too
                    # ignores such a transform
                    child = tr.child_frame_id.lstrip("/")
                    self.tf_skipped[child] = self.tf_skipped.get(child, 0) + 1
                    continue
                self.tf.add(tr.header.frame_id, tr.child_frame_id, stamp_ns(tr.header) or t_bag, pose, static=static)

    def _read_pose_topic(self, topic: str, conns: list[Any]) -> None:
        samples: list[tuple[int, EgoPose]] = []
        no_heading = 0
        for t_bag, msg in self._messages(conns, "pose topic"):
            pose = pose_of(msg)
            if not abs(math.hypot(pose.qx, pose.qy, pose.qz, pose.qw) - 1.0) <= LIMITS.max_quaternion_error:
                no_heading += 1  # e.g. a GNSS fix without heading (all-zero quaternion): no orientation to use
                continue
            samples.append((stamp_ns(msg.header) or t_bag, pose))
            if self.base_frame is None:
                self.base_frame = getattr(msg, "child_frame_id", "") or None
        self.poses_skipped = no_heading
        if not samples:
            raise SourceError(f"{self.path}: pose topic {topic} holds no message with a usable pose"
                              + (f" ({no_heading} without a unit quaternion)" if no_heading else ""))
        samples.sort(key=lambda s: s[0])
        self.pose_times = [s[0] for s in samples]
        self.poses = [s[1] for s in samples]

    def _pose(self, frame_id: str, t: int) -> EgoPose | str:
        """The pose of ``frame_id`` in the world at ``t``, or why there is none."""
        if self.use_tf:
            try:
                return self.tf.lookup(frame_id, t)
            except KeyError as exc:
                skipped = "".join(f"; {n} transform(s) to {f!r} skipped: rotation not a unit quaternion"
                                  for f, n in sorted(self.tf_skipped.items()))
                return f"no TF for the scan: {exc.args[0]}{skipped}"
        if not self.poses:
            return IDENTITY
        base = interpolate_pose(self.pose_times, self.poses, t)
        if self.base_frame and frame_id in self.tf and self.base_frame in self.tf:
            try:
                return compose(base, self.tf.lookup(frame_id, t, ancestor=self.base_frame))
            except KeyError:
                pass
        if not self._warned_extrinsic:
            self._warned_extrinsic = True
            log.info("%s: no /tf_static path from %s to %s: the vehicle pose stands in for the sensor's",
                     self.path, self.base_frame or "the pose topic's frame", frame_id)
        return base

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
            stamp = stamp_ns(msg.header) or int(t_bag)
            # ROS 1 habit "/velodyne": the frame is "velodyne" (as the TF lookup reads it); a leading slash would go on
            # into every message downstream, and ROS 2's tf2 refuses frame IDs that start with one
            frame_id = msg.header.frame_id.lstrip("/") or "lidar"
            pose = self._pose(frame_id, stamp)
            if isinstance(pose, str):
                yield FrameError(origin, pose)
                continue
            if self.msgtype == POINTCLOUD2:
                try:
                    pts, names = pointcloud2_to_array(msg)
                except ValueError as exc:
                    yield FrameError(origin, f"bad PointCloud2: {exc}")
                    continue
                pts, _ = finite_rows(pts)
                level = self._levelling(frame_id)
                if level is not None:  # into the base frame's axes at the sensor (module doc)
                    rot, turn = level
                    pts, pose, frame_id = turn_points(pts, rot), compose(pose, turn), frame_id + FRAME_SUFFIX
                yield ScanFrame(stamp, pose, pts, names, origin, frame_id)
            else:
                try:
                    objects = [detected_object_from_ros(o) for o in msg.objects]
                except ValidationError as exc:
                    err = exc.errors(include_url=False)[0]
                    loc = ".".join(str(p) for p in err.get("loc", ()))
                    yield FrameError(origin, f"invalid DetectedObject ({loc}: {err.get('msg')})")
                    continue
                except (AttributeError, TypeError, ValueError) as exc:
                    yield FrameError(origin, f"unexpected DetectedObjects layout: {exc}")
                    continue
                yield DetectionFrame(stamp, pose, objects, origin, frame_id)

    def close(self) -> None:
        reader, self.reader = getattr(self, "reader", None), None
        if reader is not None:
            try:
                reader.close()
            except Exception:
                pass
