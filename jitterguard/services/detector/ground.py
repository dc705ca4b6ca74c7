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
vegetation its error is −0.24…+0.16 m (5–95 %), half that of a level fit.

The same plane's slope is taken out too (``sensor_tilt: auto``, the default): every return's z becomes its height
above the road plane under it (a shear, z − sₓx − s_y y; x and y, and with them every box's footprint, stay as
they are), so a sensor pitched or rolled against the road — a mount that is not level, a vehicle braking, a
crest — hands the network the level road it learnt on. The network reads absolute heights: on the real
scene-0523 a scan frame pitched by 1° cost the shipped weights a third of their car AP and all their pedestrians,
2° seven tenths of the car AP (docs/detector.md, "The sensor's tilt"). ``sensor_tilt: level`` takes the frame as
level (the detector before 5 Dec 2026).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

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
MAX_TILT_DEG = 10.0
"""A plane steeper than this is not the road under the vehicle (steep streets climb 6°–9°, a mount's tilt is a
degree or two): no estimate."""


@dataclass(frozen=True)
class GroundPlane:
    """The road under a scan, in the scan's frame: z = slope_x·x + slope_y·y − height."""

    height: float
    """Height of the frame's origin above the road under it, m."""
    slope_x: float = 0.0
    """dz/dx of the road (rises ahead when positive: the sensor pitched down against it, or a climb)."""
    slope_y: float = 0.0
    """dz/dy of the road."""

    @property
    def slope_deg(self) -> tuple[float, float]:
        """The slopes as angles, degrees (x, y)."""
        return math.degrees(math.atan(self.slope_x)), math.degrees(math.atan(self.slope_y))


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


def ground_plane(points: NDArray[np.floating]) -> GroundPlane | None:
    """The road plane under the scan from its own returns (height 1.84 m for nuScenes' LIDAR_TOP, ≈ 0 for a
    base_link cloud); None when too few ground cells are seen (:data:`MIN_CELLS`) or the plane is steeper than
    :data:`MAX_TILT_DEG`.

    The most common lowest-return height of the cells within :data:`NEAR_M` starts a plane, fitted by least
    squares to the cells within :data:`BAND_M` of it, three times."""
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
    if math.hypot(coef[0], coef[1]) > math.tan(math.radians(MAX_TILT_DEG)):
        return None
    return GroundPlane(height=-float(coef[2]), slope_x=float(coef[0]), slope_y=float(coef[1]))


def ground_height(points: NDArray[np.floating]) -> float | None:
    """:func:`ground_plane`'s height alone (None where it has none)."""
    plane = ground_plane(points)
    return None if plane is None else plane.height


def scan_ground(points: NDArray[np.floating], sensor_height_m: float | None, tilt: bool,
                last: GroundPlane | None = None) -> GroundPlane:
    """The ground a scan is moved by: its height declared (``sensor_height_m``) or measured, its slope measured
    (``tilt``) or none (a level frame). What a scan too bare to measure cannot give is ``last``'s (the caller's
    previous answer; the trained height and a level road before the first)."""
    plane = ground_plane(points) if sensor_height_m is None or tilt else None
    return ground_of(plane, sensor_height_m, tilt, last)


def ground_of(plane: GroundPlane | None, sensor_height_m: float | None, tilt: bool,
              last: GroundPlane | None = None) -> GroundPlane:
    """:func:`scan_ground` from the scan's measured ``plane`` (None: none found, or none measured)."""
    if last is None:
        last = GroundPlane(TRAINED_SENSOR_HEIGHT_M)
    height = sensor_height_m if sensor_height_m is not None else plane.height if plane is not None else last.height
    if not tilt:
        return GroundPlane(float(height))
    src = plane if plane is not None else last
    return GroundPlane(float(height), src.slope_x, src.slope_y)


WATCH_SCANS = 20
"""Scans in a row that must say the same before :class:`GroundWatch` tells the operator (a bare scan or a ramp now and
then is no fault)."""
WARN_TILT_DEG = 5.0
"""A road plane tilted more than this, scan after scan, is a frame turned against the vehicle, not a road."""


class GroundWatch:
    """What the scans' ground says about their frame, told once a spell: no road plane in :data:`WATCH_SCANS` scans
    in a row (axes other than x forward and z up, a sensor mounted at an angle, nothing but sky or walls: the
    detector then keeps the last height, or the trained 1.84 m, and may see little), or a plane tilted more than
    :data:`WARN_TILT_DEG` (the shear levels the degree or two of a mount or a braking vehicle; a turned frame must be
    published turned back by the mounting rotation). Pure: the service logs what :meth:`observe` returns."""

    def __init__(self, scans: int = WATCH_SCANS, tilt_deg: float = WARN_TILT_DEG) -> None:
        self.scans, self.tilt_deg = scans, tilt_deg
        self._missing = self._tilted = 0
        self._told: str | None = None

    def observe(self, plane: GroundPlane | None) -> str | None:
        """This scan's measured plane (None: none found); a message when a spell has just lasted long enough."""
        if plane is None:
            self._missing, self._tilted = self._missing + 1, 0
        else:
            tilt = math.degrees(math.atan(math.hypot(plane.slope_x, plane.slope_y)))
            self._missing, self._tilted = 0, (self._tilted + 1 if tilt > self.tilt_deg else 0)
        if self._missing == 0 and self._tilted == 0:
            self._told = None  # the ground is a road again: a later spell is told afresh
            return None
        kind = "missing" if self._missing >= self.scans else "tilted" if self._tilted >= self.scans else None
        if kind is None or kind == self._told:
            return None
        self._told = kind
        if kind == "missing":
            return (f"no road plane found under the last {self.scans} scans: the points must be in a frame with x"
                    " forward and z up at the sensor (or in base_link); until a plane is found the detector keeps"
                    " the last height and slope (docs/deployment.md, 'Your sensor's frame')")
        sx, sy = plane.slope_deg if plane is not None else (0.0, 0.0)
        return (f"the road under the last {self.scans} scans is tilted {sx:+.1f}° along x and {sy:+.1f}° along y:"
                f" more than {self.tilt_deg:g}° is a frame turned against the vehicle, which the detector's levelling"
                " only approximates; publish the points turned by the LiDAR's mounting rotation (docs/deployment.md,"
                " 'Your sensor's frame')")


def _unmoved(rows: NDArray[np.floating], ground: GroundPlane) -> bool:
    """Nothing to move: ``ground`` is the trained frame's own road (level, 1.84 m down), or there are no rows."""
    level = ground.slope_x == 0.0 and ground.slope_y == 0.0
    return (level and ground.height == TRAINED_SENSOR_HEIGHT_M) or len(rows) == 0


def _road_rise(rows: NDArray[np.floating], ground: GroundPlane) -> NDArray[np.floating]:
    """How far ``ground``'s plane rises under each row's x, y above its height under the origin."""
    return ground.slope_x * rows[:, 0] + ground.slope_y * rows[:, 1]


def to_trained_frame(points: NDArray[np.float32], ground: GroundPlane) -> NDArray[np.float32]:
    """``points`` as the network was trained to see them: each z made its height above ``ground``'s plane, less
    :data:`TRAINED_SENSOR_HEIGHT_M` (a copy; the same array where there is nothing to move)."""
    if _unmoved(points, ground):
        return points
    out = np.array(points, dtype=np.float32, copy=True)
    z = out[:, 2].astype(np.float64) + (ground.height - TRAINED_SENSOR_HEIGHT_M)
    if ground.slope_x or ground.slope_y:  # (a level plane leaves even a stray infinite x's z alone)
        z -= _road_rise(out, ground)
    out[:, 2] = z
    return out


def boxes_to_trained_frame(boxes: NDArray[np.floating], ground: GroundPlane) -> NDArray[np.floating]:
    """Boxes of the scan's frame (x, y, z first) where :func:`to_trained_frame` puts their points: a training
    sample's labels moved with its scan (a copy; the same array where nothing is moved)."""
    if _unmoved(boxes, ground):
        return boxes
    out = boxes.copy()
    out[:, 2] += (ground.height - TRAINED_SENSOR_HEIGHT_M) - _road_rise(out, ground)
    return out


def boxes_to_scan_frame(boxes: NDArray[np.floating], ground: GroundPlane) -> NDArray[np.floating]:
    """Boxes found in :func:`to_trained_frame`'s points (x, y, z first) back in the scan's frame (a copy; the same
    array where nothing was moved)."""
    if _unmoved(boxes, ground):
        return boxes
    out = boxes.copy()
    out[:, 2] += _road_rise(out, ground) - (ground.height - TRAINED_SENSOR_HEIGHT_M)
    return out
