"""The named scenario generators. Each turns (rng, duration) into a :class:`~jitterguard.sim.layout.Layout`.

Conventions: world frame x east, y north, ground at z = 0, right-hand traffic, lanes 3.5 m wide. Every random
choice comes from the one ``rng`` passed in, so a (name, seed, duration) triple always yields the same world.
Extents scale with the duration so that a 60 s drive still passes parked cars and meets traffic to the end.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from . import catalog as cat
from .layout import Layout, LayoutBuilder
from .paths import Path, arc_points, straight, turn_path
from .primitives import Tag
from .traffic import ScriptedStop, SpeedZone, StopLine

SIDEWALK_WIDTH = 3.5
WALK_OFFSETS = (1.1, 2.0)  # walker lanes, metres from the curb: with / against the x axis
CURB_STRIP = 0.35  # trees, poles and parked bicycles stand this far from the curb

_PED_IDM = dict(a_max=0.8, b_comfort=1.2, headway_s=0.8, min_gap=0.6)
_CYCLE_IDM = dict(a_max=1.0, b_comfort=1.5, headway_s=1.0, min_gap=1.2)
_HEAVY_IDM = dict(a_max=0.9, b_comfort=1.6, headway_s=1.6, min_gap=2.5)


def _pick(rng: np.random.Generator, table: dict[str, float]) -> str:
    keys = list(table)
    p = np.asarray([table[k] for k in keys], dtype=np.float64)
    return keys[int(rng.choice(len(keys), p=p / p.sum()))]


HEAVY_KEYS = ("truck", "bus", "trailer", "semi", "long_trailer")
"""Catalogue keys that drive like heavy vehicles: slower starts, longer headways, 0.8 × the lane's speed."""


def _idm_for(cls_key: str) -> dict[str, float]:
    if cls_key in HEAVY_KEYS:
        return dict(_HEAVY_IDM)
    if cls_key in ("bicycle",):
        return dict(_CYCLE_IDM)
    if cls_key in ("pedestrian", "child"):
        return dict(_PED_IDM)
    return {}


# --------------------------------------------------------------------------------------------- building blocks


def _fill_lane(b: LayoutBuilder, lane: int, s_from: float, s_to: float, gap: tuple[float, float],
               speed: tuple[float, float], mix: dict[str, float], *, stops_every: tuple[float, float] | None = None,
               p_stopper: float = 0.0, skip: Callable[[float], bool] | None = None,
               stop_ok: Callable[[float], bool] | None = None) -> None:
    """Spread agents over [s_from, s_to] on ``lane`` with random gaps; a fraction makes scripted stops."""
    rng = b.rng
    s = s_to - rng.uniform(0, gap[1])
    while s > s_from:
        key = _pick(rng, mix)
        v = rng.uniform(*speed) * (0.8 if key in HEAVY_KEYS else 1.0)
        stops: list[ScriptedStop] = []
        if stops_every and rng.random() < p_stopper:
            pos = s + rng.uniform(*stops_every) * 0.5
            while pos < s + v * b.duration_s + 50:
                if stop_ok is None or stop_ok(pos):
                    stops.append(ScriptedStop(pos, float(rng.uniform(3.0, 9.0))))
                pos += rng.uniform(*stops_every)
        if (skip is None or not skip(s)) and b.lane_is_free(lane, s, 12.0, 2.0):
            b.add_agent(lane, key, s, v, stops=stops, idm=_idm_for(key))
        s -= rng.uniform(*gap)


_KERBSIDE_MIX = {"car": 0.82, "van": 0.1, "truck": 0.05, "motorcycle": 0.03}


def _parallel_parking(b: LayoutBuilder, x0: float, x1: float, y: float, heading: float,
                      keep_clear: Sequence[tuple[float, float]] = (), p_gap: float = 0.12, along_x: bool = True,
                      mix: dict[str, float] | None = None) -> None:
    """Parallel-parked vehicles along y = ``y`` between x0 and x1, bumper gaps 0.6–2.5 m, some empty spots
    (``along_x=False``: along the line x = ``y`` between y = x0 and x1)."""
    rng = b.rng
    x = x0 + rng.uniform(0, 4)
    while x < x1:
        if rng.random() < p_gap:
            x += rng.uniform(5.0, 14.0)
            continue
        key = _pick(rng, mix or _KERBSIDE_MIX)
        size = cat.CLASSES[key].sample_size(rng)
        cx = x + size[0] / 2
        if cx + size[0] / 2 > x1:
            break
        if not any(a - size[0] / 2 < cx < c + size[0] / 2 for a, c in keep_clear):
            yy = y + float(np.clip(rng.normal(0, 0.1), -0.2, 0.2)) * (0.3 if cat.CLASSES[key].label == cat.Label.TRUCK
                                                                     else 1.0)
            px, py = (cx, yy) if along_x else (yy, cx)
            b.add_static(key, px, py, heading + float(rng.normal(0, 0.02)), cat.VEHICLE_PARKED if key != "motorcycle"
                         else cat.CYCLE_WITHOUT_RIDER, size=size)
        x += size[0] + rng.uniform(0.6, 2.5)


def _diagonal_row(b: LayoutBuilder, x0: float, x1: float, y_edge: float, side: int, heading: float,
                  pitch: float, occupancy: float, mix: dict[str, float] | None = None) -> list[tuple[float, float]]:
    """Angled stalls along an aisle edge at y = ``y_edge``; cars extend away from the aisle (``side`` ±1).

    Returns the centres of the empty stalls (for a car arriving later). Angled cars overlap in their projection
    on the aisle, so each hides part of its neighbour from a passing sensor (the paper's Fig. 4a)."""
    rng = b.rng
    empty: list[tuple[float, float]] = []
    x = x0 + rng.uniform(0, pitch)
    c, s = abs(math.cos(heading)), abs(math.sin(heading))
    while x < x1:
        key = _pick(rng, mix or {"car": 0.85, "van": 0.12, "truck": 0.03})
        size = cat.CLASSES[key].sample_size(rng)
        depth_half = size[0] / 2 * s + size[1] / 2 * c
        y = y_edge + side * (depth_half + rng.uniform(0.1, 0.4))
        if rng.random() > occupancy or b.add_static(
                key, x, y, heading + float(rng.normal(0, 0.015)), cat.VEHICLE_PARKED, size=size) < 0:
            empty.append((x, y_edge + side * (2.4 * s + 1.0 * c + 0.25)))
        x += pitch
    return empty


def _screen(b: LayoutBuilder, x0: float, x1: float, y_kerb: float, y_front: float, side: int) -> None:
    """What stands between a road and the row of stalls beyond it: a raised verge from the kerb at ``y_kerb`` to
    ``y_front`` (0.1–0.25 m high), street trees on it 0.5–0.9 m from the kerb every 5–14 m (the walk behind them
    is the caller's), and along the stalls' fronts a low wall (0.25 m thick) or a hedge (0.4–0.9 m deep), 0.7–1.5 m
    tall, in lengths with gaps — the sensor sees little of the cars behind it but their upper halves under the
    crowns (why: docs/detector.md, "A row of nose-in cars"). A simplification: road users stand on the road's
    level, so the feet of people on the verge are inside its raised slab (their boxes 0.1–0.25 m too low there)."""
    rng = b.rng
    width = abs(y_front - y_kerb)
    mid = (y_kerb + y_front) / 2
    b.clutter.box((x0 + x1) / 2, mid, x1 - x0, width, 0.0, rng.uniform(0.1, 0.25), reflectivity=0.3, tag=Tag.WALL)
    x = x0 + rng.uniform(0.0, 8.0)
    while x < x1:
        _tree(b, x, y_kerb + side * rng.uniform(0.5, 0.9))
        x += rng.uniform(5.0, 14.0)
    hedge = rng.random() < 0.5
    tag, deep = (Tag.HEDGE, rng.uniform(0.4, 0.9)) if hedge else (Tag.WALL, 0.25)
    height = rng.uniform(0.7, 1.5)
    x = x0
    while x < x1:
        length = rng.uniform(10.0, 40.0)
        b.clutter.box(x + length / 2, y_front - side * (deep / 2 + 0.1), length, deep, 0.0, height,
                      reflectivity=0.15 if hedge else 0.25, tag=tag)
        x += length + (rng.uniform(1.0, 4.0) if rng.random() < 0.4 else 0.0)


def _tree(b: LayoutBuilder, x: float, y: float) -> None:
    rng = b.rng
    trunk_top = rng.uniform(2.0, 3.0)
    b.clutter.cylinder(x, y, rng.uniform(0.12, 0.2), 0.0, trunk_top + 0.5, reflectivity=0.25, tag=Tag.TREE_TRUNK)
    r = rng.uniform(1.4, 2.6)
    b.clutter.cylinder(x, y, r, trunk_top, trunk_top + rng.uniform(2.5, 5.0), reflectivity=0.12, tag=Tag.TREE_CROWN)


def _lamp_pole(b: LayoutBuilder, x: float, y: float, arm_dir: float) -> None:
    h = b.rng.uniform(6.0, 8.0)
    b.clutter.cylinder(x, y, 0.1, 0.0, h, reflectivity=0.5, tag=Tag.POLE)
    b.clutter.box(x + math.cos(arm_dir) * 0.9, y + math.sin(arm_dir) * 0.9, 1.8, 0.15, h - 0.25, h, yaw=arm_dir,
                  reflectivity=0.5, tag=Tag.POLE)


def _sign(b: LayoutBuilder, x: float, y: float, facing: float) -> None:
    b.clutter.cylinder(x, y, 0.04, 0.0, 2.6, reflectivity=0.5, tag=Tag.POLE)
    b.clutter.box(x, y, 0.05, 0.7, 2.0, 2.7, yaw=facing, reflectivity=0.95, tag=Tag.SIGN)


def _curb_furniture(b: LayoutBuilder, x0: float, x1: float, y: float, along_x: bool = True,
                    keep_clear: Sequence[tuple[float, float]] = ()) -> None:
    """Trees, lamp poles and signs on the curb strip (line ``y`` if along x, else line x = ``y``)."""
    rng = b.rng
    x = x0 + rng.uniform(0, 6)
    arm = (math.pi / 2 if y < 0 else -math.pi / 2) if along_x else (0.0 if y < 0 else math.pi)
    while x < x1:
        if not any(a < x < c for a, c in keep_clear):
            px, py = (x, y) if along_x else (y, x)
            r = rng.random()
            if r < 0.6:
                _tree(b, px, py)
            elif r < 0.85:
                _lamp_pole(b, px, py, arm)
            else:
                _sign(b, px, py, 0.0 if along_x else math.pi / 2)
        x += rng.uniform(7.0, 16.0)


def _buildings(b: LayoutBuilder, x0: float, x1: float, y_front: float, side: int, along_x: bool = True) -> None:
    """A row of building blocks whose facade is at ``y_front`` (facing the street), with alleys between."""
    rng = b.rng
    x = x0
    while x < x1:
        length = rng.uniform(8.0, 35.0)
        depth = rng.uniform(8.0, 15.0)
        height = rng.uniform(5.0, 20.0)
        xe = min(x + length, x1)
        cx, cy = (x + xe) / 2, y_front + side * depth / 2
        if along_x:
            b.clutter.box(cx, cy, xe - x, depth, 0.0, height, reflectivity=rng.uniform(0.15, 0.4), tag=Tag.BUILDING)
        else:
            b.clutter.box(cy, cx, depth, xe - x, 0.0, height, reflectivity=rng.uniform(0.15, 0.4), tag=Tag.BUILDING)
        if rng.random() < 0.25:  # a low garden wall or hedge in front of this block
            fx, fy = (cx, y_front - side * 0.3)
            tag = Tag.HEDGE if rng.random() < 0.5 else Tag.WALL
            w = 0.6 if tag == Tag.HEDGE else 0.25
            if along_x:
                b.clutter.box(fx, fy, (xe - x) * 0.8, w, 0.0, rng.uniform(0.7, 1.3), reflectivity=0.2, tag=tag)
            else:
                b.clutter.box(fy, fx, w, (xe - x) * 0.8, 0.0, rng.uniform(0.7, 1.3), reflectivity=0.2, tag=tag)
        x = xe + (rng.uniform(2.0, 6.0) if rng.random() < 0.3 else 0.0)


def _sidewalk_people(b: LayoutBuilder, x0: float, x1: float, y_inner: float, side: int, density: float,
                     crossing: tuple[float, float] | None = None, red: tuple[tuple[float, float], ...] = (),
                     keep_clear: tuple[float, float] | None = None) -> None:
    """Pedestrians on a 3.5 m sidewalk starting at |y| = ``y_inner``: walkers in both directions (they queue at
    the curb of ``crossing`` = (x_west, x_east) that they meet first while ``red``), standing and sitting people
    near the facades. Nobody starts or stands inside ``keep_clear`` = (x_lo, x_hi) (a crossing road)."""
    rng = b.rng
    length = x1 - x0
    for direction, off in ((+1, WALK_OFFSETS[0]), (-1, WALK_OFFSETS[1])):
        yy = side * (y_inner + off)
        if direction > 0:
            path = straight((x0 - 200, yy), (x1 + 400, yy))
            base = x0 - 200
        else:
            path = straight((x1 + 200, yy), (x0 - 400, yy))
            base = x1 + 200
        lines = [] if crossing is None else [StopLine(abs(crossing[0 if direction > 0 else 1] - base), red)]
        lane = b.add_lane(path, lines)
        s_lo, s_hi = 200 - 1.6 * b.duration_s, 200 + length
        def in_clear(s: float, base: float = base, direction: int = direction) -> bool:
            return keep_clear is not None and keep_clear[0] < base + direction * s < keep_clear[1]

        _fill_lane(b, lane, s_lo, s_hi, (12.0 / density, 60.0 / density), (1.2, 1.6),
                   {"pedestrian": 0.92, "child": 0.08}, skip=in_clear)
    facing = -side * math.pi / 2
    for key, per_m, attr in (("pedestrian", 1 / 30.0, cat.PED_STANDING), ("sitting", 1 / 90.0, cat.PED_SITTING)):
        for _ in range(rng.poisson(length * per_m * density)):
            x = rng.uniform(x0, x1)
            if keep_clear is None or not keep_clear[0] < x < keep_clear[1]:
                b.add_static(key, x, side * (y_inner + 2.95), facing + rng.uniform(-0.4, 0.4) * (key == "pedestrian"),
                             attr)


def _parked_bicycles(b: LayoutBuilder, x0: float, x1: float, y: float, rate_per_100m: float) -> None:
    rng = b.rng
    for _ in range(rng.poisson((x1 - x0) / 100.0 * rate_per_100m)):
        x = rng.uniform(x0, x1)
        b.add_static("parked_bicycle", x, y, float(rng.choice([0.0, math.pi]) + rng.normal(0, 0.05)),
                     cat.CYCLE_WITHOUT_RIDER)


def _signal_plan(r0: float, g_ego: float, g_cross: float, horizon: float, all_red: float = 2.0
                 ) -> tuple[tuple[tuple[float, float], ...], tuple[tuple[float, float], ...]]:
    """Green intervals of the ego road and the cross road: cross road green first, then ego road, repeating."""
    ego_green, cross_green = [], []
    cross_green.append((-100.0, r0 - all_red))
    t = r0
    while t < horizon + 60:
        ego_green.append((t, t + g_ego))
        t += g_ego + all_red
        cross_green.append((t, t + g_cross))
        t += g_cross + all_red
    return tuple(ego_green), tuple(cross_green)


def _complement(green: tuple[tuple[float, float], ...], horizon: float) -> tuple[tuple[float, float], ...]:
    red, t = [], -1000.0
    for a, e in green:
        if a > t:
            red.append((t, a))
        t = e
    red.append((t, horizon + 1e6))
    return tuple(red)


# --------------------------------------------------------------------------------------------- scenarios


def parking_street(rng: np.random.Generator, duration_s: float) -> Layout:
    """A straight street with parallel-parked cars on both sides; the ego passes at 5–12 m/s in traffic."""
    b = LayoutBuilder(rng, duration_s)
    v_ego = rng.uniform(5.0, 12.0)
    x0, x1 = -90.0, v_ego * duration_s + 130.0
    far = 2000.0
    ego_lane = b.add_lane(straight((-far, -1.75), (far, -1.75)))
    b.add_agent(ego_lane, "car", far, v_ego, is_ego=True, size=(4.7, 1.9, 1.8))
    if rng.random() < 0.6:  # a delivery van or truck ahead that stops every so often: stop-and-go for the ego
        key = "truck" if rng.random() < 0.4 else "van"
        s_lead = far + rng.uniform(25.0, 45.0)
        stops = []
        pos = s_lead + rng.uniform(30.0, 90.0)
        while pos < s_lead + v_ego * duration_s:
            stops.append(ScriptedStop(pos, float(rng.uniform(3.0, 8.0))))
            pos += rng.uniform(60.0, 160.0)
        b.add_agent(ego_lane, key, s_lead, v_ego * rng.uniform(0.9, 1.15), stops=stops, idm=_idm_for(key))
    _fill_lane(b, ego_lane, far + 70.0, far + 70.0 + v_ego * duration_s, (30.0, 80.0), (v_ego + 1.0, v_ego + 4.0),
               {"car": 0.85, "van": 0.1, "motorcycle": 0.05})
    _fill_lane(b, ego_lane, far - 60.0, far - 12.0, (15.0, 40.0), (v_ego, v_ego + 2.0), {"car": 1.0})
    opp = b.add_lane(straight((far, 1.75), (-far, 1.75)))
    _fill_lane(b, opp, far - x1 - 13.0 * duration_s, far - x0 + 20.0, (20.0, 75.0), (8.0, 13.0),
               {"car": 0.78, "van": 0.08, "truck": 0.07, "bus": 0.04, "motorcycle": 0.03},
               stops_every=(80.0, 200.0), p_stopper=0.15)
    for sgn in (-1, 1):
        bike = b.add_lane(straight((-far * sgn, sgn * 4.2), (far * sgn, sgn * 4.2)))
        s_lo = far + (x0 if sgn < 0 else -x1) - 6.0 * duration_s
        s_hi = far + (x1 if sgn < 0 else -x0)
        _fill_lane(b, bike, s_lo, s_hi, (40.0, 180.0), (3.5, 6.5), {"bicycle": 1.0})
    curb = 7.0
    for side in (-1, 1):
        _parallel_parking(b, x0, x1, side * 5.95, 0.0 if side < 0 else math.pi)
        _curb_furniture(b, x0, x1, side * (curb + CURB_STRIP))
        _buildings(b, x0 - 30, x1 + 30, side * (curb + SIDEWALK_WIDTH), side)
        _parked_bicycles(b, x0, x1, side * (curb + CURB_STRIP), 3.0)
        _sidewalk_people(b, x0, x1, curb, side, density=rng.uniform(0.6, 1.4))
    return b.build()


def _pull_in_path(stall: tuple[float, float], heading: float, aisle_y: float, aisle_heading: float) -> Path:
    """Drive along the aisle, turn left by the stall angle and roll straight into the stall's centre."""
    ex, ey = stall
    dh = math.atan2(math.sin(heading - aisle_heading), math.cos(heading - aisle_heading))
    sign = 1.0 if dh > 0 else -1.0
    radius = 4.5
    for _ in range(20):
        # arc end A = E - Ls·u(h1); centre C = A + sign·R·n(h1); arc start S = C - sign·R·n(h0); S.y = aisle_y
        ls = (ey - aisle_y + sign * radius * (math.cos(heading) - math.cos(aisle_heading))) / math.sin(heading)
        if ls >= 1.0:
            break
        radius *= 0.85
    ax, ay = ex - ls * math.cos(heading), ey - ls * math.sin(heading)
    cx, cy = ax - sign * radius * math.sin(heading), ay + sign * radius * math.cos(heading)
    a0 = aisle_heading - sign * math.pi / 2
    arc = arc_points(cx, cy, radius, a0, a0 + dh)
    sx = arc[0, 0]
    start = (sx - 300.0 * math.cos(aisle_heading), aisle_y)
    return Path(np.vstack([np.asarray([start], dtype=np.float64), arc, np.asarray([[ex, ey]])]))


def diagonal_lot(rng: np.random.Generator, duration_s: float,
                 angles_deg: tuple[float, ...] = (45.0, 60.0),
                 stall_width_m: tuple[float, float] | None = None, screened: bool = False) -> Layout:
    """A parking lot aisle lined with angled stalls (``angles_deg``: the stall angle to the aisle, one drawn per
    lot; ``stall_width_m``: the range a lot's stall width is drawn from, else 2.9 m); parked cars occlude each
    other as the ego passes. ``screened``: the ego drives a road (3.3–9 m to its kerb) and the rows nearest it
    stand behind a raised verge 2.5–4.5 m wide with street trees, people walking and standing on it, and a low
    wall or hedge along the cars' fronts (:func:`_screen`)."""
    b = LayoutBuilder(rng, duration_s)
    v_ego = rng.uniform(3.5, 7.5)
    x0, x1 = -70.0, v_ego * duration_s + 100.0
    far = 2000.0
    angle = math.radians(float(rng.choice(list(angles_deg))))
    stall = 2.9 if stall_width_m is None else float(rng.uniform(*stall_width_m))
    pitch = stall / math.sin(angle)
    aisle_half = 3.3
    road_half, verge = (float(rng.uniform(3.3, 9.0)), float(rng.uniform(2.5, 4.5))) if screened else (aisle_half, 0.0)
    shift = road_half + verge - aisle_half  # how far the rows stand beyond where an aisle would put them
    depth = 5.6 * math.sin(angle) + 2.1 * math.cos(angle) + 0.5
    island = 1.2
    aisle2 = aisle_half + shift + 2 * depth + island + aisle_half
    ego_lane = b.add_lane(straight((-far, 0.0), (far, 0.0)))
    b.add_agent(ego_lane, "car", far, v_ego, is_ego=True, size=(4.7, 1.9, 1.8))
    if rng.random() < 0.5:  # a car ahead that stops for a pedestrian / searches for a spot
        stops = [ScriptedStop(far + rng.uniform(40.0, 80.0) + k * rng.uniform(50.0, 120.0), float(rng.uniform(2, 6)))
                 for k in range(3)]
        b.add_agent(ego_lane, "car", far + rng.uniform(18.0, 35.0), v_ego * 0.9, stops=stops)
    for side in (-1, 1):
        # island between back-to-back rows first (clutter before cars, so cars avoid it)
        yi = side * (aisle_half + shift + depth + island / 2)
        x = x0 + rng.uniform(0, 10)
        while x < x1:
            if rng.random() < 0.5:
                _lamp_pole(b, x, yi, 0.0)
            else:
                _tree(b, x, yi)
            x += rng.uniform(15.0, 30.0)
        b.clutter.box((x0 + x1) / 2, yi, x1 - x0, 0.5, 0.0, 0.15, reflectivity=0.3, tag=Tag.WALL)  # curb
        # near rows face the ego aisle (which runs +x); outer aisles are one-way, opposite senses
        if screened:  # the verge, then people standing on it (they step onto its slab; its trunks refuse them)
            _screen(b, x0, x1, side * road_half, side * (road_half + verge), side)
            for _ in range(rng.poisson((x1 - x0) / 40.0)):
                b.add_static("pedestrian", rng.uniform(x0, x1), side * (road_half + rng.uniform(1.2, 1.8)),
                             rng.uniform(-3, 3), cat.PED_STANDING)
        _diagonal_row(b, x0, x1, side * (aisle_half + shift), side, side * angle, pitch, rng.uniform(0.7, 0.92))
        y2 = side * aisle2
        d = -side
        h_aisle = 0.0 if d > 0 else math.pi
        far_heading = h_aisle + angle  # cars turn left from the outer aisle into the far row
        empty = _diagonal_row(b, x0, x1, side * (aisle2 - aisle_half), -side, far_heading, pitch,
                              rng.uniform(0.6, 0.9))
        outer = b.add_lane(straight((-far * d, y2), (far * d, y2)))
        ahead = [e for e in empty if x0 + 30 < e[0] < x1 - 40]
        if ahead and rng.random() < 0.8:  # a car arrives and parks in an empty stall
            stall = ahead[int(rng.integers(len(ahead)))]
            path = _pull_in_path(stall, far_heading, y2, h_aisle)
            lane = b.add_lane(path)
            t_arrive = max(2.0, (stall[0] - 10.0) / v_ego - 2.0)
            s_turn = path.project(stall[0] - d * 8.0, y2)
            b.add_agent(lane, "car", max(0.0, s_turn - 3.5 * t_arrive), 3.5,
                        stops=[ScriptedStop(path.length + 2.3, 1e9)], parks_after_s=0.0)
        else:  # or slow traffic in the outer aisle
            s_lo = far + (x0 if d > 0 else -x1) - 5.0 * duration_s
            s_hi = far + (x1 if d > 0 else -x0)
            _fill_lane(b, outer, s_lo, s_hi, (40.0, 120.0), (2.5, 5.5), {"car": 0.9, "van": 0.1})
        # walkers along the aisle edges (the verge's walk when screened) and people standing on the island
        yw = side * (road_half + 1.5 if screened else road_half - 0.6)
        walk = b.add_lane(straight((-far * side, yw), (far * side, yw)))
        s_lo = far + (x0 if side > 0 else -x1) - 1.6 * duration_s
        s_hi = far + (x1 if side > 0 else -x0)
        _fill_lane(b, walk, s_lo, s_hi, (15.0, 60.0), (0.9, 1.5), {"pedestrian": 0.9, "child": 0.1})
        # (on the island's curb: until 6 Dec 2026 the curb refused every one of them, so no lot had anyone on it)
        for _ in range(rng.poisson((x1 - x0) / 60.0)):
            b.add_static("pedestrian", rng.uniform(x0, x1), yi + rng.uniform(-0.2, 0.2), rng.uniform(-3, 3),
                         cat.PED_STANDING)
        # boundary fence and buildings beyond the outer aisle
        yf = side * (aisle2 + aisle_half + 1.5)
        b.clutter.box((x0 + x1) / 2, yf, x1 - x0 + 60, 0.1, 0.0, 1.8, reflectivity=0.15, tag=Tag.FENCE)
        _buildings(b, x0 - 30, x1 + 30, side * (aisle2 + aisle_half + 6.0), side)
    return b.build()


def _intersection(rng: np.random.Generator, duration_s: float, mixed: bool) -> Layout:
    b = LayoutBuilder(rng, duration_s)
    v_ego = rng.uniform(9.0, 13.0)
    far = 2000.0
    r0 = rng.uniform(8.0, 12.0)
    g_ego, g_cross = rng.uniform(16.0, 22.0), rng.uniform(15.0, 19.0)
    ego_green, cross_green = _signal_plan(r0, g_ego, g_cross, duration_s, all_red=3.0)
    ego_red, cross_red = _complement(ego_green, duration_s), _complement(cross_green, duration_s)
    # people walk with the parallel traffic, starting 2 s after it and stopping 5 s before its red
    # people walk with the parallel traffic, from 4 s after its green (vehicles that ran the amber have cleared)
    # until 10 s before its end (crossing 10.8 m between the curb extensions at ±5.4 m takes < 9 s at 1.2 m/s)
    walk_x = _complement(tuple((a + 4.0, max(a + 4.0, e - 10.0)) for a, e in cross_green), duration_s)
    walk_y = _complement(tuple((a + 4.0, max(a + 4.0, e - 10.0)) for a, e in ego_green), duration_s)
    stop = 11.5
    curb = 7.2
    bulb = 5.4  # curb extensions at the crosswalks
    north_in = 11.5 if mixed else curb  # the ego road's north sidewalk starts here (mixed: angled parking)
    stop_south = north_in + SIDEWALK_WIDTH + 0.8
    x_east = v_ego * duration_s + 100.0
    x_west = -(v_ego * r0 + 150.0)
    y_far = 120.0
    box = 12.0 + (north_in - curb)
    vehicles = {"car": 0.8, "van": 0.08, "truck": 0.06, "bus": 0.03, "motorcycle": 0.03}
    if mixed:
        vehicles = {"car": 0.62, "van": 0.1, "truck": 0.12, "bus": 0.06, "motorcycle": 0.1}

    # ---- static scenery first, so that parked objects and people keep clear of it
    for cx, cy in ((-curb, -curb), (curb, -curb), (-curb, north_in), (curb, north_in)):
        b.clutter.cylinder(cx, cy, 0.12, 0.0, 5.5, reflectivity=0.5, tag=Tag.POLE)  # traffic lights
        b.clutter.box(cx, cy, 0.4, 0.4, 4.3, 5.4, reflectivity=0.7, tag=Tag.SIGN)
    clear = [(-box - 2, box + 2)]
    _curb_furniture(b, x_west, x_east, -(curb + CURB_STRIP), keep_clear=clear)
    _curb_furniture(b, x_west, x_east, north_in + CURB_STRIP, keep_clear=clear)
    for sx in (-1, 1):
        _curb_furniture(b, -y_far, y_far, sx * (curb + CURB_STRIP), along_x=False, keep_clear=clear)
    _buildings(b, x_west - 30, -(curb + SIDEWALK_WIDTH), -(curb + SIDEWALK_WIDTH), -1)
    _buildings(b, curb + SIDEWALK_WIDTH, x_east + 30, -(curb + SIDEWALK_WIDTH), -1)
    _buildings(b, x_west - 30, -(curb + SIDEWALK_WIDTH), north_in + SIDEWALK_WIDTH, 1)
    _buildings(b, curb + SIDEWALK_WIDTH, x_east + 30, north_in + SIDEWALK_WIDTH, 1)
    for sx in (-1, 1):
        _buildings(b, north_in + SIDEWALK_WIDTH, y_far + 30, sx * (curb + SIDEWALK_WIDTH), sx, along_x=False)
        _buildings(b, -y_far - 30, -(curb + SIDEWALK_WIDTH), sx * (curb + SIDEWALK_WIDTH), sx, along_x=False)

    def road_lane(p0: tuple[float, float], p1: tuple[float, float], red: tuple[tuple[float, float], ...],
                  line_xy: tuple[float, float]) -> int:
        path = straight(p0, p1)
        return b.add_lane(path, [StopLine(path.project(*line_xy), red)])

    # ---- ego road, eastbound: a queue at the red light ahead of the ego, the ego, followers
    east = road_lane((-far, -1.75), (far, -1.75), ego_red, (-stop, -1.75))
    s_line = b.lane_path(east).project(-stop, -1.75)
    n_queue = int(rng.integers(0, 3))
    for k in range(n_queue):
        b.add_agent(east, "car", s_line - 2.5 - 2.4 - k * 7.0, v_ego, v0=0.0)
    s_ego = s_line - (v_ego * max(1.0, r0 - 9.0) + 20.0 + n_queue * 7.0)  # arrives ≈3 s before green
    b.add_agent(east, "car", s_ego, v_ego, is_ego=True, size=(4.7, 1.9, 1.8))
    _fill_lane(b, east, s_ego - 10.0 * duration_s, s_ego - 15.0, (20.0, 60.0), (9.0, 13.0), vehicles)
    _fill_lane(b, east, s_line + 15.0, s_line + 15 + v_ego * duration_s, (30.0, 80.0), (10.0, 14.0), vehicles)
    west = road_lane((far, 1.75), (-far, 1.75), ego_red, (stop, 1.75))
    s_west_line = b.lane_path(west).project(stop, 1.75)
    _fill_lane(b, west, far - x_east - 12.0 * duration_s, s_west_line - 35.0, (15.0, 60.0), (8.0, 13.0), vehicles,
               stops_every=(60.0, 200.0) if mixed else None, p_stopper=0.3 if mixed else 0.0,
               stop_ok=lambda s: abs(far - s) > box + 20.0)
    # ---- cross road: northbound straight; the north arm's southbound traffic all turns right (west)
    north = road_lane((1.75, -far), (1.75, far), cross_red, (1.75, -stop))
    _fill_lane(b, north, far - y_far - 12.0 * duration_s, far + 20.0, (15.0, 60.0), (8.0, 13.0), vehicles)
    radius = 5.0 - 1.75 + 2.2
    cxy = (-1.75 - radius, 1.75 + radius)
    for lane_x, lane_y, r, mix, gaps, speeds in (
        (-1.75, 1.75, radius, {k: v for k, v in vehicles.items() if k != "bus"}, (15.0, 60.0), (11.0, 14.0)),
        (-4.2, 4.2, radius - 2.45, {"bicycle": 1.0}, (25.0, 120.0), (3.5, 6.0)),
    ):
        arc = arc_points(cxy[0], cxy[1], r, 0.0, -math.pi / 2)
        path = turn_path((lane_x, far), (lane_x, cxy[1]), arc, (-far, lane_y))
        curve = SpeedZone(path.project(lane_x, cxy[1]), path.project(cxy[0], lane_y), math.sqrt(2.5 * r))
        lane = b.add_lane(path, [StopLine(path.project(lane_x, stop_south), cross_red)], [curve])
        s_l = path.project(lane_x, stop_south)
        _fill_lane(b, lane, s_l - y_far - 10.0 * duration_s, s_l - 35.0, gaps, speeds, mix)
    # ---- bike lanes with the same signals
    for (p0, p1, red, line) in (
        ((-far, -4.2), (far, -4.2), ego_red, (-stop, -4.2)),
        ((far, 4.2), (-far, 4.2), ego_red, (stop, 4.2)),
        ((4.2, -far), (4.2, far), cross_red, (4.2, -stop)),
    ):
        lane = road_lane(p0, p1, red, line)
        s_l = b.lane_path(lane).project(*line)
        _fill_lane(b, lane, s_l - 120.0 - 5.0 * duration_s, s_l - 10.0, (25.0, 120.0), (3.5, 6.0),
                   {"bicycle": 1.0} if not mixed else {"bicycle": 0.8, "motorcycle": 0.2})
    # ---- parked vehicles beyond the intersection
    _parallel_parking(b, x_west, -box - 14.0, -6.1, 0.0)
    _parallel_parking(b, box + 14.0, x_east, -6.1, 0.0)
    _parallel_parking(b, x_west, -box - 14.0, 6.1, math.pi)
    if mixed:
        angle = math.radians(60.0)
        _diagonal_row(b, box + 14.0, x_east, 5.0, 1, math.pi - angle, 2.9 / math.sin(angle), 0.8,
                      mix={"car": 0.88, "van": 0.12})
        b.add_static("trailer", -45.0, -6.4, 0.0, cat.VEHICLE_PARKED)
    else:
        _parallel_parking(b, box + 14.0, x_east, 6.1, math.pi)
    for sx in (-1, 1):
        heading = -math.pi / 2 if sx < 0 else math.pi / 2
        _parallel_parking(b, box + 14.0, y_far, sx * 6.1, heading, along_x=False)
        _parallel_parking(b, -y_far, -box - 14.0, sx * 6.1, heading, along_x=False)
        _parked_bicycles(b, box, x_east, sx * (curb + CURB_STRIP) if sx < 0 else north_in + CURB_STRIP, 2.0)
    # ---- pedestrians: along both roads' sidewalks, crossing at the crosswalks with their own signal
    dens = rng.uniform(0.8, 1.5) * (1.3 if mixed else 1.0)
    corner = (-curb - SIDEWALK_WIDTH - 0.5, curb + SIDEWALK_WIDTH + 0.5)
    for side, y_in in ((-1, curb), (1, north_in)):
        _sidewalk_people(b, x_west, x_east, y_in, side, dens, crossing=(-bulb, bulb), red=walk_y, keep_clear=corner)
    for sx in (-1, 1):  # cross-road sidewalks: people walking along y, crossing the ego road
        for direction, off in ((1, WALK_OFFSETS[0]), (-1, WALK_OFFSETS[1])):
            xx = sx * (curb + off)
            path = straight((xx, -far * direction), (xx, far * direction))
            lane = b.add_lane(path, [StopLine(path.project(xx, -direction * bulb), walk_x)])
            y_lo, y_hi = -curb - SIDEWALK_WIDTH - 0.5, north_in + SIDEWALK_WIDTH + 0.5

            def in_road(s: float, direction: int = direction) -> bool:
                return y_lo < direction * (s - far) < y_hi

            _fill_lane(b, lane, far - y_far - 1.6 * duration_s, far + y_far, (12.0 / dens, 60.0 / dens), (1.2, 1.6),
                       {"pedestrian": 0.9, "child": 0.1}, skip=in_road)
    return b.build()


def intersection(rng: np.random.Generator, duration_s: float) -> Layout:
    """A signalised four-way intersection: the ego queues at red, crossing traffic, people on crosswalks."""
    return _intersection(rng, duration_s, mixed=False)


def mixed(rng: np.random.Generator, duration_s: float) -> Layout:
    """The intersection with angled parking on one arm, more trucks, buses with stops, motorcycles."""
    return _intersection(rng, duration_s, mixed=True)


_FLEET_MIX = {"car": 0.5, "van": 0.1, "pickup": 0.14, "truck": 0.14, "semi": 0.06, "long_trailer": 0.03,
              "bus": 0.03}
"""Kerbside parking of a commercial street: a real fleet's spread of sizes (pick-ups, rigid trucks, buses,
tractor-semitrailers and trailers 11–18 m long), not the residential mix of the other scenarios."""
_YARD_MIX = {"semi": 0.3, "long_trailer": 0.2, "truck": 0.2, "bus": 0.1, "van": 0.1, "pickup": 0.1}


def perpendicular_lot(rng: np.random.Generator, duration_s: float) -> Layout:
    """The parking lot of :func:`diagonal_lot` with stalls at right angles to the aisles, the commonest layout of
    real lots, 2.3–2.8 m wide (a real lot's 8–9 ft): each parked car shows the sensor its front or back between two
    neighbours 0.3–1 m away, its flanks hidden — a near-continuous band of car fronts — and the far rows stand
    14–15 m off the ego's aisle (why it exists: docs/detector.md, "A row of nose-in cars"). A scenario of its own,
    so that the diagonal lot's seeds keep their worlds."""
    return diagonal_lot(rng, duration_s, angles_deg=(90.0,), stall_width_m=(2.3, 2.8))


def screened_lot(rng: np.random.Generator, duration_s: float) -> Layout:
    """:func:`perpendicular_lot` seen from a road: the rows nearest the ego stand behind a raised verge with street
    trees and a low wall or hedge along the cars' fronts, as the row of nose-in cars the shipped detector missed on
    a real scene does (docs/detector.md, "A row of nose-in cars")."""
    return diagonal_lot(rng, duration_s, angles_deg=(90.0,), stall_width_m=(2.3, 2.8), screened=True)


def loading_street(rng: np.random.Generator, duration_s: float) -> Layout:
    """A commercial street beside a loading yard: large vehicles parked side by side nose to the street, often
    behind a low wall or fence (few returns, each hiding the next), kerbside parking of a mixed fleet, trucks and
    buses in traffic. Training data for a detector that meets real trucks; the evaluation scenarios do not use it."""
    b = LayoutBuilder(rng, duration_s)
    v_ego = rng.uniform(4.0, 10.0)
    x0, x1 = -90.0, v_ego * duration_s + 120.0
    far = 2000.0
    curb = 7.0
    ego_lane = b.add_lane(straight((-far, -1.75), (far, -1.75)))
    b.add_agent(ego_lane, "car", far, v_ego, is_ego=True, size=(4.7, 1.9, 1.8))
    heavy = {"car": 0.55, "van": 0.1, "pickup": 0.1, "truck": 0.12, "bus": 0.06, "semi": 0.07}
    _fill_lane(b, ego_lane, far + 60.0, far + 60.0 + v_ego * duration_s, (35.0, 90.0), (v_ego + 1.0, v_ego + 3.0),
               heavy)
    opp = b.add_lane(straight((far, 1.75), (-far, 1.75)))
    _fill_lane(b, opp, far - x1 - 12.0 * duration_s, far - x0 + 20.0, (20.0, 70.0), (7.0, 12.0), heavy,
               stops_every=(80.0, 200.0), p_stopper=0.15)
    # south: a kerb of mixed parking, furniture, shops, people
    _parallel_parking(b, x0, x1, -5.95, 0.0, mix=_FLEET_MIX)
    _curb_furniture(b, x0, x1, -(curb + CURB_STRIP))
    _buildings(b, x0 - 30, x1 + 30, -(curb + SIDEWALK_WIDTH), -1)
    _sidewalk_people(b, x0, x1, curb, -1, density=rng.uniform(0.4, 1.0))
    # north: the yard's edge (a low wall, a fence or open), vehicles nose-in side by side, a warehouse behind
    yard = curb + 1.5
    x = x0
    while x < x1:
        length = rng.uniform(20.0, 60.0)
        edge = rng.choice(3, p=[0.4, 0.3, 0.3])
        if edge == 0:
            b.clutter.box(x + length / 2, yard - 0.4, length, 0.3, 0.0, rng.uniform(0.8, 1.6), reflectivity=0.25,
                          tag=Tag.WALL)
        elif edge == 1:
            b.clutter.box(x + length / 2, yard - 0.4, length, 0.1, 0.0, rng.uniform(1.5, 2.2), reflectivity=0.15,
                          tag=Tag.FENCE)
        x += length + rng.uniform(6.0, 12.0)  # a gate
    x = x0 + rng.uniform(0, 4)
    while x < x1:
        if rng.random() < 0.2:
            x += rng.uniform(3.5, 9.0)
            continue
        key = _pick(rng, _YARD_MIX)
        size = cat.CLASSES[key].sample_size(rng)
        heading = math.pi / 2 if rng.random() < 0.5 else -math.pi / 2
        b.add_static(key, x + size[1] / 2, yard + 0.5 + size[0] / 2 + rng.uniform(0.0, 1.5),
                     heading + float(rng.normal(0, 0.02)), cat.VEHICLE_PARKED, size=size)
        x += size[1] + rng.uniform(0.8, 2.5)
    depth = rng.uniform(15.0, 30.0)
    b.clutter.box((x0 + x1) / 2, yard + 20.0 + depth / 2, x1 - x0 + 60.0, depth, 0.0, rng.uniform(8.0, 14.0),
                  reflectivity=0.3, tag=Tag.BUILDING)
    for _ in range(rng.poisson((x1 - x0) / 40.0)):  # yard workers
        b.add_static("pedestrian", rng.uniform(x0, x1), yard + rng.uniform(0.5, 1.5), rng.uniform(-3, 3),
                     cat.PED_STANDING)
    return b.build()


SCENARIOS: dict[str, Callable[[np.random.Generator, float], Layout]] = {
    "parking-street": parking_street,
    "diagonal-lot": diagonal_lot,
    "intersection": intersection,
    "mixed": mixed,
    "loading-street": loading_street,
    "perpendicular-lot": perpendicular_lot,
    "screened-lot": screened_lot,
}
