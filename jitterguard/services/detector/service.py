"""The detector's Zenoh adapter: ``points`` in, one ``detections`` message per processed scan out.

Threading. The ``points`` subscriber's callback only decodes and validates the scan (the runtime counts and
logs a malformed payload as ``rejected`` and the service goes on) and drops it into a depth-1 slot; one worker
thread takes the slot's scan, runs the network and publishes. A scan costs the network tens to hundreds of
milliseconds, so a queue would only grow: when a scan arrives while the previous one is still waiting in the
slot, the waiting one is replaced — the detector always works on the newest scan, and a stale one is worth
less to a tracker than a fresh one. Never silently: every replaced scan counts as ``skipped_scans`` and each
burst of them is logged at once with the seq gap, a steady overload every 30 s with a summary
(:class:`BehindReport`). The callback never blocks, so a BLOCK-publishing replay is not
slowed by a slow detector (it is by a slow network link, as it should be).

Frames and covariances follow :mod:`.adapter`: sensor frame, the scan's header and ego pose carried over, the
network's sensor-frame variances in the covariance fields; the tracker rotates them into the world frame.

Counters (in the heartbeat): ``scans`` (processed), ``skipped_scans``, ``detections`` (objects published),
``empty_scans`` (no finite point: published with no objects so the tracker still sees the frame),
``nonfinite_points``, ``nonfinite_detections``, ``out_of_limit_detections`` (dropped: the tracker's reader would
refuse the frame for them), ``detect_errors``, ``detect_ms_last`` (end-to-end time of the latest scan, rounded),
``stacked_sweeps_last`` (scans in the latest network input, for a model trained on stacked sweeps: :mod:`.sweeps`),
``sweep_resets`` (times the held sweeps were dropped because a scan's stamp went back or its ego pose jumped),
``scans_without_intensity`` (scans with no ``intensity`` field given to a network trained with intensity: fed 0,
which costs it objects — told once in the log),
``sensor_height_cm_last`` (the height above the road the latest scan's frame was taken to have, cm: the declared
``sensor_height_m`` or the scan's own estimate, :mod:`.ground` — an operator sees a wrong frame or mount at once),
``ground_slope_x_cdeg_last`` / ``ground_slope_y_cdeg_last`` (the road plane's slope along the scan frame's x / y
axis that was taken out, 1/100 degree: a sensor pitched or rolled against the road, or a climb; 0 with
``sensor_tilt: level``) and the runtime's ``received`` / ``rejected`` (with ``rejected.points`` / ``over_limit.points``: a scan too large
or whose ego pose is no pose) / ``published``.
"""

from __future__ import annotations

import threading
import time

from ...runtime import Service, ZenohOptions
from ...runtime.progress import ProgressPolicy
from ...runtime.service import _BurstLogger
from ...schemas import LimitExceeded, keys
from ...schemas.models import PointCloud
from ...schemas.wire import LIMITS, MAX_MAP_ENTRIES, check_pose
from .config import DetectorParams
from .adapter import class_labels, detections_payload, publishable_detections, scan_points, scan_pose
from .ground import GroundWatch
from .sweeps import MAX_LAG_S, SweepStacker
from .inference import Detector, crop_box

WAIT_S = 0.2
STALL_S = 30.0
"""A scan waiting this long with no detections out is a stall (a CPU network takes up to a few seconds)."""
"""How often the idle worker looks at the stop event."""
BURST_QUIET_S = 5.0
"""A burst of skipping ends after this long without a skipped scan; the next skip starts a new one."""
SUMMARY_S = 30.0
"""While a burst goes on, one summary line at most this often (a steady overload is not silent either)."""


class BehindReport:
    """Decides when falling behind is worth a log line, and what the line says. Pure: times are passed in.

    The first skip of a burst is reported at once with its seq gap; while skipping continues (no gap of
    ``quiet_s`` without a skip) a summary follows at most every ``summary_s``, counting scans skipped and
    processed since the last line.
    """

    def __init__(self, quiet_s: float = BURST_QUIET_S, summary_s: float = SUMMARY_S) -> None:
        self.quiet_s, self.summary_s = quiet_s, summary_s
        self._last_skip = -1e18
        self._last_line = -1e18
        self._skipped = 0
        self._processed = 0

    def taken(self, now: float, seq: int, skipped: int, first: int, last: int, detect_ms: int) -> str | None:
        """The worker took scan ``seq`` after ``skipped`` replaced ones (seqs ``first``..``last``): a log line or None."""
        self._processed += 1
        if not skipped:
            return None
        new_burst = now - self._last_skip >= self.quiet_s
        self._last_skip = now
        self._skipped += skipped
        if new_burst:
            gap = f"seq {first}" if first == last else f"seqs {first}..{last}"
            line = (f"falling behind: skipped {skipped} scan(s) ({gap}) that arrived while the network was busy"
                    f" (last scan took {detect_ms} ms); processing the newest, seq {seq}")
        elif now - self._last_line >= self.summary_s:
            line = (f"still falling behind: skipped {self._skipped} scan(s) and processed {self._processed} in the"
                    f" last {now - self._last_line:.0f} s (last scan took {detect_ms} ms); now at seq {seq}")
        else:
            return None
        self._last_line = now
        self._skipped = self._processed = 0
        return line


class _Slot:
    """The newest scan not yet taken by the worker, and what it replaced since the worker last took one."""

    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.scan: PointCloud | None = None
        self.skipped = 0
        self.skipped_first = -1
        self.skipped_last = -1

    def put(self, scan: PointCloud) -> bool:
        """Store ``scan``; True when it replaced one the worker had not taken yet."""
        with self.cond:
            replaced = self.scan is not None
            if self.scan is not None:
                if self.skipped == 0:
                    self.skipped_first = self.scan.header.seq
                self.skipped += 1
                self.skipped_last = self.scan.header.seq
            self.scan = scan
            self.cond.notify()
            return replaced

    def take(self, timeout: float) -> tuple[PointCloud, int, int, int] | None:
        """(scan, scans skipped before it, first and last skipped seq), or None after ``timeout``."""
        with self.cond:
            if self.scan is None:
                self.cond.wait(timeout)
            if self.scan is None:
                return None
            out = (self.scan, self.skipped, self.skipped_first, self.skipped_last)
            self.scan, self.skipped, self.skipped_first, self.skipped_last = None, 0, -1, -1
            return out

    def wake(self) -> None:
        with self.cond:
            self.cond.notify_all()


MAX_SCAN_BYTES = DetectorParams.model_fields["max_scan_bytes"].default
"""A ``points`` payload larger than this is refused unread (``max_scan_bytes`` of the service's parameters)."""


class DetectorService(Service):
    """The ``jitterguard detector`` process."""

    name = "detector"

    def __init__(self, opts: ZenohOptions, detector: Detector, *, has_twist: bool = True, sweeps: int | None = None,
                 max_sweep_lag_s: float = MAX_LAG_S, max_scan_bytes: int = MAX_SCAN_BYTES) -> None:
        """``sweeps``: scans stacked per network input (None: the weights' :attr:`Detector.sweeps`); only a model
        with five point fields reads the stack's time lag, so a four-field model is never given more than one."""
        # check the model's classes before the session opens: a bad config must fail before anything is on the network
        class_labels(detector.config.class_names)
        self.detector = detector
        self.has_twist = has_twist
        self._slot = _Slot()
        n = (sweeps or detector.sweeps) if detector.config.num_point_features >= 5 else 1
        # every arriving scan is held (the callback), the worker stacks the one it takes: a slow network skips
        # scans, never sweeps
        self._sweeps = SweepStacker(n, max_sweep_lag_s) if n > 1 else None
        self._sweeps_lock = threading.Lock()
        super().__init__(opts)
        self._behind = BehindReport()
        self._error_log = _BurstLogger(self.log)
        self._ground_watch = GroundWatch()
        self._told_no_intensity = False
        self._pub = self.publisher(keys.detections(self.ns))
        self.monitor_progress(ProgressPolicy(stall_s=STALL_S))  # points in -> detections out (runtime.progress)
        self.spawn(self._worker, "worker")
        # the lists and maps of a scan bounded before they are built: a 2 MB scan whose ``fields`` held two million
        # one-byte items cost this callback 7 s and 1.9 GB (64 MB of them would take minutes and exhaust memory)
        self.subscribe(keys.points(self.ns), PointCloud, self._on_scan, max_bytes=max_scan_bytes,
                       max_array_len=LIMITS.max_list_items, max_map_len=MAX_MAP_ENTRIES)

    def _on_scan(self, msg: PointCloud, key: str) -> None:
        """Zenoh callback (the scan is already validated): newest scan into the slot, count what it replaced. A
        scan whose ego pose the readers downstream would refuse (no unit quaternion, beyond the limits) is
        refused here, counted per key, before it reaches the sweeps or the network."""
        try:
            check_pose(PointCloud.__name__, "ego_pose", msg.ego_pose)
        except LimitExceeded as exc:
            self.reject(exc, keys.points(self.ns), key)
            return
        self.progress.input(time.monotonic())
        if self._sweeps is not None:
            rotation, translation = scan_pose(msg)
            points, _ = scan_points(msg)
            # the ego's body cropped in this scan's own frame: moved into a later one, it would lie behind the
            # vehicle, outside the newest scan's crop box
            points = crop_box(points, self.detector.self_crop)
            with self._sweeps_lock:
                self._sweeps.add(msg.header.stamp, rotation, translation, points)
        if self._slot.put(msg):
            self.counters.inc("skipped_scans")

    def on_close(self) -> None:
        self._slot.wake()

    # ------------------------------------------------------------------ the worker (owns the network)

    def _worker(self) -> None:
        while not self.stop_event.is_set():
            got = self._slot.take(WAIT_S)
            if got is None:
                continue
            scan, skipped, first, last = got
            line = self._behind.taken(time.monotonic(), scan.header.seq, skipped, first, last,
                                      self.counters.get("detect_ms_last"))
            if line:
                self.log.warning("%s", line)
            try:
                self.process(scan)
            except Exception as exc:  # a bad scan or a bug must not stop detection: count, log, next scan
                self.counters.inc("detect_errors")
                self.progress.failure(time.monotonic(), f"{type(exc).__name__}: {exc}"[:200])
                self._error_log.warn(f"scan seq {scan.header.seq} failed: {type(exc).__name__}: {exc}")
                self.log.debug("scan seq %d failed", scan.header.seq, exc_info=True)
            else:
                self.progress.output(time.monotonic())

    def process(self, scan: PointCloud) -> None:
        """Detect on one validated scan and publish its ``DetectedObjects``."""
        t0 = time.perf_counter()
        points, bad = scan_points(scan)
        if bad:
            self.counters.inc("nonfinite_points", bad)
        if "intensity" not in scan.fields and self.detector.config.use_intensity:
            self.counters.inc("scans_without_intensity")
            if not self._told_no_intensity:  # fed 0 as documented, but not without a word: it costs detections
                self._told_no_intensity = True
                self.log.warning("scans carry no 'intensity' field (fields %s): the network was trained with"
                                 " intensity and is fed 0 for every return, which costs it objects; for such a"
                                 " sensor train weights with --no-intensity", list(scan.fields))
        if len(points) == 0:
            self.counters.inc("empty_scans")
        elif self._sweeps is not None:
            rotation, translation = scan_pose(scan)
            with self._sweeps_lock:
                points = self._sweeps.stack(scan.header.stamp, rotation, translation, points)
                stacked, resets = self._sweeps.last_stacked, self._sweeps.resets
            self.counters.set("stacked_sweeps_last", stacked)
            self.counters.set("sweep_resets", resets)
        det, dropped, beyond = publishable_detections(self.detector.detect, points,
                                                      uncertainty=self.detector.config.uncertainty)
        if dropped:
            self.counters.inc("nonfinite_detections", dropped)
            self._error_log.warn(f"scan seq {scan.header.seq}: dropped {dropped} detection(s) holding a"
                                 " non-finite number")
        if beyond:  # published, the tracker would refuse the whole frame for one of them
            self.counters.inc("out_of_limit_detections", beyond)
            self._error_log.warn(f"scan seq {scan.header.seq}: dropped {beyond} detection(s) beyond the wire's"
                                 " limits (position, speed or variance)")
        self._pub.put(detections_payload(det, scan.header, scan.ego_pose, self.detector.config.class_names,
                                         has_twist=self.has_twist))
        self.counters.inc("published")
        self.counters.inc("scans")
        self.counters.inc("detections", len(det))
        self.counters.set("detect_ms_last", round((time.perf_counter() - t0) * 1e3))
        ground = self.detector.ground_last
        self.counters.set("sensor_height_cm_last", round(ground.height * 100))
        self.counters.set("ground_slope_x_cdeg_last", round(ground.slope_deg[0] * 100))
        self.counters.set("ground_slope_y_cdeg_last", round(ground.slope_deg[1] * 100))
        if self.detector.measures_ground and (told := self._ground_watch.observe(self.detector.plane_measured)):
            self.log.warning("%s", told)
        self.last_seq = scan.header.seq
