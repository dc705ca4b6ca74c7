"""Scan effects (sim-to-real): uneven ground, objects standing on it, glass, dropout, intensity, clutter."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import pytest

from jitterguard.schemas import Label
from jitterguard.sim import GroundTruthFrame, make_scenario
from jitterguard.sim.effects import (COMPONENTS, MEASURED_INTENSITY, ScanEffects, draw_effects, street_clutter,
                                     vegetation_masses)
from jitterguard.sim.layout import rectangles_overlap
from jitterguard.sim.lidar import cast_frame, terrain_rho
from jitterguard.sim.sensors import hdl32e
from jitterguard.sim.world import BASE_STAMP_NS


def cars_frame(xy: list[tuple[float, float]]) -> GroundTruthFrame:
    n = len(xy)
    return GroundTruthFrame(
        seq=0, stamp_ns=BASE_STAMP_NS, ego_x=0.0, ego_y=0.0, ego_yaw=0.0,
        instance_ids=np.arange(1, n + 1, dtype=np.int64), labels=np.full(n, int(Label.CAR)),
        centers=np.array([(x, y, 0.85) for x, y in xy]).reshape(-1, 3), sizes=np.tile([4.6, 1.9, 1.7], (n, 1)),
        yaws=np.zeros(n), velocities=np.zeros((n, 2)), moving=np.zeros(n, bool),
        attributes=("vehicle.parked",) * n, visibility=np.ones(n), num_points=np.zeros(n, np.int64))


def assert_opt_in(component: str, field: str, lo: float, hi: float, base: str = "random",
                  seeds: Sequence[int] = range(10)) -> None:
    """``random`` leaves ``component`` out; switched on (over ``base``) it draws ``field`` in [lo, hi], 0 when off,
    and changes no other draw — so the scans of every recipe written before it are cast as they were."""
    from jitterguard.sim.effects import parse_components

    assert component not in parse_components("random")
    for seed in seeds:
        plain = draw_effects(np.random.default_rng(seed), parse_components(base))
        on = draw_effects(np.random.default_rng(seed), parse_components(f"{base},{component}"))
        assert getattr(plain, field) == 0.0 and lo <= getattr(on, field) <= hi
        assert on == ScanEffects(**{**plain.__dict__, field: getattr(on, field)})


def test_defaults_leave_the_ideal_scan_unchanged() -> None:
    f = make_scenario("parking-street", 2, duration_s=1.0).frame(4)
    a, _ = cast_frame(f, seed=1)
    b, _ = cast_frame(f, seed=1, effects=ScanEffects())
    np.testing.assert_array_equal(a.points, b.points)
    assert a.object_lift is None and b.object_lift is not None and not b.object_lift.any()


def test_rays_meet_a_tilted_ground_where_the_plane_says() -> None:
    spec = hdl32e()
    fx = ScanEffects(mount_offset_m=0.1, tilt=(0.03, -0.02))
    rho = terrain_rho(spec, fx).reshape(spec.azimuth_steps, spec.num_beams)
    az = -math.pi + (np.arange(spec.azimuth_steps) + 0.5) * 2 * math.pi / spec.azimuth_steps
    tan_el = np.tan(spec.elevations)
    # ray height rho·tan(el) = -H + 0.1 + 0.03·x + (-0.02)·y with x = rho cos az, y = rho sin az
    slope = 0.03 * np.cos(az)[:, None] - 0.02 * np.sin(az)[:, None]
    exact = (-spec.mount_height_m + 0.1) / (tan_el[None, :] - slope)
    ok = np.isfinite(rho)
    assert ok[:, :15].all()  # the steep beams all reach the ground
    np.testing.assert_allclose(rho[ok], exact[ok], rtol=1e-6)
    assert not ok[:, -5:].any()  # upward beams never do


def test_uneven_ground_moves_the_returns_and_lifts_the_objects() -> None:
    f = cars_frame([(20.0, 0.0), (-15.0, 8.0)])
    fx = ScanEffects(curvature=(2e-3, 0.0, 0.0))  # the road rises ahead and behind: +0.4 m at 20 m
    res, _ = cast_frame(f, hdl32e(), seed=0, effects=fx)
    np.testing.assert_allclose(res.object_lift, [0.4, 0.225], rtol=1e-9)
    ground = res.points[res.owner == -2]
    far = ground[np.abs(ground[:, 0]) > 15]
    x = far[:, 0].astype(np.float64)
    np.testing.assert_allclose(far[:, 2], -1.84 + 1e-3 * x ** 2, atol=0.1)  # range noise only
    car = res.points[res.owner == 0]
    assert car[:, 2].min() > -1.84 + 0.4 - 0.15  # the car stands on the raised road


def test_glass_dropout_and_the_roof_thin_the_returns() -> None:
    f = cars_frame([(10.0, 4.0)])
    ideal, _ = cast_frame(f, seed=3, effects=ScanEffects())
    glass, _ = cast_frame(f, seed=3, effects=ScanEffects(glass_pass=1.0))
    dark, _ = cast_frame(f, seed=3, effects=ScanEffects(object_dropout=0.5))
    n0, ng, nd = (int(r.num_points[0]) for r in (ideal, glass, dark))
    assert ng < 0.85 * n0 and nd == pytest.approx(0.5 * n0, rel=0.15)
    z_top = ideal.points[ideal.owner == 0][:, 2].max()
    assert glass.points[glass.owner == 0][:, 2].max() < z_top - 0.3  # no returns from the cabin
    roof, _ = cast_frame(f, seed=3, effects=ScanEffects(ego_body=True))
    near = lambda r: int((np.hypot(r.points[:, 0], r.points[:, 1]) < 3.5).sum())  # noqa: E731
    assert near(roof) < 0.8 * near(ideal)


def test_measured_intensities_follow_the_surface_medians() -> None:
    f = cars_frame([(8.0, 3.0), (-9.0, -4.0)])
    res, _ = cast_frame(f, seed=5, effects=ScanEffects(intensity="measured"))
    ground = res.points[res.owner == -2, 3]
    car = res.points[res.owner >= 0, 3]
    assert np.median(ground) == pytest.approx(MEASURED_INTENSITY["ground"][0], rel=0.15)
    assert np.median(car) < 8 and np.percentile(car, 99) > 80  # dark paint, a few reflectors
    none, _ = cast_frame(f, seed=5, effects=ScanEffects(intensity="none"))
    assert not none.points[:, 3].any()


def test_street_clutter_keeps_off_the_road_users_and_the_ego() -> None:
    keep_out = np.array([[10.0, 5.0, 2.3, 1.0, 0.3], [-12.0, -6.0, 2.3, 1.0, -0.2]])
    for seed in range(5):
        prims = street_clutter(ScanEffects(clutter_density=2.0, clutter_seed=seed), keep_out, 1.84)
        assert len(prims) > 20
        assert np.all(prims.z[:, 0] == pytest.approx(-1.84))
        for x, y, hl, hw, _ in keep_out:
            d = np.hypot(prims.center[:, 0] - x, prims.center[:, 1] - y)
            assert np.all(d > min(hl, hw))  # nothing inside a car's footprint


def _crossing_the_ego(prims) -> list[int]:
    """Primitives whose footprint overlaps the ego car (4.7 × 1.9 m under the sensor)."""
    ego = np.array([0.0, 0.0, 2.35, 0.95, 0.0])
    return [i for i in range(len(prims))
            if rectangles_overlap(np.array([*prims.center[i], *prims.half[i], prims.yaw[i]]), ego)]


def test_street_clutter_and_vegetation_never_cross_the_ego_car() -> None:
    """Each piece is tested whole against the ego: seed 46 anchored a 13 m wall off the ego's spot that ran
    through the car, and a turned vegetation mass passed the axis-aligned margin onto it (clutter seed 191)."""
    fx = draw_effects(np.random.default_rng(46))
    clutter = street_clutter(fx, np.zeros((0, 5)), 1.84)
    assert len(clutter) > 20 and not _crossing_the_ego(clutter)
    veg = vegetation_masses(ScanEffects(vegetation_density=0.5, clutter_seed=191), np.zeros((0, 5)), 1.84)
    assert len(veg) > 100 and not _crossing_the_ego(veg)
    for seed in range(40):
        fx = draw_effects(np.random.default_rng(seed), (*COMPONENTS, "vegetation"))
        assert not _crossing_the_ego(street_clutter(fx, np.zeros((0, 5)), 1.84))
        assert not _crossing_the_ego(vegetation_masses(fx, np.zeros((0, 5)), 1.84))


def test_vegetation_is_opt_in_keeps_the_other_draws_and_returns_from_several_depths() -> None:
    """``random`` leaves vegetation out (the scans of earlier recipes are cast as they were); switched on it
    changes no other draw; its masses keep off the road users and return from inside the mass, not one face."""
    from jitterguard.sim.effects import parse_components, vegetation_masses

    assert "vegetation" in parse_components("random,vegetation")
    assert_opt_in("vegetation", "vegetation_density", 0.1, 0.5, seeds=(4,))
    keep_out = np.array([[10.0, 5.0, 2.3, 1.0, 0.3], [-12.0, -6.0, 2.3, 1.0, -0.2]])
    for seed in range(5):
        prims = vegetation_masses(ScanEffects(vegetation_density=1.0, clutter_seed=seed), keep_out, 1.84)
        assert len(prims) > 40 and np.all(prims.z[:, 1] - prims.z[:, 0] >= 0.4)
        for x, y, hl, hw, _ in keep_out:
            assert np.all(np.hypot(prims.center[:, 0] - x, prims.center[:, 1] - y) > min(hl, hw))
    # one mass in front of the sensor: its returns spread in range over more than a blob's size
    f = cars_frame([(-20.0, -10.0)])
    fx = ScanEffects(vegetation_density=1.0, clutter_seed=3)
    res, _ = cast_frame(f, seed=0, effects=fx)
    off_ground = res.points[(res.owner < 0) & (res.points[:, 2] > -1.84 + 0.3)]
    assert len(off_ground) > 200  # the ideal scan of this frame has no scenery at all
    rng_ = np.hypot(off_ground[:, 0], off_ground[:, 1])
    az = np.round(np.degrees(np.arctan2(off_ground[:, 1], off_ground[:, 0])))
    spreads = [np.ptp(rng_[az == a]) for a in np.unique(az) if (az == a).sum() >= 5]
    assert np.median(spreads) > 0.5


def test_clear_glass_is_opt_in_and_keeps_the_other_draws() -> None:
    """``clear-glass`` draws the glass's pass-through from 85–100 % (``glass``: 50–95 %) and changes no other draw,
    so the scans of earlier recipes are cast as they were (what glass that passes every ray does to a car's
    returns: ``test_glass_dropout_and_the_roof_thin_the_returns`` above)."""
    from jitterguard.sim.effects import parse_components

    assert "clear-glass" not in parse_components("random")
    for seed in range(20):
        plain = draw_effects(np.random.default_rng(seed), parse_components("random"))
        clear = draw_effects(np.random.default_rng(seed), parse_components("random,clear-glass"))
        assert 0.85 <= clear.glass_pass <= 1.0 and 0.5 <= plain.glass_pass <= 0.95
        assert clear == ScanEffects(**{**plain.__dict__, "glass_pass": clear.glass_pass})


def test_drawn_effects_are_seeded_and_within_their_ranges() -> None:
    a = draw_effects(np.random.default_rng(9))
    assert a == draw_effects(np.random.default_rng(9)) and a != draw_effects(np.random.default_rng(10))
    for s in range(30):
        fx = draw_effects(np.random.default_rng(s))
        assert 0.5 <= fx.glass_pass <= 0.95 and 0.2 <= fx.object_dropout <= 0.55
        assert abs(fx.ground_offset(np.array([0.0]), np.array([0.0]))[0]) < 0.6
    with pytest.raises(ValueError, match="intensity"):
        ScanEffects(intensity="bright")


def test_components_switch_effects_on_one_at_a_time_with_the_same_draws() -> None:
    from jitterguard.sim.effects import COMPONENTS, parse_components

    assert parse_components("random") == tuple(sorted(COMPONENTS)) and parse_components("none") == ()
    assert parse_components("glass, ground") == ("glass", "ground")
    assert "intensity" not in parse_components("random,no-intensity")
    with pytest.raises(ValueError, match="moon"):
        parse_components("ground,moon")
    full = draw_effects(np.random.default_rng(4))
    glass = draw_effects(np.random.default_rng(4), ("glass",))
    assert glass.glass_pass == full.glass_pass and glass.flat and glass.object_dropout == 0.0
    assert glass.intensity == "legacy" and glass.clutter_density == 0.0 and not glass.ego_body
    ground = draw_effects(np.random.default_rng(4), ("ground",))
    assert ground.tilt == full.tilt and ground.glass_pass == 0.0
    assert draw_effects(np.random.default_rng(4), ("no-intensity",)).intensity == "none"


def test_motion_within_the_sweep_smears_the_static_world_by_when_it_was_swept() -> None:
    """A wall 10 m ahead, the ego at 10 m/s: swept at the start of the 50 ms turn it shows up ≈ 0.48 m too far
    ahead (the sensor was that far behind, and nothing de-skews), swept at the end ≈ 0.02 m."""
    from dataclasses import replace

    from jitterguard.sim.primitives import PrimitiveList

    wall = PrimitiveList()
    wall.box(10.0, 0.0, 0.2, 6.0, -1.8, 1.0, reflectivity=0.9)
    f = replace(cars_frame([]), ego_speed=10.0, clutter=wall.build())
    spec = replace(hdl32e(), range_sigma_m=0.0)
    x_face = 9.9
    early, _ = cast_frame(f, spec, seed=0, effects=ScanEffects(motion=True, sweep_start=-0.3))
    late, _ = cast_frame(f, spec, seed=0, effects=ScanEffects(motion=True, sweep_start=0.3))
    still, _ = cast_frame(f, spec, seed=0, effects=ScanEffects())
    on = lambda r: r.points[r.owner == -1]  # noqa: E731
    assert np.median(on(still)[:, 0]) == pytest.approx(x_face, abs=0.01)
    assert np.median(on(early)[:, 0]) - x_face == pytest.approx(10.0 * 0.05 * (1 - 0.5 / 12), abs=0.03)
    assert np.median(on(late)[:, 0]) - x_face == pytest.approx(10.0 * 0.05 * 0.5 / 12, abs=0.03)
    assert len(on(early)) == pytest.approx(len(on(still)), rel=0.05)


# ------------------------------------------------------------------------- sweeps of one stack: one world


def test_effects_seen_from_another_sensor_describe_the_same_ground() -> None:
    fx = ScanEffects(mount_offset_m=0.05, tilt=(0.01, -0.02), curvature=(0.001, -0.002, 0.0005),
                     undulation=((0.1, 0.3, 0.2, 1.0), (0.05, -0.1, 0.4, 0.3)))
    x, y, yaw = 3.0, -1.5, 0.4
    moved = fx.seen_from(x, y, yaw)
    u = np.random.default_rng(0).uniform(-30, 30, (200, 2))
    c, s = math.cos(yaw), math.sin(yaw)
    q = u @ np.array([[c, -s], [s, c]]).T + [x, y]  # the same places in the first sensor's frame
    np.testing.assert_allclose(moved.ground_offset(u[:, 0], u[:, 1]), fx.ground_offset(q[:, 0], q[:, 1]), atol=1e-12)
    assert fx.seen_from(0.0, 0.0, 0.0) == fx


def test_anchored_sweeps_see_one_ground_and_one_street_furniture() -> None:
    """Two frames 0.5 s apart of a driving ego, cast with the same effects: anchored on the newer sensor, the
    older sweep's ground and clutter land where the newer one has them once moved into its frame; hung on each
    sensor (no anchor), they move with the car."""
    from scipy.spatial import cKDTree

    from jitterguard.services.detector.data import _sensor_pose
    from jitterguard.services.detector.sweeps import relative_transform
    from jitterguard.sim.sensors import hdl32e
    from jitterguard.sim.world import make_scenario

    spec = hdl32e()
    sc = make_scenario("mixed", 3, 20.0, 20.0)
    new, old = sc.frame(110), sc.frame(100)
    assert math.hypot(new.ego_x - old.ego_x, new.ego_y - old.ego_y) > 1.0  # the ego moved
    fx = ScanEffects(tilt=(0.03, -0.02), curvature=(0.002, 0.0, 0.0), clutter_density=0.4, clutter_seed=11,
                     building_drop=0.5)
    anchor = (new.ego_x, new.ego_y, new.ego_yaw)
    newest, _ = cast_frame(new, spec, 0, effects=fx, anchor=anchor)
    rot, trans = relative_transform(*_sensor_pose(new, spec), *_sensor_pose(old, spec))
    furniture = cKDTree(newest.points[newest.owner == -1, :3])
    out = {}
    for name, a in (("anchored", anchor), ("hung", None)):
        scan, _ = cast_frame(old, spec, 0, effects=fx, anchor=a)
        xyz = scan.points[:, :3].astype(np.float64) @ rot.T + trans
        g = scan.owner == -2
        dz = np.abs(xyz[g, 2] - (fx.ground_offset(xyz[g, 0], xyz[g, 1]) - spec.mount_height_m))
        out[name] = (np.percentile(dz, 90), np.percentile(furniture.query(xyz[scan.owner == -1])[0], 90))
    assert out["anchored"][0] < 0.02 < 0.04 < out["hung"][0]
    assert out["anchored"][1] < 1.0 < 2.0 < out["hung"][1]


def test_kerb_trees_are_opt_in_and_stand_beside_the_parked_cars_with_their_crowns_over_them() -> None:
    """``kerb-trees`` changes no other draw; each tree stands beside a long side of a parked car, off every road user
    and the ego, and what of its porous crown is over the car clears the car's roof; in the cast scan the crowns
    return around the car and the car keeps most of its returns."""
    from jitterguard.sim.effects import kerbside_trees
    from jitterguard.sim.primitives import Tag

    assert_opt_in("kerb-trees", "kerb_trees", 0.2, 0.7)
    parked = np.array([[12.0, 6.0, 2.3, 0.95, 0.0], [-9.0, -6.0, 2.3, 0.95, 0.1], [4.0, -7.0, 2.3, 0.95, 1.5]])
    fx = ScanEffects(kerb_trees=1.0, clutter_seed=5)
    prims = kerbside_trees(fx, parked, parked, np.full(len(parked), 1.7), 1.84)
    trunks = prims.tag == int(Tag.POLE)
    crowns = prims.tag == int(Tag.TREE_CROWN)
    assert trunks.sum() >= 2 and crowns.sum() >= 10
    for i in np.flatnonzero(crowns):  # a blob over a car starts above its roof (1.7 m)
        blob = np.array([*prims.center[i], *prims.half[i], prims.yaw[i]])
        if any(rectangles_overlap(blob, car) for car in parked):
            assert prims.z[i, 0] >= -1.84 + 1.7
    sides = set()
    for tx, ty in prims.center[trunks]:
        d = np.hypot(parked[:, 0] - tx, parked[:, 1] - ty)
        x, y, hl, hw, yaw = parked[int(np.argmin(d))]
        lx = np.cos(yaw) * (tx - x) + np.sin(yaw) * (ty - y)
        ly = -np.sin(yaw) * (tx - x) + np.cos(yaw) * (ty - y)
        sides.add(bool(ly * np.sign(-np.sin(yaw) * x + np.cos(yaw) * y) > 0))  # away from the sensor or towards it
        assert abs(lx) <= hl + 1e-9 and hw < abs(ly) <= hw + 2.0 + 1e-9  # beside it
    assert not _crossing_the_ego(prims)
    for seed in range(6, 16):  # trees on both sides: the kerb's, and the one towards the sensor (a median, a verge)
        more = kerbside_trees(ScanEffects(kerb_trees=1.0, clutter_seed=seed), parked, parked,
                              np.full(len(parked), 1.7), 1.84)
        for tx, ty in more.center[more.tag == int(Tag.POLE)]:
            x, y, _, _, yaw = parked[int(np.argmin(np.hypot(parked[:, 0] - tx, parked[:, 1] - ty)))]
            ly = -np.sin(yaw) * (tx - x) + np.cos(yaw) * (ty - y)
            sides.add(bool(ly * np.sign(-np.sin(yaw) * x + np.cos(yaw) * y) > 0))
    assert sides == {True, False}
    f = cars_frame([(12.0, 6.0)])
    bare, _ = cast_frame(f, seed=0, effects=ScanEffects(clutter_seed=5))
    treed, _ = cast_frame(f, seed=0, effects=fx)
    canopy = treed.points[(treed.owner < 0) & (treed.points[:, 2] > -1.84 + 2.3)]
    assert len(canopy) > 30 and np.median(np.hypot(canopy[:, 0] - 12.0, canopy[:, 1] - 6.0)) < 5.0
    assert (treed.owner == 0).sum() >= 0.8 * (bare.owner == 0).sum()


def test_street_objects_are_opt_in_person_sized_off_the_road_users_and_half_beside_parked_cars() -> None:
    """``street-objects`` changes no other draw; its cones, piles, bins and boards stand on the ground, 0.7–1.8 m
    tall and at most 1.8 m across — a person's size — never on a road user or the ego car, about half of them within
    2.5 m of a parked car's side; in the cast scan they return, as no road user."""
    from jitterguard.sim.effects import street_objects

    assert_opt_in("street-objects", "street_objects", 0.1, 0.4, base="random,vegetation")
    parked = np.array([[12.0, 6.0, 2.3, 0.95, 0.0], [-9.0, -6.0, 2.3, 0.95, 0.1], [4.0, -7.0, 2.3, 0.95, 1.5]])
    near = total = 0
    for seed in range(20):
        prims = street_objects(ScanEffects(street_objects=0.4, clutter_seed=seed), parked, parked, 1.84)
        assert not _crossing_the_ego(prims)
        for i in range(len(prims)):
            piece = np.array([*prims.center[i], *prims.half[i], prims.yaw[i]])
            assert not any(rectangles_overlap(piece, car) for car in parked)
        assert np.all(prims.z[:, 0] >= -1.84 - 1e-9) and np.all(prims.z[:, 1] <= -1.84 + 1.8 + 1e-9)
        assert np.all(prims.half.max(1) <= 0.9 + 1e-9)
        objects = {(round(x, 3), round(y, 3)) for x, y in prims.center[prims.z[:, 0] <= -1.84 + 1e-9]}
        for x, y in objects:  # one per object: the pieces that stand on the ground (a pile's lumps may share one)
            total += 1
            near += bool(np.min(np.hypot(parked[:, 0] - x, parked[:, 1] - y)) < 2.3 + 2.5)
    assert total > 100 and 0.3 < near / total < 0.8
    assert not street_objects(ScanEffects(clutter_seed=3), parked, parked, 1.84).center.size  # density 0: nothing
    f = cars_frame([(12.0, 6.0), (-9.0, -6.0)])
    fx = ScanEffects(street_objects=0.4, clutter_seed=4)
    bare, _ = cast_frame(f, seed=0, effects=ScanEffects(clutter_seed=4))
    seen, _ = cast_frame(f, seed=0, effects=fx)
    cars = np.column_stack([f.centers[:, :2], f.sizes[:, :2] / 2, f.yaws])  # both parked, the ego at the origin
    prims = street_objects(fx, cars, cars, 1.84)  # what cast_frame placed
    extra = seen.points[seen.owner < 0]
    assert len(extra) > len(bare.points[bare.owner < 0]) + 20
    hits = np.min(np.hypot(extra[:, None, 0] - prims.center[None, :, 0], extra[:, None, 1] - prims.center[None, :, 1]),
                  axis=1) < 0.5
    assert hits.sum() > 20 and np.all(extra[hits, 2] < -1.84 + 1.9)


def test_incidence_loses_the_grazing_returns_of_road_users_only_and_is_opt_in() -> None:
    """With ``incidence`` a road user's return is lost where the ray grazes its surface: a car seen from its end keeps
    the returns of the end the sensor faces and loses those of its side along the line of sight (and of its roof),
    a car beside the sensor keeps its side, the ground keeps every return; the draw is opt-in and changes no other."""

    f = cars_frame([(15.0, 2.0), (0.0, 8.0)])  # the first seen from behind, the second broadside
    ideal, _ = cast_frame(f, seed=4, effects=ScanEffects())
    graze, _ = cast_frame(f, seed=4, effects=ScanEffects(incidence=1.0))
    end_on = lambda r: r.points[r.owner == 0]  # noqa: E731
    rear = lambda p: int((p[:, 0] < 12.7 + 0.3).sum())  # noqa: E731
    side = lambda p: int((p[:, 0] > 13.5).sum())  # noqa: E731  its flank and roof, met at 5–9°
    assert side(end_on(ideal)) >= 15 and side(end_on(graze)) < 0.5 * side(end_on(ideal))
    assert rear(end_on(graze)) >= 0.9 * rear(end_on(ideal))
    assert int(graze.num_points[1]) >= 0.9 * int(ideal.num_points[1])
    ground = lambda r: int((r.owner == -2).sum())  # noqa: E731
    assert ground(graze) == ground(ideal)
    assert_opt_in("incidence", "incidence", 0.5, 1.0, base="random,vegetation")
