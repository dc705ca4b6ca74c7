"""Ground truth of the synthetic world: determinism, kinematic consistency, nuScenes attribute semantics."""

from __future__ import annotations

import math
from collections import defaultdict

import numpy as np
import pytest

from jitterguard.schemas import Label
from jitterguard.sim import SCENARIO_NAMES, SENSOR_HEIGHT_M, GroundTruthFrame, Scenario, make_scenario
from jitterguard.sim.catalog import ATTRIBUTES, MOVING_SPEED_MPS
from jitterguard.sim.layout import rectangles_overlap


def _common(a: GroundTruthFrame, b: GroundTruthFrame, c: GroundTruthFrame):
    ids = np.intersect1d(np.intersect1d(a.instance_ids, b.instance_ids), c.instance_ids)
    return (ids, np.searchsorted(a.instance_ids, ids), np.searchsorted(b.instance_ids, ids),
            np.searchsorted(c.instance_ids, ids))


def test_every_named_scenario_builds_with_expected_frame_count(
        scenarios: dict[str, Scenario], all_frames: dict[str, list[GroundTruthFrame]]) -> None:
    assert set(scenarios) == set(SCENARIO_NAMES)
    for sc in scenarios.values():
        assert sc.num_frames == 120 == len(sc)
        assert len(all_frames[sc.name]) == 120
        f = sc.frame(5)
        assert f.seq == 5 and f.stamp_ns - sc.frame(4).stamp_ns == 100_000_000
        assert f.num_objects > 10


def test_unknown_scenario_and_bad_arguments_are_rejected() -> None:
    with pytest.raises(ValueError, match="unknown scenario"):
        make_scenario("highway", 0)
    with pytest.raises(ValueError):
        make_scenario("mixed", 0, duration_s=-1.0)
    sc = make_scenario("parking-street", 0, duration_s=2.0)
    with pytest.raises(IndexError):
        sc.frame(sc.num_frames)


def test_same_seed_same_world_different_seed_different_world() -> None:
    a = make_scenario("intersection", 3, duration_s=6.0)
    b = make_scenario("intersection", 3, duration_s=6.0)
    c = make_scenario("intersection", 4, duration_s=6.0)
    for i in (0, 31, 59):
        fa, fb = a.frame(i), b.frame(i)
        np.testing.assert_array_equal(fa.instance_ids, fb.instance_ids)
        np.testing.assert_array_equal(fa.centers, fb.centers)
        np.testing.assert_array_equal(fa.velocities, fb.velocities)
        assert fa.attributes == fb.attributes
        assert (fa.ego_x, fa.ego_y, fa.ego_yaw) == (fb.ego_x, fb.ego_y, fb.ego_yaw)
    fc = c.frame(31)
    assert fc.num_objects != a.frame(31).num_objects or not np.allclose(fc.centers, a.frame(31).centers)


def test_instances_keep_label_and_size_and_ids_are_unique(all_frames: dict[str, list[GroundTruthFrame]]) -> None:
    for frames in all_frames.values():
        seen: dict[int, tuple[int, tuple[float, ...]]] = {}
        for f in frames:
            assert len(np.unique(f.instance_ids)) == f.num_objects
            assert np.all(f.instance_ids > 0)
            for iid, lab, size in zip(f.instance_ids.tolist(), f.labels.tolist(), f.sizes):
                key = (lab, tuple(np.round(size, 9)))
                assert seen.setdefault(iid, key) == key


def test_parked_objects_never_move(all_frames: dict[str, list[GroundTruthFrame]]) -> None:
    static_attrs = ("vehicle.parked", "cycle.without_rider", "pedestrian.sitting_lying_down")
    for name, frames in all_frames.items():
        first: dict[int, np.ndarray] = {}
        n_parked = 0
        for f in frames:
            rows = [n for n, a in enumerate(f.attributes) if a in static_attrs]
            assert np.all(f.velocities[rows] == 0.0) and not np.any(f.moving[rows])
            poses = np.column_stack([f.centers[rows], f.yaws[rows]])
            for iid, pose in zip(f.instance_ids[rows].tolist(), poses):
                assert np.array_equal(first.setdefault(iid, pose), pose), (name, iid)
            n_parked += len(rows)
        assert n_parked > 0, name


def test_velocities_match_finite_differences_of_positions(scenarios: dict[str, Scenario],
                                                          all_frames: dict[str, list[GroundTruthFrame]]) -> None:
    for sc in scenarios.values():
        frames = all_frames[sc.name]
        dt = 2.0 / sc.rate_hz
        checked = 0
        for a, b, c in zip(frames, frames[1:], frames[2:]):
            _, ia, ib, ic = _common(a, b, c)
            v_fd = (c.centers[ic, :2] - a.centers[ia, :2]) / dt
            v = b.velocities[ib]
            # on straight stretches the central difference is the velocity; on curves the chord is shorter than
            # the arc, so compare speeds there
            straight = np.abs(np.angle(np.exp(1j * (c.yaws[ic] - a.yaws[ia])))) < 1e-9
            assert np.all(np.abs(v_fd - v)[straight] < 0.2), sc.name
            assert np.all(np.abs(np.hypot(*v_fd.T) - np.hypot(*v.T)) < 0.2), sc.name
            checked += int(np.sum(np.hypot(*v.T) > 1.0))
        assert checked > 50, sc.name


def test_motion_state_and_attributes_follow_nuscenes_semantics(
        all_frames: dict[str, list[GroundTruthFrame]]) -> None:
    vehicle = {Label.CAR, Label.TRUCK, Label.BUS, Label.TRAILER}
    counts: dict[str, int] = defaultdict(int)
    for frames in all_frames.values():
        for f in frames:
            speed = np.hypot(f.velocities[:, 0], f.velocities[:, 1])
            np.testing.assert_array_equal(f.moving, speed > MOVING_SPEED_MPS)
            for lab, attr, mv in zip(f.labels.tolist(), f.attributes, f.moving.tolist()):
                assert attr in ATTRIBUTES
                counts[attr] += 1
                if lab in vehicle:
                    assert attr.startswith("vehicle.")
                    assert mv == (attr == "vehicle.moving")
                elif lab == Label.PEDESTRIAN:
                    assert attr.startswith("pedestrian.")
                    assert mv == (attr == "pedestrian.moving")
                else:
                    assert lab in (Label.BICYCLE, Label.MOTORCYCLE) and attr.startswith("cycle.")
                    if attr == "cycle.without_rider":
                        assert not mv
    for attr in ATTRIBUTES:  # the four scenarios together exercise every attribute
        assert counts[attr] > 0, attr


def test_stop_and_go_the_ego_stops_at_the_red_light() -> None:
    sc = make_scenario("intersection", 11, duration_s=25.0, rate_hz=10.0)
    speeds = np.array([f.ego_speed for f in sc])
    xs = np.array([f.ego_x for f in sc])
    assert speeds.min() < 0.1 < 8.0 < speeds.max()
    assert np.all(np.diff(xs) >= -1e-9)  # never backs up
    stopped_x = xs[speeds < 0.1]
    assert np.all(stopped_x < -11.0)  # waits before the stop line


def test_ego_passes_parked_cars_at_street_speed(scenarios: dict[str, Scenario]) -> None:
    sc = scenarios["parking-street"]
    f0, f1 = sc.frame(0), sc.frame(sc.num_frames - 1)
    assert 0.0 < f1.ego_x - f0.ego_x <= 12.0 * sc.duration_s
    assert abs(f0.ego_yaw) < 1e-9
    parked = [n for n, a in enumerate(f0.attributes) if a == "vehicle.parked"]
    rel_y = np.abs(f0.centers[parked, 1] - f0.ego_y)
    assert len(parked) > 15 and np.all((rel_y > 3.0) & (rel_y < 9.0))


def test_vehicles_never_overlap(scenarios: dict[str, Scenario]) -> None:
    for sc in scenarios.values():
        for i in range(0, sc.num_frames, 20):
            f = sc.frame(i)
            rect = np.column_stack([f.centers[:, :2], f.sizes[:, 0] / 2 - 0.05, f.sizes[:, 1] / 2 - 0.05, f.yaws])
            big = np.flatnonzero(f.labels != Label.PEDESTRIAN)
            for a in big:
                for b in range(f.num_objects):
                    if b == a or (b in big and b < a):
                        continue
                    if np.hypot(*(rect[a, :2] - rect[b, :2])) < 8.0:
                        assert not rectangles_overlap(rect[a], rect[b]), (sc.name, i, a, b)


def test_visibility_is_a_fraction_and_occlusion_lowers_it(scenarios: dict[str, Scenario]) -> None:
    f = scenarios["diagonal-lot"].frame(30)
    assert np.all((f.visibility >= 0.0) & (f.visibility <= 1.0))
    rel_y = np.abs(f.centers[:, 1] - f.ego_y)
    close = (np.abs(f.centers[:, 0] - f.ego_x) < 20.0) & (f.labels == Label.CAR)
    near_row = (rel_y < 8.0) & close  # the rows lining the ego's aisle
    far_row = (rel_y > 9.0) & (rel_y < 17.0) & close  # back-to-back rows behind them
    assert near_row.sum() > 5 and far_row.sum() > 5
    assert f.visibility[near_row].mean() > f.visibility[far_row].mean() + 0.2


def test_objects_listed_only_within_the_radius() -> None:
    sc = make_scenario("parking-street", 2, duration_s=3.0, gt_radius_m=30.0)
    for f in sc:
        d = np.hypot(f.centers[:, 0] - f.ego_x, f.centers[:, 1] - f.ego_y)
        assert np.all(d <= 30.0)
        assert math.isfinite(f.stamp_ns / 1e9)


def test_the_loading_street_parks_a_real_truck_fleet(scenarios: dict[str, Scenario]) -> None:
    """Issue 16's "size distributions of real fleets": pick-ups, tractor-semitrailers and long trailers stand in
    the loading street (nose-in, side by side), while the other scenarios keep their rigid trucks, so their
    worlds — and every figure measured on them — are unchanged."""
    from jitterguard.sim.catalog import CLASSES
    from jitterguard.sim.shapes import template_key

    f = scenarios["loading-street"].frame(0)
    trucks = f.labels == Label.TRUCK
    keys = {template_key(int(lab), a, sz) for lab, a, sz in zip(f.labels, f.attributes, f.sizes)}
    assert {"semi", "pickup", "truck", "trailer"} <= keys
    assert np.any(f.sizes[trucks, 0] > 12.0) and np.any(f.sizes[trucks, 0] < 6.5)
    yard = (f.centers[:, 1] - f.ego_y > 8.0) & np.isin(f.labels, [Label.TRUCK, Label.TRAILER, Label.BUS])
    assert yard.sum() >= 5
    assert np.all(np.abs(np.abs(np.sin(f.yaws[yard])) - 1.0) < 0.01)  # nose to the street
    # a rigid truck's size, clipped at 2 SD, never reaches the pick-up's or the semi's template
    truck = CLASSES["truck"]
    lo = np.asarray(truck.mean_size) - 2 * np.asarray(truck.std_size)
    hi = np.asarray(truck.mean_size) + 2 * np.asarray(truck.std_size)
    assert template_key(Label.TRUCK, "vehicle.parked", lo) == template_key(Label.TRUCK, "vehicle.parked", hi) == "truck"
    for name in ("parking-street", "diagonal-lot", "intersection", "mixed"):
        g = scenarios[name].frame(0)
        assert {template_key(int(lab), a, sz) for lab, a, sz in zip(g.labels, g.attributes, g.sizes)
                if lab == Label.TRUCK} <= {"truck"}


def test_the_perpendicular_lot_parks_cars_side_by_side_at_right_angles(scenarios: dict[str, Scenario]) -> None:
    """Real lots are mostly 90° stalls: each car shows the aisle its front or back between neighbours 0.3–1 m away,
    out to the far rows 14–15 m off the ego's aisle. The diagonal lot keeps its 45° and 60° stalls (its seeds, and
    every figure on them, keep their worlds)."""
    def parked(name: str) -> tuple[np.ndarray, np.ndarray]:
        f = scenarios[name].frame(0)
        m = np.array([a == "vehicle.parked" for a in f.attributes]) & (f.labels == Label.CAR)
        return f.centers[m, :2] - [f.ego_x, f.ego_y], f.yaws[m]

    xy, yaw = parked("perpendicular-lot")
    assert len(yaw) >= 20
    assert np.all(np.abs(np.abs(np.sin(yaw)) - 1.0) < 0.01)  # the ego's aisle runs along x
    gaps = np.sort(np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1]), axis=1)[:, 1]
    assert np.median(gaps) < 3.5  # a neighbour one stall away
    assert np.abs(xy[:, 1]).max() > 14.0  # the far rows
    _, yaw = parked("diagonal-lot")
    angles = np.degrees(np.abs(np.arcsin(np.abs(np.sin(yaw)))))
    assert np.all((np.abs(angles - 45.0) < 3.0) | (np.abs(angles - 60.0) < 3.0))


def test_the_screened_lot_hides_its_near_rows_behind_a_low_wall_or_hedge(scenarios: dict[str, Scenario]) -> None:
    """A row of nose-in cars seen from a road across a verge with street trees and a low wall or hedge shows the
    sensor little of them, and least below the screen's top: in a scan the near rows return under half as often as
    in the open 90° lot, and a far smaller share of what they return lies under 0.8 m; those rows stand beyond a kerb
    3.3–9 m off the ego's lane and a verge with people standing on it."""
    from jitterguard.sim.lidar import cast_frame
    from jitterguard.sim.primitives import Tag

    def near_rows(name: str) -> tuple[float, float, float]:
        f = scenarios[name].frame(0)
        scan, _ = cast_frame(f)
        rel = f.centers[:, 1] - f.ego_y
        parked = np.array([a == "vehicle.parked" for a in f.attributes]) & (f.labels == Label.CAR)
        nearest = np.abs(rel[parked]).min()
        rows = np.flatnonzero(parked & (np.abs(rel) < nearest + 3.0) & (np.abs(f.centers[:, 0] - f.ego_x) < 30.0))
        z = scan.points[np.isin(scan.owner, rows), 2] + SENSOR_HEIGHT_M  # over the road
        return float(np.mean(z < 0.8)), len(z) / len(rows), float(nearest)

    low_open, returns_open, near_open = near_rows("perpendicular-lot")
    low_screened, returns_screened, near_screened = near_rows("screened-lot")
    assert low_open > 0.25
    assert low_screened < low_open / 2
    assert returns_screened < returns_open / 2
    assert near_screened > near_open + 1.5  # beyond the verge
    cl = scenarios["screened-lot"].layout.clutter
    screens = np.isin(cl.tag, [int(Tag.WALL), int(Tag.HEDGE)]) & (cl.z[:, 1] >= 0.7) & (cl.z[:, 1] <= 1.5)
    assert screens.sum() >= 2
    assert np.any(cl.tag == int(Tag.TREE_TRUNK))
    f = scenarios["screened-lot"].frame(0)  # people stand on the verge, between the kerb and the cars (and on the
    standing = np.array([a == "pedestrian.standing" for a in f.attributes])  # islands beyond the rows)
    assert np.sum(standing & (np.abs(f.centers[:, 1] - f.ego_y) < near_screened)) >= 3


def test_tractor_semitrailers_in_traffic_drive_like_heavy_vehicles() -> None:
    """A 15 m semi in a lane takes the heavy vehicles' IDM (slow starts, long headways) and 0.8 × the lane's
    speed, as rigid trucks do; a car in the same lane keeps the defaults."""
    from jitterguard.sim.layout import LayoutBuilder
    from jitterguard.sim.paths import straight
    from jitterguard.sim.scenarios import _HEAVY_IDM, _fill_lane

    b = LayoutBuilder(np.random.default_rng(0), 10.0)
    lane = b.add_lane(straight((0.0, 0.0), (2000.0, 0.0)))
    _fill_lane(b, lane, 0.0, 1500.0, (30.0, 40.0), (10.0, 10.0), {"semi": 0.5, "car": 0.5})
    members = b._lanes[lane].members
    semis = [m.agent for m in members if m.cls.key == "semi"]
    cars = [m.agent for m in members if m.cls.key == "car"]
    assert len(semis) >= 5 and len(cars) >= 5
    assert all(a.headway_s == _HEAVY_IDM["headway_s"] and a.a_max == _HEAVY_IDM["a_max"] for a in semis)
    assert all(a.v_desired == 8.0 for a in semis) and all(a.v_desired == 10.0 for a in cars)
    assert all(a.headway_s != _HEAVY_IDM["headway_s"] for a in cars)


def test_people_step_onto_kerbs_but_walls_and_other_objects_refuse_them() -> None:
    """``add_static`` refuses a footprint that overlaps clutter, except clutter a person steps onto (up to
    ``STEP_UP_M``): a pedestrian stands on a 0.15 m kerb where a car may not park; a 1 m wall refuses both, and so
    does a person or car already there."""
    from jitterguard.sim.layout import STEP_UP_M, LayoutBuilder
    from jitterguard.sim.primitives import Tag

    b = LayoutBuilder(np.random.default_rng(0), 10.0)
    b.clutter.box(0.0, 0.0, 20.0, 0.5, 0.0, 0.15, tag=Tag.WALL)  # a kerb
    b.clutter.box(0.0, 10.0, 20.0, 0.3, 0.0, 1.0, tag=Tag.WALL)  # a garden wall
    b.clutter.box(0.0, 20.0, 20.0, 0.5, 0.0, STEP_UP_M + 0.05, tag=Tag.WALL)  # a planter's edge
    on_kerb = b.add_static("pedestrian", 2.0, 0.0, 0.0, "pedestrian.standing")
    assert on_kerb > 0
    assert b.add_static("car", -5.0, 0.0, 0.0, "vehicle.parked") == -1
    assert b.add_static("pedestrian", 2.0, 10.0, 0.0, "pedestrian.standing") == -1
    assert b.add_static("child", 2.0, 20.0, 0.0, "pedestrian.standing") == -1
    assert b.add_static("sitting", 2.1, 0.0, 0.0, "pedestrian.sitting_lying_down") == -1  # someone stands there
    on_road = b.add_static("pedestrian", 2.0, 5.0, 0.0, "pedestrian.standing")
    assert on_road > 0


def test_a_person_on_a_kerb_stands_on_its_top() -> None:
    """Who steps onto a kerb stands on it: the ground-truth box and the body's parts start at the kerb's top (the
    highest step under the footprint), while a person beside it and a parked car stand on the road."""
    from jitterguard.sim.layout import LayoutBuilder
    from jitterguard.sim.lidar import scene_primitives
    from jitterguard.sim.paths import straight
    from jitterguard.sim.primitives import Tag
    from jitterguard.sim.sensors import hdl32e

    b = LayoutBuilder(np.random.default_rng(0), 10.0)
    b.clutter.box(10.0, 0.0, 20.0, 0.5, 0.0, 0.15, tag=Tag.WALL)  # a kerb
    b.clutter.box(10.0, 0.4, 20.0, 0.3, 0.0, 0.25, tag=Tag.WALL)  # a higher step beside it
    ids = [b.add_static("pedestrian", 12.0, 0.0, 0.0, "pedestrian.standing"),  # on the kerb and the step
           b.add_static("pedestrian", 12.0, -3.0, 0.0, "pedestrian.standing"),  # on the road
           b.add_static("car", 10.0, 6.0, 0.0, "vehicle.parked")]
    b.add_agent(b.add_lane(straight((-40.0, -10.0), (40.0, -10.0))), "car", 5.0, 0.0, is_ego=True)
    layout = b.build()
    np.testing.assert_allclose(layout.static_base, [0.25, 0.0, 0.0])
    frame = Scenario("kerb", 0, layout, 10.0).frame(0)
    rows = [int(np.flatnonzero(frame.instance_ids == i)[0]) for i in ids]
    np.testing.assert_allclose(frame.centers[rows, 2] - frame.sizes[rows, 2] / 2, [0.25, 0.0, 0.0], atol=1e-12)
    spec = hdl32e()
    prims, owner = scene_primitives(frame, spec)
    for r, base in zip(rows, (0.25, 0.0, 0.0)):
        lowest = prims.z[owner == r].min() + spec.mount_height_m
        assert lowest == pytest.approx(base, abs=0.02 + 1e-9)


def test_people_stand_on_the_lots_islands(scenarios: dict[str, Scenario]) -> None:
    """The diagonal lot puts standing people on the islands between its back-to-back rows (their curb is a kerb
    they step onto): standing pedestrians are in every lot seed, beyond the near row, not on the ego's aisle."""
    for seed in range(3):
        layout = make_scenario("diagonal-lot", seed).layout
        standing = np.array([a == "pedestrian.standing" for a in layout.static_attributes])
        assert standing.sum() >= 2, seed
        assert np.all(np.abs(layout.static_xy[standing, 1]) > 8.0), seed


def test_no_one_stands_inside_a_trunk_wall_or_hedge() -> None:
    """Every standing person of the lots stands clear of clutter taller than a kerb: the verge's people are placed
    after its trees and screen, so those refuse them (placed before, 3 of 217 stood inside a trunk over seeds 0–9)."""
    from jitterguard.sim.layout import STEP_UP_M

    for name in ("screened-lot", "diagonal-lot"):
        for seed in range(7):
            layout = make_scenario(name, seed).layout
            cl = layout.clutter
            tall = (cl.z[:, 1] > STEP_UP_M) & (cl.z[:, 0] < 2.0)
            others = np.column_stack([cl.center, cl.half, cl.yaw])[tall]
            for i, attr in enumerate(layout.static_attributes):
                if attr != "pedestrian.standing":
                    continue
                (x, y), size = layout.static_xy[i], layout.static_sizes[i]
                fp = np.array([x, y, size[0] / 2, size[1] / 2, layout.static_yaw[i]])
                near = others[np.hypot(others[:, 0] - x, others[:, 1] - y) < 20.0]
                assert not any(rectangles_overlap(fp, o) for o in near), (name, seed, i)
