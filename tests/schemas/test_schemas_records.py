"""Fixed-layout msgpack records (schemas.records, the record shapes of schemas.wire): what they write is what the
models read, and what they read back is only ever what the models accept."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from jitterguard.schemas import DecodeError, TrackedColumns, decode, encode, read_tracked_objects
from jitterguard.schemas import wire as tl
from jitterguard.schemas.models import (
    Header,
    ObjectClassification,
    Pose,
    TrackedObject,
    TrackedObjects,
    TrackObservation,
    TrackState,
)
from jitterguard.schemas.records import RecordLayout


def _decode_records(data: bytes):
    """The records of a ``tracked`` payload when it is in the record shape, else None."""
    try:
        cols = read_tracked_objects(data)
    except DecodeError:
        return None
    return None if cols.normalised else cols


def _write(header: dict, records: np.ndarray, observed: list[str] = ()) -> bytes:
    return tl.write_tracked_objects(TrackedColumns(Header(**header), Pose(), records, list(observed)))


def _records(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = rng.normal(0, 0.3, (n, 6, 6))
    cov = (a @ a.transpose(0, 2, 1)).reshape(n, 36)  # a covariance: symmetric, positive semi-definite
    half_yaw = rng.uniform(-np.pi / 2, np.pi / 2, n)  # a unit quaternion about +z
    return tl.TRACKED.pack(n, {
        tl.ID: [f"{int(v):032x}" for v in rng.integers(0, 2**62, n)], tl.EXISTENCE: rng.uniform(0, 1, n),
        tl.LABEL: rng.integers(0, 8, n), tl.LABEL_PROB: rng.uniform(0, 1, n), tl.X: rng.normal(0, 50, n),
        tl.Y: rng.normal(0, 50, n), tl.QZ: np.sin(half_yaw), tl.QW: np.cos(half_yaw), tl.POSE_COV: cov,
        tl.VX: rng.normal(0, 5, n),
        tl.STATIONARY: rng.random(n) < 0.5, tl.ORIENTATION: rng.integers(0, 3, n), tl.LENGTH: rng.uniform(0.5, 6, n),
    })


def _payload(n: int = 12, seed: int = 0) -> tuple[bytes, np.ndarray]:
    rec = _records(n, seed)
    return _write({"stamp": 5, "frame_id": "map", "seq": 3}, rec, ["ab" * 16]), rec


def test_packed_records_decode_with_the_model_to_the_columns() -> None:
    data, rec = _payload()
    msg = decode(TrackedObjects, data)
    assert msg.header == Header(stamp=5, frame_id="map", seq=3) and msg.observed_track_ids == ["ab" * 16]
    assert [o.object_id for o in msg.objects] == [i.decode() for i in rec[tl.ID].tolist()]
    for k, o in enumerate(msg.objects):
        kin = o.kinematics
        assert kin.pose_with_covariance.pose.position.x == rec[tl.X][k]
        assert list(kin.pose_with_covariance.covariance) == rec[tl.POSE_COV]["v"][k].tolist()
        assert kin.is_stationary == (rec[tl.STATIONARY][k] == 0xC3)
        assert o.classification == [ObjectClassification(label=int(rec[tl.LABEL][k]),
                                                         probability=float(rec[tl.LABEL_PROB][k]))]
        assert kin.pose_with_covariance.pose.orientation.w == rec[tl.QW][k]
        assert kin.pose_with_covariance.pose.orientation.x == 0.0  # not given: the example's value
    # and they are byte for byte what encoding the model gives: the layout is msgpack's own form of these maps
    assert encode(msg) == data


def test_a_model_encoded_payload_of_that_shape_is_read_back_as_records() -> None:
    data, rec = _payload(seed=1)
    again = encode(decode(TrackedObjects, data))
    got = _decode_records(again)
    assert got is not None and got.header.seq == 3
    assert RecordLayout.to_bytes(got.objects) == RecordLayout.to_bytes(rec)
    empty = _decode_records(encode(TrackedObjects(header=Header(stamp=1))))
    assert empty is not None and len(empty.objects) == 0


def test_other_shapes_are_left_to_the_general_decoder() -> None:
    obj = TrackedObject(object_id="cd" * 16, classification=[ObjectClassification(label=1, probability=0.6),
                                                             ObjectClassification(label=2, probability=0.4)])
    two_classes = encode(TrackedObjects(header=Header(stamp=1), objects=[obj]))
    assert _decode_records(two_classes) is None
    assert decode(TrackedObjects, two_classes).objects[0].classification[1].label == 2  # valid all the same
    one_class = encode(TrackedObjects(header=Header(stamp=1), objects=[
        TrackedObject(object_id="cd" * 16, classification=[ObjectClassification()])]))
    assert _decode_records(one_class) is not None


@pytest.mark.parametrize("name, value", [
    (tl.EXISTENCE, 1.5), (tl.EXISTENCE, float("nan")), (tl.X, float("inf")), (tl.LABEL_PROB, -0.1),
])
def test_a_value_the_model_refuses_is_never_read_as_a_record(name: str, value: float) -> None:
    data, rec = _payload()
    bad = RecordLayout.copy(rec)
    bad[name][4] = value
    payload = _write({"stamp": 5, "frame_id": "map", "seq": 3}, bad)
    assert _decode_records(payload) is None
    with pytest.raises(DecodeError):
        decode(TrackedObjects, payload)


def test_random_corruptions_are_read_only_where_the_model_accepts_them_and_then_identically() -> None:
    """The fast path's promise: a payload it reads, the model reads too, with the same values."""
    data, _ = _payload(n=6, seed=2)
    rng = np.random.default_rng(7)
    read = refused_by_model = 0
    for _ in range(600):
        buf = bytearray(data)
        for pos in rng.integers(0, len(buf), rng.integers(1, 4)):
            buf[pos] = int(rng.integers(0, 256))
        got = _decode_records(bytes(buf))
        try:
            model = decode(TrackedObjects, bytes(buf))
        except DecodeError:
            refused_by_model += 1
            assert got is None
            continue
        if got is not None:
            read += 1
            assert [o.object_id for o in model.objects] == [i.decode() for i in got.objects[tl.ID].tolist()]
            assert [o.kinematics.pose_with_covariance.pose.position.x for o in model.objects] == \
                got.objects[tl.X].tolist()
            assert [o.existence_probability for o in model.objects] == got.objects[tl.EXISTENCE].tolist()
    assert read > 50 and refused_by_model > 50  # both sides were exercised


def test_copy_keeps_the_bytes_between_fields() -> None:
    _, rec = _payload(n=3)
    dup = RecordLayout.copy(rec)
    dup[tl.X] = 1.0
    assert RecordLayout.to_bytes(dup)[:20] == RecordLayout.to_bytes(rec)[:20]
    assert decode(TrackedObjects, _write({"stamp": 1}, dup)).objects[2].kinematics \
        .pose_with_covariance.pose.position.x == 1.0


def test_pack_refuses_an_id_of_the_wrong_length() -> None:
    with pytest.raises(ValueError, match="object_id"):
        tl.TRACKED.pack(1, {tl.ID: ["abc"]})


def test_track_state_records_are_valid_observations() -> None:
    layout = tl.TRACK_STATE
    rec = layout.pack(2, {"object_id": ["ef" * 16, "01" * 16], "label": [7, 1], "x": [1.5, -2.0], "hits": [3, 10**6],
                          "age_s": [0.0, 12.5]})
    dets = tl.DETECTED.pack(2, {})
    for k, payload in enumerate(tl.write_track_observations(Header(stamp=1, seq=9), dets, rec)):
        st = decode(TrackObservation, payload).track
        assert st == TrackState(object_id=["ef" * 16, "01" * 16][k], label=[7, 1][k], x=[1.5, -2.0][k],
                                y=0.0, hits=[3, 10**6][k], age_s=[0.0, 12.5][k])
        assert msgpack.unpackb(payload)["header"] == {"stamp": 1, "frame_id": "map", "seq": 9}


def test_a_layout_refuses_rules_it_cannot_carry() -> None:
    from jitterguard.schemas.models import ClassifierConfig, PointCloud

    for model, example in ((ClassifierConfig, ClassifierConfig()),
                           (PointCloud, PointCloud(header=Header(stamp=1), num_points=0, data=b""))):
        with pytest.raises(TypeError):
            RecordLayout.of(model, example)
