"""``observe_tentative``: the tracker publishes tentative tracks' detections on ``tracks/{id}`` (never in ``tracked``'s
objects), the classifier's window of a track then starts with its first detection, only published tracks get a
motion state or teach the calibration, and the bridges' joiner waits only for the motion states that will come."""

from __future__ import annotations

import numpy as np

from jitterguard.eval.pipeline import _classify, run_pipeline
from jitterguard.schemas import DetectedColumns, decode, encode, read_detected_objects
from jitterguard.schemas.models import (
    ClassifierConfig,
    DetectedObjects,
    Header,
    MotionState,
    TrackedObjects,
    TrackObservation,
)
from jitterguard.services.bridge.joiner import FrameJoiner
from jitterguard.services.classifier.adapter import ClassifierAdapter
from jitterguard.services.tracker.adapter import detection_frame, observation_payloads, tracked_payload
from jitterguard.services.tracker.config import default_config
from jitterguard.services.tracker.core import TrackerCore
from jitterguard.sim.detection_model import NoiseConfig
from jitterguard.sim.world import make_scenario

CAR = 1
T0 = 1_700_000_000_000_000_000


def detections(seq: int, xy, existence: float = 0.9) -> DetectedColumns:
    """A ``detections`` payload of cars at ``xy`` (sensor frame = world frame: identity ego pose), read back as
    the tracker service reads it."""
    objs = [{"existence_probability": existence, "classification": [{"label": CAR, "probability": 1.0}],
             "kinematics": {"pose_with_covariance": {"pose": {"position": {"x": float(x), "y": float(y)}},
                                                     "covariance": [0.04 if j in (0, 7) else 0.0 for j in range(36)]},
                            "has_position_covariance": True},
             "shape": {"dimensions": {"x": 4.5, "y": 1.9, "z": 1.5}}} for x, y in xy]
    msg = DetectedObjects.model_validate({"header": {"stamp": T0 + seq * 100_000_000, "frame_id": "lidar",
                                                     "seq": seq}, "objects": objs})
    return read_detected_objects(encode(msg))


def step(core: TrackerCore, adapter: ClassifierAdapter | None, seq: int, xy, existence: float = 0.9):
    """One frame through the tracker core (and the classifier adapter) as the services run it."""
    cols = detections(seq, xy, existence)
    df = detection_frame(cols)
    res = core.step(df)
    payloads = observation_payloads(cols, df, res)
    closing = tracked_payload(cols, df, res)
    out = _classify(adapter, [p for _, p in payloads], closing, df.stamp_ns * 1e-9) if adapter is not None else None
    return res, payloads, closing, out


def _tracker(on: bool) -> TrackerCore:
    return TrackerCore(default_config().model_copy(update={"observe_tentative": on}))


def test_a_tentative_track_is_observed_but_never_in_tracked() -> None:
    core = _tracker(True)
    hits = core.config.confirm_hits
    for k in range(hits + 1):
        res = step(core, None, k, [(10.0 + 0.5 * k, 0.0)])[0]
        if k < hits - 1:
            assert len(res.tracks) == 0 and len(res.tentative) == 1  # observed, not confirmed
            assert res.observed_ids == res.tentative.ids
            assert int(res.tentative.hits[0]) == k + 1
        else:
            assert len(res.tracks) == 1 and len(res.tentative) == 0
            assert res.observed_ids == res.tracks.ids
    # off (the default): a tentative track is not observed at all
    off = _tracker(False)
    res = step(off, None, 0, [(10.0, 0.0)])[0]
    assert res.observed_ids == [] and len(res.tentative) == 0


def test_tentative_payloads_carry_the_detection_and_the_tracked_message_leaves_them_out() -> None:
    core = _tracker(True)
    # a confirmed car at x=10 and, from frame 3 on, a second car at x=30 that is tentative in frame 3 and 4
    for k in range(5):
        res, payloads, closing, _ = step(core, None, k, [(10.0, 0.0)] + ([(30.0, 5.0)] if k >= 3 else []))
    tracked = decode(TrackedObjects, closing)
    assert len(tracked.objects) == 1 and len(tracked.observed_track_ids) == 2
    new_id = next(t for t in tracked.observed_track_ids if t != tracked.objects[0].object_id)
    obs = {tid: decode(TrackObservation, p) for tid, p in payloads}
    assert set(obs) == set(tracked.observed_track_ids)
    assert obs[new_id].track.hits == 2
    assert obs[new_id].detection.kinematics.pose_with_covariance.pose.position.x == 30.0


def _run(on: bool, frames: int = 6) -> list:
    core, adapter = _tracker(on), ClassifierAdapter(ClassifierConfig())
    return [step(core, adapter, k, [(10.0, 0.0)])[3] for k in range(frames)]


def test_the_classifier_window_starts_at_birth_and_tentative_tracks_get_no_motion_state() -> None:
    hits = default_config().confirm_hits
    on, off = _run(True), _run(False)
    for k, (a, b) in enumerate(zip(on, off)):
        if k < hits - 1:  # tentative: nothing published, no decision to send
            assert len(a.reported) == 0 and a.decided is None
            assert list(ClassifierAdapter.motion_payloads(None, a)) == []  # type: ignore[arg-type]
        else:
            # the same confirmed track; its window holds every detection since birth, not since confirmation
            assert len(a.reported) == len(b.reported) == 1
            assert int(a.decisions.window_length[0]) == k + 1
            assert int(b.decisions.window_length[0]) == k - hits + 2
            (tid, payload), = ClassifierAdapter.motion_payloads(None, a)  # type: ignore[arg-type]
            assert decode(MotionState, payload).window_length == k + 1


def test_a_track_never_confirmed_teaches_the_calibration_nothing() -> None:
    """A clutter return the existence gate keeps tentative for longer than a window: its window fills, but the
    online calibration pools nothing from it (and its window is evicted once the tracker stops observing it)."""
    cfg = default_config().model_copy(update={"observe_tentative": True, "confirm_min_existence": 0.99})
    core = TrackerCore(cfg)
    adapter = ClassifierAdapter(ClassifierConfig(window_size=5))
    rng = np.random.default_rng(0)
    for k in range(25):
        xy = [(10.0 + rng.normal(0, 0.1), rng.normal(0, 0.1))] if k < 20 else []
        res, _, _, out = step(core, adapter, k, xy, existence=0.3)
        assert len(res.tracks) == 0 and len(out.reported) == 0
        if k == 19:
            assert adapter.core.track_ids() == res.tentative.ids  # its window lives while it is observed
    assert adapter.core.online_calibration.counts["blocks"] == 0
    assert adapter.core.track_ids() == []


def test_the_joiner_waits_only_for_published_tracks_motion() -> None:
    a, b = "a" * 32, "b" * 32
    hdr = Header(stamp=1_003, seq=3, frame_id="map")
    j = FrameJoiner(motion_wait_s=10.0)
    # a frame before, without inputs: the first frame of a run waits for every input stream; the next ones only
    # for those the frame before them had (none here), so frame 3 waits for its motion states alone
    j.add_objects(TrackedObjects(header=Header(stamp=1_002, seq=2, frame_id="map")), 0.0)
    assert [f.seq for f in j.poll(10.0)] == [2]
    j.add_tracked(TrackedObjects(header=hdr, observed_track_ids=[a, b]))  # b is tentative: not in objects
    j.add_objects(TrackedObjects.model_validate({"header": hdr.model_dump(), "objects": [{"object_id": a}]}), 10.0)
    assert j.poll(10.1) == []
    j.add_motion(MotionState(header=hdr, track_id=a, state="static", mode="z_test", window_length=4,
                            threshold=2.58, alpha=2.58))
    (f,) = j.poll(10.1)
    assert set(f.motion) == {a} and j.counters.get("motion_missing", 0) == 0


def test_the_evaluator_scores_published_tracks_only_and_catches_more_young_movers() -> None:
    frames = lambda: make_scenario("mixed", 5, 8.0, 10.0)  # noqa: E731
    recs = {on: run_pipeline(frames(), NoiseConfig.jittery(), 5, ClassifierConfig(),
                             default_config().model_copy(update={"observe_tentative": on})) for on in (False, True)}
    off, on = recs[False], recs[True]
    assert set(on.track_id.tolist()) == set(off.track_id.tolist())  # the same published tracks, nothing tentative
    key = lambda r: {(t, s): w for t, s, w in zip(r.track_id.tolist(), r.seq.tolist(), r.window.tolist())}  # noqa
    k_off, k_on = key(off), key(on)
    assert set(k_off) == set(k_on)
    longer = [k_on[x] - k_off[x] for x in k_off]
    assert max(longer) >= 2 and min(longer) >= 0  # windows only gain the tentative detections
