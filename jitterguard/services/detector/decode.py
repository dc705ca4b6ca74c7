"""From head maps to boxes: heatmap peaks → top-K → box decoding → per-class circle NMS.

Circle NMS (CenterPoint) suppresses a lower-scored detection of the same class whose BEV centre lies within a
class-specific squared distance of a kept one; it needs no box overlap computation and runs on CPU in
microseconds for the few hundred candidates a scan yields.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from numpy.typing import NDArray
from torch import Tensor

from .config import BOX_DIM, DetectorConfig, Detections3D


def circle_nms(xy: NDArray[np.float32], scores: NDArray[np.float32], dist2: float) -> NDArray[np.int64]:
    """Indices kept by greedy circle NMS, in descending score order."""
    order = np.argsort(-scores, kind="stable")
    pts = xy[order]
    d2 = ((pts[:, None, :] - pts[None, :, :]) ** 2).sum(-1)
    suppressed = np.zeros(len(order), np.bool_)
    keep = []
    for i in range(len(order)):
        if suppressed[i]:
            continue
        keep.append(order[i])
        suppressed |= d2[i] <= dist2
    return np.asarray(keep, np.int64)


@torch.no_grad()
def decode(out: dict[str, Tensor], config: DetectorConfig, score_threshold: float | None = None
           ) -> list[Detections3D]:
    """Decode a batch of raw head maps into per-scan detections (sensor frame, log-variances in m², m²/s², rad²)."""
    thr = config.score_threshold if score_threshold is None else score_threshold
    heat = torch.sigmoid(out["heatmap"])
    b, c, h, w = heat.shape
    peaks = heat * (F.max_pool2d(heat, 3, stride=1, padding=1) == heat)
    k = min(config.max_objects, c * h * w)
    scores, idx = peaks.view(b, -1).topk(k)
    cls = idx // (h * w)
    pix = idx % (h * w)
    r = config.point_cloud_range
    cell_x = config.voxel_size[0] * config.out_size_factor
    cell_y = config.voxel_size[1] * config.out_size_factor

    def take(name: str) -> Tensor:
        f = out[name]
        return f.view(b, f.shape[1], -1).gather(2, pix.unsqueeze(1).expand(b, f.shape[1], k)).transpose(1, 2)

    reg, height, dim, rot, vel = take("reg"), take("height"), take("dim"), take("rot"), take("vel")
    xs = ((pix % w).float() + reg[..., 0]) * cell_x + r[0]
    ys = ((pix // w).float() + reg[..., 1]) * cell_y + r[1]
    yaw = torch.atan2(rot[..., 0], rot[..., 1])
    boxes = torch.cat([xs[..., None], ys[..., None], height, dim.clamp(max=5.0).exp(), yaw[..., None], vel], dim=-1)
    logvar = take("logvar").clamp(min=config.logvar_min) if config.uncertainty and "logvar" in out else None
    results = []
    boxes, scores, cls = boxes.float().cpu(), scores.float().cpu(), cls.cpu()
    logvar = logvar.float().cpu() if logvar is not None else None
    for i in range(b):
        keep = scores[i] > thr
        bx = boxes[i][keep].numpy().astype(np.float32)
        sc = scores[i][keep].numpy().astype(np.float32)
        lb = cls[i][keep].numpy().astype(np.int64)
        lv = logvar[i][keep].numpy().astype(np.float32) if logvar is not None else None
        kept: list[NDArray[np.int64]] = []
        for ci in np.unique(lb):
            rows = np.flatnonzero(lb == ci)
            kept.append(rows[circle_nms(bx[rows, :2], sc[rows], config.nms_dist2[int(ci)])])
        sel = np.concatenate(kept) if kept else np.zeros(0, np.int64)
        sel = sel[np.argsort(-sc[sel], kind="stable")][: config.post_max_size]
        results.append(Detections3D(bx[sel].reshape(-1, BOX_DIM), sc[sel], lb[sel],
                                    lv[sel] if lv is not None else None))
    return results
