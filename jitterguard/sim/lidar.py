"""Ray-cast LiDAR: a spinning sensor's beams against the world's primitives and a flat ground.

How it stays fast in numpy: every ray starts at the sensor, so a primitive can only be hit by the rays of the
azimuth columns its footprint spans and the beams its vertical extent spans. Each primitive yields exactly
those (ray, primitive) pairs — no ray is tested against the whole scene — and one batched slab test over all
pairs finds the hits; the nearest hit per ray wins. Distances are measured horizontally (ρ) so that a box is a
2-D slab test plus a z-slab [z0·cot el, z1·cot el] and a vertical cylinder a circle plus the same z-slab.

Sensor effects: Gaussian range noise, random dropout, weak returns lost with range and low reflectivity,
min/max range, porous tree crowns and fences (a ray passes with some probability). Intensity follows the
surface's reflectivity, falling off with range, on nuScenes' 0…255 scale. Motion during the sweep is not modelled
(every point is taken at the frame's stamp).

:class:`~jitterguard.sim.effects.ScanEffects` (``effects=``) adds what real scans show and ideal ones lack:
a ground that is not the plane under the car (rays are marched against the height field; objects and scenery
stand on it), glass that rays pass through, lost returns on dark road users, mixed pixels at depth edges, the
sensor's own roof blocking its steepest beams, other range noise and measured intensity distributions.
Without it the ideal scan comes out bit for bit as before.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from .catalog import VEHICLE_PARKED
from .effects import (BRIGHT_SPOT_FRACTION, GRAZING_COS, MEASURED_INTENSITY, ScanEffects, kerbside_trees,
                      street_clutter, street_objects, vegetation_masses)
from .primitives import BOX, PrimitiveList, Primitives, Tag
from .sensors import LidarSpec, azimuths, hdl32e
from .shapes import crank_angle, gait_stride, object_primitives
from .world import GroundTruthFrame

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]

GROUND_REFLECTIVITY = 0.12
_POROSITY = {int(Tag.TREE_CROWN): 0.55, int(Tag.FENCE): 0.35, int(Tag.HEDGE): 0.1}
_CLUTTER_OWNER = -1
_GROUND_OWNER = -2
_EGO_OWNER = -3
_SURFACE_OF_TAG = {int(Tag.OBJECT): "object", int(Tag.GLASS): "glass", int(Tag.TREE_TRUNK): "vegetation",
                   int(Tag.TREE_CROWN): "vegetation", int(Tag.HEDGE): "vegetation", int(Tag.POLE): "pole",
                   int(Tag.SIGN): "sign", int(Tag.FENCE): "building", int(Tag.WALL): "building",
                   int(Tag.BUILDING): "building", int(Tag.EGO): "building"}
_RHO_GRID = np.geomspace(0.3, 130.0, 140)
"""Horizontal distances at which rays are tested against an uneven ground (≈4.4 % apart; the crossing is then
interpolated linearly, exact for a plane and within millimetres for the gentle surfaces drawn)."""


@dataclass(frozen=True, eq=False)
class ScanResult:
    """A scan: ``points`` (P, 4) float32 x, y, z, intensity in the sensor frame; ``ring`` (P,) beam index (0 =
    lowest); ``owner`` (P,) the frame row of the object hit (−1 clutter, −2 ground); per object row,
    ``num_points`` (returns on it), ``num_rays_visible`` (rays whose first hit is the object, before range
    limits and dropout) and ``num_rays_alone`` (rays that would hit it with nothing in front of it);
    ``object_lift`` (metres the effects' ground raised each object; None for the ideal flat ground)."""

    points: F32
    ring: NDArray[np.int16]
    owner: NDArray[np.int64]
    num_points: NDArray[np.int64]
    num_rays_visible: NDArray[np.int64]
    num_rays_alone: NDArray[np.int64]
    object_lift: F64 | None = None


class _Tables:
    """Per-sensor trigonometry, computed once per :class:`LidarSpec`."""

    def __init__(self, spec: LidarSpec) -> None:
        az = azimuths(spec)
        self.cos_az = np.cos(az).astype(np.float32)
        self.sin_az = np.sin(az).astype(np.float32)
        el = spec.elevations
        self.el = el
        self.cos_el = np.cos(el)
        with np.errstate(divide="ignore"):
            self.cot_el = np.where(np.abs(el) < 1e-12, np.inf, 1.0 / np.tan(el)).astype(np.float32)
        # horizontal distance at which each beam meets the ground (inf for beams at or above the horizon)
        self.rho_ground = np.where(el < -1e-9, spec.mount_height_m * np.abs(self.cot_el), np.inf)
        self.daz = 2.0 * math.pi / spec.azimuth_steps


_TABLE_CACHE: dict[int, tuple[LidarSpec, _Tables]] = {}


def _tables(spec: LidarSpec) -> _Tables:
    hit = _TABLE_CACHE.get(id(spec))
    if hit is None or hit[0] is not spec:
        if len(_TABLE_CACHE) > 16:
            _TABLE_CACHE.clear()
        hit = (spec, _Tables(spec))
        _TABLE_CACHE[id(spec)] = hit
    return hit[1]


def to_sensor_frame(prims: Primitives, ego_x: float, ego_y: float, ego_yaw: float, height: float) -> Primitives:
    """World-frame primitives into the sensor frame (origin at the sensor, z up from the sensor)."""
    c, s = math.cos(ego_yaw), math.sin(ego_yaw)
    dx, dy = prims.center[:, 0] - ego_x, prims.center[:, 1] - ego_y
    return replace(prims, center=np.column_stack([c * dx + s * dy, -s * dx + c * dy]), z=prims.z - height,
                   yaw=prims.yaw - ego_yaw)


def _extents(p: Primitives) -> tuple[F64, F64, F64, F64]:
    """Per primitive: azimuth interval [lo, hi] (lo may be < −π), nearest and farthest horizontal distance."""
    cx, cy = p.center[:, 0], p.center[:, 1]
    dist = np.hypot(cx, cy)
    mid = np.arctan2(cy, cx)
    box = p.kind == BOX
    c, s = np.cos(p.yaw), np.sin(p.yaw)
    sl = np.array([1.0, 1.0, -1.0, -1.0])
    sw = np.array([1.0, -1.0, -1.0, 1.0])
    px = cx[:, None] + c[:, None] * p.half[:, :1] * sl - s[:, None] * p.half[:, 1:] * sw
    py = cy[:, None] + s[:, None] * p.half[:, :1] * sl + c[:, None] * p.half[:, 1:] * sw
    rel = np.arctan2(py, px) - mid[:, None]
    rel = (rel + np.pi) % (2 * np.pi) - np.pi
    box_lo, box_hi = rel.min(axis=1), rel.max(axis=1)
    # nearest point of a rectangle: clamp the origin into the rectangle in its own frame
    ox, oy = -(c * cx + s * cy), (s * cx - c * cy)
    qx = np.clip(ox, -p.half[:, 0], p.half[:, 0]) - ox
    qy = np.clip(oy, -p.half[:, 1], p.half[:, 1]) - oy
    box_near = np.hypot(qx, qy)
    box_far = np.sqrt(((np.abs(ox) + p.half[:, 0]) ** 2 + (np.abs(oy) + p.half[:, 1]) ** 2))
    r = p.half[:, 0]
    half = np.arcsin(np.clip(r / np.maximum(dist, 1e-9), 0.0, 1.0))
    lo = np.where(box, box_lo, -half) + mid
    hi = np.where(box, box_hi, half) + mid
    near = np.where(box, box_near, np.maximum(dist - r, 0.0))
    far = np.where(box, box_far, dist + r)
    inside = near <= 1e-9
    lo = np.where(inside, -np.pi, lo)
    hi = np.where(inside, np.pi, hi)
    return lo, hi, near, far


def terrain_rho(spec: LidarSpec, effects: ScanEffects, columns: NDArray[np.bool_] | None = None) -> F64:
    """Horizontal distance (per ray, column-major like :func:`cast`'s ray index) at which each ray meets the
    effects' ground, inf where it does not within the grid (or its column is not in ``columns``): the first
    sample where the ray has dropped below the surface, interpolated linearly between that sample and the one
    before."""
    tb = _tables(spec)
    nb, na = spec.num_beams, spec.azimuth_steps
    full = np.full((na, nb), np.inf)
    cols_idx = np.arange(na) if columns is None else np.flatnonzero(columns)
    out = np.full((len(cols_idx), nb), np.inf)
    tan_el = np.tan(tb.el)
    ca, sa = tb.cos_az[cols_idx].astype(np.float64), tb.sin_az[cols_idx].astype(np.float64)
    rho = _RHO_GRID
    x = ca[:, None] * rho[None, :]  # (na, K)
    y = sa[:, None] * rho[None, :]
    g = effects.ground_offset(x, y) - spec.mount_height_m  # ground z in the sensor frame, (na, K)
    for b in range(nb):
        f = rho[None, :] * tan_el[b] - g  # ray height above the ground; > 0 near the sensor
        below = f <= 0.0
        hit = below.any(axis=1)
        k = np.argmax(below, axis=1)
        cols = np.flatnonzero(hit & (k > 0))
        k1 = k[cols]
        f0, f1 = f[cols, k1 - 1], f[cols, k1]
        r0, r1 = rho[k1 - 1], rho[k1]
        out[cols, b] = r0 + (r1 - r0) * f0 / (f0 - f1)
    full[cols_idx] = out
    return full.reshape(-1)


def cast(prims: Primitives, owner: NDArray[np.int64], spec: LidarSpec, rng: np.random.Generator,
         num_objects: int, *, with_ground: bool = True, effects: ScanEffects | None = None,
         columns: NDArray[np.bool_] | None = None) -> ScanResult:
    """Cast every ray of ``spec`` against sensor-frame ``prims`` (``owner``: object row, −1 for clutter, −3 the
    sensor's own vehicle). ``effects`` (see the module doc) changes the ground, porosity, dropout, noise and
    intensity; the primitives must already stand on its ground (:func:`cast_frame` lifts them). ``columns``
    (azimuth steps,) casts only those azimuth columns (one sector of a sweep with motion)."""
    fx = effects or ScanEffects()
    tb = _tables(spec)
    nb, na = spec.num_beams, spec.azimuth_steps
    max_rho = spec.max_range_m  # a horizontal distance bound; the 3-D limit is applied at the end
    lo, hi, near, far = _extents(prims)
    keep = (near < max_rho) & (prims.z[:, 1] > prims.z[:, 0])
    # beams whose elevation can reach the primitive's vertical extent
    z0, z1 = prims.z[:, 0], prims.z[:, 1]
    nr = np.maximum(near, 1e-3)
    el_hi = np.where(z1 > 0, np.arctan2(z1, nr), np.arctan2(z1, far))
    el_lo = np.where(z0 > 0, np.arctan2(z0, far), np.arctan2(z0, nr))
    b0 = np.searchsorted(tb.el, el_lo, side="left")
    b1 = np.searchsorted(tb.el, el_hi, side="right")
    j0 = np.ceil((lo + math.pi) / tb.daz - 0.5).astype(np.int64)
    j1 = np.floor((hi + math.pi) / tb.daz - 0.5).astype(np.int64)
    ncol = np.where(keep, np.maximum(j1 - j0 + 1, 0), 0)
    nbeam = np.maximum(b1 - b0, 0)
    count = ncol * nbeam
    # porous primitives let a fraction of their rays through
    prim_idx = np.repeat(np.arange(len(prims)), count)
    total = len(prim_idx)
    start = np.cumsum(count) - count
    k = np.arange(total) - np.repeat(start, count)
    nbp = nbeam[prim_idx]
    col = (j0[prim_idx] + k // nbp) % na
    beam = b0[prim_idx] + k % nbp
    if columns is not None:
        sel = columns[col]
        prim_idx, col, beam = prim_idx[sel], col[sel], beam[sel]
    ca, sa = tb.cos_az[col], tb.sin_az[col]
    cot = tb.cot_el[beam]
    # z-slab in horizontal distance: rho in [z0·cot, z1·cot] (sorted)
    za = (z0[prim_idx] * cot).astype(np.float32)
    zb = (z1[prim_idx] * cot).astype(np.float32)
    rho_in = np.minimum(za, zb)
    rho_out = np.maximum(za, zb)
    cx = prims.center[prim_idx, 0].astype(np.float32)
    cy = prims.center[prim_idx, 1].astype(np.float32)
    hl = prims.half[prim_idx, 0].astype(np.float32)
    is_box = prims.kind[prim_idx] == BOX
    bi = np.flatnonzero(is_box)
    ci = np.flatnonzero(~is_box)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if len(bi):
            yaw = prims.yaw[prim_idx[bi]]
            cyaw, syaw = np.cos(yaw).astype(np.float32), np.sin(yaw).astype(np.float32)
            dx = ca[bi] * cyaw + sa[bi] * syaw  # ray direction in the box frame
            dy = sa[bi] * cyaw - ca[bi] * syaw
            ox = -(cx[bi] * cyaw + cy[bi] * syaw)  # sensor position in the box frame
            oy = cx[bi] * syaw - cy[bi] * cyaw
            hw = prims.half[prim_idx[bi], 1].astype(np.float32)
            ix, iy = 1.0 / dx, 1.0 / dy
            tx1, tx2 = (-hl[bi] - ox) * ix, (hl[bi] - ox) * ix
            ty1, ty2 = (-hw - oy) * iy, (hw - oy) * iy
            rho_in[bi] = np.maximum(rho_in[bi], np.maximum(np.minimum(tx1, tx2), np.minimum(ty1, ty2)))
            rho_out[bi] = np.minimum(rho_out[bi], np.minimum(np.maximum(tx1, tx2), np.maximum(ty1, ty2)))
        if len(ci):
            b = ca[ci] * cx[ci] + sa[ci] * cy[ci]
            disc = b * b - (cx[ci] * cx[ci] + cy[ci] * cy[ci] - hl[ci] * hl[ci])
            root = np.sqrt(np.maximum(disc, 0.0))
            rho_in[ci] = np.where(disc >= 0, np.maximum(rho_in[ci], b - root), np.inf)
            rho_out[ci] = np.where(disc >= 0, np.minimum(rho_out[ci], b + root), -np.inf)
        hit = (rho_in <= rho_out) & (rho_in > 0.0)
    ray = col * nb + beam
    hit_idx = np.flatnonzero(hit)
    hit_ray = ray[hit_idx]
    hit_rho = rho_in[hit_idx].astype(np.float64)
    hit_prim = prim_idx[hit_idx]
    # rays that would hit each object if nothing else were there (for the ray-cast visibility)
    obj_of_hit = owner[hit_prim]
    is_obj = obj_of_hit >= 0
    alone = np.zeros(num_objects, np.int64)
    if num_objects and is_obj.any():
        pairs = np.unique(obj_of_hit[is_obj] * (na * nb) + hit_ray[is_obj])
        alone = np.bincount(pairs // (na * nb), minlength=num_objects)
    # porosity: some rays pass through tree crowns and fences
    por = np.zeros(len(prims))
    for tag, p in _POROSITY.items():
        por[prims.tag == tag] = p
    if fx.glass_pass:
        por[prims.tag == int(Tag.GLASS)] = fx.glass_pass
    passes = rng.random(len(hit_prim)) < por[hit_prim]
    hit_ray, hit_rho, hit_prim = hit_ray[~passes], hit_rho[~passes], hit_prim[~passes]
    # nearest hit per ray: sort by (ray, rho) and keep the first of each ray
    best_rho = np.full(na * nb, np.inf)
    if with_ground:
        best_rho = np.tile(tb.rho_ground, na) if fx.flat else terrain_rho(spec, fx, columns)
    if columns is not None:
        best_rho[~np.repeat(columns, nb)] = np.inf
    best_prim = np.full(na * nb, -1, np.int64)
    if len(hit_ray):
        order = np.lexsort((hit_rho, hit_ray))
        r_sorted = hit_ray[order]
        first = np.ones(len(order), bool)
        first[1:] = r_sorted[1:] != r_sorted[:-1]
        sel = order[first]
        rr, rho_sel = hit_ray[sel], hit_rho[sel]
        closer = rho_sel < best_rho[rr]
        best_rho[rr[closer]] = rho_sel[closer]
        best_prim[rr[closer]] = hit_prim[sel][closer]
    # 3-D range, limits, noise, dropout
    beam_of_ray = np.tile(np.arange(nb), na)
    col_of_ray = np.repeat(np.arange(na), nb)
    rng3 = best_rho / tb.cos_el[beam_of_ray]
    prim_refl = np.append(prims.reflectivity, GROUND_REFLECTIVITY)  # index −1 → ground
    refl = prim_refl[best_prim]
    owner_all = np.append(owner, _GROUND_OWNER)
    first_owner = owner_all[best_prim]
    valid = np.isfinite(rng3) & (rng3 >= spec.min_range_m) & (rng3 <= spec.max_range_m)
    # weak far returns from dark surfaces are lost: detection range scales with sqrt(reflectivity)
    reach = spec.max_range_m * np.sqrt(np.clip(refl / 0.5, 0.05, 1.0))
    p_lost = spec.dropout + 0.5 * np.clip((rng3 - 0.6 * reach) / (0.4 * reach + 1e-9), 0.0, 1.0)
    u = rng.random(na * nb)
    if fx.object_dropout:
        p_lost = p_lost + fx.object_dropout * (first_owner >= 0)
    if fx.incidence:
        on_user = np.flatnonzero((first_owner >= 0) & np.isfinite(best_rho))
        cos_in = _cos_incidence(prims, best_prim[on_user], best_rho[on_user], tb.el[beam_of_ray[on_user]],
                                tb.cos_az[col_of_ray[on_user]], tb.sin_az[col_of_ray[on_user]])
        p_lost[on_user] += fx.incidence * np.clip((GRAZING_COS - cos_in) / GRAZING_COS, 0.0, 1.0)
    valid &= (u >= p_lost) & (first_owner != _EGO_OWNER)
    if fx.mixed_pixels:
        rng3 = _mixed_pixels(rng3, valid, na, nb, fx.mixed_pixels, rng)
    idx = np.flatnonzero(valid)
    sigma = spec.range_sigma_m if fx.range_sigma_m is None else fx.range_sigma_m
    r = rng3[idx] + rng.standard_normal(len(idx)) * sigma
    bm, cl = beam_of_ray[idx], col_of_ray[idx]
    ce, se = np.cos(tb.el[bm]), np.sin(tb.el[bm])
    pts = np.empty((len(idx), 4), np.float32)
    pts[:, 0] = r * ce * tb.cos_az[cl]
    pts[:, 1] = r * ce * tb.sin_az[cl]
    pts[:, 2] = r * se
    prim_hit = best_prim[idx]
    own = owner_all[prim_hit]
    if fx.intensity == "legacy":
        inten = 255.0 * refl[idx] / (1.0 + (r / 40.0) ** 2) * (1.0 + 0.1 * rng.standard_normal(len(idx)))
    elif fx.intensity == "measured":
        tags = np.append(prims.tag, -1)[prim_hit]
        inten = _measured_intensity(tags, own, fx.intensity_gain, rng)
    else:
        inten = np.zeros(len(idx))
    pts[:, 3] = np.clip(np.round(inten), 0.0, 255.0)
    counts = np.bincount(own[own >= 0], minlength=num_objects) if num_objects else np.zeros(0, np.int64)
    first_obj = first_owner[first_owner >= 0]
    visible = np.bincount(first_obj, minlength=num_objects) if num_objects else np.zeros(0, np.int64)
    return ScanResult(pts, bm.astype(np.int16), own.astype(np.int64), counts.astype(np.int64),
                      visible.astype(np.int64), alone)


def _cos_incidence(prims: Primitives, prim: NDArray[np.int64], rho: F64, el: F64, ca: NDArray[np.float32],
                   sa: NDArray[np.float32]) -> F64:
    """|cos| of the angle between each ray and the normal of the face it meets first: ``prim`` the primitive hit,
    ``rho`` the horizontal distance to the hit, ``el`` / ``ca``, ``sa`` the ray's elevation and azimuth. A hit at
    the primitive's top or bottom height is on a horizontal face (cos = |sin el|); otherwise on a box's side or end
    (the one the hit lies on) or a cylinder's mantle (its radial normal)."""
    px, py, z = rho * ca, rho * sa, rho * np.tan(el)
    horiz = np.abs(np.cos(el))
    z0, z1 = prims.z[prim, 0], prims.z[prim, 1]
    on_flat = (np.abs(z - z1) < 1e-3) | (np.abs(z - z0) < 1e-3)
    dx, dy = px - prims.center[prim, 0], py - prims.center[prim, 1]
    yaw = prims.yaw[prim]
    cy, sy = np.cos(yaw), np.sin(yaw)
    lx, ly = dx * cy + dy * sy, -dx * sy + dy * cy
    end = np.abs(np.abs(lx) - prims.half[prim, 0]) < np.abs(np.abs(ly) - prims.half[prim, 1])
    box_cos = np.where(end, np.abs(ca * cy + sa * sy), np.abs(-ca * sy + sa * cy))
    radial = np.hypot(dx, dy)
    cyl_cos = np.abs(ca * dx + sa * dy) / np.maximum(radial, 1e-9)
    side = np.where(prims.kind[prim] == BOX, box_cos, cyl_cos) * horiz
    return np.where(on_flat, np.abs(np.sin(el)), side)


def _mixed_pixels(rng3: F64, valid: NDArray[np.bool_], na: int, nb: int, fraction: float,
                  rng: np.random.Generator) -> F64:
    """Returns at a depth edge (the next column of the same beam lies ≥ 1 m farther) moved, with probability
    ``fraction``, to a uniform point between the edge and the background: the beam's footprint straddles both
    and the receiver averages them (the "veil" behind real objects)."""
    grid = np.where(valid, rng3, np.inf).reshape(na, nb)
    out = rng3.reshape(na, nb).copy()
    for shift in (1, -1):
        nxt = np.roll(grid, shift, axis=0)
        with np.errstate(invalid="ignore"):
            gap = nxt - grid
        edge = np.isfinite(grid) & (gap > 1.0) & (rng.random((na, nb)) < fraction / 2)
        far = np.where(np.isfinite(nxt), nxt, grid + 5.0)
        out[edge] = grid[edge] + rng.random(int(edge.sum())) * (far[edge] - grid[edge])
    return out.reshape(-1)


def _measured_intensity(tags: NDArray[np.int16], owner: NDArray[np.int64], gain: float,
                        rng: np.random.Generator) -> F64:
    """Intensities drawn from :data:`~jitterguard.sim.effects.MEASURED_INTENSITY` per surface kind (tag −1 =
    ground), times ``gain``; a few returns on road users hit retro-reflectors."""
    med = np.full(len(tags), MEASURED_INTENSITY["ground"][0])
    sd = np.full(len(tags), MEASURED_INTENSITY["ground"][1])
    for tag, kind in _SURFACE_OF_TAG.items():
        m = tags == tag
        med[m], sd[m] = MEASURED_INTENSITY[kind]
    out = med * np.exp(sd * rng.standard_normal(len(tags))) * gain
    bright = (owner >= 0) & (rng.random(len(tags)) < BRIGHT_SPOT_FRACTION)
    out[bright] = rng.uniform(80.0, 255.0, int(bright.sum()))
    return out


def scene_primitives(frame: GroundTruthFrame, spec: LidarSpec, limbs: bool = False, pedal: bool = False
                     ) -> tuple[Primitives, NDArray[np.int64]]:
    """Objects' parts and nearby clutter of ``frame`` in the sensor frame, with their owners (−1 = clutter);
    ``limbs``: pedestrians with legs and arms in the stride of the frame's moment; ``pedal``: cyclists' legs at
    the crank angle of that moment."""
    stamp_s = frame.stamp_ns * 1e-9
    stride = gait_stride(stamp_s, frame.velocities, frame.instance_ids) if limbs else None
    crank = crank_angle(stamp_s, frame.velocities, frame.instance_ids) if pedal else None
    objs, owner = object_primitives(frame.centers, frame.sizes, frame.yaws, frame.labels, frame.attributes,
                                    frame.instance_ids, stride, crank)
    parts = [objs]
    owners = [owner]
    if frame.clutter is not None and len(frame.clutter):
        cl = frame.clutter
        d = np.hypot(cl.center[:, 0] - frame.ego_x, cl.center[:, 1] - frame.ego_y) - cl.footprint_radius()
        cl = cl.subset(d < spec.max_range_m)
        parts.append(cl)
        owners.append(np.full(len(cl), _CLUTTER_OWNER, np.int64))
    prims = to_sensor_frame(Primitives.concat(parts), frame.ego_x, frame.ego_y, frame.ego_yaw, spec.mount_height_m)
    return prims, np.concatenate(owners)


def ego_body(effects: ScanEffects, spec: LidarSpec, rng: np.random.Generator) -> Primitives:
    """The sensor's own roof as a sensor-frame box (x forward): 1.7–2.3 m long, 1.5–1.8 m wide, its top
    0.25–0.45 m below the sensor, the mount 0.2–0.8 m ahead of its centre. Empty unless ``effects.ego_body``."""
    if not effects.ego_body:
        return Primitives.empty()
    length, width = rng.uniform(1.7, 2.3), rng.uniform(1.5, 1.8)
    top = -rng.uniform(0.25, 0.45)
    pl = PrimitiveList()
    pl.box(-rng.uniform(0.2, 0.8), 0.0, length, width, -spec.mount_height_m, top, reflectivity=0.3, tag=Tag.EGO)
    return pl.build()


def cast_frame(frame: GroundTruthFrame, sensor: LidarSpec | None = None, seed: int = 0,
               effects: ScanEffects | None = None, anchor: tuple[float, float, float] | None = None
               ) -> tuple[ScanResult, GroundTruthFrame]:
    """Scan ``frame`` and return the scan plus the frame with ``num_points`` and ray-cast ``visibility`` filled in.

    Visibility = rays whose first hit is the object / rays that would hit it alone (porous crowns and fences
    count as occluding only where they stopped the ray); objects no ray reaches keep their analytic estimate.
    Randomness is seeded by (``seed``, frame seq), so a frame always scans the same. With ``effects`` every
    object and piece of scenery is lifted onto the effects' ground (by the height under its object's centre);
    the lift of each object is in ``ScanResult.object_lift``.

    ``anchor``: the world (x, y, yaw) of the sensor whose frame ``effects`` are drawn in, when that is not this
    frame's — the sweeps of one stack (:func:`~jitterguard.services.detector.data.synthetic_samples` with
    ``sweeps``): every sweep then sees the same ground, street clutter, vegetation and left-out buildings in the
    world, not copies that move with the car. Without it (the default) the effects hang on this frame's sensor,
    as every single-sweep scan has always been cast.
    """
    spec = sensor or hdl32e()
    prims, owner = scene_primitives(frame, spec, limbs=effects is not None and effects.limbs,
                                    pedal=effects is not None and effects.pedal)
    rng = np.random.default_rng([seed, frame.seq])
    lift = np.zeros(frame.num_objects)
    if effects is not None:
        # where this sensor stands in the frame the effects are drawn in (identity without an anchor)
        ax, ay, ayaw = anchor if anchor is not None else (frame.ego_x, frame.ego_y, frame.ego_yaw)
        ca, sa = math.cos(ayaw), math.sin(ayaw)
        px = ca * (frame.ego_x - ax) + sa * (frame.ego_y - ay)
        py = -sa * (frame.ego_x - ax) + ca * (frame.ego_y - ay)
        turn = frame.ego_yaw - ayaw
        here = effects if anchor is None else effects.seen_from(px, py, turn)
        if effects.building_drop > 0:
            if anchor is None:
                u = np.random.default_rng([effects.clutter_seed, 1]).random(len(prims))
            else:  # keyed on where each piece stands in the anchor's frame, so that every sweep drops the same
                back = to_sensor_frame(prims, -(math.cos(turn) * px + math.sin(turn) * py),
                                       -(-math.sin(turn) * px + math.cos(turn) * py), -turn, 0.0)
                u = _position_hash(back.center, effects.clutter_seed)
            drop = (prims.tag == int(Tag.BUILDING)) & (u < effects.building_drop)
            prims, owner = prims.subset(~drop), owner[~drop]
        if (effects.clutter_density > 0 or effects.vegetation_density > 0 or effects.kerb_trees > 0
                or effects.street_objects > 0):
            dx, dy = frame.centers[:, 0] - ax, frame.centers[:, 1] - ay
            keep_out = np.column_stack([ca * dx + sa * dy, -sa * dx + ca * dy, frame.sizes[:, 0] / 2,
                                        frame.sizes[:, 1] / 2, frame.yaws - ayaw])
            parked = keep_out[np.array([a == VEHICLE_PARKED for a in frame.attributes], dtype=bool)]
            # a density or share of 0 draws no piece: each function then returns nothing
            extra = Primitives.concat([street_clutter(effects, keep_out, spec.mount_height_m),
                                       vegetation_masses(effects, keep_out, spec.mount_height_m),
                                       kerbside_trees(effects, keep_out, parked, frame.sizes[:, 2],
                                                      spec.mount_height_m),
                                       street_objects(effects, keep_out, parked, spec.mount_height_m)])
            if anchor is not None:
                extra = to_sensor_frame(extra, px, py, turn, 0.0)
            prims = Primitives.concat([prims, extra])
            owner = np.concatenate([owner, np.full(len(extra), _CLUTTER_OWNER, np.int64)])
        if not here.flat:
            c, s = math.cos(frame.ego_yaw), math.sin(frame.ego_yaw)
            dx, dy = frame.centers[:, 0] - frame.ego_x, frame.centers[:, 1] - frame.ego_y
            lift = here.ground_offset(c * dx + s * dy, -s * dx + c * dy)
            own_lift = np.where(owner >= 0, lift[np.maximum(owner, 0)] if len(lift) else 0.0,
                                here.ground_offset(prims.center[:, 0], prims.center[:, 1]))
            prims = replace(prims, z=prims.z + own_lift[:, None])
        body = ego_body(here, spec, rng)
        prims = Primitives.concat([prims, body])
        owner = np.concatenate([owner, np.full(len(body), _EGO_OWNER, np.int64)])
        effects = here
    if effects is not None and effects.motion:
        res = _cast_moving(frame, prims, owner, spec, rng, effects)
    else:
        res = cast(prims, owner, spec, rng, frame.num_objects, effects=effects)
    if effects is not None:
        res = replace(res, object_lift=lift)
    vis = frame.visibility.copy()
    reached = res.num_rays_alone > 0
    vis[reached] = np.clip(res.num_rays_visible[reached] / res.num_rays_alone[reached], 0.0, 1.0)
    return res, replace(frame, num_points=res.num_points.copy(), visibility=vis, points_counted=True)


def _position_hash(xy: F64, seed: int) -> F64:
    """A uniform number in [0, 1) per footprint centre, the same wherever it is computed from (centres on a
    0.25 m grid): the left-out buildings of the sweeps of one stack agree."""
    cell = np.round(np.asarray(xy, np.float64) / 0.25).astype(np.int64)
    h = (cell[:, 0] * 73856093) ^ (cell[:, 1] * 19349663) ^ (int(seed) * 83492791)
    h = (h ^ (h >> 13)) * 1274126177
    h = h ^ (h >> 16)
    return (h & 0xFFFFFF).astype(np.float64) / float(0x1000000)


MOTION_SECTORS = 12
"""Azimuth sectors a sweep with motion is cast in (each at its own moment: 4.2 ms apart at 20 Hz)."""


def _cast_moving(frame: GroundTruthFrame, prims: Primitives, owner: NDArray[np.int64], spec: LidarSpec,
                 rng: np.random.Generator, effects: ScanEffects) -> ScanResult:
    """One turn cast sector by sector, each with the scene where it was when the beams swept it (see
    :attr:`~jitterguard.sim.effects.ScanEffects.motion`), reported in the sensor frame at the end of the turn."""
    period = 1.0 / spec.rate_hz
    c, s = math.cos(frame.ego_yaw), math.sin(frame.ego_yaw)
    v_obj = np.column_stack([c * frame.velocities[:, 0] + s * frame.velocities[:, 1],
                             -s * frame.velocities[:, 0] + c * frame.velocities[:, 1]]) if frame.num_objects \
        else np.zeros((0, 2))
    v_prim = np.zeros((len(prims), 2))
    is_obj = owner >= 0
    v_prim[is_obj] = v_obj[owner[is_obj]]
    v_prim[owner == _EGO_OWNER] = frame.ego_speed, 0.0  # the roof moves with the sensor
    az = azimuths(spec)
    phase = ((az - effects.sweep_start) % (2 * math.pi)) / (2 * math.pi)  # 0 at the start of the turn … 1 at its end
    sector = np.minimum((phase * MOTION_SECTORS).astype(np.int64), MOTION_SECTORS - 1)
    parts: list[ScanResult] = []
    for k in range(MOTION_SECTORS):
        lag = period * (1.0 - (k + 0.5) / MOTION_SECTORS)  # how long before the end of the turn
        shift = np.column_stack([np.full(len(prims), frame.ego_speed * lag), np.zeros(len(prims))]) - v_prim * lag
        moved = replace(prims, center=prims.center + shift)
        parts.append(cast(moved, owner, spec, rng, frame.num_objects, effects=effects, columns=sector == k))
    return ScanResult(
        np.concatenate([p.points for p in parts]), np.concatenate([p.ring for p in parts]),
        np.concatenate([p.owner for p in parts]), sum(p.num_points for p in parts),
        sum(p.num_rays_visible for p in parts), sum(p.num_rays_alone for p in parts))


def scan(frame: GroundTruthFrame, sensor: LidarSpec | None = None, seed: int = 0) -> F32:
    """(P, 4) float32 x, y, z, intensity in the sensor frame: one full turn of ``sensor`` (HDL-32E by default)."""
    return cast_frame(frame, sensor, seed)[0].points
