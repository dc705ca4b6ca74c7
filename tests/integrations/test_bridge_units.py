"""Pure parts of the bridges: the frame joiner, the Foxglove scene builders, the ground split of the sensor pose,
and the Autoware twist convention. No network, no files."""

from __future__ import annotations

import math

import numpy as np
import pytest

from jitterguard.ros2.autoware import twist_from_object_frame, twist_to_object_frame, uuid_bytes
from jitterguard.schemas.models import (
    DetectedObjects,
    GroundTruthObjects,
    Header,
    MotionState,
    PointCloud,
    Pose,
    Shape,
    TrackedObjects,
    Vector3,
)
from jitterguard.services.bridge.frames import ground_split
from jitterguard.services.bridge.joiner import MAX_MOTION_PER_FRAME, FrameJoiner, JoinedFrame
from jitterguard.services.bridge.paths import next_free_path

A, B, C = "a" * 32, "b" * 32, "c" * 32


def hdr(seq: int, frame_id: str = "map") -> Header:
    return Header(stamp=1_000 + seq, seq=seq, frame_id=frame_id)


def objects(seq: int, ids=(A, B), stationary=()) -> TrackedObjects:
    return TrackedObjects.model_validate({"header": hdr(seq).model_dump(), "objects": [
        {"object_id": i, "kinematics": {"is_stationary": i in stationary,
                                        "twist_with_covariance": {"twist": {"linear": {"x": 0.0 if i in stationary else 2.0}}}},
         "shape": {"dimensions": {"x": 4.0, "y": 1.8, "z": 1.5}}} for i in ids]})


def tracked(seq: int, observed=(A, B)) -> TrackedObjects:
    return TrackedObjects(header=hdr(seq), observed_track_ids=list(observed))


def motion(seq: int, tid: str, state: str = "static", z: float = 0.5) -> MotionState:
    return MotionState(header=hdr(seq), track_id=tid, state=state, mode="z_test", z_x=z, z_y=z / 2, threshold=1.96,
                       alpha=1.96, window_length=5)


# ------------------------------------------------------------------------------------------------ joiner


def test_a_frame_goes_out_once_all_its_motion_arrived_with_everything_of_its_seq() -> None:
    j = FrameJoiner(motion_wait_s=1.0)
    j.add_points(PointCloud(header=hdr(3, "lidar"), num_points=0, data=b""))
    j.add_detections(DetectedObjects(header=hdr(3, "lidar")))
    j.add_groundtruth(GroundTruthObjects(header=hdr(3)))
    j.add_tracked(tracked(3))
    j.add_objects(objects(3), now=0.0)  # the classifier puts objects before the frame's motion messages
    j.add_motion(motion(3, A))
    assert j.poll(now=0.1) == []  # B's decision has not arrived yet
    j.add_motion(motion(3, B, "dynamic"))
    (f,) = j.poll(now=0.1)
    assert f.seq == 3 and f.points is not None and f.detections is not None and f.groundtruth is not None
    assert set(f.motion) == {A, B} and f.sensor_frame == "lidar"
    assert j.counters.get("motion_missing", 0) == 0


def test_another_publishers_message_of_the_same_seq_is_not_joined_into_the_frame() -> None:
    """A second publisher on the namespace (a test replay, a stray tool) puts a scan of the same seq under its own
    stamp: it had been joined into the frame (a 2-point cloud in another sensor frame in a Foxglove recording), or
    had replaced the frame's own scan when it came second. Seq and stamp together name a frame."""
    j = FrameJoiner(motion_wait_s=1.0)
    stray = PointCloud(header=Header(stamp=77, seq=3, frame_id="velodyne"), num_points=0, data=b"")
    j.add_points(PointCloud(header=hdr(3, "lidar"), num_points=0, data=b""))
    j.add_points(stray)  # after the frame's own scan
    j.add_tracked(tracked(3, observed=()))
    j.add_objects(objects(3), now=0.0)
    (f3,) = j.poll(now=1.0)
    assert f3.points is not None and f3.points.header.frame_id == "lidar"
    assert j.counters["stamp_mismatch"] == 1
    j.add_points(stray.model_copy(update={"header": Header(stamp=77, seq=4, frame_id="velodyne")}))  # before it
    j.add_tracked(tracked(4, observed=()))
    j.add_objects(objects(4), now=2.0)
    assert j.poll(now=2.1) == []  # frame 3 had points: frame 4 waits for its own, not the stray's
    j.add_points(PointCloud(header=hdr(4, "lidar"), num_points=0, data=b""))
    (f4,) = j.poll(now=2.1)
    assert f4.points is not None and f4.points.header.frame_id == "lidar" and j.counters["stamp_mismatch"] == 2


def test_missing_motion_times_out_and_a_later_frame_overtakes_a_waiting_one() -> None:
    j = FrameJoiner(motion_wait_s=0.25)
    j.add_tracked(tracked(1))
    j.add_objects(objects(1), now=0.0)
    j.add_motion(motion(1, A))
    assert j.poll(now=0.2) == []
    (f1,) = j.poll(now=0.3)  # B's motion was shed: the frame goes with what it has
    assert set(f1.motion) == {A} and j.counters["motion_missing"] == 1
    j.add_tracked(tracked(2))
    j.add_objects(objects(2), now=1.0)
    j.add_objects(objects(3), now=1.05)
    out = j.poll(now=1.06)  # frame 3's objects: frame 2 will get no more motion
    assert [f.seq for f in out] == [2]
    assert [f.seq for f in j.poll(now=2.0)] == [3]


def test_a_frame_waits_for_the_inputs_the_previous_frame_had() -> None:
    """Nothing orders the detector's detections N before the classifier's objects N at a bridge: a frame whose
    detections are late waits for them (up to ``motion_wait_s``) when the frame before had detections."""
    j = FrameJoiner(motion_wait_s=0.25)
    for seq in (1, 2):
        if seq == 1:
            j.add_detections(DetectedObjects(header=hdr(seq, "lidar")))
        j.add_tracked(tracked(seq, observed=()))
    j.add_objects(objects(1), now=0.0)
    assert j.poll(now=0.0) == []  # the first frame has no frame before it: it waits for every input stream...
    (f1,) = j.poll(now=0.25)  # ...for motion_wait_s at most (this run has no points nor ground truth)
    assert f1.detections is not None
    j.add_objects(objects(2), now=1.0)
    assert j.poll(now=1.1) == []  # frame 1 had detections: frame 2 waits for its own
    j.add_detections(DetectedObjects(header=hdr(2, "lidar")))
    (f2,) = j.poll(now=1.1)
    assert f2.detections is not None and f2.detections.header.seq == 2
    j.add_tracked(tracked(3, observed=()))
    j.add_objects(objects(3), now=2.0)
    (f3,) = j.poll(now=2.3)  # the detector went away: the frame goes out without them after motion_wait_s
    assert f3.detections is None
    j.add_tracked(tracked(4, observed=()))
    j.add_objects(objects(4), now=3.0)
    assert [f.seq for f in j.poll(now=3.0)] == [4]  # and the next frame no longer waits for them


def test_the_first_frame_waits_for_late_detections_too() -> None:
    """The first frame of a run (and the first after an upstream restart) has no frame before it to say which inputs
    exist: it waits for all of them, so late detections still make it (a trial saw the first frame go out without
    them)."""
    for restart in (False, True):
        j = FrameJoiner(motion_wait_s=0.25)
        if restart:  # a run, then the replay starts over (seq 1 is more than RESTART_GAP back: no straggler)
            for seq in (100, 101):
                j.add_points(PointCloud(header=hdr(seq, "lidar"), num_points=0, data=b""))
                j.add_tracked(tracked(seq, observed=()))
                j.add_objects(objects(seq), now=0.0)
            assert [f.seq for f in j.poll(now=1.0)] == [100, 101]
        j.add_points(PointCloud(header=hdr(1, "lidar"), num_points=0, data=b""))
        j.add_tracked(tracked(1, observed=()))
        j.add_objects(objects(1), now=2.0)
        assert j.poll(now=2.0) == []
        j.add_detections(DetectedObjects(header=hdr(1, "lidar")))  # after the objects
        (f1,) = j.poll(now=2.25)  # no ground truth in this run: out once motion_wait_s is over
        assert f1.points is not None and f1.detections is not None


def test_made_up_motion_ids_cannot_grow_a_frames_buffer() -> None:
    """Anyone on the bus may put ``motion/{id}``: a frame keeps at most MAX_MOTION_PER_FRAME of them (a frame has at
    most that many objects), the rest counted; a real one already held is still replaced."""
    j = FrameJoiner(motion_wait_s=0.0)
    for i in range(MAX_MOTION_PER_FRAME + 500):
        j.add_motion(motion(5, f"{i:032x}"))
    j.add_motion(motion(5, f"{0:032x}", state="dynamic"))
    assert len(j._motion.items[(5, hdr(5).stamp)]) == MAX_MOTION_PER_FRAME and j.counters["motion_dropped"] == 500
    assert j._motion.items[(5, hdr(5).stamp)][f"{0:032x}"].state == "dynamic"


def test_a_track_without_a_decision_this_frame_keeps_its_latest_one() -> None:
    j = FrameJoiner(motion_wait_s=0.0)
    j.add_motion(motion(1, A, "dynamic", z=5.0))
    j.add_objects(objects(1), now=0.0)
    j.poll(now=0.0)
    j.add_objects(objects(2), now=1.0)  # A not observed in frame 2
    (f,) = j.poll(now=1.0)
    assert A not in f.motion and f.last_motion[A].state == "dynamic" and f.last_motion[A].header.seq == 1
    j.add_objects(objects(3, ids=(B,)), now=2.0)  # A is gone: forgotten
    j.poll(now=2.0)
    j.add_objects(objects(4, ids=(A,)), now=3.0)
    (f4,) = j.poll(now=3.0)
    assert f4.last_motion == {}


def test_stragglers_are_dropped_and_an_upstream_restart_starts_over() -> None:
    j = FrameJoiner(motion_wait_s=0.0, max_pending=4)
    for s in range(10, 13):
        j.add_objects(objects(s), now=0.0)
    assert [f.seq for f in j.poll(now=0.0)] == [10, 11, 12]
    j.add_motion(motion(11, A))  # a straggler of a frame already out
    assert j.counters["late_messages"] == 1
    j.add_objects(objects(0), now=1.0)  # the replay restarted at seq 0
    assert [f.seq for f in j.poll(now=1.0)] == [0] and j.counters["seq_restarts"] == 1


def test_a_second_publishers_old_seqs_do_not_start_the_joiner_over() -> None:
    """A test replay on the namespace puts scans at seq 0, 1, … while the stack is at seq 40: each had been taken
    for an upstream restart, clearing every frame in flight (their scans and detections lost) and counted
    ``seq_restarts``. Only the frames' anchor, ``objects``, says the upstream restarted; then the inputs of the
    restarted run that came first are still there for its frames."""
    j = FrameJoiner(motion_wait_s=1.0)
    for s in range(40, 43):
        j.add_detections(DetectedObjects(header=hdr(s, "lidar")))
        j.add_tracked(tracked(s, observed=()))
        j.add_objects(objects(s), now=0.0)
    assert [f.seq for f in j.poll(now=0.0)] == [40, 41, 42]
    j.add_detections(DetectedObjects(header=hdr(43, "lidar")))
    j.add_tracked(tracked(43, observed=()))
    for s in (0, 1):  # the stray publisher's
        j.add_points(PointCloud(header=Header(stamp=5 + s, seq=s, frame_id="velodyne"), num_points=0, data=b""))
    j.add_objects(objects(43), now=0.5)
    (f43,) = j.poll(now=0.5)
    assert f43.detections is not None and f43.points is None and "seq_restarts" not in j.counters
    # a real restart: the restarted run's detections and tracked of seq 0 arrive before its objects
    j.add_detections(DetectedObjects(header=Header(stamp=9_000, seq=0, frame_id="lidar")))
    j.add_tracked(TrackedObjects(header=Header(stamp=9_000, seq=0, frame_id="map"), observed_track_ids=[]))
    j.add_objects(objects(0).model_copy(update={"header": Header(stamp=9_000, seq=0, frame_id="map")}), now=1.0)
    (f0,) = j.poll(now=2.0)  # the first frame after a restart waits for every input stream, motion_wait_s at most
    assert j.counters["seq_restarts"] == 1 and f0.detections is not None and f0.detections.header.stamp == 9_000


def test_a_replay_that_starts_over_soon_is_followed_not_dropped() -> None:
    """A short ``--loop`` pass or an early supervisord restart sends seq 0 again a few frames in: under a new stamp
    (wall-clock loops) it is a restart at once; under its old stamp it is one once it lies more than RESTART_GAP
    frames back. Until 3 Dec anything within ``max_pending`` (32) frames was dropped as late, every frame of a
    20-frame loop's later passes with it."""
    from jitterguard.services.bridge.joiner import RESTART_GAP

    j = FrameJoiner(motion_wait_s=0.0)
    for s in range(5):
        j.add_objects(objects(s), now=0.0)
    assert [f.seq for f in j.poll(now=0.0)] == list(range(5))
    j.add_motion(motion(3, A))  # a straggler: the stamp frame 3 went out with
    assert j.counters["late_messages"] == 1 and "seq_restarts" not in j.counters
    again = objects(0).model_copy(update={"header": Header(stamp=9_000, seq=0, frame_id="map")})
    j.add_objects(again, now=1.0)  # seq 0 under a new stamp: the stream started over
    assert [(f.seq, f.stamp_ns) for f in j.poll(now=1.0)] == [(0, 9_000)] and j.counters["seq_restarts"] == 1
    k = FrameJoiner(motion_wait_s=0.0)
    for s in range(RESTART_GAP + 2):
        k.add_objects(objects(s), now=0.0)
    k.poll(now=0.0)
    k.add_objects(objects(0), now=1.0)  # a pass on recorded stamps: the same stamp, but too far back for a straggler
    assert [f.seq for f in k.poll(now=1.0)] == [0] and k.counters["seq_restarts"] == 1


def test_inputs_of_frames_that_never_close_are_bounded() -> None:
    j = FrameJoiner(max_pending=3)
    for s in range(10):
        j.add_points(PointCloud(header=hdr(s, "lidar"), num_points=0, data=b""))
    assert j.counters["dropped_pending"] == 7
    j.add_objects(objects(9), now=0.0)
    (f,) = j.poll(now=1.0)
    assert f.points is not None


def test_bad_joiner_settings_are_refused() -> None:
    with pytest.raises(ValueError):
        FrameJoiner(motion_wait_s=-1)
    with pytest.raises(ValueError):
        FrameJoiner(max_pending=0)


# ------------------------------------------------------------------------------------------------ frames


@pytest.mark.parametrize("yaw,roll,pitch,z", [(0.0, 0.0, 0.0, 1.8), (2.9, 0.02, -0.03, 1.73), (-1.2, -0.1, 0.05, 0.4)])
def test_ground_split_composes_back_to_the_sensor_pose(yaw, roll, pitch, z) -> None:
    from scipy.spatial.transform import Rotation

    r = Rotation.from_euler("ZYX", [yaw, pitch, roll])
    x, y, zq, w = r.as_quat()
    pose = Pose.model_validate({"position": {"x": 12.0, "y": -3.0, "z": z},
                                "orientation": {"x": x, "y": y, "z": zq, "w": w}})
    g = ground_split(pose)
    back = Rotation.from_euler("z", g.yaw) * Rotation.from_quat(g.rest)
    assert (back * r.inv()).magnitude() < 1e-12
    assert (g.x, g.y, g.z) == (12.0, -3.0, z)
    assert abs(Rotation.from_quat(g.rest).as_euler("ZYX")[0]) < 1e-12  # no yaw left below the ground frame


# ------------------------------------------------------------------------------------------------ Autoware


def test_autoware_twists_are_in_the_object_frame_and_round_trip() -> None:
    yaw = math.radians(30)
    lin = Vector3(x=math.cos(yaw) * 5.0, y=math.sin(yaw) * 5.0, z=0.1)  # 5 m/s along the heading, frame axes
    cov = np.zeros(36)
    cov[0], cov[7], cov[1], cov[6], cov[35] = 0.4, 0.1, 0.05, 0.05, 0.02
    (vx, vy, vz), ocov = twist_to_object_frame(lin, cov, yaw)
    assert (vx, vy, vz) == pytest.approx((5.0, 0.0, 0.1), abs=1e-12)  # Autoware: speed on linear.x
    o = np.asarray(ocov).reshape(6, 6)
    assert np.trace(o[:2, :2]) == pytest.approx(0.5) and o[5, 5] == 0.02 and np.allclose(o, o.T)
    back, bcov = twist_from_object_frame(Vector3(x=vx, y=vy, z=vz), ocov, yaw)
    assert (back["x"], back["y"]) == pytest.approx((lin.x, lin.y), abs=1e-12)
    assert bcov == pytest.approx(list(cov), abs=1e-12)
    zero, zcov = twist_to_object_frame(Vector3(), np.zeros(36), yaw)  # a static object stays exactly zero
    assert zero == (0.0, 0.0, 0.0) and not any(zcov)


def test_track_ids_become_the_uuid_bytes_they_spell() -> None:
    tid = "0123456789abcdef0011223344556677"
    assert bytes(uuid_bytes(tid)).hex() == tid and len(uuid_bytes(tid)) == 16


def test_next_free_path_never_overwrites(tmp_path) -> None:
    p = tmp_path / "run.mcap"
    assert next_free_path(p) == p
    p.write_text("x")
    (tmp_path / "run.1.mcap").write_text("x")
    assert next_free_path(p) == tmp_path / "run.2.mcap"


# ------------------------------------------------------------------------------------------------ scene

fm = pytest.importorskip("foxglove.messages")


def test_ellipses_are_the_sigma_contours_of_the_covariance() -> None:
    from jitterguard.services.foxglove.scene import ellipse_xy

    cov = np.array([[0.5, 0.2], [0.2, 0.1]])
    for sigma in (1.0, 2.0):
        pts = ellipse_xy(cov[0, 0], cov[0, 1], cov[1, 1], sigma)
        maha = np.einsum("ij,jk,ik->i", pts, np.linalg.inv(cov), pts)
        assert maha == pytest.approx(sigma**2, rel=1e-9)  # every point on the σ-contour


def test_tracks_scene_colours_by_state_and_gives_static_objects_no_arrow() -> None:
    from jitterguard.services.foxglove.scene import STATE_COLORS, frame_messages, motion_statistics

    f = JoinedFrame(seq=5, stamp_ns=1_005, objects=objects(5, ids=(A, B, C), stationary=(A,)),
                    motion={A: motion(5, A, "static", 0.4), B: motion(5, B, "dynamic", 6.0)})
    msgs = frame_messages(f)
    assert set(msgs) == {"/jitterguard/tracks", "/jitterguard/motion"}  # no pose, points or detections this frame
    upd = msgs["/jitterguard/tracks"]
    schema = upd.get_schema()
    from google.protobuf.json_format import MessageToDict

    from .decoding import protobuf_class

    decoded = MessageToDict(protobuf_class(schema.name, schema.data).FromString(upd.encode()))
    ents = {e["id"]: e for e in decoded["entities"]}
    assert len(ents) == 3
    assert "arrows" not in ents[A] and len(ents[B]["arrows"]) == 1 and len(ents[C]["arrows"]) == 1
    assert ents[A]["cubes"][0]["color"]["b"] == pytest.approx(STATE_COLORS["static"][2])
    assert ents[B]["cubes"][0]["color"]["r"] == pytest.approx(STATE_COLORS["dynamic"][0])
    assert "z=6.00" in ents[B]["texts"][0]["text"] and ents[C]["texts"][0]["text"].endswith("unknown")
    stats = motion_statistics(f)
    assert stats["counts"] == {"static": 1, "dynamic": 1, "undecided": 0, "unknown": 1}
    assert stats["max_z"] == 6.0 and [r["value"] for r in stats["z_by_track"]] == [0.4, 6.0]


def test_each_track_has_its_own_series_in_the_z_plot_even_with_counter_ids() -> None:
    """The evaluator's track IDs are counters zero-padded in front: labels from their first digits were all
    "car 000000", and the shipped layout's Plot drew one series for every car."""
    from jitterguard.services.foxglove.scene import motion_statistics

    ids = [f"{k:032x}" for k in (1, 2, 3)]
    j = FrameJoiner(motion_wait_s=0.0)
    for t in ids:
        j.add_motion(motion(1, t, "dynamic", z=3.0))
    j.add_objects(objects(1, ids=tuple(ids)), now=0.0)
    (f,) = j.poll(now=0.0)
    labels = [r["label"] for r in motion_statistics(f)["z_by_track"]]
    assert len(labels) == 3 and len(set(labels)) == 3


def test_the_shipped_layout_is_the_generated_one_and_names_only_real_topics() -> None:
    import json
    import re
    from pathlib import Path

    from jitterguard.services.foxglove.layout import layout_json
    from jitterguard.services.foxglove.scene import MOTION_SCHEMA, TOPICS

    shipped = Path(__file__).resolve().parents[2] / "deploy" / "foxglove" / "jitterguard.json"
    assert shipped.read_text() == layout_json(), "regenerate: python -m jitterguard.services.foxglove.layout"
    doc = json.loads(layout_json())
    text = json.dumps(doc)
    panels = re.findall(r'"panelType": "(\w+)"', text)
    assert sorted(panels) == ["Plot", "Table", "ThreeDee"]
    for topic in set(re.findall(r'"(/jitterguard/[a-z_]+)', text)):
        assert topic in TOPICS, topic
    for field in re.findall(r'/jitterguard/motion\.(\w+)', text):
        assert field in MOTION_SCHEMA["properties"], field


@pytest.mark.integration
def test_a_bridge_counts_malformed_payloads_per_key_and_keeps_joining() -> None:
    """Garbage on any input key is rejected and counted per key (the runtime's rule); the next valid frame still
    reaches the sink, joined with its motion."""
    import zenoh

    from jitterguard.runtime import build_config, free_tcp_port, loopback_options
    from jitterguard.schemas import encode, keys
    from jitterguard.services.bridge.service import BridgeService

    from helpers import wait_until

    class ListSink:
        def __init__(self) -> None:
            self.frames: list[JoinedFrame] = []
            self.closed = False

        def write(self, frame: JoinedFrame) -> None:
            self.frames.append(frame)

        def close(self) -> None:
            self.closed = True

    ns, port = "bridge_bad", free_tcp_port()
    sink = ListSink()
    svc = BridgeService(loopback_options(ns, port, listen_self=True), sink, motion_wait_s=0.2)
    client = zenoh.open(build_config(loopback_options(ns, port)))
    try:
        pub = client.declare_publisher(keys.objects(ns))
        assert wait_until(lambda: pub.matching_status.matching, 10)
        client.put(keys.objects(ns), b"\x93not a model")
        client.put(keys.motion(ns, A), encode(motion(1, A)).replace(b"z_test", b"zztest"))
        client.put(keys.points(ns), b"")
        assert wait_until(lambda: svc.counters.get("rejected") == 3, 10)
        c = svc.counters.snapshot()
        assert c["rejected.objects"] == 1 and c["rejected.motion/*"] == 1 and c["rejected.points"] == 1
        client.put(keys.tracked(ns), encode(tracked(4, observed=(A,))))
        client.put(keys.motion(ns, A), encode(motion(4, A, "dynamic", 3.0)))
        client.put(keys.objects(ns), encode(objects(4, ids=(A,))))
        assert wait_until(lambda: len(sink.frames) == 1, 10)
        assert sink.frames[0].seq == 4 and sink.frames[0].motion[A].state == "dynamic"
        assert svc.last_seq == 4
    finally:
        client.close()
        svc.close()
    assert sink.closed


def test_a_negative_zero_z_is_shown_as_zero() -> None:
    """A static window inside the H0 speed bound comes from the classifier with z = -0.0: every such car's label
    read "z=-0.00", its metadata "-0" and the motion JSON -0.0 (seen in a recorded `up` run)."""
    from google.protobuf.json_format import MessageToDict

    from jitterguard.services.foxglove.scene import frame_messages, motion_statistics

    from .decoding import protobuf_class

    f = JoinedFrame(seq=5, stamp_ns=1_005, objects=objects(5, ids=(A,), stationary=(A,)),
                    motion={A: motion(5, A, "static", -0.0)})
    upd = frame_messages(f)["/jitterguard/tracks"]
    schema = upd.get_schema()
    [ent] = MessageToDict(protobuf_class(schema.name, schema.data).FromString(upd.encode()))["entities"]
    assert "z=0.00 " in ent["texts"][0]["text"], ent["texts"][0]["text"]
    meta = {kv["key"]: kv["value"] for kv in ent["metadata"]}
    assert meta["z_x"] == "0" and meta["z_y"] == "0", meta
    [row] = motion_statistics(f)["tracks"]
    assert all(math.copysign(1.0, row[k]) > 0 for k in ("z_x", "z_y", "z")), row


def test_a_polygon_shape_is_drawn_as_its_footprint_not_a_flat_cube() -> None:
    """Autoware's UNKNOWN clusters come as POLYGON shapes: a footprint, length and width 0. Foxglove got a 0 × 0 cube
    for each (nothing to see); it now gets the footprint's outline at the bottom and top of the object's height, in
    the object's frame, decoded back from the protobuf the panel reads. Boxes stay cubes."""
    from google.protobuf.json_format import MessageToDict

    from jitterguard.services.foxglove.scene import frame_messages

    from .decoding import protobuf_class

    objs = objects(5, ids=(A, B))
    square = [{"x": 1.0, "y": 1.0, "z": 0.0}, {"x": -1.0, "y": 1.0, "z": 0.0}, {"x": -1.0, "y": -1.0, "z": 0.0},
              {"x": 1.0, "y": -1.0, "z": 0.0}]
    objs.objects[1].shape = Shape.model_validate({"type": Shape.POLYGON, "footprint": square,
                                                  "dimensions": {"x": 0.0, "y": 0.0, "z": 1.2}})
    upd = frame_messages(JoinedFrame(seq=5, stamp_ns=1_005, objects=objs))["/jitterguard/tracks"]
    schema = upd.get_schema()
    ents = {e["id"]: e for e in MessageToDict(protobuf_class(schema.name, schema.data).FromString(upd.encode()))["entities"]}
    assert len(ents[A]["cubes"]) == 1 and "lines" not in ents[A]
    assert "cubes" not in ents[B] and len(ents[B]["lines"]) == 2
    for line, z in zip(ents[B]["lines"], (-0.6, 0.6)):
        assert line["type"] == "LINE_LOOP"
        assert [(p.get("x", 0.0), p.get("y", 0.0), p.get("z", 0.0)) for p in line["points"]] == \
            [(q["x"], q["y"], z) for q in square]


@pytest.mark.parametrize(("mode", "want", "not_in", "statistic"), [
    ("chi2", "χ²=12.50 thr=5.99", "z=", 12.5),
    ("velocity_threshold", "v=2.40 m/s thr=1.00", "z=", 2.4),
    ("z_test", "z=3.00 α=1.96", "χ²", 3.0),
])
def test_a_tracks_label_shows_the_statistic_that_decided_it(mode: str, want: str, not_in: str,
                                                             statistic: float) -> None:
    """In χ² mode (``eval --mode chi2`` and its MCAP, or a live classifier so set) every label read max(z_x, z_y), a
    wire field the decision never compared with anything: a track called dynamic on χ² = 12.5 > 5.99 showed "z=3.00
    α=1.96", and one called static could show a z above its α. The label, the entity's metadata and the motion row
    now carry the statistic of the message's own mode and the threshold it was held to."""
    from google.protobuf.json_format import MessageToDict

    from jitterguard.services.foxglove.scene import frame_messages, motion_statistics

    from .decoding import protobuf_class

    thr = {"chi2": 5.99, "velocity_threshold": 1.0, "z_test": 1.96}[mode]
    m = MotionState(header=hdr(5), track_id=A, state="dynamic", mode=mode, z_x=3.0, z_y=1.5, chi2=12.5,
                    threshold=thr, alpha=1.96, window_length=5, speed=2.4)
    f = JoinedFrame(seq=5, stamp_ns=1_005, objects=objects(5, ids=(A,)), motion={A: m})
    upd = frame_messages(f)["/jitterguard/tracks"]
    schema = upd.get_schema()
    [ent] = MessageToDict(protobuf_class(schema.name, schema.data).FromString(upd.encode()))["entities"]
    text = ent["texts"][0]["text"]
    assert want in text and not_in not in text, text
    meta = {kv["key"]: kv["value"] for kv in ent["metadata"]}
    assert meta["mode"] == mode and float(meta["statistic"]) == pytest.approx(statistic), meta
    [row] = motion_statistics(f)["tracks"]
    assert row["mode"] == mode and row["statistic"] == pytest.approx(statistic) and row["chi2"] == 12.5, row


@pytest.mark.integration
def test_a_motion_state_on_another_tracks_key_is_refused_and_the_frame_keeps_the_real_one() -> None:
    """A motion state naming track B put on track A's key (a publisher the ACL allows only ``motion/A``) had been
    taken as B's: the bridge keyed it by the payload's ID, so B was recorded and shown dynamic while the classifier had
    called it static. The tracker's static hints refuse such a message already; a bridge now does too (counted
    ``rejected.motion/*``), and B's own state stands."""
    import zenoh

    from jitterguard.runtime import build_config, free_tcp_port, loopback_options
    from jitterguard.schemas import encode, keys
    from jitterguard.services.bridge.service import BridgeService

    from helpers import wait_until

    class ListSink:
        def __init__(self) -> None:
            self.frames: list[JoinedFrame] = []

        def write(self, frame: JoinedFrame) -> None:
            self.frames.append(frame)

        def close(self) -> None:
            pass

    ns, port = "bridge_forged", free_tcp_port()
    sink = ListSink()
    svc = BridgeService(loopback_options(ns, port, listen_self=True), sink, points=False, motion_wait_s=0.5)
    client = zenoh.open(build_config(loopback_options(ns, port)))
    try:
        pub = client.declare_publisher(keys.objects(ns))
        assert wait_until(lambda: pub.matching_status.matching, 10)
        client.put(keys.tracked(ns), encode(tracked(4, observed=(A, B))))
        client.put(keys.motion(ns, B), encode(motion(4, B, "static", 0.5)))
        client.put(keys.motion(ns, A), encode(motion(4, A, "static", 0.5)))
        client.put(keys.motion(ns, A), encode(motion(4, B, "dynamic", 9.0)))  # B's ID on A's key
        assert wait_until(lambda: svc.counters.get("received") == 4, 10)
        client.put(keys.objects(ns), encode(objects(4, ids=(A, B))))
        assert wait_until(lambda: len(sink.frames) == 1, 10)
        frame = sink.frames[0]
        assert frame.motion[B].state == "static" and frame.motion[A].state == "static", frame.motion
        assert svc.counters.get("rejected.motion/*") == 1
    finally:
        client.close()
        svc.close()


@pytest.mark.integration
def test_a_sink_that_fails_frame_after_frame_makes_the_bridge_failing_and_one_that_recovers_ok() -> None:
    """A recording that wrote nothing (a full disk: every write raising) had left the bridge's health ``ok``, so
    ``status`` and ``/readyz`` said all was well and the watchdog never restarted it. Five failures in a row are
    ``failing``, with the sink's error as the reason; the next frame written makes it ``ok`` again."""
    import zenoh

    from jitterguard.runtime import build_config, free_tcp_port, loopback_options
    from jitterguard.schemas import encode, keys
    from jitterguard.services.bridge.service import BridgeService

    from helpers import wait_until

    class FullDisk:
        def __init__(self) -> None:
            self.full = True
            self.frames: list[JoinedFrame] = []

        def write(self, frame: JoinedFrame) -> None:
            if self.full:
                raise OSError(28, "No space left on device")
            self.frames.append(frame)

        def close(self) -> None:
            pass

    ns, port = "bridge_full", free_tcp_port()
    sink = FullDisk()
    svc = BridgeService(loopback_options(ns, port, listen_self=True), sink, points=False, motion_wait_s=0.2)
    client = zenoh.open(build_config(loopback_options(ns, port)))
    try:
        pub = client.declare_publisher(keys.objects(ns))
        assert wait_until(lambda: pub.matching_status.matching, 10)
        assert svc.health().ok  # nothing to write yet: idle, not stalled
        for seq in range(1, 6):
            client.put(keys.tracked(ns), encode(tracked(seq, observed=(A,))))
            client.put(keys.motion(ns, A), encode(motion(seq, A)))
            client.put(keys.objects(ns), encode(objects(seq, ids=(A,))))
            assert wait_until(lambda s=seq: svc.counters.get("sink_errors") == s, 10)
        health = svc.health()
        assert health.state == "failing" and "No space left on device" in health.reason, health
        sink.full = False
        client.put(keys.tracked(ns), encode(tracked(6, observed=(A,))))
        client.put(keys.motion(ns, A), encode(motion(6, A)))
        client.put(keys.objects(ns), encode(objects(6, ids=(A,))))
        assert wait_until(lambda: len(sink.frames) == 1, 10)
        assert svc.health().ok
    finally:
        client.close()
        svc.close()
