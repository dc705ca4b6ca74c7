"""A lossy, duplicating, reordering relay between the services: nothing crashes, states keep coming, every
loss, duplicate and out-of-order frame is counted.

replay -> (ns src) -> relay -> (ns up) -> tracker -> (ns up) -> relay -> (ns down) -> classifier

The relay (this test's Zenoh session) duplicates some detection frames and re-sends some old ones (the tracker
must drop and count them), drops 10 % of ``tracks/*`` and duplicates / re-sends some ``tracked`` frames (the
classifier must count missing observations and duplicate or late frames and still publish ``objects`` and
``motion/*``).
"""

from __future__ import annotations

import random
import subprocess
import sys
import threading
from collections import deque
from pathlib import Path

import pytest
import zenoh

from jitterguard.bench.pipeline import stop_processes
from jitterguard.runtime import ZenohOptions, build_config, free_tcp_port, open_session
from jitterguard.schemas import decode, keys
from jitterguard.schemas.models import Heartbeat

from helpers import wait_until

pytestmark = pytest.mark.integration


def _spawn(log: Path, *args: str) -> subprocess.Popen:
    with open(log, "wb") as out:
        return subprocess.Popen([sys.executable, "-m", "jitterguard.cli", *args], stdout=out, stderr=subprocess.STDOUT)


def test_lossy_duplicating_relay(tmp_path):
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    procs = {"router": _spawn(tmp_path / "router.log", "router", "--listen", ep)}
    rng = random.Random(7)
    lock = threading.Lock()
    stats = {"tracks_dropped": 0, "tracks_passed": 0, "det_dup": 0, "det_old": 0, "tracked_dup": 0, "tracked_old": 0,
             "objects": 0, "motion": 0}
    beats: dict[str, Heartbeat] = {}
    old_det: deque[bytes] = deque(maxlen=10)
    old_tracked: deque[bytes] = deque(maxlen=10)
    try:
        cfg = build_config(ZenohOptions(ns="src", connect=(ep,), listen=()))
        with open_session(cfg, timeout_s=60) as s:
            pub_det = s.declare_publisher(keys.detections("up"), congestion_control=zenoh.CongestionControl.BLOCK)
            pub_tracked = s.declare_publisher(keys.tracked("down"), congestion_control=zenoh.CongestionControl.BLOCK)

            def forward_with_repeats(pub, old: deque[bytes], name: str):
                """Forward each frame; 5 % of them twice, and 5 % followed by one of ten frames back."""
                def forward(sample) -> None:
                    data = sample.payload.to_bytes()
                    pub.put(data)
                    with lock:
                        r = rng.random()
                        if r < 0.05:
                            stats[f"{name}_dup"] += 1
                            pub.put(data)
                        elif r < 0.10 and len(old) > 3:
                            stats[f"{name}_old"] += 1
                            pub.put(old[0])
                        old.append(data)
                return forward

            on_det = forward_with_repeats(pub_det, old_det, "det")

            def on_track(sample) -> None:
                with lock:
                    drop = rng.random() < 0.10
                    stats["tracks_dropped" if drop else "tracks_passed"] += 1
                if not drop:
                    s.put(str(sample.key_expr).replace("jg/up/", "jg/down/", 1), sample.payload.to_bytes())

            on_tracked = forward_with_repeats(pub_tracked, old_tracked, "tracked")

            def on_beat(sample) -> None:
                hb = decode(Heartbeat, sample.payload.to_bytes())
                beats[hb.service] = hb

            def bump(name: str):
                def cb(_sample) -> None:
                    with lock:
                        stats[name] += 1
                return cb

            s.declare_subscriber(keys.detections("src"), on_det)
            s.declare_subscriber(keys.tracks_all("up"), on_track)
            s.declare_subscriber(keys.tracked("up"), on_tracked)
            s.declare_subscriber("jg/*/heartbeat/*", on_beat)
            s.declare_subscriber(keys.objects("down"), bump("objects"))
            s.declare_subscriber(keys.motion_all("down"), bump("motion"))
            procs["classifier"] = _spawn(tmp_path / "classifier.log", "classifier", "--ns", "down", "--connect", ep)
            procs["tracker"] = _spawn(tmp_path / "tracker.log", "tracker", "--ns", "up", "--connect", ep)
            procs["replay"] = _spawn(tmp_path / "replay.log", "replay", "synthetic:mixed", "--level", "detections",
                                     "--loop", "--ns", "src", "--connect", ep)

            def enough() -> bool:
                with lock:
                    ok = stats["objects"] >= 60 and stats["det_dup"] >= 2 and stats["det_old"] >= 2 \
                        and stats["tracked_dup"] >= 2 and stats["tracked_old"] >= 2
                return ok

            assert wait_until(enough, timeout=90, period=0.2), (stats, (tmp_path / "classifier.log").read_text()[-2000:])
            n_obj = stats["objects"]
            # fresh heartbeats after the counts above
            beats.clear()
            assert wait_until(lambda: {"tracker", "classifier"} <= set(beats), timeout=10)
            assert wait_until(lambda: stats["objects"] > n_obj + 5, timeout=30)  # still publishing
            assert stats["motion"] > 0
            dead = {n: p.returncode for n, p in procs.items() if p.poll() is not None}
            assert not dead, dead
            tc, cc = beats["tracker"].counters, beats["classifier"].counters
            assert tc.get("dropped_duplicate", 0) >= 1, tc
            assert tc.get("dropped_out_of_order", 0) >= 1, tc
            assert cc.get("frames.missing_observations", 0) >= 1, cc
            assert cc.get("frames.duplicate_or_late_frames", 0) >= 1, cc
            assert cc.get("rejected", 0) == 0 and tc.get("rejected", 0) == 0
            print(f"\nrelay: {stats}\ntracker: {tc}\nclassifier: { {k: v for k, v in cc.items() if 'bucket' not in k} }")
    finally:
        stop_processes(procs.values())
