"""Join one frame's messages from every stage into one :class:`JoinedFrame` — the pure core of the bridges out of
jitterguard (the Foxglove server and MCAP recorder, the ROS 2 bag recorder).

A frame is the set of messages that share a ``header.seq`` and ``header.stamp`` (every stage passes both on
unchanged; the stamp keeps a second publisher on the namespace — a test replay, a stray tool — from joining its
scan of the same seq into the frame: kept apart, it is dropped with the frame's older inputs and counted
``stamp_mismatch``): the replay's ``points`` (or ``detections`` at detection
level) and optional ``groundtruth``, the detector's ``detections``, the tracker's ``tracked`` (whose
``observed_track_ids`` that are also among the classifier's ``objects`` say which ``motion/{id}`` messages the frame
will have: tentative tracks may be observed but get none), the classifier's ``objects`` and
its ``motion/{id}``. Nothing orders messages across keys (DESIGN.md), and the classifier publishes ``objects`` before
the frame's ``motion/{id}``, so:

- ``objects`` of seq N opens the frame for output; it is emitted once every ``motion/{id}`` of the IDs ``tracked`` N
  listed has arrived and so has every input stream (points, detections, ground truth) the previous frame out had
  (nothing orders the detector's ``detections`` N before the classifier's ``objects`` N at a bridge: on a loaded
  machine a bag had lost one frame's detections that way; the first frame of a run, with no frame before it, waits
  for all three), or ``motion_wait_s`` after ``objects`` N arrived (what arrived by then goes out; the rest is
  counted ``motion_missing``), or as soon as a later frame's ``objects`` arrives (the classifier sheds the motion
  messages of a frame when it is behind; a viewer must not fall behind waiting for them);
- inputs (points, detections, ground truth, tracked, motion) wait in per-seq buffers holding at most
  ``max_pending`` frames; the oldest go first (counted) — a frame that never gets its ``objects`` (the classifier
  was down) must not pin memory;
- a seq lower than the last emitted one is a straggler of a frame already out (dropped, ``late_messages``) while it
  is at most ``RESTART_GAP`` frames back and carries the stamp that frame went out with; further back, or under
  another stamp (a replay looping on wall-clock stamps), the upstream restarted (a replay restarted by supervisord
  starts again at seq 0) once ``objects`` says so: the open frames and the emitted seqs are forgotten, counted
  ``seq_restarts``; inputs that arrived first are kept for the restarted run's frames.

No I/O, no clock: callers pass ``now`` (monotonic seconds).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

from ...schemas.models import (
    DetectedObjects,
    GroundTruthObjects,
    MotionState,
    PointCloud,
    Pose,
    TrackedObjects,
)
from ...schemas.wire import LIMITS

T = TypeVar("T")


def motion_expected(tracked: TrackedObjects, objects: TrackedObjects) -> list[str]:
    """The IDs that get a ``motion/{id}`` in a frame: observed (``tracked``) and published (the classifier's
    ``objects``); a tracker with ``observe_tentative`` lists its tentative tracks as observed too (the
    classifier's windows start with them), but they have no motion state."""
    published = {o.object_id for o in objects.objects}
    return [t for t in tracked.observed_track_ids if t in published]


DEFAULT_MOTION_WAIT_S = 0.25
DEFAULT_MAX_PENDING = 32
MAX_MOTION_PER_FRAME = LIMITS.max_objects
"""``motion/{id}`` messages kept per frame: a frame has at most ``max_objects`` objects, so more are made-up track IDs
(anyone on the bus may put one); beyond it they are dropped and counted ``motion_dropped`` — the per-frame buffer had
grown with every ID put."""
RESTART_GAP = 8
"""A message this many frames behind the last one out is no straggler (a frame goes out once its motion states are
in, ``motion_wait_s`` after its objects, or when a later frame's objects arrive: what is late is a frame or two
late) but a restarted upstream. Until 3 Dec it was ``max_pending`` (32): a replay that started over within 3.2 s
(a short ``--loop`` pass, an early supervisord restart) had every later frame dropped as late."""


@dataclass
class JoinedFrame:
    """Everything the pipeline said about one frame (``objects`` always; the rest when it exists)."""

    seq: int
    stamp_ns: int
    objects: TrackedObjects
    points: PointCloud | None = None
    detections: DetectedObjects | None = None
    groundtruth: GroundTruthObjects | None = None
    tracked: TrackedObjects | None = None
    motion: dict[str, MotionState] = field(default_factory=dict)
    """This frame's ``MotionState`` per track ID (only tracks observed in the frame have one)."""
    last_motion: dict[str, MotionState] = field(default_factory=dict)
    """For tracks in ``objects`` without a ``MotionState`` this frame: the latest one of an earlier frame."""

    @property
    def sensor_pose(self) -> Pose | None:
        """The sensor's pose in the world at this frame (from the scan, else from the detections)."""
        if self.points is not None:
            return self.points.ego_pose
        if self.detections is not None:
            return self.detections.ego_pose
        return None

    @property
    def sensor_frame(self) -> str:
        for msg in (self.points, self.detections):
            if msg is not None and msg.header.frame_id:
                return msg.header.frame_id
        return "lidar"

    @property
    def world_frame(self) -> str:
        return self.objects.header.frame_id or "map"


Frame = tuple[int, int]
"""A frame's (seq, stamp)."""


class _BySeq(Generic[T]):
    """A bounded (seq, stamp) → value map that forgets its oldest entries first."""

    def __init__(self, cap: int) -> None:
        self.cap = cap
        self.items: OrderedDict[Frame, T] = OrderedDict()

    def put(self, frame: Frame, value: T) -> int:
        """Store; returns how many old entries were dropped to stay within ``cap``."""
        self.items[frame] = value
        self.items.move_to_end(frame)
        dropped = 0
        while len(self.items) > self.cap:
            self.items.popitem(last=False)
            dropped += 1
        return dropped

    def pop(self, frame: Frame) -> T | None:
        return self.items.pop(frame, None)

    def drop_through(self, seq: int) -> int:
        """Forget every entry up to ``seq``; returns how many of them had ``seq`` itself (under another stamp)."""
        gone = [f for f in self.items if f[0] <= seq]
        for f in gone:
            del self.items[f]
        return sum(1 for f in gone if f[0] == seq)

    def clear(self) -> None:
        self.items.clear()


class FrameJoiner:
    """Collects messages per seq and releases :class:`JoinedFrame` s in seq order (see the module docstring)."""

    def __init__(self, motion_wait_s: float = DEFAULT_MOTION_WAIT_S, max_pending: int = DEFAULT_MAX_PENDING) -> None:
        if motion_wait_s < 0 or max_pending < 1:
            raise ValueError("motion_wait_s must be >= 0 and max_pending >= 1")
        self.motion_wait_s = motion_wait_s
        self.counters: dict[str, int] = {}
        self._points: _BySeq[PointCloud] = _BySeq(max_pending)
        self._detections: _BySeq[DetectedObjects] = _BySeq(max_pending)
        self._truth: _BySeq[GroundTruthObjects] = _BySeq(max_pending)
        self._tracked: _BySeq[TrackedObjects] = _BySeq(max_pending)
        self._motion: _BySeq[dict[str, MotionState]] = _BySeq(max_pending)
        self._open: OrderedDict[int, tuple[TrackedObjects, float]] = OrderedDict()  # seq → (objects, arrived at)
        self._last_emitted = -1
        self._emitted: OrderedDict[int, int] = OrderedDict()  # seq → stamp of the last frames out
        self._latest: dict[str, MotionState] = {}  # track ID → its latest MotionState, for tracks still reported
        # the input streams the last frame out had: the next one waits for them; None before the first frame out
        # (or after a restart): it waits for every one, at most motion_wait_s (its detections may be late too)
        self._expected: list[_BySeq[Any]] | None = None

    def _count(self, name: str, n: int = 1) -> None:
        if n:
            self.counters[name] = self.counters.get(name, 0) + n

    def _restart_check(self, seq: int, stamp: int, *, anchor: bool = False) -> bool:
        """False if (``seq``, ``stamp``) belongs to a frame already emitted (a straggler). When the seqs went back
        further than a straggler could, or an emitted seq comes back under another stamp, the upstream restarted —
        as the frames' anchor, ``objects``, says: it starts the joiner over. An input that says so is kept, keyed
        by its seq and stamp, for the restarted run's objects to take: it may as well be a second publisher's on the
        namespace (a test replay), and each of its messages had cleared every frame in flight."""
        if seq > self._last_emitted:
            return True
        out_as = self._emitted.get(seq)
        if self._last_emitted - seq > RESTART_GAP or (out_as is not None and out_as != stamp):
            if not anchor:
                return True
            self._open.clear()
            self._latest.clear()
            self._expected = None
            self._emitted.clear()
            self._last_emitted = -1
            self._count("seq_restarts")
            return True
        self._count("late_messages")
        return False

    # ---------------------------------------------------------------------------------------- inputs

    def _keep(self, buffer: _BySeq[Any], msg: Any) -> None:
        if self._restart_check(msg.header.seq, msg.header.stamp):
            self._count("dropped_pending", buffer.put((msg.header.seq, msg.header.stamp), msg))

    def add_points(self, msg: PointCloud) -> None:
        self._keep(self._points, msg)

    def add_detections(self, msg: DetectedObjects) -> None:
        self._keep(self._detections, msg)

    def add_groundtruth(self, msg: GroundTruthObjects) -> None:
        self._keep(self._truth, msg)

    def add_tracked(self, msg: TrackedObjects) -> None:
        self._keep(self._tracked, msg)

    def add_motion(self, msg: MotionState) -> None:
        seq = msg.header.seq
        if not self._restart_check(seq, msg.header.stamp):
            return
        frame = (seq, msg.header.stamp)
        per = self._motion.items.get(frame)
        if per is None:
            per = {}
            self._count("dropped_pending", self._motion.put(frame, per))
        if len(per) >= MAX_MOTION_PER_FRAME and msg.track_id not in per:
            self._count("motion_dropped")
            return
        per[msg.track_id] = msg

    def add_objects(self, msg: TrackedObjects, now: float) -> None:
        seq = msg.header.seq
        if self._restart_check(seq, msg.header.stamp, anchor=True):
            self._open[seq] = (msg, now)
            self._open.move_to_end(seq)

    # ---------------------------------------------------------------------------------------- output

    def _complete(self, seq: int, objects: TrackedObjects) -> bool:
        frame = (seq, objects.header.stamp)
        tracked = self._tracked.items.get(frame)
        if tracked is None:
            return False
        expected = self._expected if self._expected is not None else (self._points, self._detections, self._truth)
        if any(frame not in buffer.items for buffer in expected):
            return False
        got = self._motion.items.get(frame, {})
        return all(t in got for t in motion_expected(tracked, objects))

    def poll(self, now: float) -> list[JoinedFrame]:
        """Frames ready to go out, in seq order: complete, timed out, or overtaken by a later ``objects``."""
        out: list[JoinedFrame] = []
        for seq in sorted(self._open):
            objects, t_open = self._open[seq]
            later = any(s > seq for s in self._open)
            if not (later or self._complete(seq, objects) or now - t_open >= self.motion_wait_s):
                break  # frames go out in order: a waiting frame holds the later ones back
            del self._open[seq]
            out.append(self._take(seq, objects))
        return out

    def flush(self) -> list[JoinedFrame]:
        """Every open frame, now (at shutdown)."""
        return [self._take(seq, self._open.pop(seq)[0]) for seq in sorted(self._open)]

    def _take(self, seq: int, objects: TrackedObjects) -> JoinedFrame:
        key = (seq, objects.header.stamp)
        tracked = self._tracked.pop(key)
        motion = self._motion.pop(key) or {}
        if tracked is not None:
            self._count("motion_missing", sum(1 for t in motion_expected(tracked, objects) if t not in motion))
        ids = [o.object_id for o in objects.objects]
        last = {t: self._latest[t] for t in ids if t not in motion and t in self._latest}
        self._latest = {t: m for t in ids if (m := motion.get(t) or self._latest.get(t)) is not None}
        frame = JoinedFrame(seq=seq, stamp_ns=objects.header.stamp, objects=objects, points=self._points.pop(key),
                            detections=self._detections.pop(key), groundtruth=self._truth.pop(key),
                            tracked=tracked, motion=motion, last_motion=last)
        for b in (self._points, self._detections, self._truth, self._tracked, self._motion):
            # older frames never got their objects: they will not be emitted; this seq under another stamp is
            # another publisher's
            self._count("stamp_mismatch", b.drop_through(seq))
        self._expected = [b for b, v in ((self._points, frame.points), (self._detections, frame.detections),
                                          (self._truth, frame.groundtruth)) if v is not None]
        self._last_emitted = max(self._last_emitted, seq)
        self._emitted[seq] = objects.header.stamp
        while len(self._emitted) > self._points.cap:
            self._emitted.popitem(last=False)
        self._count("frames")
        return frame
