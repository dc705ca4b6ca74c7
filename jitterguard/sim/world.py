"""Seeded synthetic scenarios with ground truth: the world the simulator, the detection-level model and the
LiDAR all read.

``make_scenario(name, seed)`` generates a :class:`Scenario` once (traffic simulated on a fine grid); frames are
sampled lazily by interpolation, so iterating a 60 s scenario costs little until a LiDAR scan is cast. The
ground truth speaks nuScenes semantics (attributes ``vehicle.parked`` etc.) because that is what the paper and
the evaluation measure against; labels are Autoware's.

Frames: world frame with the ground at z = 0; the ego pose is the LiDAR's pose (``SENSOR_HEIGHT_M`` above the
ground). Only objects within ``gt_radius_m`` of the sensor are listed in a frame.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from . import catalog as cat
from .layout import FAMILY_CYCLE, FAMILY_PEDESTRIAN, FAMILY_VEHICLE, SIM_DT, Layout
from .primitives import CYLINDER, Primitives
from .scenarios import SCENARIOS
from .visibility import estimate_visibility

SENSOR_HEIGHT_M = 1.84
"""Height of the LiDAR above the ground (nuScenes' LIDAR_TOP is mounted at ≈1.84 m)."""

BASE_STAMP_NS = 1_700_000_000_000_000_000
"""Stamp of frame 0; scenarios start at a fixed epoch so that exports are byte-for-byte reproducible."""

SCENARIO_NAMES: tuple[str, ...] = tuple(SCENARIOS)


WORLD_VERSION = 1
"""Bumped whenever what a seed casts changes — scenario generation, object shapes, the ray caster: caches of cast
scans name it in their recipe (``train``'s and ``eval-detector``'s ``cache-*`` folders), so a folder reused after an
upgrade casts its scans anew instead of scoring or training on the old world. (1: people stand on the kerbs they
step onto, 6 Dec 2026.)"""


@dataclass(frozen=True, eq=False)
class GroundTruthFrame:
    """Ground truth of one frame. Arrays are aligned: row n describes object ``instance_ids[n]``.

    Positions and velocities are in the world frame; ``ego_*`` is the sensor pose. ``num_points`` counts the
    LiDAR returns inside each box where ``points_counted`` says so — a LiDAR scan was cast for this frame, or the
    annotations count them (nuScenes' ``num_lidar_pts``) — and is 0 otherwise; ``visibility`` is the ray-cast
    fraction where a scan was cast, an analytic estimate (or the annotation's visibility level) otherwise.
    ``clutter`` is the static scenery (trees, poles, walls, buildings) the LiDAR also sees; it carries no labels.
    ``unscored``: labelled objects that are no road user (nuScenes' barriers, traffic cones, debris) as (category,
    x, y) in the world frame — never scored, only what a ghost track is told to stand on.
    """

    seq: int
    stamp_ns: int
    ego_x: float
    ego_y: float
    ego_yaw: float
    instance_ids: NDArray[np.int64]
    labels: NDArray[np.int64]
    centers: NDArray[np.float64]
    sizes: NDArray[np.float64]
    yaws: NDArray[np.float64]
    velocities: NDArray[np.float64]
    moving: NDArray[np.bool_]
    attributes: tuple[str, ...]
    visibility: NDArray[np.float64]
    num_points: NDArray[np.int64]
    clutter: Primitives | None = field(default=None, repr=False)
    ego_speed: float = 0.0
    points_counted: bool = False
    unscored: tuple[tuple[str, float, float], ...] = ()

    @property
    def num_objects(self) -> int:
        return len(self.instance_ids)


def frame_count(duration_s: float, rate_hz: float) -> int:
    """Frames of a scenario ``duration_s`` long sampled at ``rate_hz``: whole frames only, with a tolerance for a
    product such as 0.3 · 10 landing just under 3. The one count of the world, the sim CLI's input check and the
    synthetic replay source's probe (a probe that rounded announced frames the source never yielded)."""
    return int(math.floor(duration_s * rate_hz + 1e-9))


class Scenario:
    """A generated scenario: ``num_frames`` frames at ``rate_hz``; ``frame(i)`` samples ground truth at i/rate."""

    def __init__(self, name: str, seed: int, layout: Layout, rate_hz: float, gt_radius_m: float = 80.0) -> None:
        if rate_hz <= 0:
            raise ValueError("rate_hz must be positive")
        self.name = name
        self.seed = seed
        self.rate_hz = float(rate_hz)
        self.duration_s = layout.duration_s
        self.gt_radius_m = float(gt_radius_m)
        self.layout = layout
        self.num_frames = frame_count(layout.duration_s, rate_hz)
        ids = np.concatenate([layout.static_ids, layout.dyn_ids])
        self._order = np.argsort(ids, kind="stable")
        self._n_static = len(layout.static_ids)
        self.categories: dict[int, str] = dict(
            zip(layout.static_ids.tolist(), layout.static_categories)) | dict(
            zip(layout.dyn_ids.tolist(), layout.dyn_categories))
        """nuScenes category name of every instance (``vehicle.car``, ``human.pedestrian.adult``, ...)."""

    def __len__(self) -> int:
        return self.num_frames

    def __iter__(self) -> Iterator[GroundTruthFrame]:
        for i in range(self.num_frames):
            yield self.frame(i)

    def __repr__(self) -> str:
        return (f"Scenario({self.name!r}, seed={self.seed}, frames={self.num_frames} @ {self.rate_hz:g} Hz, "
                f"objects={self.layout.num_objects})")

    def _interp(self, t: float) -> tuple[int, float]:
        k = t / SIM_DT
        k0 = int(min(max(math.floor(k), 0), len(self.layout.t_grid) - 2))
        return k0, float(min(max(k - k0, 0.0), 1.0))

    def frame(self, i: int) -> GroundTruthFrame:
        """Ground truth of frame ``i`` (0 ≤ i < num_frames)."""
        if not 0 <= i < self.num_frames:
            raise IndexError(f"frame {i} out of range [0, {self.num_frames})")
        L = self.layout
        t = i / self.rate_hz
        k0, w = self._interp(t)

        def lerp(a: np.ndarray) -> np.ndarray:
            return a[k0] * (1.0 - w) + a[k0 + 1] * w

        ego_x, ego_y = float(lerp(L.ego_x)), float(lerp(L.ego_y))
        ego_yaw = float(np.angle(np.exp(1j * lerp(L.ego_yaw))))
        ego_speed = float(lerp(L.ego_speed))
        nd = len(L.dyn_ids)
        dx, dy, dyaw = lerp(L.dyn_x), lerp(L.dyn_y), lerp(L.dyn_yaw)
        dvx, dvy = lerp(L.dyn_vx), lerp(L.dyn_vy)
        xy = np.concatenate([L.static_xy, np.stack([dx, dy], axis=1)])[self._order]
        keep = np.hypot(xy[:, 0] - ego_x, xy[:, 1] - ego_y) <= self.gt_radius_m
        rows = self._order[keep]
        is_dyn = rows >= self._n_static
        di = rows[is_dyn] - self._n_static
        si = rows[~is_dyn]
        ids = np.concatenate([L.static_ids, L.dyn_ids])[rows]
        labels = np.concatenate([L.static_labels, L.dyn_labels])[rows]
        sizes = np.concatenate([L.static_sizes, L.dyn_sizes])[rows]
        yaws = np.concatenate([L.static_yaw, np.angle(np.exp(1j * dyaw))])[rows]
        vel = np.concatenate([np.zeros((self._n_static, 2)), np.stack([dvx, dvy], axis=1)])[rows]
        base = np.concatenate([L.static_base, np.zeros(len(L.dyn_ids))])[rows]
        centers = np.column_stack([xy[keep], base + sizes[:, 2] / 2])
        speed = np.hypot(vel[:, 0], vel[:, 1])
        moving = speed > cat.MOVING_SPEED_MPS
        attrs: list[str] = [""] * len(rows)
        static_pos = np.flatnonzero(~is_dyn)
        for p, r in zip(static_pos, si):
            attrs[p] = L.static_attributes[r]
        fam = L.dyn_family[di] if nd else np.zeros(0, np.int64)
        for p, r, f in zip(np.flatnonzero(is_dyn), di, fam):
            mv = bool(moving[p])
            if f == FAMILY_VEHICLE:
                attrs[p] = cat.VEHICLE_MOVING if mv else (
                    cat.VEHICLE_PARKED if t >= L.dyn_parks_after[r] and speed[p] == 0.0 else cat.VEHICLE_STOPPED)
            elif f == FAMILY_PEDESTRIAN:
                attrs[p] = cat.PED_MOVING if mv else cat.PED_STANDING
            else:
                assert f == FAMILY_CYCLE
                attrs[p] = cat.CYCLE_WITH_RIDER
        visibility = self._visibility(centers, sizes, yaws, ego_x, ego_y, ego_yaw)
        return GroundTruthFrame(
            seq=i,
            stamp_ns=BASE_STAMP_NS + int(round(t * 1e9)),
            ego_x=ego_x, ego_y=ego_y, ego_yaw=ego_yaw,
            instance_ids=ids.astype(np.int64),
            labels=labels.astype(np.int64),
            centers=centers,
            sizes=sizes,
            yaws=yaws,
            velocities=vel,
            moving=moving,
            attributes=tuple(attrs),
            visibility=visibility,
            num_points=np.zeros(len(rows), dtype=np.int64),
            clutter=L.clutter,
            ego_speed=ego_speed,
        )

    def _visibility(self, centers: np.ndarray, sizes: np.ndarray, yaws: np.ndarray, ex: float, ey: float,
                    eyaw: float) -> np.ndarray:
        c, s = math.cos(eyaw), math.sin(eyaw)
        rx = c * (centers[:, 0] - ex) + s * (centers[:, 1] - ey)
        ry = -s * (centers[:, 0] - ex) + c * (centers[:, 1] - ey)
        cl = self.layout.clutter
        near = np.hypot(cl.center[:, 0] - ex, cl.center[:, 1] - ey) - cl.footprint_radius() < self.gt_radius_m
        cl = cl.subset(near)
        ox = c * (cl.center[:, 0] - ex) + s * (cl.center[:, 1] - ey)
        oy = -s * (cl.center[:, 0] - ex) + c * (cl.center[:, 1] - ey)
        oyaw = np.where(cl.kind == CYLINDER, 0.0, cl.yaw - eyaw)
        return estimate_visibility(
            rx, ry, sizes[:, 0] / 2, sizes[:, 1] / 2, yaws - eyaw, centers[:, 2] - sizes[:, 2] / 2,
            centers[:, 2] + sizes[:, 2] / 2,
            ox, oy, cl.half[:, 0], cl.half[:, 1], oyaw, cl.z[:, 0], cl.z[:, 1], SENSOR_HEIGHT_M,
        )


def make_scenario(name: str, seed: int, duration_s: float = 20.0, rate_hz: float = 10.0, *,
                  gt_radius_m: float = 80.0) -> Scenario:
    """Generate scenario ``name`` (one of :data:`SCENARIO_NAMES`) deterministically from ``seed``.

    ``duration_s`` is meant for 10–60 s (anything in (0, 600] works); ``rate_hz`` is the frame rate of
    :meth:`Scenario.frame` (the HDL-32E spins at 20 Hz, nuScenes keyframes are 2 Hz)."""
    if name not in SCENARIOS:
        raise ValueError(f"unknown scenario {name!r}; expected one of {', '.join(SCENARIO_NAMES)}")
    if not 0 < duration_s <= 600:
        raise ValueError("duration_s must be in (0, 600]")
    rng = np.random.default_rng(np.random.SeedSequence([seed, _name_key(name)]))
    return Scenario(name, seed, SCENARIOS[name](rng, float(duration_s)), rate_hz, gt_radius_m)


def _name_key(name: str) -> int:
    """A stable integer per scenario name (Python's ``hash`` of a str is salted per process)."""
    return int.from_bytes(name.encode(), "little") % (2**63)
