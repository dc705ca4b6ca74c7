"""Detector presets and the two array bundles every detector module speaks: ground-truth samples and detections.

Kept free of torch so that data, evaluation and the service adapter import it cheaply. Boxes are always
``(N, 9)`` float32 in the *sensor* frame: ``x, y, z, l, w, h, yaw, vx, vy`` with ``z`` the box centre,
``yaw`` counter-clockwise from +x and velocities in m/s (nuScenes' box convention, yaw as CenterPoint decodes it).
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Annotated, Literal, overload

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, PositiveInt, field_validator

from ...config import load, param_file, presets
from ...files import not_a_file
from ...schemas.models import LIST_AS_TUPLE, Label

F32 = NDArray[np.float32]
I64 = NDArray[np.int64]

CLASS_NAMES: tuple[str, ...] = ("car", "truck", "bus", "bicycle", "pedestrian")
"""The detector's classes, in head order (the paper's five; Autoware's CenterPoint classes)."""

CLASS_LABELS: tuple[Label, ...] = (Label.CAR, Label.TRUCK, Label.BUS, Label.BICYCLE, Label.PEDESTRIAN)
"""Autoware label of each class index."""

AUTOWARE_TO_CLASS: dict[int, int] = {
    int(Label.CAR): 0,
    int(Label.TRUCK): 1,
    int(Label.TRAILER): 1,  # Autoware's CenterPoint folds trailers into trucks
    int(Label.BUS): 2,
    int(Label.BICYCLE): 3,
    int(Label.MOTORCYCLE): 3,  # ... and motorcycles into bicycles
    int(Label.PEDESTRIAN): 4,
}
"""Autoware label → class index; labels absent here (UNKNOWN) are not detector targets."""

CLASS_RANGE_M: tuple[float, ...] = (50.0, 50.0, 50.0, 40.0, 40.0)
"""nuScenes' evaluation range per class (BEV distance from the sensor); boxes beyond it are not scored."""

BOX_DIM = 9
VAR_NAMES: tuple[str, ...] = ("x", "y", "vx", "vy", "yaw")
"""Order of the log-variance channels (paper §III-A)."""


class DetectorConfig(BaseModel):
    """Architecture, grid and target parameters of one CenterPoint-PointPillars variant (a preset file, or the
    ``config`` stored in a weights file).

    ``point_cloud_range`` is (x_min, y_min, z_min, x_max, y_max, z_max) in the sensor frame; the BEV grid is
    ``grid_size`` pillars of ``voxel_size`` metres; the heads run at ``out_size_factor`` times coarser.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    name: str = Field(description="the preset this architecture is, or was derived from")
    point_cloud_range: tuple[float, float, float, float, float, float]
    voxel_size: tuple[float, float, float]
    max_points_per_pillar: PositiveInt
    max_pillars: PositiveInt
    pfn_channels: PositiveInt
    backbone_layers: tuple[int, ...]
    backbone_strides: tuple[int, ...]
    backbone_channels: tuple[int, ...]
    neck_upsample_strides: tuple[float, ...]
    neck_channels: tuple[int, ...]
    head_channels: PositiveInt
    out_size_factor: PositiveInt
    head_conv_layers: PositiveInt = Field(
        2, description="3x3 conv layers per separate head, the output conv included (CenterPoint: one hidden + the"
        " output = 2; lite: the output conv straight off the shared conv = 1)")
    uncertainty: bool = Field(
        True, description="variance heads (log sigma^2 for x, y, vx, vy, yaw) trained with Gaussian NLL; false"
        " gives the vanilla model")
    gaussian_overlap: float = 0.1
    min_radius: int = 2
    max_objects: PositiveInt = 500
    score_threshold: Annotated[float, Field(ge=0.0, le=1.0)] = 0.1
    nms_dist2: tuple[float, ...] = Field(
        (4.0, 12.0, 10.0, 0.85, 0.175),
        description="circle-NMS threshold per class on the squared BEV centre distance in m^2 (CenterPoint's"
        " circle_nms semantics and nuScenes values: car 4 = 2 m, pedestrian 0.175 = 0.42 m)")
    post_max_size: PositiveInt = Field(
        300, description="detections kept per scan after NMS (a diagonal lot holds 100+ cars in range)")
    num_point_features: PositiveInt = Field(
        4, description="point fields fed in: x, y, z, intensity (intensity scaled to [0, 1] by dividing by 255)")
    use_intensity: bool = Field(
        True, description="feed the intensity field (false: it is fed as 0 in training and inference alike, for"
        " sensors whose intensities differ from what the model was trained on; `train --no-intensity`)")
    logvar_min: float = -10.0
    class_names: tuple[str, ...] = CLASS_NAMES

    @property
    def grid_size(self) -> tuple[int, int]:
        """(nx, ny) pillars."""
        r, v = self.point_cloud_range, self.voxel_size
        return round((r[3] - r[0]) / v[0]), round((r[4] - r[1]) / v[1])

    @property
    def feature_map_size(self) -> tuple[int, int]:
        """(nx, ny) cells of the heads' output."""
        nx, ny = self.grid_size
        return nx // self.out_size_factor, ny // self.out_size_factor

    @property
    def num_classes(self) -> int:
        return len(self.class_names)


PRESETS: dict[str, DetectorConfig] = {
    name: load(DetectorConfig, param_file("detector", name)) for name in presets("detector")}
"""The shipped architectures (``jitterguard/config/detector.<name>.param.yaml``): ``paper``, the paper's deployed
model (±100 m, 0.390625 m pillars, 512×512, SECOND [3,5,5]/[64,128,256], FPN to 384), and ``lite``, real time on
two CPU cores (nuScenes' ±51.2 m, 0.4 m pillars, 256×256, a thinner and shallower SECOND)."""
PAPER, LITE = PRESETS["paper"], PRESETS["lite"]


SENSOR_HEIGHT_RANGE_M = (-2.0, 6.0)
"""Heights of a scan's frame above the road a deployment may declare (``sensor_height_m``): a base_link cloud is
0, a truck's roof LiDAR 4–5 m; what lies outside is a typo (a height in centimetres, a sign)."""


def parse_sensor_height(text: str) -> float | Literal["auto"]:
    """A ``--sensor-height`` value: ``auto`` or metres within :data:`SENSOR_HEIGHT_RANGE_M`; ValueError otherwise."""
    if text.strip().lower() == "auto":
        return "auto"
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"expected 'auto' or a height in metres, got {text!r}") from None
    lo, hi = SENSOR_HEIGHT_RANGE_M
    if not lo <= value <= hi:  # (NaN fails too)
        raise ValueError(f"expected 'auto' or a height in metres within [{lo:g}, {hi:g}], got {text!r}")
    return value


def declared_height(value: float | str | None) -> float | None:
    """The :class:`~.inference.Detector`'s ``sensor_height_m`` for a config or ``--sensor-height`` value: None
    (measure) for ``auto``; a value not given (None) is the service's default (:class:`DetectorParams`')."""
    if value is None:
        value = DetectorParams.model_fields["sensor_height_m"].default
    return None if value == "auto" else float(value)


def measures_tilt(value: str | None) -> bool:
    """The :class:`~.inference.Detector`'s ``sensor_tilt`` for a config or ``--sensor-tilt`` value (None: the
    service's default, :class:`DetectorParams`')."""
    if value is None:
        value = DetectorParams.model_fields["sensor_tilt"].default
    return value == "auto"


SELF_CROP_M: tuple[float, float, float, float] = (-2.0, -2.0, 2.0, 2.0)
"""The default box (x_min, y_min, x_max, y_max, sensor frame, metres) whose returns are the vehicle's own body and
are dropped before the network sees the scan. A roof-mounted spinning LiDAR sees its own car: on nuScenes'
LIDAR_TOP a third of every scan's returns lie within 0.5 m of the sensor and a few thousand more on the roof,
bonnet and boot out to 1.2 m to one side and 1.6 m to the other (x ±0.63 m, y −1.18…+1.59 m in its frame), and
the shipped weights, shown them, report a car at the sensor in every scan — a ghost that drives with the ego
and reads as moving. Cropping only nuScenes' ``remove_close(1.0)`` square leaves the bonnet and boot returns, and
the ghost with them. This default is a passenger car (≈ 4.5 × 1.8 m) around a roof-centre sensor whichever axis
is forward: ±2 m. It crops what lies within about 1.1 m of the car's sides too — set your vehicle's box (as
Autoware's self-cropping ``crop_box_filter`` takes its dimensions), or null to keep every return."""


def check_crop_box(box: Sequence[float] | None) -> tuple[float, float, float, float] | None:
    """``box`` as four floats (x_min, y_min, x_max, y_max) if it is one — finite, each min below its max — else
    ``ValueError``; None stays None (no crop). The one check of a self-crop box, for the parameter file and for
    a :class:`~.inference.Detector` built in code alike."""
    if box is None:
        return None
    b = tuple(float(v) for v in box)
    if len(b) != 4 or not all(math.isfinite(v) for v in b) or b[0] >= b[2] or b[1] >= b[3]:
        raise ValueError(f"self_crop must be (x_min, y_min, x_max, y_max), finite, with x_min < x_max and"
                         f" y_min < y_max, got {list(box)}")
    return b  # type: ignore[return-value]


class DetectorParams(BaseModel):
    """``jitterguard detector --config FILE``: how the service runs (the architecture comes with the weights)."""

    # strict about types, as the wire is: a YAML ``score_threshold: yes`` had been read as 1.0 (every detection
    # dropped), ``threads: "4"`` as 4
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, strict=True)

    preset: str = Field("lite", description="architecture preset whose shipped weights load when weights is null")
    weights: str | None = Field(None, description="weights file (torch.save dict, loaded weights_only)")
    threads: Annotated[int, Field(ge=1, le=1024)] | None = Field(None, description="torch CPU threads (null: all)")
    score_threshold: Annotated[float, Field(ge=0.0, le=1.0)] | None = Field(
        None, description="keep detections scoring above this (null: the weights' config)")
    twist: bool = Field(True, description="publish the network's velocity as the twist")
    self_crop: Annotated[tuple[float, float, float, float] | None, LIST_AS_TUPLE] = Field(
        SELF_CROP_M, description="drop returns inside this box (x_min, y_min, x_max, y_max; sensor frame, m): the"
        " vehicle's own body (default: a passenger car around a roof-centre sensor; null: keep every return)")
    sweeps: Annotated[int, Field(ge=1, le=20)] | None = Field(
        None, description="scans stacked per network input for a model trained on stacked sweeps (five point"
        " fields: x, y, z, intensity, time lag): the newest and the earlier ones of the last max_sweep_lag_s, moved"
        " into its frame through the scans' poses (null: what the weights were trained with; 1 for a four-field"
        " model)")
    max_sweep_lag_s: Annotated[float, Field(gt=0.0, le=5.0)] = Field(
        0.55, description="earlier scans older than this are not stacked, s (CenterPoint: 0.5 s)")
    flips: bool = Field(False, description="average the network over the scan and its three mirror images"
                        " (CenterPoint's test-time flips: on the real nuScenes scene-0523 car AP 0.184 -> 0.212,"
                        " pedestrian 0.089 -> 0.119; in the synthetic loop more ghost vehicles called moving in"
                        " 'mixed'; about 4x the network's time, over 100 ms a scan on 2 CPU cores: for a GPU or a"
                        " larger CPU; docs/detector.md)")
    max_scan_bytes: Annotated[int, Field(ge=1 << 20)] = Field(
        64 << 20, description="larger points payloads are refused unread (counted rejected.points, over_limit.points):"
        " 64 MiB is 4 million points of four float32 fields, ten times a 128-beam sensor's scan")
    sensor_height_m: Annotated[float, Field(ge=SENSOR_HEIGHT_RANGE_M[0], le=SENSOR_HEIGHT_RANGE_M[1])] | Literal[
        "auto"] = Field("auto", description="height of the scans' frame above the road, m: 1.84 for nuScenes'"
                        " LIDAR_TOP, your LiDAR's mounting height for its own frame, 0 for a cloud in base_link"
                        " (Autoware's concatenated cloud); scans are moved to the 1.84 m the network was trained at"
                        " and the boxes back ('auto': measured from each scan's ground returns; docs/detector.md)")
    sensor_tilt: Literal["auto", "level"] = Field(
        "auto", description="'auto': the road plane's slope under each scan is measured and taken out (every"
        " return's z made its height above the plane), so a sensor pitched or rolled against the road, a braking"
        " vehicle or a crest hands the network the level road it learnt on; 'level': the scans' frame is taken as"
        " level (docs/detector.md 'The sensor's tilt')")
    backend: Literal["torch", "onnxruntime"] = Field("torch", description="what runs the network")
    onnx: str | None = Field(None, description="onnxruntime backend: a folder written by `jitterguard export-onnx`"
                             " (null: export weights / preset at start-up into a temporary folder)")

    @field_validator("self_crop")
    @classmethod
    def _box_has_extent(cls, box: tuple[float, float, float, float] | None) -> tuple[float, ...] | None:
        return check_crop_box(box)


def onnx_network(folder: str) -> str | None:
    """The architecture an ONNX export folder holds (its ``detector.json``'s ``config.name``), or None where the
    manifest cannot tell (missing or malformed: the backend's loader says why, naming the file). Read as plain JSON,
    the graphs not hashed: a start-up check, not the load."""
    import json

    try:
        with open(os.path.join(folder, "detector.json"), encoding="utf-8") as f:
            doc = json.load(f)
    except (OSError, ValueError):
        return None
    name = doc.get("config", {}).get("name") if isinstance(doc, dict) and isinstance(doc.get("config"), dict) else None
    return name if isinstance(name, str) else None


def params_refusal(params: DetectorParams) -> tuple[str, str] | None:
    """``(key, why)`` if the detector cannot start with ``params`` — a preset it does not have, a weights file or an
    ONNX folder that is not there, ONNX without its backend, a preset given (file or flag) that contradicts the
    network the ONNX folder holds (it had been ignored without a word: the file said paper, the detector ran the
    export's lite), the onnxruntime backend without its packages — else
    None: the one check of ``jitterguard detector`` and of ``up --detector-config``, which had started the whole
    stack on such a file and then watched the detector crash three times."""
    if params.preset not in PRESETS:
        return "preset", f"expected one of {', '.join(PRESETS)}, got {params.preset!r}"
    if params.weights is not None and (why := not_a_file(params.weights)):
        return "weights", why
    if params.onnx is not None and (params.backend != "onnxruntime" or params.weights is not None):
        return "onnx", "goes with backend onnxruntime and replaces weights"
    if params.onnx is not None and not os.path.isdir(params.onnx):
        return "onnx", f"folder not found: {params.onnx}"
    if params.onnx is not None and "preset" in params.model_fields_set:
        held = onnx_network(params.onnx)
        if held is not None and held != params.preset:
            return "preset", (f"{params.preset!r} contradicts onnx {params.onnx}, a {held!r} network (its"
                              " detector.json); drop preset (the export fixes the network) or point onnx at a"
                              f" {params.preset!r} export")
    if params.backend == "onnxruntime":  # without an export folder the weights are exported at start-up
        import importlib.util

        needed = ("onnxruntime",) if params.onnx is not None else ("onnxruntime", "onnx", "onnxscript")
        missing = [m for m in needed if importlib.util.find_spec(m) is None]
        if missing:  # had been found only after the start-up export, and reported against --weights
            return "backend", (f"onnxruntime needs the {', '.join(missing)} package{'s' if len(missing) > 1 else ''}"
                               " (pip install 'jitterguard[onnx]')")
    return None


@dataclass(frozen=True)
class Sample:
    """One labelled scan: points (P, 4) x, y, z, intensity (0–255) in the sensor frame; boxes (M, 9) and class
    indices (M,) in the same frame; ``num_points`` (M,) LiDAR returns inside each box (0 = not visible);
    ``token`` names the scan (scenario/seed/frame or a nuScenes sample token). ``pseudo``: the boxes are a
    model's own detections (self-training), which teach where objects are but not how precisely — their
    regression targets are not trained on (:func:`~.targets.build_targets`). ``unscored``: labelled objects of no
    detector class (nuScenes' barriers, traffic cones, debris…) as (category, x, y) in the same frame — never
    trained on or scored, only what a false positive is told to stand on
    (:func:`~.evaluate.false_positives_on`)."""

    points: F32
    boxes: F32
    labels: I64
    num_points: I64
    token: str = ""
    pseudo: bool = False
    unscored: tuple[tuple[str, float, float], ...] = ()


class LazySamples(Sequence[Sample]):
    """A sequence of samples built one at a time on access (from disk or a dataroot), so a training set never has
    to fit in memory; subclasses say how long they are and how to build sample ``i``."""

    def _sample(self, i: int) -> Sample:
        raise NotImplementedError

    @overload
    def __getitem__(self, i: int) -> Sample: ...

    @overload
    def __getitem__(self, i: slice) -> list[Sample]: ...

    def __getitem__(self, i: int | slice) -> Sample | list[Sample]:
        if isinstance(i, slice):
            return [self._sample(j) for j in range(*i.indices(len(self)))]
        if not -len(self) <= i < len(self):
            raise IndexError(i)
        return self._sample(i % len(self))

    def __iter__(self) -> Iterator[Sample]:
        for i in range(len(self)):
            yield self._sample(i)


@dataclass(frozen=True)
class Detections3D:
    """Decoded detections of one scan in the sensor frame: boxes (K, 9), scores (K,), class indices (K,), and
    log-variances (K, 5) of x, y, vx, vy, yaw (``None`` for the vanilla model)."""

    boxes: F32
    scores: F32
    labels: I64
    log_variances: F32 | None

    def __len__(self) -> int:
        return len(self.scores)

    def subset(self, keep: NDArray[np.bool_]) -> "Detections3D":
        """The detections where ``keep`` is true, in order."""
        lv = self.log_variances[keep] if self.log_variances is not None else None
        return Detections3D(self.boxes[keep], self.scores[keep], self.labels[keep], lv)

    @staticmethod
    def empty(uncertainty: bool = True) -> "Detections3D":
        return Detections3D(np.zeros((0, BOX_DIM), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int64),
                            np.zeros((0, len(VAR_NAMES)), np.float32) if uncertainty else None)
