"""Augmentations of a :class:`Sample` as pure numpy functions: global rotation, scale, mirror flips, range
filtering and ground-truth sampling (pasting boxes with their points from other scans).

Why pure and explicit: each takes a Sample (and, where random, an ``np.random.Generator``) and returns a new
Sample, so a DataLoader worker seeds its own generator and a test can replay any augmentation. Every transform
moves points, box centres, yaws and velocities together, so a point inside a box stays inside it.

Box layout (N, 9): x, y, z, l, w, h, yaw, vx, vy in the sensor frame (see ``config.py``).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from .config import BOX_DIM, Sample

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
B = NDArray[np.bool_]

CENTERPOINT_SAMPLE_COUNTS: tuple[int, ...] = (2, 3, 4, 6, 2)
"""Objects pasted per class (car, truck, bus, bicycle, pedestrian): CenterPoint's nuScenes ``sample_groups``."""


def _wrap(a: NDArray[np.floating]) -> NDArray[np.floating]:
    """Angles into [−π, π)."""
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def global_rotate(sample: Sample, angle: float) -> Sample:
    """Rotate the whole scene by ``angle`` (radians, counter-clockwise) about the sensor's z axis."""
    c, s = math.cos(angle), math.sin(angle)
    pts = sample.points.copy()
    x, y = sample.points[:, 0], sample.points[:, 1]
    pts[:, 0] = c * x - s * y
    pts[:, 1] = s * x + c * y
    b = sample.boxes.astype(np.float64)
    out = b.copy()
    out[:, 0] = c * b[:, 0] - s * b[:, 1]
    out[:, 1] = s * b[:, 0] + c * b[:, 1]
    out[:, 6] = _wrap(b[:, 6] + angle)
    out[:, 7] = c * b[:, 7] - s * b[:, 8]
    out[:, 8] = s * b[:, 7] + c * b[:, 8]
    return replace(sample, points=pts, boxes=out.astype(np.float32))


def global_scale(sample: Sample, factor: float) -> Sample:
    """Scale the scene about the sensor by ``factor``: point coordinates, box centres, sizes and velocities
    (a scaled world moves proportionally faster, as in mmdet3d's GlobalRotScaleTrans)."""
    if factor <= 0:
        raise ValueError("scale factor must be positive")
    pts = sample.points.copy()
    pts[:, :3] *= np.float32(factor)
    b = sample.boxes.copy()
    b[:, :6] *= np.float32(factor)
    b[:, 7:9] *= np.float32(factor)
    return replace(sample, points=pts, boxes=b)


def flip_x(sample: Sample) -> Sample:
    """Mirror across the x axis (y → −y): left becomes right. Yaw → −yaw, vy → −vy. Its own inverse."""
    pts = sample.points.copy()
    pts[:, 1] = -pts[:, 1]
    b = sample.boxes.copy()
    b[:, 1] = -b[:, 1]
    b[:, 6] = _wrap(-b[:, 6].astype(np.float64)).astype(np.float32)
    b[:, 8] = -b[:, 8]
    return replace(sample, points=pts, boxes=b)


def flip_y(sample: Sample) -> Sample:
    """Mirror across the y axis (x → −x): front becomes back. Yaw → π − yaw, vx → −vx. Its own inverse."""
    pts = sample.points.copy()
    pts[:, 0] = -pts[:, 0]
    b = sample.boxes.copy()
    b[:, 0] = -b[:, 0]
    b[:, 6] = _wrap(np.pi - b[:, 6].astype(np.float64)).astype(np.float32)
    b[:, 7] = -b[:, 7]
    return replace(sample, points=pts, boxes=b)


def global_tilt(sample: Sample, pitch: float, roll: float, dz: float = 0.0) -> Sample:
    """Tilt the scene about the sensor (``pitch`` about the y axis, nose down for positive values; ``roll``
    about the x axis; radians) and shift it by ``dz`` metres in z: what a sensor on a vehicle sees when the
    road ahead rises, falls or banks relative to the vehicle, and when the mounting height differs.

    Points and box centres are rotated; boxes stay upright (their yaw is the heading of the rotated forward
    axis, which a few degrees of tilt leave unchanged to first order) and velocities keep their ground-plane
    components rotated with the centres."""
    cp, sp, cr, sr = math.cos(pitch), math.sin(pitch), math.cos(roll), math.sin(roll)
    # R = R_y(pitch) @ R_x(roll)
    rot = np.array([[cp, sp * sr, sp * cr], [0.0, cr, -sr], [-sp, cp * sr, cp * cr]])
    pts = sample.points.copy()
    pts[:, :3] = (sample.points[:, :3].astype(np.float64) @ rot.T + (0.0, 0.0, dz)).astype(np.float32)
    b = sample.boxes.astype(np.float64).copy()
    b[:, :3] = b[:, :3] @ rot.T + (0.0, 0.0, dz)
    v = np.column_stack([b[:, 7], b[:, 8], np.zeros(len(b))]) @ rot.T
    b[:, 7:9] = v[:, :2]
    return replace(sample, points=pts, boxes=b.astype(np.float32))


def random_augment(
    sample: Sample,
    rng: np.random.Generator,
    *,
    rotation: tuple[float, float] = (-math.pi / 4, math.pi / 4),
    scale: tuple[float, float] = (0.95, 1.05),
    flip_x_prob: float = 0.5,
    flip_y_prob: float = 0.5,
) -> Sample:
    """CenterPoint's global augmentation: random mirror flips, then a rotation uniform in ``rotation`` and a
    scale uniform in ``scale``. Draws exactly four numbers from ``rng`` whatever the settings, so a seed gives
    the same later draws however the ranges are configured."""
    u_fx, u_fy, angle, factor = rng.random(), rng.random(), rng.uniform(*rotation), rng.uniform(*scale)
    out = sample
    if u_fx < flip_x_prob:
        out = flip_x(out)
    if u_fy < flip_y_prob:
        out = flip_y(out)
    if rotation[0] != rotation[1] or rotation[0] != 0.0:
        out = global_rotate(out, float(angle))
    if scale[0] != scale[1] or scale[0] != 1.0:
        out = global_scale(out, float(factor))
    return out


@dataclass(frozen=True)
class TrainAugment:
    """The training augmentation as one picklable callable (DataLoader workers get a copy): CenterPoint's
    :func:`random_augment` with rotations uniform in ±``rotation_deg``, then — when ``tilt_deg`` > 0 — a
    :func:`global_tilt` with pitch and roll ~ N(0, ``tilt_deg``) and a height shift ~ N(0, 0.05 m per degree).

    A full ±180° rotation makes the detector indifferent to how its sensor frame is turned (nuScenes' LIDAR_TOP
    has x to the right, KITTI's x forward, synthetic scans x forward)."""

    rotation_deg: float = 45.0
    tilt_deg: float = 0.0
    gt_db: GTDatabase | None = None
    """With a database: CenterPoint's ground-truth sampling first (:func:`gt_sample`, ``gt_counts`` per class) —
    objects pasted where their own scans had them, whatever stands there in this one, so the network must find an
    object from its returns rather than from where a scene's layout puts objects."""
    gt_counts: tuple[int, ...] = CENTERPOINT_SAMPLE_COUNTS

    def __call__(self, sample: Sample, rng: np.random.Generator) -> Sample:
        r = math.radians(self.rotation_deg)
        out = sample if self.gt_db is None else gt_sample(sample, self.gt_db, rng, self.gt_counts)
        out = random_augment(out, rng, rotation=(-r, r))
        if self.tilt_deg > 0:
            t = math.radians(self.tilt_deg)
            out = global_tilt(out, float(rng.normal(0, t)), float(rng.normal(0, t)),
                              float(rng.normal(0, 0.05 * self.tilt_deg)))
        return out


def filter_range(sample: Sample, point_cloud_range: Sequence[float]) -> Sample:
    """Drop points outside the detector's ``(x_min, y_min, z_min, x_max, y_max, z_max)`` and boxes whose
    centre lies outside it in bird's-eye view (as mmdet3d's ObjectRangeFilter: heights are not checked, because
    the grid has a single pillar in z)."""
    x0, y0, z0, x1, y1, z1 = (float(v) for v in point_cloud_range)
    p = sample.points
    keep_p = (p[:, 0] >= x0) & (p[:, 0] < x1) & (p[:, 1] >= y0) & (p[:, 1] < y1) & (p[:, 2] >= z0) & (p[:, 2] < z1)
    b = sample.boxes
    keep_b = (b[:, 0] >= x0) & (b[:, 0] < x1) & (b[:, 1] >= y0) & (b[:, 1] < y1)
    return replace(sample, points=p[keep_p], boxes=b[keep_b], labels=sample.labels[keep_b],
                   num_points=sample.num_points[keep_b])


def drop_empty(sample: Sample, min_points: int = 1) -> Sample:
    """Drop boxes with fewer than ``min_points`` LiDAR returns (nuScenes annotates boxes nothing hit; a detector
    cannot learn them — mmdet3d's ``use_valid_flag``)."""
    keep = sample.num_points >= min_points
    return replace(sample, boxes=sample.boxes[keep], labels=sample.labels[keep], num_points=sample.num_points[keep])


def points_in_boxes(points: NDArray[np.floating], boxes: NDArray[np.floating], margin: float = 0.0) -> B:
    """(P, N) mask: point p lies inside box n (grown by ``margin`` metres on every side)."""
    if len(boxes) == 0 or len(points) == 0:
        return np.zeros((len(points), len(boxes)), bool)
    b = np.asarray(boxes, np.float64)
    d = np.asarray(points, np.float64)[:, None, :3] - b[None, :, :3]
    c, s = np.cos(b[:, 6]), np.sin(b[:, 6])
    lx = c * d[..., 0] + s * d[..., 1]
    ly = -s * d[..., 0] + c * d[..., 1]
    half = b[:, 3:6] / 2 + margin
    return (np.abs(lx) <= half[:, 0]) & (np.abs(ly) <= half[:, 1]) & (np.abs(d[..., 2]) <= half[:, 2])


def _corners_bev(boxes: NDArray[np.floating]) -> F64:
    """(N, 4, 2) BEV corners."""
    b = np.asarray(boxes, np.float64)
    c, s = np.cos(b[:, 6]), np.sin(b[:, 6])
    sl = np.array([0.5, 0.5, -0.5, -0.5])
    sw = np.array([0.5, -0.5, -0.5, 0.5])
    lx = b[:, 3:4] * sl
    ly = b[:, 4:5] * sw
    x = b[:, 0:1] + c[:, None] * lx - s[:, None] * ly
    y = b[:, 1:2] + s[:, None] * lx + c[:, None] * ly
    return np.stack([x, y], axis=-1)


def bev_overlaps(a: NDArray[np.floating], b: NDArray[np.floating]) -> B:
    """(Na, Nb) mask: rotated BEV rectangles of ``a`` and ``b`` intersect (separating-axis test)."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros((len(a), len(b)), bool)
    ca, cb = _corners_bev(a), _corners_bev(b)
    ya, yb = np.asarray(a, np.float64)[:, 6], np.asarray(b, np.float64)[:, 6]
    ax_a = np.stack([np.stack([np.cos(ya), np.sin(ya)], -1), np.stack([-np.sin(ya), np.cos(ya)], -1)], 1)
    ax_b = np.stack([np.stack([np.cos(yb), np.sin(yb)], -1), np.stack([-np.sin(yb), np.cos(yb)], -1)], 1)
    separated = np.zeros((len(a), len(b)), bool)
    # axes of a: (Na, 2, 2); projections of a's corners (Na, 2, 4), of b's corners (Na, Nb, 2, 4)
    pa = np.einsum("nkd,ncd->nkc", ax_a, ca)
    pb = np.einsum("nkd,mcd->nmkc", ax_a, cb)
    separated |= ((pb.min(-1) > pa.max(-1)[:, None]) | (pb.max(-1) < pa.min(-1)[:, None])).any(-1)
    qb = np.einsum("mkd,mcd->mkc", ax_b, cb)
    qa = np.einsum("mkd,ncd->nmkc", ax_b, ca)
    separated |= ((qa.min(-1) > qb.max(-1)[None]) | (qa.max(-1) < qb.min(-1)[None])).any(-1)
    return ~separated


@dataclass(frozen=True)
class GTDatabase:
    """Ground-truth objects cut out of training scans for pasting: boxes (M, 9), classes (M,), point counts
    (M,), and the points of object m at ``points[offsets[m]:offsets[m + 1]]`` (sensor frame of its source scan,
    so a pasted object keeps its range, elevation and point density)."""

    boxes: F32
    labels: I64
    num_points: I64
    points: F32
    offsets: I64

    def __len__(self) -> int:
        return len(self.labels)

    def object_points(self, m: int) -> F32:
        return self.points[self.offsets[m]:self.offsets[m + 1]]


def build_gt_database(samples: Iterable[Sample], min_points: int = 5) -> GTDatabase:
    """Collect every box with at least ``min_points`` points inside it (counted on the scan itself, since a
    stored ``num_points`` may include returns that a range filter later removed)."""
    boxes, labels, counts, chunks = [], [], [], []
    for s in samples:
        if len(s.boxes) == 0:
            continue
        inside = points_in_boxes(s.points, s.boxes)
        n_in = inside.sum(axis=0)
        for k in np.flatnonzero(n_in >= min_points):
            boxes.append(s.boxes[k])
            labels.append(int(s.labels[k]))
            counts.append(int(n_in[k]))
            chunks.append(s.points[inside[:, k]])
    offsets = np.zeros(len(chunks) + 1, np.int64)
    offsets[1:] = np.cumsum([len(c) for c in chunks]) if chunks else []
    return GTDatabase(
        boxes=np.asarray(boxes, np.float32).reshape(-1, BOX_DIM),
        labels=np.asarray(labels, np.int64),
        num_points=np.asarray(counts, np.int64),
        points=np.concatenate(chunks).astype(np.float32) if chunks else np.zeros((0, 4), np.float32),
        offsets=offsets,
    )


def gt_sample(sample: Sample, db: GTDatabase, rng: np.random.Generator,
              counts: Sequence[int] = CENTERPOINT_SAMPLE_COUNTS) -> Sample:
    """Paste up to ``counts[c]`` database objects of each class ``c`` into ``sample`` at their recorded
    positions. A candidate whose BEV footprint overlaps a box already in the scene (or one pasted before it) is
    skipped; the scan's points inside a pasted box are removed so the pasted object is not mixed with what was
    there. Boxes equal to one of the sample's own (the database built from the same scan) overlap it and are
    skipped too."""
    if len(db) == 0:
        return sample
    picks: list[int] = []
    for c, k in enumerate(counts):
        pool = np.flatnonzero(db.labels == c)
        if k <= 0 or len(pool) == 0:
            continue
        picks.extend(rng.choice(pool, size=min(k, len(pool)), replace=False).tolist())
    if not picks:
        return sample
    rng.shuffle(picks)
    cand = db.boxes[picks]
    clash_scene = np.asarray(bev_overlaps(cand, sample.boxes).any(axis=1))
    clash_self = bev_overlaps(cand, cand)
    accepted: list[int] = []
    for i in range(len(picks)):
        if clash_scene[i] or any(clash_self[i, j] for j in accepted):
            continue
        accepted.append(i)
    if not accepted:
        return sample
    new_boxes = cand[accepted]
    idx = [picks[i] for i in accepted]
    covered = points_in_boxes(sample.points, new_boxes).any(axis=1)
    pts = np.concatenate([sample.points[~covered]] + [db.object_points(m) for m in idx]).astype(np.float32)
    return Sample(
        points=pts,
        boxes=np.concatenate([sample.boxes, new_boxes]).astype(np.float32),
        labels=np.concatenate([sample.labels, db.labels[idx]]).astype(np.int64),
        num_points=np.concatenate([sample.num_points, db.num_points[idx]]).astype(np.int64),
        token=sample.token,
    )
