"""The tracker's Zenoh adapter: ``detections`` in; ``tracks/{id}`` per observed track, then ``tracked``.

Threading: a detections frame arrives through one callback that only copies the payload into an inbox queue
(:meth:`~jitterguard.runtime.Service.subscribe_inbox`); one worker thread, blocked on that queue, wakes at once,
validates the frame (:func:`~.convert.decode_detections`: records for the usual shape, generated Structs
otherwise; a malformed payload is counted as ``rejected`` and skipped), owns the :class:`TrackerCore` — nothing
else touches it — and per frame publishes every ``tracks/{id}`` first (:class:`~jitterguard.runtime.keyed_publishers.KeyedPublishers`) and the closing ``tracked`` last (the classifier
waits for the IDs that ``tracked.observed_track_ids`` names). All puts use BLOCK congestion control: a lost
observation would silently shorten a classifier window. A full inbox slows BLOCK publishers instead of
dropping frames.

Counters (in the heartbeat): ``frames``, ``dropped_duplicate``, ``dropped_out_of_order``, ``tracks_born``,
``tracks_deleted``, ``resets`` (the source went back in time: tracks dropped), ``source_restarts`` (its seq began
again while time went on: tracks kept), ``static_hints_received`` / ``_applied`` / ``_unknown`` and the runtime's
``received`` / ``rejected`` / ``published``. How a frame is told apart from a late one is
:mod:`jitterguard.stream_order`.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable
from typing import Any

from ...runtime import Service, ZenohOptions
from ...runtime.gc_policy import IdleCollector, manage_gc_for_latency
from ...schemas import DecodeError, keys
from ...schemas.models import MotionState
from .config import TrackerConfig, default_config
from .convert import (decode_detections, detections_codec, ego_pose_map, frame_from_message, observation_payloads,
                      tracked_payload)
from .core import FrameRejected, TrackerCore
from .lifecycle import new_track_id

FRAME_CHANNEL = 64
IDLE_WAIT_S = 0.05
"""How long the idle worker blocks for a frame before it looks at the stop flag (a frame wakes it at once)."""


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
        manage_gc: bool = False,
    ) -> None:
        """``manage_gc``: take the garbage collector off the frame path (process-wide, see
        :mod:`jitterguard.runtime.gc_policy`; for the ``jitterguard tracker`` process, not for embedders)."""
        # build the core before the session opens: a bad config must fail before anything is on the network
        self.core = TrackerCore(config or default_config(), id_factory)
        self.static_hints = static_hints
        self._hints: list[MotionState] = []
        self._hints_lock = threading.Lock()
        self._codec = detections_codec()
        self._manage_gc = manage_gc
        self._idle_gc = IdleCollector()
        if manage_gc:
            manage_gc_for_latency()
        super().__init__(opts)
        self._det_key = keys.detections(self.ns)
        self._tracked_pub = self.publisher(keys.tracked(self.ns))
        self.monitor_progress()  # detections in -> tracked out (runtime.progress)
        self._det_inbox = self.subscribe_inbox(self._det_key, capacity=FRAME_CHANNEL, progress=True)
        self._track_pubs = self.keyed_publishers(lambda tid: keys.track(self.ns, tid))
        if static_hints:
            self.subscribe(keys.motion_all(self.ns), MotionState, self._on_motion)
        self.spawn(self._worker, "worker")

    def _on_motion(self, msg: MotionState, _key: str) -> None:
        """Zenoh callback: keep the static decisions for the worker (applied before the next frame)."""
        if msg.state == "static":
            self.counters.inc("static_hints_received")
            with self._hints_lock:
                self._hints.append(msg)

    # ------------------------------------------------------------------ the worker (owns the core)

    def _worker(self) -> None:
        collect = False  # a frame was processed since the last idle collection
        while not self.stop_event.is_set():
            if collect and self._det_inbox.empty():  # between frames: the collector's turn (gc_policy)
                self._idle_gc.collect()
                collect = False
            try:
                payload, _key = self._det_inbox.get(timeout=IDLE_WAIT_S)
            except queue.Empty:
                continue
            self.counters.inc("received")
            try:  # the contract's validation, on msgspec Structs generated from the model (schemas.fast)
                msg = decode_detections(self._codec, payload)
            except DecodeError as exc:
                self.reject(exc, self._det_key)
                self.progress.output(time.monotonic())  # dealt with: rejected and counted
                continue
            collect = self._manage_gc
            try:
                self._apply_hints()
                self.process(msg)
            except Exception as exc:  # a bug must not silently stop tracking: count, log, go on with the next frame
                self.counters.inc("handler_errors")
                self.progress.failure(time.monotonic(), f"{type(exc).__name__}: {exc}"[:200])
                self.log.exception("frame seq %d failed", msg.header.seq)
            else:
                self.progress.output(time.monotonic())  # published, or dropped on purpose (counted)

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

    def process(self, msg: Any) -> None:
        """Track one validated frame (as :func:`~.convert.decode_detections` gives it; a Struct is edited in
        place) and publish the observations, then ``tracked``."""
        frame = frame_from_message(msg)
        try:
            result = self.core.step(frame)
        except FrameRejected as rej:
            self.counters.inc(f"dropped_{rej.reason}")
            return
        if result.reset:
            self.counters.inc("resets")
            self.log.warning("detections went back in time (seq %d): source rewound, tracker reset", frame.seq)
        elif result.source_restarted:
            self.counters.inc("source_restarts")
            self.log.warning("detections restarted at seq %d with time going on: source restarted, tracks kept",
                             frame.seq)
        self._publish(observation_payloads(msg, frame, result))
        self._tracked_pub.put(tracked_payload(frame, result, ego_pose_map(msg)))  # after the observations went out
        self.counters.inc("frames")
        self.counters.inc("tracks_born", len(result.born))
        self.counters.inc("tracks_deleted", len(result.deleted))
        self.last_seq = frame.seq

    def _publish(self, observations: list[tuple[str, bytes]]) -> None:
        """Put each ``tracks/{id}`` (``tracked`` follows)."""
        for tid, payload in observations:
            self._track_pubs.put(tid, payload)
        self.counters.inc("published", len(observations) + 1)
