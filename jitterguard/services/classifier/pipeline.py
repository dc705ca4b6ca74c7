"""The classifier's per-message work without Zenoh: payload bytes in, payload bytes out.

What :class:`~.service.ClassifierService` does between receiving a sample and putting one, with the transport
and the threads left out, so it can be driven (and timed, ``bench.bench_frame_cost``) in-process. No I/O;
the caller passes the clock.

Where the time goes decides the shape. At 200 tracks × 20 Hz the work is dominated by validating payloads,
so:

* every payload is validated by :class:`~jitterguard.schemas.fast.StructCodec` — msgspec Structs generated
  from the pydantic models, which validate while parsing and fall back to pydantic for anything they do not
  accept on their own (the rules and error messages stay the models'; a quarter of the cost);
* an observation is validated and reduced to the eight numbers the core needs *as it arrives*
  (:meth:`ClassifierPipeline.observation`), so when the frame-closing ``tracked`` arrives only that message
  and the frame itself remain;
* ``tracked`` is read as records (:mod:`jitterguard.schemas.tracked_layout`: the payload's bytes viewed as a
  numpy structured array and checked column-wise) whenever it has the usual shape, so deciding a frame is a few
  column writes and ``objects`` is the edited copy's bytes; any other valid shape goes through the Structs;
* the ``motion/{id}`` payloads are only built after ``objects`` is out (:meth:`ClassifierPipeline.motion_payloads`).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import msgspec
import numpy as np

from ...geometry import yaw_from_quaternion, yaws_from_quaternions
from ...schemas import SCHEMA_VERSION
from ...schemas import tracked_layout as tl
from ...schemas.layout import RecordLayout
from ...schemas.fast import StructCodec
from ...schemas.models import X_X, X_Y, Y_Y, ClassifierConfig, TrackedObjects, TrackObservation
from .calibration import NoiseModel
from .core import STATIC, Decisions, MotionClassifierCore, Observations
from .frames import CompleteFrame, FrameAssembler

ObservationRow = tuple[str, int, float, float, float, float, float, float]
"""What the core needs of one ``TrackObservation``: id, label, x, y, cov xx, xy, yy, tracker speed."""


def observation_row(msg: Any) -> ObservationRow:
    """The core's numbers from a validated ``TrackObservation`` (the model or its Struct; world frame)."""
    pwc = msg.detection.kinematics.pose_with_covariance
    cov, pos, trk = pwc.covariance, pwc.pose.position, msg.track
    return (trk.object_id, trk.label, pos.x, pos.y, cov[X_X], cov[X_Y], cov[Y_Y], math.hypot(trk.vx, trk.vy))


def observations_from_rows(rows: list[ObservationRow], seq: int, stamp_ns: int,
                           sensor_xy: tuple[float, float] = (0.0, 0.0)) -> Observations:
    """One frame's observation rows as the core's arrays (``sensor_xy``: the frame's ``ego_pose`` position)."""
    sx, sy = sensor_xy
    if not rows:
        return Observations.from_lists([], [], [], [], [], [], [], [], stamp_ns=stamp_ns, seq=seq, sensor_x=sx,
                                       sensor_y=sy)
    ids, labels, x, y, cxx, cxy, cyy, speed = zip(*rows)
    return Observations.from_lists(list(ids), labels, x, y, cxx, cxy, cyy, speed, stamp_ns=stamp_ns, seq=seq,
                                   sensor_x=sx, sensor_y=sy)


def sensor_position(ego_pose: Any) -> tuple[float, float]:
    """The sensor's world x, y from a frame's ``ego_pose`` (origin when the message has none)."""
    if ego_pose is None:
        return 0.0, 0.0
    return float(ego_pose.position.x), float(ego_pose.position.y)


def apply_decisions_to_objects(objects: list[Any], dec: Decisions) -> None:
    """Edit the tracker's objects (``TrackedObject`` models or their Structs) in place: static ⇒ zero twist,
    window-mean position, ``is_stationary``; dynamic and undecided pass through with ``is_stationary = false``."""
    states = dec.state.tolist()
    mx, my = dec.mean_x.tolist(), dec.mean_y.tolist()
    for obj, state, x, y in zip(objects, states, mx, my):
        kin = obj.kinematics
        if state == STATIC:
            kin.is_stationary = True
            pos = kin.pose_with_covariance.pose.position
            pos.x, pos.y = x, y
            twist = kin.twist_with_covariance.twist
            for v in (twist.linear, twist.angular):
                v.x = v.y = v.z = 0.0
        else:
            kin.is_stationary = False


@dataclass
class Poses:
    """What the state queryable reports of each object besides the decision."""

    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    length: np.ndarray
    width: np.ndarray


class RecordObjects:
    """A frame's ``tracked`` objects as records (:mod:`jitterguard.schemas.tracked_layout`), the fast form:
    deciding is a few column writes on a copy, encoding is the copy's bytes."""

    def __init__(self, header: Any, records: np.ndarray, ego_pose: Any = None) -> None:
        self.header, self.records, self.ego_pose = header, records, ego_pose

    @property
    def ids(self) -> np.ndarray:
        return np.asarray(self.records[tl.ID], dtype="S32")

    def decided(self, dec: Decisions) -> tuple[RecordObjects, bytes]:
        """The objects with ``dec`` applied (as :func:`apply_decisions_to_objects`) and their payload."""
        out = RecordLayout.copy(self.records)
        static = dec.state == STATIC
        out[tl.STATIONARY] = np.where(static, 0xC3, 0xC2)
        out[tl.X] = np.where(static, dec.mean_x, out[tl.X])
        out[tl.Y] = np.where(static, dec.mean_y, out[tl.Y])
        for name in (tl.VX, tl.VY, tl.VZ, tl.WX, tl.WY, tl.WZ):
            out[name] = np.where(static, 0.0, out[name])
        h = self.header
        header = {"stamp": h.stamp, "frame_id": h.frame_id, "seq": h.seq}
        return RecordObjects(h, out, self.ego_pose), tl.encode_tracked_objects(header, out, (),
                                                                               tl.pose_map(self.ego_pose))

    def poses(self) -> Poses:
        r = self.records
        return Poses(r[tl.X].astype(np.float64), r[tl.Y].astype(np.float64),
                     yaws_from_quaternions(r[tl.QX], r[tl.QY], r[tl.QZ], r[tl.QW]),
                     r[tl.LENGTH].astype(np.float64), r[tl.WIDTH].astype(np.float64))


class StructObjects:
    """A frame's ``tracked`` message as the generated Structs, the general form: any valid ``TrackedObjects``
    (several classifications, a polygon footprint, ...) that :class:`RecordObjects` cannot hold."""

    def __init__(self, tracked: Any, codec: StructCodec) -> None:
        self.tracked, self._codec = tracked, codec
        self.header = tracked.header
        self.ego_pose = tracked.ego_pose

    @property
    def ids(self) -> np.ndarray:
        return np.asarray([o.object_id for o in self.tracked.objects], dtype="S32")

    def decided(self, dec: Decisions) -> tuple[StructObjects, bytes]:
        """The objects with ``dec`` applied (in place: this frame's Structs are not used again) and the payload."""
        apply_decisions_to_objects(self.tracked.objects, dec)
        self.tracked.observed_track_ids = []
        return self, self._codec.encode(self.tracked)

    def poses(self) -> Poses:
        objs = self.tracked.objects
        pos = [o.kinematics.pose_with_covariance.pose for o in objs]
        return Poses(np.array([p.position.x for p in pos]), np.array([p.position.y for p in pos]),
                     np.array([yaw_from_quaternion(p.orientation.x, p.orientation.y, p.orientation.z,
                                                   p.orientation.w) for p in pos]),
                     np.array([o.shape.dimensions.x for o in objs]), np.array([o.shape.dimensions.y for o in objs]))


@dataclass
class FrameOutput:
    """One decided frame: the ``objects`` payload and what the motion messages and the state are built from."""

    seq: int
    header: Any  # the ``tracked`` header (Struct)
    objects: RecordObjects | StructObjects  # the published objects, decisions applied; not edited afterwards
    payload: bytes  # ``objects``, ready to put
    reported: np.ndarray  # the IDs of ``objects`` (S32)
    decisions: Decisions  # one per object in ``objects``
    observed: Observations  # this frame's observations (the tracks that get a ``motion/{id}``)
    decided: Decisions | None  # the core's decisions for ``observed``; None when nothing was observed
    config: ClassifierConfig  # in force for this frame
    received_at: float
    missing: int


class ClassifierPipeline:
    """Frame assembly plus the core, fed with raw payloads. Not thread-safe: one worker owns it."""

    def __init__(self, config: ClassifierConfig | None = None, *, straggler_timeout_s: float = 0.05,
                 calibration_model: NoiseModel | None = None) -> None:
        self.core = MotionClassifierCore(config or ClassifierConfig(), calibration_model=calibration_model)
        self.assembler: FrameAssembler[ObservationRow, Any] = FrameAssembler(straggler_timeout_s=straggler_timeout_s)
        self._observation_codec = StructCodec(TrackObservation)
        self._tracked_codec = StructCodec(TrackedObjects, raw_float_blocks=16)  # covariances stay bytes
        self._encoder = msgspec.msgpack.Encoder()

    def observation(self, data: bytes) -> None:
        """Validate one ``tracks/{id}`` payload and keep its row (a straggler of a frame already decided is
        counted ``late_observations`` and dropped).

        Raises :class:`~jitterguard.schemas.DecodeError` for a payload that fails validation.
        """
        msg = self._observation_codec.decode(data)
        self.assembler.add_observation_item(msg.header.seq, msg.track.object_id, observation_row(msg))

    def close(self, data: bytes, received_at: float) -> bool:
        """Validate one ``tracked`` payload and register it as the close of its frame; False when it was a
        duplicate or stale. A tracker restart (its seq starting again) resets the core.

        Raises :class:`~jitterguard.schemas.DecodeError` for a payload that fails validation.
        """
        fast = tl.decode_tracked_records(data)
        if fast is not None:
            header, expected = fast.header, fast.observed_track_ids
            objects: RecordObjects | StructObjects = RecordObjects(header, fast.records, fast.ego_pose)
        else:  # another shape, or invalid: the general decoder decides (and names the field)
            msg = self._tracked_codec.decode(data)
            header, expected, objects = msg.header, msg.observed_track_ids, StructObjects(msg, self._tracked_codec)
        restarts = self.assembler.counts.get("upstream_restarts", 0)
        ok = self.assembler.add_close_item(header.seq, expected, objects, received_at, stamp_ns=header.stamp)
        if self.assembler.counts.get("upstream_restarts", 0) != restarts:
            self.core.reset()
        return ok

    def ready(self, now: float, *, give_up: bool = True) -> list[CompleteFrame[ObservationRow, Any]]:
        """Frames complete (or, with ``give_up``, timed out waiting for stragglers) at ``now``, in seq order."""
        return self.assembler.pop_ready(now, give_up=give_up)

    @property
    def pending(self) -> int:
        """Frames closed but still waiting for stragglers."""
        return self.assembler.pending

    def finish(self, frame: CompleteFrame[ObservationRow, Any]) -> FrameOutput:
        """Decide a complete frame and encode its ``objects`` payload."""
        tracked: RecordObjects | StructObjects = frame.tracked
        header = tracked.header
        obs = observations_from_rows(frame.observations, header.seq, header.stamp, sensor_position(tracked.ego_pose))
        decided = self.core.update(obs) if len(obs) else None
        reported = tracked.ids
        dec = self.core.last_decisions(reported)
        objects, payload = tracked.decided(dec)
        return FrameOutput(seq=header.seq, header=header, objects=objects, payload=payload,
                           reported=reported, decisions=dec, observed=obs, decided=decided, config=self.core.config,
                           received_at=frame.received_at, missing=frame.missing)

    def settle(self, out: FrameOutput) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
        """The bookkeeping that can wait until ``objects`` is out (call before the next frame): evict the
        windows of tracks ``out`` no longer reports; returns how many, and each reported object's label, last
        update stamp and seq (for the state queryable)."""
        evicted = self.core.retain(out.reported)
        return (evicted, *self.core.last_meta(out.reported))

    def motion_payloads(self, out: FrameOutput) -> Iterator[tuple[str, bytes]]:
        """``(track_id, MotionState payload)`` per observed track of ``out``.

        Built as plain maps from arrays the core just computed (every value finite and in range by
        construction, ``tests/test_classifier_service.py`` validates them): a model per track would cost
        more than the frame.
        """
        dec = out.decided
        if dec is None:
            return
        h = {"stamp": out.header.stamp, "frame_id": "map", "seq": out.header.seq}
        mode = out.config.mode
        names = dec.state_names()
        cols = {k: getattr(dec, k).tolist() for k in
                ("z_x", "z_y", "chi2", "threshold", "alpha", "window_length", "speed", "mean_x", "mean_y")}
        labels = out.observed.labels.tolist()
        for i, tid in enumerate(out.observed.track_ids.tolist()):
            tid_s = tid.decode()
            msg = {"schema_version": SCHEMA_VERSION, "header": h, "track_id": tid_s, "label": labels[i],
                   "state": names[i], "mode": mode, **{k: v[i] for k, v in cols.items()}}
            yield tid_s, self._encoder.encode(msg)
