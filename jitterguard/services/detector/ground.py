"""How high the scan's frame sits above the road, and moving a scan to the height the network was trained at.

The network learnt its world from scans whose origin is the LiDAR, 1.84 m above the road (nuScenes' LIDAR_TOP
and the synthetic HDL-32E): a pillar's z features say "road" at −1.84 m and "car roof" near −0.3 m. A sensor
mounted elsewhere, or a cloud published in ``base_link`` (ground at z = 0, as Autoware's concatenated cloud is),
hands it the same world shifted up or down, and what it learnt no longer fits: on the real nuScenes scene-0523
the shipped weights' car AP falls from 0.18 to 0.15 with the scans 0.3 m higher and to 0.003 with them 1.84 m
higher (a ``base_link`` cloud); on synthetic hold-out scans cast from 1.5 m or 2.3 m it loses 0.03
(docs/detector.md, "The sensor's height").

So the detector moves every scan to the trained height before the network (z + h − 1.84, h the frame's
height above the road) and its boxes back after. ``h`` is a deployment's constant when it is known
(``sensor_height_m: 1.95``; ``0`` for a ``base_link`` cloud) or, by default, measured from each scan's own
ground returns (:func:`ground_height`): no calibration to get wrong, and a vehicle that pitches or a frame that
changes between recordings is followed scan by scan. The estimate fits a plane to the lowest return of each
1 m cell within 30 m and reads its height under the sensor; the plane (rather than a level mode of the
heights) keeps a sloped street from biasing it — on synthetic scans with uneven, sloped ground, clutter and
vegetation its error is −0.24…+0.16 m (5–95 %), half that of a level fit. Roll and pitch are not corrected:
the training scans' sensor is level over sloped ground, as a vehicle's base_link axes are.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ...sim.world import SENSOR_HEIGHT_M

TRAINED_SENSOR_HEIGHT_M = SENSOR_HEIGHT_M
"""Height above the road of the frame every shipped network was trained in (the HDL-32E of nuScenes' LIDAR_TOP)."""

CELL_M = 1.0
"""Ground cells: the lowest return of each is a ground candidate (a car fills few cells; its lowest return is
often the road under or beside it)."""
MIN_RETURNS_PER_CELL = 3
"""Fewer returns in a cell say little (a lone mixed pixel or a noise return below the road)."""
RANGE_M = (3.0, 30.0)
"""Horizontal range of the cells: inside 3 m lie the vehicle's own body and roof; beyond 30 m the beams are far
apart and the road is seen through gaps."""
Z_RANGE_M = (-5.0, 1.5)
"""Heights (scan frame) a road can have: a sensor up to 5 m above it, or a base_link cloud (road at 0)."""
NEAR_M = 12.0
"""The first guess is the most common cell height within this range: the road near the vehicle, before the
plane takes the farther cells in."""
BAND_M = 0.2
"""Cells within this distance of the plane are its ground (kerbs are 0.1–0.15 m; a car's underbody 0.2–0.3 m)."""
MIN_CELLS = 20
"""Fewer ground cells than this (a scan of the sky, a wall in front of the sensor): no estimate."""


def ground_cells(points: NDArray[np.floating]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Centre x, y and lowest return z of every :data:`CELL_M` cell of the x-y plane holding at least
    :data:`MIN_RETURNS_PER_CELL` returns within :data:`RANGE_M` and :data:`Z_RANGE_M`. (One pass over a dense grid:
    3 ms for a 124,000-point KITTI scan where sorting the returns by cell took 19 ms.)"""
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    with np.errstate(over="ignore", invalid="ignore"):  # a stray 1e30 return squares to inf: out of range, no warning
        r2 = x * x + y * y
    m = (r2 > RANGE_M[0] ** 2) & (r2 < RANGE_M[1] ** 2) & (z > Z_RANGE_M[0]) & (z < Z_RANGE_M[1])
    half = int(np.ceil(RANGE_M[1] / CELL_M)) + 1
    side = 2 * half + 1
    cell = ((np.floor(x[m] / CELL_M) + half) * side + np.floor(y[m] / CELL_M) + half).astype(np.int64)
    counts = np.bincount(cell, minlength=side * side)
    lowest = np.full(side * side, np.inf)
    np.minimum.at(lowest, cell, z[m])
    seen = np.flatnonzero(counts >= MIN_RETURNS_PER_CELL)
    return (seen // side - half + 0.5) * CELL_M, (seen % side - half + 0.5) * CELL_M, lowest[seen]


def ground_height(points: NDArray[np.floating]) -> float | None:
    """Height of the scan frame's origin above the road under it, m (1.84 for nuScenes' LIDAR_TOP, ≈ 0 for a
    base_link cloud), from the scan's own returns; None when too few ground cells are seen (:data:`MIN_CELLS`).

    The most common lowest-return height of the cells within :data:`NEAR_M` starts a plane, fitted by least
    squares to the cells within :data:`BAND_M` of it, three times; the answer is minus the plane's height at
    x = y = 0."""
    if len(points) == 0:
        return None
    x, y, z = ground_cells(points)
    if len(z) < MIN_CELLS:
        return None
    near = np.hypot(x, y) < NEAR_M
    if near.sum() < MIN_CELLS // 2:
        near = np.ones_like(near)
    counts, edges = np.histogram(z[near], bins=np.arange(Z_RANGE_M[0], Z_RANGE_M[1] + 0.05, 0.05))
    smooth = np.convolve(counts, np.ones(4), "same")  # a 0.2 m window: the road's own roughness
    start = float(edges[int(np.argmax(smooth))] + 0.025)
    design = np.c_[x, y, np.ones_like(x)]
    keep = np.abs(z - start) < 2 * BAND_M
    coef = np.array([0.0, 0.0, start])
    for _ in range(3):
        if keep.sum() < MIN_CELLS // 2:
            break
        coef = np.linalg.lstsq(design[keep], z[keep], rcond=None)[0]
        keep = np.abs(design @ coef - z) < BAND_M
    return -float(coef[2])


def height_shift(points: NDArray[np.floating], sensor_height_m: float | None,
                 fallback_m: float = TRAINED_SENSOR_HEIGHT_M) -> tuple[float, float]:
    """(shift, height): the z to add to ``points`` to bring them to :data:`TRAINED_SENSOR_HEIGHT_M`
    (``height − 1.84``; boxes found in the shifted scan move back by −shift) and the height used —
    ``sensor_height_m`` when given, else :func:`ground_height` of the scan, else ``fallback_m`` (the caller's last
    estimate, or the trained height)."""
    height = sensor_height_m
    if height is None:
        height = ground_height(points)
        if height is None:
            height = fallback_m
    return float(height) - TRAINED_SENSOR_HEIGHT_M, float(height)


def shift_z(points: NDArray[np.float32], dz: float) -> NDArray[np.float32]:
    """``points`` with ``dz`` added to their z (a copy; the same array when ``dz`` is 0)."""
    if dz == 0.0 or len(points) == 0:
        return points
    out = np.array(points, dtype=np.float32, copy=True)
    out[:, 2] += np.float32(dz)
    return out
