"""Detector presets and the two array bundles every detector module speaks: ground-truth samples and detections.

Kept free of torch so that data, evaluation and the service adapter import it cheaply. Boxes are always
``(N, 9)`` float32 in the *sensor* frame: ``x, y, z, l, w, h, yaw, vx, vy`` with ``z`` the box centre,
``yaw`` counter-clockwise from +x and velocities in m/s (nuScenes' box convention, yaw as CenterPoint decodes it).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ...schemas.models import Label

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


@dataclass(frozen=True)
class DetectorConfig:
    """Architecture, grid and target parameters of one CenterPoint-PointPillars variant.

    ``point_cloud_range`` is (x_min, y_min, z_min, x_max, y_max, z_max) in the sensor frame; the BEV grid is
    ``grid_size`` pillars of ``voxel_size`` metres; the heads run at ``out_size_factor`` times coarser.
    """

    name: str
    point_cloud_range: tuple[float, float, float, float, float, float]
    voxel_size: tuple[float, float, float]
    max_points_per_pillar: int
    max_pillars: int
    pfn_channels: int
    backbone_layers: tuple[int, ...]
    backbone_strides: tuple[int, ...]
    backbone_channels: tuple[int, ...]
    neck_upsample_strides: tuple[float, ...]
    neck_channels: tuple[int, ...]
    head_channels: int
    out_size_factor: int
    head_conv_layers: int = 2
    """3×3 conv layers per separate head, the output conv included (CenterPoint: one hidden + the output ⇒ 2;
    ``lite``: the output conv straight off the shared conv ⇒ 1)."""
    uncertainty: bool = True
    """Variance heads (log σ² for x, y, vx, vy, yaw) trained with Gaussian NLL; False gives the vanilla model."""
    gaussian_overlap: float = 0.1
    min_radius: int = 2
    max_objects: int = 500
    score_threshold: float = 0.1
    nms_dist2: tuple[float, ...] = (4.0, 12.0, 10.0, 0.85, 0.175)
    """Circle-NMS threshold per class on the *squared* BEV centre distance in m² (CenterPoint's circle_nms
    semantics and nuScenes values: car 4 ⇒ 2 m, pedestrian 0.175 ⇒ 0.42 m)."""
    post_max_size: int = 300
    """Detections kept per scan after NMS (a diagonal lot holds 100+ cars in range, more than nuScenes scenes)."""
    num_point_features: int = 4
    """Point fields fed in: x, y, z, intensity (intensity scaled to [0, 1] by dividing by 255)."""
    logvar_min: float = -10.0
    class_names: tuple[str, ...] = field(default=CLASS_NAMES)

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


PAPER = DetectorConfig(
    name="paper",
    point_cloud_range=(-100.0, -100.0, -5.0, 100.0, 100.0, 3.0),
    voxel_size=(0.390625, 0.390625, 8.0),
    max_points_per_pillar=20,
    max_pillars=40000,
    pfn_channels=64,
    backbone_layers=(3, 5, 5),
    backbone_strides=(2, 2, 2),
    backbone_channels=(64, 128, 256),
    neck_upsample_strides=(0.5, 1.0, 2.0),
    neck_channels=(128, 128, 128),
    head_channels=64,
    out_size_factor=4,
)
"""The paper's deployed model (DESIGN.md): ±100 m, 0.390625 m pillars, 512×512, SECOND [3,5,5]/[64,128,256], FPN to 384."""

LITE = DetectorConfig(
    name="lite",
    point_cloud_range=(-51.2, -51.2, -3.0, 51.2, 51.2, 3.0),
    voxel_size=(0.4, 0.4, 6.0),
    max_points_per_pillar=16,
    max_pillars=16000,
    pfn_channels=32,
    backbone_layers=(1, 2, 2),
    backbone_strides=(2, 2, 2),
    backbone_channels=(32, 64, 128),
    neck_upsample_strides=(0.5, 1.0, 2.0),
    neck_channels=(64, 64, 64),
    head_channels=32,
    out_size_factor=4,
    head_conv_layers=1,
)
"""Real time on two CPU cores: nuScenes' ±51.2 m range, 0.4 m pillars (256×256), thinner and shallower SECOND."""

PRESETS: dict[str, DetectorConfig] = {"paper": PAPER, "lite": LITE}


@dataclass(frozen=True)
class Sample:
    """One labelled scan: points (P, 4) x, y, z, intensity (0–255) in the sensor frame; boxes (M, 9) and class
    indices (M,) in the same frame; ``num_points`` (M,) LiDAR returns inside each box (0 = not visible);
    ``token`` names the scan (scenario/seed/frame or a nuScenes sample token). ``pseudo``: the boxes are a
    model's own detections (self-training), which teach where objects are but not how precisely — their
    regression targets are not trained on (:func:`~.targets.build_targets`)."""

    points: F32
    boxes: F32
    labels: I64
    num_points: I64
    token: str = ""
    pseudo: bool = False


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

    @staticmethod
    def empty(uncertainty: bool = True) -> "Detections3D":
        return Detections3D(np.zeros((0, BOX_DIM), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int64),
                            np.zeros((0, len(VAR_NAMES)), np.float32) if uncertainty else None)
