"""Bounded work per message, in all: the bounds on each list and each map left the number of them open, so a
payload of nested lists of empty maps (one byte each) was built in full — 60–100× its size in memory and seconds of
a worker — before it was refused. Now the maps and lists one payload builds are bounded by its size
(:class:`~jitterguard.schemas.codec.ContainerBudget`), in both forms a hot message is read in, and so is every list
of the record form's envelope (an ``observed_track_ids`` of 200 000 IDs had passed there)."""

from __future__ import annotations

import msgpack
import pytest

from jitterguard.schemas import wire
from jitterguard.schemas.codec import BYTES_PER_CONTAINER, CONTAINER_FLOOR, LimitExceeded, decode, encode
from jitterguard.schemas.models import Header, Pose, TrackedObjects, TrackObservation


def _array(n: int) -> bytes:
    return b"\xdc" + n.to_bytes(2, "big")


def _nested_empty_maps(outer: int) -> bytes:
    """``outer`` × 1024 lists of 1024 empty maps each: every list within the per-list bound, one byte a map."""
    inner = _array(1024) + b"\x80" * 1024
    return _array(outer) + (_array(1024) + inner * 1024) * outer


def test_a_track_observation_of_a_million_empty_maps_is_refused_as_over_the_budget() -> None:
    header = msgpack.packb({"stamp": 1, "frame_id": "map", "seq": 1})
    payload = (b"\x84" + msgpack.packb("schema_version") + msgpack.packb(1) + msgpack.packb("header") + header
               + msgpack.packb("track") + _nested_empty_maps(1) + msgpack.packb("detection") + msgpack.packb({}))
    assert len(payload) < wire.LIMITS.max_payload_bytes
    read = wire.read_track_observations([payload])
    (_, err), = read.errors
    assert isinstance(err, LimitExceeded) and "maps and lists" in str(err), err
    with pytest.raises(LimitExceeded, match="maps and lists"):  # the general reading too
        decode(TrackObservation, payload)


def test_the_record_forms_envelope_is_bounded_like_the_models_reading() -> None:
    ids = [f"{i:032x}" for i in range(1, 20_001)]
    payload = wire.write_tracked_objects(wire.TrackedColumns(Header(stamp=1, seq=1), Pose(), wire.TRACKED.pack(0, {}),
                                                             ids))
    with pytest.raises(LimitExceeded, match="more than 1024 items"):
        wire.read_tracked_objects(payload)
    flat = (b"\x84" + msgpack.packb("schema_version") + msgpack.packb(1) + msgpack.packb("header")
            + msgpack.packb({"stamp": 1, "frame_id": "map", "seq": 1}) + msgpack.packb("junk")
            + b"\xdd" + (1 << 20).to_bytes(4, "big") + b"\x80" * (1 << 20) + msgpack.packb("objects") + b"\x90")
    with pytest.raises(LimitExceeded):
        wire.read_tracked_objects(flat)


def test_real_messages_stay_well_inside_the_budget() -> None:
    """A full-size message, built as the services build them, is read whole: the budget refuses none of them."""
    from jitterguard.schemas.models import TrackedObject

    msg = TrackedObjects(header=Header(stamp=1, seq=1), objects=[TrackedObject(object_id=f"{i:032x}")
                                                                  for i in range(1, 1001)])
    data = encode(msg)
    assert decode(TrackedObjects, data) == msg
    containers = 1 + 1000 * sum(1 for _ in _containers(msgpack.unpackb(data)["objects"][0]))
    assert containers * BYTES_PER_CONTAINER < len(data) + CONTAINER_FLOOR * BYTES_PER_CONTAINER


def _containers(value: object):
    if isinstance(value, (dict, list)):
        yield value
        for v in value.values() if isinstance(value, dict) else value:
            yield from _containers(v)


def test_a_scan_is_held_to_a_few_maps_whatever_its_size() -> None:
    """A scan's bulk is one byte string: nested empty maps in a 2 MiB payload are refused after 64 maps and lists,
    not after the hundred thousand its size would allow; a real scan (any size) is read."""
    import numpy as np

    from jitterguard.schemas.models import PointCloud

    real = PointCloud(header=Header(stamp=1, seq=1), num_points=200_000,
                      data=np.zeros((200_000, 4), np.float32).tobytes())
    assert decode(PointCloud, encode(real), max_array_len=1024, max_map_len=64) == real
    header = msgpack.packb({"stamp": 1, "frame_id": "lidar", "seq": 1})
    hostile = (b"\x83" + msgpack.packb("schema_version") + msgpack.packb(1) + msgpack.packb("header") + header
               + msgpack.packb("junk") + _array(1024) + (_array(1024) + b"\x80" * 1024) * 2)
    with pytest.raises(LimitExceeded, match="more than 64 maps and lists"):
        decode(PointCloud, hostile, max_array_len=1024, max_map_len=64)
