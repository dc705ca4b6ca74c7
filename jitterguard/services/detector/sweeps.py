"""Stacked LiDAR sweeps, as CenterPoint reads nuScenes: the newest scan plus the earlier ones of the last half
second, each moved into the newest scan's sensor frame through the poses, with the time lag in seconds as a fifth
point column (0 for the newest scan).

Why: one sweep of a 32-beam sensor puts a handful of returns on a distant or half-hidden car; ten sweeps put up to
ten times as many, and the time lag lets the network tell where the object was from where it is (CenterPoint's
velocity head learns from exactly that). A model trained on stacked sweeps (``jitterguard train --sweeps N``, or
``--nuscenes … --sweeps 10``) takes five point fields; every path that feeds it — the live detector service, the
offline evaluator, ``eval-detector``, the nuScenes loader — stacks with the functions here, so the live service
gives the network what it was trained on.

Pure: numpy in, numpy out, no I/O and no clock; :class:`SweepStacker` keeps the recent scans in a bounded deque.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...geometry import rotation_from_quaternion

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]

DEFAULT_SWEEPS = 10
"""CenterPoint's nuScenes input: ten sweeps (0.5 s of a 20 Hz sensor)."""
MAX_LAG_S = 0.55
"""Earlier sweeps more than this older than the newest are left out (CenterPoint: 0.5 s, plus a stamp's jitter)."""
MIN_RANGE_M = 1.0
"""Returns of an earlier sweep this close to its sensor are dropped: the ego's own body, which moved since."""
MAX_EGO_SPEED_MPS = 100.0
"""Faster than this (360 km/h) between two scans, the sensor's pose jumped (a relocalisation, another map, a
restarted localiser) rather than moved: its earlier sweeps would be stacked where they never were, or — a kilometre
off — out of range and yet counted, so :class:`SweepStacker` clears its history as it does when time goes back."""
MAX_EGO_TURN_RAD_S = math.pi
"""The same for the heading: a turn faster than 180° a second between two scans is a jump, not a vehicle turning."""


@dataclass(frozen=True)
class EarlierSweep:
    """One earlier sweep, already expressed in the newest scan's sensor frame by ``rotation`` and ``translation``
    (``p_new = rotation @ p + translation``), ``time_lag_s`` older."""

    points: F32
    rotation: F64
    translation: F64
    time_lag_s: float


def relative_transform(new_rotation: F64, new_translation: F64, old_rotation: F64, old_translation: F64
                       ) -> tuple[F64, F64]:
    """The transform taking points of an earlier sweep's sensor frame into the newest scan's, both sensor poses
    given in one world frame (sensor → world): ``p_new = R_newᵀ (R_old p + t_old − t_new)``."""
    rotation = new_rotation.T @ old_rotation
    translation = new_rotation.T @ (np.asarray(old_translation, np.float64) - np.asarray(new_translation, np.float64))
    return rotation, translation


def stack_sweeps(key: F32, earlier: Sequence[EarlierSweep], min_range_m: float = MIN_RANGE_M) -> F32:
    """(P, 5) float32 x, y, z, intensity, time lag: the ``key`` scan's (P, ≥4) points with lag 0, then every
    earlier sweep's moved into the key frame with its lag, their returns within ``min_range_m`` of their own
    sensor dropped first."""
    parts = [np.column_stack([key[:, :4], np.zeros(len(key), np.float32)]).astype(np.float32, copy=False)]
    for sw in earlier:
        p = sw.points
        p = p[np.hypot(p[:, 0], p[:, 1]) >= min_range_m]
        xyz = p[:, :3].astype(np.float64) @ sw.rotation.T + sw.translation
        parts.append(np.column_stack([xyz, p[:, 3], np.full(len(p), sw.time_lag_s)]).astype(np.float32))
    return np.concatenate(parts)


def pose_matrices(position: Sequence[float], orientation_xyzw: Sequence[float]) -> tuple[F64, F64]:
    """(3×3 rotation, translation) of a pose given as a position and an (x, y, z, w) quaternion."""
    return rotation_from_quaternion(*(float(v) for v in orientation_xyzw)), np.asarray(position, np.float64)


def sweeps_of(num_point_features: int, meta: Mapping[str, Any] | None) -> int:
    """How many sweeps a model takes: 1 for a four-field model; for a five-field one (x, y, z, intensity, time
    lag) what its training stacked (the weights' ``meta.source.sweeps``), :data:`DEFAULT_SWEEPS` when unrecorded."""
    if num_point_features < 5:
        return 1
    source = (meta or {}).get("source")
    n = source.get("sweeps") if isinstance(source, Mapping) else None
    return int(n) if isinstance(n, int) and n >= 1 else DEFAULT_SWEEPS


def _jumped(r0: F64, t0: F64, r1: F64, t1: F64, dt: float) -> bool:
    """Whether a sensor posed (r0, t0) and ``dt`` seconds later (r1, t1) moved faster than a vehicle can."""
    turn = math.acos(min(1.0, max(-1.0, (float(np.trace(r0.T @ r1)) - 1.0) / 2.0)))
    return bool(np.linalg.norm(t1 - t0) > MAX_EGO_SPEED_MPS * dt or turn > MAX_EGO_TURN_RAD_S * dt)


@dataclass(frozen=True)
class _Scan:
    stamp_ns: int
    rotation: F64
    translation: F64
    points: F32


class SweepStacker:
    """The scans a live stream has delivered lately, and the stack for the newest.

    :meth:`add` every scan that arrives — also those a busy detector will skip, so a stack never lacks sweeps
    because the network was slow — and :meth:`stack` the one the network takes: it gets that scan plus the up to
    ``sweeps − 1`` newest earlier ones no more than ``max_lag_s`` older. A scan whose stamp is not after the newest
    one held (a replay that rewound, a restarted source), or whose pose jumped from the newest one's (faster than
    :data:`MAX_EGO_SPEED_MPS` or :data:`MAX_EGO_TURN_RAD_S`: a relocalisation), clears the history first: sweeps of
    another time or place would be stacked in the wrong place. Memory is bounded by ``sweeps`` scans.
    """

    def __init__(self, sweeps: int, max_lag_s: float = MAX_LAG_S, min_range_m: float = MIN_RANGE_M) -> None:
        if sweeps < 1:
            raise ValueError("sweeps must be >= 1")
        if not max_lag_s > 0:
            raise ValueError("max_lag_s must be > 0")
        self.sweeps, self.max_lag_s, self.min_range_m = int(sweeps), float(max_lag_s), float(min_range_m)
        self._held: deque[_Scan] = deque(maxlen=self.sweeps)
        self.resets = 0
        """How often the history was cleared because time went back or the pose jumped."""
        self.last_stacked = 0
        """Scans in the latest :meth:`stack` (the newest included)."""

    def __len__(self) -> int:
        return len(self._held)

    def add(self, stamp_ns: int, rotation: F64, translation: F64, points: F32) -> None:
        """Hold one arriving scan (sensor-frame (P, ≥4) points; the sensor's pose in the world at ``stamp_ns``)."""
        if self.sweeps == 1:
            return
        rotation, translation = np.asarray(rotation, np.float64), np.asarray(translation, np.float64)
        if self._held:
            last = self._held[-1]
            if stamp_ns == last.stamp_ns:  # the same scan delivered twice: keep the first
                return
            dt = (stamp_ns - last.stamp_ns) * 1e-9
            if dt < 0.0 or _jumped(last.rotation, last.translation, rotation, translation, dt):
                self._held.clear()
                self.resets += 1
        self._held.append(_Scan(int(stamp_ns), rotation, translation, points))

    def earlier(self, stamp_ns: int, rotation: F64, translation: F64) -> list[EarlierSweep]:
        """The held scans before ``stamp_ns`` and within the lag, newest first, at most ``sweeps − 1``, in the
        frame of the sensor at ``(rotation, translation)``."""
        out: list[EarlierSweep] = []
        for s in reversed(self._held):
            if len(out) >= self.sweeps - 1:
                break
            lag = (stamp_ns - s.stamp_ns) * 1e-9
            if lag <= 0.0:
                continue
            if lag > self.max_lag_s:
                break
            r, t = relative_transform(rotation, translation, s.rotation, s.translation)
            out.append(EarlierSweep(s.points, r, t, lag))
        return out

    def stack(self, stamp_ns: int, rotation: F64, translation: F64, points: F32) -> F32:
        """(P, 5) points for the network: ``points`` (the scan taken, lag 0) and the earlier held sweeps
        (how many in all: :attr:`last_stacked`)."""
        earlier = self.earlier(stamp_ns, rotation, translation)
        self.last_stacked = 1 + len(earlier)
        return stack_sweeps(points, earlier, self.min_range_m)
