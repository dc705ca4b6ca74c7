"""Integration: the replay publisher on real Zenoh sessions (peer mode, loopback, multicast off, free ports),
in-process and through the ``jitterguard replay`` command in a subprocess."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

from jitterguard.runtime import build_config, free_tcp_port, loopback_options
from jitterguard.schemas import DetectedObjects, PointCloud, decode, encode, keys
from jitterguard.schemas.models import DetectedObject, Heartbeat, ObjectClassification
from jitterguard.services.replay.frames import DetectionFrame, EgoPose
from jitterguard.services.replay.service import ReplayService
from jitterguard.services.replay.runner import ReplayPlan
from jitterguard.services.replay.sources.base import MemorySource

from .helpers import MS, memory, scan, write_bin

pytestmark = pytest.mark.integration
REPO = Path(__file__).resolve().parents[2]


class Collector:
    """A subscriber session listening on a free loopback port; keeps raw payloads per key."""

    def __init__(self, ns: str, *key_fns) -> None:
        self.port = free_tcp_port()
        self.session = zenoh.open(build_config(loopback_options(ns, self.port, listen_self=True)))
        self.lock = threading.Lock()
        self.payloads: dict[str, list[bytes]] = {}
        self.subs = [self.session.declare_subscriber(fn(ns), self._on) for fn in key_fns]

    def _on(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.payloads.setdefault(str(sample.key_expr), []).append(sample.payload.to_bytes())

    def wait_for(self, key: str, n: int, timeout: float = 20.0) -> list[bytes]:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self.lock:
                got = list(self.payloads.get(key, []))
            if len(got) >= n:
                return got
            time.sleep(0.02)
        return got

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()
        self.session.close()


@pytest.fixture
def ns(request: pytest.FixtureRequest) -> str:
    return f"t{os.getpid()}-{abs(hash(request.node.name)) % 10**8}"


def test_points_arrive_complete_in_order_with_pose_and_exact_data(ns: str) -> None:
    col = Collector(ns, keys.points)
    try:
        src = memory(12)
        with ReplayService(loopback_options(ns, col.port)) as svc:
            assert svc.wait_for_subscribers(10.0)
            stats = svc.replay(src, ReplayPlan(rate=None, loop=True, passes=2))
            assert svc.counters.get("published") == 24
        got = [decode(PointCloud, p) for p in col.wait_for(keys.points(ns), 24)]
    finally:
        col.close()
    assert stats.published == 24 and len(got) == 24
    assert [m.header.seq for m in got] == list(range(24))
    stamps = [m.header.stamp for m in got]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    for m in got[:12]:
        want = scan(m.header.seq)
        assert m.fields == ["x", "y", "z", "intensity"] and m.header.frame_id == want.frame_id
        pts = np.frombuffer(m.data, dtype="<f4").reshape(m.num_points, 4)
        np.testing.assert_array_equal(pts, want.points)
        assert m.ego_pose.position.x == pytest.approx(want.pose.x)
        assert m.ego_pose.orientation.z == pytest.approx(want.pose.qz)


def test_detection_frames_go_on_the_detections_key(ns: str) -> None:
    col = Collector(ns, keys.detections, keys.points)
    obj = DetectedObject(classification=[ObjectClassification(label=7, probability=0.8)])
    frames = [DetectionFrame(i * 100 * MS, EgoPose.from_yaw(i, 0, 0), [obj] * i, f"d#{i}", "base_link") for i in range(3)]
    try:
        with ReplayService(loopback_options(ns, col.port), kind="detections") as svc:
            assert svc.wait_for_subscribers(10.0)
            svc.replay(MemorySource(frames, kind="detections"), ReplayPlan(rate=None))
        got = [decode(DetectedObjects, p) for p in col.wait_for(keys.detections(ns), 3)]
        with col.lock:
            assert keys.points(ns) not in col.payloads
    finally:
        col.close()
    assert [len(m.objects) for m in got] == [0, 1, 2]
    assert got[2].objects[0].classification[0].label == 7 and got[2].header.frame_id == "base_link"
    assert got[1].ego_pose.position.x == pytest.approx(1.0)


def test_a_scan_cannot_go_on_the_detections_key(ns: str) -> None:
    with ReplayService(loopback_options(ns, free_tcp_port(), listen_self=True), kind="detections") as svc:
        with pytest.raises(TypeError, match="cannot go on"):
            svc.emit(scan(0), 0, 0)


def test_a_replay_whose_frames_keep_failing_to_read_says_so_in_its_health(ns: str) -> None:
    """Frames skipped one after another (a recording gone bad under a looping replay) had left the replay's health
    ``ok`` while nothing entered the pipeline: from the fifth in a row it is ``failing`` naming the last error, and
    the next frame that reads makes it ``ok`` again."""
    with ReplayService(loopback_options(ns, free_tcp_port(), listen_self=True)) as svc:
        assert svc.health().ok
        svc.replay(memory(8, errors=(1, 2, 3, 4, 5, 6, 7)), ReplayPlan(rate=None))
        health = svc.health()
        assert health.state == "failing" and "the last 7 frames failed to read" in health.reason
        assert "bad7.bin" in health.reason
        svc.replay(memory(8, errors=(0, 1, 2, 3)), ReplayPlan(rate=None))  # four in a row, then frames read
        assert svc.health().ok


# -------------------------------------------------------------------------------------- the command


def _cli(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "jitterguard.cli", *args], cwd=REPO, capture_output=True, text=True, timeout=timeout
    )


def test_cli_replays_a_kitti_folder_skipping_and_naming_the_corrupt_scan(ns: str, tmp_path: Path) -> None:
    for i in range(5):
        write_bin(tmp_path / f"{i:06d}.bin", np.full((100, 4), i, dtype=np.float32))
    (tmp_path / "000002.bin").write_bytes(b"\x00" * 7)
    col = Collector(ns, keys.points)
    try:
        proc = _cli("replay", str(tmp_path), "--rate", "max", "--ns", ns, "--connect", f"tcp/127.0.0.1:{col.port}",
                    "--no-progress", "--wait-subscriber", "20", "--log-level", "WARNING")
        got = [decode(PointCloud, p) for p in col.wait_for(keys.points(ns), 4)]
    finally:
        col.close()
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    bad_lines = [ln for ln in proc.stderr.splitlines() if "000002.bin" in ln]
    assert len(bad_lines) == 1 and "whole number" in bad_lines[0]
    assert "replayed 4 frame(s)" in proc.stderr and "1 unreadable" in proc.stderr
    assert [m.header.seq for m in got] == [0, 1, 2, 3]
    assert [int(np.frombuffer(m.data, "<f4")[0]) for m in got] == [0, 1, 3, 4]
    assert [m.header.stamp for m in got] == [0, 100 * MS, 300 * MS, 400 * MS]


def test_cli_on_error_stop_exits_65_naming_the_file(ns: str, tmp_path: Path) -> None:
    """A deliberate stop on bad input is status 65 (EX_DATAERR), not 1: supervisord (the stack's ``exitcodes``) and
    systemd (``RestartPreventExitStatus``) leave it stopped. Exit 1 had been restarted, the same bad frame read
    again, for ever."""
    from jitterguard.runtime.service import EXIT_BAD_INPUT

    write_bin(tmp_path / "000000.bin", np.zeros((3, 4)))
    (tmp_path / "000001.bin").write_bytes(b"\x01\x02")
    proc = _cli("replay", str(tmp_path), "--rate", "max", "--on-error", "stop", "--ns", ns,
                "--listen", f"tcp/127.0.0.1:{free_tcp_port()}", "--no-progress", "--wait-subscriber", "0")
    assert EXIT_BAD_INPUT == 65
    assert proc.returncode == EXIT_BAD_INPUT, proc.stderr
    assert "Traceback" not in proc.stderr
    assert any("stopped at unreadable frame" in ln and "000001.bin" in ln for ln in proc.stderr.splitlines())
    assert "skipped" not in proc.stderr  # the frame's own line had said "skipped" before the replay stopped on it


def test_a_stop_on_bad_input_under_supervisord_outlives_its_startsecs(ns: str, tmp_path: Path) -> None:
    """supervisord counts any exit before a program's ``startsecs`` as a failed start and starts it again (up to
    ``startretries``, then FATAL) whatever its status: a replay that stopped on its first bad frame within a second
    would be restarted after all. Under supervisord (``SUPERVISOR_ENABLED``) it exits only once it has run
    :data:`~jitterguard.services.replay.cli.SUPERVISED_STOP_AFTER_S`."""
    from jitterguard.services.replay.cli import SUPERVISED_STOP_AFTER_S

    (tmp_path / "000000.bin").write_bytes(b"\x01\x02")
    write_bin(tmp_path / "000001.bin", np.zeros((3, 4)))
    args = [sys.executable, "-m", "jitterguard.cli", "replay", str(tmp_path), "--rate", "max", "--on-error", "stop",
            "--ns", ns, "--listen", f"tcp/127.0.0.1:{free_tcp_port()}", "--no-progress", "--wait-subscriber", "0"]
    t0 = time.monotonic()
    proc = subprocess.run(args, cwd=REPO, capture_output=True, text=True, timeout=60,
                          env={**os.environ, "SUPERVISOR_ENABLED": "1"})
    took = time.monotonic() - t0
    assert proc.returncode == 65, proc.stderr
    assert took >= SUPERVISED_STOP_AFTER_S > 2, took  # the stack's replay has startsecs=2


def test_cli_sigint_stops_a_looping_replay_cleanly(ns: str, tmp_path: Path) -> None:
    write_bin(tmp_path / "000000.bin", np.zeros((3, 4)))
    col = Collector(ns, keys.points)
    proc = subprocess.Popen(
        [sys.executable, "-m", "jitterguard.cli", "replay", str(tmp_path), "--loop", "--rate", "1", "--ns", ns,
         "--connect", f"tcp/127.0.0.1:{col.port}", "--no-progress", "--wait-subscriber", "20"],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        got = col.wait_for(keys.points(ns), 2, timeout=30)  # it is looping: interrupt it mid-replay
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        col.close()
    assert len(got) >= 2
    assert proc.returncode == 0, err
    assert "interrupted" in err and "Traceback" not in err
    assert [decode(PointCloud, p).header.seq for p in got[:2]] == [0, 1]


def test_bench_counts_every_scan_at_rate_max_with_none_dropped() -> None:
    from jitterguard.bench.replay import bench_replay_repeated

    r = bench_replay_repeated(2, frames=40, points=2000)
    assert r["sent"] == 40 and r["received"] == 40
    assert r["dropped_all_runs"] == 0 and r["out_of_order_all_runs"] == 0 and r["decode_errors"] == 0
    assert r["points_per_scan"] == 2000
    assert len(r["scans_per_s_runs"]) == 2


@pytest.mark.skipif(
    __import__("importlib.util").util.find_spec("jitterguard.sim.detection_model") is None, reason="jitterguard.sim not there yet"
)
def test_cli_replays_synthetic_detections(ns: str) -> None:
    col = Collector(ns, keys.detections)
    try:
        proc = _cli("replay", "synthetic:parking-street", "--level", "detections", "--duration", "0.5", "--seed", "3",
                    "--rate", "max", "--ns", ns, "--connect", f"tcp/127.0.0.1:{col.port}", "--no-progress",
                    "--wait-subscriber", "20")
        got = [decode(DetectedObjects, p) for p in col.wait_for(keys.detections(ns), 5)]
    finally:
        col.close()
    assert proc.returncode == 0, proc.stderr
    assert [m.header.seq for m in got] == [0, 1, 2, 3, 4]
    assert all(len(m.objects) > 0 for m in got) and got[0].header.frame_id == "lidar"


@pytest.mark.skipif(
    __import__("importlib.util").util.find_spec("jitterguard.sim.lidar") is None, reason="jitterguard.sim.lidar not there yet"
)
def test_cli_replays_synthetic_scans_with_ego_pose(ns: str) -> None:
    col = Collector(ns, keys.points)
    try:
        proc = _cli("replay", "synthetic:intersection", "--duration", "0.3", "--seed", "1", "--rate", "max", "--ns", ns,
                    "--connect", f"tcp/127.0.0.1:{col.port}", "--no-progress", "--wait-subscriber", "20")
        got = [decode(PointCloud, p) for p in col.wait_for(keys.points(ns), 3)]
    finally:
        col.close()
    assert proc.returncode == 0, proc.stderr
    assert [m.header.seq for m in got] == [0, 1, 2]
    assert all(m.num_points > 1000 and m.fields == ["x", "y", "z", "intensity", "ring"] for m in got)
    assert all(m.ego_pose.position.z > 1.0 for m in got)  # the sensor pose, not the ground point under the car


def test_a_replay_at_rate_max_that_exits_at_once_loses_none_of_its_last_scans(ns: str, tmp_path: Path) -> None:
    """A process that closed its session and exited straight after its last put lost its last scans on their
    way through the router: `replay --rate max` of three real-size scans delivered one or two in 5 of 12 runs.
    Twelve runs of three 35k-point scans, through a router process as in the stack, must deliver all 36."""
    rng = np.random.default_rng(0)
    for i in range(3):
        write_bin(tmp_path / f"{i:06d}.bin", rng.normal(size=(35_000, 4)))
    port = free_tcp_port()
    got: list[int] = []
    router = subprocess.Popen([sys.executable, "-m", "jitterguard.cli", "router", "--listen", f"tcp/127.0.0.1:{port}"],
                              cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        sub_session = zenoh.open(build_config(loopback_options(ns, port)))
    except Exception:
        router.kill()
        raise
    try:
        sub = sub_session.declare_subscriber(keys.points(ns), lambda sample: got.append(1))
        for run in range(12):
            proc = _cli("replay", str(tmp_path), "--rate", "max", "--ns", ns, "--connect", f"tcp/127.0.0.1:{port}",
                        "--no-progress", "--wait-subscriber", "20", "--log-level", "WARNING")
            assert proc.returncode == 0, proc.stderr
            deadline = time.monotonic() + 5.0
            while len(got) < 3 * (run + 1) and time.monotonic() < deadline:
                time.sleep(0.02)
            assert len(got) == 3 * (run + 1), f"run {run}: {len(got)} of {3 * (run + 1)} scans arrived"
        sub.undeclare()
    finally:
        sub_session.close()
        router.terminate()
        router.wait(timeout=10)


def test_a_replay_told_to_wait_for_a_service_waits_for_its_ready_heartbeat_not_any_subscriber(ns: str) -> None:
    """A viewer that subscribes first does not start the replay: only the named service's heartbeat saying ok."""
    def beat(health: str) -> bytes:
        return encode(Heartbeat(service="detector", pid=1, stamp=time.time_ns(), last_seq=-1, health=health,
                                health_reason="" if health == "ok" else "starting: loading weights"))

    col = Collector(ns, keys.points)  # the viewer: a subscriber, but not the detector
    try:
        with ReplayService(loopback_options(ns, col.port)) as svc:
            assert svc.wait_for_subscribers(10.0)
            assert not svc.wait_for_service("detector", 0.5)  # no heartbeat at all
            col.session.put(keys.heartbeat(ns, "detector"), beat("stalled"))
            assert not svc.wait_for_service("detector", 0.5)  # up, but not ready
            threading.Timer(0.3, lambda: col.session.put(keys.heartbeat(ns, "detector"), beat("ok"))).start()
            t0 = time.monotonic()
            assert svc.wait_for_service("detector", 10.0)
            assert 0.2 <= time.monotonic() - t0 < 5.0
    finally:
        col.close()


def test_a_stop_during_the_waits_is_not_reported_as_their_timeout(ns: str, caplog: pytest.LogCaptureFixture) -> None:
    """Stopped (Ctrl-C, SIGTERM) while it waited for the detector and a subscriber, the replay had logged "detector
    not ready after 30.0 s; replaying anyway" and "no subscriber … after 30.0 s" of waits that lasted a moment."""
    import logging

    from jitterguard.services.replay.cli import _run

    with ReplayService(loopback_options(ns, free_tcp_port(), listen_self=True)) as svc:
        timer = threading.Timer(0.3, svc.stop)
        timer.start()
        with caplog.at_level(logging.INFO, logger="jitterguard.replay"):
            code = _run(svc, memory(3), ReplayPlan(rate=None), 30.0, False, "detector")
        timer.join()
    assert code == 0
    said = " ".join(r.getMessage() for r in caplog.records)
    assert "not ready after" not in said and "no subscriber" not in said, said
