"""Augmentations move points, boxes, yaws and velocities consistently."""

from __future__ import annotations

import math

import numpy as np
import pytest

from jitterguard.services.detector.augment import (
    bev_overlaps,
    build_gt_database,
    drop_empty,
    filter_range,
    flip_x,
    flip_y,
    global_rotate,
    global_scale,
    gt_sample,
    points_in_boxes,
    random_augment,
)
from jitterguard.services.detector.config import LITE, Sample
from jitterguard.services.detector.data import synthetic_samples


@pytest.fixture(scope="module")
def samples() -> list[Sample]:
    return list(synthetic_samples(["mixed", "intersection"], [5], frames_per_scenario=2, duration_s=10.0))


def _inside_counts(s: Sample) -> np.ndarray:
    return points_in_boxes(s.points, s.boxes).sum(axis=0)


def _heading(b: np.ndarray) -> np.ndarray:
    """Unit heading vectors of boxes (yaw compared without wrap-around trouble)."""
    return np.stack([np.cos(b[:, 6]), np.sin(b[:, 6])], 1)


def _assert_same(a: Sample, b: Sample, atol: float = 1e-4) -> None:
    np.testing.assert_allclose(a.points, b.points, atol=atol)
    np.testing.assert_allclose(np.delete(a.boxes, 6, 1), np.delete(b.boxes, 6, 1), atol=atol)
    np.testing.assert_allclose(_heading(a.boxes), _heading(b.boxes), atol=atol)


@pytest.mark.parametrize("op", [flip_x, flip_y, lambda s: global_rotate(s, 0.7), lambda s: global_scale(s, 1.04),
                                lambda s: random_augment(s, np.random.default_rng(3))])
def test_points_stay_inside_their_boxes(samples: list[Sample], op) -> None:
    for s in samples:
        before = _inside_counts(s)
        assert before.sum() > 100
        after = _inside_counts(op(s))
        # float32 rounding can move a point that sat exactly on a face; nothing more
        assert np.abs(after - before).max() <= 1


def test_flips_are_involutions(samples: list[Sample]) -> None:
    s = samples[0]
    for flip in (flip_x, flip_y):
        _assert_same(flip(flip(s)), s, atol=1e-6)
        assert not np.allclose(flip(s).points, s.points)
    _assert_same(flip_x(flip_y(s)), global_rotate(s, math.pi))  # two mirrors = half turn


def test_flip_mirrors_heading_and_velocity() -> None:
    # a car at (10, 5) heading 30° and driving along its heading at 4 m/s
    yaw = math.radians(30)
    box = np.array([[10, 5, -1, 4, 2, 1.5, yaw, 4 * math.cos(yaw), 4 * math.sin(yaw)]], np.float32)
    s = Sample(np.zeros((0, 4), np.float32), box, np.zeros(1, np.int64), np.zeros(1, np.int64))
    fx, fy = flip_x(s).boxes[0], flip_y(s).boxes[0]
    np.testing.assert_allclose(fx[[0, 1, 6]], [10, -5, -yaw], atol=1e-6)
    np.testing.assert_allclose(fy[[0, 1, 6]], [-10, 5, math.pi - yaw], atol=1e-6)
    for b in (fx, fy):  # still driving along its heading
        np.testing.assert_allclose(b[7:9], 4 * np.array([math.cos(b[6]), math.sin(b[6])]), atol=1e-5)


def test_rotation_preserves_distances_and_composes(samples: list[Sample]) -> None:
    s = samples[1]
    r = global_rotate(s, 1.1)
    np.testing.assert_allclose(np.linalg.norm(r.points[:, :3], axis=1), np.linalg.norm(s.points[:, :3], axis=1),
                               rtol=1e-5)
    np.testing.assert_allclose(np.hypot(r.boxes[:, 7], r.boxes[:, 8]), np.hypot(s.boxes[:, 7], s.boxes[:, 8]),
                               atol=1e-5)
    np.testing.assert_array_equal(r.points[:, 2:], s.points[:, 2:])
    _assert_same(global_rotate(r, -1.1), s)
    # velocity keeps its angle to the heading
    rel = lambda b: np.arctan2(b[:, 8], b[:, 7]) - b[:, 6]  # noqa: E731
    moving = np.hypot(s.boxes[:, 7], s.boxes[:, 8]) > 0.5
    assert moving.any()
    np.testing.assert_allclose(np.cos(rel(r.boxes)[moving] - rel(s.boxes)[moving]), 1.0, atol=1e-6)


def test_scale(samples: list[Sample]) -> None:
    s = samples[0]
    g = global_scale(s, 1.05)
    np.testing.assert_allclose(g.points[:, :3], s.points[:, :3] * 1.05, rtol=1e-6)
    np.testing.assert_array_equal(g.points[:, 3], s.points[:, 3])
    np.testing.assert_allclose(g.boxes[:, 3:6], s.boxes[:, 3:6] * 1.05, rtol=1e-6)
    np.testing.assert_array_equal(g.boxes[:, 6], s.boxes[:, 6])
    with pytest.raises(ValueError):
        global_scale(s, 0.0)


def test_random_augment_is_seeded_and_within_ranges(samples: list[Sample]) -> None:
    s = samples[0]
    a = random_augment(s, np.random.default_rng(11))
    b = random_augment(s, np.random.default_rng(11))
    np.testing.assert_array_equal(a.points, b.points)
    factors = []
    for seed in range(20):
        out = random_augment(s, np.random.default_rng(seed))
        factors.append(np.linalg.norm(out.points[:, :3], axis=1).sum() / np.linalg.norm(s.points[:, :3], axis=1).sum())
    assert 0.95 - 1e-6 <= min(factors) < max(factors) <= 1.05 + 1e-6
    same = random_augment(s, np.random.default_rng(0), rotation=(0.0, 0.0), scale=(1.0, 1.0), flip_x_prob=0,
                          flip_y_prob=0)
    np.testing.assert_array_equal(same.points, s.points)


def test_filter_range_and_drop_empty(samples: list[Sample]) -> None:
    s = samples[0]
    r = LITE.point_cloud_range
    f = filter_range(s, r)
    assert 0 < len(f.points) < len(s.points) and 0 < len(f.boxes) < len(s.boxes)
    assert (np.abs(f.points[:, :2]) < 51.2).all() and (np.abs(f.boxes[:, :2]) < 51.2).all()
    assert ((f.points[:, 2] >= -3) & (f.points[:, 2] < 3)).all()
    assert len(f.labels) == len(f.num_points) == len(f.boxes)
    d = drop_empty(s, 1)
    assert (d.num_points >= 1).all() and len(d.boxes) == np.count_nonzero(s.num_points >= 1)


def test_bev_overlaps() -> None:
    a = np.array([[0, 0, 0, 4, 2, 1, 0, 0, 0]], float)
    b = np.array([[3.9, 0, 0, 4, 2, 1, 0, 0, 0],       # overlaps by 0.1 m along x
                  [4.1, 0, 0, 4, 2, 1, 0, 0, 0],       # 0.1 m gap
                  [2.5, 2.5, 0, 4, 2, 1, math.pi / 4, 0, 0],  # rotated: its corner reaches into a ...
                  [3.2, 3.2, 0, 4, 2, 1, math.pi / 4, 0, 0]], float)  # ... and here it does not
    assert bev_overlaps(a, b)[0].tolist() == [True, False, True, False]


def test_gt_sampling_pastes_without_overlap(samples: list[Sample]) -> None:
    db = build_gt_database(samples[1:], min_points=5)
    assert len(db) > 20 and set(db.labels.tolist()) >= {0, 4}
    s = samples[0]
    out = gt_sample(s, db, np.random.default_rng(0), counts=(4, 2, 2, 4, 4))
    added = len(out.boxes) - len(s.boxes)
    assert added > 0
    np.testing.assert_array_equal(out.boxes[:len(s.boxes)], s.boxes)
    ov = bev_overlaps(out.boxes, out.boxes)
    np.fill_diagonal(ov, False)
    assert not ov[len(s.boxes):].any()  # pasted boxes overlap nothing
    # each pasted box holds exactly its database points, and the scene's points there are gone
    new = out.boxes[len(s.boxes):]
    inside = points_in_boxes(out.points, new).sum(0)
    np.testing.assert_array_equal(inside, out.num_points[len(s.boxes):])
    # pasting from a database of the sample's own objects adds nothing (they all overlap themselves)
    own = build_gt_database([s])
    same = gt_sample(s, own, np.random.default_rng(0), counts=(50,) * 5)
    assert len(same.boxes) == len(s.boxes)
    # a class counted 0 is never pasted, whatever the draw; the others still are
    for seed in range(5):
        no_ped = gt_sample(s, db, np.random.default_rng(seed), counts=(4, 2, 2, 4, 0))
        pasted = no_ped.labels[len(s.labels):]
        assert len(pasted) > 0 and not (pasted == 4).any()


def test_train_augment_rotates_within_its_range_and_tilts_points_with_boxes(samples: list[Sample]) -> None:
    import math

    import dataclasses

    from jitterguard.services.detector.augment import TrainAugment, global_tilt

    s = samples[0]
    centres = np.column_stack([s.boxes[:, :3], np.zeros(len(s.boxes))]).astype(np.float32)
    with_centres = dataclasses.replace(s, points=np.concatenate([s.points, centres]))
    t = global_tilt(with_centres, math.radians(3.0), math.radians(-2.0), 0.2)
    np.testing.assert_allclose(t.points[len(s.points):, :3], t.boxes[:, :3], atol=1e-4)  # centres move as points
    np.testing.assert_allclose(t.boxes[:, 3:7], s.boxes[:, 3:7])  # sizes and yaw kept (boxes stay upright)
    t = global_tilt(s, math.radians(3.0), math.radians(-2.0), 0.2)
    np.testing.assert_allclose(np.linalg.norm(t.points[:, :3] - [0, 0, 0.2], axis=1),
                               np.linalg.norm(s.points[:, :3], axis=1), rtol=1e-5)
    yaws = []
    for seed in range(40):
        a = TrainAugment(rotation_deg=180.0, tilt_deg=1.0)(s, np.random.default_rng(seed))
        assert len(a.points) == len(s.points)
        yaws.append(float(a.boxes[0, 6]))
    assert np.ptp(yaws) > 4.0  # full turns, not ±45°
    same = TrainAugment(0.0, 0.0)(s, np.random.default_rng(1))
    assert same.points.shape == s.points.shape


def test_train_augment_with_a_database_pastes_objects_before_the_global_transform(samples: list[Sample]) -> None:
    import pickle

    from jitterguard.services.detector.augment import TrainAugment

    db = build_gt_database(samples[1:], min_points=5)
    plain, pasting = TrainAugment(rotation_deg=0.0), TrainAugment(rotation_deg=0.0, gt_db=db)
    s = samples[0]
    a, b = plain(s, np.random.default_rng(3)), pasting(s, np.random.default_rng(3))
    added = len(b.boxes) - len(a.boxes)
    assert added > 0 and len(a.boxes) == len(s.boxes)
    # the pasted boxes went through the same flips and scale as the scene's: their points are still inside
    np.testing.assert_array_equal(points_in_boxes(b.points, b.boxes[-added:]).sum(0), b.num_points[-added:])
    # a DataLoader worker gets a copy that pastes the same objects
    again = pickle.loads(pickle.dumps(pasting))(s, np.random.default_rng(3))
    np.testing.assert_array_equal(again.boxes, b.boxes)
