"""The tracker's adapter: detections columns -> core arrays, core result -> TrackObservation / TrackedObjects
payloads."""

from __future__ import annotations

import math

import numpy as np
import pytest

from jitterguard.geometry import quaternion_from_yaw, rotate_cov2, yaw_from_quaternion
from jitterguard.schemas import decode, encode, read_detected_objects
from jitterguard.schemas.wire import _area as shape_area
from jitterguard.schemas.models import (
    X_X,
    X_Y,
    Y_X,
    Y_Y,
    YAW_YAW,
    DetectedObject,
    DetectedObjectKinematics,
    DetectedObjects,
    Header,
    ObjectClassification,
    Point,
    Pose,
    PoseWithCovariance,
    Quaternion,
    Shape,
    TrackedObjects,
    TrackObservation,
    Twist,
    TwistWithCovariance,
    Vector3,
)
from jitterguard.services.tracker.config import default_config
from jitterguard.services.tracker.adapter import VEL_VAR_FLOOR, detection_frame, observation_payloads, tracked_payload
from jitterguard.services.tracker.core import TrackerCore
from helpers import to_message
from jitterguard.bench.tracker_sequences import make_sequence


def frame_from_message(msg: DetectedObjects):
    return detection_frame(read_detected_objects(encode(msg)))


def _run(seq_frames):
    core = TrackerCore()
    for sf in seq_frames:
        msg = to_message(sf)
        cols = read_detected_objects(encode(msg))
        frame = detection_frame(cols)
        res = core.step(frame)
        yield sf, msg, frame, res, (observation_payloads(cols, frame, res), tracked_payload(cols, frame, res))


def test_frame_from_message_recovers_the_detector_arrays() -> None:
    sf = make_sequence(3, n_frames=1).frames[0]
    frame = frame_from_message(to_message(sf))
    d = sf.detections
    for name in ("x", "y", "z", "length", "width", "height", "cov_xx", "cov_xy", "cov_yy", "var_yaw", "label_prob"):
        np.testing.assert_allclose(getattr(frame, name), getattr(d, name), atol=1e-9, err_msg=name)
    np.testing.assert_allclose(np.cos(frame.yaw - d.yaw), 1.0, atol=1e-9)
    assert frame.label.tolist() == d.label.tolist()
    assert frame.has_cov.all() and (frame.ego_x, frame.ego_y) == (d.ego_x, d.ego_y)
    assert frame.ego_yaw == pytest.approx(d.ego_yaw)
    np.testing.assert_allclose(frame.area, d.length * d.width)


def test_detections_of_another_shape_give_the_same_frame_and_payloads() -> None:
    """A payload the records cannot view (here: floats written as float32, legal msgpack) is read by the model and
    normalised into the same columns; the core's arrays and the payloads must be what the record form gives."""
    import dataclasses

    ids = iter(f"{i:032x}" for i in range(10**6))
    core_r = TrackerCore(id_factory=lambda: next(ids))
    ids2 = iter(f"{i:032x}" for i in range(10**6))
    core_m = TrackerCore(id_factory=lambda: next(ids2))
    checked = 0
    for sf in make_sequence(7, n_frames=10).frames:
        msg = to_message(sf)
        data = encode(msg)
        cols, cols_m = read_detected_objects(data), read_detected_objects(_reordered(data))
        assert not cols.normalised and cols_m.normalised
        fr, fm = detection_frame(cols), detection_frame(cols_m)
        for f in dataclasses.fields(fr):
            a, b = getattr(fr, f.name), getattr(fm, f.name)
            if isinstance(a, np.ndarray):
                np.testing.assert_array_equal(a, b, err_msg=f.name)
                assert a.dtype == b.dtype, f.name
            else:
                assert a == b, f.name
        res_r, res_m = core_r.step(fr), core_m.step(fm)
        assert observation_payloads(cols, fr, res_r) == observation_payloads(cols_m, fm, res_m)
        assert tracked_payload(cols, fr, res_r) == tracked_payload(cols_m, fm, res_m)
        checked += len(res_r.observed_ids)
    assert checked > 20


def _reordered(data: bytes) -> bytes:
    """The same message with each object's keys in another order: valid, not the record shape."""
    import msgpack

    raw = msgpack.unpackb(data)
    raw["objects"] = [dict(reversed(list(o.items()))) for o in raw["objects"]]
    return msgpack.packb(raw)


def test_highest_probability_class_wins_and_no_class_means_unknown() -> None:
    objs = [
        DetectedObject(classification=[ObjectClassification(label=7, probability=0.3),
                                        ObjectClassification(label=6, probability=0.6)]),
        DetectedObject(classification=[]),
    ]
    f = frame_from_message(DetectedObjects(header=Header(stamp=1, seq=0), objects=objs))
    assert f.label.tolist() == [6, 0]
    assert f.label_prob[0] == pytest.approx(0.6)


def test_footprint_area_follows_autowares_getarea() -> None:
    assert shape_area(Shape(type=0, dimensions=Vector3(x=4.0, y=2.0, z=1.0))) == pytest.approx(8.0)
    assert shape_area(Shape(type=1, dimensions=Vector3(x=2.0, y=2.0, z=1.0))) == pytest.approx(math.pi)
    square = [Point(x=0, y=0), Point(x=3, y=0), Point(x=3, y=2), Point(x=0, y=2)]
    assert shape_area(Shape(type=2, footprint=square)) == pytest.approx(6.0)


def test_outputs_decode_as_the_contract_models_and_carry_the_frame() -> None:
    seq = make_sequence(5, n_frames=12)
    for sf, msg, frame, res, (obs, closing) in _run(seq.frames):
        tracked = decode(TrackedObjects, closing)
        assert tracked.header.seq == msg.header.seq and tracked.header.stamp == msg.header.stamp
        assert tracked.header.frame_id == "map"
        assert [o.object_id for o in tracked.objects] == res.tracks.ids
        assert tracked.observed_track_ids == [tid for tid, _ in obs] == res.observed_ids
        for tid, payload in obs:
            m = decode(TrackObservation, payload)
            assert m.header == tracked.header and m.track.object_id == tid
    assert len(tracked.objects) > 5 and len(obs) > 5  # the loop really checked something


def test_observation_detection_is_in_the_world_frame_with_rotated_covariance() -> None:
    ego_yaw = 1.1
    qx, qy, qz, qw = quaternion_from_yaw(ego_yaw)
    cov = [0.0] * 36
    cov[X_X], cov[X_Y], cov[Y_X], cov[Y_Y], cov[YAW_YAW] = 0.04, 0.01, 0.01, 0.16, 0.02
    cov[5] = cov[30] = 0.003  # x-yaw correlation
    det_yaw = 0.3
    dq = quaternion_from_yaw(det_yaw)
    obj = DetectedObject(
        classification=[ObjectClassification(label=1, probability=0.9)],
        kinematics=DetectedObjectKinematics(
            pose_with_covariance=PoseWithCovariance(
                pose=Pose(position=Point(x=10.0, y=2.0, z=0.7), orientation=Quaternion(x=dq[0], y=dq[1], z=dq[2], w=dq[3])),
                covariance=cov),
            has_position_covariance=True,
            twist_with_covariance=TwistWithCovariance(twist=Twist(linear=Vector3(x=3.0, y=0.0))),
            has_twist=True,
        ),
        shape=Shape(type=0, dimensions=Vector3(x=4.5, y=1.9, z=1.5)),
    )
    core = TrackerCore(default_config(confirm_hits=1))
    msg = DetectedObjects(header=Header(stamp=10**9, frame_id="lidar", seq=7),
                          ego_pose=Pose(position=Point(x=100.0, y=50.0, z=1.8),
                                        orientation=Quaternion(x=qx, y=qy, z=qz, w=qw)),
                          objects=[obj])
    cols = read_detected_objects(encode(msg))
    frame = detection_frame(cols)
    res = core.step(frame)
    obs = observation_payloads(cols, frame, res)
    assert len(obs) == 1
    det = decode(TrackObservation, obs[0][1]).detection
    pose = det.kinematics.pose_with_covariance.pose
    c, s = math.cos(ego_yaw), math.sin(ego_yaw)
    assert (pose.position.x, pose.position.y, pose.position.z) == pytest.approx(
        (100 + c * 10 - s * 2, 50 + s * 10 + c * 2, 2.5))
    o = pose.orientation
    assert yaw_from_quaternion(o.x, o.y, o.z, o.w) == pytest.approx(det_yaw + ego_yaw)
    wc = det.kinematics.pose_with_covariance.covariance
    rxx, rxy, ryy = rotate_cov2(0.04, 0.01, 0.16, ego_yaw)
    assert (wc[X_X], wc[X_Y], wc[Y_X], wc[Y_Y]) == pytest.approx((rxx, rxy, rxy, ryy))
    assert wc[YAW_YAW] == pytest.approx(0.02)
    assert (wc[5], wc[11]) == pytest.approx((c * 0.003, s * 0.003))  # cov(x, yaw) rotated with x/y
    assert (wc[30], wc[31]) == pytest.approx((c * 0.003, s * 0.003))
    assert det.kinematics.has_position_covariance
    lin = det.kinematics.twist_with_covariance.twist.linear
    assert (lin.x, lin.y) == pytest.approx((3 * c, 3 * s))
    # the track state riding along
    st = decode(TrackObservation, obs[0][1]).track
    assert (st.x, st.y) == pytest.approx((res.tracks.x[0], res.tracks.y[0]))
    assert st.hits == 1 and st.label == 1 and st.age_s == 0.0
    assert decode(TrackedObjects, tracked_payload(cols, frame, res)).ego_pose == msg.ego_pose  # the contract's ego pose


def test_a_detection_without_covariance_is_observed_with_the_filters_measurement_covariance() -> None:
    """Autoware's lidar_centerpoint reports no position covariance. The observation the classifier receives then
    carries the covariance the filter measured the detection with — the class's, along (r_long) and across (r_lat)
    its heading in the world — and says it has one; a detection with its own covariance keeps it."""
    ego_yaw, det_yaw = 0.5, 0.3
    qx, qy, qz, qw = quaternion_from_yaw(ego_yaw)
    dq = quaternion_from_yaw(det_yaw)

    def car(x: float, cov: list[float] | None) -> DetectedObject:
        return DetectedObject(
            classification=[ObjectClassification(label=1, probability=0.9)],
            kinematics=DetectedObjectKinematics(
                pose_with_covariance=PoseWithCovariance(
                    pose=Pose(position=Point(x=x, y=2.0, z=0.7),
                              orientation=Quaternion(x=dq[0], y=dq[1], z=dq[2], w=dq[3])),
                    covariance=cov or [0.0] * 36),
                has_position_covariance=cov is not None, orientation_availability=1),
            shape=Shape(type=0, dimensions=Vector3(x=4.5, y=1.9, z=1.5)))
    own = [0.0] * 36
    own[X_X], own[Y_Y] = 0.04, 0.09
    config = default_config(confirm_hits=1)
    core = TrackerCore(config)
    msg = DetectedObjects(header=Header(stamp=10**9, frame_id="lidar", seq=1),
                          ego_pose=Pose(position=Point(x=100.0, y=50.0, z=1.8),
                                        orientation=Quaternion(x=qx, y=qy, z=qz, w=qw)),
                          objects=[car(10.0, None), car(30.0, own)])
    cols = read_detected_objects(encode(msg))
    frame = detection_frame(cols)
    res = core.step(frame)
    dets = sorted((decode(TrackObservation, p).detection for _, p in observation_payloads(cols, frame, res)),
                  key=lambda d: d.kinematics.pose_with_covariance.pose.position.x)
    assert len(dets) == 2 and all(d.kinematics.has_position_covariance for d in dets)
    car_params = config.classes["car"]
    heading = det_yaw + ego_yaw
    c, s = math.cos(heading), math.sin(heading)
    rl, rt = car_params.r_long ** 2, car_params.r_lat ** 2
    wc = dets[0].kinematics.pose_with_covariance.covariance
    assert (wc[X_X], wc[X_Y], wc[Y_X], wc[Y_Y]) == pytest.approx(
        (c * c * rl + s * s * rt, c * s * (rl - rt), c * s * (rl - rt), s * s * rl + c * c * rt))
    assert sum(abs(v) for i, v in enumerate(wc) if i not in (X_X, X_Y, Y_X, Y_Y)) == 0.0
    kept = dets[1].kinematics.pose_with_covariance.covariance
    rxx, rxy, ryy = rotate_cov2(0.04, 0.0, 0.09, ego_yaw)
    assert (kept[X_X], kept[X_Y], kept[Y_Y]) == pytest.approx((rxx, rxy, ryy))


def test_a_covariance_or_twist_that_rotation_takes_past_the_limits_is_not_published_so() -> None:
    """A variance of 1e6 on both sensor axes with a covariance of −0.99e6 (each within the wire's bound) is 1.99e6 on
    one world axis at 45°, and (999, −999) m/s is 1413 m/s: the tracker took them and republished them rotated, and
    the classifier refused every such observation and went ``failing``. They are now published as a detection
    without them (the class's covariance, no twist), which the classifier's reader takes; a detection whose twist is
    flagged absent is read so (msgpack's false byte had been read as true)."""
    from jitterguard.schemas.wire import read_track_observations

    qx, qy, qz, qw = quaternion_from_yaw(math.pi / 4)
    huge = [0.0] * 36
    huge[X_X], huge[Y_Y], huge[X_Y], huge[Y_X] = 1e6, 1e6, -0.99e6, -0.99e6

    def car(x: float, cov: list[float], v: tuple[float, float], has_twist: bool = True) -> DetectedObject:
        return DetectedObject(
            classification=[ObjectClassification(label=1, probability=0.9)],
            kinematics=DetectedObjectKinematics(
                pose_with_covariance=PoseWithCovariance(pose=Pose(position=Point(x=x, y=2.0, z=0.7)), covariance=cov),
                has_position_covariance=True,
                twist_with_covariance=TwistWithCovariance(twist=Twist(linear=Vector3(x=v[0], y=v[1]))),
                has_twist=has_twist),
            shape=Shape(type=0, dimensions=Vector3(x=4.5, y=1.9, z=1.5)))
    small = [0.0] * 36
    small[X_X], small[Y_Y] = 0.04, 0.09
    tilted = list(small)  # x and y against z: (0.9e6, 0.9e6) rotates to (0, 1.27e6), so both go unknown (zero)
    tilted[2] = tilted[12] = tilted[8] = tilted[13] = 0.9e6
    tilted[14] = 1e6  # var(z), which rotation about z leaves alone
    msg = DetectedObjects(header=Header(stamp=10**9, frame_id="lidar", seq=1),
                          ego_pose=Pose(position=Point(x=100.0, y=50.0, z=1.8),
                                        orientation=Quaternion(x=qx, y=qy, z=qz, w=qw)),
                          objects=[car(10.0, huge, (3.0, 0.0)), car(30.0, small, (999.0, -999.0)),
                                   car(50.0, small, (0.0, 0.0), has_twist=False), car(70.0, tilted, (1.0, 0.0))])
    cols = read_detected_objects(encode(msg))
    frame = detection_frame(cols)
    assert frame.has_twist.tolist() == [True, True, False, True]
    res = TrackerCore(default_config(confirm_hits=1)).step(frame)
    obs = observation_payloads(cols, frame, res)
    read = read_track_observations([p for _, p in obs])  # the classifier's reader: had refused two of the three
    assert not read.errors and len(read.index) == 4, read.errors
    dets = sorted((decode(TrackObservation, p).detection for _, p in obs),
                  key=lambda d: d.kinematics.pose_with_covariance.pose.position.x)
    wc = dets[0].kinematics.pose_with_covariance.covariance
    assert max(abs(v) for v in wc) < 10.0 and dets[0].kinematics.has_position_covariance  # the class's
    fast = dets[1].kinematics
    assert not fast.has_twist and (fast.twist_with_covariance.twist.linear.x, fast.twist_with_covariance.twist.linear.y) == (0.0, 0.0)
    assert dets[0].kinematics.has_twist and dets[0].kinematics.twist_with_covariance.twist.linear.x == pytest.approx(3 / math.sqrt(2))
    tc = dets[3].kinematics.pose_with_covariance.covariance  # its own x-y block kept (the filter used it), rotated
    assert (tc[2], tc[8], tc[12], tc[13], tc[14]) == (0.0, 0.0, 0.0, 0.0, 1e6)
    assert (tc[X_X], tc[Y_Y]) == pytest.approx(rotate_cov2(0.04, 0.0, 0.09, math.pi / 4)[::2])


def test_tracked_object_carries_filter_state_and_world_twist() -> None:
    seq = make_sequence(6, n_frames=30)
    *_, (sf, msg, frame, res, (obs, closing)) = _run(seq.frames)
    tracked = decode(TrackedObjects, closing)
    for i, o in enumerate(tracked.objects):
        k = o.kinematics
        assert k.twist_with_covariance.twist.linear.x == pytest.approx(res.tracks.vel[i, 0])
        assert k.twist_with_covariance.twist.linear.y == pytest.approx(res.tracks.vel[i, 1])
        cov = k.pose_with_covariance.covariance
        assert cov[X_X] == pytest.approx(res.tracks.pose_cov[i, 0, 0])
        assert cov[X_Y] == cov[Y_X] == pytest.approx(res.tracks.pose_cov[i, 0, 1])
        tc = k.twist_with_covariance.covariance
        # the filter's velocity covariance plus a floor: never "known exactly" (a stopped car's lateral term, a CV
        # track's yaw rate had been published as 0)
        assert tc[Y_Y] == pytest.approx(res.tracks.vel_cov[i, 1, 1] + VEL_VAR_FLOOR)
        assert tc[X_X] >= VEL_VAR_FLOOR and tc[35] > 0.0
        assert all(tc[d] > 0.0 and cov[d] > 0.0 for d in (14, 21, 28))  # vz / z, roll, pitch: had been 0 in the twist
        assert not k.is_stationary
        assert o.classification[0].label == int(res.tracks.label[i])
        q = k.pose_with_covariance.pose.orientation
        assert math.cos(yaw_from_quaternion(q.x, q.y, q.z, q.w) - res.tracks.yaw[i]) == pytest.approx(1.0)
        assert o.shape.dimensions.x == pytest.approx(res.tracks.dims[i, 0])


@pytest.mark.parametrize("var_yaw", [1e-300, 1e-20])
def test_a_tiny_heading_variance_never_makes_a_tracked_frame_the_classifier_refuses(var_yaw: float) -> None:
    """A detector's heading variance of 1e-20 is valid on the wire; taken as it was, the update rounded tracks'
    heading variances below zero, and the classifier's reader refused each ``tracked`` frame carrying one (whole
    frames lost, counted only downstream as ``rejected.tracked``). Floored, every frame reads."""
    from jitterguard.schemas.wire import read_tracked_objects

    frames = make_sequence(5, n_frames=80).frames
    for sf in frames:
        sf.detections.var_yaw[:] = var_yaw
    core = TrackerCore()
    published = 0
    for sf in frames:
        cols = read_detected_objects(encode(to_message(sf)))
        frame = detection_frame(cols)
        res = core.step(frame)
        published += len(read_tracked_objects(tracked_payload(cols, frame, res)).objects)  # raises if refused
        assert (np.diagonal(core.tracks.P, axis1=1, axis2=2) >= 0.0).all()
    assert published > 100
