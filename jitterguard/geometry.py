"""Rigid-body transforms, each written once: yaw <-> quaternion, quaternion algebra, sensor -> world for points,
orientations and covariances.

All array functions are pure and vectorised over leading dimensions. Covariances are rotated as ``R Σ Rᵀ`` — never
by copying the diagonal — because a detector's along-beam and across-beam variances differ and the world axes are
not the sensor's once the ego turns. The tracker core (gating, measurement) and its adapter (what it republishes)
rotate through the same :func:`rotate_cov2`, so both see the same world-frame numbers.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]
Quat = tuple[float, float, float, float]
X_X, X_Y, Y_X, Y_Y = 0, 1, 6, 7  # Autoware's 6x6 covariance indices (row-major over x, y, z, roll, pitch, yaw)


UNIT_QUATERNION_TOL = 1e-9
"""|‖q‖² − 1| up to which a quaternion's heading is read with the unit-quaternion shortcut 1 − 2(y² + z²) (error
≤ ~1e-9 rad, and every well-formed heading stays bit for bit what it was); beyond it, from the rotation's own
entries w² + x² − y² − z²: the wire accepts quaternions 1 % off unit (``max_quaternion_error``), and the shortcut
had turned such a 90° heading into 91.1° — 1 m sideways at 50 m."""


def yaw_from_quaternion(x: float, y: float, z: float, w: float) -> float:
    """Heading (rotation about +z) of a quaternion, in radians; a quaternion need not be of unit length (the
    rotation it stands for is that of q / ‖q‖, and atan2 does not see the common factor)."""
    yy_zz = y * y + z * z
    n2 = w * w + x * x + yy_zz
    den = 1.0 - 2.0 * yy_zz if abs(n2 - 1.0) <= UNIT_QUATERNION_TOL else w * w + x * x - yy_zz
    return math.atan2(2.0 * (w * z + x * y), den)


def yaws_from_quaternions(x: ArrayLike, y: ArrayLike, z: ArrayLike, w: ArrayLike) -> F64:
    """:func:`yaw_from_quaternion` over arrays, bit for bit (``math.atan2`` per element: numpy's ``arctan2``
    can differ in the last bit, and the same detection must give the same heading whatever form it came in)."""
    x, y, z, w = (np.asarray(a, dtype=np.float64) for a in (x, y, z, w))
    yy_zz = y * y + z * z
    n2 = w * w + x * x + yy_zz
    num = 2.0 * (w * z + x * y)
    den = np.where(np.abs(n2 - 1.0) <= UNIT_QUATERNION_TOL, 1.0 - 2.0 * yy_zz, w * w + x * x - yy_zz)
    return np.fromiter(map(math.atan2, num.tolist(), den.tolist()), dtype=np.float64, count=num.size)


def quaternion_from_yaw(yaw: float) -> Quat:
    """(x, y, z, w) of a pure rotation about +z."""
    return (0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0))


def quaternion_multiply(a: Quat, b: Quat) -> Quat:
    """Hamilton product a * b of (x, y, z, w) quaternions: rotate by b first, then by a."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz)


def quaternions_about_z(q: F64, yaw: float) -> F64:
    """``q(yaw) * q`` for each row of ``q`` ((M, 4) x, y, z, w): orientations turned by ``yaw`` about +z."""
    az, aw = math.sin(0.5 * yaw), math.cos(0.5 * yaw)
    return np.column_stack([aw * q[:, 0] - az * q[:, 1], aw * q[:, 1] + az * q[:, 0],
                            aw * q[:, 2] + az * q[:, 3], aw * q[:, 3] - az * q[:, 2]])


def rotation_from_quaternion(x: float, y: float, z: float, w: float) -> F64:
    """3x3 rotation of a (not necessarily unit) quaternion."""
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if n < 1e-12:
        raise ValueError("zero quaternion")
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def quaternion_from_rotation(r: F64) -> Quat:
    """(x, y, z, w) of a 3x3 rotation (projected onto SO(3) first, so slightly noisy matrices are fine)."""
    u, _, vt = np.linalg.svd(np.asarray(r, dtype=np.float64))
    r = u @ vt
    if np.linalg.det(r) < 0:
        raise ValueError("matrix is a reflection, not a rotation")
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        w, x, y, z = 0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2]) * 2
        w, x, y, z = (r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s
    elif r[1, 1] > r[2, 2]:
        s = math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2]) * 2
        w, x, y, z = (r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s
    else:
        s = math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1]) * 2
        w, x, y, z = (r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s
    if w < 0:  # one canonical sign, so equal rotations compare equal
        x, y, z, w = -x, -y, -z, -w
    return float(x), float(y), float(z), float(w)


def rotate_xy(x: ArrayLike, y: ArrayLike, yaw: float) -> tuple[F64, F64]:
    """Planar vectors (velocities, offsets) turned by ``yaw`` about +z."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    c, s = math.cos(yaw), math.sin(yaw)
    return c * x - s * y, s * x + c * y


def sensor_to_world_xy(x: ArrayLike, y: ArrayLike, ego_x: float, ego_y: float, ego_yaw: float) -> tuple[F64, F64]:
    """Planar points from the sensor frame into the world frame given the ego pose."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    c, s = math.cos(ego_yaw), math.sin(ego_yaw)
    return ego_x + c * x - s * y, ego_y + s * x + c * y


def world_to_sensor_xy(x: ArrayLike, y: ArrayLike, ego_x: float, ego_y: float, ego_yaw: float) -> tuple[F64, F64]:
    """Inverse of :func:`sensor_to_world_xy`."""
    dx, dy = np.asarray(x, dtype=np.float64) - ego_x, np.asarray(y, dtype=np.float64) - ego_y
    c, s = math.cos(ego_yaw), math.sin(ego_yaw)
    return c * dx + s * dy, -s * dx + c * dy


def rotate_cov2(cxx: ArrayLike, cxy: ArrayLike, cyy: ArrayLike, yaw: ArrayLike) -> tuple[F64, F64, F64]:
    """Rotate 2x2 covariances [[cxx, cxy], [cxy, cyy]] by ``yaw``: returns the entries of R Σ Rᵀ."""
    cxx, cxy, cyy = (np.asarray(a, dtype=np.float64) for a in (cxx, cxy, cyy))
    c, s = np.cos(yaw), np.sin(yaw)
    rxx = c * c * cxx - 2.0 * c * s * cxy + s * s * cyy
    ryy = s * s * cxx + 2.0 * c * s * cxy + c * c * cyy
    rxy = c * s * (cxx - cyy) + (c * c - s * s) * cxy
    return rxx, rxy, ryy


def scale_beam_covariance(x: ArrayLike, y: ArrayLike, cxx: ArrayLike, cxy: ArrayLike, cyy: ArrayLike,
                          k_along: ArrayLike, k_across: ArrayLike) -> tuple[F64, F64, F64]:
    """Sensor-frame 2x2 covariances of points at sensor-frame (x, y) with the variance along the beam to the point
    multiplied by ``k_along`` and across it by ``k_across`` (the covariance by √(k_along·k_across)): Σ' = D Σ D in
    the beam frame, D = diag(√k_along, √k_across). Scalars or one factor per row."""
    cxx, cxy, cyy = (np.asarray(a, dtype=np.float64) for a in (cxx, cxy, cyy))
    phi = np.arctan2(y, x)
    c, s = np.cos(phi), np.sin(phi)
    # into the beam frame: Σ_b = Rᵀ Σ R
    bll = c * c * cxx + 2 * c * s * cxy + s * s * cyy
    btt = s * s * cxx - 2 * c * s * cxy + c * c * cyy
    blt = -c * s * cxx + (c * c - s * s) * cxy + c * s * cyy
    k_along, k_across = np.asarray(k_along, dtype=np.float64), np.asarray(k_across, dtype=np.float64)
    bll, btt, blt = bll * k_along, btt * k_across, blt * np.sqrt(k_along * k_across)
    return (c * c * bll - 2 * c * s * blt + s * s * btt,
            c * s * (bll - btt) + (c * c - s * s) * blt,
            s * s * bll + 2 * c * s * blt + c * c * btt)


def cov2_largest_variance(cxx: ArrayLike, cxy: ArrayLike, cyy: ArrayLike) -> F64:
    """The larger eigenvalue of each 2×2 covariance: the largest variance it gives along any axis, so the bound on
    every entry after any rotation about z (rotated variances and |covariance| never exceed it)."""
    cxx, cxy, cyy = (np.asarray(v, dtype=np.float64) for v in (cxx, cxy, cyy))
    with np.errstate(invalid="ignore", over="ignore"):
        return 0.5 * (cxx + cyy) + np.hypot(0.5 * (cxx - cyy), cxy)


def rotate_cov6(cov: F64, yaw: float) -> F64:
    """6x6 covariances ``(M, 36)`` (Autoware's layout) with x and y turned by ``yaw`` about +z: the x/y block by
    :func:`rotate_cov2` and the x/y rows and columns against z, roll, pitch, yaw with it (R Σ Rᵀ, R = Rz ⊕ I4)."""
    cov = np.asarray(cov, dtype=np.float64)
    out = cov.copy()
    xx, xy, yy = rotate_cov2(cov[:, X_X], cov[:, X_Y], cov[:, Y_Y], yaw)
    # a singular block (cxy² = cxx·cyy) can rotate to a variance of −1e-18: no variance is negative
    out[:, X_X], out[:, X_Y], out[:, Y_X], out[:, Y_Y] = np.maximum(xx, 0.0), xy, xy, np.maximum(yy, 0.0)
    c, s = math.cos(yaw), math.sin(yaw)
    for k in range(2, 6):
        a, b = cov[:, k], cov[:, 6 + k]  # rows x and y at column k
        out[:, k], out[:, 6 + k] = c * a - s * b, s * a + c * b
        a, b = cov[:, 6 * k], cov[:, 6 * k + 1]  # row k at columns x and y
        out[:, 6 * k], out[:, 6 * k + 1] = c * a - s * b, s * a + c * b
    return out


def _rect_corners(cx: F64, cy: F64, length: F64, width: F64, yaw: F64) -> F64:
    """(N, 4, 2) corners of oriented rectangles, counter-clockwise."""
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    lx = np.array([0.5, -0.5, -0.5, 0.5])[None, :] * length[:, None]
    ly = np.array([0.5, 0.5, -0.5, -0.5])[None, :] * width[:, None]
    return np.stack([cx[:, None] + c * lx - s * ly, cy[:, None] + s * lx + c * ly], axis=-1)


def _inside(p: F64, corners: F64) -> NDArray[np.bool_]:
    """(N, K): whether each of the K points ``p`` (N, K, 2) lies in the counter-clockwise rectangle ``corners``
    (N, 4, 2) of its row (boundary included, with a little slack for rounding)."""
    a = corners[:, :, None, :]  # (N, 4, 1, 2)
    e = np.roll(corners, -1, axis=1)[:, :, None, :] - a
    d = p[:, None, :, :] - a
    cross = e[..., 0] * d[..., 1] - e[..., 1] * d[..., 0]  # (N, 4, K)
    return (cross >= -1e-9).all(axis=1)


def rect_iou(a: tuple[ArrayLike, ...], b: tuple[ArrayLike, ...]) -> F64:
    """Bird's-eye IoU of oriented rectangles, pair by pair: ``a`` and ``b`` are (cx, cy, length, width, yaw),
    each entry an array of N; returns N IoUs in [0, 1] (0 where an area is zero).

    The intersection of two convex quadrilaterals is the convex polygon whose vertices are the corners of each
    inside the other plus the crossings of their edges; its area comes from the shoelace formula with the
    vertices ordered by angle about their mean. Vectorised over pairs with a fixed 24 candidate points per pair
    (invalid ones collapse onto the first valid vertex and add no area), so a frame's overlap check is a few
    array expressions, not a polygon clip per pair in Python.
    """
    A = _rect_corners(*(np.asarray(v, dtype=np.float64) for v in a))
    B = _rect_corners(*(np.asarray(v, dtype=np.float64) for v in b))
    n = A.shape[0]
    if n == 0:
        return np.zeros(0)
    # edge crossings: edge i of A (p + t r) against edge j of B (q + u s)
    p, r = A[:, :, None, :], (np.roll(A, -1, axis=1) - A)[:, :, None, :]
    q, s = B[:, None, :, :], (np.roll(B, -1, axis=1) - B)[:, None, :, :]
    rxs = r[..., 0] * s[..., 1] - r[..., 1] * s[..., 0]
    qp = q - p
    safe = np.where(np.abs(rxs) > 1e-12, rxs, 1.0)
    t = (qp[..., 0] * s[..., 1] - qp[..., 1] * s[..., 0]) / safe
    u = (qp[..., 0] * r[..., 1] - qp[..., 1] * r[..., 0]) / safe
    cross_ok = (np.abs(rxs) > 1e-12) & (t >= 0.0) & (t <= 1.0) & (u >= 0.0) & (u <= 1.0)
    xpts = (p + t[..., None] * r).reshape(n, 16, 2)
    pts = np.concatenate([A, B, xpts], axis=1)  # (N, 24, 2)
    ok = np.concatenate([_inside(A, B), _inside(B, A), cross_ok.reshape(n, 16)], axis=1)
    cnt = ok.sum(axis=1)
    centre = (pts * ok[..., None]).sum(axis=1) / np.maximum(cnt, 1)[:, None]
    ang = np.arctan2(pts[..., 1] - centre[:, None, 1], pts[..., 0] - centre[:, None, 0])
    order = np.argsort(np.where(ok, ang, np.inf), axis=1)
    pts = np.take_along_axis(pts, order[..., None], axis=1)
    ok = np.take_along_axis(ok, order, axis=1)
    pts = np.where(ok[..., None], pts, pts[:, :1, :])
    nxt = np.roll(pts, -1, axis=1)
    inter = 0.5 * np.abs((pts[..., 0] * nxt[..., 1] - pts[..., 1] * nxt[..., 0]).sum(axis=1))
    inter = np.where(cnt >= 3, inter, 0.0)
    area_a = np.asarray(a[2], dtype=np.float64) * np.asarray(a[3], dtype=np.float64)
    area_b = np.asarray(b[2], dtype=np.float64) * np.asarray(b[3], dtype=np.float64)
    union = area_a + area_b - inter
    return np.where(union > 1e-12, np.clip(inter / np.where(union > 1e-12, union, 1.0), 0.0, 1.0), 0.0)


STANDS_ON_M = 1.0
"""A box stands on a labelled object when their bird's-eye centres are closer than this (what a false positive or a
ghost track is told to stand on)."""


def nearest_within(xy: ArrayLike, others: ArrayLike, radius: float = STANDS_ON_M) -> NDArray[np.int64]:
    """For each of the (N, 2) points ``xy``, the index of the nearest of the (M, 2) points ``others`` closer than
    ``radius``, −1 where none is."""
    p = np.asarray(xy, np.float64).reshape(-1, 2)
    o = np.asarray(others, np.float64).reshape(-1, 2)
    out = np.full(len(p), -1, np.int64)
    if len(p) and len(o):
        d = np.hypot(p[:, None, 0] - o[None, :, 0], p[:, None, 1] - o[None, :, 1])
        j = d.argmin(1)
        near = d[np.arange(len(p)), j] < radius
        out[near] = j[near]
    return out
