"""The scans' height above the road (``sensor_height_m``) and tilt against it (``sensor_tilt``): measured from each
scan's ground, or declared.

The network was trained with its sensor 1.84 m above the road; a scan from a sensor mounted elsewhere, or a cloud in
``base_link`` (road at z = 0), is moved to that height before the network and its boxes moved back. What is
tested: the estimate on planes of known height and slope, on ray-cast scans from other mounting heights and on
the real scene's scans; the plane's slope, and that a pitched or rolled scan gives the boxes of the level one; that a
scan lifted by any amount gives the same boxes, lifted; the declared height; the config and its refusals.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
from pydantic import ValidationError

from jitterguard.services.detector.config import DetectorParams, declared_height, measures_tilt, parse_sensor_height
from jitterguard.services.detector.data import synthetic_samples
from jitterguard.services.detector.ground import (TRAINED_SENSOR_HEIGHT_M, GroundPlane, GroundWatch, boxes_to_scan_frame,
                                                 boxes_to_trained_frame, ground_height, ground_plane, scan_ground,
                                                 to_trained_frame)
from jitterguard.services.detector.inference import Detector
from jitterguard.sim.sensors import hdl32e
from helpers import NUSC


def _plane_scan(height: float, slope: tuple[float, float] = (0.0, 0.0), n: int = 20_000, seed: int = 0,
                clutter: int = 0) -> np.ndarray:
    """Returns on a plane ``height`` below the origin (rising by ``slope`` per metre in x and y), 2–40 m around
    it, with 2 cm of range noise, and ``clutter`` returns on car-sized blocks standing on it."""
    rng = np.random.default_rng(seed)
    r, a = rng.uniform(2.0, 40.0, n), rng.uniform(-np.pi, np.pi, n)
    x, y = r * np.cos(a), r * np.sin(a)
    z = -height + slope[0] * x + slope[1] * y + rng.normal(0.0, 0.02, n)
    pts = [np.column_stack([x, y, z, rng.uniform(0, 50, n)])]
    if clutter:
        cx, cy = rng.uniform(-25, 25, (2, 40))
        k = rng.integers(0, 40, clutter)
        bx, by = cx[k] + rng.uniform(-2, 2, clutter), cy[k] + rng.uniform(-0.9, 0.9, clutter)
        bz = -height + slope[0] * bx + slope[1] * by + rng.uniform(0.3, 1.5, clutter)
        pts.append(np.column_stack([bx, by, bz, rng.uniform(0, 50, clutter)]))
    return np.concatenate(pts).astype(np.float32)


def _lift(points: np.ndarray, dz: float) -> np.ndarray:
    out = points.copy()
    out[:, 2] += np.float32(dz)
    return out


def _turn(points: np.ndarray, pitch_deg: float, roll_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """``points`` seen from a frame pitched and rolled by the angles (a rigid turn about the origin), and the turn."""
    p, r = np.radians(pitch_deg), np.radians(roll_deg)
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    turn = ry @ rx
    out = points.copy()
    out[:, :3] = (points[:, :3].astype(np.float64) @ turn.T).astype(np.float32)
    return out, turn


@pytest.mark.parametrize("height", [0.0, 1.2, 1.84, 2.6, 4.5])
def test_the_height_of_a_flat_road_is_found_whatever_the_frame(height: float) -> None:
    assert ground_height(_plane_scan(height, clutter=8_000)) == pytest.approx(height, abs=0.03)


def test_a_sloped_road_is_read_under_the_sensor_not_ahead_of_it() -> None:
    """A 6 % grade falls 1.8 m over the 30 m the cells reach: the plane is read at the sensor, where the
    network's training scans put the road."""
    scan = _plane_scan(1.84, slope=(0.06, -0.02), clutter=8_000)
    assert ground_height(scan) == pytest.approx(1.84, abs=0.05)
    plane = ground_plane(scan)
    assert plane is not None and plane.slope_x == pytest.approx(0.06, abs=0.003)
    assert plane.slope_y == pytest.approx(-0.02, abs=0.003)
    assert plane.slope_deg[0] == pytest.approx(np.degrees(np.arctan(0.06)), abs=0.2)


def test_a_plane_steeper_than_a_road_is_no_estimate() -> None:
    assert ground_plane(_plane_scan(1.84, slope=(0.2, 0.0))) is None  # 11.3°: a ramp or a wall's foot
    assert ground_plane(_plane_scan(1.84, slope=(0.15, 0.0))) is not None  # 8.5°: a steep street


def test_no_estimate_without_ground_and_the_fallback_is_used() -> None:
    wall = np.column_stack([np.full(5000, 6.0), np.linspace(-10, 10, 5000), np.linspace(-1, 3, 5000),
                            np.zeros(5000)]).astype(np.float32)
    assert ground_height(wall) is None
    assert ground_height(np.zeros((0, 4), np.float32)) is None
    rng = np.random.default_rng(3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a stray return of 1e30 (or NaN) neither raises nor warns: it is out of range
        broken = np.concatenate([_plane_scan(1.84), rng.normal(0, 1e30, (500, 4)).astype(np.float32),
                                 np.full((500, 4), np.nan, np.float32)])
        assert ground_height(broken) == pytest.approx(1.84, abs=0.03)
    last = GroundPlane(2.0, 0.01, -0.02)  # a bare scan keeps what the one before measured
    assert scan_ground(wall, None, True, last) == last
    assert scan_ground(wall, None, False, last) == GroundPlane(2.0)
    assert scan_ground(wall, None, True) == GroundPlane(TRAINED_SENSOR_HEIGHT_M)  # before any: trained, level
    tilted = _plane_scan(1.3, slope=(0.03, 0.01))
    declared = scan_ground(tilted, 0.0, True, last)  # declared height: not measured, the slope is
    assert declared.height == 0.0 and declared.slope_x == pytest.approx(0.03, abs=0.003)
    assert scan_ground(tilted, 0.0, False, last) == GroundPlane(0.0)  # declared and level: nothing measured


def test_the_operator_is_told_once_a_spell_when_the_ground_says_the_frame_is_wrong() -> None:
    """No plane for 20 scans in a row (a frame with z not up), or one tilted past 5° for 20 (a turned mount): one
    warning each spell; a bare scan now and then, or the degree or two the detector levels, says nothing."""
    watch = GroundWatch(scans=20, tilt_deg=5.0)
    road, steep = GroundPlane(1.84, 0.02, -0.01), GroundPlane(1.84, np.tan(np.radians(7.0)), 0.0)
    said = [watch.observe(None if k % 10 == 9 else road) for k in range(99)]  # a bare scan every tenth
    assert said == [None] * 99
    said = [watch.observe(None) for _ in range(60)]
    assert [k for k, m in enumerate(said) if m] == [19] and "no road plane found under the last 20 scans" in said[19]
    said = [watch.observe(steep) for _ in range(45)]  # a new spell: told once, after 20 scans of it
    assert [k for k, m in enumerate(said) if m] == [19] and "tilted +7.0° along x" in said[19]
    assert watch.observe(road) is None and [watch.observe(None) for _ in range(20)][-1] is not None  # afresh


def test_the_detector_keeps_the_plane_it_measured_in_the_latest_scan() -> None:
    auto = Detector.load(None, "lite", threads=1)
    auto.detect(_plane_scan(1.6, slope=(0.03, 0.0)))
    assert auto.measures_ground and auto.plane_measured is not None
    assert auto.plane_measured.height == pytest.approx(1.6, abs=0.05)
    wall = np.column_stack([np.full(5000, 6.0), np.linspace(-10, 10, 5000), np.linspace(-1, 3, 5000),
                            np.zeros(5000)]).astype(np.float32)
    auto.detect(wall)
    assert auto.plane_measured is None and auto.ground_last.height == pytest.approx(1.6, abs=0.05)  # kept
    declared = Detector.load(None, "lite", threads=1, sensor_height_m=1.84, sensor_tilt=False)
    declared.detect(_plane_scan(1.6))
    assert not declared.measures_ground and declared.plane_measured is None  # nothing measured, nothing to tell


def test_the_trained_frame_moves_only_z_and_the_boxes_come_back() -> None:
    pts = _plane_scan(1.0, slope=(0.05, -0.03), n=200)
    ground = GroundPlane(1.0, 0.05, -0.03)
    out = to_trained_frame(pts, ground)
    want = pts[:, 2] - 0.05 * pts[:, 0] + 0.03 * pts[:, 1] + (1.0 - TRAINED_SENSOR_HEIGHT_M)
    np.testing.assert_allclose(out[:, 2], want, atol=1e-5)
    np.testing.assert_allclose(out[:, 2], -TRAINED_SENSOR_HEIGHT_M, atol=0.1)  # the road, level at the trained height
    np.testing.assert_array_equal(out[:, [0, 1, 3]], pts[:, [0, 1, 3]])
    assert not np.shares_memory(out, pts)
    level = GroundPlane(TRAINED_SENSOR_HEIGHT_M)
    assert to_trained_frame(pts, level) is pts  # nothing to move: no copy
    boxes = np.array([[10.0, -4.0, -1.0, 4.5, 1.9, 1.6, 0.3]])
    back = boxes_to_scan_frame(boxes, ground)
    np.testing.assert_allclose(back[0, 2], -1.0 + 0.05 * 10.0 - 0.03 * -4.0 - (1.0 - TRAINED_SENSOR_HEIGHT_M))
    np.testing.assert_array_equal(back[:, [0, 1, 3, 4, 5, 6]], boxes[:, [0, 1, 3, 4, 5, 6]])
    assert boxes_to_scan_frame(boxes, level) is boxes


@pytest.mark.parametrize("mount", [1.5, 1.84, 2.3])
def test_ray_cast_scans_from_other_mounts_are_measured_within_a_few_centimetres(mount: float) -> None:
    """The synthetic world's HDL-32E at three mounting heights, ideal scans of four scenarios: the median
    estimate is the mount within 3 cm, every one within 10 cm."""
    spec = dataclasses.replace(hdl32e(), mount_height_m=mount)
    scans = synthetic_samples(["parking-street", "diagonal-lot", "intersection", "mixed"], [1000],
                              frames_per_scenario=2, sensor=spec)
    est = np.array([ground_height(s.points) for s in scans])
    assert abs(np.median(est) - mount) < 0.03 and np.abs(est - mount).max() < 0.10, est


def test_a_lifted_scan_gives_the_same_boxes_lifted() -> None:
    """The same scan in the sensor's frame and in base_link (every point 1.84 m higher): with the height measured
    the network sees the same input, so the boxes are the same but for the lift; with the trained height declared
    it sees a world 1.84 m too high and finds little."""
    scan = next(iter(synthetic_samples(["parking-street"], [1001], frames_per_scenario=1))).points
    lifted = _lift(scan, 1.84)
    auto = Detector.load(None, "lite", threads=2)
    here, there = auto.detect(scan), auto.detect(lifted)
    assert auto.ground_last.height == pytest.approx(1.84 - 1.84, abs=0.05)
    assert len(here) >= 5 and len(there) == len(here)
    np.testing.assert_allclose(there.boxes[:, 2], here.boxes[:, 2] + 1.84, atol=1e-3)
    np.testing.assert_allclose(there.boxes[:, [0, 1, 3, 4, 5]], here.boxes[:, [0, 1, 3, 4, 5]], atol=1e-3)
    np.testing.assert_allclose(there.scores, here.scores, atol=1e-4)
    fixed = Detector.load(None, "lite", threads=2, sensor_height_m=TRAINED_SENSOR_HEIGHT_M)
    assert fixed.ground_last == GroundPlane(TRAINED_SENSOR_HEIGHT_M)
    blind = fixed.detect(lifted)
    found, kept = here.boxes[here.scores >= 0.5, :2], blind.boxes[blind.scores >= 0.5, :2]
    gap = np.hypot(*(found[:, None, :] - kept[None, :, :]).transpose(2, 0, 1)) if len(kept) else np.full((len(found), 1), 99.0)
    assert len(found) >= 10 and (gap.min(axis=1) < 1.0).sum() < len(found) / 3  # most of its confident objects lost
    declared = Detector.load(None, "lite", threads=2, sensor_height_m=0.0)  # base_link, declared
    np.testing.assert_allclose(declared.detect(lifted).boxes[:, 2], fixed.detect(scan).boxes[:, 2] + 1.84, atol=1e-3)


@pytest.mark.parametrize("pitch, roll", [(2.0, 0.0), (-2.0, 0.0), (0.0, 2.0)])
def test_a_pitched_or_rolled_scan_gives_the_level_scans_boxes(pitch: float, roll: float) -> None:
    """One synthetic scan seen from a frame turned by 2°: with the tilt measured the network sees (nearly) the
    level scan — every confident object found again within 0.3 m, at its height; with the frame taken as level the
    road ahead climbs or falls 1 m over 30 m and the network loses objects."""
    scan = next(iter(synthetic_samples(["mixed"], [1002], frames_per_scenario=1))).points
    turned, turn = _turn(scan, pitch, roll)
    auto = Detector.load(None, "lite", threads=2)
    here = auto.detect(scan)
    there = auto.detect(turned)
    slope = np.degrees(np.arctan([auto.ground_last.slope_x, auto.ground_last.slope_y]))
    np.testing.assert_allclose(slope, [-pitch, roll], atol=0.3)  # the frame's turn, read off the road
    found = here.boxes[here.scores >= 0.5]
    back = there.boxes[there.scores >= 0.3, :3] @ turn  # into the level frame (the inverse turn of row vectors)
    assert len(found) >= 8
    gap = np.hypot(*(found[:, None, :2] - back[None, :, :2]).transpose(2, 0, 1))
    assert (gap.min(axis=1) < 0.3).all()  # every confident object of the level scan, found confidently again
    np.testing.assert_allclose(back[gap.argmin(axis=1), 2], found[:, 2], atol=0.15)
    level = Detector.load(None, "lite", threads=2, sensor_tilt=False)
    blind = level.detect(turned)
    kept = blind.boxes[blind.scores >= 0.3, :3] @ turn
    lost = np.hypot(*(found[:, None, :2] - kept[None, :, :2]).transpose(2, 0, 1)).min(axis=1) >= 0.3 if len(kept) \
        else np.ones(len(found), bool)
    assert lost.sum() >= 1  # (in this scan: the taken-as-level frame loses or moves some of them)


def test_a_training_sample_is_levelled_labels_and_all() -> None:
    """``train --level-scans``: a sample from a frame pitched 2° is moved as the detector moves scans at inference;
    its road is level at the trained height and each box still stands on it (its centre as high above the road
    as in the unturned sample), and the boxes move back to where they were."""
    from jitterguard.services.detector.train_cli import _Prepared

    sample = next(iter(synthetic_samples(["parking-street"], [1003], frames_per_scenario=1)))
    turned, turn = _turn(sample.points, 2.0, 0.0)
    boxes = sample.boxes.copy()
    boxes[:, :3] = boxes[:, :3] @ turn.T
    tilted = dataclasses.replace(sample, points=turned, boxes=boxes)
    pcr = Detector.load(None, "lite", threads=1).config.point_cloud_range
    flat = _Prepared([tilted], pcr, level=True)[0]
    plane = ground_plane(flat.points)
    assert plane is not None and abs(plane.slope_deg[0]) < 0.1 and plane.height == pytest.approx(1.84, abs=0.03)
    plain = _Prepared([sample], pcr)[0]  # the unturned sample, as the synthetic world cast it
    assert len(flat.boxes) == len(plain.boxes) > 3
    np.testing.assert_allclose(flat.boxes[:, 2], plain.boxes[:, 2], atol=0.15)  # on the road as before
    ground = scan_ground(turned, None, True)
    np.testing.assert_allclose(boxes_to_scan_frame(boxes_to_trained_frame(boxes, ground), ground), boxes, atol=1e-5)
    assert _Prepared([tilted], pcr)[0].points[:, 2].tolist() == turned[
        _in_grid(turned, pcr), 2].tolist()  # without level the view moves nothing


def _in_grid(points: np.ndarray, pcr) -> np.ndarray:
    x0, y0, z0, x1, y1, z1 = pcr
    p = points
    return (p[:, 0] >= x0) & (p[:, 0] < x1) & (p[:, 1] >= y0) & (p[:, 1] < y1) & (p[:, 2] >= z0) & (p[:, 2] < z1)


@pytest.mark.skipif(not NUSC.is_dir(), reason="../shared/data/nuscenes-scene-0523 absent")
def test_the_real_scenes_scans_sit_at_their_calibrated_mount() -> None:
    """scene-0523's LIDAR_TOP is mounted 1.84 m up (calibrated_sensor); the road under a real street's car is
    not a plane, so the estimates spread, but within 15 cm of the mount."""
    from jitterguard.services.detector.data import nuscenes_samples

    est = np.array([ground_height(s.points) for s in nuscenes_samples(NUSC)])
    assert len(est) == 40 and np.abs(est - 1.84).max() < 0.15 and abs(np.median(est) - 1.84) < 0.08, est


def test_config_and_flag_values() -> None:
    assert DetectorParams().sensor_height_m == "auto" and declared_height("auto") is None
    assert DetectorParams().sensor_tilt == "auto" and measures_tilt(None) and not measures_tilt("level")
    with pytest.raises(ValidationError, match="sensor_tilt"):
        DetectorParams.model_validate({"sensor_tilt": "pitched"})
    assert declared_height(None) is None  # not given: the service's default, auto
    assert DetectorParams.model_validate({"sensor_height_m": 0}).sensor_height_m == 0.0  # YAML's 0: base_link
    assert declared_height(DetectorParams(sensor_height_m=1.95).sensor_height_m) == 1.95
    for bad in (184, -3.0, "tall", float("nan"), True):
        with pytest.raises(ValidationError, match="sensor_height_m"):
            DetectorParams.model_validate({"sensor_height_m": bad})
    assert parse_sensor_height(" AUTO ") == "auto" and parse_sensor_height("0") == 0.0
    for bad in ("184", "nan", "inf", "", "1.8m"):
        with pytest.raises(ValueError, match="expected 'auto' or a height in metres"):
            parse_sensor_height(bad)
