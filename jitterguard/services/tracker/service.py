"""The tracker's Zenoh adapter: ``detections`` in; ``tracks/{id}`` per observed track, then ``tracked``.

Threading: Zenoh runs each subscriber's callback on its own thread behind a bounded FIFO, so the callbacks here
only validate (the runtime does that) and enqueue. One worker thread owns the :class:`TrackerCore` — nothing
else touches it — and per frame publishes every ``tracks/{id}`` first and the closing ``tracked`` last (the
classifier waits for the IDs that ``tracked.observed_track_ids`` names). All puts use BLOCK congestion
control: a lost observation would silently shorten a classifier window.

Counters (in the heartbeat): ``frames``, ``dropped_duplicate``, ``dropped_out_of_order``, ``dropped_overflow``
(the frame queue was full: the tracker is slower than its input), ``tracks_born``, ``tracks_deleted``,
``resets`` (the source rewound), ``static_hints_applied`` / ``static_hints_unknown`` and the runtime's
``received`` / ``rejected`` / ``published``.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable

from ...runtime import Service, ZenohOptions
from ...schemas import keys
from ...schemas.models import DetectedObjects, MotionState
from .config import TrackerConfig, default_config
from .convert import frame_from_message, frame_messages
from .core import FrameRejected, TrackerCore
from .lifecycle import new_track_id

FRAME_QUEUE = 64


class TrackerService(Service):
    """The ``jitterguard tracker`` process."""

    name = "tracker"

    def __init__(
        self,
        opts: ZenohOptions,
        config: TrackerConfig | None = None,
        *,
        static_hints: bool = False,
        id_factory: Callable[[], str] = new_track_id,
        queue_size: int = FRAME_QUEUE,
    ) -> None:
        # build the core before the session opens: a bad config must fail before anything is on the network
        self.core = TrackerCore(config or default_config(), id_factory)
        self.static_hints = static_hints
        self._frames: queue.Queue[DetectedObjects] = queue.Queue(maxsize=queue_size)
        self._hints: list[MotionState] = []
        self._hints_lock = threading.Lock()
        super().__init__(opts)
        self._tracked_pub = self.publisher(keys.tracked(self.ns))
        self.subscribe(keys.detections(self.ns), DetectedObjects, self._on_detections)
        if static_hints:
            self.subscribe(keys.motion_all(self.ns), MotionState, self._on_motion)
        self.spawn(self._worker, "worker")

    # ------------------------------------------------------------------ Zenoh callbacks: enqueue only

    def _on_detections(self, msg: DetectedObjects, _key: str) -> None:
        try:
            self._frames.put_nowait(msg)
        except queue.Full:
            self.counters.inc("dropped_overflow")

    def _on_motion(self, msg: MotionState, _key: str) -> None:
        if msg.state == "static":
            with self._hints_lock:
                self._hints.append(msg)

    # ------------------------------------------------------------------ the worker (owns the core)

    def _worker(self) -> None:
        while not self.stop_event.is_set():
            try:
                msg = self._frames.get(timeout=0.1)
            except queue.Empty:
                continue
            try:
                self._apply_hints()
                self.process(msg)
            except Exception:  # a bug must not silently stop tracking: count, log, go on with the next frame
                self.counters.inc("handler_errors")
                self.log.exception("frame seq %d failed", msg.header.seq)

    def _apply_hints(self) -> None:
        with self._hints_lock:
            hints, self._hints = self._hints, []
        if not hints:
            return
        latest = {h.track_id: h for h in hints}  # several frames' hints for one track: the newest wins
        ids = list(latest)
        applied = self.core.apply_static_hints(ids, [latest[t].mean_x for t in ids], [latest[t].mean_y for t in ids])
        self.counters.inc("static_hints_applied", applied)
        if applied < len(ids):
            self.counters.inc("static_hints_unknown", len(ids) - applied)

    def process(self, msg: DetectedObjects) -> None:
        """Track one frame and publish its observations and the closing ``tracked`` message."""
        frame = frame_from_message(msg)
        try:
            result = self.core.step(frame)
        except FrameRejected as rej:
            self.counters.inc(f"dropped_{rej.reason}")
            return
        if result.reset:
            self.counters.inc("resets")
            self.log.warning("detections rewound to seq %d: source restarted, tracker reset", msg.header.seq)
        observations, closing = frame_messages(msg, frame, result)
        for obs in observations:
            self.put(keys.track(self.ns, obs.track.object_id), obs)
        self.publish(self._tracked_pub, closing)
        self.counters.inc("frames")
        self.counters.inc("tracks_born", len(result.born))
        self.counters.inc("tracks_deleted", len(result.deleted))
        self.last_seq = msg.header.seq
