"""The classifier as a Zenoh service: a thin adapter around :class:`MotionClassifierCore`.

Threads: Zenoh's subscriber callbacks only decode and enqueue; one worker thread owns the core, assembles
frames (observations + the closing ``tracked``), decides, and publishes ``objects`` first (what the
predictor waits for) and then ``motion/{id}``. Config writes go through the same queue, so a write is
applied between two frames and the reply reports what is in force from the next frame on.
"""

from __future__ import annotations

import math
import queue
import threading
import time
from collections import deque
from concurrent.futures import Future
from dataclasses import dataclass

import numpy as np
import zenoh

from ...geometry import yaw_from_quaternion
from ...runtime import Service, ZenohOptions
from ...schemas import SCHEMA_VERSION, DecodeError, decode, decode_with_raw, encode, keys, peek_header_seq
from ...schemas.models import (
    X_X,
    X_Y,
    Y_Y,
    ClassifierConfig,
    ClassifierStateSnapshot,
    ConfigReply,
    Header,
    TrackedObjects,
    TrackObservation,
)
from .core import STATE_NAMES, STATIC, Decisions, MotionClassifierCore, Observations
from .frames import CompleteFrame, FrameAssembler

CONFIG_APPLY_TIMEOUT_S = 2.0
LATENCY_WINDOW = 4096
LATENCY_BUCKETS_MS = (0.5, 1, 2, 5, 10, 20, 50, 100, 200, 500, 1000)
"""Frame-latency histogram buckets; exported as counters so the sidecar's /metrics can rebuild it."""


def observations_from_messages(msgs: list[TrackObservation], seq: int, stamp_ns: int) -> Observations:
    """Flatten one frame's TrackObservation messages into the core's arrays (world frame)."""
    ids, labels, x, y, cxx, cxy, cyy, speed = [], [], [], [], [], [], [], []
    for m in msgs:
        det = m.detection
        cov = det.kinematics.pose_with_covariance.covariance
        pos = det.kinematics.pose_with_covariance.pose.position
        trk = m.track
        ids.append(trk.object_id)
        labels.append(trk.label)
        x.append(pos.x)
        y.append(pos.y)
        cxx.append(cov[X_X])
        cxy.append(cov[X_Y])
        cyy.append(cov[Y_Y])
        speed.append(math.hypot(trk.vx, trk.vy))
    return Observations.from_lists(ids, labels, x, y, cxx, cxy, cyy, speed, stamp_ns=stamp_ns, seq=seq)


def apply_decisions_to_objects(objects: list[dict], dec: Decisions) -> None:
    """Edit the tracker's objects (validated msgpack maps) in place: static ⇒ zero twist, window-mean
    position, ``is_stationary``; dynamic and undecided pass through with ``is_stationary = false``."""
    states = dec.state.tolist()
    mx, my = dec.mean_x.tolist(), dec.mean_y.tolist()
    for obj, state, x, y in zip(objects, states, mx, my):
        kin = obj["kinematics"]
        if state == STATIC:
            kin["is_stationary"] = True
            pos = kin["pose_with_covariance"]["pose"]["position"]
            pos["x"], pos["y"] = x, y
            twist = kin["twist_with_covariance"]["twist"]
            twist["linear"] = {"x": 0.0, "y": 0.0, "z": 0.0}
            twist["angular"] = {"x": 0.0, "y": 0.0, "z": 0.0}
        else:
            kin["is_stationary"] = False


@dataclass
class _Latest:
    """What the state queryable reports: the last processed frame (immutable once stored)."""

    header: Header
    tracked: TrackedObjects
    decisions: Decisions
    labels: np.ndarray
    stamps: np.ndarray
    seqs: np.ndarray
    config: ClassifierConfig
    encoded: bytes | None = None


class ClassifierService(Service):
    name = "classifier"

    def __init__(self, opts: ZenohOptions, config: ClassifierConfig | None = None, *,
                 straggler_timeout_s: float = 0.05) -> None:
        super().__init__(opts)
        self.core = MotionClassifierCore(config or ClassifierConfig())
        self.assembler = FrameAssembler(straggler_timeout_s=straggler_timeout_s)
        self.latencies_ms: deque[float] = deque(maxlen=LATENCY_WINDOW)
        self._queue: queue.Queue = queue.Queue()
        self._latest: _Latest | None = None
        self._latest_lock = threading.Lock()
        self._objects_pub = self.publisher(keys.objects(self.ns))
        # Both inputs are pulled and decoded by the worker, so one thread owns all per-frame work.
        self._obs_sub = self.subscribe_channel(keys.tracks_all(self.ns))
        self._tracked_sub = self.subscribe_channel(keys.tracked(self.ns))
        self.queryable(keys.classifier_config(self.ns), self._on_config_query)
        self.queryable(keys.classifier_state(self.ns), self._on_state_query)
        self.spawn(self._worker, "worker")

    # ---------------------------------------------------------------- the worker

    def _pull(self, sub: zenoh.Subscriber, kind: str, events: list, limit: int) -> None:
        while len(events) < limit:
            sample = sub.try_recv()
            if sample is None:
                return
            self.counters.inc("received")
            events.append((kind, (sample.payload.to_bytes(), str(sample.key_expr)), time.perf_counter()))

    def _worker(self) -> None:
        raws: dict[int, dict] = {}
        while not self.stop_event.is_set():
            events: list = []
            # Observations first: the tracker sent them before the message that closes their frame.
            self._pull(self._obs_sub, "obs", events, 4096)
            self._pull(self._tracked_sub, "close", events, 4096 + 64)
            while len(events) < 8192:
                try:
                    events.append(self._queue.get_nowait())
                except queue.Empty:
                    break
            for kind, item, t0 in events:
                if kind == "obs":  # a straggler for a frame already closed is dropped: skip validating it
                    seq = peek_header_seq(item[0])
                    if seq is not None and self.assembler.is_late(seq):
                        self.assembler.count("late_observations")
                        continue
                self._handle(kind, item, t0, raws)
            for frame in self.assembler.pop_ready(time.perf_counter()):
                self._process(frame, raws.pop(frame.seq, None))
            if events:
                for k, v in self.assembler.counts.items():
                    self.counters.set(f"frames.{k}", v)
            else:
                time.sleep(0.0005)

    def _handle(self, kind: str, item, t0: float | None, raws: dict[int, dict]) -> None:
        if kind == "obs":
            obs = self.accept(TrackObservation, item[0], keys.tracks_all(self.ns), item[1])
            if obs is not None:
                self.assembler.add_observation(obs)
        elif kind == "close":
            data, key = item
            try:
                msg, raw = decode_with_raw(TrackedObjects, data)
            except DecodeError:
                self.accept(TrackedObjects, data, keys.tracked(self.ns), key)  # counts and logs it
                return
            restarts = self.assembler.counts.get("upstream_restarts", 0)
            if self.assembler.add_close(msg, t0):
                raws[msg.header.seq] = raw
            if self.assembler.counts.get("upstream_restarts", 0) != restarts:
                self.core.reset()
                raws.clear()
                raws[msg.header.seq] = raw
        elif kind == "config":
            cfg, fut = item
            self.core.configure(cfg)
            self.counters.inc("config_changes")
            fut.set_result(self.core.config)
        elif kind == "call":  # run a function on the worker, between frames
            fn, fut = item
            fut.set_result(fn())

    def _process(self, frame: CompleteFrame, raw: dict | None) -> None:
        header = frame.tracked.header
        obs = observations_from_messages(frame.observations, header.seq, header.stamp)
        if len(obs):
            decided = self.core.update(obs)
        else:
            decided = None
        reported = np.asarray([o.object_id for o in frame.tracked.objects], dtype="S32")
        evicted = self.core.retain(reported)
        if evicted:
            self.counters.inc("windows_evicted", evicted)
        dec = self.core.last_decisions(reported)

        out = raw if raw is not None else frame.tracked.model_dump(mode="python")
        apply_decisions_to_objects(out["objects"], dec)
        out["observed_track_ids"] = []
        self._objects_pub.put(encode(out))
        self._record_latency((time.perf_counter() - frame.received_at) * 1e3)
        self.counters.inc("published")
        self.counters.inc("frames_processed")
        self.last_seq = header.seq

        if decided is not None:
            self._publish_motion(header, obs, decided)
        labels, stamps, seqs = self.core.last_meta(reported)
        with self._latest_lock:
            self._latest = _Latest(header, frame.tracked, dec, labels, stamps, seqs, self.core.config)

    def _record_latency(self, ms: float) -> None:
        self.latencies_ms.append(ms)
        le = next((b for b in LATENCY_BUCKETS_MS if ms <= b), math.inf)
        self.counters.inc(f"frame_latency_ms.bucket.{le:g}")
        self.counters.inc("frame_latency_ms.sum_us", int(ms * 1000))
        self.counters.inc("frame_latency_ms.count")

    def _publish_motion(self, header: Header, obs: Observations, dec: Decisions) -> None:
        """One MotionState per observed track. Built as plain maps from arrays the core just computed
        (every value finite and in range by construction): a model per track costs more than the frame."""
        cfg = self.core.config
        h = {"stamp": header.stamp, "frame_id": "map", "seq": header.seq}
        names = dec.state_names()
        cols = {k: getattr(dec, k).tolist() for k in
                ("z_x", "z_y", "chi2", "threshold", "alpha", "window_length", "speed", "mean_x", "mean_y")}
        labels = obs.labels.tolist()
        for i, tid in enumerate(obs.track_ids.tolist()):
            tid_s = tid.decode()
            msg = {"schema_version": SCHEMA_VERSION, "header": h, "track_id": tid_s, "label": labels[i],
                   "state": names[i], "mode": cfg.mode, **{k: v[i] for k, v in cols.items()}}
            self.put(keys.motion(self.ns, tid_s), encode(msg))

    # ---------------------------------------------------------------- queryables

    def run_on_worker(self, fn, timeout: float = CONFIG_APPLY_TIMEOUT_S):
        """Run ``fn()`` on the worker thread between two frames and return its result."""
        fut: Future = Future()
        self._queue.put(("call", (fn, fut), None))
        return fut.result(timeout=timeout)

    def _on_config_query(self, query: zenoh.Query) -> None:
        payload = query.payload.to_bytes() if query.payload is not None else b""
        if not payload:
            query.reply(query.key_expr, encode(ConfigReply(ok=True, config=self.core.config)))
            return
        try:
            cfg = decode(ClassifierConfig, payload)
        except DecodeError as exc:
            self.counters.inc("rejected")
            self.counters.inc("rejected.classifier/config")
            query.reply_err(encode(ConfigReply(ok=False, config=self.core.config, error=str(exc))))
            return
        fut: Future = Future()
        self._queue.put(("config", (cfg, fut), None))
        try:
            in_force = fut.result(timeout=CONFIG_APPLY_TIMEOUT_S)
        except Exception as exc:  # worker stuck or stopping: say so, the write may not be in force
            query.reply_err(encode(ConfigReply(ok=False, config=self.core.config, error=f"not applied: {exc}")))
            return
        self.log.info("config applied: %s", in_force.model_dump(exclude={"schema_version"}))
        query.reply(query.key_expr, encode(ConfigReply(ok=True, config=in_force)))

    def state_map(self) -> dict:
        """The ``classifier/state`` payload as a plain map (a ``ClassifierStateSnapshot`` when validated).

        Built from the arrays of the last frame with one ``tolist`` per column: a sidecar polls this at frame
        rate, and a model per track would cost the classifier more than the frame itself.
        """
        with self._latest_lock:
            latest = self._latest
        base = {"schema_version": SCHEMA_VERSION, "counters": self.counters.snapshot()}
        if latest is None:
            return {**base, "header": {"stamp": 0, "frame_id": "map", "seq": 0},
                    "config": self.core.config.model_dump(mode="python"), "tracks": []}
        dec = latest.decisions
        col = {k: getattr(dec, k).tolist() for k in
               ("z_x", "z_y", "chi2", "alpha", "threshold", "window_length", "speed", "mean_x", "mean_y")}
        states, labels = dec.state.tolist(), latest.labels.tolist()
        stamps, seqs = latest.stamps.tolist(), latest.seqs.tolist()
        window_size = latest.config.window_size
        tracks = []
        for i, obj in enumerate(latest.tracked.objects):
            pose = obj.kinematics.pose_with_covariance.pose
            q = pose.orientation
            static = states[i] == STATIC
            tracks.append({
                "track_id": obj.object_id, "label": labels[i], "state": STATE_NAMES[states[i]],
                "z_x": col["z_x"][i], "z_y": col["z_y"][i], "chi2": col["chi2"][i], "alpha": col["alpha"][i],
                "threshold": col["threshold"][i], "window_length": col["window_length"][i],
                "window_size": window_size, "speed": col["speed"][i],
                "x": col["mean_x"][i] if static else pose.position.x,
                "y": col["mean_y"][i] if static else pose.position.y,
                "yaw": yaw_from_quaternion(q.x, q.y, q.z, q.w),
                "length": obj.shape.dimensions.x, "width": obj.shape.dimensions.y,
                "last_update_ns": stamps[i], "last_seq": seqs[i],
            })
        return {**base, "header": latest.header.model_dump(mode="python"),
                "config": latest.config.model_dump(mode="python"), "tracks": tracks}

    def state_snapshot(self) -> ClassifierStateSnapshot:
        """:meth:`state_map`, validated (for in-process users and tests)."""
        return ClassifierStateSnapshot.model_validate(self.state_map())

    def _on_state_query(self, query: zenoh.Query) -> None:
        with self._latest_lock:
            latest = self._latest
        if latest is not None and latest.encoded is not None:
            query.reply(query.key_expr, latest.encoded)
            return
        data = encode(self.state_map())
        if latest is not None:
            latest.encoded = data  # same frame, same answer: encode once per frame
        query.reply(query.key_expr, data)

