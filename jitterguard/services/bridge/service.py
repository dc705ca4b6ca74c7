"""The Zenoh adapter of the bridges: subscribe to every stage's output, join frames (:mod:`.joiner`), hand each
joined frame to a sink (the Foxglove server / MCAP writer, the ROS 2 bag writer).

A bridge is a viewer and recorder beside the pipeline, never in its path: callbacks only validate (the runtime
counts and logs malformed payloads per key) and enqueue; one worker thread joins and writes. When the worker falls
behind, the bounded inbox drops the newest message and counts it (``inbox_dropped``) rather than slowing Zenoh's
delivery to the pipeline's own subscribers. A sink that fails on a frame is counted (``sink_errors``) and logged
once per burst; the next frame is tried again. Its health is the sink's progress: a recording that fails frame after
frame (a full disk) is ``failing`` with the sink's error in its heartbeat, ``status`` and ``/readyz``, and the
runtime's watchdog restarts it (supervised restarts write a numbered file); before, it had stayed ``ok`` while it
wrote nothing.

Counters (heartbeat): ``frames`` (written), ``write_ms_last`` (the sink's time on the latest frame), ``inbox_dropped``,
``sink_errors`` and the joiner's (``motion_missing``,
``dropped_pending``, ``late_messages``, ``seq_restarts``, ``stamp_mismatch``), plus the runtime's ``received`` / ``rejected``.
"""

from __future__ import annotations

import queue
import time
from typing import Any, Protocol

from ...runtime import Service, ZenohOptions
from ...runtime.service import _BurstLogger
from ...schemas import keys
from ...schemas.models import (
    DetectedObjects,
    GroundTruthObjects,
    MotionState,
    PointCloud,
    TrackedObjects,
)
from ...schemas.wire import LIMITS, MAX_MAP_ENTRIES
from ..detector.config import DetectorParams
from .joiner import DEFAULT_MOTION_WAIT_S, FrameJoiner, JoinedFrame

INBOX_CAPACITY = 8192
MAX_SCAN_BYTES = DetectorParams.model_fields["max_scan_bytes"].default
"""A ``points`` payload larger than this is refused unread (the detector's default ``max_scan_bytes``)."""
BOUNDS = {"max_array_len": max(LIMITS.max_objects, LIMITS.max_list_items), "max_map_len": MAX_MAP_ENTRIES}
"""What any message a bridge reads may hold, checked before it is built (the pipeline's own readers hold theirs to
the same :class:`~jitterguard.schemas.wire.Limits`): the bridge reads every message with its pydantic model, and a
1 MB ``detections`` of a million empty objects had cost minutes of its callback thread and gigabytes."""
POLL_S = 0.02
FEED_BATCH = 64
"""Messages joined between two looks for ready frames."""


class FrameSink(Protocol):
    """Where joined frames go. ``write`` runs on the bridge's worker thread only."""

    def write(self, frame: JoinedFrame) -> None: ...

    def close(self) -> None: ...


class BridgeService(Service):
    """Joins the pipeline's messages per frame and writes each frame to ``sink``."""

    name = "bridge"

    def __init__(self, opts: ZenohOptions, sink: FrameSink, *, points: bool = True,
                 motion_wait_s: float = DEFAULT_MOTION_WAIT_S) -> None:
        self.sink = sink
        self.joiner = FrameJoiner(motion_wait_s=motion_wait_s)
        self._inbox: queue.Queue[tuple[str, Any, float]] = queue.Queue(maxsize=INBOX_CAPACITY)
        self._sink_closed = False
        super().__init__(opts)
        self._sink_log = _BurstLogger(self.log)
        self._sink_progress = self.monitor_progress()  # no input() calls: a bridge with nothing to write is idle, not stalled
        self.spawn(self._worker, "worker")
        ns = self.ns
        subs: list[tuple[str, type, str]] = [
            (keys.objects(ns), TrackedObjects, "objects"),
            (keys.tracked(ns), TrackedObjects, "tracked"),
            (keys.motion_all(ns), MotionState, "motion"),
            (keys.detections(ns), DetectedObjects, "detections"),
            (keys.groundtruth(ns), GroundTruthObjects, "groundtruth"),
        ]
        if points:
            subs.append((keys.points(ns), PointCloud, "points"))
        for key, model, kind in subs:
            self.subscribe(key, model, self._enqueue(kind), **BOUNDS,
                           max_bytes=MAX_SCAN_BYTES if kind == "points" else LIMITS.max_payload_bytes)

    def _enqueue(self, kind: str) -> Any:
        def handler(msg: Any, key: str) -> None:
            if kind == "motion" and self.foreign_track(MotionState.__name__, msg.track_id, key,
                                                       keys.motion_all(self.ns)):
                return  # keyed by the payload's ID in the joiner: B's state on A's key had replaced B's own
            try:
                self._inbox.put_nowait((kind, msg, time.monotonic()))
            except queue.Full:
                self.counters.inc("inbox_dropped")
        return handler

    def _feed(self, kind: str, msg: Any, at: float) -> None:
        j = self.joiner
        if kind == "objects":
            j.add_objects(msg, at)
        elif kind == "motion":
            j.add_motion(msg)
        elif kind == "tracked":
            j.add_tracked(msg)
        elif kind == "detections":
            j.add_detections(msg)
        elif kind == "points":
            j.add_points(msg)
        else:
            j.add_groundtruth(msg)

    def _write(self, frames: list[JoinedFrame]) -> None:
        for f in frames:
            t0 = time.perf_counter()
            try:
                self.sink.write(f)
            except Exception as exc:  # noqa: BLE001 - a sink failure loses one frame, never the bridge
                self.counters.inc("sink_errors")
                error = f"writing frame seq {f.seq} failed: {type(exc).__name__}: {exc}"
                self._sink_log.warn(error)
                self._sink_progress.failure(time.monotonic(), error[:200])
                continue
            self._sink_progress.output(time.monotonic())
            self.counters.inc("frames")
            self.counters.set("write_ms_last", round((time.perf_counter() - t0) * 1e3))
            self.last_seq = f.seq
        for k, v in self.joiner.counters.items():
            if k != "frames":
                self.counters.set(k, v)

    def _worker(self) -> None:
        while not self.stop_event.is_set():
            try:
                item: tuple[str, Any, float] | None = self._inbox.get(timeout=POLL_S)
            except queue.Empty:
                item = None
            fed = 0
            while item is not None:
                self._feed(*item)
                fed += 1
                if fed >= FEED_BATCH:  # a busy inbox must not keep ready frames waiting (their inputs age out)
                    break
                try:
                    item = self._inbox.get_nowait()
                except queue.Empty:
                    item = None
            self._write(self.joiner.poll(time.monotonic()))

    def close(self) -> None:
        """Stop and join the worker, close the session, then write the frames still open and close the sink."""
        super().close()
        if self._sink_closed:
            return
        self._sink_closed = True
        self._write(self.joiner.flush())
        try:
            self.sink.close()
        except Exception:  # noqa: BLE001
            self.log.exception("closing the sink failed")
