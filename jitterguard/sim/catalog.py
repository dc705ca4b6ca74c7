"""Object classes of the synthetic world: Autoware labels, nuScenes categories, typical sizes, attributes.

Sizes follow nuScenes' per-category statistics (length, width, height in metres) so that a detector trained on
synthetic scans sees familiar box shapes. A cyclist's box includes the rider, as in nuScenes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..schemas.models import Label

# nuScenes attribute names (the only motion semantics the ground truth speaks).
VEHICLE_MOVING = "vehicle.moving"
VEHICLE_STOPPED = "vehicle.stopped"
VEHICLE_PARKED = "vehicle.parked"
PED_MOVING = "pedestrian.moving"
PED_STANDING = "pedestrian.standing"
PED_SITTING = "pedestrian.sitting_lying_down"
CYCLE_WITH_RIDER = "cycle.with_rider"
CYCLE_WITHOUT_RIDER = "cycle.without_rider"
ATTRIBUTES = (
    CYCLE_WITH_RIDER,
    CYCLE_WITHOUT_RIDER,
    PED_MOVING,
    PED_SITTING,
    PED_STANDING,
    VEHICLE_MOVING,
    VEHICLE_PARKED,
    VEHICLE_STOPPED,
)

MOVING_SPEED_MPS = 0.1
"""Ground-truth motion threshold: an object is ``moving`` iff its speed exceeds this (m/s)."""


@dataclass(frozen=True)
class ObjectClass:
    """One kind of road user: its label, nuScenes category, and a size distribution (mean, std per axis)."""

    key: str
    label: int
    category: str
    mean_size: tuple[float, float, float]
    std_size: tuple[float, float, float]

    def sample_size(self, rng: np.random.Generator) -> np.ndarray:
        """Draw (length, width, height) clipped to ±2 standard deviations."""
        mean = np.asarray(self.mean_size)
        std = np.asarray(self.std_size)
        return mean + std * np.clip(rng.standard_normal(3), -2.0, 2.0)


CLASSES: dict[str, ObjectClass] = {
    c.key: c
    for c in (
        ObjectClass("car", Label.CAR, "vehicle.car", (4.63, 1.96, 1.73), (0.35, 0.10, 0.15)),
        ObjectClass("van", Label.CAR, "vehicle.car", (5.3, 2.05, 2.2), (0.3, 0.08, 0.15)),
        ObjectClass("truck", Label.TRUCK, "vehicle.truck", (7.0, 2.5, 3.0), (1.0, 0.12, 0.3)),
        # the rest of a real truck fleet (nuScenes files pick-ups and tractor-semitrailers under vehicle.truck);
        # only the loading-street scenario parks them, so the other scenarios' worlds are unchanged
        ObjectClass("pickup", Label.TRUCK, "vehicle.truck", (5.5, 2.0, 1.9), (0.3, 0.08, 0.08)),
        ObjectClass("semi", Label.TRUCK, "vehicle.truck", (15.0, 2.55, 3.9), (1.2, 0.05, 0.12)),
        ObjectClass("long_trailer", Label.TRAILER, "vehicle.trailer", (12.5, 2.55, 3.9), (1.2, 0.05, 0.12)),
        ObjectClass("bus", Label.BUS, "vehicle.bus.rigid", (11.5, 2.95, 3.45), (0.6, 0.05, 0.12)),
        ObjectClass("trailer", Label.TRAILER, "vehicle.trailer", (9.0, 2.5, 3.6), (1.5, 0.1, 0.2)),
        ObjectClass("motorcycle", Label.MOTORCYCLE, "vehicle.motorcycle", (2.1, 0.78, 1.47), (0.15, 0.06, 0.08)),
        ObjectClass("bicycle", Label.BICYCLE, "vehicle.bicycle", (1.75, 0.62, 1.72), (0.1, 0.05, 0.08)),
        ObjectClass("parked_bicycle", Label.BICYCLE, "vehicle.bicycle", (1.72, 0.55, 1.1), (0.08, 0.04, 0.05)),
        ObjectClass("pedestrian", Label.PEDESTRIAN, "human.pedestrian.adult", (0.73, 0.67, 1.75), (0.1, 0.08, 0.09)),
        ObjectClass("child", Label.PEDESTRIAN, "human.pedestrian.child", (0.5, 0.5, 1.2), (0.05, 0.05, 0.1)),
        ObjectClass("sitting", Label.PEDESTRIAN, "human.pedestrian.adult", (0.8, 0.7, 1.3), (0.08, 0.06, 0.06)),
    )
}

VEHICLE_LABELS = frozenset({Label.CAR, Label.TRUCK, Label.BUS, Label.TRAILER})
CYCLE_LABELS = frozenset({Label.MOTORCYCLE, Label.BICYCLE})
