"""A scenario's content before it is sampled into frames: static objects, lanes of moving agents, the ego,
clutter. :class:`LayoutBuilder` collects them; :meth:`LayoutBuilder.build` runs each lane's traffic simulation
once on a fine time grid, so that sampling any frame later is a cheap interpolation.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from .catalog import CLASSES, CYCLE_LABELS, VEHICLE_LABELS, ObjectClass
from .paths import Path
from .primitives import PrimitiveList, Primitives
from .traffic import LaneAgent, ScriptedStop, SpeedZone, StopLine, simulate_lane

F64 = NDArray[np.float64]

SIM_DT = 0.05
"""Time step of the traffic simulation (s); frames interpolate between its samples."""

STEP_UP_M = 0.3
"""The highest clutter a person stands on rather than is refused by (kerbs 0.1–0.25 m, a lot island's 0.15 m curb);
a wall, a hedge or a planter above it is an obstacle."""

# attribute families: how a dynamic object's nuScenes attribute follows from its speed
FAMILY_VEHICLE = 0
FAMILY_PEDESTRIAN = 1
FAMILY_CYCLE = 2


def family_of(label: int) -> int:
    if label in VEHICLE_LABELS:
        return FAMILY_VEHICLE
    if label in CYCLE_LABELS:
        return FAMILY_CYCLE
    return FAMILY_PEDESTRIAN


def rectangles_overlap(a: F64, b: F64) -> bool:
    """Separating-axis test of two oriented rectangles given as (x, y, half_length, half_width, yaw)."""
    def corners(r: F64) -> F64:
        c, s = math.cos(r[4]), math.sin(r[4])
        lx = np.array([1.0, 1.0, -1.0, -1.0]) * r[2]
        ly = np.array([1.0, -1.0, -1.0, 1.0]) * r[3]
        return np.stack([r[0] + c * lx - s * ly, r[1] + s * lx + c * ly], axis=1)

    ca, cb = corners(a), corners(b)
    for yaw in (a[4], a[4] + math.pi / 2, b[4], b[4] + math.pi / 2):
        axis = np.array([math.cos(yaw), math.sin(yaw)])
        pa, pb = ca @ axis, cb @ axis
        if pa.max() <= pb.min() or pb.max() <= pa.min():
            return False
    return True


@dataclass
class _LaneMember:
    instance_id: int
    cls: ObjectClass
    size: F64
    agent: LaneAgent
    parks_after_s: float | None
    is_ego: bool


@dataclass
class _Lane:
    path: Path
    stop_lines: list[StopLine]
    speed_zones: list[SpeedZone] = field(default_factory=list)
    members: list[_LaneMember] = field(default_factory=list)


@dataclass(frozen=True, eq=False)
class Layout:
    """Everything a :class:`~jitterguard.sim.world.Scenario` samples frames from (arrays, read-only by convention).

    Static objects never move. Dynamic objects are sampled on ``t_grid`` (K,): ``dyn_x`` etc. are (K, Nd);
    ``dyn_yaw`` is unwrapped over time so that linear interpolation never spins through ±π.
    """

    duration_s: float
    static_ids: NDArray[np.int64]
    static_labels: NDArray[np.int64]
    static_sizes: F64
    static_xy: F64
    static_yaw: F64
    static_attributes: tuple[str, ...]
    static_categories: tuple[str, ...]
    static_base: F64  # how high each stands above the road: a person on a kerb, a lot island's curb, a verge
    dyn_ids: NDArray[np.int64]
    dyn_labels: NDArray[np.int64]
    dyn_sizes: F64
    dyn_family: NDArray[np.int64]
    dyn_parks_after: F64  # +inf: never counts as parked when at rest
    dyn_categories: tuple[str, ...]
    t_grid: F64
    dyn_x: F64
    dyn_y: F64
    dyn_yaw: F64
    dyn_vx: F64
    dyn_vy: F64
    ego_x: F64
    ego_y: F64
    ego_yaw: F64
    ego_speed: F64
    clutter: Primitives

    @property
    def num_objects(self) -> int:
        return len(self.static_ids) + len(self.dyn_ids)


class LayoutBuilder:
    """Collects a scenario's content; one instance per scenario generation, seeded by the caller's rng."""

    def __init__(self, rng: np.random.Generator, duration_s: float) -> None:
        self.rng = rng
        self.duration_s = duration_s
        self.clutter = PrimitiveList()
        self._next_id = 1
        self._static: list[tuple[int, ObjectClass, F64, float, float, float, str, float]] = []
        self._lanes: list[_Lane] = []
        self._ego: tuple[_Lane, _LaneMember] | None = None
        self._footprints: list[F64] = []

    def _new_id(self) -> int:
        i = self._next_id
        self._next_id += 1
        return i

    # ------------------------------------------------------------------ static objects
    def add_static(self, cls_key: str, x: float, y: float, yaw: float, attribute: str,
                   size: Sequence[float] | F64 | None = None, clearance: float = 0.05) -> int:
        """A road user that never moves in this scenario (parked car, standing/sitting pedestrian, parked bike).

        Returns its instance id, or -1 (and adds nothing) if its footprint, grown by ``clearance``, would overlap
        an earlier static object or clutter: generators may scatter freely and rely on this to stay physical. A
        person steps onto clutter up to :data:`STEP_UP_M` high (a kerb, a lot island's curb, a raised verge), so that
        is no obstacle to one, and stands on the highest such step under their footprint (``Layout.static_base``:
        their box and their body lifted by it)."""
        cls = CLASSES[cls_key]
        sz = cls.sample_size(self.rng) if size is None else np.asarray(size, dtype=np.float64)
        fp = np.array([x, y, sz[0] / 2 + clearance, sz[1] / 2 + clearance, yaw])
        step_up = STEP_UP_M if family_of(int(cls.label)) == FAMILY_PEDESTRIAN else 0.0
        tops = self.clutter.footprint_tops()
        under = [tops[i] for i in self._overlapping(fp, self.clutter.footprints())]  # the clutter it stands over
        if any(top > step_up for top in under) or self._overlapping(fp, self._footprints):
            return -1
        iid = self._new_id()
        self._static.append((iid, cls, sz, float(x), float(y), float(yaw), attribute, max(under, default=0.0)))
        self._footprints.append(fp)
        return iid

    def _overlapping(self, fp: F64, others: list[F64]) -> list[int]:
        """Indices of the footprints ``others`` (x, y, half_l, half_w, yaw) that ``fp`` overlaps."""
        if not others:
            return []
        o = np.array(others).reshape(-1, 5)
        reach = np.hypot(o[:, 2], o[:, 3]) + math.hypot(fp[2], fp[3])
        near = np.flatnonzero(np.hypot(o[:, 0] - fp[0], o[:, 1] - fp[1]) < reach)
        return [int(i) for i in near if rectangles_overlap(fp, o[i])]

    # ------------------------------------------------------------------ lanes of moving agents
    def add_lane(self, path: Path, stop_lines: Sequence[StopLine] = (), speed_zones: Sequence[SpeedZone] = ()
                 ) -> int:
        """A lane along ``path``; its agents stop at red ``stop_lines`` and slow down in ``speed_zones`` (curves)."""
        self._lanes.append(_Lane(path, list(stop_lines), list(speed_zones)))
        return len(self._lanes) - 1

    def lane_path(self, lane: int) -> Path:
        return self._lanes[lane].path

    def add_agent(self, lane: int, cls_key: str, s0: float, v_desired: float, *,
                  stops: Sequence[ScriptedStop] = (), start_delay_s: float = 0.0,
                  parks_after_s: float | None = None, size: Sequence[float] | F64 | None = None,
                  v0: float | None = None, is_ego: bool = False, idm: dict[str, float] | None = None) -> int:
        """Put a road user on ``lane`` at arc length ``s0``; returns its instance id (0 for the ego).

        ``idm`` overrides :class:`~jitterguard.sim.traffic.LaneAgent`'s IDM parameters (a_max, b_comfort, ...)."""
        cls = CLASSES[cls_key]
        sz = cls.sample_size(self.rng) if size is None else np.asarray(size, dtype=np.float64)
        agent = LaneAgent(s0=s0, v_desired=v_desired, length=float(sz[0]), v0=v0, stops=tuple(stops),
                          start_delay_s=start_delay_s, **(idm or {}))
        iid = 0 if is_ego else self._new_id()
        member = _LaneMember(iid, cls, sz, agent, parks_after_s, is_ego)
        self._lanes[lane].members.append(member)
        if is_ego:
            if self._ego is not None:
                raise ValueError("a scenario has exactly one ego")
            self._ego = (self._lanes[lane], member)
        return iid

    def lane_is_free(self, lane: int, s: float, length: float, margin: float) -> bool:
        """True if no agent on ``lane`` starts within ``margin`` of a box of ``length`` centred at ``s``."""
        return all(abs(m.agent.s0 - s) > (m.agent.length + length) / 2 + margin for m in self._lanes[lane].members)

    # ------------------------------------------------------------------ build
    def build(self) -> Layout:
        if self._ego is None:
            raise ValueError("no ego in the scenario")
        t_grid = np.arange(0.0, self.duration_s + 2 * SIM_DT, SIM_DT)
        dyn: list[tuple[_LaneMember, F64, F64, F64, F64, F64]] = []
        ego_arrays: tuple[F64, F64, F64, F64] | None = None
        for lane in self._lanes:
            members = sorted(lane.members, key=lambda m: -m.agent.s0)
            s, v = simulate_lane([m.agent for m in members], lane.stop_lines, t_grid, lane.speed_zones)
            x, y, h = lane.path.pose_at(s)
            h = np.unwrap(h, axis=0) if len(members) else h
            for j, m in enumerate(members):
                vx, vy = v[:, j] * np.cos(h[:, j]), v[:, j] * np.sin(h[:, j])
                if m.is_ego:
                    ego_arrays = (x[:, j], y[:, j], h[:, j], v[:, j])
                else:
                    dyn.append((m, x[:, j], y[:, j], h[:, j], vx, vy))
        assert ego_arrays is not None
        dyn.sort(key=lambda d: d[0].instance_id)
        k = len(t_grid)

        def stack(i: int) -> F64:
            cols: list[F64] = [d[i] for d in dyn]  # type: ignore[misc]
            return np.stack(cols, axis=1) if dyn else np.zeros((k, 0))

        st = self._static
        return Layout(
            duration_s=self.duration_s,
            static_ids=np.array([r[0] for r in st], dtype=np.int64),
            static_labels=np.array([int(r[1].label) for r in st], dtype=np.int64),
            static_sizes=np.array([r[2] for r in st], dtype=np.float64).reshape(-1, 3),
            static_xy=np.array([(r[3], r[4]) for r in st], dtype=np.float64).reshape(-1, 2),
            static_yaw=np.array([r[5] for r in st], dtype=np.float64),
            static_attributes=tuple(r[6] for r in st),
            static_categories=tuple(r[1].category for r in st),
            static_base=np.array([r[7] for r in st], dtype=np.float64),
            dyn_ids=np.array([d[0].instance_id for d in dyn], dtype=np.int64),
            dyn_labels=np.array([int(d[0].cls.label) for d in dyn], dtype=np.int64),
            dyn_sizes=np.array([d[0].size for d in dyn], dtype=np.float64).reshape(-1, 3),
            dyn_family=np.array([family_of(int(d[0].cls.label)) for d in dyn], dtype=np.int64),
            dyn_parks_after=np.array(
                [np.inf if d[0].parks_after_s is None else d[0].parks_after_s for d in dyn], dtype=np.float64),
            dyn_categories=tuple(d[0].cls.category for d in dyn),
            t_grid=t_grid,
            dyn_x=stack(1), dyn_y=stack(2), dyn_yaw=stack(3), dyn_vx=stack(4), dyn_vy=stack(5),
            ego_x=ego_arrays[0], ego_y=ego_arrays[1], ego_yaw=ego_arrays[2], ego_speed=ego_arrays[3],
            clutter=self.clutter.build(),
        )
