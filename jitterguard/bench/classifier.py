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
from ..services.classifier.core import MotionClassifierCore, Observations
from ..services.classifier.service import ClassifierService
from ..services.classifier.synthetic_tracks import FrameRecords, TrackScenario, generate


def _frame(rng: np.random.Generator, ids: list[str], t: int) -> Observations:
    n = len(ids)
    moving = np.arange(n) % 2 == 0
    return Observations.from_lists(
        ids, np.ones(n), rng.normal(0, 0.1, n) + moving * 0.5 * t, rng.normal(0, 0.1, n),
        np.full(n, 0.01), np.zeros(n), np.full(n, 0.02), np.where(moving, 5.0, 0.2), seq=t,
    )


def bench_core(sizes: tuple[int, ...] = (10, 100, 1000), window: int = 10, frames: int = 300, seed: int = 0) -> dict:
    """Median time of one ``update`` (window full, after warm-up) for each track count."""
    out: dict[str, dict[str, float]] = {}
    for n in sizes:
        rng = np.random.default_rng(seed)
        ids = [f"{i:032x}" for i in range(n)]
        core = MotionClassifierCore(ClassifierConfig(window_size=window), capacity=n)
        batches = [_frame(rng, ids, t) for t in range(frames + window)]
        for b in batches[:window]:  # warm-up: fill every window
            core.update(b)
        times = []
        for b in batches[window:]:
            t0 = time.perf_counter()
            core.update(b)
            times.append(time.perf_counter() - t0)
        med = float(np.median(times))
        out[f"tracks_{n}"] = {"median_ms": med * 1e3, "updates_per_s": n / med}
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
        "e2e_p50_ms": float(np.percentile(e2e, 50)) if e2e.size else None,
        "e2e_p99_ms": float(np.percentile(e2e, 99)) if e2e.size else None,
        "frames_sent": n_frames,
        "frames_processed": processed,
        "frames_received_downstream": len(received),
        "frames_dropped": n_frames - processed,
        "rejected": result["counters"].get("rejected", 0),
        "counters": {k: v for k, v in result["counters"].items() if k.startswith("frames.") or k == "motion_frames_shed"},
    }
