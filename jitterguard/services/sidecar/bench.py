"""``jitterguard bench sidecar``: ``GET /v1/state`` latency with N live tracks while the pipeline runs.

Layout, as deployed: the classifier, a track feeder (standing in for the tracker) and the sidecar each run in
their own OS process (``spawn``, so no Zenoh session crosses a fork), meshed over loopback Zenoh with
multicast scouting off. This process is the HTTP load client. It waits for the classifier to report all N
tracks, warms up, then times every ``GET /v1/state`` (request sent → whole body read) for the measured span
and reads the classifier's frame counter from ``/metrics`` before and after, so the JSON states the frame
rate the pipeline actually sustained during the measurement, next to the latency percentiles.

Feeding: N tracks from the built-in synthetic scenario, ``base_frames`` frames generated once and replayed
in a loop with fresh sequence numbers and stamps (generating 500 objects × 20 Hz of pydantic models live
would measure the generator, not the sidecar).
"""

from __future__ import annotations

import multiprocessing as mp
import os
import platform
import re
import signal
import threading
import time
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from ...runtime import free_tcp_port, loopback_options

NS = "bench-sidecar"


@dataclass(frozen=True)
class BenchParams:
    tracks: int = 500
    rate_hz: float = 20.0
    duration_s: float = 15.0
    warmup_s: float = 3.0
    request_rate_hz: float = 50.0  # 0: back to back
    seed: int = 0
    base_frames: int = 40
    poll_period_s: float = 0.05


# ------------------------------------------------------------------------------------------ child processes


def _stop_on_sigterm() -> threading.Event:
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    return stop


def _classifier_main(zport: int) -> None:
    from ...runtime import setup_logging
    from ..classifier.service import ClassifierService

    setup_logging("WARNING")
    ClassifierService(loopback_options(NS, zport, listen_self=True)).run_forever()


def _feeder_main(zport: int, params: BenchParams, ready: Any) -> None:
    import msgpack
    import zenoh

    from ...runtime.zenoh_config import build_config
    from ...schemas import keys
    from ..classifier.synthetic_tracks import TrackScenario, generate

    stop = _stop_on_sigterm()
    n = params.tracks
    sc = TrackScenario(n_static=n - n // 4 - n // 20, n_moving=n // 4, n_starting=n // 20, rate_hz=params.rate_hz,
                       start_frame=params.base_frames // 2, seed=params.seed)
    base = []
    for fr in generate(sc, params.base_frames):
        obs = [(keys.track(NS, o.track.object_id), o.model_dump(mode="python")) for o in fr.observations]
        base.append((obs, fr.tracked.model_dump(mode="python")))
    session = zenoh.open(build_config(loopback_options(NS, zport)))
    ready.set()
    block = zenoh.CongestionControl.BLOCK
    period = 1.0 / params.rate_hz
    seq, next_t = 0, time.monotonic()
    stamp0 = time.time_ns()
    try:
        while not stop.is_set():
            obs, tracked = base[seq % len(base)]
            header = {"stamp": stamp0 + int(seq * period * 1e9), "frame_id": "map", "seq": seq}
            for key, d in obs:
                d["header"] = header
                session.put(key, msgpack.packb(d, use_bin_type=True), congestion_control=block)
            tracked["header"] = header
            session.put(keys.tracked(NS), msgpack.packb(tracked, use_bin_type=True), congestion_control=block)
            seq += 1
            next_t += period
            delay = next_t - time.monotonic()
            if delay < -1.0:  # hopelessly behind: do not burst to catch up
                next_t = time.monotonic()
            stop.wait(max(0.0, delay))
    finally:
        session.close()


def _sidecar_main(zport: int, port: int, poll_period_s: float) -> None:
    from ...runtime import setup_logging
    from .app import SidecarSettings
    from .cli import serve

    setup_logging("WARNING")
    serve(SidecarSettings(zenoh=loopback_options(NS, zport), poll_period_s=poll_period_s), "127.0.0.1", port,
          "WARNING")


# ------------------------------------------------------------------------------------------ the load client


def _percentiles(values: list[float]) -> dict[str, float]:
    a = np.asarray(values, dtype=np.float64)
    if a.size == 0:
        return {"n": 0}
    return {"n": int(a.size), "mean": float(a.mean()), "p50": float(np.percentile(a, 50)),
            "p90": float(np.percentile(a, 90)), "p99": float(np.percentile(a, 99)), "max": float(a.max())}


def _frames_total(client: Any) -> float:
    m = re.search(r"^jitterguard_classifier_frames_total (\S+)$", client.get("/metrics").text, re.M)
    return float(m.group(1)) if m else float("nan")


def run_bench(params: BenchParams) -> dict[str, Any]:
    """Start the three processes, measure, stop them; returns the result as a JSON-able dict."""
    import httpx

    ctx = mp.get_context("spawn")
    zport, port = free_tcp_port(), free_tcp_port()
    fed = ctx.Event()
    procs = [ctx.Process(target=_classifier_main, args=(zport,), name="classifier", daemon=True)]
    procs[0].start()
    procs.append(ctx.Process(target=_sidecar_main, args=(zport, port, params.poll_period_s), name="sidecar",
                             daemon=True))
    procs.append(ctx.Process(target=_feeder_main, args=(zport, params, fed), name="feeder", daemon=True))
    for p in procs[1:]:
        p.start()
    url = f"http://127.0.0.1:{port}"
    try:
        with httpx.Client(base_url=url, timeout=10.0) as c:
            deadline = time.monotonic() + 120
            tracks_seen = 0
            while time.monotonic() < deadline:  # all N tracks live in the sidecar's view
                for p in procs:
                    if not p.is_alive():
                        raise RuntimeError(f"bench process {p.name} exited with {p.exitcode}")
                try:
                    r = c.get("/v1/state")
                    if r.status_code == 200:
                        tracks_seen = r.json()["counts"]["total"]
                        if tracks_seen >= params.tracks:
                            break
                except httpx.HTTPError:
                    pass
                time.sleep(0.2)
            else:
                raise RuntimeError(f"the sidecar never showed {params.tracks} tracks (saw {tracks_seen})")
            time.sleep(params.warmup_s)
            lat: list[float] = []
            staleness: list[float] = []
            sizes: list[int] = []
            counts: list[int] = []
            statuses: dict[int, int] = {}
            not_ready = 0
            f0, t0 = _frames_total(c), time.monotonic()
            end = t0 + params.duration_s
            gap = 1.0 / params.request_rate_hz if params.request_rate_hz > 0 else 0.0
            next_t = t0
            i = 0
            while True:
                now = time.monotonic()
                if now >= end:
                    break
                if gap:
                    if now < next_t:
                        time.sleep(next_t - now)
                    next_t += gap
                s = time.perf_counter()
                r = c.get("/v1/state")
                body = r.content
                lat.append((time.perf_counter() - s) * 1e3)
                statuses[r.status_code] = statuses.get(r.status_code, 0) + 1
                if r.status_code != 200:
                    continue
                sizes.append(len(body))
                if r.headers.get("x-classifier-ready") == "false":
                    not_ready += 1
                if i % 10 == 0:  # parsing every reply would load the client, not the server
                    doc = r.json()
                    counts.append(doc["counts"]["total"])
                    staleness.append((time.time_ns() - doc["polled_at_ns"]) / 1e6)
                i += 1
            f1, t1 = _frames_total(c), time.monotonic()
            ready = c.get("/readyz").json()
        return {
            "bench": "sidecar",
            "what": "GET /v1/state latency (request sent to whole body read) with N live tracks, "
                    "classifier + feeder + sidecar in separate processes over loopback Zenoh",
            "params": asdict(params),
            "tracks_seen": {"min": int(min(counts)), "max": int(max(counts))} if counts else None,
            "pipeline_hz": (f1 - f0) / (t1 - t0),
            "frames_measured": f1 - f0,
            "get_state_ms": _percentiles(lat),
            "status_counts": {str(k): v for k, v in sorted(statuses.items())},
            "replies_while_heartbeat_late": not_ready,
            "body_bytes_mean": float(np.mean(sizes)) if sizes else 0.0,
            "state_staleness_ms": _percentiles(staleness),
            "classifier_ready_at_end": ready["ready"],
            "host": {"cpus": os.cpu_count(), "python": platform.python_version(), "machine": platform.machine()},
            "target": {"p99_ms_max": 20.0, "p99_met": bool(lat) and float(np.percentile(lat, 99)) <= 20.0,
                       "pipeline_at_rate": (f1 - f0) / (t1 - t0) >= 0.95 * params.rate_hz,
                       "all_200": set(statuses) == {200}},
        }
    finally:
        for p in reversed(procs):
            if p.is_alive():
                p.terminate()
        for p in reversed(procs):
            p.join(timeout=10)
            if p.is_alive():
                p.kill()
                p.join()
