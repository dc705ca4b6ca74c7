"""Benchmarks of the classifier: the pure core per frame, the per-frame work in-process, and the live service.

Two service figures: ``p50_ms``/``p99_ms`` time a frame inside the classifier process, from the moment its
``tracked`` sample reaches the classifier's Zenoh subscriber (stamped on the subscriber's callback, before any
queueing or decoding) to the return of the ``objects`` put; ``e2e_p50_ms``/``e2e_p99_ms`` time it from the
feeder's ``put`` of ``tracked`` to the arrival of ``objects`` back at the feeder — an upper bound that
includes both transports. The classifier runs in its own process (spawned, as under the supervisor, with
``manage_gc`` as ``jitterguard classifier`` runs it), fed over loopback Zenoh at a fixed rate.
``frame_cost`` is the same per-frame work without transport or threads, in thread CPU time.
"""

from __future__ import annotations

import gc
import multiprocessing as mp
import time

import numpy as np

from ..runtime import Service, free_tcp_port, loopback_options
from ..runtime.gc_policy import GC_GEN0_THRESHOLD
from ..schemas import keys, peek_header
from ..schemas.models import ClassifierConfig, Header
from ..services.classifier.adapter import ClassifierAdapter
from ..services.classifier.calibration import NoiseModel
from ..services.classifier.core import MotionClassifierCore, Observations
from ..services.classifier.service import ClassifierService
from ..services.classifier.synthetic_tracks import FrameRecords, TrackScenario, generate


_BENCH_LABELS = np.array([1] * 6 + [2] + [7] * 2 + [6])  # cars, a truck, pedestrians, a bicycle (per 10 tracks)


class _Scene:
    """Tracks as the classifier sees them from a tracker at 10 Hz: 5–60 m around the sensor, a third moving
    (vehicles 5 m/s, vulnerable road users 1.4 m/s), 0.1 m jitter, ``missed`` of observations missed, tracks born at
    staggered frames (so ring buffers are at every rotation) and mixed classes (so the calibration's groups
    differ). The windows then hold the time patterns a live stream gives, not one shared pattern — though
    fewer distinct ones than a tracker's stream, where each missed detection gives a window gaps of its own
    (docs/performance.md, "The correlation kernel by recursion")."""

    def __init__(self, n: int, seed: int, missed: float = 0.05) -> None:
        self.rng = np.random.default_rng(seed)
        self.missed = missed
        self.ids = np.array([f"{i:032x}" for i in range(n)], dtype="S32")
        self.labels = _BENCH_LABELS[np.arange(n) % len(_BENCH_LABELS)]
        r, a = self.rng.uniform(5.0, 60.0, n), self.rng.uniform(0.0, 2 * np.pi, n)
        self.start = np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
        speed = np.where(self.labels >= 6, 1.4, 5.0) * (np.arange(n) % 3 == 0)
        h = self.rng.uniform(0.0, 2 * np.pi, n)
        self.vel = speed[:, None] * np.stack([np.cos(h), np.sin(h)], axis=1)
        self.born = np.arange(n) % 10

    def frame(self, k: int) -> Observations:
        seen = (self.born <= k) & (self.rng.random(len(self.ids)) > self.missed)
        n = int(seen.sum())
        t = k * 0.1
        pos = self.start[seen] + self.vel[seen] * t + self.rng.normal(0.0, 0.1, (n, 2))
        return Observations(
            track_ids=self.ids[seen], labels=self.labels[seen], x=pos[:, 0], y=pos[:, 1],
            cxx=np.full(n, 0.01), cxy=np.zeros(n), cyy=np.full(n, 0.02),
            speed=np.hypot(self.vel[seen, 0], self.vel[seen, 1]), stamp_ns=1_700_000_000_000_000_000 + k * 100_000_000,
            seq=k)


PAPER_STATISTIC = ClassifierConfig(calibration="off", effective_n="cluster", min_speed_mps=0.0, jump_veto=False)
"""The paper's statistic and decision: reported variances as they are, each half one sample, H0 v = 0, no veto."""


def bench_core(sizes: tuple[int, ...] = (10, 100, 1000), window: int | None = None, frames: int = 300,
               seed: int = 0) -> dict:
    """Time of one ``update`` per track count on the same frames, alternating frame by frame (back to back, so
    all see the same machine load): the default configuration (online calibration: the statistic plus pooling
    the windows that turned over, ~1/W of the tracks per frame), ``file_*`` (the same statistic with fixed
    scales, as with ``calibration: file``: no learning) and ``paper_*`` (:data:`PAPER_STATISTIC`). Median, mean
    and p99 [ms] after a warm-up of 3 windows."""
    window = ClassifierConfig().window_size if window is None else window  # the shipped default
    out: dict[str, dict[str, float]] = {}
    for n in sizes:
        scene = _Scene(n, seed)
        from_file = ClassifierConfig(window_size=window, calibration="file", calibration_file="bench.yaml")
        cores = {"default": MotionClassifierCore(ClassifierConfig(window_size=window), capacity=n),
                 "file": MotionClassifierCore(from_file, capacity=n, calibration_model=NoiseModel.prior()),
                 "paper": MotionClassifierCore(PAPER_STATISTIC.model_copy(update={"window_size": window}), capacity=n)}
        batches = [scene.frame(k) for k in range(frames + 3 * window)]
        times: dict[str, list[float]] = {name: [] for name in cores}
        for i, b in enumerate(batches):
            for name, core in cores.items():
                t0 = time.perf_counter()
                core.update(b)
                if i >= 3 * window:
                    times[name].append(time.perf_counter() - t0)
        row: dict[str, float] = {}
        for name, ts in times.items():
            arr = np.asarray(ts) * 1e3
            prefix = "" if name == "default" else f"{name}_"
            row[f"{prefix}median_ms"] = float(np.median(arr))
            row[f"{prefix}mean_ms"] = float(arr.mean())
            row[f"{prefix}p99_ms"] = float(np.percentile(arr, 99))
        row["updates_per_s"] = n / (row["median_ms"] * 1e-3)
        out[f"tracks_{n}"] = row
    return out


def _encoded_frames(tracks: int, n_frames: int, rate_hz: float, seed: int, ns: str) -> list[tuple[list[tuple[str, bytes]], bytes]]:
    """``n_frames`` of the synthetic track scenario as the tracker puts them: ``(tracks/{id} key, payload)``
    per observation, then the ``tracked`` payload; 40 distinct frames looped with fresh seqs."""
    sc = TrackScenario(n_static=tracks // 2, n_moving=tracks - tracks // 2 - 1, n_starting=1, seed=seed, rate_hz=rate_hz)
    pool = [FrameRecords.of(f) for f in generate(sc, 40)]
    out = []
    for i in range(n_frames):
        header = Header(stamp=1_700_000_000_000_000_000 + round(i * 1e9 / rate_hz), frame_id="map", seq=i)
        obs, tracked = pool[i % len(pool)].payloads(header)
        out.append(([(keys.track(ns, tid), p) for tid, p in obs], tracked))
    return out


def bench_frame_cost(tracks: int = 200, frames: int = 200, seed: int = 0) -> dict:
    """CPU time of the classifier's per-frame work in this process, no transport: median ms per frame of
    validating the observations, validating the closing ``tracked``, deciding and packing ``objects``
    (together: the work left when ``tracked`` arrives, once the observations are in), and what follows the
    ``objects`` put (building the ``motion/{id}`` payloads, evicting windows). Thread CPU time, so it is insensitive to contention, unlike the service figures
    (cache effects of a busy machine remain); garbage collection is managed as in the service process."""
    encoded = _encoded_frames(tracks, frames, 20.0, seed, "bench")
    pipe = ClassifierAdapter()
    thresholds = gc.get_threshold()
    gc.collect()
    gc.set_threshold(GC_GEN0_THRESHOLD, 1000, 1000)  # as manage_gc_for_latency, without freezing the caller's heap
    parts: dict[str, list[float]] = {"observations_ms": [], "close_ms": [], "finish_ms": [], "after_put_ms": []}
    try:
        _drive(pipe, encoded, parts)
    finally:
        gc.set_threshold(*thresholds)
    warm = frames // 10  # the first frames fill the windows and warm the caches
    at_close = np.add(parts["close_ms"], parts["finish_ms"])[warm:]
    res: dict[str, float | int] = {"tracks": tracks, "frames": frames - warm}
    res.update({k: float(np.median(v[warm:])) for k, v in parts.items()})
    res["at_close_ms"] = float(np.median(at_close))
    res["at_close_p99_ms"] = float(np.percentile(at_close, 99))
    return res


def _drive(pipe, encoded: list, parts: dict[str, list[float]]) -> None:
    for obs_payloads, tracked_payload in encoded:
        t0 = time.thread_time()
        for k in range(0, len(obs_payloads), 64):  # as the service takes them off its channel
            pipe.observations([p for _, p in obs_payloads[k:k + 64]])
        t1 = time.thread_time()
        pipe.close(tracked_payload, t1)
        t2 = time.thread_time()
        (frame,) = pipe.ready(t2)
        out = pipe.finish(frame)
        t3 = time.thread_time()
        for _ in pipe.motion_payloads(out):
            pass
        pipe.settle(out)
        t4 = time.thread_time()
        for k, a, b in (("observations_ms", t0, t1), ("close_ms", t1, t2), ("finish_ms", t2, t3), ("after_put_ms", t3, t4)):
            parts[k].append((b - a) * 1e3)
        gc.collect(1)  # the service's worker does this between frames


def _classifier_process(opts, conn) -> None:  # runs in a spawned child, as `jitterguard classifier` would
    svc = ClassifierService(opts, manage_gc=True)
    conn.send("ready")
    conn.recv()  # wait for "stop"
    time.sleep(0.3)  # let the last frames finish
    conn.send({"latencies_ms": list(svc.latencies_ms), "counters": svc.counters.snapshot()})
    svc.close()


def bench_service(tracks: int = 200, rate_hz: float = 20.0, duration_s: float = 60.0, seed: int = 0) -> dict:
    """Run the real classifier service for ``duration_s`` at ``tracks`` × ``rate_hz``; latency percentiles."""
    port = free_tcp_port()
    ns = "bench"
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_classifier_process, args=(loopback_options(ns, port, listen_self=True), child))
    proc.start()
    parent.recv()

    class _Feeder(Service):
        name = "bench-feeder"

    feeder = _Feeder(loopback_options(ns, port))
    received: dict[int, float] = {}
    sent: dict[int, float] = {}

    def on_objects(sample) -> None:
        t = time.perf_counter()
        head = peek_header(sample.payload.to_bytes())
        if head is not None:
            received[head[0]] = t

    feeder.session.declare_subscriber(keys.objects(ns), on_objects)
    time.sleep(1.0)  # let the mesh settle before the clock starts
    n_frames = int(duration_s * rate_hz)
    period = 1.0 / rate_hz
    # Encode every frame before the clock starts: the feeder shares these cores with the classifier,
    # and what is measured is the classifier, not the feeder's encoder.
    encoded = _encoded_frames(tracks, n_frames, rate_hz, seed, ns)
    t_next = time.monotonic()
    for i, (obs_payloads, tracked_payload) in enumerate(encoded):
        for key, payload in obs_payloads:
            feeder.put(key, payload)
        feeder.put(keys.tracked(ns), tracked_payload)
        sent[i] = time.perf_counter()
        t_next += period
        time.sleep(max(0.0, t_next - time.monotonic()))
    time.sleep(1.0)
    parent.send("stop")
    result = parent.recv()
    proc.join(10)
    feeder.close()
    lat = np.asarray(result["latencies_ms"])
    e2e = np.asarray([(received[s] - sent[s]) * 1e3 for s in sent if s in received])
    processed = result["counters"].get("frames_processed", 0)
    return {
        "tracks": tracks,
        "rate_hz": rate_hz,
        "duration_s": duration_s,
        "p50_ms": float(np.percentile(lat, 50)) if lat.size else None,
        "p99_ms": float(np.percentile(lat, 99)) if lat.size else None,
        "max_ms": float(lat.max()) if lat.size else None,
        "frames_over_60_ms": int((lat > 60.0).sum()),  # stalls, and the frames queued behind them
        "e2e_p50_ms": float(np.percentile(e2e, 50)) if e2e.size else None,
        "e2e_p99_ms": float(np.percentile(e2e, 99)) if e2e.size else None,
        "frames_sent": n_frames,
        "frames_processed": processed,
        "frames_received_downstream": len(received),
        "frames_dropped": n_frames - processed,
        "rejected": result["counters"].get("rejected", 0),
        "counters": {k: v for k, v in result["counters"].items() if k.startswith("frames.") or k == "motion_frames_shed"},
    }
