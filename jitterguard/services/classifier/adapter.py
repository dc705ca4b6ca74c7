"""The classifier's seam between wire and core: payload bytes in, payload bytes out, without Zenoh or threads.

What :class:`~.service.ClassifierService` does between receiving samples and putting them, with the transport left
out, so the offline evaluator and the benchmark drive exactly the live code in-process. No I/O; the caller passes
the clock. Every payload is read by the one read function of its message (:mod:`jitterguard.schemas.wire`):
observations in batches as they arrive (:meth:`ClassifierAdapter.observations`), reduced at once to the eight
numbers the core needs, so when the frame-closing ``tracked`` arrives only that message and the decision remain;
``objects`` is the ``tracked`` records with the decisions written into a copy, and the ``motion/{id}`` payloads
are built only after ``objects`` is out (:meth:`ClassifierAdapter.motion_payloads`).
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from ...geometry import yaws_from_quaternions
from ...schemas import wire
from ...schemas.models import X_X, X_Y, Y_Y, ClassifierConfig, Header
from ...schemas.wire import (
    LIMITS,
    Limits,
    ObservationColumns,
    TrackedColumns,
    peek_header,
    read_track_observations,
    read_tracked_objects,
    write_motion_states,
    write_tracked_objects,
)
from ...stream_order import StreamGuard, StreamLimits
from .assembly import CompleteFrame, FrameAssembler
from .calibration import NoiseModel, OnlineCalibration
from .core import STATIC, Decisions, MotionClassifierCore, Observations

ObservationRow = tuple[str, int, float, float, float, float, float, float]
"""What the core needs of one ``TrackObservation``: id, label, x, y, cov xx, xy, yy, tracker speed."""


def observation_rows(cols: ObservationColumns) -> list[tuple[int, str, ObservationRow]]:
    """``(seq, track_id, row)`` per observation of ``cols`` (world frame: the tracker republishes rotated)."""
    d, t = cols.detections, cols.tracks
    cov = d[wire.POSE_COV]["v"]
    ids = [i.decode() for i in t["object_id"].tolist()]
    cols_ = (ids, t["label"].tolist(), d[wire.X].tolist(), d[wire.Y].tolist(), cov[:, X_X].tolist(),
             cov[:, X_Y].tolist(), cov[:, Y_Y].tolist(), list(map(math.hypot, t["vx"].tolist(), t["vy"].tolist())))
    return [(s, r[0], r) for s, r in zip(cols.seq.tolist(), zip(*cols_))]


def observations_from_rows(rows: Sequence[ObservationRow], seq: int, stamp_ns: int,
                           sensor_xy: tuple[float, float] = (0.0, 0.0),
                           published_ids: np.ndarray | None = None) -> Observations:
    """One frame's observation rows as the core's arrays (``sensor_xy``: the frame's ``ego_pose`` position, the
    origin of the line of sight along and across which the variances are calibrated; ``published_ids``: the IDs
    (S32) of the frame's ``tracked`` objects — other observed tracks are tentative)."""
    sx, sy = sensor_xy
    if not rows:
        return Observations.from_lists([], [], [], [], [], [], [], [], stamp_ns=stamp_ns, seq=seq, sensor_x=sx,
                                       sensor_y=sy)
    ids, labels, x, y, cxx, cxy, cyy, speed = zip(*rows)
    return Observations.from_lists(list(ids), labels, x, y, cxx, cxy, cyy, speed, stamp_ns=stamp_ns, seq=seq,
                                   sensor_x=sx, sensor_y=sy, published_ids=published_ids)


def decided_objects(objects: np.ndarray, dec: Decisions) -> np.ndarray:
    """A copy of ``tracked``'s object records with ``dec`` applied: static ⇒ zero twist, window-mean position,
    ``is_stationary``; dynamic and undecided pass through with ``is_stationary = false``."""
    out = wire.TRACKED.copy(objects)
    static = dec.state == STATIC
    out[wire.STATIONARY] = np.where(static, 0xC3, 0xC2)
    out[wire.X] = np.where(static, dec.mean_x, out[wire.X])
    out[wire.Y] = np.where(static, dec.mean_y, out[wire.Y])
    for name in (wire.VX, wire.VY, wire.VZ, wire.WX, wire.WY, wire.WZ):
        out[name] = np.where(static, 0.0, out[name])
    return out


@dataclass
class Poses:
    """What the state queryable reports of each object besides the decision."""

    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    length: np.ndarray
    width: np.ndarray

    @staticmethod
    def of(r: np.ndarray) -> Poses:
        return Poses(r[wire.X].astype(np.float64), r[wire.Y].astype(np.float64),
                     yaws_from_quaternions(r[wire.QX], r[wire.QY], r[wire.QZ], r[wire.QW]),
                     r[wire.LENGTH].astype(np.float64), r[wire.WIDTH].astype(np.float64))


@dataclass
class FrameOutput:
    """One decided frame: the ``objects`` payload and what the motion messages and the state are built from."""

    seq: int
    header: Header  # the ``tracked`` header
    objects: np.ndarray  # the published object records, decisions applied; not edited afterwards
    payload: bytes  # ``objects``, ready to put
    reported: np.ndarray  # the IDs of ``objects`` (S32)
    decisions: Decisions  # one per object in ``objects``
    observed: Observations  # this frame's observations of published tracks (the tracks that get a ``motion/{id}``)
    decided: Decisions | None  # the core's decisions for ``observed``; None when nothing was observed
    windows: np.ndarray  # the IDs (S32) whose windows live on: published or observed (tentative ones too; repeats)
    config: ClassifierConfig  # in force for this frame
    window: int  # observations a window held for this frame (``window_size``, or fewer for a slow stream)
    received_at: float
    missing: int


class ClassifierAdapter:
    """Frame assembly plus the core, fed with payloads. Not thread-safe: one worker owns it."""

    def __init__(self, config: ClassifierConfig | None = None, *, straggler_timeout_s: float = 0.05,
                 limits: Limits = LIMITS, stream: StreamLimits | None = None,
                 calibration_model: NoiseModel | None = None, calibration: OnlineCalibration | None = None) -> None:
        """``calibration_model``: the scales for ``calibration: file``; ``calibration``: an online calibration to
        continue (the evaluator carries one across the recordings of one drive)."""
        self.core = MotionClassifierCore(config or ClassifierConfig(), calibration_model=calibration_model,
                                         online=calibration)
        self.assembler: FrameAssembler[ObservationRow, TrackedColumns] = FrameAssembler(
            straggler_timeout_s=straggler_timeout_s, max_frame_observations=limits.max_objects,
            guard=StreamGuard(stream or StreamLimits()))
        self.limits = limits

    def observations(self, payloads: Sequence[bytes], key_ids: Sequence[str] | None = None) -> ObservationColumns:
        """Read ``tracks/{id}`` payloads and keep each one's row (a straggler of a frame already decided is
        counted ``late_observations`` and dropped). The refused ones come back in ``errors``; ``key_ids``: the
        track IDs their keys name (a payload about another track is refused)."""
        cols = read_track_observations(payloads, self.limits, key_ids)
        for (seq, tid, row), stamp in zip(observation_rows(cols), cols.stamp.tolist()):
            self.assembler.add_observation_item(seq, tid, row, int(stamp))
        return cols

    def close(self, data: bytes, received_at: float) -> TrackedColumns | None:
        """Read one ``tracked`` payload and register it as the close of its frame; None when it was dropped (a
        duplicate, a late frame or a jump not yet confirmed: judged from its header, before it is read). A
        confirmed rewind (time going back: the tracker reset its tracks) resets the core; a confirmed restart of the
        seq with time going on keeps it (the tracker copies the scans' seq and keeps its tracks over a restarted
        driver: resetting had wiped every window).

        Raises :class:`~jitterguard.schemas.DecodeError` for a payload that fails validation.
        """
        head = peek_header(data)
        verdict = self.assembler.admit(*head, received_at) if head is not None else None
        if verdict is not None and not verdict.accepted:
            return None
        cols = read_tracked_objects(data, self.limits)
        h = cols.header
        restarts = self.assembler.counts.get("upstream_restarts", 0)
        ok = self.assembler.add_close_item(h.seq, cols.observed_track_ids, cols, received_at, h.stamp, verdict)
        if self.assembler.counts.get("upstream_restarts", 0) != restarts:  # time went back: the tracks are gone
            self.core.reset()
        return cols if ok else None

    def ready(self, now: float, *, give_up: bool = True) -> list[CompleteFrame[ObservationRow, TrackedColumns]]:
        """Frames complete (or, with ``give_up``, timed out waiting for stragglers) at ``now``, in seq order."""
        return self.assembler.pop_ready(now, give_up=give_up)

    @property
    def pending(self) -> int:
        """Frames closed but still waiting for stragglers."""
        return self.assembler.pending

    def finish(self, frame: CompleteFrame[ObservationRow, TrackedColumns]) -> FrameOutput:
        """Decide a complete frame and write its ``objects`` payload (``tracked`` with the decisions applied)."""
        tracked = frame.tracked
        h = tracked.header
        pos = tracked.ego_pose.position
        reported = np.asarray(tracked.objects[wire.ID], dtype="S32")
        every = observations_from_rows(frame.observations, h.seq, h.stamp, (float(pos.x), float(pos.y)), reported)
        decided = self.core.update(every) if len(every) else None
        obs, windows = every, reported
        in_frame = np.isin(every.track_ids, reported) if decided is not None else None
        if decided is not None and in_frame is not None and not in_frame.all():
            # a tentative track's window fills, but it has no decision to publish until ``tracked`` lists it; nor
            # has a track this frame's ``tracked`` leaves out (a foreign tracker's): ``published`` means "ever"
            obs, decided = every.subset(in_frame), decided.subset(in_frame)
            decided = decided if len(obs) else None
            windows = np.concatenate([reported, every.track_ids])
        dec = self.core.last_decisions(reported)
        objects = decided_objects(tracked.objects, dec)
        payload = write_tracked_objects(TrackedColumns(h, tracked.ego_pose, objects, []))
        return FrameOutput(seq=h.seq, header=h, objects=objects, payload=payload, reported=reported, decisions=dec,
                           observed=obs, decided=decided, windows=windows,
                           config=self.core.config, window=self.core.window, received_at=frame.received_at,
                           missing=frame.missing)

    def settle(self, out: FrameOutput) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
        """The work that can wait until ``objects`` is out (call before the next frame): learn the online
        calibration from the windows that filled and evict the windows of tracks ``out`` neither reports nor
        observed (a tentative track keeps its window while the tracker observes it); returns how many, and each
        reported object's label, last update stamp and seq (for the state queryable)."""
        evicted = self.core.retain(out.windows)  # learns first
        return (evicted, *self.core.last_meta(out.reported))

    def motion_payloads(self, out: FrameOutput) -> Iterator[tuple[str, bytes]]:
        """``(track_id, MotionState payload)`` per observed track of ``out``."""
        dec = out.decided
        if dec is None:
            return
        ids = [i.decode() for i in out.observed.track_ids.tolist()]
        cols = {k: getattr(dec, k) for k in
                ("z_x", "z_y", "chi2", "threshold", "alpha", "window_length", "speed", "mean_x", "mean_y")}
        cols["label"] = out.observed.labels
        header = Header(stamp=out.header.stamp, frame_id="map", seq=out.header.seq)
        yield from zip(ids, write_motion_states(header, ids, dec.state_names(), out.config.mode, cols))

