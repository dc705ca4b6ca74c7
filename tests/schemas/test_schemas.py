"""The wire contract: round trips, every validation rule DESIGN.md lists, and decode fuzzing."""

from __future__ import annotations

import copy
import math
import re
import sys

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


def test_a_config_holding_negative_zero_is_the_config_holding_zero():
    """-0.0 == 0.0, but a config holding -0.0 had its own version tag: a conditional write naming the tag read for
    the equal config was refused with 412. Every float field, map value and list entry is kept as 0.0."""
    from jitterguard.schemas.models import config_etag

    neg = ClassifierConfig(min_speed_mps=-0.0, view_slide_m_per_class={"car": -0.0}, alpha_default=1.5)
    pos = ClassifierConfig(min_speed_mps=0.0, view_slide_m_per_class={"car": 0.0}, alpha_default=1.5)
    assert config_etag(neg) == config_etag(pos)
    assert math.copysign(1.0, neg.min_speed_mps) == 1.0 and math.copysign(1.0, neg.view_slide_m_per_class["car"]) == 1.0
    assert config_etag(ClassifierConfig(min_speed_mps=0.1)) != config_etag(pos)  # other values are untouched


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


# ------------------------------------------------------------------ the read functions agree with the models
# read_<message> views records where the payload has their shape and asks the model otherwise: it must accept
# exactly what decode accepts (within the limits), give the columns the model's values give, and name the same
# field when it refuses.

from jitterguard.schemas import wire  # noqa: E402
from jitterguard.schemas.models import (  # noqa: E402
    Point,
    Pose,
    PoseWithCovariance,
    Quaternion,
    Shape,
    TrackedObjectKinematics,
    Vector3,
)
from jitterguard.schemas.records import RecordLayout  # noqa: E402


def _cov(seed: float) -> tuple[float, ...]:
    return tuple(seed * (i + 1) if i in (0, 7, 14, 21, 28, 35) else -seed * i / 7 for i in range(36))


def _rich_tracked(odd: bool = True) -> TrackedObjects:
    ids = [TID, "fedcba9876543210fedcba9876543210"]
    classes = [ObjectClassification(label=Label.CAR, probability=0.4), ObjectClassification(label=Label.TRUCK, probability=0.6)]
    objs = [
        TrackedObject(
            object_id=tid, existence_probability=0.75, classification=classes if odd else classes[1:],
            kinematics=TrackedObjectKinematics(
                pose_with_covariance=PoseWithCovariance(
                    pose=Pose(position=Point(x=12.5 * k, y=-3.25, z=0.5), orientation=Quaternion(z=0.38, w=0.92)),
                    covariance=_cov(0.01 * (k + 1))),
                orientation_availability=1, is_stationary=bool(k)),
            shape=Shape(type=2, footprint=[Point(x=1.0, y=2.0), Point(x=-1.0, y=0.5), Point(x=0.0, y=-1.0)] if odd else [],
                        dimensions=Vector3(x=4.5, y=1.9, z=1.6)),
        )
        for k, tid in enumerate(ids)
    ]
    return TrackedObjects(header=Header(stamp=1_700_000_000_000_000_000, frame_id="map", seq=42),
                          ego_pose=Pose(position=Point(x=3.0, y=4.0)), objects=objs, observed_track_ids=ids)


def _rich_detections(odd: bool = True) -> DetectedObjects:
    t = _rich_tracked(odd)
    objs = [DetectedObject(existence_probability=o.existence_probability, classification=o.classification,
                           shape=o.shape) for o in t.objects]
    for o, src in zip(objs, t.objects):
        o.kinematics.pose_with_covariance = src.kinematics.pose_with_covariance
        o.kinematics.has_position_covariance = True
    return DetectedObjects(header=Header(stamp=5, frame_id="lidar", seq=3), ego_pose=t.ego_pose, objects=objs)


def _rich_observation() -> TrackObservation:
    det = DetectedObject(existence_probability=0.9, classification=[ObjectClassification(label=Label.PEDESTRIAN)])
    det.kinematics.pose_with_covariance.covariance = _cov(0.02)
    det.kinematics.has_position_covariance = True
    return TrackObservation(header=Header(stamp=5, seq=3), detection=det,
                            track=TrackState(object_id=TID, label=7, x=-1.5, y=2.5, yaw=0.3, vx=1.25, vy=-0.5, hits=4, age_s=0.4))


def _expected_objects(layout: RecordLayout, objs: list) -> list[dict]:
    """What the columns must hold: the model's objects, normalised to the record shape."""
    return _got_objects(wire.records_of(layout, objs))


def _got_objects(records) -> list[dict]:
    return [msgpack.unpackb(RecordLayout.to_bytes(records[k:k + 1])) for k in range(len(records))]


_NO_LIMITS = wire.Limits(max_abs_coordinate_m=sys.float_info.max, max_abs_speed_mps=sys.float_info.max,
                         max_variance=sys.float_info.max, max_correlation=math.inf, max_quaternion_error=math.inf,
                         max_dimension_m=sys.float_info.max, max_abs_yaw_rad=sys.float_info.max)
"""The limits are tested on their own below; here the read functions must agree with the model exactly (every
finite value is within these; hypothesis once drew 1.7000000000000001e+308, just past a rounder bound)."""


def _read(model, payload):
    if model is TrackObservation:
        cols = wire.read_track_observations([payload], _NO_LIMITS)
        if cols.errors:
            raise cols.errors[0][1]
        return cols
    return (wire.read_tracked_objects if model is TrackedObjects else wire.read_detected_objects)(payload, _NO_LIMITS)


def _agree(model, payload) -> None:
    ok, ref = _outcome(lambda b: decode(model, b), payload)
    ok_read, got = _outcome(lambda b: _read(model, b), payload)
    assert ok_read == ok, (ref, got)
    if not ok:
        assert got == ref  # the same field is named
        return
    if model is TrackObservation:
        assert got.seq.tolist() == [ref.header.seq] and got.stamp.tolist() == [ref.header.stamp]
        assert _got_objects(got.detections) == _expected_objects(wire.DETECTED, [ref.detection])
        assert _got_objects(got.tracks) == _expected_objects(wire.TRACK_STATE, [ref.track])
        return
    assert got.header == ref.header and got.ego_pose == ref.ego_pose
    layout = wire.TRACKED if model is TrackedObjects else wire.DETECTED
    assert _got_objects(got.objects) == _expected_objects(layout, ref.objects)
    if model is TrackedObjects:
        assert got.observed_track_ids == ref.observed_track_ids
    else:
        assert got.area.tolist() == pytest.approx([wire._area(o.shape) for o in ref.objects])


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
    for _ in range(data.draw(st.integers(0, 3))):
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


_READ = {TrackedObjects: _rich_tracked, DetectedObjects: _rich_detections, TrackObservation: _rich_observation}


@settings(max_examples=600, deadline=None)
@given(st.sampled_from(list(_READ)), st.booleans(), st.data())
def test_read_functions_accept_reject_and_return_what_the_model_does(model, odd, data):
    make = _READ[model]
    inst = make(odd) if model is not TrackObservation else make()
    _agree(model, _mutated(inst, data))


def test_records_shape_is_read_as_records_and_the_rest_is_normalised_and_said():
    plain = wire.read_tracked_objects(encode(_rich_tracked(odd=False)))
    assert not plain.normalised and not plain.objects.flags.writeable  # a view of the payload
    odd = wire.read_tracked_objects(encode(_rich_tracked(odd=True)))
    assert odd.normalised
    assert odd.objects[wire.LABEL].tolist() == [Label.TRUCK, Label.TRUCK]  # the most probable class
    det = wire.read_detected_objects(encode(_rich_detections(odd=True)))
    assert det.normalised and det.area.tolist() == pytest.approx([2.25, 2.25])  # the polygon's area, kept
    assert wire.write_tracked_objects(plain) == encode(_rich_tracked(odd=False))  # written back byte for byte
    single = msgpack.packb(_rich_tracked(odd=False).model_dump(mode="python"), use_single_float=True)
    assert wire.read_tracked_objects(single).normalised  # float32 is legal msgpack, not the record shape


def test_observations_are_read_in_batches_and_a_bad_one_costs_only_itself():
    good = wire.write_track_observations(Header(stamp=5, seq=3), wire.records_of(wire.DETECTED, [_rich_observation().detection]),
                                         wire.records_of(wire.TRACK_STATE, [_rich_observation().track]))[0]
    assert decode(TrackObservation, good) == _rich_observation()
    cols = wire.read_track_observations([good, b"\x00junk", encode(_rich_observation()), good[:-1], good])
    assert cols.index.tolist() == [0, 2, 4] and cols.normalised == 1  # the model read the third
    assert [i for i, _ in cols.errors] == [1, 3] and all(isinstance(e, DecodeError) for _, e in cols.errors)
    assert cols.tracks["object_id"].tolist() == [TID.encode()] * 3


def test_a_batch_with_a_refused_observation_is_freed_without_the_cycle_collector():
    """The error kept for a refused payload had kept its traceback, whose frame held the error list and the whole
    batch (and the frames below it the payload's copy and its unpacked map): a reference cycle, freed only when the
    garbage collector next ran: three rounds of 20,000 refused 100 kB observations grew the classifier 231 → 862 MB
    (``scripts/flood_memory.py --pad 100000``). The errors keep no traceback: the batch goes when its columns do."""
    import gc

    bad = msgpack.packb({**msgpack.unpackb(encode(_rich_observation())), "pad": b"\0" * 1000})
    gc.collect()
    gc.disable()
    try:
        cols = wire.read_track_observations([bad, b"\x00junk", encode(_rich_observation())])
        assert [i for i, _ in cols.errors] == [0, 1]
        del cols
        assert gc.collect() == 0  # nothing was left for the cycle collector
    finally:
        gc.enable()


def test_an_observation_read_in_another_form_and_then_refused_is_not_counted_as_normalised():
    """A payload the model read (another valid msgpack form) and then refused — about another track than its key
    names — had been counted `normalised` as well as rejected."""
    other = encode(_rich_observation())  # the model's own form, not the record shape
    cols = wire.read_track_observations([other, other], key_ids=[TID, "f" * 32])
    assert cols.index.tolist() == [0] and [i for i, _ in cols.errors] == [1]
    assert cols.normalised == 1


def test_a_key_that_is_not_utf8_is_a_decode_error():
    for read in (wire.read_detected_objects, wire.read_tracked_objects):
        with pytest.raises(DecodeError):
            read(b"\x81\xa2\xca\xca\x01")


# ------------------------------------------------------------------ limits: bounded work per message


def test_oversized_payloads_are_refused_from_their_headers():
    limits = wire.Limits(max_objects=10, max_payload_bytes=4096)
    many = msgpack.packb({"schema_version": 1, "header": {"stamp": 1}, "objects": [{}] * 11})
    with pytest.raises(wire.LimitExceeded, match="11 objects exceed max_objects 10"):
        wire.read_detected_objects(many, limits)
    with pytest.raises(wire.LimitExceeded, match="objects"):  # in another form too: counted before validation
        wire.read_detected_objects(msgpack.packb({"objects": [{}] * 11, "header": {"stamp": 1}, "x": 1}), limits)
    with pytest.raises(wire.LimitExceeded, match="bytes exceed"):
        wire.read_tracked_objects(b"\x80" + b"\x00" * 5000, limits)
    huge = msgpack.packb({"schema_version": 1, "header": {"stamp": 1}, "objects": [{}] * 1_000_000})
    with pytest.raises(wire.LimitExceeded):  # the default limit: read from the header, in no time
        wire.read_detected_objects(huge)


@pytest.mark.parametrize(("path", "value", "field", "bound"), [
    (["objects", 0, "kinematics", "pose_with_covariance", "pose", "position", "x"], 1e300, "position.x",
     "max_abs_coordinate_m"),
    (["objects", 1, "kinematics", "pose_with_covariance", "covariance"], [0.0] * 7 + [1e9] + [0.0] * 28, "covariance",
     "an entry beyond max_variance"),
    # a correlation past 1 with small variances: the message had named no bound, and sent operators to max_variance
    (["objects", 1, "kinematics", "pose_with_covariance", "covariance"], [1.0, 50.0] + [0.0] * 4 + [50.0, 1.0]
     + [0.0] * 28, "covariance", "x-y covariance beyond max_correlation"),
    (["objects", 0, "kinematics", "twist_with_covariance", "twist", "linear", "y"], -5e3, "linear.y",
     "max_abs_speed_mps"),
    (["ego_pose", "position", "y"], 2e7, "ego_pose.position", "max_abs_coordinate_m"),
    (["objects", 1, "shape", "dimensions", "x"], 1e300, "shape.dimensions.x", "max_dimension_m"),  # had overflowed
    (["objects", 0, "shape", "dimensions", "z"], -2e3, "shape.dimensions.z", "max_dimension_m"),  # areas and IoUs
])
def test_coordinates_variances_and_speeds_beyond_the_limits_are_refused_naming_the_bound(path, value, field, bound):
    payload = _mutate(_rich_tracked(odd=False), path, value)
    decode(TrackedObjects, payload)  # valid for the model...
    with pytest.raises(wire.LimitExceeded, match=field) as err:  # ...but beyond what any real sensor reports
        wire.read_tracked_objects(payload)
    assert bound in str(err.value)


def test_a_track_state_heading_beyond_the_limit_and_a_repeated_track_are_refused():
    obs = msgpack.unpackb(encode(_rich_observation()))
    obs["track"]["yaw"] = 1e300
    (err,) = wire.read_track_observations([msgpack.packb(obs)]).errors
    assert isinstance(err[1], wire.LimitExceeded) and "track.yaw" in str(err[1])
    obs["track"]["yaw"] = -3 * math.pi  # unwrapped, but a heading
    assert not wire.read_track_observations([msgpack.packb(obs)]).errors
    tracked = _rich_tracked(odd=False)
    twice = tracked.model_copy(update={"objects": [tracked.objects[0], tracked.objects[1], tracked.objects[0]]})
    with pytest.raises(DecodeError, match=r"objects\.2\.object_id: repeats objects\.0"):  # published twice before
        wire.read_tracked_objects(encode(twice))


def test_a_top_level_key_given_twice_is_refused_whatever_reads_it():
    """msgpack keeps a repeated key's last value, while the services judge a frame's order by its first
    ``header`` (peek_header): a payload with two headers would be ordered as one frame and applied as another."""
    good = _rich_tracked(odd=False)
    first, second = msgpack.packb("header") + msgpack.packb({"stamp": 7, "seq": 6}), msgpack.packb("header")
    second += msgpack.packb({"stamp": 2**63 - 1, "seq": 2**62})
    rest = b"".join(msgpack.packb(k) + msgpack.packb(v) for k, v in good.model_dump(mode="python").items()
                    if k != "header")
    forged = bytes([0x80 | (len(good.model_dump()) + 1)]) + first + second + rest
    assert wire.peek_header(forged) == (6, 7)
    for read in (wire.read_tracked_objects, lambda b: decode(TrackedObjects, b)):
        with pytest.raises(DecodeError, match="given more than once"):
            read(forged)
    obs = _rich_observation().model_dump(mode="python")
    twice = b"\x85" + msgpack.packb("header") + msgpack.packb({"stamp": 1, "seq": 1}) + b"".join(
        msgpack.packb(k) + msgpack.packb(v) for k, v in obs.items())
    cols = wire.read_track_observations([twice])
    assert len(cols.index) == 0 and "given more than once" in str(cols.errors[0][1])


def test_lists_beyond_their_bound_are_refused_before_they_are_built():
    """A list of millions of one-byte maps (classifications, footprint points) is refused from its header, and an
    object count beyond ``max_objects`` is read from the header in the model's form too."""
    limits = wire.Limits(max_list_items=100)
    det = _rich_detections(odd=False).model_dump(mode="python")
    det["objects"][0]["shape"]["footprint"] = [{}] * 101
    with pytest.raises(wire.LimitExceeded, match="holds more than 100 items"):
        wire.read_detected_objects(msgpack.packb(det), limits)
    det["objects"][0]["shape"]["footprint"] = [{}] * 100  # at the bound: read (by the model) and normalised
    assert wire.read_detected_objects(msgpack.packb(det), limits).normalised
    obs = _rich_observation().model_dump(mode="python")
    obs["detection"]["classification"] = [{}] * 101
    cols = wire.read_track_observations([msgpack.packb(obs)], limits)
    assert len(cols.index) == 0 and isinstance(cols.errors[0][1], wire.LimitExceeded)
    body = b"".join(msgpack.packb(k) + msgpack.packb(v) for k, v in det.items() if k != "objects")
    many = bytes([0x80 | len(det)]) + body + msgpack.packb("objects") + b"\xdd" + (5000).to_bytes(4, "big")
    with pytest.raises(wire.LimitExceeded, match="5000 objects exceed max_objects 1000"):  # unread: 4 bytes say it
        wire.read_detected_objects(many + b"\x80" * 5000)
    with pytest.raises(wire.LimitExceeded, match="5000 objects exceed"):  # also behind a repeated key
        wire.read_detected_objects(bytes([0x80 | (len(det) + 1)]) + msgpack.packb("header") + msgpack.packb(
            det["header"]) + many[1:] + b"\x80" * 5000)


def test_maps_beyond_any_models_fields_are_refused_before_they_are_built():
    """A hot message's maps have fixed fields; one of 100 000 keys (in an object, in the header, or at the top level)
    had been built and handed to pydantic, which lists every unknown key as an error: a 4 MB payload of one such map
    cost a service's worker 2 s. It is refused from the map's header now (LimitExceeded, counted ``over_limit``),
    whatever the read function; a map at the bound is read by the model as before."""
    keys_ = {f"k{i}": 0 for i in range(100_000)}
    det = _rich_detections(odd=False).model_dump(mode="python")
    obs = _rich_observation().model_dump(mode="python")
    tracked = _rich_tracked(odd=False).model_dump(mode="python")
    in_object = copy.deepcopy(det)
    in_object["objects"][0]["kinematics"] = {**in_object["objects"][0]["kinematics"], **keys_}
    in_header = {**tracked, "header": {**tracked["header"], **keys_}}
    for read, payload in ((wire.read_detected_objects, in_object), (wire.read_detected_objects, keys_),
                          (wire.read_tracked_objects, in_header), (wire.read_tracked_objects, keys_)):
        with pytest.raises(wire.LimitExceeded, match=f"map holds more than {wire.MAX_MAP_ENTRIES} entries"):
            read(msgpack.packb(payload))
    for payload in ({**obs, "track": {**obs["track"], **keys_}}, keys_):
        cols = wire.read_track_observations([msgpack.packb(payload)])
        assert len(cols.index) == 0 and isinstance(cols.errors[0][1], wire.LimitExceeded)
    with pytest.raises(wire.LimitExceeded):
        decode(TrackedObjects, msgpack.packb(in_header), max_map_len=wire.MAX_MAP_ENTRIES)
    assert wire.peek_header(msgpack.packb(in_header)) is None
    few = {f"k{i}": 0 for i in range(wire.MAX_MAP_ENTRIES - len(det["objects"][0]["kinematics"]))}
    at_bound = copy.deepcopy(det)
    at_bound["objects"][0]["kinematics"].update(few)
    with pytest.raises(DecodeError, match="Extra inputs") as exc:  # the model names the first unknown key
        wire.read_detected_objects(msgpack.packb(at_bound))
    assert not isinstance(exc.value, wire.LimitExceeded)


@pytest.mark.parametrize(("path", "value", "field"), [
    (["objects", 1, "kinematics", "pose_with_covariance", "covariance"],
     [0.04, 0.05] + [0.0] * 4 + [0.05, 0.04] + [0.0] * 28, "pose_with_covariance.covariance"),  # |ρ| = 1.25
    (["objects", 0, "kinematics", "pose_with_covariance", "pose", "orientation"],
     {"x": 1e200, "y": 1e200, "z": 1e200, "w": -1e200}, "pose.orientation"),
    (["objects", 0, "kinematics", "pose_with_covariance", "pose", "orientation"],
     {"x": 0.0, "y": 0.0, "z": 1.0, "w": 1.0}, "pose.orientation"),  # length √2: a heading read off it is 117°
    (["ego_pose", "orientation"], {"x": 0.0, "y": 0.0, "z": 0.0, "w": 0.0}, "ego_pose.orientation"),
])
def test_covariances_that_are_none_and_orientations_that_are_no_rotation_are_refused(path, value, field):
    """A covariance whose x-y block has |cxy| > sqrt(cxx·cyy) turns into a negative variance once rotated (and made
    the classifier call a moving car static); a quaternion far from unit length gives a wrong heading, or NaN."""
    payload = _mutate(_rich_tracked(odd=False), path, value)
    decode(TrackedObjects, payload)  # valid for the model...
    with pytest.raises(wire.LimitExceeded, match=field):  # ...but no covariance, no rotation
        wire.read_tracked_objects(payload)
    rounded = _mutate(_rich_tracked(odd=False), ["ego_pose", "orientation"], {"z": 0.38, "w": 0.92})
    assert wire.read_tracked_objects(rounded).ego_pose.orientation.z == 0.38  # within max_quaternion_error


def test_a_singular_covariance_rotates_to_no_negative_variance():
    """cxy² = cxx·cyy (a box known only along one diagonal) is a covariance; rotated by any yaw its variances stay
    ≥ 0, so the tracker never republishes what the classifier's reader refuses."""
    from jitterguard.geometry import rotate_cov6

    cov = np.zeros((1, 36))
    cov[0, [0, 7]], cov[0, [1, 6]] = 0.04, -0.04 * (1 + 5e-7)
    rotated = np.concatenate([rotate_cov6(cov, yaw) for yaw in np.linspace(0.0, 2 * np.pi, 4001)])
    assert (rotated[:, [0, 7]] >= 0.0).all()
    assert rotated[:, [0, 7]].min() == 0.0  # the clamp acted: without it the smallest is about -1e-8


def test_a_rank_one_covariance_rotated_onto_an_axis_is_read():
    """A covariance known along one axis only, rotated by the ego yaw onto a world axis, comes out of R Σ Rᵀ as
    cxx 2, cyy 0 and a rounding residue cxy 2.2e-16: a covariance, but past the relative bound |cxy| ≤ sqrt(cxx·cyy)
    = 0, so the classifier's reader refused the observations the tracker had published. A real excess is still
    refused."""
    for cxy, ok in ((2.2e-16, True), (-2.2e-16, True), (1e-6, False)):
        cov = [2.0, cxy] + [0.0] * 4 + [cxy, 0.0] + [0.0] * 28
        payload = _mutate(_rich_tracked(odd=False),
                          ["objects", 1, "kinematics", "pose_with_covariance", "covariance"], cov)
        if ok:
            assert len(wire.read_tracked_objects(payload).objects) == len(_rich_tracked(odd=False).objects)
        else:
            with pytest.raises(wire.LimitExceeded, match="pose_with_covariance.covariance"):
                wire.read_tracked_objects(payload)


def test_a_stamp_beyond_int64_is_refused_on_receipt():
    for stamp in (2**63, 2**64 - 1):
        with pytest.raises(DecodeError, match="header.stamp"):
            wire.read_detected_objects(_mutate(_rich_detections(odd=False), ["header", "stamp"], stamp))


def test_peek_header_reads_seq_and_stamp_without_validating():
    assert wire.peek_header(encode(_rich_observation())) == (3, 5)
    assert wire.peek_header(encode(_rich_tracked())) == (42, 1_700_000_000_000_000_000)
    assert wire.peek_header(b"\x00garbage") is None
    assert wire.peek_header(msgpack.packb({"header": {"seq": "x", "stamp": 1}})) is None
    assert wire.peek_header(msgpack.packb([1, 2])) is None
    # values the header model refuses are not a frame's order: the read refuses the payload (counted rejected),
    # where judged by them it had been dropped as a jump or a late frame
    for seq, stamp in ((2**64 - 1, 1), (-5, 1), (1, -1), (1, 2**64 - 1), (True, 1)):
        assert wire.peek_header(msgpack.packb({"header": {"seq": seq, "stamp": stamp}})) is None, (seq, stamp)
    assert wire.peek_header(msgpack.packb({"header": {"seq": 2**63 - 1, "stamp": 0}})) == (2**63 - 1, 0)


@pytest.mark.parametrize(("path", "value", "field"), [
    (["header", "seq"], "12", "header.seq"),
    (["header", "stamp"], 1.0, "header.stamp"),
    (["objects", 0, "kinematics", "pose_with_covariance", "pose", "position", "x"], "10.5", "position.x"),
    (["objects", 0, "kinematics", "has_position_covariance"], "yes", "has_position_covariance"),
    (["objects", 0, "classification", 0, "label"], True, "label"),
    (["objects", 0, "classification", 0, "label"], 1.0, "label"),
    (["objects", 0, "kinematics", "pose_with_covariance", "covariance"], ["0.1"] + [0.0] * 35, "covariance.0"),
])
def test_a_value_of_the_wrong_type_is_refused_not_coerced(path, value, field):
    """The wire is strict: a string "12" had been read as seq 12, "yes" as True, True and 1.0 as label 1."""
    payload = _mutate(_rich_tracked(odd=False), path, value)
    for read in (lambda d: decode(TrackedObjects, d), wire.read_tracked_objects):
        with pytest.raises(DecodeError, match=re.escape(field)):
            read(payload)
    assert decode(TrackedObjects, _mutate(_rich_tracked(odd=False), ["header", "seq"], 12)).header.seq == 12


@pytest.mark.parametrize("version", ["missing", True, 2, 1.0])
def test_a_payload_must_say_it_was_written_to_this_schema_version(version) -> None:
    """A payload without schema_version (or True, which equals 1) had been read as version 1."""
    raw = msgpack.unpackb(encode(_rich_tracked()))
    if version == "missing":
        del raw["schema_version"]
    else:
        raw["schema_version"] = version
    data = msgpack.packb(raw)
    for read in (lambda d: decode(TrackedObjects, d), wire.read_tracked_objects):
        with pytest.raises(DecodeError, match=r"TrackedObjects\.schema_version: must be 1"):
            read(data)
    raw["schema_version"] = 1
    assert decode(TrackedObjects, msgpack.packb(raw)) == _rich_tracked()


def test_a_heading_is_read_right_off_a_quaternion_the_wire_accepts_as_near_unit() -> None:
    """The wire takes quaternions 1 % off unit length; the unit-quaternion shortcut 1 − 2(y² + z²) had read such a
    90° heading as 91.1°. Unit ones keep their headings bit for bit (the shortcut still serves them), and the array
    form equals the scalar one element by element."""
    import math

    from jitterguard.geometry import yaw_from_quaternion, yaws_from_quaternions

    for yaw in (0.3, math.pi / 2, 2.5, -1.2):
        x, y, z, w = 0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)
        assert yaw_from_quaternion(x, y, z, w) == math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
        for scale in (0.99, 1.01):
            assert yaw_from_quaternion(x * scale, y * scale, z * scale, w * scale) == pytest.approx(yaw, abs=1e-12)
    qs = np.array([[0.0, 0.0, math.sin(0.7), math.cos(0.7)], [0.0, 0.0, 0.7141, 0.7141], [0.01, 0.02, 0.3, 0.95]])
    arr = yaws_from_quaternions(*qs.T)
    assert arr.tolist() == [yaw_from_quaternion(*q) for q in qs.tolist()]
    assert arr[1] == pytest.approx(math.pi / 2, abs=1e-12)  # 1.0099 × a unit 90° quaternion


def test_a_state_reply_is_refused_past_its_bounds_before_it_is_built() -> None:
    """The sidecar reads ``classifier/state`` within ``wire.STATE_REPLY_BOUNDS``: a reply over 64 MiB is refused from
    its size, a list longer than any frame can hold before it is built; a real state of 1,000 tracks passes."""
    from jitterguard.schemas.codec import decode_with_raw
    from jitterguard.schemas.models import ClassifierConfig, ClassifierStateSnapshot, Header, TrackStateEntry

    with pytest.raises(wire.LimitExceeded, match="bytes exceed 67108864"):
        decode_with_raw(ClassifierStateSnapshot, b"\x80" + bytes(64 << 20), **wire.STATE_REPLY_BOUNDS)
    long_list = msgpack.packb({"schema_version": 1, "tracks": [0] * ((1 << 18) + 1)})
    with pytest.raises(wire.LimitExceeded, match="a list holds more than 262144 items"):
        decode_with_raw(ClassifierStateSnapshot, long_list, **wire.STATE_REPLY_BOUNDS)
    entry = dict(label=1, state="static", z_x=0.1, z_y=0.2, chi2=0.3, alpha=2.58, threshold=2.58, window_length=20,
                 window_size=20, speed=0.1, x=10.0, y=5.0, last_update_ns=1, last_seq=1)
    snap = ClassifierStateSnapshot(header=Header(stamp=1, seq=1), config=ClassifierConfig(), counters={"frames": 1},
                                   tracks=[TrackStateEntry(track_id=f"{i:032x}", **entry) for i in range(1000)])
    data = encode(snap)
    back, _ = decode_with_raw(ClassifierStateSnapshot, data, **wire.STATE_REPLY_BOUNDS)
    assert back == snap and len(data) < 1 << 20
