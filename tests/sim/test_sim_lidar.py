"""The ray-cast LiDAR: real beam tables, geometry of the returns, sensor effects, occlusion and point counts."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from jitterguard.schemas import Label
from jitterguard.sim import GroundTruthFrame, SENSOR_HEIGHT_M, make_scenario
from helpers import iter_scans
from jitterguard.sim.lidar import cast, cast_frame, scan
from jitterguard.sim.primitives import PrimitiveList
from jitterguard.sim.sensors import hdl32e, os1_64, vlp16
from jitterguard.sim.shapes import TEMPLATES, object_primitives
from jitterguard.sim.world import BASE_STAMP_NS


def cars_frame(xy: list[tuple[float, float]], yaw: float = 0.0, seq: int = 0) -> GroundTruthFrame:
    """Parked cars at sensor-frame positions (the ego sits at the world origin facing +x), no clutter."""
    n = len(xy)
    return GroundTruthFrame(
        seq=seq, stamp_ns=BASE_STAMP_NS, ego_x=0.0, ego_y=0.0, ego_yaw=0.0,
        instance_ids=np.arange(1, n + 1, dtype=np.int64), labels=np.full(n, int(Label.CAR)),
        centers=np.array([(x, y, 0.85) for x, y in xy]).reshape(-1, 3), sizes=np.tile([4.6, 1.9, 1.7], (n, 1)),
        yaws=np.full(n, yaw), velocities=np.zeros((n, 2)), moving=np.zeros(n, bool),
        attributes=("vehicle.parked",) * n, visibility=np.ones(n), num_points=np.zeros(n, np.int64))


def test_beam_tables_match_the_data_sheets() -> None:
    h = hdl32e()
    assert h.num_beams == 32 and h.azimuth_steps == 1085 and h.rate_hz == 20.0 and h.range_sigma_m == 0.02
    assert h.elevations_deg[0] == pytest.approx(-30.67) and h.elevations_deg[-1] == pytest.approx(10.67)
    assert np.allclose(np.diff(h.elevations_deg), 1.3329, atol=1e-3)
    v = vlp16()
    assert v.num_beams == 16 and np.allclose(v.elevations_deg, np.arange(-15, 16, 2))
    o = os1_64()
    assert o.num_beams == 64 and o.elevations_deg[0] == pytest.approx(-22.5) and o.elevations_deg[-1] == 22.5


@pytest.mark.parametrize("sensor", [hdl32e(), vlp16(), os1_64()], ids=lambda s: s.name)
def test_every_return_lies_on_its_beam(sensor) -> None:
    f = cars_frame([(8.0, 4.0), (-12.0, -5.0), (3.0, -20.0)])
    res, _ = cast_frame(f, sensor, seed=1)
    p = res.points.astype(np.float64)
    assert p.dtype == np.float64 and res.points.dtype == np.float32 and res.points.shape[1] == 4
    assert 0 < len(p) <= sensor.num_rays
    elev = np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1]))
    r = np.linalg.norm(p[:, :3], axis=1)
    slack = 4 * sensor.range_sigma_m / np.maximum(r, 1.0) + 1e-4  # noise moves points along the beam only
    assert np.all(np.abs(elev - sensor.elevations[res.ring]) < slack)
    assert np.all((r >= sensor.min_range_m - 0.1) & (r <= sensor.max_range_m + 0.1))
    assert np.all((p[:, 3] >= 0) & (p[:, 3] <= 255))
    assert set(np.unique(res.ring)) <= set(range(sensor.num_beams))


def test_flat_ground_and_range_noise() -> None:
    res, _ = cast_frame(cars_frame([]), hdl32e(), seed=2)
    p = res.points
    assert np.all(res.owner == -2)  # nothing but ground
    # downward beams only; ground at the mount height below the sensor, ±2 cm range noise
    assert np.all(res.ring < 23)
    z_err = p[:, 2] + SENSOR_HEIGHT_M
    r = np.linalg.norm(p[:, :3], axis=1)
    scaled = z_err / (np.abs(p[:, 2]) / r)  # back to the range axis
    assert np.std(scaled) == pytest.approx(0.02, rel=0.1)
    assert abs(np.mean(scaled)) < 0.002


def test_wall_beyond_max_range_returns_nothing_and_dropout_thins_returns() -> None:
    spec = hdl32e()
    far, near = PrimitiveList(), PrimitiveList()
    far.box(150.0, 0.0, 1.0, 60.0, -1.0, 10.0, reflectivity=0.9)
    near.box(10.0, 0.0, 0.2, 30.0, -1.8, 8.0, reflectivity=0.9)
    res = cast(far.build(), np.array([-1]), spec, np.random.default_rng(0), 0, with_ground=False)
    assert len(res.points) == 0
    no_drop = cast(near.build(), np.array([-1]), replace(spec, dropout=0.0), np.random.default_rng(0), 0,
                   with_ground=False)
    half_drop = cast(near.build(), np.array([-1]), replace(spec, dropout=0.5), np.random.default_rng(0), 0,
                     with_ground=False)
    assert len(half_drop.points) / len(no_drop.points) == pytest.approx(0.5, abs=0.03)
    x = no_drop.points[:, 0]
    assert np.all(np.abs(x - 9.9) < 0.1)  # the wall's near face


def test_returns_on_an_object_lie_inside_its_box_and_are_counted() -> None:
    f = cars_frame([(7.0, 3.0), (-6.0, -4.0)], yaw=0.4)
    res, g = cast_frame(f, hdl32e(), seed=3)
    for k in range(2):
        pts = res.points[res.owner == k].astype(np.float64)
        assert len(pts) == g.num_points[k] > 100
        c, s = math.cos(g.yaws[k]), math.sin(g.yaws[k])
        dx, dy = pts[:, 0] - g.centers[k, 0], pts[:, 1] - g.centers[k, 1]
        lx, ly = c * dx + s * dy, -s * dx + c * dy
        z = pts[:, 2] + SENSOR_HEIGHT_M
        tol = 0.1
        assert np.all(np.abs(lx) <= g.sizes[k, 0] / 2 + tol) and np.all(np.abs(ly) <= g.sizes[k, 1] / 2 + tol)
        assert np.all((z >= -tol) & (z <= g.sizes[k, 2] + tol))
    assert np.all(g.visibility > 0.9)


def test_occlusion_lowers_point_counts_and_visibility() -> None:
    alone, ga = cast_frame(cars_frame([(16.0, 0.0)]), hdl32e(), seed=4)
    behind, gb = cast_frame(cars_frame([(8.0, 0.5), (16.0, 0.0)]), hdl32e(), seed=4)
    assert gb.num_points[1] < 0.3 * ga.num_points[0]
    assert gb.visibility[1] < 0.3 < 0.9 < ga.visibility[0]
    assert gb.num_points[0] > ga.num_points[0]  # nearer means more points


def test_templates_stay_inside_the_unit_box() -> None:
    for key, t in TEMPLATES.items():
        for kind, cx, cy, z0, z1, hl, hw, _ in t:
            assert 0.0 <= z0 < z1 <= 1.0, key
            if kind == 0:
                assert abs(cx) + hl <= 0.5 + 1e-9 and abs(cy) + hw <= 0.5 + 1e-9, key
            else:  # a cylinder's radius is a fraction of the width
                assert abs(cy) + hl <= 0.5 + 1e-9, key
    prims, owner = object_primitives(np.array([[0.0, 0.0, 0.85]]), np.array([[4.6, 1.9, 1.7]]), np.zeros(1),
                                     np.array([Label.CAR]), ("vehicle.parked",), np.array([1]))
    assert len(prims) == len(TEMPLATES["car"]) and np.all(owner == 0)


def test_scans_are_deterministic_per_seed_and_frame() -> None:
    sc = make_scenario("parking-street", 1, duration_s=1.0)
    f = sc.frame(3)
    a, b, c = scan(f, seed=5), scan(f, seed=5), scan(f, seed=6)
    np.testing.assert_array_equal(a, b)
    assert len(a) != len(c) or not np.array_equal(a, c)


def test_scenario_scans_fill_point_counts_and_see_clutter() -> None:
    sc = make_scenario("intersection", 3, duration_s=0.3)
    out = list(iter_scans(sc, hdl32e(), seed=0))
    assert len(out) == sc.num_frames
    for frame, res in out:
        assert frame.num_points.sum() == int(np.sum(res.owner >= 0))
        assert np.any(res.owner == -1) and np.any(res.owner == -2)  # clutter and ground
        hit = frame.num_points > 0
        assert hit.sum() > 5 and np.all(frame.visibility[hit] > 0)
        assert 20_000 < len(res.points) <= hdl32e().num_rays


def test_only_the_faces_turned_to_the_sensor_are_hit() -> None:
    """An axis-aligned box at (10, 6): the sensor sees its -x and -y faces, never its +x or +y faces."""
    prims = PrimitiveList()
    prims.box(10.0, 6.0, 4.0, 2.0, -1.8, 0.0, reflectivity=0.9)  # x 8..12, y 5..7; no range noise below
    spec = replace(hdl32e(), range_sigma_m=0.0)
    res = cast(prims.build(), np.array([-1]), spec, np.random.default_rng(0), 0, with_ground=False)
    p = res.points[:, :3].astype(np.float64)
    assert len(p) > 50
    on_near_x = np.abs(p[:, 0] - 8.0) < 0.1
    on_near_y = np.abs(p[:, 1] - 5.0) < 0.1
    assert np.all(on_near_x | on_near_y)
    assert on_near_x.sum() > 10 and on_near_y.sum() > 10
    # nothing from the far faces' interiors (points there would be off both near faces)
    assert not np.any((np.abs(p[:, 0] - 12.0) < 0.05) & (p[:, 1] > 5.1))
    assert not np.any((np.abs(p[:, 1] - 7.0) < 0.05) & (p[:, 0] > 8.1))


def _walker_frame(stamp_s: float, speed: float) -> GroundTruthFrame:
    """One pedestrian 6 m to the left front of the sensor, heading +y (across the line of sight) at ``speed``."""
    return GroundTruthFrame(
        seq=0, stamp_ns=BASE_STAMP_NS + int(round(stamp_s * 1e9)), ego_x=0.0, ego_y=0.0, ego_yaw=0.0,
        instance_ids=np.array([7]), labels=np.array([int(Label.PEDESTRIAN)]), centers=np.array([[6.0, 0.5, 0.875]]),
        sizes=np.array([[0.73, 0.67, 1.75]]), yaws=np.array([np.pi / 2]), velocities=np.array([[0.0, speed]]),
        moving=np.array([speed > 0]), attributes=("pedestrian.moving" if speed else "pedestrian.standing",),
        visibility=np.ones(1), num_points=np.zeros(1, np.int64))


def test_walker_limbs_stay_inside_the_box_at_any_stride() -> None:
    from jitterguard.sim.shapes import GAIT

    for key, coef in GAIT.items():
        assert len(coef) == len(TEMPLATES[key])
    for size in ([0.73, 0.67, 1.75], [0.5, 0.5, 1.2], [0.55, 0.8, 1.9]):  # adult, child, a wide one
        for stride in (-1.0, -0.4, 0.0, 1.0):
            prims, _ = object_primitives(np.array([[3.0, -2.0, size[2] / 2]]), np.array([size]), np.array([0.7]),
                                         np.array([int(Label.PEDESTRIAN)]), ("pedestrian.moving",), np.array([1]),
                                         np.array([stride]))
            assert len(prims) == len(TEMPLATES["walker"])
            c, s = np.cos(0.7), np.sin(0.7)
            rel = prims.center - [3.0, -2.0]
            lx, ly = rel[:, 0] * c + rel[:, 1] * s, -rel[:, 0] * s + rel[:, 1] * c
            reach = prims.half[:, 0]  # boxes here are torso-aligned: half-length along x; cylinders: radius
            assert np.all(np.abs(lx) + reach <= size[0] / 2 + 1e-9)
            across = np.where(prims.kind == 0, prims.half[:, 1], prims.half[:, 0])
            assert np.all(np.abs(ly) + across <= size[1] / 2 + 1e-9)


def test_limbs_are_opt_in_and_a_walker_strides_while_a_standing_one_does_not() -> None:
    """Without ``limbs`` a pedestrian is cast as before, the same at every moment; with it a walker's feet spread
    and close along its heading as the stride goes on, and one standing still keeps its pose."""
    from jitterguard.sim.effects import ScanEffects, draw_effects, parse_components

    assert "limbs" not in parse_components("random") and "limbs" in parse_components("random,limbs")
    plain = draw_effects(np.random.default_rng(4), parse_components("random"))
    limbs = draw_effects(np.random.default_rng(4), parse_components("random,limbs"))
    assert limbs == ScanEffects(**{**plain.__dict__, "limbs": True}) and not plain.limbs

    def feet_spread(stamp_s: float, speed: float, on: bool) -> float:
        res, _ = cast_frame(_walker_frame(stamp_s, speed), seed=0, effects=ScanEffects(limbs=on))
        p = res.points[res.owner == 0]
        low = p[p[:, 2] < -1.84 + 0.45]  # returns from the lower legs
        assert len(low) >= 2
        return float(np.ptp(low[:, 1]))  # along the walker's heading (+y)

    stamps = np.arange(0.0, 1.2, 0.1)
    before = [cast_frame(_walker_frame(t, 1.4), seed=0)[0].points for t in stamps[:2]]
    np.testing.assert_array_equal(before[0], before[1])  # no limbs: no pose changes with time
    walking = [feet_spread(t, 1.4, True) for t in stamps]
    standing = [feet_spread(t, 0.0, True) for t in stamps]
    assert np.ptp(standing) < 1e-9
    assert max(walking) > max(standing) + 0.25 and min(walking) < max(walking) - 0.15


def _cyclist_frame(stamp_s: float, speed: float) -> GroundTruthFrame:
    """One bicycle with its rider 6 m to the left front of the sensor, heading +y at ``speed``."""
    return GroundTruthFrame(
        seq=0, stamp_ns=BASE_STAMP_NS + int(round(stamp_s * 1e9)), ego_x=0.0, ego_y=0.0, ego_yaw=0.0,
        instance_ids=np.array([7]), labels=np.array([int(Label.BICYCLE)]), centers=np.array([[6.0, 0.5, 0.85]]),
        sizes=np.array([[1.7, 0.6, 1.7]]), yaws=np.array([np.pi / 2]), velocities=np.array([[0.0, speed]]),
        moving=np.array([speed > 0]), attributes=("cycle.with_rider",), visibility=np.ones(1),
        num_points=np.zeros(1, np.int64))


def test_pedaller_stays_inside_the_box_and_its_feet_go_round_half_a_turn_apart() -> None:
    from jitterguard.sim.shapes import PEDAL

    for key, coef in PEDAL.items():
        assert coef.shape == (len(TEMPLATES[key]), 3)
    shins = []
    for size in ([1.7, 0.6, 1.7], [1.5, 0.5, 1.4], [2.0, 0.8, 1.9]):  # a usual bicycle, a small one, a large one
        for angle in np.linspace(0.0, 2 * np.pi, 13):
            prims, _ = object_primitives(np.array([[3.0, -2.0, size[2] / 2]]), np.array([size]), np.array([0.7]),
                                         np.array([int(Label.BICYCLE)]), ("cycle.with_rider",), np.array([1]),
                                         crank=np.array([angle]))
            assert len(prims) == len(TEMPLATES["pedaller"])
            c, s = np.cos(0.7), np.sin(0.7)
            rel = prims.center - [3.0, -2.0]
            lx, ly = rel[:, 0] * c + rel[:, 1] * s, -rel[:, 0] * s + rel[:, 1] * c
            reach = prims.half[:, 0]
            assert np.all(np.abs(lx) + reach <= size[0] / 2 + 1e-9)
            across = np.where(prims.kind == 0, prims.half[:, 1], prims.half[:, 0])
            assert np.all(np.abs(ly) + across <= size[1] / 2 + 1e-9)
            assert np.all(prims.z[:, 0] >= -1e-9) and np.all(prims.z[:, 1] <= size[2] + 1e-9)
            if size[0] == 1.7:
                shins.append((lx[4:6].copy(), prims.z[4:6, 0].copy()))
    x = np.array([a for a, _ in shins])
    z = np.array([b for _, b in shins])
    np.testing.assert_allclose(x.sum(axis=1), 2 * 0.05 * 1.7, atol=1e-9)  # the feet mirror each other
    np.testing.assert_allclose(z.sum(axis=1), 2 * 0.08 * 1.7, atol=1e-9)
    assert np.ptp(x[:, 0]) == pytest.approx(2 * 0.10 * 1.7) and np.ptp(z[:, 0]) == pytest.approx(2 * 0.07 * 1.7)


def test_pedal_is_opt_in_and_a_riding_cyclist_pedals_while_a_stopped_one_does_not() -> None:
    """Without ``pedal`` a cyclist is cast as before, the same at every moment; with it the returns of a riding
    cyclist change from scan to scan as the legs go round, and a stopped one keeps its pose."""
    from jitterguard.sim.effects import ScanEffects, draw_effects, parse_components

    assert "pedal" not in parse_components("random") and "pedal" in parse_components("random,pedal")
    plain = draw_effects(np.random.default_rng(4), parse_components("random,limbs"))
    pedal = draw_effects(np.random.default_rng(4), parse_components("random,limbs,pedal"))
    assert pedal == ScanEffects(**{**plain.__dict__, "pedal": True}) and not plain.pedal

    def returns(stamp_s: float, speed: float, on: bool) -> np.ndarray:
        res, _ = cast_frame(_cyclist_frame(stamp_s, speed), seed=0, effects=ScanEffects(pedal=on))
        return res.points[res.owner == 0]

    stamps = (0.0, 0.2, 0.4)
    for speed, on in ((4.0, False), (0.0, False), (0.0, True)):
        first = returns(stamps[0], speed, on)
        for t in stamps[1:]:
            np.testing.assert_array_equal(returns(t, speed, on), first)
    riding = [returns(t, 4.0, True) for t in stamps]
    assert all(len(a) != len(b) or not np.array_equal(a, b) for a, b in zip(riding, riding[1:]))
    # a pedestrian in the same place is cast the same with and without pedal
    walker = [cast_frame(_walker_frame(0.3, 1.4), seed=0, effects=ScanEffects(limbs=True, pedal=on))[0].points
              for on in (False, True)]
    np.testing.assert_array_equal(walker[0], walker[1])
