"""What a buggy upstream or an intruder on the bus sends, against real services over real Zenoh sessions.

Issue 18's probes, as tests: one ``detections`` of 100,000 empty objects (it once wedged the tracker with a
74.5 GiB allocation) and one stamped an hour ahead (it once reset the tracker and lost every track) must cost
nothing but a counter; a flood of 20,000 ``tracked`` messages (it once grew the classifier to 954 MB and silenced
``objects`` for 29 s) must leave its memory bounded and ``objects`` flowing again at once.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time

import msgpack
import numpy as np
import pytest
import zenoh

from helpers import to_message, wait_until
from jitterguard.bench.pipeline import stop_processes, vm_rss_kb
from jitterguard.bench.tracker_sequences import CAR, Obj, make_sequence
from jitterguard.runtime import build_config, free_tcp_port, loopback_options
from jitterguard.schemas import decode, encode, keys, peek_header
from jitterguard.schemas.models import Header, Heartbeat
from jitterguard.services.classifier.service import ClassifierService
from jitterguard.services.classifier.synthetic_tracks import FrameRecords, TrackScenario, generate
from jitterguard.services.tracker.service import TrackerService

pytestmark = pytest.mark.integration
T0 = 1_700_000_000_000_000_000
PERIOD = 50_000_000  # 20 Hz
HOUR = 3600 * 10**9


def test_a_huge_detections_and_one_an_hour_ahead_cost_a_counter_and_no_track() -> None:
    ns, port = "hostile_det", free_tcp_port()
    tracker = TrackerService(loopback_options(ns, port, listen_self=True))
    classifier = ClassifierService(loopback_options(ns, port))
    client = zenoh.open(build_config(loopback_options(ns, port)))
    objects: list[tuple[int, float, set[str]]] = []  # (seq, arrival, track IDs)
    lock = threading.Lock()

    def on_objects(sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        ids = {o["object_id"] for o in msgpack.unpackb(data)["objects"]}
        with lock:
            objects.append((peek_header(data)[0], time.monotonic(), ids))

    client.declare_subscriber(keys.objects(ns), on_objects)
    parked = [Obj(gid=g, label=CAR, x0=10.0 + 8 * g, y0=5.0, yaw0=0.0) for g in range(3)]
    scene = make_sequence(1, n_frames=120, objects=parked, ego_speed=0.0, ego_yaw_rate=0.0, miss_rate=0.0,
                          fp_rate=0.0, flip_rate=0.0, class_flicker=0.0, noise_base=0.05)

    def put(payload: bytes) -> None:
        client.put(keys.detections(ns), payload, congestion_control=zenoh.CongestionControl.BLOCK)

    def frame(k: int, stamp: int | None = None) -> bytes:
        msg = to_message(scene.frames[k])
        return encode(msg.model_copy(update={"header": Header(stamp=stamp or T0 + k * PERIOD, frame_id="lidar", seq=k)}))

    try:
        k = 0
        while not wait_until(lambda: bool(objects), 0.2) and k < 100:  # the mesh is up once objects come back
            put(frame(k))
            k += 1
        for k in range(k, k + 40):  # tracks confirmed and steady
            put(frame(k))
            time.sleep(0.05)
        assert wait_until(lambda: objects and objects[-1][0] == k, 10)
        with lock:
            before = objects[-1][2]
        assert len(before) == 3
        k += 1
        huge = msgpack.packb({"schema_version": 1, "header": {"stamp": T0 + k * PERIOD, "frame_id": "lidar", "seq": k},
                              "objects": [{}] * 100_000})
        put(huge)
        put(frame(k + 1, stamp=T0 + (k + 1) * PERIOD + HOUR))
        sent = time.monotonic()
        put(frame(k + 2))  # the next normal frame
        assert wait_until(lambda: any(s == k + 2 for s, _, _ in objects), 2.0), "objects did not resume within 2 s"
        with lock:
            seq, arrived, after = next(o for o in objects if o[0] == k + 2)
        assert arrived - sent < 2.0 and after == before  # no track lost, none born
        assert wait_until(lambda: tracker.counters.get("over_limit.detections") == 1)
        assert tracker.counters.get("rejected.detections") == 1 and tracker.counters.get("dropped_jump") == 1
        assert tracker.counters.get("resets") == 0 and tracker.counters.get("handler_errors") == 0
        assert classifier.counters.get("frames.upstream_restarts") == 0
    finally:
        client.close()
        classifier.close()
        tracker.close()


def test_a_flood_of_tracked_keeps_the_classifier_bounded_and_objects_resume() -> None:
    ns, port = "hostile_flood", free_tcp_port()
    proc = subprocess.Popen([sys.executable, "-m", "jitterguard.cli", "classifier", "--ns", ns,
                             "--listen", f"tcp/127.0.0.1:{port}", "--log-level", "WARNING"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    client = zenoh.open(build_config(loopback_options(ns, port)))
    seen: list[int] = []
    client.declare_subscriber(keys.objects(ns), lambda s: seen.append(peek_header(s.payload.to_bytes())[0]))
    beats: list[Heartbeat] = []  # the classifier's counters
    client.declare_subscriber(keys.heartbeat(ns, "classifier"),
                              lambda s: beats.append(decode(Heartbeat, s.payload.to_bytes())))
    pool = [FrameRecords.of(f) for f in generate(TrackScenario(n_static=10, n_moving=10, n_starting=0, seed=4), 20)]
    block = zenoh.CongestionControl.BLOCK

    def send(i: int) -> bytes:
        obs, tracked = pool[i % len(pool)].payloads(Header(stamp=T0 + i * PERIOD, frame_id="map", seq=i))
        for tid, payload in obs:
            client.put(keys.track(ns, tid), payload, congestion_control=block)
        client.put(keys.tracked(ns), tracked, congestion_control=block)
        return tracked

    try:
        i = 0
        while not wait_until(lambda: bool(seen), 0.2) and i < 300:  # the classifier is up once objects come back
            send(i)
            i += 1
        assert seen, f"the classifier never answered: {proc.stderr.read1(2000) if proc.poll() is not None else ''}"
        captured = []
        for i in range(i, i + 60):  # a steady minute's worth of frames at 20 Hz, compressed: the baseline
            captured.append(send(i))
            time.sleep(0.02)
        assert wait_until(lambda: seen[-1] == i, 10)
        time.sleep(0.5)
        baseline = vm_rss_kb(proc.pid)
        peak = baseline
        stop = threading.Event()

        def sample_rss() -> None:
            nonlocal peak
            while not stop.is_set():
                peak = max(peak, vm_rss_kb(proc.pid) or 0)
                time.sleep(0.02)

        sampler = threading.Thread(target=sample_rss)
        sampler.start()
        rng = np.random.default_rng(0)
        for n in range(20_000):  # captured frames replayed in a loop, and now and then a made-up far seq
            payload = captured[n % len(captured)]
            if n % 97 == 0:
                raw = msgpack.unpackb(payload)
                raw["header"]["seq"] = int(rng.integers(2**40, 2**62))
                payload = msgpack.packb(raw)
            client.put(keys.tracked(ns), payload)
        flood_end = time.monotonic()
        i += 1
        send(i)  # the next live frame
        resumed = wait_until(lambda: seen[-1] == i, 2.0)
        took = time.monotonic() - flood_end
        stop.set()
        sampler.join()
        print(f"\nflood: RSS {baseline} kB -> peak {peak} kB; objects again {took:.2f} s after its end")
        assert resumed, f"objects did not resume within 2 s after the flood ({took:.2f} s)"
        assert peak < 2 * baseline, f"RSS {peak} kB against a baseline of {baseline} kB"
        assert proc.poll() is None
        # The replayed frames are old and the far seqs never confirmed: dropped and counted, nothing reset.
        assert wait_until(lambda: beats and beats[-1].last_seq == i, 5)  # a heartbeat after the live frame
        counters = beats[-1].counters
        assert counters.get("frames.upstream_restarts", 0) == 0 and counters.get("frames.jumps", 0) == 0, counters
        assert counters.get("frames.duplicate_or_late_frames", 0) > 0, counters
    finally:
        client.close()
        stop_processes([proc])
