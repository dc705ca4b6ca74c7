"""The replay as a Zenoh service: frames into wire messages (:mod:`.adapter`), put on ``points`` or ``detections``.

Puts use BLOCK congestion control, so with ``--rate max`` a consumer that falls behind slows the replay
down instead of losing scans. The replay runs on the caller's thread (the CLI's main thread) and stops
promptly when the service's stop event is set.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from ...runtime import Service, ZenohOptions
from ...runtime.progress import FAILING, Health, ProgressPolicy
from ...schemas import encode, keys
from ...schemas.models import Heartbeat
from ...schemas.wire import HEARTBEAT_BOUNDS
from .adapter import message_for, truth_for
from .frames import Frame, FrameError, ScanFrame
from .pacing import Clock
from .runner import ReplayPlan, ReplayStats, run_replay
from .sources.base import Source


class ReplayService(Service):
    """Publishes one source's frames on ``jg/{ns}/points`` or ``jg/{ns}/detections``."""

    name = "replay"

    def __init__(self, opts: ZenohOptions, kind: str = "points") -> None:
        if kind not in ("points", "detections"):
            raise ValueError(f"kind must be 'points' or 'detections', got {kind!r}")
        super().__init__(opts)
        self.kind = kind
        self.key = keys.points(self.ns) if kind == "points" else keys.detections(self.ns)
        self.pub = self.publisher(self.key, block=True)
        self._truth_pub: object | None = None  # declared with the first frame that has labels
        self._failed_in_row = 0  # frames that failed to read since the last one published
        self._last_error = ""

    def _wait(self, done: Callable[[], bool], timeout_s: float) -> bool:
        """Poll ``done`` until it holds (True), ``timeout_s`` passes or the service stops (False)."""
        deadline = time.monotonic() + timeout_s
        while not self.stop_event.is_set():
            if done():
                return True
            if time.monotonic() >= deadline:
                return False
            self.stop_event.wait(0.02)
        return False

    def wait_for_subscribers(self, timeout_s: float) -> bool:
        """Wait until some subscriber matches our key (a replay into the void loses its first frames)."""
        return self._wait(lambda: self.pub.matching_status.matching, timeout_s)

    def wait_for_service(self, name: str, timeout_s: float) -> bool:
        """Wait until ``name``'s heartbeat says it is ready (health ``ok``): the pipeline's own consumer, not any
        subscriber. A Foxglove bridge or a recorder that subscribes first had started the replay before the
        detector was up, so its first scans went only to them (and the run's summary said nothing was dropped).
        A service's first heartbeat comes a heartbeat period after its session opens, by when it has subscribed."""
        ready = threading.Event()

        def on_beat(hb: Heartbeat, _key: str) -> None:
            if hb.health == "ok":
                ready.set()

        self.subscribe(keys.heartbeat(self.ns, name), Heartbeat, on_beat, **HEARTBEAT_BOUNDS)
        return self._wait(ready.is_set, timeout_s)

    def emit(self, frame: Frame, seq: int, stamp_ns: int) -> None:
        if (self.kind == "points") != isinstance(frame, ScanFrame):
            raise TypeError(f"{frame.origin}: a {type(frame).__name__} cannot go on {self.key}")
        truth = truth_for(frame, seq, stamp_ns)
        if truth is not None:  # before the frame, so a viewer holds the labels when the frame's results close it
            if self._truth_pub is None:
                self._truth_pub = self.publisher(keys.groundtruth(self.ns), block=False)
            self._truth_pub.put(encode(truth))  # type: ignore[attr-defined]
            self.counters.inc("groundtruth_published")
        self.pub.put(encode(message_for(frame, seq, stamp_ns)))
        self.counters.inc("published")
        self.last_seq = seq
        self._failed_in_row = 0

    def health(self) -> Health:
        """``failing`` while the last frames (``ProgressPolicy.failing_frames`` or more in a row) failed to read:
        a replay skipping every frame of a recording gone bad had reported ``ok`` while nothing entered the
        pipeline. (The replay has no input, so no watchdog restarts it for this: a restart reads the same files.)"""
        n = self._failed_in_row
        if n >= ProgressPolicy.failing_frames:
            return Health(FAILING, f"the last {n} frames failed to read (last: {self._last_error})")
        return super().health()

    def replay(
        self,
        source: Source,
        plan: ReplayPlan,
        *,
        clock: Clock | None = None,
        on_error: Callable[[FrameError], None] | None = None,
        on_published: Callable[[Frame, int], None] | None = None,
    ) -> ReplayStats:
        """Run the replay on this thread until it ends, fails on a bad frame (``on_error='stop'``) or stops."""

        def count_error(err: FrameError) -> None:
            self.counters.inc("frame_errors")
            self._failed_in_row += 1
            self._last_error = str(err)
            if on_error:
                on_error(err)

        # "late" counted as it happens: a looping replay (the stack's) never returns its stats
        return run_replay(source, plan, self.emit, clock=clock, stop=self.stop_event, on_error=count_error,
                          on_published=on_published, on_late=lambda: self.counters.inc("late"),
                          on_restamped=self.counters.inc)

