"""Road users shaped beyond single boxes, as sets of primitives that fit inside their ground-truth box.

Why: a detector trained on boxes-within-boxes learns nothing about wheel gaps, cabins or a cyclist's silhouette;
and occlusion (the paper's jitter source) depends on the silhouette. Each template is a table of parts whose
positions and extents are fractions of the object's (length, width, height), so one template fits every
instance; the part layout picks on label, attribute (a parked bicycle has no rider) and size (a tall "car" is a
van). All parts stay inside the box, so LiDAR returns on an object are the points inside its box.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..schemas.models import Label
from .primitives import BOX, CYLINDER, Primitives, Tag

F64 = NDArray[np.float64]

# part rows: kind, cx, cy (fractions of L, W), z0, z1 (fractions of H), half_l (frac of L, cylinder radius: frac of
# W), half_w (frac of W), reflectivity multiplier
_B, _C = BOX, CYLINDER
TEMPLATES: dict[str, F64] = {
    "car": np.array([
        (_B, 0.00, 0.00, 0.17, 0.58, 0.50, 0.50, 1.0),    # body above the wheel gaps
        (_B, -0.06, 0.00, 0.58, 1.00, 0.27, 0.44, 0.35),  # cabin (glass returns weakly)
        (_B, 0.33, 0.40, 0.00, 0.20, 0.07, 0.10, 0.15),   # wheels
        (_B, 0.33, -0.40, 0.00, 0.20, 0.07, 0.10, 0.15),
        (_B, -0.32, 0.40, 0.00, 0.20, 0.07, 0.10, 0.15),
        (_B, -0.32, -0.40, 0.00, 0.20, 0.07, 0.10, 0.15),
    ]),
    "van": np.array([
        (_B, 0.00, 0.00, 0.14, 0.50, 0.50, 0.50, 1.0),
        (_B, -0.04, 0.00, 0.50, 1.00, 0.44, 0.48, 0.6),
        (_B, 0.34, 0.40, 0.00, 0.16, 0.07, 0.10, 0.15),
        (_B, 0.34, -0.40, 0.00, 0.16, 0.07, 0.10, 0.15),
        (_B, -0.33, 0.40, 0.00, 0.16, 0.07, 0.10, 0.15),
        (_B, -0.33, -0.40, 0.00, 0.16, 0.07, 0.10, 0.15),
    ]),
    "truck": np.array([
        (_B, 0.38, 0.00, 0.16, 0.80, 0.12, 0.50, 1.0),    # cab
        (_B, -0.13, 0.00, 0.25, 1.00, 0.37, 0.50, 0.8),   # cargo box, a gap behind the cab
        (_B, 0.05, 0.00, 0.12, 0.25, 0.45, 0.30, 0.3),    # chassis
        (_B, 0.36, 0.40, 0.00, 0.14, 0.05, 0.10, 0.15),
        (_B, 0.36, -0.40, 0.00, 0.14, 0.05, 0.10, 0.15),
        (_B, -0.30, 0.40, 0.00, 0.14, 0.10, 0.10, 0.15),
        (_B, -0.30, -0.40, 0.00, 0.14, 0.10, 0.10, 0.15),
    ]),
    "pickup": np.array([
        (_B, 0.17, 0.00, 0.20, 0.62, 0.33, 0.50, 1.0),    # hood and lower cab
        (_B, 0.08, 0.00, 0.62, 1.00, 0.12, 0.44, 0.35),   # cab glass
        (_B, -0.33, 0.00, 0.20, 0.34, 0.17, 0.50, 0.8),   # bed floor
        (_B, -0.33, 0.46, 0.34, 0.62, 0.17, 0.04, 0.9),   # bed sides and tailgate: the bed is open above
        (_B, -0.33, -0.46, 0.34, 0.62, 0.17, 0.04, 0.9),
        (_B, -0.48, 0.00, 0.34, 0.62, 0.02, 0.50, 0.9),
        (_B, 0.33, 0.40, 0.00, 0.20, 0.07, 0.10, 0.15),
        (_B, 0.33, -0.40, 0.00, 0.20, 0.07, 0.10, 0.15),
        (_B, -0.31, 0.40, 0.00, 0.20, 0.07, 0.10, 0.15),
        (_B, -0.31, -0.40, 0.00, 0.20, 0.07, 0.10, 0.15),
    ]),
    "semi": np.array([
        (_B, 0.41, 0.00, 0.14, 0.80, 0.09, 0.48, 1.0),    # tractor cab
        (_B, -0.09, 0.00, 0.32, 1.00, 0.41, 0.50, 0.8),   # semitrailer box, open underneath
        (_B, 0.22, 0.00, 0.12, 0.30, 0.10, 0.30, 0.3),    # tractor chassis under the trailer's front
        (_B, 0.43, 0.40, 0.00, 0.14, 0.035, 0.10, 0.15),  # steer axle
        (_B, 0.43, -0.40, 0.00, 0.14, 0.035, 0.10, 0.15),
        (_B, 0.24, 0.40, 0.00, 0.14, 0.06, 0.10, 0.15),   # drive axles
        (_B, 0.24, -0.40, 0.00, 0.14, 0.06, 0.10, 0.15),
        (_B, -0.41, 0.40, 0.00, 0.14, 0.06, 0.10, 0.15),  # trailer tandem
        (_B, -0.41, -0.40, 0.00, 0.14, 0.06, 0.10, 0.15),
        (_C, 0.12, 0.35, 0.00, 0.32, 0.04, 0.04, 0.4),    # landing gear
        (_C, 0.12, -0.35, 0.00, 0.32, 0.04, 0.04, 0.4),
    ]),
    "bus": np.array([
        (_B, 0.00, 0.00, 0.10, 1.00, 0.50, 0.50, 0.9),
        (_B, 0.30, 0.42, 0.00, 0.10, 0.05, 0.08, 0.15),
        (_B, 0.30, -0.42, 0.00, 0.10, 0.05, 0.08, 0.15),
        (_B, -0.25, 0.42, 0.00, 0.10, 0.05, 0.08, 0.15),
        (_B, -0.25, -0.42, 0.00, 0.10, 0.05, 0.08, 0.15),
    ]),
    "trailer": np.array([
        (_B, 0.00, 0.00, 0.30, 1.00, 0.50, 0.50, 0.8),
        (_B, -0.30, 0.40, 0.00, 0.30, 0.12, 0.10, 0.15),
        (_B, -0.30, -0.40, 0.00, 0.30, 0.12, 0.10, 0.15),
        (_C, 0.40, 0.00, 0.00, 0.30, 0.05, 0.05, 0.4),    # landing leg
    ]),
    "motorcycle_rider": np.array([
        (_B, 0.00, 0.00, 0.18, 0.48, 0.42, 0.40, 0.8),
        (_B, 0.38, 0.00, 0.00, 0.42, 0.11, 0.12, 0.15),
        (_B, -0.38, 0.00, 0.00, 0.42, 0.11, 0.15, 0.15),
        (_C, -0.08, 0.00, 0.45, 0.86, 0.28, 0.28, 0.5),   # rider
        (_C, -0.04, 0.00, 0.86, 1.00, 0.17, 0.17, 0.6),   # helmet
    ]),
    "motorcycle": np.array([
        (_B, 0.00, 0.00, 0.20, 0.62, 0.42, 0.45, 0.8),
        (_B, 0.38, 0.00, 0.00, 0.55, 0.11, 0.12, 0.15),
        (_B, -0.38, 0.00, 0.00, 0.55, 0.11, 0.15, 0.15),
    ]),
    "bicycle_rider": np.array([
        (_B, 0.30, 0.00, 0.00, 0.40, 0.18, 0.06, 0.3),    # wheels
        (_B, -0.30, 0.00, 0.00, 0.40, 0.18, 0.06, 0.3),
        (_B, 0.00, 0.00, 0.26, 0.50, 0.25, 0.08, 0.5),    # frame
        (_B, 0.22, 0.00, 0.52, 0.60, 0.04, 0.45, 0.5),    # handlebar
        (_C, 0.00, 0.15, 0.20, 0.52, 0.13, 0.13, 0.4),    # legs
        (_C, 0.00, -0.15, 0.20, 0.52, 0.13, 0.13, 0.4),
        (_C, -0.05, 0.00, 0.52, 0.86, 0.32, 0.32, 0.5),   # torso
        (_C, 0.00, 0.00, 0.86, 1.00, 0.19, 0.19, 0.6),    # head
    ]),
    "bicycle": np.array([
        (_B, 0.30, 0.00, 0.00, 0.62, 0.18, 0.08, 0.3),
        (_B, -0.30, 0.00, 0.00, 0.62, 0.18, 0.08, 0.3),
        (_B, 0.00, 0.00, 0.40, 0.80, 0.25, 0.10, 0.5),
        (_B, 0.22, 0.00, 0.85, 1.00, 0.04, 0.48, 0.5),
    ]),
    "pedestrian": np.array([
        (_C, 0.00, 0.17, 0.00, 0.47, 0.14, 0.14, 0.4),    # legs
        (_C, 0.00, -0.17, 0.00, 0.47, 0.14, 0.14, 0.4),
        (_B, 0.00, 0.00, 0.47, 0.84, 0.24, 0.46, 0.6),    # torso and arms
        (_C, 0.00, 0.00, 0.86, 1.00, 0.15, 0.15, 0.5),    # head
    ]),
    "walker": np.array([
        (_C, 0.00, 0.14, 0.00, 0.26, 0.10, 0.10, 0.4),    # shins (legs in two parts: a stride tilts them)
        (_C, 0.00, -0.14, 0.00, 0.26, 0.10, 0.10, 0.4),
        (_C, 0.00, 0.14, 0.26, 0.48, 0.13, 0.13, 0.4),    # thighs
        (_C, 0.00, -0.14, 0.26, 0.48, 0.13, 0.13, 0.4),
        (_B, 0.00, 0.00, 0.48, 0.83, 0.20, 0.28, 0.6),    # torso, arms free beside it
        (_C, 0.00, 0.38, 0.50, 0.82, 0.08, 0.08, 0.5),    # arms
        (_C, 0.00, -0.38, 0.50, 0.82, 0.08, 0.08, 0.5),
        (_C, 0.00, 0.00, 0.86, 1.00, 0.15, 0.15, 0.5),    # head
    ]),
    "sitting": np.array([
        (_B, 0.15, 0.00, 0.28, 0.42, 0.35, 0.40, 0.5),    # thighs
        (_B, 0.40, 0.00, 0.00, 0.30, 0.08, 0.35, 0.4),    # shins
        (_B, -0.18, 0.00, 0.42, 0.82, 0.18, 0.45, 0.6),   # torso
        (_C, -0.15, 0.00, 0.83, 1.00, 0.16, 0.16, 0.5),   # head
    ]),
    "box": np.array([(_B, 0.0, 0.0, 0.0, 1.0, 0.5, 0.5, 1.0)]),
}


TEMPLATES["pedaller"] = np.concatenate([
    TEMPLATES["bicycle_rider"][:4],                       # wheels, frame and handlebar as "bicycle_rider"
    np.array([
        (_C, 0.05, 0.15, 0.08, 0.32, 0.11, 0.11, 0.4),    # shins (legs in two parts: the cranks move them)
        (_C, 0.05, -0.15, 0.08, 0.32, 0.11, 0.11, 0.4),
        (_C, 0.00, 0.15, 0.32, 0.52, 0.13, 0.13, 0.4),    # thighs
        (_C, 0.00, -0.15, 0.32, 0.52, 0.13, 0.13, 0.4),
    ]),
    TEMPLATES["bicycle_rider"][6:],                       # torso and head as "bicycle_rider"
])


GAIT: dict[str, F64] = {"walker": np.array([0.30, -0.30, 0.15, -0.15, 0.0, -0.20, 0.20, 0.0])}
"""Per template row, how far (a fraction of the object's length) the part moves forward at the peak of a
stride: feet furthest, knees half as far, each arm against the leg on its side; see :func:`gait_stride`."""

GAIT_CYCLE_HZ = 0.9
"""Strides per second of a walker (a cadence of ≈ 1.8 steps/s, as adults walk at 1.2–1.5 m/s)."""

GAIT_FULL_STRIDE_MPS = 1.3
"""Speed at and above which a walker's stride is full (slower walkers take proportionally shorter steps)."""


PEDAL: dict[str, F64] = {"pedaller": np.array([
    (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0),
    (0.10, 0.07, 0.0), (0.10, 0.07, np.pi),    # shins: round with the pedals, the two feet half a turn apart
    (0.03, 0.05, 0.0), (0.03, 0.05, np.pi),    # thighs: the knees rise and fall
    (0.0, 0.0, 0.0), (0.0, 0.0, 0.0),
])}
"""Per template row of a cyclist: how far the part moves along the heading (a fraction of the object's length)
and up (of its height) as the cranks turn, and its phase on the crank: a part at crank angle θ sits
``(ax · L · cos(θ + φ), az · H · sin(θ + φ))`` from its rest place (see :func:`crank_angle`)."""

PEDAL_HZ = 1.3
"""Crank turns per second of a riding cyclist (≈ 80 rpm, an easy cadence; gears keep it near constant)."""

PEDAL_MIN_MPS = 0.5
"""Speed below which a cyclist is taken to coast or stand: the cranks stay at the angle the instance was given."""


def instance_fraction(instance_ids: NDArray[np.int64]) -> F64:
    """A number in [0, 1) per instance id, stable over time and spread over ids (a multiplicative hash): what an
    instance keeps from scan to scan — its paint, its gait's phase."""
    return (np.asarray(instance_ids, np.int64) * 2654435761 % 1000) / 1000.0


def _ground_speed(velocities: F64) -> F64:
    """|v| of each (vx, vy) row (empty for no objects)."""
    return np.hypot(velocities[:, 0], velocities[:, 1]) if len(velocities) else np.zeros(0)


def gait_stride(stamp_s: float, velocities: F64, instance_ids: NDArray[np.int64]) -> F64:
    """The signed stride of each object at ``stamp_s``, in [−1, 1]: 0 for one standing still, a full swing for one
    walking at :data:`GAIT_FULL_STRIDE_MPS` or faster. Each instance has its own phase (a hash of its id), so a
    crowd does not march in step, and the phase advances with time, so consecutive scans catch other poses."""
    speed = _ground_speed(velocities)
    phase = instance_fraction(instance_ids)
    return np.clip(speed / GAIT_FULL_STRIDE_MPS, 0.0, 1.0) * np.sin(2 * np.pi * (GAIT_CYCLE_HZ * stamp_s + phase))


def crank_angle(stamp_s: float, velocities: F64, instance_ids: NDArray[np.int64]) -> F64:
    """The crank angle [rad] of each object at ``stamp_s``: turning at :data:`PEDAL_HZ` while it rides at
    :data:`PEDAL_MIN_MPS` or faster, still otherwise; each instance starts at its own angle (the hash of
    :func:`instance_fraction`), so a group of riders does not pedal in step."""
    speed = _ground_speed(velocities)
    turns = instance_fraction(instance_ids) + np.where(speed >= PEDAL_MIN_MPS, PEDAL_HZ * stamp_s, 0.0)
    return 2 * np.pi * turns


GLASS_PARTS: dict[str, tuple[int, ...]] = {"car": (1,), "van": (1,), "pickup": (1,)}
"""Template rows that are mostly glass (a car's cabin): tagged :attr:`Tag.GLASS` so that the LiDAR's effects
can let rays through them (real cabins return little: nuScenes cars carry 22 % of their returns in the upper
40 % of the box, ideal ray-cast ones 47 %)."""


def template_key(label: int, attribute: str, size: F64, limbs: bool = False, pedal: bool = False) -> str:
    """Which part layout an object gets (``limbs``: a standing or walking pedestrian gets the articulated
    ``walker``, else the one-piece torso of the scans cast before it existed; ``pedal``: a bicycle's rider gets
    two-part legs on the pedals, ``pedaller``)."""
    if label == Label.CAR:
        return "van" if size[2] > 2.0 else "car"
    if label == Label.TRUCK:  # the size tells a pick-up and a tractor-semitrailer from a rigid truck
        return "semi" if size[0] > 11.0 else "pickup" if size[2] < 2.2 else "truck"
    if label == Label.BUS:
        return "bus"
    if label == Label.TRAILER:
        return "trailer"
    if label == Label.MOTORCYCLE:
        return "motorcycle" if attribute == "cycle.without_rider" else "motorcycle_rider"
    if label == Label.BICYCLE:
        if attribute == "cycle.without_rider":
            return "bicycle"
        return "pedaller" if pedal else "bicycle_rider"
    if label == Label.PEDESTRIAN:
        if attribute == "pedestrian.sitting_lying_down":
            return "sitting"
        return "walker" if limbs else "pedestrian"
    return "box"


def _part_tags(key: str, m: int) -> NDArray[np.int16]:
    tags = np.full(m, int(Tag.OBJECT), np.int16)
    tags[list(GLASS_PARTS.get(key, ()))] = int(Tag.GLASS)
    return tags


def object_primitives(centers: F64, sizes: F64, yaws: F64, labels: NDArray[np.int64], attributes: tuple[str, ...],
                      instance_ids: NDArray[np.int64], stride: F64 | None = None, crank: F64 | None = None
                      ) -> tuple[Primitives, NDArray[np.int64]]:
    """All parts of N objects in the world frame, and the object row each part belongs to.

    ``stride`` (N,), from :func:`gait_stride`: pedestrians get limbs, swung by it along their heading (see
    :data:`GAIT`); None keeps every template as scans were cast before limbs existed. ``crank`` (N,), from
    :func:`crank_angle`: bicycle riders' legs go round with the pedals (see :data:`PEDAL`); None keeps them as
    scans were cast before."""
    keys = [template_key(int(lab), attr, sz, stride is not None, crank is not None)
            for lab, attr, sz in zip(labels, attributes, sizes)]
    parts: list[Primitives] = []
    owners: list[NDArray[np.int64]] = []
    for key in dict.fromkeys(keys):
        rows = np.flatnonzero(np.array([k == key for k in keys]))
        t = TEMPLATES[key]
        n, m = len(rows), len(t)
        L, W, H = (sizes[rows, i][:, None] for i in range(3))
        kind = np.broadcast_to(t[:, 0].astype(np.int8), (n, m))
        lx, ly = t[:, 1] * L, t[:, 2] * W
        base = centers[rows, 2][:, None] - H / 2  # what it stands on: the road, or a kerb a person stepped onto
        z0, z1 = base + t[:, 3] * H, base + t[:, 4] * H
        if key in GAIT and stride is not None:
            lx = lx + GAIT[key][None, :] * stride[rows][:, None] * L
        if key in PEDAL and crank is not None:
            ax, az, offset = PEDAL[key].T
            angle = crank[rows][:, None] + offset[None, :]
            lx = lx + ax[None, :] * np.cos(angle) * L
            lift = az[None, :] * np.sin(angle) * H
            z0, z1 = z0 + lift, z1 + lift
        c, s = np.cos(yaws[rows])[:, None], np.sin(yaws[rows])[:, None]
        cx = centers[rows, 0][:, None] + c * lx - s * ly
        cy = centers[rows, 1][:, None] + s * lx + c * ly
        is_cyl = t[:, 0] == CYLINDER
        hl = np.where(is_cyl, t[:, 5] * W, t[:, 5] * L)
        hw = t[:, 6] * W
        # a per-instance paint colour: reflectivity 0.2 … 0.8, stable over time
        paint = 0.2 + 0.6 * instance_fraction(instance_ids[rows])
        refl = np.clip(paint[:, None] * t[:, 7], 0.02, 1.0)
        parts.append(Primitives(
            kind.reshape(-1).copy(), np.stack([cx, cy], axis=-1).reshape(-1, 2),
            np.stack([z0, z1], axis=-1).reshape(-1, 2), np.stack([hl, hw], axis=-1).reshape(-1, 2),
            np.broadcast_to(yaws[rows][:, None], (n, m)).reshape(-1).copy(), refl.reshape(-1),
            np.tile(_part_tags(key, m), n)))
        owners.append(np.repeat(rows, m))
    if not parts:
        return Primitives.empty(), np.zeros(0, np.int64)
    return Primitives.concat(parts), np.concatenate(owners).astype(np.int64)
