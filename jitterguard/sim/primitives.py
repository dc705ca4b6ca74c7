"""Solid primitives the world is built from: yaw-oriented boxes and vertical cylinders with a z extent.

Both the static clutter (trees, poles, fences, walls, buildings) and the shapes of road users are sets of
primitives, so one ray caster and one occlusion estimate serve both. Stored as a struct of arrays because every
consumer is vectorised over primitives.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
from numpy.typing import NDArray

BOX = 0
CYLINDER = 1


class Tag(IntEnum):
    """What a primitive belongs to; the BEV renderer and intensity model use it, the ray caster does not."""

    OBJECT = 0
    TREE_TRUNK = 1
    TREE_CROWN = 2
    POLE = 3
    FENCE = 4
    WALL = 5
    BUILDING = 6
    HEDGE = 7
    SIGN = 8
    GLASS = 9
    """A road user's windows: rays pass through with :attr:`~jitterguard.sim.effects.ScanEffects.glass_pass`."""
    EGO = 10
    """The sensor's own vehicle (roof around the mount); its hits return nothing."""


@dataclass(frozen=True, eq=False)
class Primitives:
    """P primitives: ``kind`` BOX/CYLINDER, footprint ``center`` (P,2), ``z`` (P,2) bottom/top, ``half`` (P,2)
    half-length/half-width (a cylinder's radius twice), ``yaw`` (P,), ``reflectivity`` (P,) 0..1, ``tag`` (P,)."""

    kind: NDArray[np.int8]
    center: NDArray[np.float64]
    z: NDArray[np.float64]
    half: NDArray[np.float64]
    yaw: NDArray[np.float64]
    reflectivity: NDArray[np.float64]
    tag: NDArray[np.int16]

    def __len__(self) -> int:
        return len(self.kind)

    @staticmethod
    def empty() -> "Primitives":
        return Primitives(
            np.zeros(0, np.int8), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0),
            np.zeros(0, np.int16),
        )

    @staticmethod
    def concat(parts: Sequence["Primitives"]) -> "Primitives":
        parts = [p for p in parts if len(p)]
        if not parts:
            return Primitives.empty()
        return Primitives(
            *(np.concatenate([getattr(p, f) for p in parts]) for f in
              ("kind", "center", "z", "half", "yaw", "reflectivity", "tag"))
        )

    def subset(self, mask: NDArray[np.bool_] | NDArray[np.int64]) -> "Primitives":
        return Primitives(self.kind[mask], self.center[mask], self.z[mask], self.half[mask], self.yaw[mask],
                          self.reflectivity[mask], self.tag[mask])

    def footprint_radius(self) -> NDArray[np.float64]:
        """Radius of a circle around each footprint (for range culling)."""
        return np.where(self.kind == BOX, np.hypot(self.half[:, 0], self.half[:, 1]), self.half[:, 0])


class PrimitiveList:
    """Append-only builder for :class:`Primitives` (scenario generation is sequential; arrays come at the end)."""

    def __init__(self) -> None:
        self._rows: list[tuple[int, float, float, float, float, float, float, float, float, int]] = []
        self._footprints: list[NDArray[np.float64]] = []
        self._tops: list[float] = []

    def box(self, x: float, y: float, length: float, width: float, z0: float, z1: float, yaw: float = 0.0,
            reflectivity: float = 0.3, tag: Tag = Tag.OBJECT) -> None:
        self._rows.append((BOX, x, y, z0, z1, length / 2, width / 2, yaw, reflectivity, int(tag)))
        if z0 < 2.0:
            self._footprints.append(np.array([x, y, length / 2, width / 2, yaw]))
            self._tops.append(z1)

    def cylinder(self, x: float, y: float, radius: float, z0: float, z1: float, reflectivity: float = 0.3,
                 tag: Tag = Tag.OBJECT) -> None:
        self._rows.append((CYLINDER, x, y, z0, z1, radius, radius, 0.0, reflectivity, int(tag)))
        if z0 < 2.0:
            self._footprints.append(np.array([x, y, radius, radius, 0.0]))
            self._tops.append(z1)

    def footprints(self) -> list[NDArray[np.float64]]:
        """Ground footprints (x, y, half_length, half_width, yaw) of everything that reaches below 2 m
        (tree crowns and lamp arms do not block the ground)."""
        return self._footprints

    def footprint_tops(self) -> list[float]:
        """The top height of each of :meth:`footprints` (a kerb's 0.15 m, a wall's 1.2 m): what a person could step
        onto."""
        return self._tops

    def build(self) -> Primitives:
        if not self._rows:
            return Primitives.empty()
        a = np.asarray(self._rows, dtype=np.float64)
        return Primitives(
            a[:, 0].astype(np.int8), a[:, 1:3].copy(), a[:, 3:5].copy(), a[:, 5:7].copy(), a[:, 7].copy(),
            a[:, 8].copy(), a[:, 9].astype(np.int16),
        )
