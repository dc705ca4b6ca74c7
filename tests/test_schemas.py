"""The wire contract: round trips, every validation rule DESIGN.md lists, and decode fuzzing."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jitterguard.schemas import DecodeError, decode, encode, keys
from jitterguard.schemas.models import (
    SCHEMA_VERSION,
    X_X,
    Y_Y,
    ClassifierConfig,
    DetectedObject,
    DetectedObjects,
    Header,
    Label,
    MotionState,
    ObjectClassification,
    PointCloud,
    TrackedObject,
    TrackedObjects,
    TrackObservation,
    TrackState,
)

TID = "0123456789abcdef0123456789abcdef"


def _tracked() -> TrackedObjects:
    obj = TrackedObject(object_id=TID, classification=[ObjectClassification(label=Label.CAR, probability=0.8)])
    return TrackedObjects(header=Header(stamp=123, seq=7), objects=[obj], observed_track_ids=[TID])


def _points(n: int = 5) -> PointCloud:
    data = np.arange(n * 4, dtype="<f4").tobytes()
    return PointCloud(header=Header(stamp=1, frame_id="lidar", seq=0), num_points=n, data=data)


def _mutate(model, path: list, value) -> bytes:
    raw = model.model_dump(mode="python")
    node = raw
    for p in path[:-1]:
        node = node[p]
    node[path[-1]] = value
    return msgpack.packb(raw, use_bin_type=True)


def test_round_trip_keeps_every_field():
    for model in (_tracked(), _points(), ClassifierConfig(alpha_per_class={"car": 2.58})):
        back = decode(type(model), encode(model))
        assert back == model
        assert back.schema_version == SCHEMA_VERSION


@pytest.mark.parametrize(
    ("path", "value", "field"),
    [
        (["objects", 0, "kinematics", "pose_with_covariance", "pose", "position", "x"], math.nan, "position.x"),
        (["objects", 0, "kinematics", "pose_with_covariance", "pose", "position", "y"], math.inf, "position.y"),
        (["objects", 0, "kinematics", "pose_with_covariance", "covariance"], [0.0] * 35, "covariance"),
        (["objects", 0, "kinematics", "pose_with_covariance", "covariance"], [0.0] * 37, "covariance"),
        (["objects", 0, "classification", 0, "label"], 8, "label"),
        (["objects", 0, "classification", 0, "label"], -1, "label"),
        (["objects", 0, "object_id"], "not-a-uuid", "object_id"),
        (["objects", 0, "object_id"], TID.upper(), "object_id"),
        (["observed_track_ids", 0], TID[:-1], "observed_track_ids"),
        (["header", "stamp"], -5, "header.stamp"),
        (["schema_version"], 99, "schema_version"),
    ],
)
def test_validation_rejects_and_names_the_field(path, value, field):
    with pytest.raises(DecodeError) as err:
        decode(TrackedObjects, _mutate(_tracked(), path, value))
    assert field in str(err.value)
    assert str(err.value).startswith("TrackedObjects.")


def test_negative_variance_rejected_at_its_index():
    for idx in (X_X, Y_Y, 35):
        cov = [0.0] * 36
        cov[idx] = -0.1
        data = _mutate(_tracked(), ["objects", 0, "kinematics", "pose_with_covariance", "covariance"], cov)
        with pytest.raises(DecodeError, match=f"covariance.{idx}"):
            decode(TrackedObjects, data)
    cov = [0.0] * 36
    cov[1] = -0.1  # off-diagonal terms may be negative
    decode(TrackedObjects, _mutate(_tracked(), ["objects", 0, "kinematics", "pose_with_covariance", "covariance"], cov))


def test_point_buffer_must_match_field_count():
    pc = _points(5)
    with pytest.raises(DecodeError, match="data"):
        decode(PointCloud, _mutate(pc, ["data"], pc.data[:-4]))
    with pytest.raises(DecodeError, match="fields"):
        decode(PointCloud, _mutate(pc, ["fields"], ["x", "y", "intensity", "z"]))
    with pytest.raises(DecodeError):
        decode(PointCloud, _mutate(pc, ["num_points"], 6))


def test_unknown_fields_and_wrong_shapes_rejected():
    with pytest.raises(DecodeError, match="bogus"):
        decode(TrackedObjects, _mutate(_tracked(), ["bogus"], 1))
    with pytest.raises(DecodeError, match="expected a msgpack map"):
        decode(TrackedObjects, msgpack.packb([1, 2, 3]))
    with pytest.raises(DecodeError, match="not valid msgpack"):
        decode(TrackedObjects, b"\xc1")


def test_classifier_config_rules():
    with pytest.raises(ValueError, match="min_window"):
        ClassifierConfig(window_size=4, min_window=5)
    with pytest.raises(ValueError, match="unknown class"):
        ClassifierConfig(alpha_per_class={"spaceship": 2.0})
    with pytest.raises(ValueError, match="alpha_default"):
        ClassifierConfig(alpha_default=0.0)
    cfg = ClassifierConfig(alpha_default=1.5, alpha_per_class={"pedestrian": 1.28})
    assert cfg.alpha_for(Label.PEDESTRIAN) == 1.28
    assert cfg.alpha_for(Label.CAR) == 1.5


def test_keys():
    assert keys.track("ns1", TID) == f"jg/ns1/tracks/{TID}"
    assert keys.tracks_all() == "jg/default/tracks/*"
    assert keys.motion("a", TID) == f"jg/a/motion/{TID}"
    assert keys.classifier_config("a") == "jg/a/classifier/config"
    assert keys.last_chunk(keys.track("a", TID)) == TID
    for bad in ("a/b", "a*", "", "x y"):
        with pytest.raises(ValueError):
            keys.points(bad)


_VALID = [
    encode(_tracked()),
    encode(_points()),
    encode(TrackObservation(header=Header(stamp=1), detection=DetectedObject(), track=TrackState(object_id=TID, x=1, y=2))),
    encode(MotionState(header=Header(stamp=1), track_id=TID, state="static", mode="z_test", threshold=1.96, alpha=1.96, window_length=3)),
    encode(DetectedObjects(header=Header(stamp=1), objects=[DetectedObject()])),
]
_MODELS = [TrackedObjects, PointCloud, TrackObservation, MotionState, DetectedObjects]


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=512), st.sampled_from(_MODELS))
def test_fuzz_random_bytes_raise_only_decode_error(data, model):
    try:
        decode(model, data)
    except DecodeError:
        pass


@settings(max_examples=400, deadline=None)
@given(st.integers(0, len(_VALID) - 1), st.data())
def test_fuzz_mutated_valid_payloads_raise_only_decode_error(i, data):
    payload = bytearray(_VALID[i])
    n = data.draw(st.integers(1, 8))
    for _ in range(n):
        op = data.draw(st.sampled_from(["flip", "cut", "insert"]))
        pos = data.draw(st.integers(0, max(0, len(payload) - 1)))
        if op == "flip" and payload:
            payload[pos] ^= data.draw(st.integers(1, 255))
        elif op == "cut":
            del payload[pos:pos + data.draw(st.integers(1, 16))]
        else:
            payload[pos:pos] = data.draw(st.binary(min_size=1, max_size=8))
    try:
        decode(_MODELS[i], bytes(payload))
    except DecodeError as exc:
        assert str(exc).startswith(_MODELS[i].__name__)
