"""The view term (``view_slide_m_per_class``): a box centre that slides with the sensor's view of a parked car is not
motion, a car that moves is still motion, and only the configured classes get the term.

The sensor drives past a parked car at 10 m/s; the detector places the car's centre from the faces it sees, so the
centre slides by ``SLIDE`` metres per unit turn of the line of sight (centre = true centre + SLIDE · u). The windows
are tested with the calibrated statistic's denominator (independent observations, the reported variances as they
are), so the expected z values follow from the geometry alone."""

from __future__ import annotations

import numpy as np
import pytest

from jitterguard.schemas.models import ClassifierConfig, Label
from jitterguard.services.classifier.calibration import vehicle_class_names
from jitterguard.services.classifier.core import DYNAMIC, STATIC, MotionClassifierCore, Observations

SLIDE = 1.0  # m per unit turn of the view direction, the detector's (unknown to the classifier)
SIGMA = 0.05  # m, the reported and the drawn jitter
HZ = 10.0
CAR_ID, PED_ID = f"{1:032x}", f"{2:032x}"


def _config(slide: float | None) -> ClassifierConfig:
    view = {} if slide is None else dict.fromkeys(vehicle_class_names(), slide)
    return ClassifierConfig(calibration="off", effective_n="independent", min_speed_mps=0.1,
                            view_slide_m_per_class=view)


def _drive(core: MotionClassifierCore, sensor_x: np.ndarray, objects: dict[str, tuple[Label, np.ndarray]],
           rng: np.random.Generator) -> dict[str, int]:
    """Feed one frame per sensor position; objects[id] = (label, (frames, 2) true centres). The last states."""
    states: dict[str, int] = {}
    for j, sx in enumerate(sensor_x):
        ids, labels, xs, ys = [], [], [], []
        for tid, (label, centres) in objects.items():
            p = centres[j]
            u = (p - (sx, 0.0)) / np.linalg.norm(p - (sx, 0.0))
            seen = p + SLIDE * u + rng.normal(0.0, SIGMA, 2)  # placed from the faces the sensor sees
            ids.append(tid)
            labels.append(int(label))
            xs.append(seen[0])
            ys.append(seen[1])
        n = len(ids)
        dec = core.update(Observations.from_lists(
            ids, labels, xs, ys, np.full(n, SIGMA**2), np.zeros(n), np.full(n, SIGMA**2),
            stamp_ns=int(j / HZ * 1e9), seq=j, sensor_x=float(sx), sensor_y=0.0))
        states = dict(zip((i.decode() for i in dec.track_ids.tolist()), dec.state.tolist()))
    return states


def _parked(frames: int) -> np.ndarray:
    return np.tile([0.0, 6.0], (frames, 1))


def test_a_parked_car_sliding_with_the_view_is_static_with_the_term_and_moving_without() -> None:
    sensor = np.linspace(-10.0, 10.0, 21)  # 10 m/s past the car, 6 m to the side: the view turns ~120°
    without = _drive(MotionClassifierCore(_config(None)), sensor, {CAR_ID: (Label.CAR, _parked(21))},
                     np.random.default_rng(0))
    with_term = _drive(MotionClassifierCore(_config(1.5)), sensor, {CAR_ID: (Label.CAR, _parked(21))},
                       np.random.default_rng(0))
    assert without[CAR_ID] == DYNAMIC  # the slide (~1.2 m between half-means) is 30σ of the jitter
    assert with_term[CAR_ID] == STATIC


@pytest.mark.parametrize("y, start, speed, seed", [(8.0, -5.0, 5.0, 1), (2.0, -3.0, 3.0, 5)],
                         ids=["crossing at 5 m/s, 8 m away", "creeping at 3 m/s, 2 m away"])
def test_a_car_passing_a_stopped_sensor_stays_dynamic(y: float, start: float, speed: float, seed: int) -> None:
    """A mover turns the line of sight too, by its own motion. The term allows for the turn the *sensor's* motion
    makes (the object held at its window mean, as under H0), not that one: a car creeping past a stopped ego 2 m away
    sweeps the line of sight through more than 100°, and a term built on the observed turn would hide its 3 m of
    motion."""
    frames = 21
    t = np.arange(frames) / HZ
    path = np.stack([start + speed * t, np.full(frames, y)], axis=1)
    states = _drive(MotionClassifierCore(_config(1.5)), np.zeros(frames), {CAR_ID: (Label.CAR, path)},
                    np.random.default_rng(seed))
    assert states[CAR_ID] == DYNAMIC


def test_the_term_is_only_for_the_configured_classes() -> None:
    """Vehicles configured, pedestrians not: the same slide calls the pedestrian moving, the car static."""
    sensor = np.linspace(-10.0, 10.0, 21)
    states = _drive(MotionClassifierCore(_config(1.5)), sensor,
                    {CAR_ID: (Label.CAR, _parked(21)), PED_ID: (Label.PEDESTRIAN, _parked(21) + (0.0, 3.0))},
                    np.random.default_rng(2))
    assert states[CAR_ID] == STATIC
    assert states[PED_ID] == DYNAMIC


def test_a_larger_slide_than_configured_is_still_called_moving() -> None:
    """The term allows the slide it is told, not any: a centre sliding 6 m per unit turn exceeds 1.5 m's allowance."""
    global SLIDE
    sensor = np.linspace(-10.0, 10.0, 21)
    old, SLIDE = SLIDE, 6.0
    try:
        states = _drive(MotionClassifierCore(_config(1.5)), sensor, {CAR_ID: (Label.CAR, _parked(21))},
                        np.random.default_rng(3))
    finally:
        SLIDE = old
    assert states[CAR_ID] == DYNAMIC


@pytest.mark.parametrize("bad, field", [({"car": -0.5}, "view_slide_m_per_class.car"),
                                        ({"lorry": 1.0}, "view_slide_m_per_class")])
def test_bad_view_slides_are_refused_naming_the_field(bad: dict, field: str) -> None:
    with pytest.raises(ValueError) as err:
        ClassifierConfig(view_slide_m_per_class=bad)
    locs = {".".join(str(x) for x in e["loc"]) for e in err.value.errors()}
    assert field in locs


def test_the_default_term_is_for_vehicles_only() -> None:
    cfg = ClassifierConfig()
    assert set(cfg.view_slide_m_per_class) == set(vehicle_class_names()) == {"car", "truck", "bus", "trailer"}
    assert cfg.view_slide_for(int(Label.CAR)) == 2.0
    assert cfg.view_slide_for(int(Label.PEDESTRIAN)) == 0.0
    assert cfg.view_slide_for(int(Label.BICYCLE)) == 0.0
    assert cfg.view_slide_for(int(Label.UNKNOWN)) == 0.0


def test_a_turning_truck_passing_the_sensor_stays_dynamic() -> None:
    """A mover on a curve: its positions stray metres from a straight line, so the window's own noise scale (the
    Student-t λ of the calibrated statistic) is large. The view term is geometry, not noise: scaled by λ as well it
    would swamp the displacement (this truck at 7 m/s on a 25 m arc, 2 Hz frames, would be called static)."""
    hz, n, radius, speed, sigma = 2.0, 10, 25.0, 7.0, 0.03
    rng = np.random.default_rng(4)
    core = MotionClassifierCore(ClassifierConfig(view_slide_m_per_class={"truck": 1.5}))  # online calibration
    t = np.arange(n) / hz
    heading = -np.pi / 2 - speed * t / radius
    truck = np.stack([15.0 + radius * np.cos(heading), 30.0 + radius * np.sin(heading)], axis=1)
    for j in range(n):
        p = truck[j] + rng.normal(0.0, sigma, 2)
        dec = core.update(Observations.from_lists(
            [CAR_ID], [int(Label.TRUCK)], [p[0]], [p[1]], [sigma**2], [0.0], [sigma**2],
            stamp_ns=int(t[j] * 1e9), seq=j, sensor_x=-15.0 + 7.0 * t[j], sensor_y=0.0))
    assert dec.state[0] == DYNAMIC
    assert max(dec.z_x[0], dec.z_y[0]) > 2 * ClassifierConfig().alpha_for(int(Label.TRUCK))
