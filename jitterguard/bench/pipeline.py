"""``jitterguard bench pipeline``: detections in, classified objects out, through real tracker and classifier
processes over a real Zenoh router.

The bench spawns ``jitterguard router``, ``jitterguard tracker`` and ``jitterguard classifier`` as separate
processes (exactly what supervisord runs), publishes ``DetectedObjects`` of ``--objects`` objects at ``--rate`` Hz
on ``detections`` itself, and times each frame from its ``put`` to the arrival of the classifier's ``objects``
with the same ``header.seq`` (read with :func:`~jitterguard.schemas.peek_header`, no validation in the timing path). RSS of each
child comes from ``/proc/<pid>/status`` (VmRSS), sampled after the first minute (or 20 % of a shorter run) and at
the end. The scene: objects on a jittered 8 m grid, 30 % parked, the rest oscillating along their heading (so
the run can go on for any length without objects drifting away), detector noise 0.1-0.3 m with matching
reported variances, 5 % misses. ``--churn N`` moves N objects a frame (round robin) to a far, empty cell of the
grid, so the tracker loses N tracks a frame (they coast out over ``max_coast_s``) and confirms N new ones: N new
track IDs, hence N new ``tracks/{id}`` keys, a frame, as a detector produces on real scans. A freed cell rests
for about three seconds before it is used again, longer than a lost track coasts, so a new object is never
taken for the old one. ``tracks_born_per_frame`` (from the tracker's heartbeat) says what churn was reached.
"""

from __future__ import annotations

import gc
import math
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import zenoh

from ..geometry import quaternion_from_yaw
from ..runtime import ZenohOptions, build_config, free_tcp_port, open_session
from ..schemas import DecodeError, decode, keys, peek_header
from ..schemas.models import DetectedObjects, Heartbeat
from ..schemas.wire import HEARTBEAT_BOUNDS

CLASSES = {1: (4.5, 1.9, 1.6), 7: (0.6, 0.6, 1.7), 6: (1.8, 0.6, 1.6)}
CELL_M = 8.0
"""Grid spacing of the scene, m: wider than any association gate and than an object's oscillation."""
CELL_REST_S = 3.0
"""How long a cell an object left stays empty (the tracker's lost track coasts 1 s by default)."""


class SceneGenerator:
    """Detection-level frames as msgpack maps, patched in place from one validated template (cheap per frame)."""

    def __init__(self, n_objects: int, rate_hz: float, seed: int = 0, churn: int = 0) -> None:
        self.rng = np.random.default_rng(seed)
        self.n, self.dt, self.churn = n_objects, 1.0 / rate_hz, min(churn, n_objects)
        rest_frames = int(math.ceil(CELL_REST_S * rate_hz))
        self.side = side = int(math.ceil(math.sqrt(n_objects + self.churn * rest_frames)))
        order = self.rng.permutation(side * side)
        self.cell = order[:n_objects].copy()  # each object's cell
        self.free = deque(order[n_objects:].tolist())  # cells to move to, the longest-free first
        self.next_mover = 0
        self.x0, self.y0 = self._place(self.cell)
        self.kind = self.rng.choice([1, 7, 6], size=n_objects, p=[0.75, 0.2, 0.05])
        self.heading = self.rng.uniform(-math.pi, math.pi, n_objects)
        self.amp = np.where(self.rng.random(n_objects) < 0.3, 0.0, self.rng.uniform(1.0, 3.0, n_objects))
        self.omega = 2 * math.pi / self.rng.uniform(8.0, 20.0, n_objects)
        self.sig = 0.1 + 0.2 * self.rng.random(n_objects)
        objs = []
        for i in range(n_objects):
            dims = CLASSES[int(self.kind[i])]
            qx, qy, qz, qw = quaternion_from_yaw(float(self.heading[i]))
            cov = [0.0] * 36
            cov[0] = cov[7] = float(self.sig[i] ** 2)
            cov[14] = 0.01
            cov[35] = 0.0025
            objs.append({
                "existence_probability": 0.9,
                "classification": [{"label": int(self.kind[i]), "probability": 0.9}],
                "kinematics": {
                    "pose_with_covariance": {"pose": {"position": {"x": 0.0, "y": 0.0, "z": 0.8},
                                                      "orientation": {"x": qx, "y": qy, "z": qz, "w": qw}},
                                             "covariance": cov},
                    "has_position_covariance": True,
                },
                "shape": {"type": 0, "dimensions": {"x": dims[0], "y": dims[1], "z": dims[2]}},
            })
        model = DetectedObjects.model_validate({"header": {"stamp": 0, "frame_id": "lidar", "seq": 0},
                                                "objects": objs})
        self.template = model.model_dump(mode="python")
        self.objs = self.template["objects"]

    def _place(self, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        half = self.side / 2
        return ((cells % self.side - half) * CELL_M + self.rng.uniform(-1, 1, len(cells)),
                (cells // self.side - half) * CELL_M + self.rng.uniform(-1, 1, len(cells)))

    def _move_churned(self) -> None:
        """``churn`` objects (round robin) to the longest-free cells; their old cells rest at the back."""
        movers = (self.next_mover + np.arange(self.churn)) % self.n
        self.next_mover = (self.next_mover + self.churn) % self.n
        new = np.array([self.free.popleft() for _ in movers], dtype=self.cell.dtype)
        self.free.extend(self.cell[movers].tolist())
        self.cell[movers] = new
        self.x0[movers], self.y0[movers] = self._place(new)

    def frame(self, seq: int, stamp_ns: int) -> bytes:
        if self.churn and seq > 0:
            self._move_churned()
        t = seq * self.dt
        d = self.amp * np.sin(self.omega * t)
        x = self.x0 + d * np.cos(self.heading) + self.rng.normal(0, 1, self.n) * self.sig
        y = self.y0 + d * np.sin(self.heading) + self.rng.normal(0, 1, self.n) * self.sig
        seen = self.rng.random(self.n) > 0.05
        objs = []
        for i in np.flatnonzero(seen).tolist():
            o = self.objs[i]
            p = o["kinematics"]["pose_with_covariance"]["pose"]["position"]
            p["x"], p["y"] = float(x[i]), float(y[i])
            objs.append(o)
        msg = dict(self.template)
        msg["header"] = {"stamp": stamp_ns, "frame_id": "lidar", "seq": seq}
        msg["objects"] = objs
        return msgpack.packb(msg, use_bin_type=True)


def vm_rss_kb(pid: int) -> int | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        return None
    return None


def _pct(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    s = sorted(values)
    return s[min(len(s) - 1, max(0, int(math.ceil(q / 100 * len(s))) - 1))]


def stop_processes(procs: Iterable[subprocess.Popen], timeout_s: float = 15.0) -> None:
    """SIGTERM every process still running, then wait for each (killing one that does not stop in time)."""
    procs = list(procs)
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    for p in procs:
        try:
            p.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            p.kill()


def bench_pipeline(objects: int = 200, rate_hz: float = 20.0, duration_s: float = 60.0, seed: int = 0,
                   log_dir: Path | None = None, startup_timeout_s: float = 60.0,
                   split: bool = False, churn: int = 0, classifier_config: str | None = None,
                   tracker_config: str | None = None) -> dict[str, Any]:
    """Run the pipeline bench; ``split`` also subscribes ``tracked`` to report ``to_tracked_ms`` (the tracker's
    leg). Off by default: that extra subscriber makes the tracker send each 330 kB ``tracked`` twice and costs
    this process CPU while the classifier works, so it adds to what it measures. ``classifier_config`` and
    ``tracker_config`` are parameter files handed to those services' ``--config`` (their defaults otherwise)."""
    ns = f"bench{os.getpid()}"
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    log_dir = Path(log_dir or tempfile.mkdtemp(prefix="jg-bench-pipeline-"))
    log_dir.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    procs: dict[str, subprocess.Popen] = {}
    common = ("--ns", ns, "--connect", endpoint)
    def config_flag(path: str | None) -> tuple[str, ...]:
        return ("--config", str(Path(path).resolve())) if path else ()

    specs = {"router": ("router", "--listen", endpoint),
             "classifier": ("classifier", *common, *config_flag(classifier_config)),
             "tracker": ("tracker", *common, *config_flag(tracker_config))}
    gen = SceneGenerator(objects, rate_hz, seed, churn=churn)
    born: dict[str, int] = {}  # the tracker's latest tracks_born counter, from its heartbeat
    health: dict[str, str] = {}  # each service's latest health from its heartbeat ("ok", or why not)
    sent: dict[int, float] = {}
    recv: dict[int, float] = {}
    tracked_at: dict[int, float] = {}  # where the time goes: detections put -> tracked seen -> objects seen
    lock = threading.Condition()  # guards the stamps; notified when one arrives

    def stamp_into(into: dict[int, float]) -> Any:
        def on_sample(sample: Any) -> None:
            t = time.perf_counter()
            head = peek_header(sample.payload.to_bytes())
            if head is not None:
                with lock:
                    into.setdefault(head[0], t)
                    lock.notify_all()
        return on_sample

    # The children run in sessions of their own (a Ctrl-C on the terminal must not stop them mid-measurement), so a
    # SIGTERM to this process reaches none of them: it had ended this process at once, and left the router, the
    # tracker and the classifier running for ever. Raised as SystemExit here, it runs the ``finally`` below.
    def on_term(signum: int, _frame: Any) -> None:
        raise SystemExit(128 + signum)

    in_main = threading.current_thread() is threading.main_thread()
    old_term = signal.signal(signal.SIGTERM, on_term) if in_main else None
    try:
        for name, args in specs.items():
            out = open(log_dir / f"{name}.log", "wb")
            procs[name] = subprocess.Popen([sys.executable, "-m", "jitterguard.cli", *args], stdout=out,
                                           stderr=subprocess.STDOUT, env=env, start_new_session=True)
            out.close()
            if name == "router":
                time.sleep(0.5)
        cfg = build_config(ZenohOptions(ns=ns, connect=(endpoint,)))
        with open_session(cfg, timeout_s=startup_timeout_s) as session:
            sub = session.declare_subscriber(keys.objects(ns), stamp_into(recv))
            sub_tracked = session.declare_subscriber(keys.tracked(ns), stamp_into(tracked_at)) if split else None

            def on_beat(sample: Any) -> None:
                try:
                    hb = decode(Heartbeat, sample.payload.to_bytes(), **HEARTBEAT_BOUNDS)
                except DecodeError:
                    return
                name = keys.last_chunk(str(sample.key_expr))
                health[name] = "ok" if hb.health == "ok" else f"{hb.health}: {hb.health_reason}"
                if name == "tracker":
                    born["now"] = hb.counters.get("tracks_born", 0)

            sub_beat = session.declare_subscriber(keys.heartbeat_all(ns), on_beat)
            pub = session.declare_publisher(keys.detections(ns), congestion_control=zenoh.CongestionControl.BLOCK)
            deadline = time.monotonic() + startup_timeout_s
            # up: on the bus and saying so in a heartbeat (health ok, as the replay waits for its consumer). A token
            # alone is not: the classifier declares its own before it loads its compiled loops, which after a change
            # of their source compile for seconds (26 s on a loaded 2-core machine) while it subscribes to nothing —
            # a short run had sent every frame into that and reported 400 in, 0 out, saying nothing of why
            while True:
                alive = {keys.last_chunk(str(r.ok.key_expr)) for r in session.liveliness().get(keys.alive_all(ns))
                         if r.ok is not None}
                waiting = {n: health.get(n, "no heartbeat yet") for n in ("tracker", "classifier")
                           if n not in alive or health.get(n) != "ok"}
                if not waiting:
                    break
                dead = [n for n, p in procs.items() if p.poll() is not None]
                if dead or time.monotonic() > deadline:
                    why = dead or "timeout: " + ", ".join(f"{n} {h}" for n, h in waiting.items())
                    raise RuntimeError(f"pipeline did not come up ({why}); logs in {log_dir}")
                time.sleep(0.2)
            time.sleep(1.0)  # let the children's subscriptions reach the router
            n_frames = int(round(duration_s * rate_hz))
            rss_at = min(60.0, 0.2 * duration_s)
            rss_first: dict[str, int | None] = {}
            timeline_every = max(10.0, duration_s / 30)  # about 30 points however long the run
            timeline: list[dict[str, Any]] = []
            born_first: tuple[int | None, int] = (None, 0)
            t0 = time.perf_counter()
            stamp0 = time.time_ns()
            data = gen.frame(0, stamp0)
            gc.collect()
            gc.disable()  # collected between frames below: the load generator must not pause mid-frame
            try:
                for k in range(n_frames):
                    target = t0 + k / rate_hz
                    if target - t0 >= len(timeline) * timeline_every:
                        timeline.append({"t_s": round(target - t0), **{n: vm_rss_kb(p.pid) for n, p in procs.items()}})
                    if not rss_first and target - t0 >= rss_at:
                        rss_first = {n: vm_rss_kb(p.pid) for n, p in procs.items()}
                        born_first = (born.get("now"), k)
                    now = time.perf_counter()
                    if target > now:
                        time.sleep(target - now)
                    with lock:
                        sent[k] = time.perf_counter()
                    pub.put(data)
                    # Build the next frame once this one is through (or half a period on), not while the
                    # pipeline works on it: the load generator must not take the CPU from what it measures.
                    settle = target + 0.5 / rate_hz
                    with lock:
                        lock.wait_for(lambda: k in recv, timeout=max(0.0, settle - time.perf_counter()))
                    data = gen.frame(k + 1, stamp0 + int((k + 1) * 1e9 / rate_hz))
                    gc.collect(1)
            finally:
                gc.enable()
            wall = time.perf_counter() - t0
            drain = time.monotonic() + 5.0
            while time.monotonic() < drain:
                with lock:
                    if len(recv) >= len(sent):
                        break
                time.sleep(0.05)
            rss_end = {n: vm_rss_kb(p.pid) for n, p in procs.items()}
            time.sleep(1.2)  # one more tracker heartbeat, with every frame counted
            born_end = (born.get("now"), len(sent))
            sub.undeclare()
            sub_beat.undeclare()
            if sub_tracked is not None:
                sub_tracked.undeclare()
            pub.undeclare()
    finally:
        stop_processes(procs.values())
        if in_main:
            signal.signal(signal.SIGTERM, old_term)
    with lock:
        lat = [(recv[s] - sent[s]) * 1e3 for s in sent if s in recv]
        to_tracked = [(tracked_at[s] - sent[s]) * 1e3 for s in sent if s in tracked_at]
        late_or_lost = len(sent) - len(lat)
    growth: dict[str, float | None] = {}
    for n in procs:
        first, end = rss_first.get(n), rss_end.get(n)
        growth[n] = round(100.0 * (end - first) / first, 2) if first and end else None
    births = None
    if born_first[0] is not None and born_end[0] is not None and born_end[1] > born_first[1]:
        births = round((born_end[0] - born_first[0]) / (born_end[1] - born_first[1]), 2)
    return {
        "objects": objects, "rate_hz": rate_hz, "churn": churn, "duration_s": round(wall, 2),
        "tracks_born_per_frame": births,
        "frames_in": len(sent), "frames_out": len(lat), "frames_missing": late_or_lost,
        "p50_ms": round(statistics.median(lat), 2) if lat else None,
        "p90_ms": round(_pct(lat, 90), 2) if lat else None,
        "p99_ms": round(_pct(lat, 99), 2) if lat else None,
        "max_ms": round(max(lat), 2) if lat else None,
        "to_tracked_ms": {"p50": round(statistics.median(to_tracked), 2), "p99": round(_pct(to_tracked, 99), 2)}
        if to_tracked else None,
        "rss_sampled_after_s": round(min(60.0, 0.2 * duration_s), 1),
        "rss_kb": {n: {"first": rss_first.get(n), "end": rss_end.get(n)} for n in procs},
        "rss_growth_pct": growth,
        "rss_timeline_kb": timeline,
        "logs": str(log_dir),
    }


