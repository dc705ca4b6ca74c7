"""The wire contract: pydantic v2 models for every payload jitterguard puts on Zenoh.

Field names and semantics mirror Autoware's ``autoware_perception_msgs`` (and the ``geometry_msgs`` types
they use) so that a bridge to a ROS 2 / Autoware stack is a mechanical field copy. Where jitterguard needs
more than Autoware carries (a frame's expected track IDs, the classifier's statistics) the extra fields are
named plainly and documented here.

Validation is strict on purpose: a payload from another process is untrusted input. Every float is finite,
covariances are 36 long (row-major 6x6 over x, y, z, roll, pitch, yaw) with non-negative variances,
labels are Autoware's 0..7, track IDs are 32 lowercase hex digits (a 16-byte UUID), and a point buffer's
length must match its field count.
"""

from __future__ import annotations

import hashlib
import json
from enum import IntEnum
from typing import Annotated, Any, ClassVar, Literal

from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    NonNegativeInt,
    StringConstraints,
    field_validator,
    model_validator,
)

SCHEMA_VERSION = 1
"""Bumped on any incompatible change of a model below; every top-level payload carries it."""

COVARIANCE_SIZE = 36
# Autoware's covariance index constants (row-major 6x6 over x, y, z, roll, pitch, yaw).
X_X, X_Y, Y_X, Y_Y, Z_Z, ROLL_ROLL, PITCH_PITCH, YAW_YAW = 0, 1, 6, 7, 14, 21, 28, 35
DIAGONAL = (X_X, Y_Y, Z_Z, ROLL_ROLL, PITCH_PITCH, YAW_YAW)


class Label(IntEnum):
    """``autoware_perception_msgs/ObjectClassification`` label constants."""

    UNKNOWN = 0
    CAR = 1
    TRUCK = 2
    BUS = 3
    TRAILER = 4
    MOTORCYCLE = 5
    BICYCLE = 6
    PEDESTRIAN = 7


LABEL_NAMES: dict[int, str] = {int(v): v.name.lower() for v in Label}
LABEL_BY_NAME: dict[str, int] = {v: k for k, v in LABEL_NAMES.items()}

TrackId = Annotated[str, StringConstraints(pattern=r"^[0-9a-f]{32}$")]
"""A 16-byte UUID as 32 lowercase hex digits (checked in pydantic-core: this is on the hot path)."""


class _Strict(BaseModel):
    """Base of every model: unknown fields, non-finite floats and values of another type are errors, not silently
    kept or coerced (strict: a string "12" is no seq, True and 1.0 are no label, "yes" is no bool; an int is a
    float, and msgpack's arrays are the covariance tuples)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, validate_default=False, strict=True)


class Message(_Strict):
    """Base of every top-level payload: it carries the schema version it was written with."""

    schema_version: Literal[1] = SCHEMA_VERSION


INT64_MAX = 2**63 - 1
Int64 = Annotated[int, Field(ge=0, le=INT64_MAX)]
"""A non-negative int that fits the wire's int64 (and numpy's): a stamp 2^64 - 1 is refused on receipt, not later."""


class Header(_Strict):
    """``std_msgs/Header`` with an integer stamp (ns since epoch, int64) and a monotonically increasing ``seq``."""

    stamp: Int64
    frame_id: str = "map"
    seq: Int64 = 0


class Point(_Strict):
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0


class Vector3(_Strict):
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0


class Quaternion(_Strict):
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    w: float = 1.0


class Pose(_Strict):
    position: Point = Field(default_factory=Point)
    orientation: Quaternion = Field(default_factory=Quaternion)


class Twist(_Strict):
    linear: Vector3 = Field(default_factory=Vector3)
    angular: Vector3 = Field(default_factory=Vector3)


def _zero_cov() -> tuple[float, ...]:
    return (0.0,) * COVARIANCE_SIZE


LIST_AS_TUPLE = BeforeValidator(lambda v: tuple(v) if type(v) is list else v)
"""For a tuple field of a strict model: msgpack's arrays and YAML's sequences arrive as lists."""

_Variance = Annotated[float, Field(ge=0.0)]
Covariance = Annotated[
    tuple[tuple(_Variance if i in DIAGONAL else float for i in range(COVARIANCE_SIZE))],  # type: ignore[misc]
    LIST_AS_TUPLE,
]
"""36 floats, row-major 6x6 over (x, y, z, roll, pitch, yaw); the diagonal (variances) must be >= 0.

A fixed-length tuple lets pydantic-core check length and signs without a Python call per object, which
matters at hundreds of objects per frame; an error names the offending index (``covariance.7``).
"""


class PoseWithCovariance(_Strict):
    pose: Pose = Field(default_factory=Pose)
    covariance: Covariance = Field(default_factory=_zero_cov)


class TwistWithCovariance(_Strict):
    twist: Twist = Field(default_factory=Twist)
    covariance: Covariance = Field(default_factory=_zero_cov)


class AccelWithCovariance(_Strict):
    accel: Twist = Field(default_factory=Twist)
    covariance: Covariance = Field(default_factory=_zero_cov)


class ObjectClassification(_Strict):
    label: Annotated[int, Field(ge=0, le=7)] = Label.UNKNOWN
    probability: Annotated[float, Field(ge=0.0, le=1.0)] = 1.0


class Shape(_Strict):
    """``autoware_perception_msgs/Shape``: BOUNDING_BOX=0, CYLINDER=1, POLYGON=2; dimensions are x=length."""

    BOUNDING_BOX: ClassVar[int] = 0
    CYLINDER: ClassVar[int] = 1
    POLYGON: ClassVar[int] = 2

    type: Annotated[int, Field(ge=0, le=2)] = 0
    footprint: list[Point] = Field(default_factory=list)
    dimensions: Vector3 = Field(default_factory=Vector3)


class OrientationAvailability(IntEnum):
    UNAVAILABLE = 0
    SIGN_UNKNOWN = 1
    AVAILABLE = 2


class DetectedObjectKinematics(_Strict):
    pose_with_covariance: PoseWithCovariance = Field(default_factory=PoseWithCovariance)
    has_position_covariance: bool = False
    orientation_availability: Annotated[int, Field(ge=0, le=2)] = OrientationAvailability.AVAILABLE
    twist_with_covariance: TwistWithCovariance = Field(default_factory=TwistWithCovariance)
    has_twist: bool = False
    has_twist_covariance: bool = False


class DetectedObject(_Strict):
    existence_probability: Annotated[float, Field(ge=0.0, le=1.0)] = 1.0
    classification: list[ObjectClassification] = Field(default_factory=list)
    kinematics: DetectedObjectKinematics = Field(default_factory=DetectedObjectKinematics)
    shape: Shape = Field(default_factory=Shape)


class TrackedObjectKinematics(_Strict):
    pose_with_covariance: PoseWithCovariance = Field(default_factory=PoseWithCovariance)
    twist_with_covariance: TwistWithCovariance = Field(default_factory=TwistWithCovariance)
    acceleration_with_covariance: AccelWithCovariance = Field(default_factory=AccelWithCovariance)
    orientation_availability: Annotated[int, Field(ge=0, le=2)] = OrientationAvailability.AVAILABLE
    is_stationary: bool = False


class TrackedObject(_Strict):
    object_id: TrackId
    existence_probability: Annotated[float, Field(ge=0.0, le=1.0)] = 1.0
    classification: list[ObjectClassification] = Field(default_factory=list)
    kinematics: TrackedObjectKinematics = Field(default_factory=TrackedObjectKinematics)
    shape: Shape = Field(default_factory=Shape)


# --------------------------------------------------------------------------------------------- payloads


class PointCloud(Message):
    """One LiDAR scan: ``num_points`` rows of packed little-endian float32, one column per name in ``fields``.

    ``ego_pose`` is the sensor's pose in the world frame at ``header.stamp`` (points are in the sensor frame).
    """

    MAX_CONTAINERS: ClassVar[int] = 64
    """Maps and lists a scan may hold (its header and pose: a handful; the points are one byte string): a hostile
    payload is refused at the 65th whatever its size (:class:`~.codec.ContainerBudget`)."""

    header: Header
    ego_pose: Pose = Field(default_factory=Pose)
    fields: list[str] = Field(default_factory=lambda: ["x", "y", "z", "intensity"], min_length=3)
    num_points: NonNegativeInt
    data: bytes

    @field_validator("fields")
    @classmethod
    def _xyz_first(cls, v: list[str]) -> list[str]:
        if v[:3] != ["x", "y", "z"]:
            raise ValueError("the first three fields must be x, y, z")
        if len(set(v)) != len(v):
            raise ValueError("field names must be unique")
        return v

    @model_validator(mode="after")
    def _buffer_matches(self) -> "PointCloud":
        expected = self.num_points * len(self.fields) * 4
        if len(self.data) != expected:
            raise ValueError(
                f"data: {len(self.data)} bytes do not match {self.num_points} points x {len(self.fields)} float32 fields"
                f" ({expected} bytes)"
            )
        return self


class DetectedObjects(Message):
    """One scan's detections, in the sensor frame (``header.frame_id``), with the scan's ego pose."""

    header: Header
    ego_pose: Pose = Field(default_factory=Pose)
    objects: list[DetectedObject] = Field(default_factory=list)


class TrackState(_Strict):
    """The tracker's estimate of one track after this frame's update, world frame.

    Deliberately compact: thousands of these cross the wire per second (one per track per frame) and each
    is validated on receipt; the full ``TrackedObject`` travels once per frame in ``tracked``.
    """

    object_id: TrackId
    label: Annotated[int, Field(ge=0, le=7)] = Label.UNKNOWN
    existence_probability: Annotated[float, Field(ge=0.0, le=1.0)] = 1.0
    x: float
    y: float
    yaw: float = 0.0
    vx: float = 0.0
    vy: float = 0.0
    hits: Int64 = 0
    age_s: Annotated[float, Field(ge=0.0)] = 0.0


class TrackObservation(Message):
    """What the tracker associated to one track in one frame (``header.seq`` is the frame's seq).

    ``detection`` is in the world frame with its covariance rotated into the world frame (R Σ Rᵀ);
    ``track`` is the tracker's state after the update.
    """

    header: Header
    detection: DetectedObject
    track: TrackState


class TrackedObjects(Message):
    """``autoware_perception_msgs/TrackedObjects`` plus the frame-closing list ``observed_track_ids``.

    The tracker publishes one ``tracks/{id}`` per ID in ``observed_track_ids`` before this message, so the
    classifier knows which stragglers to wait for. The classifier's ``objects`` output leaves it empty.
    ``ego_pose`` is the sensor's pose in the world frame at ``header.stamp``, copied from the ``detections``
    the frame came from (identity where unknown): the line of sight to each object (the origin of the
    classifier's variance calibration), and the ego frame to draw.
    """

    header: Header
    ego_pose: Pose = Field(default_factory=Pose)
    objects: list[TrackedObject] = Field(default_factory=list)
    observed_track_ids: list[TrackId] = Field(default_factory=list)


class GroundTruthObject(_Strict):
    """One labelled object of a replayed frame, world frame (box centre, ``dimensions`` x = length)."""

    instance_id: Annotated[str, StringConstraints(min_length=1, max_length=64)]
    label: Annotated[int, Field(ge=0, le=7)] = Label.UNKNOWN
    pose: Pose = Field(default_factory=Pose)
    dimensions: Vector3 = Field(default_factory=Vector3)
    velocity: Vector3 = Field(default_factory=Vector3)
    moving: bool = Field(description="motion truth as the evaluator scores it (nuScenes attribute, else speed)")
    attribute: Annotated[str, StringConstraints(max_length=64)] = ""


class GroundTruthObjects(Message):
    """Ground truth of one replayed frame, for viewers (Foxglove) and recorders; never an input of the pipeline.

    Published by the replay on ``groundtruth`` when its source has labels (the synthetic world), before the frame's
    ``points`` / ``detections``, with the same ``header.seq`` and ``stamp``; ``header.frame_id`` is the world frame.
    """

    header: Header
    objects: list[GroundTruthObject] = Field(default_factory=list)


MotionLabel = Literal["static", "dynamic", "undecided"]
TestMode = Literal["z_test", "chi2", "velocity_threshold"]
EffectiveN = Literal["cluster", "independent", "measured"]
CalibrationMode = Literal["off", "online", "file"]


class MotionState(Message):
    """The classifier's decision for one track in one frame, with the statistics behind it."""

    header: Header
    track_id: TrackId
    label: Annotated[int, Field(ge=0, le=7)] = Label.UNKNOWN
    state: MotionLabel
    mode: TestMode
    z_x: float = 0.0
    z_y: float = 0.0
    chi2: float = 0.0
    threshold: float = Field(description="the value the statistic was compared with (alpha, χ² quantile or m/s)")
    alpha: float
    window_length: Int64
    speed: Annotated[float, Field(ge=0.0)] = 0.0
    mean_x: float = 0.0
    mean_y: float = 0.0


AUTHORS_ALPHA = {
    "car": 2.58,
    "truck": 2.58,
    "bus": 2.58,
    "trailer": 1.64,
    "motorcycle": 1.96,
    "bicycle": 1.64,
    "pedestrian": 1.28,
    "unknown": 1.96,
}
"""The per-class alpha the paper's authors deployed (DESIGN.md): the default (and the ``authors`` preset file)."""


def _default_alpha_per_class() -> dict[str, float]:
    return dict(AUTHORS_ALPHA)


AUTOWARE_SPEED_THRESHOLDS = {"pedestrian": 0.28, "bicycle": 0.28, "unknown": 0.28}
"""Autoware's static-obstacle-avoidance ``th_moving_speed`` for the classes below 1.0 m/s (car, truck, bus, trailer
and motorcycle: 1.0, ``velocity_threshold``'s default). Until 6 Dec a motorcycle was held to 0.28 here, as issue 15
listed it; Autoware's own ``static_obstacle_avoidance.param.yaml`` holds it to 1.0 (its ``th_moving_time`` 1.0 s)."""


def _default_speed_thresholds() -> dict[str, float]:
    return dict(AUTOWARE_SPEED_THRESHOLDS)


def _default_sustain() -> dict[str, float]:
    return {}


VEHICLE_VIEW_SLIDE_M = 2.0
"""The view term's slide for vehicles (car, truck, bus, trailer), m per unit turn of the line of sight: chosen on
tuning seeds 0–3 by a rule written first and checked on validation seeds 3000–3009 (docs/classifier.md 'The view
term')."""


def _default_view_slide() -> dict[str, float]:
    return dict.fromkeys(("car", "truck", "bus", "trailer"), VEHICLE_VIEW_SLIDE_M)


def _default_bands() -> list[float]:
    return [20.0, 40.0]


CLASS_KEYS: dict[str, Any] = {"propertyNames": {"enum": sorted(LABEL_BY_NAME)}}
"""What the JSON schema says of a per-class map's keys (the model's validator checks them, the schema had not)."""


def _check_class_names(v: dict[str, float]) -> dict[str, float]:
    unknown = sorted(set(v) - set(LABEL_BY_NAME))
    if unknown:  # the first few names, and how many: 300,000 made-up keys had made a 3 MB one-line error
        shown = ", ".join(repr(u[:40]) for u in unknown[:5])
        if len(unknown) > 5:
            shown += f" and {len(unknown) - 5} more"
        raise ValueError(f"unknown class name(s) {shown}; expected some of {sorted(LABEL_BY_NAME)}")
    return v


MAX_WINDOW = 64
"""Largest ``window_size`` (6.4 s at 10 Hz; the paper uses 10, the default is 20)."""


class ClassifierConfig(Message):
    """Everything that tunes the motion classifier; a write applies from the next frame on."""

    mode: TestMode = "z_test"
    alpha_default: Annotated[float, Field(gt=0.0, le=100.0)] = 1.96
    alpha_per_class: dict[str, Annotated[float, Field(gt=0.0, le=100.0)]] = Field(
        json_schema_extra=CLASS_KEYS,
        default_factory=_default_alpha_per_class,
        description="per-class alpha overrides, keyed by lowercase Autoware class name (car, truck, ...); default: "
        "the authors' deployed values (vehicles 2.58, pedestrian 1.28, ...)",
    )
    window_size: Annotated[int, Field(ge=2, le=MAX_WINDOW, description=(
        "observations per track window: 20 (2 s at 10 Hz; the paper's 10 with preset paper — docs/classifier.md "
        "'The window'); the calibrated test and the online calibration hold W × W matrices per window: bounded "
        "so that a config write cannot exhaust memory"))] = 20
    window_reference_hz: Annotated[float, Field(ge=0.1, le=1000.0)] | None = Field(
        10.0, description="the frame rate window_size is meant for, Hz: a slower stream (its rate measured from "
        "the frames' stamps) gets proportionally fewer observations, the same span in time, but never fewer than "
        "min(10, window_size) (the paper's window; 2 Hz key frames: 10, not 20 observations = 10 s); a faster one "
        "(from 1.6 times this rate) takes every k-th frame into the window, k = round(rate / this), the same span "
        "at this rate's cost (20 Hz: every second frame); null: window_size observations of every frame at any rate "
        "(docs/classifier.md 'The window')")
    min_window: Annotated[int, Field(ge=2, le=MAX_WINDOW)] = 2
    variance_floor: Annotated[float, Field(gt=0.0, le=1e6)] = 1e-4
    effective_n: EffectiveN = Field(
        "measured", description="cluster: each half is one sample (the paper); independent: real counts; "
        "measured: the variance of the half-mean difference under the calibrated serial correlation")
    calibration: CalibrationMode = Field(
        "online", description="off: reported variances as they are; online: learnt from the tracks, without "
        "labels (docs/calibration.md); file: the scales in calibration_file (jitterguard calibrate)")
    calibration_file: Annotated[str, StringConstraints(min_length=1, max_length=4096)] | None = Field(
        None, description="YAML written by `jitterguard calibrate`, read by the classifier when calibration is "
        "file")
    calibration_range_bands_m: Annotated[list[Annotated[float, Field(gt=0.0, le=1000.0)]],
                                         Field(max_length=8)] = Field(
        default_factory=_default_bands, description="range bands of the calibration split at these distances, m "
        "(kept sorted, repeats dropped)")
    calibration_prior_blocks: Annotated[float, Field(ge=0.0, le=1e6)] = Field(
        20.0, description="pseudo-blocks of the calibration prior at each level (class group, range band)")
    calibration_half_life_s: Annotated[float, Field(gt=0.0, le=1e7)] = Field(
        600.0, description="data time after which a calibration block counts half")
    min_speed_mps: Annotated[float, Field(ge=0.0, le=10.0)] = Field(
        0.1, description="the test's null hypothesis is |v| ≤ this, m/s: slower drifts (annotation or box wander) "
        "are not motion (0: the paper's H0, v = 0)")
    velocity_threshold: Annotated[float, Field(ge=0.0, le=100.0)] = 1.0
    velocity_threshold_per_class: dict[str, Annotated[float, Field(ge=0.0, le=100.0)]] = Field(
        json_schema_extra=CLASS_KEYS,
        default_factory=_default_speed_thresholds,
        description="per-class speed thresholds of the baseline, m/s (default: Autoware's 0.28 for pedestrians, "
        "bicycles and unknown; every other class velocity_threshold)")
    velocity_sustain_s_per_class: dict[str, Annotated[float, Field(ge=0.0, le=60.0)]] = Field(
        json_schema_extra=CLASS_KEYS,
        default_factory=_default_sustain,
        description="per-class time the speed must stay above the threshold before the baseline says dynamic, s "
        "(Autoware's th_moving_time: the `autoware-sustain` preset)")
    dynamic_hold_s_per_class: dict[str, Annotated[float, Field(ge=0.0, le=60.0)]] = Field(
        json_schema_extra=CLASS_KEYS,
        default_factory=dict,
        description="per-class time the test must keep rejecting H0 before the classifier says dynamic, s (none: at "
        "once, as the paper; a short hold in place of Autoware's th_moving_time: the `hold` preset)")

    view_slide_m_per_class: dict[str, Annotated[float, Field(ge=0.0, le=100.0)]] = Field(
        json_schema_extra=CLASS_KEYS,
        default_factory=_default_view_slide,
        description="per-class slide of a detected box centre with the sensor's view of the object, m per unit "
        "turn of the line of sight: s² Δū Δūᵀ is added to the covariance of the half-mean contrast, Δū the same "
        "contrast of the unit vectors from the sensor to the window's mean position (the turn the sensor's own "
        "motion makes), so that a parked car whose centre follows "
        "the faces the sensor sees as it drives past is not called moving (calibrated statistic only; none: "
        "no term — docs/classifier.md 'The view term')")

    jump_veto: bool = Field(
        True, description="a window the test rejects (a vehicle's from 6 observations, another class's once full) "
        "that one jump of the box explains better than steady motion "
        "(residuals about the best single step below those about the constant-velocity line and about a stand "
        "that starts or ends at one observation) is not called dynamic, whatever its test statistic: a detector "
        "that re-places a box once is not a moving object (z_test and chi2 modes; false: the paper's test alone; "
        "docs/classifier.md 'The jump veto')")

    @field_validator("alpha_per_class", "velocity_threshold_per_class", "velocity_sustain_s_per_class",
                     "dynamic_hold_s_per_class", "view_slide_m_per_class")
    @classmethod
    def _known_classes(cls, v: dict[str, float]) -> dict[str, float]:
        return _check_class_names(v)

    @field_validator("calibration_range_bands_m")
    @classmethod
    def _increasing(cls, v: list[float]) -> list[float]:
        """Band edges are a set of distances: kept sorted and without repeats (any order is accepted)."""
        return sorted(set(v))

    @field_validator("*", mode="after")
    @classmethod
    def _no_negative_zero(cls, v: Any) -> Any:
        """-0.0 kept as 0.0: the two are the same value, and a config holding -0.0 had a version tag
        (:func:`config_etag`) of its own, so a conditional write naming the tag of the equal config was refused."""
        if isinstance(v, float):
            return v + 0.0  # -0.0 + 0.0 is 0.0; every other float unchanged
        if isinstance(v, dict):
            return {k: x + 0.0 if isinstance(x, float) else x for k, x in v.items()}
        if isinstance(v, list):
            return [x + 0.0 if isinstance(x, float) else x for x in v]
        return v

    @model_validator(mode="after")
    def _window_order(self) -> "ClassifierConfig":
        if self.min_window > self.window_size:
            raise ValueError(f"min_window ({self.min_window}) must not exceed window_size ({self.window_size})")
        if self.calibration == "file" and not self.calibration_file:
            raise ValueError("calibration 'file' needs calibration_file")
        return self

    def alpha_for(self, label: int) -> float:
        return self.alpha_per_class.get(LABEL_NAMES.get(label, "unknown"), self.alpha_default)

    def speed_threshold_for(self, label: int) -> float:
        """The baseline's speed threshold for an Autoware label, m/s."""
        return self.velocity_threshold_per_class.get(LABEL_NAMES.get(label, "unknown"), self.velocity_threshold)

    def sustain_for(self, label: int) -> float:
        """How long the baseline's speed must exceed the threshold before it says dynamic, s (0: at once)."""
        return self.velocity_sustain_s_per_class.get(LABEL_NAMES.get(label, "unknown"), 0.0)

    def hold_for(self, label: int) -> float:
        """How long the test must keep rejecting H0 before the classifier says dynamic, s (0: at once)."""
        return self.dynamic_hold_s_per_class.get(LABEL_NAMES.get(label, "unknown"), 0.0)

    def view_slide_for(self, label: int) -> float:
        """How far a box centre of this class slides per unit turn of the view direction, m (0: no view term)."""
        return self.view_slide_m_per_class.get(LABEL_NAMES.get(label, "unknown"), 0.0)



ETAG_HEX = 16
"""Hex digits of a config's etag (64 bits of its SHA-256): two configs that differ never share one in practice."""
ETAG_PATTERN = rf"^[0-9a-f]{{{ETAG_HEX}}}$"


def config_etag(config: ClassifierConfig) -> str:
    """The version tag of a config: a digest of its canonical JSON, so equal configs have equal tags whoever wrote
    them and a restart does not reset it (a counter would come round to a number a writer still holds). A
    conditional write names the tag it read; the classifier applies it only while that config is still in force."""
    text = json.dumps(config.model_dump(mode="json"), sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode()).hexdigest()[:ETAG_HEX]


class ConfigReply(Message):
    """The classifier's answer to a config get/set: what is in force now, or why the write was refused.

    ``etag`` is :func:`config_etag` of ``config``, so that a client can make a conditional write (the query
    parameter ``if_match``) without computing a digest of JSON itself. ``conflict`` marks a conditional write
    refused because another write had changed the config since the writer read it (nothing applied)."""

    ok: bool
    config: ClassifierConfig
    error: str | None = None
    etag: Annotated[str, StringConstraints(pattern=ETAG_PATTERN)] | None = None
    conflict: bool = False

    @model_validator(mode="after")
    def _etag_is_the_configs(self) -> "ConfigReply":
        if self.etag is not None and self.etag != config_etag(self.config):
            raise ValueError("etag is not the digest of config")
        return self


class TrackStateEntry(_Strict):
    """One track as the classifier sees it (the ``classifier/state`` queryable)."""

    track_id: TrackId
    label: Annotated[int, Field(ge=0, le=7)]
    state: MotionLabel
    z_x: float
    z_y: float
    chi2: float
    alpha: float
    threshold: float
    window_length: Int64
    window_size: NonNegativeInt
    speed: float
    x: float
    y: float
    yaw: float = 0.0
    length: float = 0.0
    width: float = 0.0
    last_update_ns: NonNegativeInt
    last_seq: NonNegativeInt


_Scale = Annotated[float, Field(ge=0.0, le=1e6)]


class CalibrationAxis(_Strict):
    """The calibration of one class group on one line-of-sight axis (docs/calibration.md)."""

    scale: dict[str, _Scale] = Field(description="true / reported variance per range band (e.g. '0-20'), "
                                     "established tracks")
    scale_young: dict[str, _Scale] = Field(description="the same for a track's first window_size observations")
    blocks: dict[str, Annotated[float, Field(ge=0.0)]] = Field(description="evidence per band: blocks pooled "
                                                                "(after forgetting)")
    blocks_young: dict[str, Annotated[float, Field(ge=0.0)]]
    correlation: Annotated[float, Field(ge=0.0, le=1.0)] = Field(description="serially correlated share m")
    correlation_time_s: Annotated[float, Field(gt=0.0)]
    variance_factor: Annotated[float, Field(ge=0.0)] = Field(
        description="Var(half-mean difference) of a full window under the serial correlation / that of "
        "independent observations (1: none; window/2: the paper's cluster assumption)")


class CalibrationGroup(_Strict):
    track_dof: Annotated[float, Field(gt=0.0)] = Field(
        description="ν₀: prior degrees of freedom of a track's own scale (smaller: tracks differ more)")
    along: CalibrationAxis
    across: CalibrationAxis


class CalibrationState(_Strict):
    """What the classifier's variance calibration uses now (``GET /v1/state``'s ``calibration``)."""

    mode: CalibrationMode
    effective_n: EffectiveN
    range_bands_m: list[float]
    frame_interval_s: Annotated[float, Field(gt=0.0)]
    window: Annotated[int, Field(ge=1)]
    groups: dict[str, CalibrationGroup]
    counts: dict[str, int] = Field(default_factory=dict, description="blocks pooled, too fast to pool, "
                                   "down-weighted as outliers")
    effective_blocks: Annotated[float, Field(ge=0.0)] = 0.0
    scale_dof: Annotated[float, Field(gt=0.0)] | None = Field(
        None, description="degrees of freedom of the scales themselves: 2 at a cold start, 8 more per block of "
        "evidence; the test's tails are heavier while it is small. null: scales taken as given (a file, or off)")


class ClassifierStateSnapshot(Message):
    """The live per-track state of the classifier after its latest frame, and its variance calibration."""

    header: Header
    config: ClassifierConfig
    tracks: list[TrackStateEntry] = Field(default_factory=list)
    counters: dict[str, int] = Field(default_factory=dict)
    calibration: CalibrationState | None = None


class Heartbeat(Message):
    """Published every second by every service on ``jg/{ns}/heartbeat/{service}``: health beyond liveliness.

    ``counters`` are integer event counts; ``gauges`` are current values that are not counts (the classifier:
    its variance scales and correlation factors, e.g. ``calibration.vehicle.along.scale.0-20``).
    """

    service: str
    pid: NonNegativeInt
    stamp: NonNegativeInt
    last_seq: int = -1
    uptime_s: Annotated[float, Field(ge=0.0)] = 0.0
    counters: dict[str, int] = Field(default_factory=dict)
    gauges: dict[str, float] = Field(default_factory=dict)
    health: Literal["ok", "failing", "stalled"] = Field(
        "ok", description="whether the service turns its input into output (jitterguard.runtime.progress)")
    health_reason: Annotated[str, Field(max_length=500)] = ""
