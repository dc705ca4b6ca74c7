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

import math
import multiprocessing as mp
import os
import platform
import re
import threading
import time
from dataclasses import asdict, dataclass
from typing import Any

import msgpack
import numpy as np
import zenoh

from ..geometry import yaw_from_quaternion
from ..runtime import free_tcp_port, loopback_options, setup_logging
from ..runtime.signals import stop_on_signals
from ..runtime.zenoh_config import build_config
from ..schemas import encode, keys, read_track_observations
from ..schemas.models import ClassifierConfig, ClassifierStateSnapshot, Header, Heartbeat, TrackStateEntry
from ..services.classifier.adapter import observation_rows, observations_from_rows
from ..services.classifier.core import STATE_NAMES, STATIC, MotionClassifierCore
from ..services.classifier.service import ClassifierService
from ..services.classifier.synthetic_tracks import FrameRecords, TrackScenario, generate

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
    state_source: str = "pipeline"  # "pipeline": the real classifier fed by a feeder; "synthetic": see below


# ------------------------------------------------------------------------------------------ child processes


def _stop_on_sigterm() -> threading.Event:
    stop = threading.Event()
    stop_on_signals(stop.set)
    return stop


def _classifier_main(zport: int) -> None:
    setup_logging("WARNING")
    ClassifierService(loopback_options(NS, zport, listen_self=True)).run_forever()


def _feeder_main(zport: int, params: BenchParams, ready: Any) -> None:
    stop = _stop_on_sigterm()
    n = params.tracks
    sc = TrackScenario(n_static=n - n // 4 - n // 20, n_moving=n // 4, n_starting=n // 20, rate_hz=params.rate_hz,
                       start_frame=params.base_frames // 2, seed=params.seed)
    base = [FrameRecords.of(fr) for fr in generate(sc, params.base_frames)]
    session = zenoh.open(build_config(loopback_options(NS, zport)))
    ready.set()
    block = zenoh.CongestionControl.BLOCK
    period = 1.0 / params.rate_hz
    seq, next_t = 0, time.monotonic()
    stamp0 = time.time_ns()
    try:
        while not stop.is_set():
            header = Header(stamp=stamp0 + int(seq * period * 1e9), frame_id="map", seq=seq)
            obs, tracked = base[seq % len(base)].payloads(header)
            for tid, payload in obs:
                session.put(keys.track(NS, tid), payload, congestion_control=block)
            session.put(keys.tracked(NS), tracked, congestion_control=block)
            seq += 1
            next_t += period
            delay = next_t - time.monotonic()
            if delay < -1.0:  # hopelessly behind: do not burst to catch up
                next_t = time.monotonic()
            stop.wait(max(0.0, delay))
    finally:
        session.close()


def _synthetic_snapshots(params: BenchParams) -> list[dict]:
    """``base_frames`` state snapshots (as msgpack-ready maps) decided by the real classifier core."""
    n = params.tracks
    sc = TrackScenario(n_static=n - n // 4 - n // 20, n_moving=n // 4, n_starting=n // 20, rate_hz=params.rate_hz,
                       start_frame=params.base_frames // 2, seed=params.seed)
    cfg = ClassifierConfig()
    core = MotionClassifierCore(cfg, capacity=n)
    out = []
    for fr in generate(sc, params.base_frames):
        h = fr.tracked.header
        obs, _ = FrameRecords.of(fr).payloads()
        rows = [r for _, _, r in observation_rows(read_track_observations([p for _, p in obs]))]
        dec = core.update(observations_from_rows(rows, h.seq, h.stamp))
        entries = []
        for i, obj in enumerate(fr.tracked.objects):
            pose = obj.kinematics.pose_with_covariance.pose
            static = int(dec.state[i]) == STATIC
            q = pose.orientation
            entries.append(TrackStateEntry(
                track_id=obj.object_id, label=obj.classification[0].label if obj.classification else 0,
                state=STATE_NAMES[int(dec.state[i])],  # type: ignore[arg-type]  # one of the three names
                z_x=float(dec.z_x[i]), z_y=float(dec.z_y[i]),
                chi2=float(dec.chi2[i]), alpha=float(dec.alpha[i]), threshold=float(dec.threshold[i]),
                window_length=int(dec.window_length[i]), window_size=cfg.window_size, speed=float(dec.speed[i]),
                x=float(dec.mean_x[i]) if static else pose.position.x,
                y=float(dec.mean_y[i]) if static else pose.position.y,
                yaw=yaw_from_quaternion(q.x, q.y, q.z, q.w), length=obj.shape.dimensions.x,
                width=obj.shape.dimensions.y, last_update_ns=h.stamp, last_seq=h.seq))
        snap = ClassifierStateSnapshot(header=Header(stamp=h.stamp, seq=h.seq), config=cfg, tracks=entries)
        out.append(snap.model_dump(mode="python"))
    return out


def _synthetic_main(zport: int, params: BenchParams, ready: Any) -> None:
    """Stand-in for the classifier *process* with the sidecar-facing surface only: liveliness token,
    heartbeat and the ``classifier/state`` queryable, answering a new snapshot ``rate_hz`` times a second.

    Why: the sidecar's cost depends on what it is served (N tracks, a new snapshot every frame), not on how
    the classifier got there; this isolates the sidecar at the target load when the real classifier cannot
    sustain it on the bench host. The snapshots are real core decisions over the synthetic scenario.
    """
    stop = _stop_on_sigterm()
    snaps = _synthetic_snapshots(params)
    session = zenoh.open(build_config(loopback_options(NS, zport, listen_self=True)))
    token = session.liveliness().declare_token(keys.alive(NS, "classifier"))
    hb_pub = session.declare_publisher(keys.heartbeat(NS, "classifier"))
    current = {"data": b"", "seq": -1}

    def on_query(query: zenoh.Query) -> None:
        with query:
            query.reply(query.key_expr, current["data"])

    queryable = session.declare_queryable(keys.classifier_state(NS), on_query)
    period = 1.0 / params.rate_hz
    seq, next_t, last_hb, started = 0, time.monotonic(), 0.0, time.monotonic()
    stamp0 = time.time_ns()
    ready.set()
    try:
        while not stop.is_set():
            snap = snaps[seq % len(snaps)]
            stamp = stamp0 + int(seq * period * 1e9)
            snap["header"] = {"stamp": stamp, "frame_id": "map", "seq": seq}
            for t in snap["tracks"]:
                t["last_update_ns"], t["last_seq"] = stamp, seq
            snap["counters"] = {"frames_processed": seq + 1}
            current["data"], current["seq"] = msgpack.packb(snap, use_bin_type=True), seq
            now = time.monotonic()
            if now - last_hb >= 1.0:
                hb_pub.put(encode(Heartbeat(service="classifier", pid=os.getpid(), stamp=time.time_ns(),
                                            last_seq=seq, uptime_s=now - started,
                                            counters={"frames_processed": seq + 1})))
                last_hb = now
            seq += 1
            next_t += period
            stop.wait(max(0.0, next_t - time.monotonic()))
    finally:
        queryable.undeclare()
        token.undeclare()
        hb_pub.undeclare()
        session.close()


def _sidecar_main(zport: int, port: int, poll_period_s: float) -> None:
    from ..services.sidecar.app import SidecarSettings  # FastAPI and uvicorn: the optional "api" extra
    from ..services.sidecar.cli import serve

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


def _poll_stats(metrics: str) -> dict[str, float]:
    """The sidecar's own view of its classifier/state polls (count, failures, mean round trip)."""
    def value(name: str) -> float:
        m = re.search(rf"^{name} (\S+)$", metrics, re.M)
        return float(m.group(1)) if m else float("nan")
    n = value("jitterguard_sidecar_state_poll_seconds_count")
    total = value("jitterguard_sidecar_state_poll_seconds_sum")
    return {"polls": n, "failures": value("jitterguard_sidecar_state_poll_failures_total"),
            "mean_round_trip_ms": total / n * 1e3 if n else float("nan")}


def run_bench(params: BenchParams) -> dict[str, Any]:
    """Start the three processes, measure, stop them; returns the result as a JSON-able dict."""
    import httpx  # the optional "api" extra

    ctx = mp.get_context("spawn")
    zport, port = free_tcp_port(), free_tcp_port()
    fed = ctx.Event()
    if params.state_source == "synthetic":
        procs = [ctx.Process(target=_synthetic_main, args=(zport, params, fed), name="state-source", daemon=True)]
    else:
        procs = [ctx.Process(target=_classifier_main, args=(zport,), name="classifier", daemon=True)]
    procs[0].start()
    procs.append(ctx.Process(target=_sidecar_main, args=(zport, port, params.poll_period_s), name="sidecar",
                             daemon=True))
    if params.state_source != "synthetic":
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
                        # ... and the classifier up for /metrics (its heartbeat heard), which counts the frames
                        if tracks_seen >= params.tracks and not math.isnan(_frames_total(c)):
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
            polls = _poll_stats(c.get("/metrics").text)
        return {
            "bench": "sidecar",
            "what": "GET /v1/state latency (request sent to whole body read) with N live tracks; state source, "
                    "feeder and sidecar in separate processes over loopback Zenoh",
            "state_source": params.state_source,
            "params": asdict(params),
            "tracks_seen": {"min": int(min(counts)), "max": int(max(counts))} if counts else None,
            "pipeline_hz": (f1 - f0) / (t1 - t0),
            "frames_measured": f1 - f0,
            "get_state_ms": _percentiles(lat),
            "status_counts": {str(k): v for k, v in sorted(statuses.items())},
            "replies_while_heartbeat_late": not_ready,
            "body_bytes_mean": float(np.mean(sizes)) if sizes else 0.0,
            "state_staleness_ms": _percentiles(staleness),
            "sidecar_state_polls": polls,
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
