"""Track-ID survival (jitterguard.eval.survival) on hand-built sequences whose answer is counted by hand."""

from __future__ import annotations

import numpy as np

from jitterguard.bench import survival as survival_cli
from jitterguard.eval.survival import DEFAULT_MIN_POINTS, in_view, survival
from jitterguard.schemas import encode
from jitterguard.schemas.models import (
    DetectedObject,
    DetectedObjectKinematics,
    DetectedObjects,
    Header,
    Label,
    ObjectClassification,
    Point,
    Pose,
    PoseWithCovariance,
    Shape,
    Vector3,
)
from jitterguard.services.tracker.config import default_config
from jitterguard.sim.world import GroundTruthFrame

T0 = 1_700_000_000_000_000_000
DT_NS = 100_000_000


def gt_frame(k: int, points: int = 50, x: float = 20.0) -> GroundTruthFrame:
    return GroundTruthFrame(
        seq=k, stamp_ns=T0 + k * DT_NS, ego_x=0.0, ego_y=0.0, ego_yaw=0.0,
        instance_ids=np.array([7]), labels=np.array([int(Label.CAR)]), centers=np.array([[x, 0.0, 0.8]]),
        sizes=np.array([[4.5, 1.9, 1.6]]), yaws=np.zeros(1), velocities=np.zeros((1, 2)), moving=np.zeros(1, bool),
        attributes=("vehicle.parked",), visibility=np.ones(1), num_points=np.array([points]))


def detections(k: int, present: bool, x: float = 20.0, score: float = 0.9) -> DetectedObjects:
    objs = []
    if present:
        objs.append(DetectedObject(
            existence_probability=score, classification=[ObjectClassification(label=Label.CAR, probability=score)],
            kinematics=DetectedObjectKinematics(pose_with_covariance=PoseWithCovariance(
                pose=Pose(position=Point(x=x, y=0.0, z=0.8)))),
            shape=Shape(type=Shape.BOUNDING_BOX, dimensions=Vector3(x=4.5, y=1.9, z=1.6))))
    return DetectedObjects(header=Header(stamp=T0 + k * DT_NS, frame_id="lidar", seq=k), objects=objs)


def test_survival_counts_a_miss_longer_than_the_coast_time() -> None:
    """60 frames at 10 Hz of one parked car in view; the detector misses it in frames 20–34 (1.5 s > the 1 s
    coast). Track A is confirmed at frame 2, last updated at 19 and deleted at 30 (gap 1.1 s); track B is born
    at 35 and confirmed at 37. Trials (t, t + 10 frames, both < 60): A matched at t = 2..29 survives for
    t ≤ 19 (18 of 28); B at t = 37..49 always (13). 31 of 41."""
    cfg = default_config()
    assert cfg.max_coast_s == 1.0 and cfg.confirm_hits == 3
    frames = [(gt_frame(k), detections(k, not 20 <= k < 35)) for k in range(60)]
    r = survival(frames, cfg, horizon_s=1.0, min_points=10)
    assert r["trials"] == 41
    assert r["survival"] == round(31 / 41, 4) and r["survival_same_object"] == round(31 / 41, 4)
    lo, hi = r["survival_ci95"]
    assert lo < 31 / 41 < hi
    assert r["tentative_published"] == 0
    # frames 0-1 and 30-36 have the car in view without a confirmed track: 51 of 60 covered
    assert r["coverage"] == round(51 / 60, 4)


def test_an_object_out_of_view_is_not_a_trial() -> None:
    """The same miss, but the ground truth says the car had 3 LiDAR returns then (occluded): no trial spans it."""
    frames = [(gt_frame(k, points=3 if 20 <= k < 35 else 50), detections(k, not 20 <= k < 35)) for k in range(60)]
    r = survival(frames, default_config(), horizon_s=1.0, min_points=10)
    # A: t = 2..9 (t + 10 < 20 keeps the window in view) ; B: t = 37..49
    assert r["trials"] == 8 + 13 and r["survival"] == 1.0


def test_a_low_scored_ghost_is_never_confirmed_so_never_scored() -> None:
    frames = [(gt_frame(k), detections(k, True, x=-30.0, score=0.1)) for k in range(30)]
    r = survival(frames, default_config(), min_points=10)
    assert r["trials"] == 0 and r["survival"] is None and r["survival_ci95"] is None
    assert r["confirmed_per_frame"] == 0.0 and r["coverage"] == 0.0


def test_in_view_needs_points_and_range() -> None:
    assert in_view(gt_frame(0, points=10), 10) == {7}
    assert in_view(gt_frame(0, points=9), 10) == set()
    assert in_view(gt_frame(0, x=55.0), 1) == set()  # cars are scored to 50 m
    assert survival_cli.DEFAULT_MIN_POINTS == DEFAULT_MIN_POINTS


def test_score_pools_runs_and_resamples_whole_tracks() -> None:
    from jitterguard.eval.survival import SurvivalRun, score

    a = SurvivalRun(per_track={"t1": [10, 10, 10], "t2": [10, 0, 0]}, counts={"frames": 5, "born": 10})
    b = SurvivalRun(per_track={"t1": [20, 20, 18]}, counts={"frames": 5, "born": 0})  # another run's own t1
    r = score([a, b])
    assert r["trials"] == 40 and r["tracks"] == 3
    assert r["survival"] == 0.75 and r["survival_same_object"] == 0.7
    assert r["tracks_born_per_frame"] == 1.0
    lo, hi = r["survival_ci95"]
    assert lo < 0.75 < hi and hi - lo > 0.3  # three tracks: wide, as it must be
    assert score([a, b]) == r  # seeded


def test_wire_payloads_score_like_the_models_they_encode() -> None:
    """The bench feeds the detector service's wire payloads (bytes), the unit tests models: the same frames
    either way give the same trials and survival."""
    frames = [(gt_frame(k), detections(k, not 20 <= k < 35)) for k in range(60)]
    as_models = survival(frames, default_config(), horizon_s=1.0, min_points=10)
    as_bytes = survival([(g, encode(d)) for g, d in frames], default_config(), horizon_s=1.0, min_points=10)
    assert as_bytes == as_models and as_bytes["trials"] == 41
