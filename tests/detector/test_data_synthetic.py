"""Synthetic training samples and the sample cache: sensor-frame boxes sit on the scan's points, the cache
round-trips exactly."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from jitterguard.services.detector.augment import points_in_boxes
from jitterguard.services.detector.config import AUTOWARE_TO_CLASS, Sample
from jitterguard.services.detector.data import (
    CachedSamples,
    build_cache,
    frame_to_sensor_boxes,
    sample_from_scan,
    spread_indices,
    synthetic_samples,
)
from jitterguard.sim.lidar import cast_frame
from jitterguard.sim.sensors import hdl32e
from jitterguard.sim.world import make_scenario

MOUNT = hdl32e().mount_height_m


@pytest.fixture(scope="module")
def scenario():
    return make_scenario("mixed", seed=3, duration_s=12.0)


def _turning_frames(scenario, k=4):
    """Frames whose ego heading differs from the world axes (so a missing rotation would show)."""
    frames = [scenario.frame(i) for i in spread_indices(len(scenario), 12)]
    picked = [f for f in frames if abs(math.sin(f.ego_yaw)) > 0.2][:k]
    return picked or frames[:k]


def test_points_of_an_object_lie_inside_its_sensor_frame_box(scenario) -> None:
    checked = 0
    for frame in _turning_frames(scenario):
        scan, frame = cast_frame(frame, hdl32e(), seed=1)
        boxes, _ = frame_to_sensor_boxes(frame, MOUNT)
        for row in np.flatnonzero(scan.num_points >= 5):
            own = scan.points[scan.owner == row]
            inside = points_in_boxes(own, boxes[row:row + 1], margin=0.1)[:, 0]
            assert inside.all(), f"row {row}: {np.count_nonzero(~inside)} of {len(own)} points outside"
            # and the box is tight: the points' centroid is near the box centre in BEV
            assert np.hypot(*(own[:, :2].mean(0) - boxes[row, :2])) < max(boxes[row, 3], boxes[row, 4])
            checked += 1
    assert checked > 20


def test_conversion_is_the_inverse_of_the_ego_pose(scenario) -> None:
    frame = _turning_frames(scenario, 1)[0]
    boxes, labels = frame_to_sensor_boxes(frame, MOUNT)
    c, s = math.cos(frame.ego_yaw), math.sin(frame.ego_yaw)
    x, y = boxes[:, 0].astype(float), boxes[:, 1].astype(float)
    np.testing.assert_allclose(frame.ego_x + c * x - s * y, frame.centers[:, 0], atol=1e-3)
    np.testing.assert_allclose(frame.ego_y + s * x + c * y, frame.centers[:, 1], atol=1e-3)
    # objects stand on the ground: bottom at -mount height in the sensor frame
    np.testing.assert_allclose(boxes[:, 2] - boxes[:, 5] / 2, -MOUNT, atol=1e-5)
    # absolute (not ego-relative) velocity, rotated: same speed, world direction recovered
    vx, vy = boxes[:, 7].astype(float), boxes[:, 8].astype(float)
    np.testing.assert_allclose(c * vx - s * vy, frame.velocities[:, 0], atol=1e-4)
    np.testing.assert_allclose(s * vx + c * vy, frame.velocities[:, 1], atol=1e-4)
    yaw_world = np.angle(np.exp(1j * (boxes[:, 6] + frame.ego_yaw)))
    np.testing.assert_allclose(np.cos(yaw_world - frame.yaws), 1.0, atol=1e-6)
    expect = [AUTOWARE_TO_CLASS.get(int(v), -1) for v in frame.labels]
    assert labels.tolist() == expect


def test_synthetic_samples_drop_unmapped_labels_and_spread_frames() -> None:
    samples = list(synthetic_samples(["mixed"], [3], frames_per_scenario=4, duration_s=12.0, scan_seed=1))
    assert [s.token for s in samples] == [f"synthetic/mixed/3/{i}" for i in spread_indices(120, 4)]
    assert spread_indices(120, 4) == [0, 40, 79, 119]
    sc = make_scenario("mixed", seed=3, duration_s=12.0)
    scan, frame = cast_frame(sc.frame(40), hdl32e(), seed=1)
    ref = sample_from_scan(frame, scan, MOUNT)
    s = samples[1]
    np.testing.assert_array_equal(s.points, scan.points)
    np.testing.assert_array_equal(s.boxes, ref.boxes)
    assert s.labels.min() >= 0 and s.labels.max() < 5
    assert len(s.boxes) == frame.num_objects  # the synthetic world only holds detector classes ...
    labels = frame.labels.copy()
    labels[::3] = 0  # ... so make some UNKNOWN: they are dropped with their rows
    dropped = sample_from_scan(replace(frame, labels=labels), scan, MOUNT)
    keep = labels != 0
    np.testing.assert_array_equal(dropped.boxes, ref.boxes[keep])
    np.testing.assert_array_equal(dropped.num_points, scan.num_points[keep])
    assert s.num_points.sum() > 0 and s.points.dtype == np.float32 and s.boxes.dtype == np.float32
    assert s.points.shape[1] == 4 and s.boxes.shape[1] == 9


def test_spread_indices_edges() -> None:
    assert spread_indices(5, 10) == [0, 1, 2, 3, 4]
    assert spread_indices(5, 0) == []
    assert spread_indices(100, 1) == [0]


def test_cache_round_trips_exactly(tmp_path: Path) -> None:
    samples = list(synthetic_samples(["parking-street", "intersection"], [0], frames_per_scenario=2, duration_s=6.0))
    empty = Sample(np.zeros((3, 4), np.float32), np.zeros((0, 9), np.float32), np.zeros(0, np.int64),
                   np.zeros(0, np.int64), "empty")
    samples.append(empty)
    n = build_cache(tmp_path / "c", iter(samples), progress=False, meta={"why": "test"})
    assert n == len(samples) == 5
    cache = CachedSamples(tmp_path / "c")
    assert len(cache) == 5 and cache.meta == {"why": "test"}
    assert cache.tokens == [s.token for s in samples]
    for i in (3, 0, 4, 1, 2):  # random access
        a, b = samples[i], cache[i]
        assert a.token == b.token
        for f in ("points", "boxes", "labels", "num_points"):
            x, y = getattr(a, f), getattr(b, f)
            assert x.dtype == y.dtype and x.shape == y.shape
            np.testing.assert_array_equal(x, y)
    assert [s.token for s in cache[1:3]] == [samples[1].token, samples[2].token]
    assert cache[-1].token == "empty"


def test_interrupted_cache_is_refused(tmp_path: Path) -> None:
    def broken():
        yield from synthetic_samples(["parking-street"], [0], frames_per_scenario=1, duration_s=4.0)
        raise RuntimeError("killed")

    with pytest.raises(RuntimeError):
        build_cache(tmp_path, broken(), progress=False)
    with pytest.raises(FileNotFoundError, match="index.json"):
        CachedSamples(tmp_path)


def test_parallel_casting_gives_the_same_samples_in_the_same_order() -> None:
    """Casting in worker processes is only a speed-up: every scan, box and token equals the serial cast's, in
    the same order (each (scenario, seed) pair is seeded on its own, so which process casts it cannot matter)."""
    kw = dict(frames_per_scenario=2, duration_s=2.0, effects="random,vegetation")
    serial = list(synthetic_samples(["mixed", "diagonal-lot"], [3, 4], **kw))
    parallel = list(synthetic_samples(["mixed", "diagonal-lot"], [3, 4], workers=2, **kw))
    assert [s.token for s in parallel] == [s.token for s in serial]
    assert len({s.token.split("/")[1] for s in serial}) == 2 and len(serial) == 8
    for a, b in zip(serial, parallel):
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_array_equal(a.boxes, b.boxes)
        np.testing.assert_array_equal(a.labels, b.labels)


def test_stacked_synthetic_samples_carry_earlier_sweeps_with_their_lags() -> None:
    """``sweeps``: five point fields; the newest sweep at lag 0, the others a whole number of 50 ms spins back,
    evenly spaced and within 0.5 s; a static world lands where the newest sweep sees it; deterministic."""
    from scipy.spatial import cKDTree

    kw = dict(frames_per_scenario=4, duration_s=10.0, effects="ground,clutter,noise")
    two = list(synthetic_samples(["mixed"], [3], sweeps=2, **kw))
    again = list(synthetic_samples(["mixed"], [3], sweeps=2, **kw))
    assert [s.token for s in two] == [s.token for s in again]
    for a, b in zip(two, again):
        np.testing.assert_array_equal(a.points, b.points)
    steps = set()
    for s in two:
        assert s.points.shape[1] == 5
        lags = np.unique(np.round(s.points[:, 4].astype(np.float64), 4))
        assert lags[0] == 0.0 and len(lags) <= 2
        if len(lags) == 2:
            k = lags[1] / 0.05
            assert abs(k - round(k)) < 1e-3 and 1 <= round(k) <= 10
            steps.add(round(k))
            key, earlier = s.points[s.points[:, 4] == 0, :3], s.points[s.points[:, 4] > 0, :3]
            # most returns of the earlier sweep (ground, buildings, clutter, parked cars) meet the newest's
            assert np.median(cKDTree(key).query(earlier)[0]) < 0.3
    assert len(steps) >= 2  # the spacing is drawn per sample
    ten = list(synthetic_samples(["mixed"], [3], sweeps=10, **kw))
    full = [np.unique(np.round(s.points[:, 4].astype(np.float64), 4)) for s in ten]
    assert any(len(lags) == 10 for lags in full)
    for lags in full:
        np.testing.assert_allclose(lags, 0.05 * np.arange(len(lags)), atol=1e-4)  # 20 Hz, one spin apart
    with pytest.raises(ValueError, match="sweeps"):
        next(synthetic_samples(["mixed"], [3], sweeps=0, **kw))
