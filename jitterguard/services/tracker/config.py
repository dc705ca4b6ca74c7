"""Tracker configuration: Autoware's association gates, per-class motion/measurement noise, track lifecycle.

The association matrices default to Autoware's own, so ``jitterguard/config/tracker.param.yaml`` (written from
this model) is a file a user can diff against Autoware's ``data_association_matrix.param.yaml``; ``--config FILE``
overrides any subset of the keys (flat, or in Autoware's ``/**: ros__parameters:`` wrapper), through the one
loader every service uses (:mod:`jitterguard.config`).

Everything here is plain data; :meth:`TrackerConfig.tables` turns it into the numpy lookup tables the core
indexes by label on the hot path.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from ...config import dump_params, load
from ...schemas.models import LABEL_BY_NAME, LABEL_NAMES
from ...schemas.wire import Limits
from ...stream_order import StreamLimits

NUM_LABELS = 8
MATRIX_KEYS = ("can_assign_matrix", "max_dist_matrix", "max_area_matrix", "min_area_matrix", "max_rad_matrix")

# Autoware's multi_object_tracker defaults (autoware_multi_object_tracker/config/data_association_matrix.param.yaml),
# so a user can compare the two trackers on identical inputs.
CAN_ASSIGN = [  # rows: track label; columns: measurement label (UNKNOWN, CAR, TRUCK, BUS, TRAILER, MOTORBIKE, BICYCLE, PEDESTRIAN)
    1, 0, 0, 0, 0, 0, 0, 0,
    0, 1, 1, 1, 1, 0, 0, 0,
    0, 1, 1, 1, 1, 0, 0, 0,
    0, 1, 1, 1, 1, 0, 0, 0,
    0, 1, 1, 1, 1, 0, 0, 0,
    0, 0, 0, 0, 0, 1, 1, 1,
    0, 0, 0, 0, 0, 1, 1, 1,
    0, 0, 0, 0, 0, 1, 1, 1,
]
MAX_DIST = [  # rows: track label; columns: measurement label (UNKNOWN, CAR, TRUCK, BUS, TRAILER, MOTORBIKE, BICYCLE, PEDESTRIAN)
    4.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0,
    4.0, 2.0, 5.0, 5.0, 5.0, 1.0, 1.0, 1.0,
    4.0, 2.0, 5.0, 5.0, 5.0, 1.0, 1.0, 1.0,
    4.0, 2.0, 5.0, 5.0, 5.0, 1.0, 1.0, 1.0,
    4.0, 2.0, 5.0, 5.0, 5.0, 1.0, 1.0, 1.0,
    3.0, 1.0, 1.0, 1.0, 1.0, 3.0, 3.0, 2.0,
    3.0, 1.0, 1.0, 1.0, 1.0, 3.0, 3.0, 2.0,
    2.0, 1.0, 1.0, 1.0, 1.0, 3.0, 3.0, 2.0,
]
# the size of a truck is 12 m x 3 m with a margin; a trailer's bound is large not to be filtered
MAX_AREA = [  # rows: track label; columns: measurement label (UNKNOWN, CAR, TRUCK, BUS, TRAILER, MOTORBIKE, BICYCLE, PEDESTRIAN)
    10000.0, 10000.0, 10000.0, 10000.0, 10000.0, 10000.0, 10000.0, 10000.0,
    12.1, 12.1, 36.0, 40.0, 3600.0, 10000.0, 10000.0, 10000.0,
    36.0, 12.1, 36.0, 40.0, 3600.0, 10000.0, 10000.0, 10000.0,
    40.0, 12.1, 36.0, 40.0, 3600.0, 10000.0, 10000.0, 10000.0,
    3600.0, 12.1, 36.0, 40.0, 3600.0, 10000.0, 10000.0, 10000.0,
    2.5, 10000.0, 10000.0, 10000.0, 10000.0, 2.5, 2.5, 1.0,
    2.5, 10000.0, 10000.0, 10000.0, 10000.0, 2.5, 2.5, 1.0,
    2.0, 10000.0, 10000.0, 10000.0, 10000.0, 1.5, 1.5, 1.0,
]
MIN_AREA = [  # rows: track label; columns: measurement label (UNKNOWN, CAR, TRUCK, BUS, TRAILER, MOTORBIKE, BICYCLE, PEDESTRIAN)
    0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
    3.6, 3.6, 6.0, 10.0, 10.0, 0.0, 0.0, 0.0,
    6.0, 3.6, 6.0, 10.0, 10.0, 0.0, 0.0, 0.0,
    10.0, 3.6, 6.0, 10.0, 10.0, 0.0, 0.0, 0.0,
    10.0, 3.6, 6.0, 10.0, 10.0, 0.0, 0.0, 0.0,
    0.001, 0.0, 0.0, 0.0, 0.0, 0.1, 0.1, 0.1,
    0.001, 0.0, 0.0, 0.0, 0.0, 0.1, 0.1, 0.1,
    0.001, 0.0, 0.0, 0.0, 0.0, 0.1, 0.1, 0.1,
]
# a value above pi disables the heading gate for that pair
MAX_RAD = [  # rows: track label; columns: measurement label (UNKNOWN, CAR, TRUCK, BUS, TRAILER, MOTORBIKE, BICYCLE, PEDESTRIAN)
    3.15, 3.15, 3.15, 3.15, 3.15, 3.15, 3.15, 3.15,
    3.15, 1.047, 1.047, 1.047, 1.047, 3.15, 3.15, 3.15,
    3.15, 1.047, 1.047, 1.047, 1.047, 3.15, 3.15, 3.15,
    3.15, 1.047, 1.047, 1.047, 1.047, 3.15, 3.15, 3.15,
    3.15, 1.047, 1.047, 1.047, 1.047, 3.15, 3.15, 3.15,
    3.15, 3.15, 3.15, 3.15, 3.15, 3.15, 3.15, 3.15,
    3.15, 3.15, 3.15, 3.15, 3.15, 3.15, 3.15, 3.15,
    3.15, 3.15, 3.15, 3.15, 3.15, 3.15, 3.15, 3.15,
]

MotionModel = Literal["cv", "ctrv"]
MeasurementCovariance = Literal["detector", "class"]
MahalanobisCovariance = Literal["innovation", "track"]
MeasurementScaleMode = Literal["online", "off"]

PosFloat = Annotated[float, Field(gt=0.0, allow_inf_nan=False)]
NonNegFloat = Annotated[float, Field(ge=0.0, allow_inf_nan=False)]


class _Strict(BaseModel):
    """Unknown keys, non-finite floats and values of another type are errors: a YAML ``observe_tentative: 1`` or
    ``confirm_hits: "3"`` is refused, naming the field, instead of read as true or 3 (an int is a float)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, strict=True)


class ClassParams(_Strict):
    """Motion and measurement noise of one object class.

    Measurement standard deviations are in the object's own frame (along / across its heading), as in
    Autoware's trackers, and are rotated into the world frame with the measured heading; they are used when
    ``measurement_covariance`` is ``class`` or when a detection carries no covariance of its own.
    """

    model: MotionModel = "cv"
    # process noise
    q_acc: PosFloat = Field(2.0, description="CV: white-noise acceleration stddev (m/s^2); CTRV: longitudinal")
    q_acc_lat: PosFloat = Field(1.5, description="CTRV: lateral acceleration stddev (m/s^2) on the position")
    q_yaw: PosFloat = Field(0.3, description="heading random-walk stddev (rad/sqrt(s))")
    q_yaw_rate_acc: PosFloat = Field(0.5, description="CTRV: yaw-rate random-walk stddev (rad/s^2)")
    # measurement noise (class-based defaults)
    r_long: PosFloat = Field(0.5, description="position stddev along the heading (m)")
    r_lat: PosFloat = Field(0.4, description="position stddev across the heading (m)")
    r_yaw: PosFloat = Field(0.0873, description="heading stddev (rad)")
    # initial state uncertainty of a new track
    p0_vel: PosFloat = Field(5.0, description="initial speed stddev (m/s)")
    p0_yaw_rate: PosFloat = Field(0.5, description="CTRV: initial yaw-rate stddev (rad/s)")
    max_speed: PosFloat = Field(40.0, description="speed clamp (m/s): a filter never reports more")
    max_yaw_rate: PosFloat = Field(1.5, description="CTRV: yaw-rate clamp (rad/s)")
    # lifecycle
    confirm_hits: Annotated[int, Field(ge=1, le=100)] | None = Field(
        None, description="associated detections before a track of this class is confirmed (published);"
        " None: the global confirm_hits (Autoware's confident_count_threshold per class)")


def _default_classes() -> dict[str, ClassParams]:
    vehicle = dict(model="ctrv", q_acc=3.43, q_acc_lat=1.47, q_yaw=0.05, q_yaw_rate_acc=0.6,
                   r_long=0.5, r_lat=0.4, r_yaw=0.0873, p0_vel=10.0, p0_yaw_rate=0.3, max_speed=45.0,
                   max_yaw_rate=1.0)
    return {
        "unknown": ClassParams(model="cv", q_acc=2.0, q_yaw=0.5, r_long=0.5, r_lat=0.5, r_yaw=0.5, p0_vel=5.0,
                               max_speed=30.0),
        "car": ClassParams(**vehicle),
        "truck": ClassParams(**{**vehicle, "r_long": 0.8, "q_acc": 2.5}),
        "bus": ClassParams(**{**vehicle, "r_long": 0.8, "q_acc": 2.5}),
        "trailer": ClassParams(**{**vehicle, "r_long": 0.8, "q_acc": 2.5}),
        "motorcycle": ClassParams(model="cv", q_acc=3.0, q_yaw=0.5, r_long=0.5, r_lat=0.4, r_yaw=0.3,
                                  p0_vel=8.0, max_speed=40.0),
        "bicycle": ClassParams(model="cv", q_acc=2.0, q_yaw=0.5, r_long=0.5, r_lat=0.4, r_yaw=0.5236,
                               p0_vel=5.0, max_speed=15.0),
        "pedestrian": ClassParams(model="cv", q_acc=1.5, q_yaw=1.0, r_long=0.4, r_lat=0.4, r_yaw=0.5236,
                                  p0_vel=2.5, max_speed=5.0),
    }


class TrackerConfig(_Strict):
    """Everything that tunes the tracker. Defaults: Autoware's gates, Autoware-like noise, 1 s coast."""

    # ---- association (Autoware's data_association_matrix.param.yaml; rows = track label, cols = measurement)
    can_assign_matrix: list[int] = Field(
        default_factory=lambda: list(CAN_ASSIGN), min_length=NUM_LABELS**2, max_length=NUM_LABELS**2,
        description="8x8, row-major: rows are the TRACK's label, columns the MEASUREMENT's, in Autoware's order"
        " UNKNOWN, CAR, TRUCK, BUS, TRAILER, MOTORBIKE, BICYCLE, PEDESTRIAN. A (track, detection) pair is a"
        " candidate only if can_assign is 1, the distance <= max_dist, min_area <= the detection's footprint area"
        " <= max_area, the heading difference (mod pi) <= max_rad and the Mahalanobis distance < mahalanobis_gate;"
        " its score is (max_dist - dist) / max_dist and the assignment maximises the total score")
    max_dist_matrix: list[PosFloat] = Field(default_factory=lambda: list(MAX_DIST), description="metres",
                                            min_length=NUM_LABELS**2, max_length=NUM_LABELS**2)
    max_area_matrix: list[NonNegFloat] = Field(default_factory=lambda: list(MAX_AREA), description="m^2",
                                               min_length=NUM_LABELS**2, max_length=NUM_LABELS**2)
    min_area_matrix: list[NonNegFloat] = Field(default_factory=lambda: list(MIN_AREA), description="m^2",
                                               min_length=NUM_LABELS**2, max_length=NUM_LABELS**2)
    max_rad_matrix: list[NonNegFloat] = Field(
        default_factory=lambda: list(MAX_RAD), min_length=NUM_LABELS**2, max_length=NUM_LABELS**2,
        description="radians; above pi disables the heading gate")
    min_iou_matrix: list[float] | None = Field(
        None, description="accepted from an Autoware file and not applied: for boxes that passed the distance and"
        " area gates Autoware's 2D-IoU gate rarely changes the outcome")
    mahalanobis_gate: PosFloat = Field(
        3.035, description="sqrt of the 99% quantile of chi-square with 2 dof (sqrt(9.21)), as in Autoware")
    mahalanobis_covariance: MahalanobisCovariance = Field(
        "innovation",
        description="innovation: gate on the track's predicted position covariance plus the detection's"
        " (the statistically sound gate); track: on the track's covariance alone, as Autoware does",
    )
    score_threshold: NonNegFloat = Field(0.01, description="pairs scoring below it are never assigned (Autoware's)")
    gate_min_variance: NonNegFloat = Field(
        0.04,
        description="added to the Mahalanobis gate's covariance diagonal (m^2): a converged track of a parked"
        " object with an over-confident detector would otherwise reject its own detection and spawn a twin",
    )
    max_candidates: Annotated[int, Field(ge=1, le=10_000)] = Field(
        32, description="at most this many detections per track are scored, the nearest: a crowd of co-located"
        " objects costs memory bounded by the gating, not by the product of the counts")
    overlap_factor: NonNegFloat = Field(
        0.75,
        description="two tracks whose labels may share a detection and whose centres are closer than this"
        " times the narrower box's width describe one object: the one with fewer hits is deleted, as"
        " Autoware's removal of overlapped trackers does (0 disables)",
    )
    overlap_min_iou: Annotated[float, Field(ge=0.0, le=1.0)] = Field(
        0.1,
        description="two tracks whose bird's-eye boxes overlap with an IoU above this describe one object,"
        " whatever their labels: the one with fewer hits is deleted (Autoware's removeOverlappedTracker, 0.1;"
        " 0 disables). Catches the second box a detector puts on one vehicle a metre or two off its centre,"
        " which the centre-distance rule (overlap_factor) misses and which would live on as a ghost track",
    )
    overlap_min_iou_unknown: Annotated[float, Field(ge=0.0, le=1.0)] = Field(
        0.001,
        description="the same IoU bound where either track is UNKNOWN (Autoware's 0.001: an unclassified box"
        " touching a classified one is the same object, and the UNKNOWN one is deleted; 0 disables)",
    )

    # ---- measurement model
    measurement_covariance: MeasurementCovariance = Field(
        "detector",
        description="detector: the detector's own variances (rotated into the world frame) where a detection"
        " has them, class defaults where it has not; class: always the class defaults",
    )
    min_position_variance: PosFloat = Field(1e-3, description="floor on a detector's position variance (m^2)")
    measurement_scale: MeasurementScaleMode = Field(
        "off",
        description="online: learn from the tracks themselves, without labels, how far the detector's position"
        " variances are off (per class group, along and across the line of sight, per range band; the"
        " classifier's estimator) and scale them before the gate and the update; off: take them as reported"
        " (the default: on the one real scene measured, online made both motion rules worse; docs/tracker.md)",
    )
    measurement_scale_window: Annotated[int, Field(ge=5, le=100)] = Field(
        10, description="consecutive detections of one track per block the measurement scale learns from")
    classes: dict[str, ClassParams] = Field(default_factory=_default_classes)

    # ---- lifecycle
    confirm_hits: Annotated[int, Field(ge=1, le=100)] = Field(
        3, description="associated detections before a track is confirmed; only confirmed tracks are published"
        " (Autoware's confident_count_threshold; a class may override it in classes.<name>.confirm_hits)")
    confirm_min_existence: Annotated[float, Field(ge=0.0, le=1.0)] = Field(
        0.25,
        description="a track is confirmed only once its running existence probability (the smoothed scores of"
        " its detections) reaches this as well: a clutter return that the detector scores low every frame"
        " stays tentative and is never published, however often it recurs; 0 disables. Confirmation is"
        " final: a confirmed track is published until the lifecycle deletes it",
    )
    observe_tentative: bool = Field(
        False,
        description="publish the detections of tentative tracks on tracks/{id} too (listed in tracked's"
        " observed_track_ids, never in its objects): the classifier's window of a track then starts with the"
        " track's first detection, as the tracker's own velocity does, instead of at its confirmation. Off by"
        " default: on validation seeds it catches 0.3-1.4 points more moving vehicles and 0.6-3 more walkers,"
        " and calls 1.4-3.1 points more ghost vehicle rows moving (docs/tracker.md, 'Tentative observations')",
    )
    tentative_max_gap_s: PosFloat = Field(0.25, description="a tentative track missing longer is deleted")
    max_coast_s: PosFloat = Field(1.0, description="a confirmed track without a detection longer is deleted")
    max_position_stddev: PosFloat = Field(5.0, description="a track whose position stddev grows past it is deleted")
    stream: StreamLimits = Field(
        default_factory=StreamLimits, description="how far a detections frame may step from the last one taken;"
        " a discontinuity (restart, rewind, long gap) is followed only once successive frames confirm it")
    shape_smoothing: Annotated[float, Field(gt=0.0, le=1.0)] = Field(
        0.3, description="weight of a new detection's box dimensions in the track's running estimate"
    )
    limits: Limits = Field(default_factory=Limits, description="bounds on the work one detections message may cause")

    @field_validator("classes", mode="before")
    @classmethod
    def _merge_classes(cls, v: Any) -> Any:
        """A user file may tune one field of one class; everything it does not name keeps its default."""
        if not isinstance(v, dict):
            return v
        unknown = sorted(set(v) - set(LABEL_BY_NAME))
        if unknown:
            raise ValueError(f"unknown class name(s) {unknown}; expected some of {sorted(LABEL_BY_NAME)}")
        merged: dict[str, Any] = {k: p.model_dump() for k, p in _default_classes().items()}
        for name, params in v.items():
            if isinstance(params, ClassParams):
                params = params.model_dump()
            if not isinstance(params, dict):
                raise ValueError(f"classes.{name} must be a mapping")
            merged[name] = {**merged[name], **params}
        return merged

    @model_validator(mode="after")
    def _check_matrices(self) -> "TrackerConfig":
        # (each matrix's 64 entries are its field's own bound, which the JSON schema states too)
        if any(v not in (0, 1) for v in self.can_assign_matrix):
            raise ValueError("can_assign_matrix entries must be 0 or 1")
        mn = np.asarray(self.min_area_matrix)
        mx = np.asarray(self.max_area_matrix)
        bad = np.flatnonzero(mn > mx)
        if bad.size:
            i = int(bad[0])
            raise ValueError(f"min_area_matrix exceeds max_area_matrix at row {i // 8}, column {i % 8}")
        return self

    def params_for(self, label: int) -> ClassParams:
        return self.classes[LABEL_NAMES[label]]

    def tables(self) -> "ConfigTables":
        """The numpy lookup tables the core indexes by label on every frame (built once per core)."""
        by = [self.params_for(lbl) for lbl in range(NUM_LABELS)]

        def col(name: str) -> np.ndarray:
            return np.array([getattr(p, name) for p in by], dtype=np.float64)

        return ConfigTables(
            can_assign=np.asarray(self.can_assign_matrix, dtype=bool).reshape(NUM_LABELS, NUM_LABELS),
            max_dist=np.asarray(self.max_dist_matrix, dtype=np.float64).reshape(NUM_LABELS, NUM_LABELS),
            max_area=np.asarray(self.max_area_matrix, dtype=np.float64).reshape(NUM_LABELS, NUM_LABELS),
            min_area=np.asarray(self.min_area_matrix, dtype=np.float64).reshape(NUM_LABELS, NUM_LABELS),
            max_rad=np.asarray(self.max_rad_matrix, dtype=np.float64).reshape(NUM_LABELS, NUM_LABELS),
            model=np.array([1 if p.model == "ctrv" else 0 for p in by], dtype=np.int8),
            q_acc=col("q_acc"),
            q_acc_lat=col("q_acc_lat"),
            q_yaw=col("q_yaw"),
            q_yaw_rate_acc=col("q_yaw_rate_acc"),
            r_long=col("r_long"),
            r_lat=col("r_lat"),
            r_yaw=col("r_yaw"),
            p0_vel=col("p0_vel"),
            p0_yaw_rate=col("p0_yaw_rate"),
            max_speed=col("max_speed"),
            max_yaw_rate=col("max_yaw_rate"),
            confirm_hits=np.array([self.confirm_hits if p.confirm_hits is None else p.confirm_hits for p in by],
                                  dtype=np.int64),
        )


@dataclass(frozen=True)
class ConfigTables:
    """Per-label lookup tables (8 entries, or 8x8 for label pairs indexed [track_label, measurement_label])."""

    can_assign: np.ndarray
    max_dist: np.ndarray
    max_area: np.ndarray
    min_area: np.ndarray
    max_rad: np.ndarray
    model: np.ndarray
    q_acc: np.ndarray
    q_acc_lat: np.ndarray
    q_yaw: np.ndarray
    q_yaw_rate_acc: np.ndarray
    r_long: np.ndarray
    r_lat: np.ndarray
    r_yaw: np.ndarray
    p0_vel: np.ndarray
    p0_yaw_rate: np.ndarray
    max_speed: np.ndarray
    max_yaw_rate: np.ndarray
    confirm_hits: np.ndarray


# ------------------------------------------------------------------------------------------------ loading


def default_config(**overrides: Any) -> TrackerConfig:
    """The shipped defaults, with keyword overrides (what tests and the bench use)."""
    return load(TrackerConfig, overrides=overrides)


def load_config(path: str | Path | None = None, **overrides: Any) -> TrackerConfig:
    """Shipped defaults, then the keys of ``path`` (if given), then ``overrides`` (CLI flags; None = not given)."""
    return load(TrackerConfig, path, overrides=overrides)


def dump_config(config: TrackerConfig) -> str:
    """The config as a parameter file (what ``--print-config`` shows and ``config/tracker.param.yaml`` holds):
    it loads back with ``--config`` to the identical config, so it is a starting point for edits."""
    return dump_params(config, "jitterguard tracker (jitterguard tracker --config FILE); Autoware's layout",
                       rows=dict.fromkeys(MATRIX_KEYS, 8))
