"""The detector's adapter: PointCloud -> network points, Detections3D -> DetectedObjects payload (sensor frame)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from jitterguard.geometry import quaternion_from_yaw, rotate_cov2, yaw_from_quaternion
from jitterguard.schemas import decode, read_detected_objects
from jitterguard.schemas.models import (
    COVARIANCE_SIZE,
    X_X,
    Y_Y,
    YAW_YAW,
    DetectedObjects,
    Header,
    Label,
    Point,
    PointCloud,
    Pose,
    Quaternion,
    TrackObservation,
)
from jitterguard.services.detector.config import CLASS_NAMES, Detections3D
from jitterguard.services.detector.adapter import class_labels, detections_payload, finite_detections, scan_points
from jitterguard.services.tracker.adapter import detection_frame, observation_payloads
from jitterguard.services.tracker.config import default_config
from jitterguard.services.tracker.core import TrackerCore

HEADER = Header(stamp=1_700_000_000_123_456_789, frame_id="lidar", seq=42)
EGO_YAW = 0.7
EGO = Pose(position=Point(x=105.0, y=-20.0, z=1.84), orientation=Quaternion(**dict(zip("xyzw", quaternion_from_yaw(EGO_YAW)))))


def _dets(n: int = 6, seed: int = 0, uncertainty: bool = True) -> Detections3D:
    rng = np.random.default_rng(seed)
    boxes = np.column_stack([
        rng.uniform(-40, 40, n), rng.uniform(-40, 40, n), rng.uniform(-1.5, 0.5, n),  # x, y, z (centre)
        rng.uniform(0.5, 12, n), rng.uniform(0.5, 3, n), rng.uniform(1, 4, n),  # l, w, h
        rng.uniform(-math.pi, math.pi, n), rng.normal(0, 5, n), rng.normal(0, 5, n),  # yaw, vx, vy
    ]).astype(np.float32)
    lv = rng.uniform(-10, 3, (n, 5)).astype(np.float32) if uncertainty else None
    return Detections3D(boxes, rng.uniform(0.05, 1.0, n).astype(np.float32), np.arange(n) % 5, lv)


def detections_message(det: Detections3D, header: Header, ego: Pose, class_names=CLASS_NAMES, *,
                       has_twist: bool = True) -> DetectedObjects:
    """What the receiver validates: the payload read by the model (a second, independent reader)."""
    return decode(DetectedObjects, detections_payload(det, header, ego, class_names, has_twist=has_twist))


def test_every_field_is_filled_from_the_network_output() -> None:
    det = _dets()
    msg = detections_message(det, HEADER, EGO)
    assert msg.header == HEADER and msg.ego_pose == EGO
    assert len(msg.objects) == len(det)
    var = np.exp(det.log_variances.astype(np.float64))
    for i, o in enumerate(msg.objects):
        k = o.kinematics
        p = k.pose_with_covariance.pose
        b = det.boxes[i].astype(np.float64)
        assert (p.position.x, p.position.y, p.position.z) == pytest.approx(tuple(b[:3]), abs=1e-6)
        q = p.orientation
        assert math.cos(yaw_from_quaternion(q.x, q.y, q.z, q.w) - b[6]) == pytest.approx(1.0, abs=1e-9)
        d = o.shape.dimensions
        assert (d.x, d.y, d.z) == pytest.approx(tuple(b[3:6]), abs=1e-6)
        assert o.shape.type == 0
        assert o.existence_probability == pytest.approx(float(det.scores[i]))
        assert [(c.label, c.probability) for c in o.classification] == [
            (class_labels()[int(det.labels[i])], pytest.approx(float(det.scores[i])))]
        # variances: pose x, y, yaw; twist vx, vy; nothing else claimed
        cov = np.asarray(k.pose_with_covariance.covariance)
        assert (cov[X_X], cov[Y_Y], cov[YAW_YAW]) == pytest.approx((var[i, 0], var[i, 1], var[i, 4]), rel=1e-6)
        assert np.count_nonzero(np.delete(cov, [X_X, Y_Y, YAW_YAW])) == 0
        tcov = np.asarray(k.twist_with_covariance.covariance)
        assert (tcov[X_X], tcov[Y_Y]) == pytest.approx((var[i, 2], var[i, 3]), rel=1e-6)
        assert np.count_nonzero(np.delete(tcov, [X_X, Y_Y])) == 0
        lin = k.twist_with_covariance.twist.linear
        assert (lin.x, lin.y) == pytest.approx((float(b[7]), float(b[8])), abs=1e-6)
        assert k.has_position_covariance and k.has_twist and k.has_twist_covariance


def test_the_payload_is_in_the_record_shape_the_tracker_views() -> None:
    cols = read_detected_objects(detections_payload(_dets(20, seed=3), HEADER, EGO))
    assert not cols.normalised and len(cols.objects) == 20


def test_autoware_labels_follow_the_class_names() -> None:
    assert class_labels(CLASS_NAMES) == (Label.CAR, Label.TRUCK, Label.BUS, Label.BICYCLE, Label.PEDESTRIAN)
    assert class_labels(("pedestrian", "car")) == (Label.PEDESTRIAN, Label.CAR)
    with pytest.raises(ValueError, match="scooter"):
        class_labels(("car", "scooter"))


def test_vanilla_model_publishes_no_covariance() -> None:
    msg = detections_message(_dets(uncertainty=False), HEADER, EGO)
    for o in msg.objects:
        k = o.kinematics
        assert not k.has_position_covariance and not k.has_twist_covariance
        assert k.pose_with_covariance.covariance == (0.0,) * COVARIANCE_SIZE
        assert k.twist_with_covariance.covariance == (0.0,) * COVARIANCE_SIZE


def test_without_twist_the_velocity_is_not_claimed() -> None:
    msg = detections_message(_dets(), HEADER, EGO, has_twist=False)
    for o in msg.objects:
        k = o.kinematics
        assert not k.has_twist and not k.has_twist_covariance and k.has_position_covariance
        assert (k.twist_with_covariance.twist.linear.x, k.twist_with_covariance.twist.linear.y) == (0.0, 0.0)


def test_empty_detections_make_a_valid_empty_frame() -> None:
    msg = detections_message(Detections3D.empty(), HEADER, EGO)
    assert msg.objects == [] and msg.header.seq == 42 and msg.ego_pose == EGO


def test_extreme_but_finite_values_still_validate() -> None:
    det = _dets(3)
    det.scores[:] = [1.0000001, 0.0, 1e-9]  # sigmoid may round to 1 in float32 and above it after a cast
    det.log_variances[:] = [[-10.0] * 5, [50.0] * 5, [0.0] * 5]
    msg = detections_message(det, HEADER, EGO)
    assert msg.objects[0].existence_probability == 1.0
    assert msg.objects[1].kinematics.pose_with_covariance.covariance[X_X] == pytest.approx(math.exp(50.0), rel=1e-6)


def test_non_finite_detections_are_dropped_and_counted() -> None:
    det = _dets(6)
    det.boxes[1, 0] = np.nan
    det.scores[2] = np.inf
    det.log_variances[3, 4] = 1000.0  # exp overflows: no usable variance
    det.log_variances[4, 0] = -np.inf  # exp(-inf) = 0: a (degenerate) finite variance, kept
    kept, dropped = finite_detections(det)
    assert dropped == 3
    np.testing.assert_array_equal(kept.boxes, det.boxes[[0, 4, 5]])
    np.testing.assert_array_equal(kept.labels, det.labels[[0, 4, 5]])
    detections_message(kept, HEADER, EGO)  # validates
    clean, none = finite_detections(_dets(4, uncertainty=False))
    assert none == 0 and clean.log_variances is None


def _cloud(cols: dict[str, np.ndarray]) -> PointCloud:
    names = list(cols)
    arr = np.column_stack([cols[n] for n in names]).astype("<f4")
    return PointCloud(header=HEADER, ego_pose=EGO, fields=names, num_points=len(arr), data=arr.tobytes())


def test_scan_points_picks_columns_by_name_and_drops_non_finite_rows() -> None:
    rng = np.random.default_rng(1)
    x, y, z, ring = (rng.normal(size=8) for _ in range(4))
    i = rng.uniform(2.0, 250.0, size=8)  # on the network's 0–255 scale already: passed as is
    x[3] = np.nan
    pts, bad = scan_points(_cloud({"x": x, "y": y, "z": z, "ring": ring, "intensity": i}))
    assert bad == 1 and pts.dtype == np.float32 and pts.shape == (7, 4)
    keep = np.arange(8) != 3
    np.testing.assert_allclose(pts, np.column_stack([x, y, z, i])[keep].astype(np.float32))
    # a NaN intensity alone keeps the return, dark; an infinite one is clipped to the scale's ends
    i2 = i.copy()
    i2[[1, 5, 6]] = [np.nan, np.inf, -np.inf]
    pts, bad = scan_points(_cloud({"x": x, "y": y, "z": z, "intensity": i2}))
    assert bad == 1 and pts.shape == (7, 4)
    np.testing.assert_allclose(pts[:, 3], np.array([i[0], 0.0, i[2], i[4], 255.0, 0.0, i[7]], np.float32))


def test_intensity_reaches_the_network_on_its_0_to_255_scale() -> None:
    """A KITTI scan's 0–1 reflectance is scaled to 0–255 (it was fed as is live, and scaled only in ``adapt``);
    a 16-bit sensor's or a stray return's intensity is clipped into 0–255."""
    xyz = {"x": np.arange(4.0), "y": np.zeros(4), "z": np.zeros(4)}
    kitti, _ = scan_points(_cloud({**xyz, "intensity": np.array([0.0, 0.25, 0.5, 1.0])}))
    np.testing.assert_allclose(kitti[:, 3], [0.0, 63.75, 127.5, 255.0])
    wild, _ = scan_points(_cloud({**xyz, "intensity": np.array([-3.0, 7.0, 300.0, 1e5])}))
    np.testing.assert_allclose(wild[:, 3], [0.0, 7.0, 255.0, 255.0])
    nus, _ = scan_points(_cloud({**xyz, "intensity": np.array([0.0, 1.0, 2.0, 255.0])}))
    np.testing.assert_allclose(nus[:, 3], [0.0, 1.0, 2.0, 255.0])
    dark, _ = scan_points(_cloud({**xyz, "intensity": np.array([0.0, 1.0, 1.0, 0.0])}))  # whole numbers: 0–255
    np.testing.assert_allclose(dark[:, 3], [0.0, 1.0, 1.0, 0.0])
    # a reflectance scan with a stray return above 1 (one in 5,000) is still a reflectance: it was read as 0–255
    rng = np.random.default_rng(3)
    refl = rng.uniform(0.0, 1.0, 5000)
    refl[17] = 1.2
    n = len(refl)
    stray, _ = scan_points(_cloud({"x": np.arange(n, dtype=float) * 1e-3 + 5.0, "y": np.zeros(n), "z": np.zeros(n),
                                   "intensity": refl}))
    np.testing.assert_allclose(stray[:, 3], np.minimum(refl * 255.0, 255.0), rtol=1e-6)


def test_scan_without_intensity_reads_zero_intensity() -> None:
    pts, bad = scan_points(_cloud({"x": np.ones(3), "y": np.zeros(3), "z": np.zeros(3)}))
    assert bad == 0 and pts[:, 3].tolist() == [0.0, 0.0, 0.0]
    empty, _ = scan_points(_cloud({"x": np.zeros(0), "y": np.zeros(0), "z": np.zeros(0)}))
    assert empty.shape == (0, 4)


def test_tracker_reads_the_sensor_frame_and_rotates_the_covariance_once() -> None:
    """The contract end to end: the tracker consumes the detector's message unchanged; the observation it
    republishes for the classifier has the sensor-frame covariance rotated into the world frame (R Σ Rᵀ)."""
    var_x, var_y = 0.04, 0.25  # along x much tighter than along y: a copy of the diagonal would be wrong
    det = Detections3D(np.array([[12.0, 3.0, -0.9, 4.5, 1.9, 1.6, 0.3, 0.0, 0.0]], np.float32),
                       np.array([0.9], np.float32), np.array([0]),
                       np.log(np.array([[var_x, var_y, 0.5, 0.5, 0.01]], np.float32)))
    core = TrackerCore(default_config())
    obs = []
    for seq in range(4):
        header = Header(stamp=HEADER.stamp + seq * 100_000_000, frame_id="lidar", seq=seq)
        cols = read_detected_objects(detections_payload(det, header, EGO))
        frame = detection_frame(cols)
        assert (frame.cov_xx[0], frame.cov_yy[0], frame.cov_xy[0]) == pytest.approx((var_x, var_y, 0.0), rel=1e-5)
        res = core.step(frame)
        obs = observation_payloads(cols, frame, res)
    assert len(obs) == 1
    o = decode(TrackObservation, obs[0][1])
    c = o.detection.kinematics.pose_with_covariance.covariance
    want = rotate_cov2(var_x, 0.0, var_y, EGO_YAW)
    assert (c[X_X], c[1], c[Y_Y]) == pytest.approx(tuple(float(v) for v in want), rel=1e-5)
    p = o.detection.kinematics.pose_with_covariance.pose.position
    cy, sy = math.cos(EGO_YAW), math.sin(EGO_YAW)
    assert (p.x, p.y) == pytest.approx((105.0 + cy * 12.0 - sy * 3.0, -20.0 + sy * 12.0 + cy * 3.0), abs=1e-4)
