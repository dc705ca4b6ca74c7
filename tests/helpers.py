"""Small helpers shared by tests (importable as ``helpers``: pytest puts tests/ on sys.path)."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

from jitterguard.bench.tracker_sequences import SimFrame
from jitterguard.geometry import quaternion_from_yaw
from jitterguard.schemas import decode
from jitterguard.schemas.models import (X_X, X_Y, Y_X, Y_Y, YAW_YAW, DetectedObject, DetectedObjectKinematics,
    DetectedObjects, Header, ObjectClassification, Point, Pose, PoseWithCovariance, Quaternion, Shape, Vector3)
from jitterguard.sim.lidar import LidarSpec, ScanResult, cast_frame, hdl32e
from jitterguard.sim.world import GroundTruthFrame
from jitterguard.stack.control import pid_alive


SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
"""``../shared/data`` beside the repository: the real recordings (tests that need them skip where it is absent)."""
NUSC = SHARED_DATA / "nuscenes-scene-0523"
"""The one labelled real scene (nuScenes, 2 Hz key frames)."""

def stop_process(proc: subprocess.Popen, timeout: float = 20.0) -> None:
    """End a process a test started: resumed first (a test may have stopped it: SIGTERM would wait for that),
    SIGTERM, and SIGKILL if it has not ended within ``timeout``."""
    if proc.poll() is not None:
        return
    os.kill(proc.pid, signal.SIGCONT)
    proc.terminate()
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def wait_until(pred: Callable[[], bool], timeout: float = 10.0, period: float = 0.02) -> bool:
    """Poll ``pred`` until it holds or ``timeout`` passes (no fixed sleeps in tests)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(period)
    return pred()


def freeze_until_replaced(tracker_pid: Callable[[], int | None], monitor_log: Path, timeout: float) -> None:
    """SIGSTOP the running tracker (``tracker_pid()``: its pid under the stack's supervisord, None while it has
    none); the stack's monitor must end it, saying why in ``monitor_log``, and supervisord start another. The
    process is resumed whatever happens, so a failed test leaves nothing stopped."""
    frozen = tracker_pid()
    assert frozen
    os.kill(frozen, signal.SIGSTOP)
    try:
        assert wait_until(lambda: tracker_pid() not in (None, frozen), timeout=timeout, period=0.5), \
            monitor_log.read_text()[-2000:]
    finally:
        if pid_alive(frozen):
            os.kill(frozen, signal.SIGCONT)
    log = monitor_log.read_text()
    assert re.search(rf"tracker \(pid {frozen}\) has sent no heartbeat for \d+ s .*frozen", log), log[-2000:]


def iter_scans(scenario: Iterable[GroundTruthFrame], sensor: LidarSpec | None = None, seed: int = 0
               ) -> Iterator[tuple[GroundTruthFrame, ScanResult]]:
    """Every frame of a scenario with its scan: (frame with point counts and ray-cast visibility, scan)."""
    spec = sensor or hdl32e()
    for frame in scenario:
        res, f = cast_frame(frame, spec, seed)
        yield f, res


def to_message(frame: SimFrame, *, with_covariance: bool = True) -> DetectedObjects:
    """The scan as the wire message a detector publishes (sensor frame, ego pose in the world)."""
    d = frame.detections
    objs = []
    for i in range(len(d)):
        cov = [0.0] * 36
        if with_covariance:
            cov[X_X] = float(d.cov_xx[i])
            cov[X_Y] = cov[Y_X] = float(d.cov_xy[i])
            cov[Y_Y] = float(d.cov_yy[i])
            cov[YAW_YAW] = float(d.var_yaw[i])
        qx, qy, qz, qw = quaternion_from_yaw(float(d.yaw[i]))
        objs.append(DetectedObject(
            existence_probability=float(d.existence[i]),
            classification=[ObjectClassification(label=int(d.label[i]), probability=float(d.label_prob[i]))],
            kinematics=DetectedObjectKinematics(
                pose_with_covariance=PoseWithCovariance(
                    pose=Pose(position=Point(x=float(d.x[i]), y=float(d.y[i]), z=float(d.z[i])),
                              orientation=Quaternion(x=qx, y=qy, z=qz, w=qw)),
                    covariance=cov,
                ),
                has_position_covariance=with_covariance,
            ),
            shape=Shape(type=0, dimensions=Vector3(x=float(d.length[i]), y=float(d.width[i]), z=float(d.height[i]))),
        ))
    qx, qy, qz, qw = quaternion_from_yaw(d.ego_yaw)
    return DetectedObjects(
        header=Header(stamp=d.stamp_ns, frame_id="lidar", seq=d.seq),
        ego_pose=Pose(position=Point(x=d.ego_x, y=d.ego_y, z=0.0), orientation=Quaternion(x=qx, y=qy, z=qz, w=qw)),
        objects=objs,
    )


def collector(store: dict, lock, kind: str, model):
    """A Zenoh subscriber callback that decodes each sample as ``model`` (the wire's own validation) into
    ``store[kind]`` under ``lock``: the tests' independent observer of what a service published."""
    def cb(sample) -> None:
        msg = decode(model, sample.payload.to_bytes())
        with lock:
            store[kind].append(msg)

    return cb

