"""The wire contract: round trips, every validation rule DESIGN.md lists, and decode fuzzing."""

from __future__ import annotations

import copy
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


# ------------------------------------------------------------------ the hot-path decoders agree with the models
# decode_map (pydantic-core on plain maps) and StructCodec (msgspec Structs generated from the models) must
# accept exactly what decode accepts, return what it returns, and name the same field when they refuse.

from jitterguard.schemas import decode_map  # noqa: E402
from jitterguard.schemas.fast import StructCodec, block_values, struct_type  # noqa: E402
from jitterguard.schemas.models import (  # noqa: E402
    Point,
    Pose,
    PoseWithCovariance,
    Quaternion,
    Shape,
    TrackedObjectKinematics,
    Vector3,
)


def _cov(seed: float) -> tuple[float, ...]:
    return tuple(seed * (i + 1) if i in (0, 7, 14, 21, 28, 35) else -seed * i / 7 for i in range(36))


def _rich_tracked() -> TrackedObjects:
    ids = [TID, "fedcba9876543210fedcba9876543210"]
    objs = [
        TrackedObject(
            object_id=tid, existence_probability=0.75,
            classification=[ObjectClassification(label=Label.CAR, probability=0.6),
                            ObjectClassification(label=Label.TRUCK, probability=0.4)],
            kinematics=TrackedObjectKinematics(
                pose_with_covariance=PoseWithCovariance(
                    pose=Pose(position=Point(x=12.5 * k, y=-3.25, z=0.5), orientation=Quaternion(z=0.38, w=0.92)),
                    covariance=_cov(0.01 * (k + 1))),
                orientation_availability=1, is_stationary=bool(k)),
            shape=Shape(type=2, footprint=[Point(x=1.0, y=2.0), Point(x=-1.0, y=0.5)], dimensions=Vector3(x=4.5, y=1.9, z=1.6)),
        )
        for k, tid in enumerate(ids)
    ]
    return TrackedObjects(header=Header(stamp=1_700_000_000_000_000_000, frame_id="map", seq=42), objects=objs,
                          observed_track_ids=ids)


def _rich_observation() -> TrackObservation:
    det = DetectedObject(existence_probability=0.9, classification=[ObjectClassification(label=Label.PEDESTRIAN)])
    det.kinematics.pose_with_covariance.covariance = _cov(0.02)
    det.kinematics.has_position_covariance = True
    return TrackObservation(header=Header(stamp=5, seq=3), detection=det,
                            track=TrackState(object_id=TID, label=7, x=-1.5, y=2.5, yaw=0.3, vx=1.25, vy=-0.5, hits=4, age_s=0.4))


_FAST = {
    TrackedObjects: _rich_tracked(),
    TrackObservation: _rich_observation(),
    MotionState: MotionState(header=Header(stamp=1), track_id=TID, state="dynamic", mode="chi2", threshold=5.99,
                             alpha=1.96, window_length=10, speed=3.5, z_x=4.0, z_y=-1.0, mean_x=1.0, mean_y=2.0),
}
_CODECS = {m: StructCodec(m) for m in _FAST}
_RAW_CODEC = StructCodec(TrackedObjects, raw_float_blocks=16)  # what the classifier decodes `tracked` with

_ODD_VALUES = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(-(2**63), 2**64 - 1),
    st.booleans(),
    st.none(),
    st.text(max_size=34),
    st.binary(max_size=8),
    st.sampled_from([TID, TID.upper(), TID + "\n", "\n" + TID, TID[:-1], "1.5", "7", "static", "z_test",
                     [], {}, [0.0] * 35, [0.0] * 36, [0.0] * 37, [1] * 36, [-1.0] * 36, ["0"] * 36,
                     {"x": 1.0}, {"bogus": 1}, [{"label": 1}], [TID, TID]]).map(copy.deepcopy),  # fresh each draw
    st.lists(st.floats(allow_nan=False, allow_infinity=False), max_size=3),
)


def _paths(node, prefix=()) -> list[tuple]:
    out = [prefix]
    if isinstance(node, dict):
        for k, v in node.items():
            out += _paths(v, prefix + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += _paths(v, prefix + (i,))
    return out


def _mutated(model, data) -> bytes:
    raw = msgpack.unpackb(encode(model))
    single = data.draw(st.integers(0, 9)) == 0  # now and then every float as float32: legal, not canonical
    for _ in range(data.draw(st.integers(1, 3))):
        path = data.draw(st.sampled_from(_paths(raw)))
        op = data.draw(st.sampled_from(["replace", "replace", "delete", "add"]))
        if not path:
            if op == "replace":
                raw = data.draw(_ODD_VALUES)
            break
        parent = raw
        for p in path[:-1]:
            parent = parent[p]
        if op == "replace":
            parent[path[-1]] = data.draw(_ODD_VALUES)
        elif op == "delete":
            del parent[path[-1]]
        elif isinstance(parent, dict):
            parent[data.draw(st.sampled_from(["bogus", "X", "x", "seq", "objects"]))] = data.draw(_ODD_VALUES)
        else:
            parent.append(data.draw(_ODD_VALUES))
    try:
        return msgpack.packb(raw, use_bin_type=True, use_single_float=single)
    except OverflowError:  # a float beyond float32's range
        return msgpack.packb(raw, use_bin_type=True)


def _outcome(fn, payload):
    try:
        return True, fn(payload)
    except DecodeError as exc:
        return False, exc.field


@settings(max_examples=800, deadline=None)
@given(st.sampled_from([*_FAST, "raw"]), st.data())
def test_fast_decoders_accept_reject_and_return_exactly_what_the_model_does(model, data):
    codec = _RAW_CODEC if model == "raw" else _CODECS[model]
    model = codec.model
    payload = _mutated(_FAST[model], data)
    ok, ref = _outcome(lambda b: decode(model, b), payload)
    ok_map, got_map = _outcome(lambda b: decode_map(model, b), payload)
    ok_fast, got_fast = _outcome(codec.decode, payload)
    assert ok_map == ok and ok_fast == ok, (ok, ref, got_map, got_fast)
    if ok:
        want = msgpack.unpackb(encode(ref))
        assert msgpack.unpackb(encode(got_map)) == want
        assert msgpack.unpackb(codec.encode(got_fast)) == want
    else:
        assert got_map == ref and got_fast == ref  # the same field is named
    alone = codec._fast(payload)  # msgspec on its own, before any pydantic fallback: never more permissive
    if alone is not None:
        assert ok and msgpack.unpackb(codec.encode(alone)) == msgpack.unpackb(encode(ref))


def test_fast_decoder_round_trips_and_refuses_models_it_cannot_mirror():
    for model, inst in _FAST.items():
        codec = _CODECS[model]
        got = codec.decode(encode(inst))
        assert msgpack.unpackb(codec.encode(got)) == msgpack.unpackb(encode(inst))
        assert decode_map(model, encode(inst)) == inst.model_dump(mode="python")
    obs = _CODECS[TrackObservation].decode(encode(_rich_observation()))
    assert obs.track.object_id == TID and obs.detection.kinematics.pose_with_covariance.covariance[7] == pytest.approx(0.16)
    for model in (PointCloud, ClassifierConfig):  # Python validators: no exact Struct, no plain-map path
        with pytest.raises(TypeError):
            struct_type(model)
        with pytest.raises(TypeError):
            decode_map(model, encode(_points() if model is PointCloud else ClassifierConfig()))


def test_fast_decoder_takes_what_only_pydantic_coerces():
    raw = msgpack.unpackb(encode(_rich_observation()))
    raw["track"]["x"] = "1.5"  # pydantic's lax mode parses numeric strings; msgspec alone refuses them
    raw["detection"]["kinematics"]["has_twist"] = 1
    got = _CODECS[TrackObservation].decode(msgpack.packb(raw))
    assert got.track.x == 1.5 and got.detection.kinematics.has_twist is True
    raw["track"]["object_id"] = TID + "\n"  # Python's `$` would match before the newline; the model's does not
    with pytest.raises(DecodeError, match="object_id"):
        _CODECS[TrackObservation].decode(msgpack.packb(raw))


def test_raw_covariance_blocks_are_checked_like_the_model_checks_them():
    inst = _rich_tracked()
    got = _RAW_CODEC.decode(encode(inst))
    assert list(block_values(got.objects[1].kinematics.pose_with_covariance.covariance)) == list(_cov(0.02))
    path = ["objects", 1, "kinematics", "twist_with_covariance", "covariance"]
    for idx, value in ((14, -0.5), (3, math.nan), (35, math.inf)):  # negative variance, non-finite anywhere
        cov = list(_cov(0.01))
        cov[idx] = value
        with pytest.raises(DecodeError, match=f"covariance.{idx}"):
            _RAW_CODEC.decode(_mutate(inst, path, cov))
    for cov in ([0.0] * 35, [0.0] * 37):
        with pytest.raises(DecodeError, match="covariance"):
            _RAW_CODEC.decode(_mutate(inst, path, cov))
    ints = _mutate(inst, path, [1] * 36)  # ints and float32s are legal, just not the canonical encoding
    assert list(block_values(_RAW_CODEC.decode(ints).objects[1].kinematics.twist_with_covariance.covariance)) == [1.0] * 36
    raw = inst.model_dump(mode="python")
    del raw["objects"][0]["kinematics"]  # defaults fill in: their covariances must be raw blocks too
    got = _RAW_CODEC.decode(msgpack.packb(raw))
    assert list(block_values(got.objects[0].kinematics.acceleration_with_covariance.covariance)) == [0.0] * 36
    assert msgpack.unpackb(_RAW_CODEC.encode(got)) == msgpack.unpackb(encode(decode(TrackedObjects, msgpack.packb(raw))))
    single = msgpack.packb(inst.model_dump(mode="python"), use_single_float=True)
    assert msgpack.unpackb(_RAW_CODEC.encode(_RAW_CODEC.decode(single))) == msgpack.unpackb(encode(decode(TrackedObjects, single)))


def test_struct_codec_turns_a_key_that_is_not_utf8_into_a_decode_error():
    """msgspec raises UnicodeDecodeError (not its DecodeError) for such a key; a service catching DecodeError
    must still see a rejection, not a crash of its worker."""
    from jitterguard.schemas.fast import StructCodec
    from jitterguard.schemas.models import DetectedObjects

    with pytest.raises(DecodeError, match="DetectedObjects"):
        StructCodec(DetectedObjects).decode(b"\x81\xa2\xca\xca\x01")
