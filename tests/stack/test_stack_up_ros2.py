"""``jitterguard up --ros2 TOPIC``: the stack with a vehicle's ROS 2 side in the replay's place (real supervisord, real
router and services; the ROS 2 side played as zenoh-bridge-ros2dds shows it, its CDR by mcap-ros2-support): scans in
with /tf and /tf_static, Autoware's TrackedObjects out on their topic's key; replay flags with --ros2 are refused."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from jitterguard.runtime import ZenohOptions, build_config, free_tcp_port, open_session
from jitterguard.stack.control import Supervisor

pytestmark = pytest.mark.integration

POINTS = "/sensing/lidar/top/pointcloud"
TRACKING_KEY = "perception/object_recognition/tracking/objects"


def jg(*args: str, timeout: float = 180) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("JG_API_TOKEN", "ROS_DOMAIN_ID")} | {"ROS_DISTRO": "jazzy"}
    return subprocess.run([sys.executable, "-m", "jitterguard.cli", *args], capture_output=True, text=True,
                          timeout=timeout, env=env)


@pytest.mark.parametrize("middleware", ["bridge", "rmw_zenoh"])
def test_up_with_ros2_runs_the_vehicles_scans_through_to_autowares_tracked_objects(tmp_path, middleware):
    """The bridge as a client of jitterguard's router; or ROS 2 nodes on rmw_zenoh behind their own router (a second
    router here plays rmw_zenohd; ``--ros2-connect``), typed keys and attachments both ways."""
    pytest.importorskip("mcap_ros2._dynamic")
    from jitterguard.eval.detector_input import synthetic_scans
    from jitterguard.sim.world import make_scenario
    from ros2_side import RosSide, codec, rmw_key

    rd, router, ns = tmp_path / "run", free_tcp_port(), f"upros{os.getpid()}"
    rmw = middleware == "rmw_zenoh"
    procs, extra = [], []
    if rmw:
        ros_endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
        procs.append(subprocess.Popen([sys.executable, "-m", "jitterguard.cli", "router", "--listen", ros_endpoint],
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        extra = ["--ros2-middleware", "rmw_zenoh", "--ros2-connect", ros_endpoint]
    res = jg("up", "-d", "--ros2", POINTS, "--ns", ns, "--router-port", str(router), "--port", str(free_tcp_port()),
             "--run-dir", str(rd), *extra)
    assert res.returncode == 0, res.stdout + res.stderr
    session = None
    try:
        names = {p.name: p.state for p in Supervisor(rd).processes()}
        assert "replay" not in names and names.get("ros2-in") == "RUNNING" and names.get("ros2-out") == "RUNNING", names
        session = open_session(build_config(ZenohOptions(ns=ns, connect=(ros_endpoint if rmw
                                                                          else f"tcp/127.0.0.1:{router}",))))
        decode_tracked = codec("autoware_perception_msgs/msg/TrackedObjects", encode=False)
        got: list = []
        tracking = rmw_key(TRACKING_KEY, "autoware_perception_msgs/msg/TrackedObjects") if rmw else TRACKING_KEY
        session.declare_subscriber(tracking, lambda s: got.append(decode_tracked(s.payload.to_bytes())))
        ros = RosSide(session, POINTS, rmw=rmw)
        scans = list(synthetic_scans(make_scenario("parking-street", 1, 4.0, 10.0), 1))
        deadline = time.monotonic() + 120
        k = 0
        while not any(m.objects for m in got) and time.monotonic() < deadline:  # until the classifier has warmed up
            for ls in scans:
                ros.send(ls.scan, ls.scan.header.stamp + k * 5_000_000_000)
                time.sleep(0.1)
            k += 1
        assert any(m.objects for m in got), (rd / "logs" / "ros2-in.log").read_text()[-1500:]
        assert all(m.header.frame_id == "map" for m in got)
        st = jg("status", "--run-dir", str(rd), "--json")
        assert st.returncode == 0, st.stdout + st.stderr
    finally:
        if session is not None:
            session.close()
        jg("down", "--run-dir", str(rd))
        for p in procs:
            p.terminate()
            p.wait(timeout=30)


def test_up_with_ros2_tracks_the_vehicles_own_detected_objects_to_autowares_tracked_objects(tmp_path):
    """``--ros2 TOPIC --input detections`` under a real supervisord: three parked cars as the vehicle's own detector
    reports them (DetectedObjects in base_link, no covariance, a few centimetres of jitter) and a standing vehicle's
    /tf go in through the bridge's keys; tracked and classified without jitterguard's detector, they come back as
    Autoware's TrackedObjects, stationary."""
    pytest.importorskip("mcap_ros2._dynamic")
    import math

    import numpy as np

    from ros2_side import codec, stamp, transform
    from jitterguard.schemas.models import Pose

    objects_topic = "/perception/object_recognition/detection/objects"
    rd, router, ns = tmp_path / "run", free_tcp_port(), f"upobj{os.getpid()}"
    res = jg("up", "-d", "--ros2", objects_topic, "--input", "detections", "--ns", ns, "--router-port", str(router),
             "--port", str(free_tcp_port()), "--run-dir", str(rd))
    assert res.returncode == 0, res.stdout + res.stderr
    session = None
    try:
        names = {p.name: p.state for p in Supervisor(rd).processes()}
        assert "detector" not in names and names.get("tracker") == "RUNNING" and names.get("ros2-in") == "RUNNING", names
        session = open_session(build_config(ZenohOptions(ns=ns, connect=(f"tcp/127.0.0.1:{router}",))))
        decode_tracked = codec("autoware_perception_msgs/msg/TrackedObjects", encode=False)
        got: list = []
        session.declare_subscriber(TRACKING_KEY, lambda s: got.append(decode_tracked(s.payload.to_bytes())))
        encode_objects, encode_tf = (codec("autoware_perception_msgs/msg/DetectedObjects", encode=True),
                                     codec("tf2_msgs/msg/TFMessage", encode=True))
        rng = np.random.default_rng(7)
        zero = {"x": 0.0, "y": 0.0, "z": 0.0}

        def car(x: float, y: float) -> dict:
            pose = {"position": {"x": x + rng.normal(0, 0.05), "y": y + rng.normal(0, 0.05), "z": 0.8},
                    "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}
            return {"existence_probability": 0.8, "classification": [{"label": 1, "probability": 0.9}],
                    "kinematics": {"pose_with_covariance": {"pose": pose, "covariance": [0.0] * 36},
                                   "has_position_covariance": False, "orientation_availability": 1,
                                   "twist_with_covariance": {"twist": {"linear": zero, "angular": zero},
                                                             "covariance": [0.0] * 36},
                                   "has_twist": False, "has_twist_covariance": False},
                    "shape": {"type": 0, "footprint": {"points": []}, "dimensions": {"x": 4.5, "y": 1.9, "z": 1.6}}}
        t0, k = 1_700_000_000_000_000_000, 0

        def settled() -> bool:  # all three tracked and called stationary (undecided while their windows are young)
            return bool(got) and len(got[-1].objects) == 3 and all(o.kinematics.is_stationary for o in got[-1].objects)
        deadline, after = time.monotonic() + 120, None
        while time.monotonic() < deadline and (after is None or k < after):
            t = t0 + k * 100_000_000
            session.put("tf", bytes(encode_tf({"transforms": [transform("map", "base_link", t, Pose())]})))
            session.put(objects_topic.lstrip("/"), bytes(encode_objects({
                "header": {"stamp": stamp(t), "frame_id": "base_link"},
                "objects": [car(8.0, 4.0), car(15.0, 4.2), car(-6.0, -4.0)]})))
            k += 1
            time.sleep(0.1)
            if after is None and settled():
                after, first = k + 20, len(got)  # 2 s more: they stay stationary
        assert after is not None, (rd / "logs" / "ros2-in.log").read_text()[-1500:]
        assert all(len(m.objects) == 3 and all(o.kinematics.is_stationary for o in m.objects) for m in got[first:])
        last = got[-1]
        xs = sorted(o.kinematics.pose_with_covariance.pose.position.x for o in last.objects)
        assert xs == pytest.approx([-6.0, 8.0, 15.0], abs=0.3) and math.isfinite(sum(xs))
    finally:
        if session is not None:
            session.close()
        jg("down", "--run-dir", str(rd))


@pytest.mark.parametrize("args, message", [
    (["synthetic:mixed"], "SOURCE is the replay's"),
    (["--rate", "2"], "--rate is the replay's; not with --ros2"),
    (["--input", "tracks"], "--input tracks: --ros2 brings scans"),
])
def test_replay_flags_with_ros2_are_one_line_errors(tmp_path, args, message):
    res = jg("up", "--ros2", POINTS, "--run-dir", str(tmp_path / "run"), *args, timeout=60)
    assert res.returncode == 2 and message in res.stderr and res.stderr.count("\n") == 1, res.stderr


def test_up_with_ros2_and_input_detections_tracks_the_vehicles_own_detected_objects():
    """``--ros2 TOPIC --input detections``: the topic is the vehicle's DetectedObjects; ros2-in reads it with
    ``--objects-topic`` and the stack runs its tracker without a detector."""
    from jitterguard.stack.supervisor import StackSpec, programs

    objects = "/perception/object_recognition/detection/objects"
    progs = {p.name: p.args for p in programs(StackSpec(input="detections", ros2_points=objects))}
    assert "detector" not in progs and "tracker" in progs and "replay" not in progs
    assert progs["ros2-in"][-2:] == ("--objects-topic", objects) and "--points-topic" not in progs["ros2-in"]
    scans = {p.name: p.args for p in programs(StackSpec(input="points", ros2_points=POINTS))}
    assert scans["ros2-in"][-2:] == ("--points-topic", POINTS)


def test_up_passes_the_ros2_middleware_to_both_ros2_programs(tmp_path, monkeypatch):
    """``--ros2-middleware rmw_zenoh --ros2-connect`` reach ros2-in and ros2-out alike, with the domain ID of
    ``$ROS_DOMAIN_ID`` and the distribution of ``$ROS_DISTRO`` written into their command lines (what supervisord
    starts)."""
    from jitterguard.stack.cli import _ros2_args
    from jitterguard.stack.supervisor import StackSpec, programs

    monkeypatch.setenv("ROS_DOMAIN_ID", "12")
    monkeypatch.setenv("ROS_DISTRO", "humble")
    args = _ros2_args("rmw_zenoh", "tcp/127.0.0.1:7447", "default")
    assert args == ("--middleware", "rmw_zenoh", "--domain-id", "12", "--ros-distro", "humble",
                    "--ros-connect", "tcp/127.0.0.1:7447")
    assert _ros2_args("bridge", None, "default") == ()
    progs = {p.name: p.args for p in programs(StackSpec(input="points", ros2_points=POINTS, ros2_args=args))}
    for name in ("ros2-in", "ros2-out"):
        tail = progs[name][progs[name].index("--middleware"):]
        assert tail[:8] == args, progs[name]


@pytest.mark.parametrize("args, message", [
    (["--ros2", POINTS, "--ros2-middleware", "dds"], "--ros2-middleware: 'dds' is not one of"),
    (["--ros2", POINTS, "--ros2-connect", "7447"], "endpoint '7447' must look like tcp/HOST:PORT"),
    (["--ros2-middleware", "rmw_zenoh"], "--ros2-middleware is for live ROS 2: give --ros2 TOPIC"),
    (["--ros2-connect", "tcp/127.0.0.1:7447"], "--ros2-connect is for live ROS 2: give --ros2 TOPIC"),
])
def test_ros2_middleware_flags_are_checked_in_one_line(tmp_path, args, message):
    res = jg("up", "--run-dir", str(tmp_path / "run"), *args, timeout=60)
    assert res.returncode == 2 and message in res.stderr and res.stderr.count("\n") == 1, res.stderr


@pytest.mark.parametrize("variable, value, message", [
    ("ROS_DOMAIN_ID", "300", "ROS_DOMAIN_ID: 300 is outside 0-232"),
    ("ROS_DISTRO", "Jazzy 2", "ROS_DISTRO: 'Jazzy 2' is not a ROS 2 distribution's name"),
])
def test_a_bad_ros_environment_is_named_as_up_reads_it(tmp_path, variable, value, message):
    env = {k: v for k, v in os.environ.items() if k != "JG_API_TOKEN"} | {variable: value}
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "up", "--run-dir", str(tmp_path / "run"), "--ros2",
                          POINTS, "--ros2-middleware", "rmw_zenoh"],
                         capture_output=True, text=True, timeout=60, env=env)
    assert res.returncode == 2 and message in res.stderr and res.stderr.count("\n") == 1, res.stderr
