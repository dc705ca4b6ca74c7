"""The tracker as a Zenoh service: ``detections`` in; ``tracks/{id}`` per observed track, then ``tracked``.

Threading: a detections frame arrives through one callback that only copies the payload into an inbox queue
(:meth:`~jitterguard.runtime.Service.subscribe_queue`); one worker thread, blocked on that queue, wakes at once,
judges the frame's header (:mod:`jitterguard.stream_order`), reads it (:func:`~jitterguard.schemas.read_detected_objects`:
a malformed or oversized payload is counted ``rejected`` and skipped, one the model read in another shape
``normalised``), owns the :class:`TrackerCore` — nothing else touches it — and, through the adapter
(:mod:`.adapter`), per frame publishes every ``tracks/{id}`` first (plain puts per key,
:class:`~jitterguard.runtime.keyed_publishers.KeyedPublishers`) and the closing ``tracked`` last (the classifier
waits for the IDs that ``tracked.observed_track_ids`` names). All puts use BLOCK congestion control: a lost
observation would silently shorten a classifier window. The inbox is bounded (64 frames, 64 MiB): when the worker
falls behind, the oldest frame goes (counted ``dropped_queue.detections``).

Counters (in the heartbeat): ``frames``, ``dropped_duplicate``, ``dropped_out_of_order``, ``dropped_jump`` (held,
judged from the header before the payload is read), ``tracks_born`` (tentative tracks started, clutter's
included), ``tracks_confirmed`` (of those, the ones that reached the output), ``tracks_deleted`` and
``confirmed_tracks_deleted``, ``resets`` (the source went
back in time, confirmed: tracks dropped), ``source_restarts`` (its seq began again while time went on, confirmed:
tracks kept), ``jumps`` (it jumped ahead, confirmed), ``normalised.detections``, ``dropped_queue.detections``,
``static_hints_received`` / ``_applied`` / ``_implausible`` / ``_unknown`` / ``_dropped`` (beyond twice
``limits.max_objects`` tracks waiting for the next frame), ``detections_below_min_existence`` (detections whose
``existence_probability`` is below ``confirm_min_existence``: a track fed only by such stays tentative and is never
published; a detector that leaves the field at 0 is also warned of once in the log) and the runtime's ``received`` / ``rejected`` (and
``over_limit``) / ``published``. How a frame is told apart from a late one is :mod:`jitterguard.stream_order`.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np

from ...runtime import Service, ZenohOptions
from ...runtime.gc_policy import IdleCollector, manage_gc_for_latency
from ...schemas import DecodeError, DetectedColumns, LimitExceeded, keys, peek_header, read_detected_objects
from ...schemas.models import MotionState
from ...stream_order import Verdict
from ..classifier.calibration import warm_up as calibration_warm_up
from .adapter import detection_frame, observation_payloads, tracked_payload
from .config import TrackerConfig, default_config
from .core import FrameRejected, TrackerCore
from .lifecycle import new_track_id

FRAME_CHANNEL = 64
MOTION_MAX_BYTES = 64 * 1024
"""A ``motion/{id}`` payload larger than this is refused unread (a real ``MotionState`` is ~0.4 kB)."""
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
        if self.core.scale is not None:  # the measurement scale's compiled pooling, loaded now, not mid-stream
            calibration_warm_up()
        self.static_hints = static_hints
        self._hints: dict[str, MotionState] = {}  # track ID → its newest decision since the last frame
        self._hints_lock = threading.Lock()
        self._max_hints = 2 * self.core.config.limits.max_objects  # track IDs waiting for the next frame
        self._manage_gc = manage_gc
        self._idle_gc = IdleCollector()
        self._gauges: dict[str, float] = {}
        self._gauges_of: int | None = None  # id of the measurement-scale model the gauges show
        self._warned_zero_existence = False
        if manage_gc:
            manage_gc_for_latency()
        super().__init__(opts)
        self._det_key = keys.detections(self.ns)
        self._tracked_pub = self.publisher(keys.tracked(self.ns))
        self.monitor_progress()  # detections in -> tracked out (runtime.progress)
        self._det_inbox = self.subscribe_queue(self._det_key, FRAME_CHANNEL, progress=True,
                                               max_bytes=self.core.config.limits.max_payload_bytes,
                                               what="DetectedObjects", limit_name="max_payload_bytes")
        self._track_pubs = self.keyed_publishers(lambda tid: keys.track(self.ns, tid))
        if static_hints:
            self.subscribe(keys.motion_all(self.ns), MotionState, self._on_motion, max_bytes=MOTION_MAX_BYTES)
        self.spawn(self._worker, "worker")

    def _on_motion(self, msg: MotionState, key: str) -> None:
        """Zenoh callback: keep each track's newest decision for the worker (applied before the next frame if it is
        static: a dynamic decision newer than a static one cancels it — a tracker behind by a frame had applied the
        older static one, zeroing a car's velocity the classifier had since called moving); a hint whose mean lies
        beyond ``limits.max_abs_coordinate_m`` is refused and counted, as a detection there would be."""
        if self.foreign_track(MotionState.__name__, msg.track_id, key, keys.motion_all(self.ns)):
            return
        bound = self.core.config.limits.max_abs_coordinate_m
        if not (abs(msg.mean_x) <= bound and abs(msg.mean_y) <= bound):
            self.reject(LimitExceeded(MotionState.__name__, "mean_x" if not abs(msg.mean_x) <= bound else "mean_y",
                                      f"beyond max_abs_coordinate_m {bound}"), keys.motion_all(self.ns), key)
            return
        if msg.state == "static":
            self.counters.inc("static_hints_received")
        with self._hints_lock:  # several frames' decisions for one track: the newest frame's wins, whatever the
            # arrival order
            held = self._hints.get(msg.track_id)
            if held is None and len(self._hints) >= self._max_hints:
                # bounded: the classifier decides at most max_objects tracks a frame, and the worker takes every
                # hint at each frame; between frames (or with none coming) made-up track IDs had grown it for ever
                self.counters.inc("static_hints_dropped")
                return
            if held is None or msg.header.seq >= held.header.seq:
                self._hints[msg.track_id] = msg

    # ------------------------------------------------------------------ the worker (owns the core)

    def _worker(self) -> None:
        collect = False  # a frame was processed since the last idle collection
        while not self.stop_event.is_set():
            if collect and not self._det_inbox:  # between frames: the collector's turn (gc_policy)
                self._idle_gc.collect()
                collect = False
            item = self._det_inbox.get(IDLE_WAIT_S)
            if item is None:
                continue
            payload, _key, arrived = item
            self.counters.inc("received")
            head = peek_header(payload)
            verdict = None
            if head is not None:  # the order is judged before the payload is read: a replay costs nothing
                try:
                    verdict = self.core.check_order(*head, now_s=arrived)
                except FrameRejected as rej:
                    self.counters.inc(f"dropped_{rej.reason}")
                    self.progress.output(time.monotonic())  # dealt with: dropped and counted
                    continue
            try:
                cols = read_detected_objects(payload, self.core.config.limits)
            except DecodeError as exc:
                self.reject(exc, self._det_key)
                self.progress.output(time.monotonic())  # dealt with: rejected and counted
                continue
            if cols.normalised:
                self.counters.inc("normalised.detections")
            collect = self._manage_gc
            try:
                self._apply_hints()
                self.process(cols, verdict)
            except Exception as exc:  # a bug must not silently stop tracking: count, log, go on with the next frame
                self.counters.inc("handler_errors")
                self.progress.failure(time.monotonic(), f"{type(exc).__name__}: {exc}"[:200])
                self.log.exception("frame seq %d failed", cols.header.seq)
            else:
                self.progress.output(time.monotonic())  # published, or dropped on purpose (counted)

    def _apply_hints(self) -> None:
        with self._hints_lock:
            newest, self._hints = self._hints, {}
        latest = {t: m for t, m in newest.items() if m.state == "static"}
        if not latest:
            return
        ids = list(latest)
        applied, implausible = self.core.apply_static_hints(ids, [latest[t].mean_x for t in ids],
                                                            [latest[t].mean_y for t in ids])
        self.counters.inc("static_hints_applied", applied)
        if implausible:
            self.counters.inc("static_hints_implausible", implausible)
        if applied + implausible < len(ids):
            self.counters.inc("static_hints_unknown", len(ids) - applied - implausible)

    def process(self, cols: DetectedColumns, verdict: Verdict | None = None) -> None:
        """Track one frame (as :func:`~jitterguard.schemas.read_detected_objects` gives it; ``verdict``: what
        the core already said of its header) and publish the observations, then ``tracked``."""
        frame = detection_frame(cols)
        try:
            result = self.core.step(frame, verdict)
        except FrameRejected as rej:
            self.counters.inc(f"dropped_{rej.reason}")
            return
        if result.reset:
            self.counters.inc("resets")
            self.log.warning("detections went back in time (seq %d, confirmed): source rewound, tracker reset", frame.seq)
        elif result.source_restarted:
            self.counters.inc("source_restarts")
            self.log.warning("detections restarted at seq %d with time going on (confirmed): tracks kept", frame.seq)
        elif result.jumped:
            self.counters.inc("jumps")
            self.log.warning("detections jumped ahead to seq %d (confirmed): tracks kept", frame.seq)
        self._publish(observation_payloads(cols, frame, result, self.core.config.limits))
        self._tracked_pub.put(tracked_payload(cols, frame, result))  # built after the observations went out
        self.counters.inc("frames")
        self._count_low_existence(frame.existence, frame.seq)
        self.counters.inc("tracks_born", len(result.born))
        self.counters.inc("tracks_deleted", len(result.deleted))
        self.counters.inc("tracks_confirmed", result.confirmed)
        self.counters.inc("confirmed_tracks_deleted", result.confirmed_deleted)
        if result.withheld:
            self.counters.inc("tracks_withheld", result.withheld)
        self.last_seq = frame.seq
        if self.core.scale is not None and id(self.core.scale.model) != self._gauges_of:
            self._gauges_of = id(self.core.scale.model)
            self._gauges = self.core.scale.gauges()

    def _count_low_existence(self, existence: np.ndarray, seq: int) -> None:
        """Count the frame's detections below ``confirm_min_existence`` and, the first time every detection of a frame
        reports 0, say why nothing will come out. Confirmation needs a running existence probability of that much (the
        lifecycle's gate, unchanged here), so a detector that leaves ``existence_probability`` at 0 — the field's
        value when a driver does not fill it — gets every track held tentative and nothing published, which had been
        seen only as an empty ``tracked``. A non-finite existence counts as 0, as the core takes it."""
        gate = self.core.config.confirm_min_existence
        if gate <= 0.0 or existence.size == 0:
            return
        ex = np.where(np.isfinite(existence), existence, 0.0)
        below = int(np.count_nonzero(ex < gate))
        if below:
            self.counters.inc("detections_below_min_existence", below)
        if not self._warned_zero_existence and not ex.any():
            self._warned_zero_existence = True
            self.log.warning("every detection of frame %d reports existence_probability 0: a track is confirmed (and"
                             " published) only once its running existence reaches confirm_min_existence %g, so"
                             " tracks fed by such detections never are; have the detector fill the field (its score),"
                             " or set confirm_min_existence: 0 (counted in the heartbeat's"
                             " detections_below_min_existence)", seq, gate)

    def gauges(self) -> dict[str, float]:
        """The heartbeat's gauges: with ``measurement_scale: online``, what the tracker has learnt of the detector's
        variances (``measurement_scale.{group}.{along|across}.{band}``, established tracks) and the blocks behind
        it (``measurement_scale.effective_blocks``); none otherwise."""
        return self._gauges

    def _publish(self, observations: list[tuple[str, bytes]]) -> None:
        """Put each ``tracks/{id}`` (``tracked`` follows)."""
        for tid, payload in observations:
            self._track_pubs.put(tid, payload)
        self.counters.inc("published", len(observations) + 1)
