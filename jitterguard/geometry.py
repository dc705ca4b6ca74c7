"""Planar rigid-body helpers shared by every core: yaw <-> quaternion, sensor -> world transforms.

All functions are pure and vectorised over leading array dimensions. Covariances are rotated as
``R Σ Rᵀ`` — never by copying the diagonal — because a detector's along-beam and across-beam variances differ
and the world axes are not the sensor's once the ego turns.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]


def yaw_from_quaternion(x: float, y: float, z: float, w: float) -> float:
    """Heading (rotation about +z) of a quaternion, in radians."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def yaws_from_quaternions(x: ArrayLike, y: ArrayLike, z: ArrayLike, w: ArrayLike) -> F64:
    """:func:`yaw_from_quaternion` over arrays, bit for bit (``math.atan2`` per element: numpy's ``arctan2``
    can differ in the last bit, and a tracker fed records must compute what it computes from models)."""
    x, y, z, w = (np.asarray(a, dtype=np.float64) for a in (x, y, z, w))
    num, den = 2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z)
    return np.fromiter(map(math.atan2, num.tolist(), den.tolist()), dtype=np.float64, count=num.size)


def quaternion_from_yaw(yaw: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a pure rotation about +z."""
    return (0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0))


def rotate_cov2(cxx: ArrayLike, cxy: ArrayLike, cyy: ArrayLike, yaw: ArrayLike) -> tuple[F64, F64, F64]:
    """Rotate 2x2 covariances [[cxx, cxy], [cxy, cyy]] by ``yaw``: returns the entries of R Σ Rᵀ."""
    cxx = np.asarray(cxx, dtype=np.float64)
    cxy = np.asarray(cxy, dtype=np.float64)
    cyy = np.asarray(cyy, dtype=np.float64)
    c = np.cos(yaw)
    s = np.sin(yaw)
    rxx = c * c * cxx - 2.0 * c * s * cxy + s * s * cyy
    ryy = s * s * cxx + 2.0 * c * s * cxy + c * c * cyy
    rxy = c * s * (cxx - cyy) + (c * c - s * s) * cxy
    return rxx, rxy, ryy


def sensor_to_world_xy(x: ArrayLike, y: ArrayLike, ego_x: float, ego_y: float, ego_yaw: float) -> tuple[F64, F64]:
    """Transform planar points from the sensor frame into the world frame given the ego pose."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    c, s = math.cos(ego_yaw), math.sin(ego_yaw)
    return ego_x + c * x - s * y, ego_y + s * x + c * y


def world_to_sensor_xy(x: ArrayLike, y: ArrayLike, ego_x: float, ego_y: float, ego_yaw: float) -> tuple[F64, F64]:
    """Inverse of :func:`sensor_to_world_xy`."""
    dx = np.asarray(x, dtype=np.float64) - ego_x
    dy = np.asarray(y, dtype=np.float64) - ego_y
    c, s = math.cos(ego_yaw), math.sin(ego_yaw)
    return c * dx + s * dy, -s * dx + c * dy
