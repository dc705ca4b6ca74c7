"""The hot messages' object lists as record arrays (:mod:`.layout`): the tracker reads ``detections`` and
writes ``tracked`` (and each ``TrackObservation``'s detection and ``TrackState``) this way, and the classifier
reads ``tracked`` and writes ``objects`` this way. The slot names below are shared by ``TrackedObject`` and
``DetectedObject`` where their paths are the same.

The shape is the one every tracker output here has — one classification, no footprint, a 32-hex-digit
``object_id`` — and, because msgspec and msgpack-python write floats as float64 and these small ints as fixints,
it is also the shape of any such ``TrackedObjects`` encoded by them. A payload of another shape (several
classifications, a polygon footprint) or with any value the model refuses is not read here:
:func:`decode_tracked_records` returns ``None`` and the caller falls back to the general decoder.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import cache
from typing import Any

import msgspec
import numpy as np

from .fast import struct_type
from .layout import RecordLayout, array_header
from .models import SCHEMA_VERSION, DetectedObject, DetectedObjects, TrackedObject, TrackedObjects, TrackState

ID = "object_id"
EXISTENCE = "existence_probability"
LABEL = "classification.0.label"
LABEL_PROB = "classification.0.probability"
_POSE = "kinematics.pose_with_covariance"
X, Y, Z = (f"{_POSE}.pose.position.{a}" for a in "xyz")
QX, QY, QZ, QW = (f"{_POSE}.pose.orientation.{a}" for a in "xyzw")
POSE_COV = f"{_POSE}.covariance"
_TWIST = "kinematics.twist_with_covariance"
VX, VY, VZ = (f"{_TWIST}.twist.linear.{a}" for a in "xyz")
WX, WY, WZ = (f"{_TWIST}.twist.angular.{a}" for a in "xyz")
TWIST_COV = f"{_TWIST}.covariance"
ORIENTATION = "kinematics.orientation_availability"
HAS_POSITION_COV = "kinematics.has_position_covariance"  # DetectedObject only
STATIONARY = "kinematics.is_stationary"
SHAPE_TYPE = "shape.type"
LENGTH, WIDTH, HEIGHT = (f"shape.dimensions.{a}" for a in "xyz")


@cache
def tracked_object_layout() -> RecordLayout:
    """The record layout of a ``TrackedObject`` with one classification and no footprint."""
    t = struct_type(TrackedObject)
    example = msgspec.convert({"object_id": "0" * 32, "classification": [{"label": 0, "probability": 1.0}]}, t)
    return RecordLayout.of(t, example)


@cache
def track_state_layout() -> RecordLayout:
    """The record layout of the ``TrackState`` that rides with each ``TrackObservation``."""
    t = struct_type(TrackState)
    return RecordLayout.of(t, msgspec.convert({"object_id": "0" * 32, "x": 0.0, "y": 0.0}, t))


@cache
def detected_object_layout() -> RecordLayout:
    """The record layout of a ``DetectedObject`` with one classification and no footprint (what the detector,
    the replay's detection-level sources and msgspec/msgpack writers of such objects produce)."""
    t = struct_type(DetectedObject)
    return RecordLayout.of(t, msgspec.convert({"classification": [{"label": 0, "probability": 1.0}]}, t))


@cache
def _envelope(model: type) -> msgspec.msgpack.Decoder:
    """A decoder for ``model``'s generated Struct with its ``objects`` left as raw bytes (the rest validated)."""
    fields: list[Any] = []
    for f in msgspec.structs.fields(struct_type(model)):
        ftype = msgspec.Raw if f.name == "objects" else f.type
        if f.required:
            fields.append((f.name, ftype))
        elif f.default_factory is not msgspec.NODEFAULT:
            fields.append((f.name, ftype, msgspec.field(default_factory=f.default_factory)))
        else:
            fields.append((f.name, ftype, f.default))
    env = msgspec.defstruct(f"{model.__name__}Envelope", fields, kw_only=True, forbid_unknown_fields=True, gc=False)
    return msgspec.msgpack.Decoder(env)


def _decode_records(model: type, layout: RecordLayout, data: bytes | memoryview) -> tuple[Any, np.ndarray] | None:
    """``model``'s envelope and its ``objects`` as records, or None where either is not valid in this shape."""
    try:
        env = _envelope(model).decode(data)
    except (msgspec.DecodeError, ValueError):  # ValueError: e.g. a key that is not UTF-8
        return None
    raw = memoryview(env.objects)
    if not raw:
        return None
    first = raw[0]
    if first & 0xF0 == 0x90:
        n, start = first & 0x0F, 1
    elif first == 0xDC and len(raw) >= 3:
        n, start = int.from_bytes(raw[1:3], "big"), 3
    elif first == 0xDD and len(raw) >= 5:
        n, start = int.from_bytes(raw[1:5], "big"), 5
    else:
        return None
    records = layout.view(raw[start:], n)
    return None if records is None else (env, records)


_ENCODER = msgspec.msgpack.Encoder()


_IDENTITY_POSE = {"position": {"x": 0.0, "y": 0.0, "z": 0.0}, "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}


def pose_map(pose: Any) -> dict[str, Any] | None:
    """A ``Pose`` (model or generated Struct) as the plain map :func:`encode_tracked_objects` writes; None stays
    None (the field keeps its default)."""
    if pose is None:
        return None
    p, q = pose.position, pose.orientation
    return {"position": {"x": p.x, "y": p.y, "z": p.z}, "orientation": {"x": q.x, "y": q.y, "z": q.z, "w": q.w}}


def encode_tracked_objects(header: Mapping[str, Any], records: np.ndarray,
                           observed_track_ids: Sequence[str] = (), ego_pose: Mapping[str, Any] | None = None) -> bytes:
    """The ``TrackedObjects`` payload of ``records`` (from :func:`tracked_object_layout`); ``ego_pose`` is a
    ``Pose`` as a plain map (:func:`pose_map`; None: identity). Every field is written, in the model's order,
    so the bytes are what encoding the model gives."""
    enc = _ENCODER.encode
    pose = enc(ego_pose if ego_pose is not None else _IDENTITY_POSE)
    head = b"".join((b"\x85", enc("schema_version"), enc(SCHEMA_VERSION), enc("header"), enc(dict(header)),
                     enc("ego_pose"), pose, enc("objects"), array_header(len(records))))
    tail = enc("observed_track_ids") + enc(list(observed_track_ids))
    return b"".join((head, memoryview(records.view(np.uint8)), tail))  # one copy of the records


@dataclass
class TrackedRecords:
    """A validated ``TrackedObjects`` whose objects are records (read-only view of the payload)."""

    header: Any  # the generated Header Struct
    records: np.ndarray
    observed_track_ids: list[str]
    ego_pose: Any = None  # the generated Pose Struct


def decode_tracked_records(data: bytes | memoryview) -> TrackedRecords | None:
    """``data`` as :class:`TrackedRecords` if it is a valid ``TrackedObjects`` of the layout's shape, else None
    (invalid, or valid in another shape: the general decoder decides)."""
    got = _decode_records(TrackedObjects, tracked_object_layout(), data)
    if got is None:
        return None
    env, records = got
    return TrackedRecords(env.header, records, env.observed_track_ids, env.ego_pose)


@dataclass
class DetectedRecords:
    """A validated ``DetectedObjects`` whose objects are records (read-only view of the payload)."""

    header: Any  # the generated Header Struct
    ego_pose: Any  # the generated Pose Struct
    records: np.ndarray


def decode_detected_records(data: bytes | memoryview) -> DetectedRecords | None:
    """``data`` as :class:`DetectedRecords` if it is a valid ``DetectedObjects`` of the layout's shape, else
    None (the general decoder decides)."""
    got = _decode_records(DetectedObjects, detected_object_layout(), data)
    if got is None:
        return None
    env, records = got
    return DetectedRecords(env.header, env.ego_pose, records)
