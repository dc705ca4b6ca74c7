"""The tracker core fed what a broken detector or pose source produces: non-finite numbers, absurd variances,
classes it does not know, exact duplicates. Such detections must neither crash it, nor reach its outputs as NaN,
nor cost the well-formed detections of the same frame their tracks."""

from __future__ import annotations

import numpy as np
import pytest

from jitterguard.services.tracker.arrays import DetectionFrame, FrameResult
from jitterguard.services.tracker.core import TrackerCore

T0 = 1_700_000_000_000_000_000
GOOD = (30.0, -3.0)  # a parked car, detected cleanly every frame


def frame(seq: int, x, y, *, ego=(0.0, 0.0, 0.0), **cols) -> DetectionFrame:
    """Cars at sensor-frame (x, y) with a 0.2 m σ of their own, 10 Hz; ``cols`` per detection (broadcast)."""
    x, y = np.atleast_1d(np.asarray(x, dtype=float)), np.atleast_1d(np.asarray(y, dtype=float))
    m = x.size
    base = dict(label=1, has_cov=True, cov_xx=0.04, cov_xy=0.0, cov_yy=0.04, yaw=0.0)
    c = {k: np.broadcast_to(np.asarray(v), (m,)).copy() for k, v in {**base, **cols}.items()}
    return DetectionFrame(seq=seq, stamp_ns=T0 + seq * 100_000_000, ego_x=ego[0], ego_y=ego[1], ego_yaw=ego[2],
                          x=x, y=y, **c)


def assert_finite(res: FrameResult) -> None:
    for snap in (res.tracks, res.tentative):
        for name in ("x", "y", "z", "yaw", "pose_cov", "vel", "vel_cov", "yaw_rate", "yaw_rate_var", "dims",
                     "existence", "label_prob"):
            assert np.isfinite(getattr(snap, name)).all(), name


def run(frames) -> tuple[TrackerCore, list[FrameResult]]:
    core = TrackerCore()
    out = []
    for f in frames:
        res = core.step(f)
        assert_finite(res)
        out.append(res)
    return core, out


def the_good_track(core: TrackerCore, results: list[FrameResult]) -> str:
    """The one confirmed track at GOOD, the same ID in every frame from the third on."""
    ids = set()
    for res in results[2:]:
        near = np.hypot(res.tracks.x - GOOD[0], res.tracks.y - GOOD[1]) < 1.0
        assert near.sum() == 1
        ids.add(res.tracks.ids[int(np.flatnonzero(near)[0])])
    assert len(ids) == 1
    assert len(core.tracks) == 1  # nothing else: no twin, no track of the broken detection
    return ids.pop()


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_a_non_finite_detection_neither_starts_a_track_nor_costs_the_others_theirs(bad: float) -> None:
    # a NaN track had poisoned the sweep of every gate: the good detection got a new tentative track every frame
    core, results = run(frame(s, [bad, GOOD[0]], [5.0, GOOD[1]]) for s in range(8))
    the_good_track(core, results)


@pytest.mark.parametrize("cols", [
    dict(cov_xx=np.nan), dict(cov_xy=np.inf), dict(cov_yy=-np.inf), dict(var_yaw=np.inf), dict(yaw=np.nan),
    dict(yaw=np.inf), dict(vx=np.nan, vy=0.0, has_twist=True), dict(label_prob=np.nan), dict(existence=np.inf),
], ids=lambda c: ",".join(f"{k}={v}" for k, v in c.items()))
def test_broken_columns_of_a_detection_fall_back_and_the_object_is_tracked(cols: dict) -> None:
    core, results = run(frame(s, GOOD[0], GOOD[1], **cols) for s in range(8))
    the_good_track(core, results)


@pytest.mark.parametrize("cols", [dict(z=np.nan), dict(length=np.nan), dict(height=np.inf), dict(area=np.nan),
                                  dict(width=1e30), dict(length=-4.5, width=-1.9, height=-1.6, area=8.55)],
                         ids=lambda c: ",".join(c))
def test_a_detection_without_a_finite_box_is_not_taken(cols: dict) -> None:
    # a NaN height or size had stayed in its track's running estimate for good (and gone out as NaN); a box all of
    # whose sides were negative had a positive area and was tracked and published with its negative sizes
    good = dict(z=0.0, length=4.5, width=1.9, height=1.6, area=4.5 * 1.9)
    core, results = run(frame(s, [GOOD[0], 10.0], [GOOD[1], 5.0], **{k: [good[k], v] for k, v in cols.items()})
                        for s in range(8))
    the_good_track(core, results)


def test_a_class_the_tracker_does_not_know_is_unknown() -> None:
    # label 9 had raised IndexError; -1 had indexed the last class (a pedestrian)
    for label in (9, -1, 127):
        core, results = run(frame(s, GOOD[0], GOOD[1], label=label) for s in range(5))
        assert results[-1].tracks.label.tolist() == [0]


def test_a_detection_reporting_a_huge_variance_is_still_tracked() -> None:
    # σ² of 1e6 m² (the wire's bound) had started a track that the next frame deleted past max_position_stddev,
    # having taken its detection: the object was never tracked and had a new ID every other frame
    for var in (1e6, 1e30):
        core, results = run(frame(s, GOOD[0], GOOD[1], cov_xx=var, cov_yy=var) for s in range(8))
        the_good_track(core, results)


def test_exact_duplicates_of_a_detection_make_one_track() -> None:
    # more copies than max_candidates had left that many confirmed tracks of one object and ~100 new IDs a frame
    n = 100
    core, results = run(frame(s, np.full(n, GOOD[0]), np.full(n, GOOD[1])) for s in range(8))
    the_good_track(core, results)
    assert sum(len(r.born) for r in results) == 1


def test_a_frame_with_a_broken_ego_pose_is_coasted_through() -> None:
    core = TrackerCore()
    for s in range(5):
        core.step(frame(s, GOOD[0], GOOD[1]))
    tid = core.tracks.ids[0]
    for ego in ((np.nan, 0.0, 0.0), (0.0, 0.0, np.inf)):
        s += 1
        res = core.step(frame(s, GOOD[0], GOOD[1], ego=ego))
        assert_finite(res)
        assert res.born == [] and res.obs_track.size == 0
    for _ in range(3):
        s += 1
        res = core.step(frame(s, GOOD[0], GOOD[1]))
    assert res.tracks.ids == [tid] and res.obs_track.tolist() == [0]


def test_a_position_beyond_what_readers_accept_is_not_tracked() -> None:
    bound = TrackerCore().config.limits.max_abs_coordinate_m
    core, results = run(frame(s, [GOOD[0], 2.0 * bound], [GOOD[1], 0.0]) for s in range(8))
    the_good_track(core, results)


def test_a_filter_whose_state_went_non_finite_is_deleted() -> None:
    core = TrackerCore()
    for s in range(5):
        core.step(frame(s, [GOOD[0], 10.0], [GOOD[1], 5.0]))
    broken = core.tracks.ids[1]
    core.tracks.P[1, 0, 0] = np.nan  # whatever the arithmetic: nothing brings such a filter back
    res = core.step(frame(5, [GOOD[0], 10.0], [GOOD[1], 5.0]))
    assert broken in res.deleted
    assert_finite(res)


def test_a_non_finite_filter_does_not_hide_the_overlaps_of_the_others() -> None:
    core = TrackerCore()
    for s in range(4):
        core.step(frame(s, [GOOD[0], 10.0], [GOOD[1], 5.0]))
    # a second box half a metre off the good car starts a twin of its track
    res = core.step(frame(4, [GOOD[0], GOOD[0] + 0.5, 10.0], [GOOD[1], GOOD[1], 5.0]))
    (twin,) = res.born
    core.tracks.x[1, :2] = np.nan  # the other car's filter breaks
    res = core.step(frame(5, [GOOD[0], GOOD[0] + 0.5, 10.0], [GOOD[1], GOOD[1], 5.0]))
    assert twin in res.deleted  # NaN in the overlap sweep had hidden every overlap of the frame


def test_a_height_the_readers_refuse_in_the_world_is_not_tracked() -> None:
    """The wire bounds a detection's z and the ego pose's z each by ``max_abs_coordinate_m``, but the world z the
    tracker publishes is their sum: a box at 0.6 of the bound under an ego pose at 0.6 of it had been tracked and
    published, and the classifier refused every ``tracked`` frame it was in (its objects all went unclassified)
    for as long as the track lived."""
    from jitterguard.schemas import encode, read_detected_objects, read_tracked_objects
    from jitterguard.schemas.models import (X_X, Y_Y, DetectedObject, DetectedObjectKinematics, DetectedObjects,
                                            Header, ObjectClassification, Point, Pose, PoseWithCovariance,
                                            Quaternion, Shape, Vector3)
    from jitterguard.services.tracker.adapter import detection_frame, tracked_payload

    core = TrackerCore()
    high = 0.6 * core.config.limits.max_abs_coordinate_m
    cov = [0.0] * 36
    cov[X_X] = cov[Y_Y] = 0.04

    def box(x: float, y: float, z: float) -> DetectedObject:
        pose = Pose(position=Point(x=x, y=y, z=z), orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))
        return DetectedObject(classification=[ObjectClassification(label=1, probability=0.9)],
                              kinematics=DetectedObjectKinematics(
                                  pose_with_covariance=PoseWithCovariance(pose=pose, covariance=cov),
                                  has_position_covariance=True),
                              shape=Shape(type=0, dimensions=Vector3(x=4.5, y=1.9, z=1.6)))

    for s in range(6):
        msg = DetectedObjects(header=Header(stamp=T0 + s * 100_000_000, frame_id="lidar", seq=s),
                              ego_pose=Pose(position=Point(x=0.0, y=0.0, z=high),
                                            orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
                              objects=[box(GOOD[0], GOOD[1], 0.5 - high), box(10.0, 8.0, high)])
        cols = read_detected_objects(encode(msg))  # the wire takes it: each z is within the bound
        f = detection_frame(cols)
        res = core.step(f)
        tracked = read_tracked_objects(tracked_payload(cols, f, res))  # the classifier's reader
    assert len(tracked.objects) == 1 and res.tracks.z[0] == pytest.approx(0.5)
    assert len(core.tracks) == 1
