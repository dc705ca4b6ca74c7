"""Tracker core behaviour: crossing, merging, occlusion, birth and death, IDs, frame order, frames of reference."""

from __future__ import annotations

import math
import re
from collections import defaultdict

import numpy as np
import pytest

from jitterguard.geometry import rotate_cov2
from jitterguard.services.tracker.config import default_config
from jitterguard.services.tracker.core import FrameRejected, TrackerCore
from jitterguard.services.tracker.arrays import DetectionFrame
from jitterguard.bench.tracker_sequences import CAR, PED, Obj, make_sequence

DT = 0.1
T0 = 1_700_000_000_000_000_000


def frame(seq: int, xy, labels, *, t: float | None = None, ego=(0.0, 0.0, 0.0), **cols) -> DetectionFrame:
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    labels = np.asarray(labels)
    dims = {CAR: (4.5, 1.9), PED: (0.6, 0.6)}
    cols.setdefault("length", np.array([dims[int(lb)][0] for lb in labels]))
    cols.setdefault("width", np.array([dims[int(lb)][1] for lb in labels]))
    t = seq * DT if t is None else t
    return DetectionFrame(seq=seq, stamp_ns=T0 + int(round(t * 1e9)), ego_x=ego[0], ego_y=ego[1], ego_yaw=ego[2],
                          x=xy[:, 0], y=xy[:, 1], yaw=cols.pop("yaw", np.zeros(len(xy))), label=labels, **cols)


def track_ids_per_object(objects: list[Obj], n_frames: int, seed: int = 0, **kw) -> tuple[dict, TrackerCore]:
    """Run a clean-ish sequence; for every object, the set of confirmed track IDs found within 1 m of it."""
    seq = make_sequence(seed, n_frames=n_frames, objects=objects, **kw)
    core = TrackerCore()
    seen: dict[int, set[str]] = defaultdict(set)
    for f in seq.frames:
        res = core.step(f.detections)
        for gid, (gx, gy) in zip(f.gt_ids, f.gt_xy):
            if len(res.tracks) == 0:
                continue
            d = np.hypot(res.tracks.x - gx, res.tracks.y - gy)
            k = int(np.argmin(d))
            if d[k] < 1.0:
                seen[int(gid)].add(res.tracks.ids[k])
    return seen, core


QUIET = dict(miss_rate=0.0, fp_rate=0.0, ego_speed=0.0, ego_yaw_rate=0.0, flip_rate=0.0, class_flicker=0.0,
             sensor_range=100.0)


def test_crossing_cars_and_pedestrians_keep_their_ids() -> None:
    objects = [
        # two cars on perpendicular roads through the same junction, 0.8 s apart
        Obj(gid=0, label=CAR, x0=0.0, y0=20.0, yaw0=0.0, speed=8.0),
        Obj(gid=1, label=CAR, x0=26.4, y0=0.0, yaw0=math.pi / 2, speed=8.0),
        # two pedestrians whose paths cross at right angles, one second apart
        Obj(gid=2, label=PED, x0=10.0, y0=-10.0, yaw0=math.pi / 4, speed=1.4),
        Obj(gid=3, label=PED, x0=16.0 + 1.4 / math.sqrt(2), y0=-10.0 - 1.4 / math.sqrt(2), yaw0=3 * math.pi / 4,
            speed=1.4),
        # two pedestrians walking towards each other on lines 1 m apart (they pass shoulder to shoulder)
        Obj(gid=4, label=PED, x0=0.0, y0=-20.0, yaw0=0.0, speed=1.3),
        Obj(gid=5, label=PED, x0=16.0, y0=-19.0, yaw0=math.pi, speed=1.3),
    ]
    seen, _ = track_ids_per_object(objects, 100, **QUIET)
    for gid in range(6):
        assert len(seen[gid]) == 1, f"object {gid} was tracked under {len(seen[gid])} IDs"
    assert len(set().union(*seen.values())) == 6


def test_merging_objects_keep_their_ids() -> None:
    objects = [
        # car 1 merges from the left lane into car 0's lane, ending 9 m behind it
        Obj(gid=0, label=CAR, x0=10.0, y0=0.0, yaw0=0.0, speed=8.0),
        Obj(gid=1, label=CAR, x0=1.0, y0=3.5, yaw0=0.0, speed=8.0, turns=[(2.0, 3.0, -0.4), (3.0, 4.0, 0.4)]),
        # pedestrians walking side by side, 0.9 m apart
        Obj(gid=2, label=PED, x0=5.0, y0=10.0, yaw0=0.0, speed=1.3),
        Obj(gid=3, label=PED, x0=5.0, y0=10.9, yaw0=0.0, speed=1.3),
    ]
    seen, core = track_ids_per_object(objects, 80, seed=1, **QUIET)
    for gid in range(4):
        assert len(seen[gid]) == 1, f"object {gid} was tracked under {len(seen[gid])} IDs"
    assert int(core.tracks.confirmed.sum()) == 4


@pytest.mark.parametrize(("gap_s", "same_id"), [(0.7, True), (1.6, False)])
def test_occlusion_gap_within_coast_time_keeps_the_id(gap_s: float, same_id: bool) -> None:
    objects = [Obj(gid=0, label=CAR, x0=0.0, y0=5.0, yaw0=0.0, speed=6.0, occlusions=[(3.0, 3.0 + gap_s)]),
               Obj(gid=1, label=CAR, x0=30.0, y0=-5.0, yaw0=0.0)]
    seen, _ = track_ids_per_object(objects, 70, seed=2, **QUIET)
    assert (len(seen[0]) == 1) is same_id
    assert len(seen[1]) == 1


def test_birth_needs_confirm_hits_and_death_waits_for_max_coast() -> None:
    cfg = default_config()
    core = TrackerCore(cfg)
    lifetimes = []
    for k in range(3):
        res = core.step(frame(k, [[10.0, 0.0]], [CAR]))
        lifetimes.append(len(res.tracks))
        if k < cfg.confirm_hits - 1:
            assert res.obs_track.size == 0  # a tentative track is never published
    assert lifetimes == [0, 0, 1]
    tid = res.tracks.ids[0]
    assert res.observed_ids == [tid]
    # the object vanishes: the track coasts (still reported, not observed) for max_coast_s, then is deleted
    k = 3
    while True:
        res = core.step(frame(k, np.zeros((0, 2)), []))
        gone = (k - 2) * DT
        if tid in res.deleted:
            assert gone > cfg.max_coast_s
            assert gone <= cfg.max_coast_s + DT + 1e-9
            break
        assert res.tracks.ids == [tid] and res.obs_track.size == 0
        k += 1
    assert len(core.tracks) == 0


def test_isolated_false_positives_never_become_tracks() -> None:
    rng = np.random.default_rng(5)
    core = TrackerCore()
    confirmed = 0
    for k in range(100):
        xy = rng.uniform(-50, 50, size=(3, 2))
        res = core.step(frame(k, xy, [CAR, PED, CAR]))
        confirmed += len(res.tracks)
    assert confirmed == 0
    assert len(core.tracks) <= 9  # tentative ones expire after tentative_max_gap_s


def test_each_frame_counts_the_tracks_it_confirmed_and_the_confirmed_ones_it_deleted() -> None:
    """Births count clutter's tentative tracks too; the summary tells an operator how many reached the output
    (a run's "born 11,944" for ~70 objects read as a tracker losing them)."""
    rng = np.random.default_rng(7)
    core = TrackerCore()
    cfg = core.config
    born = confirmed = deleted = confirmed_deleted = 0
    for k in range(60):
        clutter = rng.uniform(-50, 50, size=(3, 2)) + np.array([0.0, 60.0])  # isolated, never within a gate
        car = [[10.0, 0.0]] if k < 30 else np.zeros((0, 2))  # a car seen for 3 s, then gone for good
        res = core.step(frame(k, np.vstack([car, clutter]) if k < 30 else clutter, [CAR] * (len(car) + 3)))
        born, confirmed = born + len(res.born), confirmed + res.confirmed
        deleted, confirmed_deleted = deleted + len(res.deleted), confirmed_deleted + res.confirmed_deleted
        if k == cfg.confirm_hits - 1:
            assert res.confirmed == 1 and res.tracks.ids  # the car's track reached the output in this frame
    assert confirmed == 1 and born >= 3 * 60  # every clutter box started a tentative track
    assert confirmed_deleted == 1 and deleted > confirmed_deleted  # the car's track coasted out; clutter expired


def test_track_ids_are_fresh_uuid4_hex_and_never_repeat_across_restarts() -> None:
    ids: list[str] = []
    for _restart in range(3):  # three "processes": a fresh core each time, same input
        core = TrackerCore()
        for k in range(40):
            # an object blinks in and out so tracks keep being born and deleted
            present = (k // 15) % 2 == 0
            res = core.step(frame(k, [[5.0, 0.0]] if present else np.zeros((0, 2)), [CAR] if present else []))
            ids.extend(res.born)
    assert len(ids) >= 6
    assert len(set(ids)) == len(ids)
    for tid in ids:
        assert re.fullmatch(r"[0-9a-f]{32}", tid)
        assert tid[12] == "4"  # UUID version 4: random, not derived from a counter or the clock


def test_duplicate_and_out_of_order_frames_are_rejected_without_touching_state() -> None:
    core = TrackerCore()
    for k in range(5):
        core.step(frame(k, [[10.0 + k * 0.5, 0.0]], [CAR]))
    before = (core.tracks.x.copy(), list(core.tracks.ids), core.last_seq)
    with pytest.raises(FrameRejected) as dup:
        core.step(frame(4, [[99.0, 0.0]], [CAR]))
    assert dup.value.reason == "duplicate"
    with pytest.raises(FrameRejected) as old:
        core.step(frame(2, [[99.0, 0.0]], [CAR]))
    assert old.value.reason == "out_of_order"
    with pytest.raises(FrameRejected) as back:  # a higher seq whose stamp goes back in time
        core.step(frame(9, [[99.0, 0.0]], [CAR], t=0.3))
    assert back.value.reason == "out_of_order"
    np.testing.assert_array_equal(core.tracks.x, before[0])
    assert core.tracks.ids == before[1] and core.last_seq == before[2]
    res = core.step(frame(5, [[12.5, 0.0]], [CAR]))  # and the stream goes on
    assert res.observed_ids == before[1]


def test_a_source_that_rewinds_far_resets_the_tracker_once_confirmed() -> None:
    core = TrackerCore()
    for k in range(5):
        core.step(frame(k, [[10.0, 0.0]], [CAR], t=100.0 + k * DT))
    old_ids = list(core.tracks.ids)
    for k in range(2):  # a replay that started over: held until a run confirms it
        with pytest.raises(FrameRejected, match="out_of_order"):
            core.step(frame(k, [[10.0, 0.0]], [CAR], t=k * DT))
    assert list(core.tracks.ids) == old_ids
    res = core.step(frame(2, [[10.0, 0.0]], [CAR], t=2 * DT))
    assert res.reset and set(old_ids) <= set(res.deleted)
    assert res.confirmed_deleted == len(old_ids) == 1  # the confirmed ones a reset drops are counted as such
    assert len(core.tracks) == 1 and core.tracks.ids[0] not in old_ids


def test_static_object_seen_from_a_moving_turning_ego_stays_put_in_the_world() -> None:
    rng = np.random.default_rng(7)
    core = TrackerCore()
    wx, wy = 20.0, 8.0
    ex, ey, eyaw = 0.0, 0.0, 0.0
    for k in range(60):
        c, s = math.cos(eyaw), math.sin(eyaw)
        dx, dy = wx - ex, wy - ey
        sx, sy = c * dx + s * dy, -s * dx + c * dy  # the object in the sensor frame
        res = core.step(frame(k, [[sx + rng.normal(0, 0.05), sy + rng.normal(0, 0.05)]], [CAR],
                              ego=(ex, ey, eyaw), yaw=np.array([-eyaw])))
        ex += 5.0 * math.cos(eyaw) * DT
        ey += 5.0 * math.sin(eyaw) * DT
        eyaw += 0.3 * DT
    assert len(res.tracks) == 1
    assert res.tracks.x[0] == pytest.approx(wx, abs=0.15)
    assert res.tracks.y[0] == pytest.approx(wy, abs=0.15)
    assert math.hypot(*res.tracks.vel[0]) < 0.5
    assert res.tracks.yaw[0] == pytest.approx(0.0, abs=0.1)  # the world heading, not the sensor-frame one


def test_detector_covariance_is_rotated_into_the_world_frame() -> None:
    """Along-beam 0.01 m^2, across-beam 0.09 m^2 in the sensor frame; the ego faces +y (yaw 90 degrees)."""
    core = TrackerCore()
    f = frame(0, [[10.0, 0.0]], [CAR], ego=(1.0, 2.0, math.pi / 2), cov_xx=np.array([0.01]),
              cov_xy=np.array([0.0]), cov_yy=np.array([0.09]), has_cov=np.array([True]))
    res = core.step(f)
    det = res.detections
    assert (det.x[0], det.y[0]) == pytest.approx((1.0, 12.0))
    assert (det.cov_xx[0], det.cov_yy[0]) == pytest.approx((0.09, 0.01))
    np.testing.assert_allclose(det.R[0, :2, :2], np.diag([0.09, 0.01]), atol=1e-12)
    # an arbitrary yaw with correlation: R Σ Rᵀ, as geometry.rotate_cov2 computes it
    core = TrackerCore()
    yaw = 0.7
    res = core.step(frame(0, [[10.0, 3.0]], [CAR], ego=(0, 0, yaw), cov_xx=np.array([0.04]),
                          cov_xy=np.array([0.01]), cov_yy=np.array([0.02]), has_cov=np.array([True])))
    Rm = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    S = np.array([[0.04, 0.01], [0.01, 0.02]])
    np.testing.assert_allclose(res.detections.R[0, :2, :2], Rm @ S @ Rm.T, atol=1e-12)
    assert rotate_cov2(0.04, 0.01, 0.02, yaw)[0] == pytest.approx(res.detections.cov_xx[0])


def test_measurement_covariance_detector_or_class_defaults() -> None:
    kw = dict(cov_xx=np.array([0.01, 0.01]), cov_xy=np.zeros(2), cov_yy=np.array([0.01, 0.01]),
              has_cov=np.array([True, False]))
    det_mode = TrackerCore(default_config(measurement_covariance="detector")).step(
        frame(0, [[5, 0], [5, 10]], [CAR, CAR], **kw)).detections.R
    cls_mode = TrackerCore(default_config(measurement_covariance="class")).step(
        frame(0, [[5, 0], [5, 10]], [CAR, CAR], **kw)).detections.R
    car = default_config().classes["car"]
    class_R = np.diag([car.r_long**2, car.r_lat**2])  # heading 0: along-heading = world x
    np.testing.assert_allclose(det_mode[0, :2, :2], np.diag([0.01, 0.01]))
    np.testing.assert_allclose(det_mode[1, :2, :2], class_R)  # no covariance from the detector: class
    np.testing.assert_allclose(cls_mode[0, :2, :2], class_R)
    np.testing.assert_allclose(cls_mode[1, :2, :2], class_R)


@pytest.mark.parametrize("mode", ["detector", "class"])
def test_both_measurement_modes_track_the_standard_scene(mode: str) -> None:
    seq = make_sequence(11, n_frames=60)
    core = TrackerCore(default_config(measurement_covariance=mode))
    for f in seq.frames:
        res = core.step(f.detections)
    assert abs(len(res.tracks) - len(seq.frames[-1].gt_ids)) <= 2


def test_static_hint_resets_velocity_and_position_of_that_track_only() -> None:
    core = TrackerCore()
    for k in range(10):  # a car that seems to creep (jitter read as motion) and a real mover
        res = core.step(frame(k, [[10.0 + 0.05 * k, 0.0], [0.0, 10.0 + 1.0 * k]], [CAR, CAR],
                              yaw=np.array([0.0, math.pi / 2])))
    creeper, mover = res.tracks.ids
    assert abs(res.tracks.vel[0, 0]) > 0.1
    # a mean 500 m off is no window of this track: one message must not move it across the map
    assert core.apply_static_hints([mover], [500.0], [500.0]) == (0, 1)
    applied = core.apply_static_hints([creeper, "f" * 32], [10.2, 0.0], [0.0, 0.0])
    assert applied == (1, 0)  # unknown IDs are ignored
    res = core.step(frame(10, [[10.2, 0.0], [0.0, 20.0]], [CAR, CAR], yaw=np.array([0.0, math.pi / 2])))
    i = res.tracks.ids.index(creeper)
    assert math.hypot(*res.tracks.vel[i]) < 0.05
    assert res.tracks.x[i] == pytest.approx(10.2, abs=0.05)
    j = res.tracks.ids.index(mover)
    assert res.tracks.vel[j, 1] == pytest.approx(10.0, abs=1.0)


def test_observations_pair_each_confirmed_track_with_its_own_detection() -> None:
    seq = make_sequence(4, n_frames=40)
    core = TrackerCore()
    for f in seq.frames:
        res = core.step(f.detections)
        assert len(set(res.obs_track.tolist())) == res.obs_track.size
        assert len(set(res.obs_det.tolist())) == res.obs_det.size
        for i, j in zip(res.obs_track, res.obs_det):
            d = math.hypot(res.tracks.x[i] - res.detections.x[j], res.tracks.y[i] - res.detections.y[j])
            assert d < 2.0
            assert res.tracks.last_update_ns[i] == f.stamp_ns
    assert res.obs_track.size > 10


@pytest.mark.parametrize("min_iou, twins", [(0.1, False), (0.0, True)])
def test_a_second_box_on_a_parked_car_never_becomes_a_track_of_its_own(min_iou: float, twins: bool) -> None:
    """The detector boxes a parked car twice every scan: once on its centre (score 0.7) and once 2.2 m along it
    (score 0.4), too far for the car's association gate (2 m). Autoware's IoU rule (footprints overlap, IoU
    0.34) deletes the second box's track at birth; without it the second box becomes a confirmed twin."""
    core = TrackerCore(default_config(overlap_min_iou=min_iou))
    confirmed: set[str] = set()
    for k in range(30):
        res = core.step(frame(k, [[20.0, 0.0], [22.2, 0.0]], [CAR, CAR], existence=np.array([0.7, 0.4])))
        confirmed.update(res.tracks.ids)
    assert len(res.tracks) == (2 if twins else 1)
    assert len(confirmed) == len(res.tracks)  # and the car's own track never changed its ID
    car = int(np.argmin(np.hypot(res.tracks.x - 20.0, res.tracks.y)))
    assert abs(res.tracks.x[car] - 20.0) < 0.2


def test_a_car_driving_past_recurring_clutter_keeps_its_id() -> None:
    """A low-scored box recurs on one spot (a bush the detector calls a car, score 0.1): its track gathers hits but
    stays tentative (``confirm_min_existence``). A confirmed car driving past it 1 m off overlaps it (IoU > 0.1)
    with fewer hits; a track that is not confirmed must not delete it (Autoware: a track that is not confident
    removes nothing). It had: the car's ID ended and the car went unpublished for 0.6 s."""
    core = TrackerCore()
    car_ids: list[str | None] = []
    for k in range(80):
        xy, ex = [[40.0, 1.0]], [0.1]
        if k >= 20:
            xy.append([10.0 * (k - 20) * DT, 0.0])
            ex.append(0.9)
        res = core.step(frame(k, xy, [CAR] * len(xy), existence=np.array(ex)))
        if k >= 24:  # confirmed by then: which published track took the car's detection
            took = [res.tracks.ids[t] for t, d in zip(res.obs_track, res.obs_det) if d == 1]
            car_ids.append(took[0] if took else None)
    assert None not in car_ids and len(set(car_ids)) == 1
    assert not any(core.tracks.confirmed[i] for i, x in enumerate(core.tracks.x[:, 0]) if abs(x - 40.0) < 0.5)


def test_never_more_confirmed_tracks_reported_than_max_objects_observed_ones_first() -> None:
    """A churning scene confirms more tracks than the downstream readers take (``limits.max_objects``): the
    frame still goes out, with every observed track and the most recently seen coasting ones, and says how
    many it withheld — instead of a ``tracked`` the classifier would refuse, frame after frame."""
    cfg = default_config()
    cfg = cfg.model_copy(update={"limits": cfg.limits.model_copy(update={"max_objects": 6})})
    core = TrackerCore(cfg)
    # four cars seen for 3 frames each (confirmed), then gone and coasting; every 3 frames four new ones
    seq, last_seen = 0, {}
    for wave in range(4):
        xy = [[10.0 + 20 * wave, 8.0 * i] for i in range(4)]
        for _ in range(3):
            res = core.step(frame(seq, xy, [CAR] * 4))
            seq += 1
            for tid in res.observed_ids:
                last_seen[tid] = seq
            assert len(res.tracks) <= 6
            assert set(res.observed_ids) <= set(res.tracks.ids)
        confirmed_alive = [t for t in core.tracks.ids if t in last_seen]
        assert res.withheld == max(0, len(confirmed_alive) - 6)
    assert res.withheld > 0 and len(res.tracks) == 6
    coasting = [t for t in res.tracks.ids if t not in res.observed_ids]
    withheld = [t for t in last_seen if t in core.tracks.ids and t not in res.tracks.ids]
    assert min(last_seen[t] for t in coasting) >= max(last_seen[t] for t in withheld)  # the longest unseen go


@pytest.mark.parametrize(("rate_hz", "speed"), [(10.0, 30.0), (10.0, 42.0), (2.0, 14.0), (2.0, 5.0)])
def test_a_car_first_seen_fast_is_tracked_with_one_id(rate_hz: float, speed: float) -> None:
    """A newborn is predicted where it was born, and the main gate reaches 2 m: a car first seen at over 20 m/s at
    10 Hz (4 m/s on nuScenes' 2 Hz key frames) got a new tentative track every frame and was never published.
    Its second detection is now found along its heading, where its own reported velocity puts it."""
    core = TrackerCore()
    ids, births = set(), 0
    for k in range(10):
        x = 10.0 + speed * k / rate_hz
        res = core.step(frame(k, [[x, 5.0]], [CAR], t=k / rate_hz, vx=np.array([speed]), vy=np.array([0.0]),
                              has_twist=np.array([True])))
        births += len(res.born)
        ids.update(res.tracks.ids)
    assert births == 1 and len(ids) == 1
    assert res.tracks.vel[0, 0] == pytest.approx(speed, rel=0.02)


def test_a_newborn_takes_no_far_box_that_its_velocity_does_not_explain() -> None:
    """Boxes 4 m apart frame after frame are noise, not a 40 m/s car, when the detector says the object stands
    (zero twist); without a twist there is nothing to tell them from a mover and no newborn gets a second chance
    (the main gate's 2 m as before): no track is made of them either way."""
    for twist in (True, False):
        core = TrackerCore()
        births = 0
        for k, x in enumerate([10.0, 14.0, 18.0, 22.0]):
            res = core.step(frame(k, [[x, 5.0]], [CAR], vx=np.array([0.0]), vy=np.array([0.0]),
                                  has_twist=np.array([twist])))
            births += len(res.born)
            assert len(res.tracks) == 0
        assert births == 4


def test_a_newborn_near_an_older_track_is_that_track_s_twin_not_a_fast_newcomer() -> None:
    """A box a confirmed car's gate missed starts a newborn beside it; the car's next box, 3 m on, is the
    car's, not a "fast" second detection of the newborn, whatever velocity it reports."""
    core = TrackerCore()
    for k in range(5):
        core.step(frame(k, [[10.0, 5.0]], [CAR]))
    (car,) = core.step(frame(5, [[10.0, 5.0]], [CAR])).tracks.ids
    kw = dict(vx=np.array([30.0, 30.0]), vy=np.zeros(2), has_twist=np.array([True, True]))
    core.step(frame(6, [[10.0, 5.0], [12.5, 5.0]], [CAR, CAR], **kw))  # a twin born 2.5 m off
    res = core.step(frame(7, [[10.0, 5.0], [15.5, 5.0]], [CAR, CAR], **kw))
    assert res.tracks.ids == [car]
    twin = [i for i in range(len(core.tracks)) if core.tracks.ids[i] != car]
    assert all(core.tracks.hits[i] == 1 for i in twin)


def test_a_track_past_its_lifetime_is_not_revived_by_a_detection_near_its_prediction() -> None:
    """Car A drives at 10 m/s, then nothing is seen for 3 s (over max_coast_s); the next frame holds only a parked
    car B where A's prediction lands. A is deleted and B born tentative under a new ID — B had been published at
    once under A's ID, with A's velocity and window, because expiry ran after the update."""
    core = TrackerCore()
    for k in range(20):
        core.step(frame(k, [[k * 1.0, 3.0]], [CAR]))
    (a,) = core.step(frame(20, [[20.0, 3.0]], [CAR])).tracks.ids
    res = core.step(frame(21, [[50.0, 3.0]], [CAR], t=5.0))
    assert a in res.deleted and len(res.born) == 1 and res.tracks.ids == []
