"""What a put flood on ``tracks/*`` costs the classifier: RSS, what it processed and what it dropped (counted or
not), and what its ingest does on the normal path. Prints JSON.

The classifier runs in a spawned child (its RSS is its own, and its garbage collection managed, as under
``jitterguard classifier``), listening on a free loopback port; this process feeds it from a plain Zenoh session (peer, multicast scouting off) with valid
``TrackObservation`` payloads (1.4 kB each) under a seq no ``tracked`` closes, ``--keys distinct`` (a new track ID
each put) or ``same`` (one ID). Per variant:

* ``flood``: ``--rounds`` rounds of ``--puts`` puts as fast as the feeder goes (BLOCK: every put reaches the
  classifier's session); after each, once the worker has drained, the child's RSS, the Python heap it traced
  (``--tracemalloc``: now, and ``py_heap_peak_kb`` its peak over the run) and the counters. ``sent - processed - dropped`` is what was lost and counted nowhere.
  ``rss_after_trim_kb``: the RSS once glibc's ``malloc_trim(0)`` returned its free pages (memory freed but kept
  by the allocator shows as the difference); ``rss_after_gc_kb``, ``rss_after_gc_trim_kb``: then after a full
  garbage collection (cyclic garbage not collected yet shows as the difference), and trimmed again.
* ``drain_per_s``: the worker paused (a call on it that waits), ``--burst`` puts queued, then released: the
  observations per second its worker takes off the ingest queue and reads (the consumer's path alone).
* ``ingest_per_s``: ``--burst`` puts with the worker running: observations per second from the first put until
  all are counted in (the receive path's per-sample cost included, both processes on the same cores).
* ``frames``: ``--tracks`` tracks at ``--rate`` Hz (20) for ``--frame-s`` seconds, each frame's observations then its
  ``tracked``: the frame latency (p50 / p99, ms) as the service counts it, and the classifier process's CPU time
  per frame (every thread: Zenoh's, the callbacks', the worker's, the heartbeat's; less sensitive to the
  machine's other load than the latency).

``--variants`` picks the ingests compared in one run: ``current`` (the service as it is), ``ring`` (the
observations in a Zenoh ``RingChannel`` of 16,384 drained with ``try_recv()``, as before the counted queue) and
``direct`` (the counted queue filled on Zenoh's receiving thread, ``indirect=False``); ``--repeat`` runs them
alternately (the same machine load for each), and ``normal_path_medians`` gives each variant's medians over the
repeats and their ratios to the last variant's.

Usage: nice -n 19 .venv/bin/python scripts/flood_memory.py [--rounds 5] [--puts 100000] [--keys distinct|same]
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import json
import multiprocessing as mp
import random
import threading
import time
import tracemalloc
from typing import Any

import msgpack
import numpy as np
import zenoh

from jitterguard.runtime import build_config, free_tcp_port, loopback_options
from jitterguard.runtime.ingest_queue import IngestQueue
from jitterguard.runtime.memtrace import rss_kb
from jitterguard.runtime.service import counter_key
from jitterguard.schemas import encode, keys
from jitterguard.schemas.models import DetectedObject, Header, ObjectClassification, TrackObservation, TrackState
from jitterguard.services.classifier.config_writes import ConfigWritePolicy
from jitterguard.services.classifier.service import ClassifierService
from jitterguard.services.classifier.synthetic_tracks import FrameRecords, TrackScenario, generate

NS = "flood"
BLOCK = zenoh.CongestionControl.BLOCK
FAR_SEQ = 10**12  # no close comes for it: observations are counted, bounded per frame, never decided


def _service_class(variant: str) -> type[ClassifierService]:
    classes = {"current": ClassifierService, "ring": _RingClassifier, "direct": _DirectClassifier}
    if variant not in classes:
        raise ValueError(f"unknown variant {variant!r}: one of {', '.join(classes)}")
    return classes[variant]


class _RingInbox:
    """``take`` over a Zenoh ``RingChannel``, as the classifier's ingest was before: the worker pulls Samples (each
    holding its receive buffer until then) and refuses an oversized one there; the ring drops uncounted."""

    def __init__(self, svc: ClassifierService, key: str, capacity: int, max_bytes: int | None, what: str,
                 limit_name: str) -> None:
        self._svc, self._key, self._max, self._what, self._limit_name = svc, key, max_bytes, what, limit_name
        self._sub = svc.session.declare_subscriber(key, zenoh.handlers.RingChannel(capacity))
        svc._declared.append(self._sub)

    def take(self, limit: int) -> list[tuple[bytes, str]]:
        samples = []
        while len(samples) < limit:
            sample = self._sub.try_recv()
            if sample is None:
                break
            samples.append(sample)
        return [(s.payload.to_bytes(), str(s.key_expr)) for s in samples
                if not self._svc.oversized(s, self._max, self._what, self._key, self._limit_name)]


class _ObservationsApart(ClassifierService):
    """The service with its observations taken in by :meth:`observations_inbox` instead of its ``tracks/*`` route
    (the closes subscribed on their own key, as before 7 Dec)."""

    def subscribe_queues(self, key_expr: str, routes: Any, route_of: Any, **kw: Any) -> list[Any]:
        if len(routes) != 2:
            return super().subscribe_queues(key_expr, routes, route_of, **kw)
        obs, close = routes
        (closes,) = super().subscribe_queues(close.key, (close,), lambda _key: 0, **kw)
        return [self.observations_inbox(obs, kw.get("max_bytes"), kw.get("limit_name", "")), closes]

    def observations_inbox(self, route: Any, max_bytes: int | None, limit_name: str) -> Any:
        raise NotImplementedError


class _RingClassifier(_ObservationsApart):
    """The ingest as it was: a Zenoh ring channel that drops its oldest sample uncounted when full."""

    def observations_inbox(self, route: Any, max_bytes: int | None, limit_name: str) -> Any:
        return _RingInbox(self, route.key, route.capacity, max_bytes, route.what, limit_name)


class _DirectClassifier(_ObservationsApart):
    """The ingest queue filled by a callback that Zenoh runs on its own receiving thread (``indirect=False``),
    not handed to a Python thread of its own first."""

    def observations_inbox(self, route: Any, max_bytes: int | None, limit_name: str) -> IngestQueue:
        key, what = route.key, route.what
        inbox = IngestQueue(route.capacity, route.max_queued_bytes)
        counter = f"dropped_queue.{counter_key(key)}"

        def on_sample(sample: zenoh.Sample) -> None:  # as Service.subscribe_queues'
            payload = sample.payload
            if max_bytes is not None and len(payload) > max_bytes:
                self.oversized(sample, max_bytes, what, key, limit_name)
                self.counters.inc("received")
                return
            dropped = inbox.push(payload.to_bytes(), str(sample.key_expr), time.monotonic())
            if dropped:
                self.counters.inc(counter, dropped)

        self._declared.append(self.session.declare_subscriber(key, zenoh.handlers.Callback(on_sample,
                                                                                             indirect=False)))
        return inbox


def _child(variant: str, port: int, trace: bool, conn) -> None:
    """The classifier process: serves ``stats``, ``pause``, ``resume``, ``trim``, ``latencies`` until ``stop``."""
    if trace:
        tracemalloc.start(1)
    svc = _service_class(variant)(loopback_options(NS, port, listen_self=True), straggler_timeout_s=0.5,
                                  config_writes=ConfigWritePolicy.open(), manage_gc=True)  # as the CLI runs it
    gate = threading.Event()
    conn.send("ready")
    while True:
        cmd = conn.recv()
        if cmd == "stop":
            break
        if cmd == "pause":
            gate.clear()
            threading.Thread(target=svc.run_on_worker, args=(gate.wait, 3600.0), daemon=True).start()
            conn.send("paused")
        elif cmd == "resume":
            gate.set()
            conn.send("resumed")
        elif cmd == "trim":
            ctypes.CDLL("libc.so.6").malloc_trim(0)
            conn.send(rss_kb())
        elif cmd == "collect":
            gc.collect()
            conn.send(rss_kb())
        elif cmd == "top":  # where the traced Python heap is now (diagnosis, --tracemalloc)
            stats = tracemalloc.take_snapshot().statistics("lineno")[:8] if trace else []
            conn.send([f"{st.size // 1024} kB {st.count} {st.traceback}" for st in stats])
        elif cmd == "latencies":
            lat = list(svc.latencies_ms)
            svc.latencies_ms.clear()
            conn.send(lat)
        else:
            conn.send({"rss_kb": rss_kb(), "counters": svc.counters.snapshot(), "cpu_s": time.process_time(),
                       "py_heap_kb": tracemalloc.get_traced_memory()[0] // 1024 if trace else None,
                       "py_heap_peak_kb": tracemalloc.get_traced_memory()[1] // 1024 if trace else None})
    gate.set()
    svc.close()
    conn.send("stopped")


class _Child:
    def __init__(self, variant: str, trace: bool) -> None:
        self.port = free_tcp_port()
        ctx = mp.get_context("spawn")
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_child, args=(variant, self.port, trace, child))
        self.proc.start()
        assert self.conn.recv() == "ready"

    def ask(self, cmd: str) -> Any:
        self.conn.send(cmd)
        return self.conn.recv()

    def stats(self) -> dict:
        return self.ask("stats")

    def wait_drained(self, expected: int, timeout: float = 120.0) -> dict:
        """Stats once ``received`` + counted drops reach ``expected``, or have not moved for 2 s."""
        last, still_since, deadline = None, time.monotonic(), time.monotonic() + timeout
        while time.monotonic() < deadline:
            s = self.stats()
            seen = _processed(s) + _dropped(s)
            if seen >= expected:
                return s
            if seen != last:
                last, still_since = seen, time.monotonic()
            elif time.monotonic() - still_since > 2.0:
                return s
            time.sleep(0.05)
        return self.stats()

    def close(self) -> None:
        self.ask("stop")
        self.proc.join(20)


def _processed(stats: dict) -> int:
    return stats["counters"].get("received", 0)


def _dropped(stats: dict) -> int:
    return stats["counters"].get("dropped_queue.tracks/*", 0)


def _flood_payloads(n: int, distinct: bool, seed: int, pad: int = 0) -> list[tuple[str, bytes]]:
    """``n`` valid observations, or with ``pad`` > 0 each one a field of ``pad`` bytes larger (refused by the
    worker's read as an unknown field, after it waited in the queue: what it costs while it waits is the point)."""
    rng = random.Random(seed)
    det = DetectedObject(classification=[ObjectClassification()])
    header = Header(stamp=FAR_SEQ, seq=FAR_SEQ)
    ids = ["%032x" % rng.getrandbits(128) for _ in range(n if distinct else 1)]
    cache: dict[str, bytes] = {}
    out = []
    for i in range(n):
        tid = ids[i % len(ids)]
        if tid not in cache:
            data = encode(TrackObservation(header=header, detection=det, track=TrackState(object_id=tid, x=1.0, y=2.0)))
            cache[tid] = msgpack.packb({**msgpack.unpackb(data), "pad": b"\0" * pad}) if pad else data
        out.append((keys.track(NS, tid), cache[tid]))
    return out


EXPRESS = False
"""``--express``: every flood put leaves in a batch of its own (Zenoh's ``express``), as puts from many publishers
or a slow one arrive; unbatched, each sample has had a receive buffer of its own."""


def _put_all(session: zenoh.Session, payloads: list[tuple[str, bytes]], express: bool = False) -> float:
    t0 = time.perf_counter()
    for key, data in payloads:
        session.put(key, data, congestion_control=BLOCK, express=express)
    return time.perf_counter() - t0


def _flood(child: _Child, session: zenoh.Session, rounds: int, payloads: list) -> dict:
    base = child.stats()
    out: dict[str, Any] = {"rss_before_kb": base["rss_kb"], "py_heap_before_kb": base["py_heap_kb"], "rounds": []}
    for _ in range(rounds):
        before = child.stats()
        put_s = _put_all(session, payloads, EXPRESS)
        after = child.wait_drained(_processed(before) + _dropped(before) + len(payloads))
        processed = _processed(after) - _processed(before)
        dropped = _dropped(after) - _dropped(before)
        out["rounds"].append({"sent": len(payloads), "put_s": round(put_s, 2), "processed": processed,
                              "dropped_counted": dropped, "uncounted": len(payloads) - processed - dropped,
                              "rss_kb": after["rss_kb"], "py_heap_kb": after["py_heap_kb"]})
    time.sleep(2.0)
    out["rss_end_kb"] = child.stats()["rss_kb"]
    out["rss_after_trim_kb"] = child.ask("trim")
    out["rss_after_gc_kb"] = child.ask("collect")
    out["rss_after_gc_trim_kb"] = child.ask("trim")
    out["py_heap_peak_kb"] = child.stats()["py_heap_peak_kb"]
    if out["py_heap_peak_kb"] is not None:
        out["py_heap_top"] = child.ask("top")
    out["counters"] = {k: v for k, v in child.stats()["counters"].items()
                       if k.startswith(("dropped", "frames.", "rejected", "received", "over_limit"))}
    return out


def _drain_rate(child: _Child, session: zenoh.Session, payloads: list) -> float:
    """Observations per second the paused worker, released, takes off a queue of ``len(payloads)``."""
    child.ask("pause")
    before = _processed(child.stats())
    _put_all(session, payloads)
    time.sleep(1.0)  # every put delivered into the queue
    t0 = time.perf_counter()
    child.ask("resume")
    after = child.wait_drained(before + len(payloads))
    took = time.perf_counter() - t0
    return (_processed(after) - before) / took


def _ingest_rate(child: _Child, session: zenoh.Session, payloads: list) -> float:
    before = _processed(child.stats())
    t0 = time.perf_counter()
    _put_all(session, payloads)
    after = child.wait_drained(before + len(payloads))
    return (_processed(after) - before) / (time.perf_counter() - t0)


def _frames(child: _Child, session: zenoh.Session, tracks: int, seconds: float, seed: int, rate: float) -> dict:
    sc = TrackScenario(n_static=tracks // 2, n_moving=tracks - tracks // 2 - 1, n_starting=1, seed=seed, rate_hz=rate)
    pool = [FrameRecords.of(f) for f in generate(sc, 40)]
    n = int(seconds * rate)
    frames = []
    for i in range(n):
        obs, tracked = pool[i % len(pool)].payloads(Header(stamp=1_700_000_000_000_000_000 + round(i * 1e9 / rate),
                                                           frame_id="map", seq=i))
        frames.append(([(keys.track(NS, tid), p) for tid, p in obs], tracked))
    child.ask("latencies")  # forget what came before
    before = child.stats()
    cpu0 = before["cpu_s"]
    t_next = time.monotonic()
    for obs, tracked in frames:
        _put_all(session, obs)
        session.put(keys.tracked(NS), tracked, congestion_control=BLOCK)
        t_next += 1.0 / rate
        time.sleep(max(0.0, t_next - time.monotonic()))
    time.sleep(1.0)
    after = child.stats()
    cpu_ms = (after["cpu_s"] - cpu0) * 1e3 / n
    counts = {k: v - before["counters"].get(k, 0) for k, v in after["counters"].items()
              if k.startswith(("frames.", "dropped_queue")) and v != before["counters"].get(k, 0)}
    lat = np.asarray(child.ask("latencies"))
    warm = len(lat) // 5
    lat = lat[warm:]
    return {"frames_sent": n, "frames_timed": int(lat.size), "p50_ms": float(np.percentile(lat, 50)),
            "p99_ms": float(np.percentile(lat, 99)), "cpu_ms_per_frame": cpu_ms,
            "processed": after["counters"].get("frames_processed", 0) - before["counters"].get("frames_processed", 0),
            "counters": counts}


def run_variant(variant: str, args: argparse.Namespace) -> dict:
    child = _Child(variant, args.tracemalloc)
    session = zenoh.open(build_config(loopback_options(NS, child.port)))
    try:
        time.sleep(1.0)  # the mesh settles
        burst = _flood_payloads(args.burst, distinct=True, seed=1)
        res: dict[str, Any] = {"variant": variant}
        res["frames"] = _frames(child, session, args.tracks, args.frame_s, seed=0, rate=args.rate)
        res["drain_per_s"] = round(_drain_rate(child, session, burst))
        res["ingest_per_s"] = round(_ingest_rate(child, session, burst))
        if args.rounds:
            res["flood"] = _flood(child, session, args.rounds, _flood_payloads(
                args.puts, distinct=args.keys == "distinct", seed=2, pad=args.pad))
        return res
    finally:
        session.close()
        child.close()


def _normal_path_ratios(runs: list[dict], base: str) -> dict:
    """Per variant, the median over the repeats of each normal-path figure and its ratio to ``base``'s median."""
    def median(variant: str, pick) -> float:
        return float(np.median([pick(r) for r in runs if r["variant"] == variant]))

    figures = {"drain_per_s": lambda r: r["drain_per_s"], "ingest_per_s": lambda r: r["ingest_per_s"],
               "frame_p50_ms": lambda r: r["frames"]["p50_ms"], "frame_p99_ms": lambda r: r["frames"]["p99_ms"],
               "cpu_ms_per_frame": lambda r: r["frames"]["cpu_ms_per_frame"]}
    out = {}
    for variant in dict.fromkeys(r["variant"] for r in runs):
        out[variant] = {name: median(variant, pick) for name, pick in figures.items()}
        if variant != base:
            out[variant]["ratio_to_" + base] = {name: round(median(variant, pick) / median(base, pick), 3)
                                                for name, pick in figures.items()}
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--variants", default="current,ring")
    p.add_argument("--rounds", type=int, default=5, help="flood rounds (0: the normal path only)")
    p.add_argument("--repeat", type=int, default=1, help="run the variants this many times, alternating")
    p.add_argument("--puts", type=int, default=100_000)
    p.add_argument("--keys", choices=("distinct", "same"), default="distinct")
    p.add_argument("--burst", type=int, default=8000, help="puts of the drain and ingest rates (fits every queue)")
    p.add_argument("--tracks", type=int, default=200)
    p.add_argument("--rate", type=float, default=20.0, help="frames per second of the normal path")
    p.add_argument("--frame-s", type=float, default=10.0)
    p.add_argument("--tracemalloc", action="store_true", help="trace the child's Python heap (slows it)")
    p.add_argument("--express", action="store_true", help="flood puts unbatched (see EXPRESS)")
    p.add_argument("--pad", type=int, default=0, help="flood payloads this many bytes larger (refused once read)")
    args = p.parse_args()
    global EXPRESS
    EXPRESS = args.express
    variants = args.variants.split(",")
    runs = [run_variant(v, args) for _ in range(args.repeat) for v in variants]  # alternated: the same load
    out: dict[str, Any] = {"keys": args.keys, "puts": args.puts, "rounds": args.rounds, "express": args.express,
                           "pad": args.pad, "repeat": args.repeat, "runs": runs,
                           "normal_path_medians": _normal_path_ratios(runs, variants[-1])}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
