"""The classifier as a Zenoh service: transport and threads around :class:`~.adapter.ClassifierAdapter`.

Threads. Observations (``tracks/*``, thousands per second) and the frame-closing ``tracked`` (once per frame) come
through one subscription (``track$*/**``), whose callback only copies each payload into the bounded queue of its key
(refusing an oversized one from its size first); one worker thread drains and reads the observations in batches as
they arrive. A close is stamped on arrival and wakes the worker: the frame latency counts from that stamp, i.e.
from the sample reaching this process's subscriber, queueing included. The worker owns the pipeline: it validates, assembles frames,
decides, and publishes ``objects`` first (what the predictor waits for, and where the frame latency ends) and then
the ``motion/{id}`` messages; the contract does not order the two. Config writes go through the same worker, so a
write is applied between two frames and the reply reports what is in force from the next frame on. One
subscription has one callback thread, so a frame's observations are queued before its close, in the order the
tracker put them, and the worker does not give a frame up for stragglers while observations still wait: no
observation received before its close is missed (with two subscriptions, a thread each, a close had been able to
overtake them).

Overload degrades instead of backing up, and every queue is bounded: ``tracked`` waits in a queue of
:data:`CLOSE_QUEUE` payloads and 64 MiB (the oldest goes, counted ``dropped_queue.tracked``), observations in a queue of
:data:`OBS_QUEUE` payloads and :data:`OBS_QUEUE_BYTES` (the oldest goes, counted ``dropped_queue.tracks/*``; what a
frame then lacks is counted ``frames.missing_observations`` too), config writes in a queue of 64; a ``tracked``
that is a duplicate, late or a jump is dropped from its header, unread. A straggler of a frame already decided is
dropped (counted ``frames.late_observations``), a frame is not given up on for stragglers while the worker is still
behind on what arrived, and when the next frame's ``tracked`` is already waiting the ``motion/{id}`` messages of
the current frame are skipped (counted ``motion_frames_shed``; the next frame's supersede them).
"""

from __future__ import annotations

import math
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any

import numpy as np
import zenoh

from ...runtime import Service, ZenohOptions
from ...runtime.service import QueueRoute
from ...runtime.gc_policy import IdleCollector, manage_gc_for_latency
from ...schemas import SCHEMA_VERSION, DecodeError, decode, encode, keys
from ...schemas.models import ETAG_HEX, ClassifierConfig, ConfigReply, config_etag
from ...schemas.wire import LIMITS, MAX_CONFIG_BYTES, MAX_MAP_ENTRIES, Limits
from ...stream_order import StreamLimits
from .adapter import ClassifierAdapter, FrameOutput, Poses
from .assembly import FrameAssembler
from .calibration import NoiseModel
from .calibration_file import CalibrationFileError, read_calibration
from .calibration_store import SAVE_PERIOD_S, CalibrationStore
from .config_store import ConfigStore
from .config_writes import ConfigWritePolicy
from .core import STATE_NAMES, Decisions, MotionClassifierCore, calibration_gauges
from . import window_kernel
from .statistics import warm_up

CONFIG_APPLY_TIMEOUT_S = 2.0
LATENCY_WINDOW = 4096
LATENCY_BUCKETS_MS = (0.5, 1, 2, 5, 10, 20, 50, 100, 200, 500, 1000)
"""Frame-latency histogram buckets; exported as counters so the sidecar's /metrics can rebuild it."""
CLOSE_QUEUE = 64
"""``tracked`` messages waiting for the worker (3.2 s at 20 Hz, as the tracker's inbox); beyond that the oldest goes."""
OBS_QUEUE = 16384
"""Observations waiting for the worker (4 s of 200 tracks at 20 Hz); beyond that the oldest goes."""
OBS_QUEUE_BYTES = 64 << 20
"""... and at most this many bytes of them (16,384 of 4 kB; an observation is ~1.4 kB): a flood of large payloads
(up to ``max_payload_bytes``, 8 MiB, each) would otherwise be bounded only at 128 GiB."""
OBS_CHUNK = 64
"""Observations validated per pass before the worker looks for a newly arrived ``tracked`` again."""
IDLE_POLL_S = 0.0005
"""How long the idle worker waits for a ``tracked`` wake-up before polling the observation channel again."""


def route_by_key(track_prefix: str, tracked_key: str) -> Callable[[str], int | None]:
    """The route of a sample of ``tracks_and_tracked``: 0 for an observation (``{track_prefix}{id}``, one chunk),
    1 for the close (``tracked_key``), ``None`` for any other key ``track$*/**`` matches (``tracks/a/b``,
    ``trackers``), which the subscriptions on the two keys had never seen either."""
    n = len(track_prefix)

    def route(key: str) -> int | None:
        if key.startswith(track_prefix):
            return 0 if len(key) > n and key.find("/", n) < 0 else None
        return 1 if key == tracked_key else None

    return route


@dataclass
class _Latest:
    """What the state queryable reports: the last processed frame (immutable once stored)."""

    header: dict[str, Any]
    objects: np.ndarray  # as published
    decisions: Decisions
    labels: np.ndarray
    stamps: np.ndarray
    seqs: np.ndarray
    config: ClassifierConfig
    window: int  # the window the frame was decided with (window_size, or fewer for a slow stream)
    encoded: bytes | None = None


class ConfigConflict(ValueError):
    """A conditional write (``if_match``) found another config in force: refused, nothing applied."""


def _is_etag(text: str) -> bool:
    return len(text) == ETAG_HEX and all(c in "0123456789abcdef" for c in text)


def _config_reply(config: ClassifierConfig, error: str | None = None, *, conflict: bool = False) -> bytes:
    """A ``ConfigReply`` carrying ``config`` and its etag: what is in force (``error`` None) or why a write was
    refused — the config and etag then are the ones in force, so a writer can redo its change at once."""
    return encode(ConfigReply(ok=error is None, config=config, error=error, etag=config_etag(config),
                              conflict=conflict))


def _window_words(window: int, stride: int) -> str:
    """'20 observations', or '20 observations of every 2nd frame' on a fast stream (the log's wording)."""
    if stride == 1:
        return f"{window} observations"
    nth = {2: "2nd", 3: "3rd"}.get(stride, f"{stride}th")
    return f"{window} observations of every {nth} frame"


class ClassifierService(Service):
    name = "classifier"

    def __init__(self, opts: ZenohOptions, config: ClassifierConfig | None = None, *,
                 straggler_timeout_s: float = 0.05, limits: Limits = LIMITS, stream: StreamLimits | None = None,
                 manage_gc: bool = False, config_writes: ConfigWritePolicy | None = None,
                 config_store: ConfigStore | None = None, calibration_model: NoiseModel | None = None,
                 calibration_store: CalibrationStore | None = None) -> None:
        """``manage_gc``: call :func:`manage_gc_for_latency` and collect garbage between frames (process-wide;
        for the process that runs the classifier, not for tests that embed it). ``config_writes``: who may
        write the config over Zenoh (default: ``JG_API_TOKEN`` holders, nobody without one). ``config_store``:
        where writes are kept so that a restart restores them (:mod:`.config_store`). ``calibration_model``: the
        scales for ``calibration: file`` (read from the config's ``calibration_file`` when not given).
        ``calibration_store``: where the online calibration is kept so that a restart goes on from it
        (:mod:`.calibration_store`)."""
        self._gauges: dict[str, float] = {}  # the heartbeat starts with the session, before the statistic warms up
        super().__init__(opts)
        # its token and heartbeat are out, but frames reaching it now are lost until it subscribes (below): the
        # statistic's first compile takes seconds, and /readyz had said ready through them
        self.starting = "warming up the calibrated statistic"
        self.config_writes = config_writes or ConfigWritePolicy.from_env()
        self._started_with = config or ClassifierConfig()
        self._store = config_store
        restored = None
        if config_store is not None:
            restored, why = config_store.load(self._started_with)
            if config_store.damaged:  # the operator's writes are lost: not the info of a first start
                self.counters.inc("config_store_errors")
                self.log.warning("%s", why)
            else:
                self.log.info("%s", why)
        config = restored or config or ClassifierConfig()
        if restored is not None and config.calibration == "file" and config.calibration_file:
            # the restored config names its own file: the model read from the flags' file (if any) is not it
            try:
                calibration_model = read_calibration(config.calibration_file)
            except CalibrationFileError as exc:  # gone or damaged since the write: not a crash
                config = self._calibration_from_flags(config_store, config, exc)
        if calibration_model is None and config.calibration == "file" and config.calibration_file:
            calibration_model = read_calibration(config.calibration_file)
        self.log.info("%s", self.config_writes.describe())
        self.log.info("deciding by %s, calibration %s, effective_n %s, H0 |v| <= %g m/s, window %d observations%s",
                      config.mode, config.calibration, config.effective_n, config.min_speed_mps, config.window_size,
                      "" if config.window_reference_hz is None
                      else f" at {config.window_reference_hz:g} Hz (proportionally fewer on a slower stream, "
                           "every k-th frame on a faster one)")
        self._manage_gc = manage_gc
        self._idle_gc = IdleCollector()
        if manage_gc:
            manage_gc_for_latency()
        online = None
        self._cal_store = calibration_store
        if calibration_store is not None:
            online = MotionClassifierCore.make_online(config)
            self.log.info("%s", calibration_store.load_into(online))
        self.pipeline = ClassifierAdapter(config, straggler_timeout_s=straggler_timeout_s, limits=limits, stream=stream,
                                          calibration_model=calibration_model, calibration=online)
        started = time.monotonic()
        warm_up()  # the compiled statistic: compiled (first run after an install) or loaded now, not on frame 1
        self.log.info("calibrated statistic ready in %.1f s%s", time.monotonic() - started,
                      "" if window_kernel.CACHED else " (compiled: no writable numba cache; set NUMBA_CACHE_DIR)")
        self._cal_slot = threading.Lock()  # guards _cal_next (held for an assignment: never blocks the worker)
        self._cal_write = threading.Lock()  # one write at a time, never an older state over a newer one
        self._cal_next: tuple[int, dict[str, np.ndarray]] | None = None  # the latest state for the writer
        self._cal_seq = self._cal_written = 0
        self._cal_mark = (self.core.online_calibration.counts["blocks"], time.monotonic())
        self._calibration = self.core.calibration_state()  # what the latest frame used (state queryable)
        self._gauges = calibration_gauges(self._calibration)  # ... flattened for the heartbeat
        self.latencies_ms: deque[float] = deque(maxlen=LATENCY_WINDOW)
        self._queue: queue.Queue = queue.Queue(maxsize=64)  # config writes and calls, run between frames
        self._wake = threading.Event()  # a close or a control call came
        self._latest: _Latest | None = None
        self._window = (self.core.window, self.core.stride)  # the last frame's window, stride (a change is logged)
        self._latest_lock = threading.Lock()
        self._obs_key = keys.tracks_all(self.ns)
        self._tracked_key = keys.tracked(self.ns)
        self._objects_pub = self.publisher(keys.objects(self.ns))
        self._motion_pubs = self.keyed_publishers(lambda tid: keys.motion(self.ns, tid),
                                                  priority=zenoh.Priority.DATA_LOW)
        self.monitor_progress()  # tracked in -> objects out (runtime.progress)
        # one subscription for both, so a frame's observations are queued before its close (in the order put); a
        # close is stamped on arrival (the frame latency counts from there, queueing included) and wakes the worker
        self._obs_in, self._closes = self.subscribe_queues(
            keys.tracks_and_tracked(self.ns),
            (QueueRoute(self._obs_key, OBS_QUEUE, OBS_QUEUE_BYTES, "TrackObservation"),
             QueueRoute(self._tracked_key, CLOSE_QUEUE, what="TrackedObjects", progress=True, wake=self._wake)),
            route_by_key(self._obs_key[:-1], self._tracked_key),
            max_bytes=self.pipeline.limits.max_payload_bytes, limit_name="max_payload_bytes")
        self.queryable(keys.classifier_config(self.ns), self._on_config_query)
        self.queryable(keys.classifier_state(self.ns), self._on_state_query)
        self.spawn(self._worker, "worker")
        if calibration_store is not None:
            self.spawn(self._calibration_writer, "calibration-store")
        self.starting = None

    def _calibration_from_flags(self, store: ConfigStore, restored: ClassifierConfig,
                                exc: CalibrationFileError) -> ClassifierConfig:
        """The restored config with the flags' calibration source in place of a file that is gone or damaged
        since the write, stored so that what is in force and what the next restart restores stay one config.
        Every other write it held stays (the whole stored config had been dropped for the file, the thresholds
        too, with an info-level warning and nothing counted; and the store, unchanged, brought the file back at
        the restart after). A lost write is counted (``config_store_errors``) as a damaged store is."""
        started = self._started_with
        config = ClassifierConfig.model_validate({**restored.model_dump(), "calibration": started.calibration,
                                                  "calibration_file": started.calibration_file})
        self.counters.inc("config_store_errors")
        self.log.warning("the stored config's calibration file is unusable (%s): calibration %s%s as the flags say,"
                         " the stored config's other settings kept", exc, config.calibration,
                         f" from {config.calibration_file}" if config.calibration == "file" else "")
        try:
            store.save(started, config)
        except OSError as err:
            self.log.warning("cannot store the config now in force at %s (%s): a restart may restore the old one",
                             store.path, err)
        return config

    @property
    def core(self) -> MotionClassifierCore:
        return self.pipeline.core

    @property
    def assembler(self) -> FrameAssembler:
        return self.pipeline.assembler

    # ---------------------------------------------------------------- the worker

    def _worker(self) -> None:
        collect_when_idle = False
        while not self.stop_event.is_set():
            try:
                collect_when_idle = self._work_once(collect_when_idle)
            except Exception as exc:  # a bug must not silently stop the classifier: count, log, go on
                self.counters.inc("handler_errors")
                self.progress.failure(time.monotonic(), f"{type(exc).__name__}: {exc}"[:200])
                self._reject_log.warn(f"classifier worker failed: {type(exc).__name__}: {exc}", kind="worker")
                self.log.debug("classifier worker failed", exc_info=True)
                self.stop_event.wait(IDLE_POLL_S)  # a failure that repeats must not spin the CPU
        self._store_calibration(final=True)

    # ---------------------------------------------------------------- the calibration store

    def _store_calibration(self, *, final: bool = False) -> None:
        """On the worker, between frames: hand the online calibration's state to the writer when new blocks
        were pooled and :data:`SAVE_PERIOD_S` has passed since the last hand-over; ``final`` (the worker is
        stopping) writes it here and now, whatever the period."""
        if self._cal_store is None or self.core.config.calibration != "online":
            return
        online = self.core.online_calibration
        blocks, now = online.counts["blocks"], time.monotonic()
        if blocks == self._cal_mark[0] or (not final and now - self._cal_mark[1] < SAVE_PERIOD_S):
            return
        self._cal_mark = (blocks, now)
        self._cal_seq += 1
        item = (self._cal_seq, online.state())
        if final:
            self._write_calibration(*item)
            return
        with self._cal_slot:
            self._cal_next = item

    def _calibration_writer(self) -> None:
        """Writes the states the worker hands over, off the frame path (a write is ~0.5 MB and an fsync)."""
        while not self.stop_event.wait(0.2):
            with self._cal_slot:
                item, self._cal_next = self._cal_next, None
            if item is not None:
                self._write_calibration(*item)

    def _write_calibration(self, seq: int, state: dict[str, np.ndarray]) -> None:
        assert self._cal_store is not None
        with self._cal_write:
            if seq <= self._cal_written:
                return
            try:
                self._cal_store.save(state)
            except OSError as exc:
                self.counters.inc("calibration_store_errors")
                self._reject_log.warn(f"cannot store the calibration in {self._cal_store.path}: {exc}",
                                      kind="calibration store")
                return
            self._cal_written = seq
            self.counters.inc("calibration_saves")

    def _work_once(self, collect_when_idle: bool) -> bool:
        """One pass of the worker: closes, control calls, observations, ready frames; idles when there is
        nothing to do. Returns whether to collect garbage at the next idle moment."""
        busy = self._take_closes()
        if busy and not self.pipeline.pending:  # every close taken was decided or dropped (counted)
            self.progress.output(time.monotonic())
        while not self._queue.empty():
            busy = True
            self._run_control(self._queue.get_nowait())
        taken = self._take_observations(OBS_CHUNK)
        busy = busy or taken > 0
        # A close is stamped when it arrives, so its straggler timeout runs while this worker may still
        # be behind on observations that did arrive: give up on missing ones only once the channel is empty.
        frames = self.pipeline.ready(time.monotonic(), give_up=taken < OBS_CHUNK)
        for i, frame in enumerate(frames):
            self._publish(self.pipeline.finish(frame), behind=i + 1 < len(frames))
            collect_when_idle = self._manage_gc
        if busy or frames:  # a frame given up on in an idle pass counts too (the last heartbeat had lagged)
            for k, v in self.pipeline.assembler.counts.items():
                self.counters.set(f"frames.{k}", v)
        elif collect_when_idle and not self.pipeline.pending:
            collect_when_idle = False
            self._collect_garbage()
        elif self._wake.wait(IDLE_POLL_S):
            self._wake.clear()
        return collect_when_idle

    def _collect_garbage(self) -> None:
        """Between frames (see :mod:`jitterguard.runtime.gc_policy`)."""
        self._idle_gc.collect()

    def _take_closes(self) -> bool:
        took = False
        for data, key, t0 in self._closes.take(CLOSE_QUEUE):
            took = True
            self.counters.inc("received")
            try:
                cols = self.pipeline.close(data, t0)
            except DecodeError as exc:
                self.reject(exc, self._tracked_key, str(key))
                continue
            if cols is not None and cols.normalised:
                self.counters.inc("normalised.tracked")
        return took

    def _take_observations(self, limit: int) -> int:
        """Read up to ``limit`` observations from the ingest queue, as one batch; returns how many were taken."""
        items = self._obs_in.take(limit)
        if not items:
            return 0
        self.counters.inc("received", len(items))
        cols = self.pipeline.observations([item[0] for item in items], [keys.last_chunk(item[1]) for item in items])
        for i, exc in cols.errors:
            self.reject(exc, self._obs_key, items[i][1])
        if cols.normalised:
            self.counters.inc("normalised.tracks", cols.normalised)
        return len(items)

    def _run_control(self, item: tuple[str, tuple, None]) -> None:
        kind, (arg, fut), model = item
        if not fut.set_running_or_notify_cancel():  # the caller gave up waiting and was told "not applied"
            return
        if kind == "config":
            arg, if_match = arg
            in_force = None if if_match is None else config_etag(self.core.config)
            if in_force != if_match:  # checked where it is applied: between frames, on the one thread that swaps
                # configs, so no write can land in between
                fut.set_exception(ConfigConflict(
                    f"conflict: the config in force is {in_force}, not {if_match} (another write changed it since it"
                    f" was read); nothing applied — read it again and redo the change"))
                return
            try:
                self.core.check_config(arg, model)  # before it is stored: a refused write is not restored
            except ValueError as exc:
                fut.set_exception(exc)
                return
            if self._store is not None:  # stored before applied: a restart restores exactly what is in force
                try:
                    self._store.save(self._started_with, arg)
                except OSError as exc:
                    self.counters.inc("config_store_errors")
                    fut.set_exception(RuntimeError(f"cannot store the config in {self._store.path}: {exc}"))
                    return
            self.core.configure(arg, model)
            self.counters.inc("config_changes")
            fut.set_result(self.core.config)
        elif kind == "call":  # run a function on the worker, between frames
            try:
                fut.set_result(arg())
            except Exception as exc:
                fut.set_exception(exc)

    def _publish(self, out: FrameOutput, *, behind: bool = False) -> None:
        """Put ``objects`` (the frame latency ends here), then, unless a later frame is already waiting
        (``behind``, or a close queued or pending), the frame's ``motion/{id}`` messages."""
        self._objects_pub.put(out.payload)
        if out.missing and out.decided is None:  # the close listed observed tracks and not one observation came
            # (an ACL or a router that leaves out tracks/**): objects go out undecided, which is no progress
            self.progress.failure(time.monotonic(), f"no tracks/* observation of the {out.missing} the frame listed")
        else:
            self.progress.output(time.monotonic())
        self._record_latency((time.monotonic() - out.received_at) * 1e3)
        self.counters.inc("published")
        self.counters.inc("frames_processed")
        self._count_states(out.decisions.state, out.decisions.vetoed)
        self.last_seq = out.seq
        if out.decided is not None:
            if behind or self._closes or self.pipeline.pending:  # the next frame is already here
                self.counters.inc("motion_frames_shed")
            else:
                self._publish_motion(out)
        if (out.window, self.core.stride) != self._window:
            interval = self.core.frame_interval_s
            self.log.info("window now %s (was %s): %s, window_size %d at %s Hz",
                          _window_words(out.window, self.core.stride), _window_words(*self._window),
                          "frame interval not measured yet (a stream restarted or just begun)" if interval is None
                          else f"frames {interval:.3g} s apart", out.config.window_size,
                          out.config.window_reference_hz)
            self._window = (out.window, self.core.stride)
        evicted, labels, stamps, seqs = self.pipeline.settle(out)
        if evicted:
            self.counters.inc("windows_evicted", evicted)
        cal = self.core.calibration_state()
        if cal is not self._calibration:
            self._calibration, self._gauges = cal, calibration_gauges(cal)
        self._store_calibration()
        with self._latest_lock:
            header = {"stamp": out.header.stamp, "frame_id": out.header.frame_id, "seq": out.header.seq}
            self._latest = _Latest(header, out.objects, out.decisions, labels, stamps, seqs, out.config, out.window)

    def _count_states(self, state: np.ndarray, vetoed: np.ndarray) -> None:
        """Object-frames per decision (``objects.static`` …, running), those of them the jump veto called static
        although the test rejected (``objects.vetoed``: how often the veto overrules the test is for an operator to
        see) and the last frame's (``now.static`` …): what the run summary reports."""
        per = np.bincount(state.astype(np.intp), minlength=len(STATE_NAMES)) if state.size else np.zeros(3, int)
        for i, name in enumerate(STATE_NAMES):
            self.counters.inc(f"objects.{name}", int(per[i]))
            self.counters.set(f"now.{name}", int(per[i]))
        self.counters.inc("objects.vetoed", int(np.count_nonzero(vetoed)))

    def _record_latency(self, ms: float) -> None:
        self.latencies_ms.append(ms)
        le = next((b for b in LATENCY_BUCKETS_MS if ms <= b), math.inf)
        self.counters.inc(f"frame_latency_ms.bucket.{le:g}")
        self.counters.inc("frame_latency_ms.sum_us", int(ms * 1000))
        self.counters.inc("frame_latency_ms.count")

    def _publish_motion(self, out: FrameOutput) -> None:
        """One MotionState per observed track (after ``objects``: the frame latency has already ended), at a
        lower Zenoh priority than ``objects``."""
        n = 0
        for tid, payload in self.pipeline.motion_payloads(out):
            self._motion_pubs.put(tid, payload)
            n += 1
        self.counters.inc("published", n)

    # ---------------------------------------------------------------- queryables

    def run_on_worker(self, fn, timeout: float = CONFIG_APPLY_TIMEOUT_S):
        """Run ``fn()`` on the worker thread between two frames and return its result."""
        fut: Future = Future()
        self._queue.put(("call", (fn, fut), None), timeout=timeout)  # bounded: queue.Full when the worker is stuck
        return fut.result(timeout=timeout)

    def _reply(self, query: zenoh.Query, key: str, attachment: bytes | None, payload: bytes) -> None:
        """A success reply, signed for a holder of the token who asked with a nonce (``config_auth``)."""
        query.reply(query.key_expr, payload,
                    attachment=self.config_writes.reply_attachment(attachment, key, payload))

    def _on_config_query(self, query: zenoh.Query) -> None:
        payload = query.payload.to_bytes() if query.payload is not None else b""
        attachment = query.attachment.to_bytes() if query.attachment is not None else None
        key = keys.classifier_config(self.ns)
        if not payload:
            self._reply(query, key, attachment, _config_reply(self.core.config))
            return
        if_match = query.parameters.get(keys.IF_MATCH)
        refused = self.config_writes.refusal(attachment, key, if_match, payload, time.time_ns())
        if refused:
            self.counters.inc("config_writes_refused")
            self._reject_log.warn(f"config write on {query.key_expr} refused: {refused}",
                                  kind="config write refused")
            query.reply_err(_config_reply(self.core.config, refused))
            return
        try:  # bounded before it is built: a config is a few hundred bytes, its maps and lists a handful of entries
            cfg = decode(ClassifierConfig, payload, max_bytes=MAX_CONFIG_BYTES, max_array_len=MAX_MAP_ENTRIES,
                         max_map_len=MAX_MAP_ENTRIES)
        except DecodeError as exc:  # counted and logged as every refused payload is: an oversized write had been
            # counted `rejected` but never `over_limit`, and no refused write was logged
            self.reject(exc, key, str(query.key_expr))
            query.reply_err(_config_reply(self.core.config, str(exc)))
            return
        if if_match is not None and not _is_etag(if_match):
            why = f"must be {ETAG_HEX} lowercase hex digits (the etag of a config reply)"
            self.reject(DecodeError("ClassifierConfig", keys.IF_MATCH, why), key,
                        str(query.key_expr))
            query.reply_err(_config_reply(self.core.config, f"{keys.IF_MATCH}: {why}"))
            return
        model = None
        if cfg.calibration == "file" and cfg.calibration_file:
            try:  # read here, off the worker: a slow disk must not stall frames
                model = read_calibration(cfg.calibration_file)
            except CalibrationFileError as exc:
                self.reject(DecodeError("ClassifierConfig", "calibration_file", str(exc)),
                            key, str(query.key_expr))
                query.reply_err(_config_reply(self.core.config, f"calibration_file: {exc}"))
                return
        fut: Future = Future()
        try:
            self._queue.put(("config", ((cfg, if_match), fut), model), timeout=CONFIG_APPLY_TIMEOUT_S)  # bounded, as above
        except queue.Full:  # 64 writes and calls wait behind a stuck worker: the writer had got no reply at all
            self.counters.inc("config_writes_unapplied")  # counted: an operator sees writes lost to a stuck worker
            query.reply_err(_config_reply(self.core.config, (
                f"not applied: the classifier's worker queue stayed full for {CONFIG_APPLY_TIMEOUT_S:g} s"
                f" ({self._queue.maxsize} writes and calls waiting)")))
            return
        try:
            in_force = fut.result(timeout=CONFIG_APPLY_TIMEOUT_S)
        except ConfigConflict as exc:  # a conditional write whose config was changed by another: nothing applied
            self.counters.inc("config_writes_conflicted")
            query.reply_err(_config_reply(self.core.config, str(exc), conflict=True))
            return
        except ValueError as exc:  # refused by the core (check_config): nothing applied
            self.counters.inc("rejected")
            self.counters.inc("rejected.classifier/config")
            query.reply_err(_config_reply(self.core.config, str(exc)))
            return
        except Exception:  # worker stuck or stopping: withdraw the write, so that "not applied" stays true
            if fut.cancel():
                self.counters.inc("config_writes_unapplied")  # withdrawn: never applied (counted only then)
                query.reply_err(_config_reply(self.core.config, (
                    f"not applied: the classifier's worker did not take it within {CONFIG_APPLY_TIMEOUT_S:g} s")))
                return
            try:  # taken meanwhile: what came of it
                in_force = fut.result(timeout=CONFIG_APPLY_TIMEOUT_S)
            except ConfigConflict as exc:
                self.counters.inc("config_writes_conflicted")
                query.reply_err(_config_reply(self.core.config, str(exc), conflict=True))
            except ValueError as exc:
                self.counters.inc("rejected")
                self.counters.inc("rejected.classifier/config")
                query.reply_err(_config_reply(self.core.config, str(exc)))
            except TimeoutError:  # still being applied (a slow config store): it may yet come into force
                query.reply_err(_config_reply(self.core.config, (
                    "not confirmed: the worker took it late and has not finished; it may still come into force: "
                    "read the config")))
            except Exception as late:  # noqa: BLE001  the worker failed it (the config store not written): not applied
                query.reply_err(_config_reply(self.core.config, f"not applied: {type(late).__name__}: {late}"))
            else:
                self.log.info("config applied: %s", in_force.model_dump(exclude={"schema_version"}))
                self._reply(query, key, attachment, _config_reply(in_force))
            return
        self.log.info("config applied: %s", in_force.model_dump(exclude={"schema_version"}))
        self._reply(query, key, attachment, _config_reply(in_force))

    def state_map(self) -> dict:
        """The ``classifier/state`` payload as a plain map (a ``ClassifierStateSnapshot`` when validated).

        Built from the arrays of the last frame with one ``tolist`` per column: a sidecar polls this at frame
        rate, and a model per track would cost the classifier more than the frame itself.
        """
        with self._latest_lock:
            latest = self._latest
        base = {"schema_version": SCHEMA_VERSION, "counters": self.counters.snapshot(),
                "calibration": self._calibration}
        if latest is None:
            return {**base, "header": {"stamp": 0, "frame_id": "map", "seq": 0},
                    "config": self.core.config.model_dump(mode="python"), "tracks": []}
        dec = latest.decisions
        col = {k: getattr(dec, k).tolist() for k in
               ("z_x", "z_y", "chi2", "alpha", "threshold", "window_length", "speed")}
        states, labels = dec.state.tolist(), latest.labels.tolist()
        stamps, seqs = latest.stamps.tolist(), latest.seqs.tolist()
        window_size = latest.window
        poses = Poses.of(latest.objects)  # static objects already carry their window mean
        ids = [i.decode() for i in latest.objects["object_id"].tolist()]
        px, py, yaw = poses.x.tolist(), poses.y.tolist(), poses.yaw.tolist()
        length, width = poses.length.tolist(), poses.width.tolist()
        tracks = []
        for i, tid in enumerate(ids):
            tracks.append({
                "track_id": tid, "label": labels[i], "state": STATE_NAMES[states[i]],
                "z_x": col["z_x"][i], "z_y": col["z_y"][i], "chi2": col["chi2"][i], "alpha": col["alpha"][i],
                "threshold": col["threshold"][i], "window_length": col["window_length"][i],
                "window_size": window_size, "speed": col["speed"][i], "x": px[i], "y": py[i], "yaw": yaw[i],
                "length": length[i], "width": width[i], "last_update_ns": stamps[i], "last_seq": seqs[i],
            })
        return {**base, "header": dict(latest.header),
                "config": latest.config.model_dump(mode="python"), "tracks": tracks}

    def gauges(self) -> dict[str, float]:
        """The heartbeat's gauges: the calibration the latest frame was decided with (:func:`calibration_gauges`)."""
        return self._gauges

    def _on_state_query(self, query: zenoh.Query) -> None:
        with self._latest_lock:
            latest = self._latest
        attachment = query.attachment.to_bytes() if query.attachment is not None else None
        key = keys.classifier_state(self.ns)
        if latest is not None and latest.encoded is not None:
            self._reply(query, key, attachment, latest.encoded)
            return
        data = encode(self.state_map())
        if latest is not None:
            latest.encoded = data  # same frame, same answer: encode once per frame
        self._reply(query, key, attachment, data)

