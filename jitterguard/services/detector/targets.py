"""CenterPoint training targets: Gaussian heatmaps per class plus per-object regression targets at centre cells.

Pure numpy so that targets are built in data-loader workers and tested without torch. Only boxes with at
least one LiDAR return inside the detector's range are targets (nuScenes' own rule: a box no ray touched
cannot be learned and is not scored).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .config import DetectorConfig, Sample

REG_DIM = 10
"""Regression target columns: reg_x, reg_y (cell offsets), z, log l, log w, log h, sin yaw, cos yaw, vx, vy."""


@dataclass
class Targets:
    """Targets of one scan. ``heatmap`` (C, H, W); per object slot k < ``max_objects``: ``ind`` (flat cell
    index y·W + x), ``mask`` (slot used), ``box`` (REG_DIM), ``yaw`` (radians), ``cls``."""

    heatmap: NDArray[np.float32]
    ind: NDArray[np.int64]
    mask: NDArray[np.bool_]
    box: NDArray[np.float32]
    yaw: NDArray[np.float32]
    cls: NDArray[np.int64]


def gaussian_radius(length: float, width: float, min_overlap: float) -> float:
    """CornerNet's radius: the largest centre shift that keeps IoU ≥ ``min_overlap`` in all three corner cases
    (both corners inside, both outside, one of each), solved as quadratics in the radius."""
    h, w = length, width
    b1 = h + w
    c1 = w * h * (1 - min_overlap) / (1 + min_overlap)
    r1 = (b1 + math.sqrt(b1 * b1 - 4 * c1)) / 2
    b2 = 2 * (h + w)
    c2 = (1 - min_overlap) * w * h
    r2 = (b2 + math.sqrt(b2 * b2 - 16 * c2)) / 2
    a3 = 4 * min_overlap
    b3 = -2 * min_overlap * (h + w)
    c3 = (min_overlap - 1) * w * h
    r3 = (b3 + math.sqrt(b3 * b3 - 4 * a3 * c3)) / 2
    return min(r1, r2, r3)


def draw_gaussian(heatmap: NDArray[np.float32], cx: int, cy: int, radius: int) -> None:
    """Max-blend a Gaussian of σ = (2r+1)/6 centred on cell (cx, cy) into ``heatmap`` (H, W), in place."""
    sigma = (2 * radius + 1) / 6.0
    r = np.arange(-radius, radius + 1)
    g = np.exp(-(r[None, :] ** 2 + r[:, None] ** 2) / (2 * sigma * sigma)).astype(np.float32)
    g[g < np.finfo(np.float32).eps * g.max()] = 0
    h, w = heatmap.shape
    x0, x1 = max(0, cx - radius), min(w, cx + radius + 1)
    y0, y1 = max(0, cy - radius), min(h, cy + radius + 1)
    if x0 >= x1 or y0 >= y1:
        return
    patch = g[y0 - (cy - radius): y1 - (cy - radius), x0 - (cx - radius): x1 - (cx - radius)]
    np.maximum(heatmap[y0:y1, x0:x1], patch, out=heatmap[y0:y1, x0:x1])


def target_mask(sample: Sample, config: DetectorConfig) -> NDArray[np.bool_]:
    """Rows of ``sample.boxes`` that are targets: seen by ≥ 1 return and centred inside the BEV grid."""
    r = config.point_cloud_range
    b = sample.boxes
    return ((sample.num_points > 0) & (b[:, 0] >= r[0]) & (b[:, 0] < r[3]) & (b[:, 1] >= r[1]) & (b[:, 1] < r[4])
            & (sample.labels >= 0) & (sample.labels < config.num_classes))


def build_targets(sample: Sample, config: DetectorConfig) -> Targets:
    """Encode ``sample``'s boxes as CenterPoint targets on the output grid. A pseudo-labelled sample's boxes
    draw the heatmap but leave ``mask`` off, so no regression loss (position, its variance, size, velocity)
    learns from a model's own guesses — trained on them the variance heads would shrink towards zero."""
    r = config.point_cloud_range
    cell_x = config.voxel_size[0] * config.out_size_factor
    cell_y = config.voxel_size[1] * config.out_size_factor
    w, h = config.feature_map_size
    k_max = config.max_objects
    heatmap = np.zeros((config.num_classes, h, w), np.float32)
    ind = np.zeros(k_max, np.int64)
    mask = np.zeros(k_max, np.bool_)
    box = np.zeros((k_max, REG_DIM), np.float32)
    yaw = np.zeros(k_max, np.float32)
    cls = np.zeros(k_max, np.int64)
    rows = np.flatnonzero(target_mask(sample, config))[:k_max]
    for k, i in enumerate(rows):
        x, y, z, length, width, height, theta, vx, vy = (float(v) for v in sample.boxes[i])
        c = int(sample.labels[i])
        fx, fy = (x - r[0]) / cell_x, (y - r[1]) / cell_y
        ix, iy = min(int(fx), w - 1), min(int(fy), h - 1)
        radius = gaussian_radius(length / cell_x, width / cell_y, config.gaussian_overlap)
        draw_gaussian(heatmap[c], ix, iy, max(config.min_radius, int(radius)))
        ind[k] = iy * w + ix
        mask[k] = not sample.pseudo
        box[k] = (fx - ix, fy - iy, z, math.log(max(length, 1e-3)), math.log(max(width, 1e-3)),
                  math.log(max(height, 1e-3)), math.sin(theta), math.cos(theta), vx, vy)
        yaw[k] = theta
        cls[k] = c
    return Targets(heatmap, ind, mask, box, yaw, cls)
