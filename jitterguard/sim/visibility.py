"""Approximate visibility of each object from the sensor, without ray casting.

Why approximate: the detection-level model needs an occlusion level for every frame, and casting 35k rays
just for that would make fast tests slow. Each target is sampled at a few azimuths across its angular extent;
at each azimuth every closer occluder (other objects, clutter) casts a vertical shadow — the band between the
rays from the sensor over its bottom and top edges — and the covered fraction of the target's height is taken.
The visibility is one minus the mean covered fraction. Good enough to drive noise and misses; the LiDAR's
ray-cast visibility (points hit vs. points the object would get alone) replaces it when a scan is cast.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]

_SAMPLES = 16


def footprint_corners(cx: F64, cy: F64, half_l: F64, half_w: F64, yaw: F64) -> tuple[F64, F64]:
    """The four footprint corners (N, 4) of oriented rectangles."""
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    lx = np.array([1.0, 1.0, -1.0, -1.0])[None, :] * half_l[:, None]
    ly = np.array([1.0, -1.0, -1.0, 1.0])[None, :] * half_w[:, None]
    return cx[:, None] + c * lx - s * ly, cy[:, None] + s * lx + c * ly


def _angular_extent(px: F64, py: F64) -> tuple[F64, F64, F64, F64]:
    """Per shape (rows of corner points relative to the sensor): centre azimuth, half-span, near and far range."""
    mid = np.arctan2(py.mean(axis=1), px.mean(axis=1))
    rel = np.angle(np.exp(1j * (np.arctan2(py, px) - mid[:, None])))
    lo, hi = rel.min(axis=1), rel.max(axis=1)
    r = np.hypot(px, py)
    return mid + (lo + hi) / 2, (hi - lo) / 2, r.min(axis=1), r.max(axis=1)


def estimate_visibility(
    rel_x: F64, rel_y: F64, half_l: F64, half_w: F64, yaw_rel: F64, z0: F64, z1: F64,
    occ_x: F64, occ_y: F64, occ_half_l: F64, occ_half_w: F64, occ_yaw_rel: F64, occ_z0: F64, occ_z1: F64,
    sensor_z: float,
) -> F64:
    """Visibility in [0, 1] of N targets (sensor-frame footprints, vertical extent z0..z1 in world z).

    The targets also occlude each other; ``occ_*`` are additional occluders (clutter) that are not targets.
    Cylinders can be passed as squares (half_l = half_w = radius)."""
    n = len(rel_x)
    if n == 0:
        return np.zeros(0)
    ax = np.concatenate([rel_x, occ_x])
    ay = np.concatenate([rel_y, occ_y])
    hl = np.concatenate([half_l, occ_half_l])
    hw = np.concatenate([half_w, occ_half_w])
    yw = np.concatenate([yaw_rel, occ_yaw_rel])
    bz0 = np.concatenate([z0, occ_z0])
    bz1 = np.concatenate([z1, occ_z1])
    px, py = footprint_corners(ax, ay, hl, hw, yw)
    centre, half_span, near, _ = _angular_extent(px, py)
    dist = np.hypot(ax, ay)
    m = len(ax)
    d = centre[None, :] - centre[:n, None]
    d = (d + np.pi) % (2 * np.pi) - np.pi  # (N, A) azimuth of each shape relative to each target
    cand = (near[None, :] < dist[:n, None]) & (np.abs(d) < half_span[None, :] + half_span[:n, None])
    cand[np.arange(n), np.arange(n)] = False
    ti, oj = np.nonzero(cand)
    if len(ti) == 0:
        return np.ones(n)
    # shadow band of each occluder projected to the target's distance, as a fraction of the target's height
    scale = dist[ti] / np.maximum(near[oj], 0.5)
    lo = sensor_z + (bz0[oj] - sensor_z) * scale
    hi = sensor_z + (bz1[oj] - sensor_z) * scale
    h = np.maximum(z1[ti] - z0[ti], 1e-3)
    covered = np.clip((np.minimum(hi, z1[ti]) - np.maximum(lo, z0[ti])) / h, 0.0, 1.0)
    samples = np.linspace(-0.95, 0.95, _SAMPLES)[None, :] * half_span[ti, None]  # (P, S)
    inside = np.abs(samples - d[ti, oj][:, None]) <= half_span[oj][:, None]
    shadow = np.zeros((n, _SAMPLES))
    np.maximum.at(shadow, ti, np.where(inside, covered[:, None], 0.0))
    del m
    return 1.0 - shadow.mean(axis=1)
