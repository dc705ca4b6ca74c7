"""One read and one write per hot message: payload bytes <-> columns, with the per-message limits.

Every service and the offline evaluator go through these functions, so there is one way a ``DetectedObjects``,
``TrackObservation``, ``TrackedObjects`` or ``MotionState`` crosses the wire. The objects of a message are
numpy records (:mod:`.records`): a view of the payload's own bytes when it has the usual shape (one
classification, no footprint, float64 values, as every writer here and msgpack writers of such objects produce),
checked against the model's rules column-wise. Any other payload is read by the pydantic model — which decides
what is valid and names the field that is not — and *normalised* into the same columns (the most probable
classification, the footprint reduced to its area); the columns say so (``normalised``) and the services count it.

Work per message is bounded before the expensive part (:class:`Limits`): the payload's size, then the object
count read from the list's msgpack header, then coordinates and variances on the columns. A payload beyond a
limit raises :class:`LimitExceeded` (a :class:`~.codec.DecodeError`, so it is rejected and counted per key).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache
from typing import Any

import msgpack
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from .codec import M, ContainerBudget, DecodeError, LimitExceeded, decode, unpack_map, validate
from .models import (
    INT64_MAX,
    SCHEMA_VERSION,
    X_X,
    X_Y,
    Y_Y,
    DetectedObject,
    DetectedObjects,
    Header,
    MotionState,
    ObjectClassification,
    Pose,
    Shape,
    TrackedObject,
    TrackedObjects,
    TrackObservation,
    TrackState,
)
from .records import RecordLayout, array_header

_POSE, _TWIST = "kinematics.pose_with_covariance", "kinematics.twist_with_covariance"
ID, EXISTENCE = "object_id", "existence_probability"
LABEL, LABEL_PROB = "classification.0.label", "classification.0.probability"
X, Y, Z = (f"{_POSE}.pose.position.{a}" for a in "xyz")
QX, QY, QZ, QW = (f"{_POSE}.pose.orientation.{a}" for a in "xyzw")
POSE_COV, TWIST_COV = f"{_POSE}.covariance", f"{_TWIST}.covariance"
VX, VY, VZ = (f"{_TWIST}.twist.linear.{a}" for a in "xyz")
WX, WY, WZ = (f"{_TWIST}.twist.angular.{a}" for a in "xyz")
ORIENTATION, HAS_POSITION_COV = "kinematics.orientation_availability", "kinematics.has_position_covariance"
STATIONARY, SHAPE_TYPE = "kinematics.is_stationary", "shape.type"
LENGTH, WIDTH, HEIGHT = (f"shape.dimensions.{a}" for a in "xyz")
"""Slot names of the object records (``TrackedObject`` and ``DetectedObject`` share them where paths agree)."""

_ONE_CLASS = [ObjectClassification()]
DETECTED = RecordLayout.of(DetectedObject, DetectedObject(classification=_ONE_CLASS))
TRACKED = RecordLayout.of(TrackedObject, TrackedObject(object_id="0" * 32, classification=_ONE_CLASS))
TRACK_STATE = RecordLayout.of(TrackState, TrackState(object_id="0" * 32, x=0.0, y=0.0))


class Limits(BaseModel):
    """Bounds on the work one message may cause; defaults no real sensor reaches (a service's ``limits:``)."""

    # strict: `true` or "5" is no count (a config file's `limits:` / `stream:` had read them as 1 and 5)
    model_config = ConfigDict(extra="forbid", strict=True)

    max_payload_bytes: int = Field(8 << 20, ge=1024, description="larger payloads are refused unread")
    max_objects: int = Field(1000, ge=1, description="objects per message, read from the list's header")
    max_list_items: int = Field(1024, ge=36, description="items of any other list (footprint points, "
                                "classifications), refused before the list is built")
    max_abs_coordinate_m: float = Field(1e7, gt=0, description="|x|, |y|, |z| of every position (UTM fits)")
    max_abs_speed_mps: float = Field(1e3, gt=0, description="|vx|, |vy|, |vz| of every twist")
    max_variance: float = Field(1e6, gt=0, description="|every entry| of a pose or twist covariance")
    max_correlation: float = Field(1.0 + 1e-6, gt=0, description="|cxy| / sqrt(cxx·cyy) of a covariance's x-y "
                                   "block: past 1 it is no covariance (a negative variance once rotated)")
    max_quaternion_error: float = Field(1e-2, gt=0, description="|‖q‖ − 1| of every orientation: headings are "
                                        "read off it as off a rotation")
    max_abs_yaw_rad: float = Field(4 * math.pi, gt=0, description="|yaw| of a track's state: a heading wrapped or "
                                   "not (1e300 only overflows the trigonometry downstream)")
    max_dimension_m: float = Field(1e3, gt=0, description="|length|, |width|, |height| of every box: "
                                   "footprints and IoUs are computed from them")


LIMITS = Limits()

MAX_HEARTBEAT_BYTES = 256 * 1024
"""A heartbeat larger than this is refused unread by every reader (the sidecar, the stack's monitor, ``status``). A
real one is a few KB (the classifier's, with its calibration gauges, ~5 KB); unbounded, a flood of 100 MB counter
maps under made-up names had been read in full and kept."""

MAX_HEARTBEAT_ENTRIES = 512
"""Entries of any map (or list) of a heartbeat — its ``counters`` and its ``gauges`` — that every reader takes; a
larger one is refused before it is built (:class:`LimitExceeded`), like one over :data:`MAX_HEARTBEAT_BYTES`. Real
heartbeats hold a few dozen counters and at most 174 gauges (the classifier's calibration with 8 range bands). Within
the byte bound a made-up one held 40,000 counters: the stack's monitor keeps the counters of 32 processes of each of
64 services and rewrites them all into ``summary.json`` every second, and two made-up services of 32 pids each
(11 MB put once) had grown it by 420 MB and left it writing a 41 MB ``summary.json`` every second for good; the
sidecar exported every entry as a ``/metrics`` series."""

HEARTBEAT_BOUNDS: dict[str, int] = {"max_bytes": MAX_HEARTBEAT_BYTES, "max_array_len": MAX_HEARTBEAT_ENTRIES,
                                    "max_map_len": MAX_HEARTBEAT_ENTRIES}
"""The bounds every heartbeat reader passes to ``decode`` or ``Service.subscribe`` (``**HEARTBEAT_BOUNDS``): one
place, so no reader is left with the byte bound alone."""

MAX_MAP_ENTRIES = 64
"""Entries of any map of a hot message: their models have fixed fields (15 at most, ``MotionState``), so a larger map is
invalid whatever it holds. Refused before it is built (:class:`LimitExceeded`): a ``detections`` or ``tracks/{id}``
payload of one 500 000-key map within ``max_payload_bytes`` had cost the tracker's and the classifier's one worker
2 s each, listing every unknown key as an error."""


MAX_CONFIG_BYTES = 64 * 1024
"""A config write larger than this is refused unread by the classifier (the sidecar's HTTP bodies are capped at 64 KB
too): a write of one 8 MB per-class map had been built and validated key by key, on the query's thread."""

CONFIG_REPLY_BOUNDS: dict[str, int] = {"max_bytes": 4 * MAX_CONFIG_BYTES, "max_array_len": MAX_MAP_ENTRIES,
                                       "max_map_len": MAX_MAP_ENTRIES}
"""What the sidecar reads of a ``ConfigReply``: a config, its etag and a reason (a few hundred bytes as the
classifier writes one). Unbounded, any node answering on the key could have had it decode megabytes per query."""

MAX_STATE_BYTES = 64 << 20
"""A ``classifier/state`` reply larger than this is refused unread by the sidecar. A real one is ~0.35 kB a track
(1,000 tracks: ~0.4 MB), so 64 MiB holds ~190,000 — more than a frame within ``max_payload_bytes`` (8 MiB) can list."""

STATE_REPLY_BOUNDS: dict[str, int] = {"max_bytes": MAX_STATE_BYTES, "max_array_len": 1 << 18,
                                      "max_map_len": MAX_HEARTBEAT_ENTRIES}
"""What the sidecar reads of a ``ClassifierStateSnapshot``: its tracks (a list of up to 262,144; the bytes bind
first), maps of at most as many entries as a heartbeat's (its counters are a heartbeat's counters). Unbounded, any
node answering on the key without a token (on one host) had the sidecar decode whatever it sent, 20 times a
second."""

# -------------------------------------------------------------------------------------------- columns


@dataclass
class DetectedColumns:
    """A ``DetectedObjects``: header, ego pose, the objects as :data:`DETECTED` records and each footprint's area."""

    header: Header
    ego_pose: Pose
    objects: np.ndarray
    area: np.ndarray
    normalised: bool = False


@dataclass
class TrackedColumns:
    """A ``TrackedObjects``: header, ego pose, the objects as :data:`TRACKED` records, the frame-closing IDs."""

    header: Header
    ego_pose: Pose
    objects: np.ndarray
    observed_track_ids: list[str]
    normalised: bool = False


@dataclass
class ObservationColumns:
    """Many ``TrackObservation`` payloads: per valid one (in payload order; ``index`` says which) its header's
    seq and stamp, the detection as a :data:`DETECTED` record and the state as a :data:`TRACK_STATE` record;
    ``errors`` the refused ones as (index, error)."""

    index: np.ndarray
    seq: np.ndarray
    stamp: np.ndarray
    detections: np.ndarray
    tracks: np.ndarray
    errors: list[tuple[int, DecodeError]]
    normalised: int = 0


# -------------------------------------------------------------------------------------------- reading


def read_detected_objects(data: bytes, limits: Limits = LIMITS) -> DetectedColumns:
    """``data`` as :class:`DetectedColumns`; :class:`~.codec.DecodeError` (or :class:`LimitExceeded`) if not valid."""
    env, objects, models = _read_listed(DetectedObjects, data, DETECTED, limits)
    area = _box_area(objects) if models is None else np.array([_area(o.shape) for o in models], dtype=np.float64)
    _check_objects(DetectedObjects.__name__, objects, limits, env.ego_pose)
    return DetectedColumns(env.header, env.ego_pose, objects, area, models is not None)


def read_tracked_objects(data: bytes, limits: Limits = LIMITS) -> TrackedColumns:
    """``data`` as :class:`TrackedColumns`; :class:`~.codec.DecodeError` (or :class:`LimitExceeded`) if not valid."""
    env, objects, models = _read_listed(TrackedObjects, data, TRACKED, limits)
    _check_objects(TrackedObjects.__name__, objects, limits, env.ego_pose)
    ids = objects[ID]
    if len(ids) > 1:  # one object per track: a repeat would be classified and published twice
        order = np.argsort(ids, kind="stable")
        twice = np.flatnonzero(ids[order][1:] == ids[order][:-1])
        if twice.size:
            first, again = sorted(order[[twice[0], twice[0] + 1]].tolist())
            raise DecodeError(TrackedObjects.__name__, f"objects.{again}.object_id", f"repeats objects.{first}")
    return TrackedColumns(env.header, env.ego_pose, objects, list(env.observed_track_ids), models is not None)


def _detached(exc: DecodeError) -> DecodeError:
    """``exc`` without its traceback and the exception it was raised over (its message says what went wrong). Why:
    kept in a list of errors, their frames (the reader's among them, through the callers' links) hold that list and
    the whole batch — payloads, their copies, their unpacked maps — in a reference cycle that only the garbage
    collector frees, and under the classifier's managed collection (a high first threshold, a frozen heap) seldom:
    three rounds of 20,000 refused 100 kB observations had grown it 231 → 862 MB (253 MB since)."""
    exc.__traceback__ = exc.__context__ = exc.__cause__ = None
    return exc


def read_track_observations(payloads: Sequence[bytes], limits: Limits = LIMITS,
                            key_ids: Sequence[str] | None = None) -> ObservationColumns:
    """Many ``TrackObservation`` payloads at once (the classifier reads thousands a second): those in the
    record shape viewed together, the rest read one by one by the model. Never raises for a bad payload.

    ``key_ids``: the track ID each payload's key names (``tracks/{id}``); a payload about another track is
    refused (``track.object_id``): a publisher allowed one key must not feed another track's window."""
    n = len(payloads)
    ok = np.zeros(n, dtype=bool)
    seq, stamp = np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64)
    dets, tracks = np.zeros(n, DETECTED.dtype), np.zeros(n, TRACK_STATE.dtype)
    det_bytes, track_bytes = (a.view(np.uint8).reshape(n, a.itemsize) for a in (dets, tracks))
    errors: list[tuple[int, DecodeError]] = []
    by_size: dict[int, list[int]] = {}
    for i, p in enumerate(payloads):
        by_size.setdefault(len(p), []).append(i)
    general: list[int] = []
    for size, idx in by_size.items():
        layout = _observation_layout(size - _observation_layout(0).itemsize)
        if layout is None:
            general += idx
            continue
        joined = b"".join([payloads[i] for i in idx])
        good = layout.valid_rows(joined, len(idx))
        rows = np.frombuffer(joined, np.uint8).reshape(len(idx), layout.itemsize)
        if not good.all():
            general += [i for i, g in zip(idx, good.tolist()) if not g]
            rows = rows[good]
        take = np.asarray(idx, dtype=np.intp)[good]
        rec = np.ascontiguousarray(rows).reshape(-1).view(layout.dtype)
        seq[take], stamp[take] = rec["header.seq"], rec["header.stamp"]
        (a, b), (c, d) = layout.spans["detection"], layout.spans["track"]
        det_bytes[take], track_bytes[take] = rows[:, a:b], rows[:, c:d]
        ok[take] = True
    normalised_at: list[int] = []
    for i in general:
        try:
            msg = decode(TrackObservation, payloads[i], max_bytes=limits.max_payload_bytes,
                         max_array_len=limits.max_list_items, max_map_len=MAX_MAP_ENTRIES)
        except DecodeError as exc:
            errors.append((i, _detached(exc)))
            continue
        seq[i], stamp[i] = msg.header.seq, msg.header.stamp
        det_bytes[i] = records_of(DETECTED, [msg.detection]).view(np.uint8)
        track_bytes[i] = records_of(TRACK_STATE, [msg.track]).view(np.uint8)
        ok[i] = True
        normalised_at.append(i)
    beyond = _beyond(dets, limits, "detection.") + _beyond(tracks, limits, "track.", state=True)
    if np.logical_or.reduce([bad for bad, _, _ in beyond]).any():
        for bad, field, bound in beyond:
            for i in np.flatnonzero(bad & ok).tolist():
                ok[i] = False
                errors.append((i, LimitExceeded(TrackObservation.__name__, field, bound)))
    if key_ids is not None:
        for i, (key, tid) in enumerate(zip(key_ids, tracks["object_id"].tolist(), strict=True)):
            if ok[i] and key.encode() != tid:
                ok[i] = False
                errors.append((i, DecodeError(TrackObservation.__name__, "track.object_id",
                                              f"not the track its key names ({key!r})")))
    # counted once every refusal is in: a payload read in another form and then refused (beyond a limit, about
    # another track than its key names) had been counted as normalised and rejected both
    normalised = int(ok[normalised_at].sum()) if normalised_at else 0
    if ok.all():
        return ObservationColumns(np.arange(n), seq, stamp, dets, tracks, [], normalised)
    keep = np.flatnonzero(ok)
    return ObservationColumns(keep, seq[keep], stamp[keep], DETECTED.select(dets, keep), TRACK_STATE.select(tracks, keep),
                              sorted(errors, key=lambda e: e[0]), normalised)


def peek_header(data: bytes) -> tuple[int, int] | None:
    """``(header.seq, header.stamp)`` of an encoded message, read without validating the rest (None if not found).

    For decisions that must come before the expensive part (a duplicate or a replay is dropped unread) and for
    timing; whatever is kept still goes through the read functions. A seq or stamp the header model refuses
    (negative, beyond int64) is not found either: the read then refuses the payload, counted ``rejected`` —
    judged by its order instead, it had been dropped as a jump or a late frame.
    """
    up = msgpack.Unpacker(raw=False, max_map_len=MAX_MAP_ENTRIES, max_array_len=MAX_MAP_ENTRIES)
    try:
        up.feed(data)
        entries = up.read_map_header()
        if entries > MAX_MAP_ENTRIES:  # no such message (a loop over millions of entries, before any was judged)
            return None
        for _ in range(entries):
            if up.unpack() == "header":
                h = up.unpack()
                seq, stamp = h.get("seq", 0), h.get("stamp")
                if all(type(v) is int and 0 <= v <= INT64_MAX for v in (seq, stamp)):
                    return seq, stamp
                return None
            up.skip()
    except Exception:  # msgpack raises several unrelated types; any of them means "not found"
        return None
    return None


# -------------------------------------------------------------------------------------------- writing


def write_detected_objects(cols: DetectedColumns) -> bytes:
    """The ``DetectedObjects`` payload of ``cols`` (objects as :data:`DETECTED` records)."""
    return _write_listed({"header": cols.header, "ego_pose": cols.ego_pose}, cols.objects, {})


def write_tracked_objects(cols: TrackedColumns) -> bytes:
    """The ``TrackedObjects`` payload of ``cols`` (objects as :data:`TRACKED` records)."""
    return _write_listed({"header": cols.header, "ego_pose": cols.ego_pose}, cols.objects,
                         {"observed_track_ids": list(cols.observed_track_ids)})


def write_track_observations(header: Header, detections: np.ndarray, tracks: np.ndarray) -> list[bytes]:
    """One ``TrackObservation`` payload per row: ``detections`` (:data:`DETECTED`) beside ``tracks``
    (:data:`TRACK_STATE`), all under ``header``."""
    layout = _observation_layout(len(header.frame_id.encode()))
    if layout is None:
        raise ValueError(f"frame id {header.frame_id!r}: observations are written in frames named in < 32 bytes")
    n = len(detections)
    rec = layout.pack(n, {"header.stamp": np.full(n, header.stamp), "header.seq": np.full(n, header.seq),
                          "header.frame_id": [header.frame_id] * n})
    rows = rec.view(np.uint8).reshape(n, layout.itemsize)
    (a, b), (c, d) = layout.spans["detection"], layout.spans["track"]
    rows[:, a:b] = detections.view(np.uint8).reshape(n, b - a)
    rows[:, c:d] = tracks.view(np.uint8).reshape(n, d - c)
    raw, size = rows.tobytes(), layout.itemsize
    return [raw[k * size:(k + 1) * size] for k in range(n)]


def write_motion_states(header: Header, track_ids: Sequence[str], states: Sequence[str], mode: str,
                        columns: dict[str, np.ndarray]) -> list[bytes]:
    """One ``MotionState`` payload per track, in order; ``columns`` holds the numeric fields by name."""
    n = len(track_ids)
    out: list[bytes] = [b""] * n
    by_state: dict[str, list[int]] = {}
    for i, s in enumerate(states):
        by_state.setdefault(s, []).append(i)
    for state, idx in by_state.items():
        layout = _motion_layout(state, mode, header.frame_id)
        take = np.asarray(idx)
        rec = layout.pack(len(idx), {"header.stamp": np.full(len(idx), header.stamp),
                                     "header.seq": np.full(len(idx), header.seq),
                                     "track_id": [track_ids[i] for i in idx],
                                     **{k: np.asarray(v)[take] for k, v in columns.items()}})
        raw, size = RecordLayout.to_bytes(rec), layout.itemsize
        for k, i in enumerate(idx):
            out[i] = raw[k * size:(k + 1) * size]
    return out


# -------------------------------------------------------------------------------------------- helpers


@cache
def _observation_layout(frame_id_bytes: int) -> RecordLayout | None:
    """The whole-message layout of a ``TrackObservation`` whose header's frame id is this long (None: none)."""
    if not 0 <= frame_id_bytes < 32:
        return None
    det = DetectedObject(classification=_ONE_CLASS)
    return RecordLayout.of(TrackObservation, TrackObservation(
        header=Header(stamp=0, frame_id="m" * frame_id_bytes), detection=det, track=TrackState(object_id="0" * 32,
                                                                                              x=0.0, y=0.0)))


@cache
def _motion_layout(state: str, mode: str, frame_id: str) -> RecordLayout:
    return RecordLayout.of(MotionState, MotionState(header=Header(stamp=0, frame_id=frame_id), track_id="0" * 32,
                                                    state=state, mode=mode, threshold=0.0, alpha=0.0, window_length=0))


def _read_listed(model: type[M], data: bytes, layout: RecordLayout, limits: Limits
                 ) -> tuple[M, np.ndarray, list[Any] | None]:
    """``data`` as ``model``: the envelope (every top-level field but ``objects``, validated by the model), the
    objects as records of ``layout``, and — where the payload is not in the record shape and the model read it —
    the model's objects (None otherwise). The size and the object count (from the list's header) are checked first,
    whatever the form."""
    name = model.__name__
    if len(data) > limits.max_payload_bytes:
        raise LimitExceeded(name, "", f"{len(data)} bytes exceed max_payload_bytes {limits.max_payload_bytes}")
    got = _view_listed(model, data, layout, limits)
    if got is not None:
        return got[0], got[1], None
    n = _object_count(data, limits.max_objects)  # another form: the model decides, its object count in bounds first
    if n > limits.max_objects:
        raise LimitExceeded(name, "objects", f"{n} objects exceed max_objects {limits.max_objects}")
    raw = unpack_map(model, data, max_array_len=max(limits.max_objects, limits.max_list_items),
                     max_map_len=MAX_MAP_ENTRIES)
    _check_lists(name, raw.get("objects"), limits.max_list_items)
    msg = validate(model, raw)
    return msg, records_of(layout, msg.objects), msg.objects


def _view_listed(model: type[M], data: bytes, layout: RecordLayout, limits: Limits) -> tuple[M, np.ndarray] | None:
    """The envelope and a view of the objects when the payload is a map in the record shape; None otherwise."""
    # the envelope's lists bounded as the model's reading bounds them (``observed_track_ids`` of 200 000 IDs had
    # passed here, refused in the other form), and its maps and lists in all by the payload's size
    bounds = {"max_array_len": max(limits.max_objects, limits.max_list_items), "max_map_len": MAX_MAP_ENTRIES,
              **ContainerBudget(model, len(data)).hooks()}
    up = msgpack.Unpacker(raw=False, strict_map_key=True, max_buffer_size=max(len(data), 1), **bounds)
    env: dict[str, Any] = {}
    try:
        up.feed(data)
        keys = up.read_map_header()
        if keys > MAX_MAP_ENTRIES:  # the model's reading refuses it before building it
            return None
        for k in range(keys):
            key = up.unpack()
            if key in env or not isinstance(key, str):
                return None
            if key != "objects":
                env[key] = up.unpack()
                continue
            n = up.read_array_header()
            if n > limits.max_objects:
                raise LimitExceeded(model.__name__, "objects", f"{n} objects exceed max_objects {limits.max_objects}")
            start, end = up.tell(), up.tell() + n * layout.itemsize
            records = layout.view(memoryview(data)[start:end], n)
            if records is None:
                return None
            rest = msgpack.Unpacker(raw=False, strict_map_key=True, max_buffer_size=max(len(data), 1), **bounds)
            rest.feed(memoryview(data)[end:])
            for _ in range(keys - k - 1):
                key = rest.unpack()
                if key in env or key == "objects" or not isinstance(key, str):
                    return None
                env[key] = rest.unpack()
            if rest.tell() != len(data) - end:
                return None
            return validate(model, {**env, "objects": []}), records
    except LimitExceeded:
        raise
    except Exception:  # malformed msgpack, or an envelope the model refuses: the model says what is wrong
        return None
    return None


def _check_lists(name: str, objects: Any, bound: int) -> None:
    """Each object's lists (classifications, footprint points) within ``bound`` — before the model validates them
    (the unpacker bounded every list only by the larger of this and the object count)."""
    if not isinstance(objects, list):
        return
    for i, o in enumerate(objects):
        if not isinstance(o, dict):
            continue
        shape = o.get("shape")
        for field, items in (("classification", o.get("classification")),
                             ("shape.footprint", shape.get("footprint") if isinstance(shape, dict) else None)):
            if isinstance(items, list) and len(items) > bound:
                raise LimitExceeded(name, f"objects.{i}.{field}",
                                    f"a list holds more than {bound} items ({len(items)})")


def _object_count(data: bytes, limit: int) -> int:
    """The object count a top-level ``objects`` list of the map ``data`` declares in its msgpack header — the first
    beyond ``limit``, else the largest — found by skipping every other value unread (0 if there is none or ``data``
    is not such a map: the model's reading then says what is wrong)."""
    up = msgpack.Unpacker(raw=False, max_buffer_size=max(len(data), 1), max_array_len=max(limit, 1 << 16))
    most = 0
    try:
        up.feed(data)
        entries = up.read_map_header()
        if entries > MAX_MAP_ENTRIES:  # no such message: the model's reading refuses it unread
            return 0
        for _ in range(entries):
            if up.unpack() != "objects":
                up.skip()
                continue
            n = up.read_array_header()
            if n > limit:
                return n
            most = max(most, n)
            for _ in range(n):
                up.skip()
    except Exception:  # malformed msgpack: not for this check to name
        pass
    return most


def _write_listed(head: dict[str, BaseModel], records: np.ndarray, tail: dict[str, Any]) -> bytes:
    pack = msgpack.packb
    parts = [bytes([0x80 | (len(head) + len(tail) + 2)]), pack("schema_version"), pack(SCHEMA_VERSION)]
    for k, v in head.items():
        parts += [pack(k), pack(v.model_dump())]
    parts += [pack("objects"), array_header(len(records)), memoryview(records.view(np.uint8))]  # one copy, in join
    for k, v in tail.items():
        parts += [pack(k), pack(v)]
    return b"".join(parts)


def records_of(layout: RecordLayout, objs: Sequence[BaseModel]) -> np.ndarray:
    """Valid models as records of ``layout`` (:data:`DETECTED`, :data:`TRACKED`, :data:`TRACK_STATE`), normalised to
    its shape: the most probable classification (UNKNOWN if none), no footprint."""
    dicts = []
    for o in objs:
        d = o.model_dump()
        if "classification" in d:
            best = max(d["classification"], key=lambda c: c["probability"], default=None)
            d["classification"] = [best or {"label": 0, "probability": 1.0}]
        if "shape" in d:
            d["shape"]["footprint"] = []
        dicts.append(d)
    if not dicts:
        return layout.pack(0, {})
    return layout.pack(len(dicts), {name: [_get(d, name) for d in dicts] for name in layout.slots})


def _get(d: Any, path: str) -> Any:
    for part in path.split("."):
        d = d[int(part)] if isinstance(d, list) else d[part]
    return d


def _area(shape: Shape) -> float:
    """Footprint area as Autoware's getArea computes it (box L*W, cylinder pi r^2, polygon shoelace)."""
    if shape.type == Shape.CYLINDER:
        return math.pi * (0.5 * shape.dimensions.x) ** 2
    if shape.type == Shape.POLYGON:
        pts = shape.footprint
        return abs(0.5 * sum(a.x * b.y - b.x * a.y for a, b in zip(pts, pts[1:] + pts[:1]))) if len(pts) > 2 else 0.0
    return shape.dimensions.x * shape.dimensions.y


def _box_area(r: np.ndarray) -> np.ndarray:
    """:func:`_area` over records (no footprint in this shape: a polygon's area is 0, as getArea gives)."""
    kind, dx, dy = r[SHAPE_TYPE], r[LENGTH].astype(np.float64), r[WIDTH].astype(np.float64)
    return np.where(kind == Shape.CYLINDER, math.pi * (0.5 * dx) ** 2, np.where(kind == Shape.POLYGON, 0.0, dx * dy))


def _beyond(records: np.ndarray, limits: Limits, prefix: str = "", *, state: bool = False
            ) -> list[tuple[np.ndarray, str, str]]:
    """Per bounded column, which records break its limit, the field to name and the bound it breaks (a refusal
    that said only "beyond the configured limit" had sent operators to ``max_variance`` for a covariance that broke
    the correlation bound)."""
    if not len(records):
        return []
    if state:  # a TrackState: planar position, velocity and heading only
        pos, vel, cov, dims = ("x", "y"), ("vx", "vy"), (), ()
    else:
        pos, vel, cov, dims = (X, Y, Z), (VX, VY, VZ), (POSE_COV, TWIST_COV), (LENGTH, WIDTH, HEIGHT)
    out = [(~(np.abs(records[c]) <= limits.max_abs_coordinate_m), prefix + c,
            f"beyond max_abs_coordinate_m {limits.max_abs_coordinate_m:g}") for c in pos]
    out += [(~(np.abs(records[c]) <= limits.max_dimension_m), prefix + c,
             f"beyond max_dimension_m {limits.max_dimension_m:g}") for c in dims]
    if state:
        out.append((~(np.abs(records["yaw"]) <= limits.max_abs_yaw_rad), prefix + "yaw",
                    f"beyond max_abs_yaw_rad {limits.max_abs_yaw_rad:g}"))
    out += [(~(np.abs(records[c]) <= limits.max_abs_speed_mps), prefix + c,
             f"beyond max_abs_speed_mps {limits.max_abs_speed_mps:g}") for c in vel]
    out += [(~(np.abs(records[c]["v"]) <= limits.max_variance).all(axis=1), prefix + c,
             f"an entry beyond max_variance {limits.max_variance:g}") for c in cov]
    if math.isfinite(limits.max_correlation):
        for c in cov:
            v = records[c]["v"]
            spread = np.sqrt(np.maximum(v[:, X_X], 0.0)) * np.sqrt(np.maximum(v[:, Y_Y], 0.0))
            # plus a rounding allowance: a rank-1 covariance rotated onto an axis comes out as cxx 2, cyy 0,
            # cxy 2.2e-16, which the relative bound alone had refused (the tracker published what this refused)
            rounding = ROUNDING_ALLOWANCE * (np.abs(v[:, X_X]) + np.abs(v[:, Y_Y]))
            out.append((~(np.abs(v[:, X_Y]) <= limits.max_correlation * spread + rounding), prefix + c,
                        f"x-y covariance beyond max_correlation {limits.max_correlation:g} of sqrt(var_x var_y)"))
    if not state:
        out.append((~(np.abs(_lengths(records) - 1.0) <= limits.max_quaternion_error),
                    f"{prefix}{_POSE}.pose.orientation",
                    f"not a unit quaternion (max_quaternion_error {limits.max_quaternion_error:g})"))
    return out


ROUNDING_ALLOWANCE = 1e-12
"""Of a covariance's trace, what its cross term may exceed the correlation bound by: floating-point rounding of
R Σ Rᵀ (a few units in the last place), far below any real excess."""


def within_limits(records: np.ndarray, limits: Limits = LIMITS) -> np.ndarray:
    """Which ``DETECTED`` records keep every bound a reader holds them to (:func:`read_detected_objects` refuses a
    whole frame for one that does not): the writer's side of the same rule, e.g. the detector dropping a box a
    stray return drove beyond ``max_variance`` rather than losing the frame."""
    beyond = _beyond(records, limits)
    return ~np.logical_or.reduce([bad for bad, _, _ in beyond]) if beyond else np.ones(len(records), dtype=bool)


def _lengths(records: np.ndarray) -> np.ndarray:
    """The length of each record's orientation quaternion (inf where its squares overflow)."""
    with np.errstate(over="ignore"):
        return np.sqrt(sum(records[c].astype(np.float64) ** 2 for c in (QX, QY, QZ, QW)))


def check_pose(name: str, field: str, pose: Pose, limits: Limits = LIMITS) -> None:
    """:class:`LimitExceeded` naming ``field`` when ``pose`` lies beyond ``max_abs_coordinate_m`` or its orientation
    is not a unit quaternion (to ``max_quaternion_error``): what every reader asks of a message's ego pose."""
    p, q = pose.position, pose.orientation
    if max(abs(p.x), abs(p.y), abs(p.z)) > limits.max_abs_coordinate_m:
        raise LimitExceeded(name, f"{field}.position", f"beyond max_abs_coordinate_m {limits.max_abs_coordinate_m}")
    length = math.hypot(q.x, q.y, q.z, q.w)
    if not abs(length - 1.0) <= limits.max_quaternion_error:
        raise LimitExceeded(name, f"{field}.orientation", f"not a unit quaternion (length {length:.6g}; "
                            f"max_quaternion_error {limits.max_quaternion_error})")


def _check_objects(name: str, objects: np.ndarray, limits: Limits, ego_pose: Pose) -> None:
    check_pose(name, "ego_pose", ego_pose, limits)
    for bad, field, bound in _beyond(objects, limits):
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise LimitExceeded(name, f"objects.{i}.{field}", bound)
