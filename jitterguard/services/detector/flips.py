"""Test-time flips: run the network on a scan and on its mirror images, and average what it says.

CenterPoint's "double flip" test-time augmentation: the scan as it is, mirrored across the sensor's y axis (x →
−x), across its x axis (y → −y) and both — four views, run as one batch or one after the other (an ONNX export
takes one scan per call); each output map is flipped back onto the original grid, with the signs of the quantities
a mirror changes put right, and the four are averaged before decoding. A peak the network sees in one view only (a
clump of clutter that happens to look like a car's corner from one side) is diluted; an object seen in every view
keeps its score. The averaged heat is a probability, so it is averaged after the sigmoid and handed to
:func:`~.decode.decode` as a logit again.

What a mirror changes (the heads of :data:`~.network.HEAD_CHANNELS`, decoded as in :mod:`.decode`): the cell
offset along the mirrored axis (x = (i + reg) · cell + x_min on a grid symmetric about the sensor, so the
mirrored cell's offset is 1 − reg), the heading's sine (y mirrored) or cosine (x mirrored), and the velocity
along the mirrored axis. Height, size and the log-variances (variances of x and y, not of signed quantities)
are unchanged.

The grid must be symmetric about the sensor for a mirrored cell to be a cell (``point_cloud_range`` with
x_min = −x_max and y_min = −y_max), which :func:`check_symmetric` checks for the weights at hand.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .config import DetectorConfig

MIRRORS: tuple[tuple[bool, bool], ...] = ((False, False), (True, False), (False, True), (True, True))
"""(x mirrored, y mirrored) of the four views, in batch order."""


def check_symmetric(config: DetectorConfig) -> None:
    """Raise ValueError unless the BEV grid is symmetric about the sensor (a mirrored cell is then a cell)."""
    r = config.point_cloud_range
    if abs(r[0] + r[3]) > 1e-6 or abs(r[1] + r[4]) > 1e-6:
        raise ValueError(f"test-time flips need a grid symmetric about the sensor; point_cloud_range is {list(r)}")


def mirrored_views(points: Tensor) -> list[Tensor]:
    """The scan (P, F) as it is and mirrored, in :data:`MIRRORS` order."""
    views = []
    for mx, my in MIRRORS:
        p = points.clone() if (mx or my) else points
        if mx:
            p[:, 0] = -p[:, 0]
        if my:
            p[:, 1] = -p[:, 1]
        views.append(p)
    return views


def merge_mirrored(out: dict[str, Tensor]) -> dict[str, Tensor]:
    """The network's output on the four :func:`mirrored_views` (batch 4) as one scan's output (batch 1): each
    map flipped back onto the original grid, signs restored, averaged; the heatmap averaged as a probability and
    returned as a logit."""
    merged: dict[str, Tensor] = {}
    for name, maps in out.items():
        views = []
        for b, (mx, my) in enumerate(MIRRORS):
            m = maps[b:b + 1]
            if name == "heatmap":
                m = torch.sigmoid(m)
            dims = ([-1] if mx else []) + ([-2] if my else [])  # maps are (B, C, y, x)
            if dims:
                m = m.flip(dims)  # a new tensor (torch copies on flip): the in-place fixes below touch only it
            if mx:
                _undo_mirror(name, m, axis=0)
            if my:
                _undo_mirror(name, m, axis=1)
            views.append(m)
        mean = torch.stack(views).mean(0)
        merged[name] = torch.logit(mean.clamp(1e-6, 1.0 - 1e-6)) if name == "heatmap" else mean
    return merged


def _undo_mirror(name: str, m: Tensor, axis: int) -> None:
    """Put right, in place, the channels of head ``name`` that a mirror of ``axis`` (0: x → −x, 1: y → −y)
    changes."""
    if name == "reg":
        m[:, axis] = 1.0 - m[:, axis]
    elif name == "rot":  # (sin yaw, cos yaw): x mirrored, yaw → π − yaw flips the cosine; y mirrored the sine
        m[:, 1 - axis] = -m[:, 1 - axis]
    elif name == "vel":
        m[:, axis] = -m[:, axis]
