"""A ROS scan's (or a detector's DetectedObjects') pose in the world and a scan's turn into the vehicle's axes, from
TF or a pose topic.

One piece shared by the two ways ROS 2 scans come in: a bag (:mod:`.bag`, every pose message read before the
first scan) and a live topic bridged into Zenoh (:mod:`jitterguard.services.ros2live`, pose messages as they come,
interleaved with the scans). The rules are :mod:`.bag`'s module doc: TF composes the chain from the tree's root
down to the cloud's frame (dynamic links interpolated at the scan's stamp, clamped outside their span), a pose
topic is interpolated and composed with the ``/tf_static`` chain to the cloud's frame; a cloud under the base frame
by a static chain is turned into the base frame's axes at the sensor. Pure: rosbags' message objects in (attribute
access only), frames out.
"""

from __future__ import annotations

import bisect
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import ValidationError

from ....geometry import rotation_from_quaternion
from ....schemas.wire import LIMITS
from ..frames import IDENTITY, NO_POSE_YET, DetectionFrame, EgoPose, FrameError, ScanFrame, compose, finite_rows
from .nuscenes import FRAME_SUFFIX, turn_points
from .ros_types import NEWER_LABELS, detected_object_from_ros, interpolate_pose, pointcloud2_to_array, pose_of, stamp_ns
from .tf import TfTree

LEVEL_TOLERANCE = 1e-9
"""A mount whose rotation matrix is the identity within this (each entry) is level and x-forward: not turned."""
TF_BASE_FRAME = "base_link"
"""The vehicle's frame in a TF tree (REP-105): clouds under it are turned into its axes."""
WORLD_FRAMES = frozenset({"map", "odom", "world", "earth"})
"""REP-105's fixed frames: a TF tree rooted in one of them puts what hangs under it in the world."""


def _unit(pose: EgoPose) -> bool:
    """A unit quaternion and a finite position: a pose that can be interpolated and composed (tf2 refuses a transform
    holding NaN, TF_NAN_INPUT; a NaN odometry position had gone into every scan interpolated from it)."""
    return (abs(math.hypot(pose.qx, pose.qy, pose.qz, pose.qw) - 1.0) <= LIMITS.max_quaternion_error
            and math.isfinite(pose.x) and math.isfinite(pose.y) and math.isfinite(pose.z))


class ScanPoser:
    """Poses from TF (``use_tf``) or from a pose topic's samples, or none (the identity)."""

    def __init__(self, *, use_tf: bool = False, turn_clouds: bool = True, max_clamp_ns: int | None = None) -> None:
        """``max_clamp_ns``: a scan stamped further than this outside the poses' span has no pose (a bag's scans
        before its localization started); None: posed at the nearest sample however far (live, where the newest
        scan is always past the newest pose and the service waits for it first)."""
        self.use_tf = use_tf
        self.max_clamp_ns = max_clamp_ns
        self.turn_clouds = turn_clouds  # PointCloud2 scans are turned into the base frame's axes; boxes are not
        self.tf = TfTree()
        self.tf_skipped: dict[str, int] = {}  # child frame → transforms skipped: no unit quaternion or not finite
        self.pose_times: list[int] = []
        self.poses: list[EgoPose] = []
        self.poses_skipped = 0  # pose messages without a unit quaternion (a GNSS fix without heading) or finite x, y, z
        self.base_frame: str | None = None  # the pose topic's child_frame_id (e.g. base_link)
        self.notes: list[str] = []  # said once each: the turn of a mount, why a cloud keeps its own axes
        self._levels: dict[str, tuple[NDArray[np.float64], EgoPose] | None] = {}
        self._warned_extrinsic = False
        self._said: set[str] = set()  # notes about messages, said once each though the caller clears ``notes``

    # ------------------------------------------------------------------------------------------ pose messages

    def add_tf(self, msg: Any, fallback_ns: int, *, static: bool) -> None:
        """Every transform of a ``tf2_msgs/TFMessage`` (stamped by its header, ``fallback_ns`` where that is 0). A
        rotation that is not a unit quaternion (an all-zero one from a hand-written static transform) or a translation
        that is not finite is skipped and counted, as tf2 ignores it: composed into a scan's pose it went out as an
        ego pose every consumer refuses (a NaN one ended the replay)."""
        for tr in msg.transforms:
            r, q = tr.transform.translation, tr.transform.rotation
            pose = EgoPose(float(r.x), float(r.y), float(r.z), float(q.x), float(q.y), float(q.z), float(q.w))
            if not _unit(pose):
                child = tr.child_frame_id.lstrip("/")
                self.tf_skipped[child] = self.tf_skipped.get(child, 0) + 1
                continue
            self.tf.add(tr.header.frame_id, tr.child_frame_id, stamp_ns(tr.header) or fallback_ns, pose, static=static)
        if static:
            self._levels.clear()  # a mount that arrives (or changes) after a scan was turned without it

    def add_pose(self, msg: Any, fallback_ns: int) -> bool:
        """One Odometry / PoseStamped / PoseWithCovarianceStamped sample (kept in stamp order); whether it was
        usable (a unit quaternion, a finite position)."""
        pose = pose_of(msg)
        if not _unit(pose):
            self.poses_skipped += 1
            return False
        t = stamp_ns(msg.header) or fallback_ns
        i = bisect.bisect_right(self.pose_times, t)
        self.pose_times.insert(i, t)
        self.poses.insert(i, pose)
        if self.base_frame is None:
            self.base_frame = getattr(msg, "child_frame_id", "") or None
        return True

    def forget_before(self, stamp: int) -> None:
        """Drop pose samples older than ``stamp`` but the last one before it (a live stream's memory stays bounded;
        a scan is never posed from before its own stamp's neighbours)."""
        self.tf.forget_before(stamp)
        i = bisect.bisect_left(self.pose_times, stamp) - 1
        if i > 0:
            del self.pose_times[:i], self.poses[:i]

    # ------------------------------------------------------------------------------------------ a scan's pose

    def base(self) -> str | None:
        """The vehicle's frame clouds are turned into, when the poses name one."""
        if not self.turn_clouds:
            return None
        if self.use_tf:
            return TF_BASE_FRAME
        if self.poses and self.base_frame:
            return self.base_frame.lstrip("/")
        return None

    def levelling(self, frame_id: str) -> tuple[NDArray[np.float64], EgoPose] | None:
        """For a scan in ``frame_id``: R, the frame's rotation in the base frame by the static chain (p' = R p),
        and the turn (no translation, Rᵀ) to compose onto its pose — or None when the scan goes out as it is (no
        base frame, no static chain from it, or a level x-forward mount). Cached; adds its note once."""
        if frame_id in self._levels:
            return self._levels[frame_id]
        found: tuple[NDArray[np.float64], EgoPose] | None = None
        note = None
        base = self.base()
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
        if note is not None and note not in self.notes:
            self.notes.append(note)
        return found

    def pose(self, frame_id: str, t: int) -> EgoPose | str:
        """The pose of ``frame_id`` in the world at ``t``, or why there is none."""
        if self.use_tf:
            try:
                if frame_id in self.tf and self.tf.root(frame_id) == TF_BASE_FRAME:
                    # the vehicle's frame is never the world (REP-105): nothing above it yet, as while a live stack's
                    # localization has no pose; posed in it, the scan had gone out with the mount for its world pose
                    return (f"no TF above {TF_BASE_FRAME} for the scan: nothing puts the vehicle in the world yet"
                            f" (localization's map -> {TF_BASE_FRAME})")
                broken = self._broken_chain(frame_id)
                if broken:
                    return broken
                return self._outside(self.tf.span(frame_id), t, "the TF tree's") or self.tf.lookup(frame_id, t)
            except ValueError as exc:  # a cycle above the frame
                return f"no TF for the scan: {exc}"
            except KeyError as exc:
                return f"no TF for the scan: {exc.args[0]}{self._skipped()}"
        if not self.poses:
            return IDENTITY
        outside = self._outside((self.pose_times[0], self.pose_times[-1]), t, "the pose topic's")
        if outside:
            return outside
        base = interpolate_pose(self.pose_times, self.poses, t)
        if self.base_frame and frame_id == self.base_frame.lstrip("/"):
            return base  # a cloud in the pose topic's own frame (Autoware's concatenated cloud in base_link)
        if self.base_frame and frame_id in self.tf and self.base_frame in self.tf:
            try:
                return compose(base, self.tf.lookup(frame_id, t, ancestor=self.base_frame))
            except KeyError:
                pass
        if not self._warned_extrinsic:
            self._warned_extrinsic = True
            self.notes.append(f"no /tf_static path from {self.base_frame or 'the pose topic frame'} to {frame_id}: "
                              "the vehicle pose stands in for the sensor's")
        return base

    def _broken_chain(self, frame_id: str) -> str | None:
        """Why the TF chain from ``frame_id`` does not reach the world, naming the missing link, or None. Its top frame
        (the root it stops at) is taken for the world unless it is plainly not one: it is no REP-105 fixed frame and
        either ``base_link`` hangs in another tree (the chain never reaches the vehicle: a sensor kit's link to it
        missing) or every link on the way is static (nothing moves the sensor: a mount alone). Such a scan had gone
        out posed at its mount near the world's origin, since only a root of ``base_link`` itself was refused."""
        if frame_id not in self.tf:
            return None  # the lookup says so, naming the frame
        top = self.tf.root(frame_id)
        if top in WORLD_FRAMES:
            return None
        chain = self.tf.chain(frame_id)
        apart = TF_BASE_FRAME in self.tf and self.tf.root(TF_BASE_FRAME) != top
        if not apart and any(c not in self.tf.static for c in chain):
            return None  # a moving chain to a root of another name (a SLAM's own fixed frame): taken as the world
        path = " -> ".join([*chain, top])
        if apart:
            base_root = self.tf.root(TF_BASE_FRAME)
            tree = f"{TF_BASE_FRAME!r}" + (f" (under {base_root!r})" if base_root != TF_BASE_FRAME else "")
            return (f"no TF for the scan: the link from {TF_BASE_FRAME!r} (or a frame under it) to {top!r} is missing:"
                    f" the chain {path} stops at {top!r}, apart from {tree}{self._skipped()}")
        return (f"no TF for the scan: the link from the world to {top!r} is missing: the chain {path} stops at {top!r}"
                f" by static links only, so nothing puts the sensor in the world{self._skipped()}")

    def _skipped(self) -> str:
        """The transforms skipped as unusable, for a refusal's reason (one may be the missing link)."""
        return "".join(f"; {n} transform(s) to {f!r} skipped: rotation not a unit quaternion or not finite"
                       for f, n in sorted(self.tf_skipped.items()))

    def _outside(self, span: tuple[int, int] | None, t: int, whose: str) -> str | None:
        """Why a scan at ``t`` has no pose when it lies more than ``max_clamp_ns`` outside ``span`` (else None): it
        had been posed at the first (last) sample, however long before localization began, so a vehicle driving
        all that while stood still and every static object around it moved."""
        if self.max_clamp_ns is None or span is None:
            return None
        first, last = span
        if t < first - self.max_clamp_ns:
            return f"{NO_POSE_YET}: the scan is {(first - t) / 1e9:.2f} s before {whose} first sample"
        if t > last + self.max_clamp_ns:
            return f"no pose any more: the scan is {(t - last) / 1e9:.2f} s after {whose} last sample"
        return None

    def scan(self, msg: Any, origin: str, fallback_ns: int) -> ScanFrame | FrameError:
        """A ``sensor_msgs/PointCloud2`` as a posed scan (finite rows, turned into the base frame's axes where its
        mount is static), or why it cannot be one."""
        stamp = stamp_ns(msg.header) or fallback_ns
        # ROS 1 habit "/velodyne": the frame is "velodyne" (as the TF lookup reads it); a leading slash would go on
        # into every message downstream, and ROS 2's tf2 refuses frame IDs that start with one
        frame_id = msg.header.frame_id.lstrip("/") or "lidar"
        pose = self.pose(frame_id, stamp)
        if isinstance(pose, str):
            return FrameError(origin, pose)
        try:
            pts, names = pointcloud2_to_array(msg)
        except ValueError as exc:
            return FrameError(origin, f"bad PointCloud2: {exc}", invalid=True)
        pts, _ = finite_rows(pts)
        level = self.levelling(frame_id)
        if level is not None:  # into the base frame's axes at the sensor
            rot, turn = level
            pts, pose, frame_id = turn_points(pts, rot), compose(pose, turn), frame_id + FRAME_SUFFIX
        return ScanFrame(stamp, pose, pts, names, origin, frame_id)

    def detections(self, msg: Any, origin: str, fallback_ns: int) -> DetectionFrame | FrameError:
        """An ``autoware_perception_msgs/DetectedObjects`` as a posed frame of detections (the boxes stay in their
        frame: the tracker moves them into the world by the pose), or why it cannot be one."""
        stamp = stamp_ns(msg.header) or fallback_ns
        frame_id = msg.header.frame_id.lstrip("/") or "lidar"  # as scan() reads a cloud's
        pose = self.pose(frame_id, stamp)
        if isinstance(pose, str):
            return FrameError(origin, pose)
        newer = sorted({NEWER_LABELS[int(c.label)] for o in msg.objects for c in o.classification
                        if int(c.label) in NEWER_LABELS})
        if newer:
            note = f"classes {', '.join(newer)} (newer autoware_msgs labels) read as UNKNOWN"
            if note not in self._said:
                self._said.add(note)
                self.notes.append(note)
        try:
            objects = [detected_object_from_ros(o) for o in msg.objects]
        except ValidationError as exc:
            err = exc.errors(include_url=False)[0]
            loc = ".".join(str(p) for p in err.get("loc", ()))
            return FrameError(origin, f"invalid DetectedObject ({loc}: {err.get('msg')})", invalid=True)
        except (AttributeError, TypeError, ValueError) as exc:
            return FrameError(origin, f"unexpected DetectedObjects layout: {exc}", invalid=True)
        return DetectionFrame(stamp, pose, objects, origin, frame_id)
