"""Planar polylines that lane agents drive along, parameterised by arc length.

A lane simulation only knows a scalar position ``s`` along its lane; a :class:`Path` turns ``s`` into a world
pose. Headings are piecewise constant per segment, so the heading at ``s`` is exactly the direction in which the
position moves there — that keeps ground-truth velocities consistent with finite differences of positions.
Positions beyond either end extrapolate along the end segment, so agents may drive off the mapped area.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]


class Path:
    """A polyline with cumulative arc length; ``pose_at(s)`` maps arc length to (x, y, heading)."""

    def __init__(self, points: ArrayLike) -> None:
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 2:
            raise ValueError("a path needs at least two (x, y) points")
        seg = np.diff(pts, axis=0)
        length = np.hypot(seg[:, 0], seg[:, 1])
        keep = np.concatenate([[True], length > 1e-9])
        pts = pts[keep]
        seg = np.diff(pts, axis=0)
        self.points = pts
        self.seg_len = np.hypot(seg[:, 0], seg[:, 1])
        self.seg_heading = np.arctan2(seg[:, 1], seg[:, 0])
        self.cum = np.concatenate([[0.0], np.cumsum(self.seg_len)])

    @property
    def length(self) -> float:
        return float(self.cum[-1])

    def pose_at(self, s: ArrayLike) -> tuple[F64, F64, F64]:
        """World (x, y, heading) at arc length ``s`` (any shape); extrapolates past both ends."""
        s = np.asarray(s, dtype=np.float64)
        idx = np.clip(np.searchsorted(self.cum, s, side="right") - 1, 0, len(self.seg_len) - 1)
        frac = (s - self.cum[idx]) / self.seg_len[idx]
        p0 = self.points[idx]
        d = self.points[idx + 1] - p0
        return p0[..., 0] + frac * d[..., 0], p0[..., 1] + frac * d[..., 1], self.seg_heading[idx]

    def project(self, x: float, y: float) -> float:
        """Arc length of the point on the path nearest to (x, y) (used to place stop lines by world position)."""
        p0 = self.points[:-1]
        d = self.points[1:] - p0
        t = np.clip(((x - p0[:, 0]) * d[:, 0] + (y - p0[:, 1]) * d[:, 1]) / self.seg_len**2, 0.0, 1.0)
        px = p0[:, 0] + t * d[:, 0]
        py = p0[:, 1] + t * d[:, 1]
        i = int(np.argmin((px - x) ** 2 + (py - y) ** 2))
        return float(self.cum[i] + t[i] * self.seg_len[i])


def straight(p0: Sequence[float], p1: Sequence[float]) -> Path:
    """A two-point path from ``p0`` to ``p1``."""
    return Path([p0, p1])


def arc_points(cx: float, cy: float, radius: float, a0: float, a1: float, step_m: float = 0.4) -> F64:
    """Points on a circular arc from angle ``a0`` to ``a1`` (radians, either direction), ~``step_m`` apart."""
    n = max(2, int(math.ceil(abs(a1 - a0) * radius / step_m)) + 1)
    a = np.linspace(a0, a1, n)
    return np.stack([cx + radius * np.cos(a), cy + radius * np.sin(a)], axis=1)


def turn_path(start: Sequence[float], corner_in: Sequence[float], arc: F64, end: Sequence[float]) -> Path:
    """Straight from ``start`` to ``corner_in``, along ``arc`` (first point ≈ corner_in), straight to ``end``."""
    return Path(np.vstack([np.asarray([start, corner_in], dtype=np.float64), arc[1:], np.asarray([end], dtype=np.float64)]))
