"""Beam tables of real spinning LiDARs: what the ray caster needs to reproduce a sensor's scan pattern.

Elevations come from the manufacturers' data sheets: the HDL-32E's 32 lasers span −30.67° … +10.67° in equal
1.33° steps (nuScenes' LIDAR_TOP: 20 Hz, ≈1085 azimuth steps per turn, ±2 cm); the VLP-16's 16 lasers span
±15° in 2° steps; the Ouster OS1-64 (rev. 6) spreads 64 beams uniformly over 45°. ``rate_hz`` is the spin rate;
a scan is one full turn.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True, eq=False)
class LidarSpec:
    """A spinning LiDAR: beam elevations (radians, ascending; ring index = position in this array), azimuth
    steps per turn, spin rate, range limits and noise."""

    name: str
    elevations: NDArray[np.float64]
    azimuth_steps: int
    rate_hz: float
    range_sigma_m: float
    max_range_m: float
    min_range_m: float = 0.9
    dropout: float = 0.02
    """Probability that any return is lost (besides the weak far returns dropped by reflectivity and range)."""
    mount_height_m: float = 1.84
    extra: dict[str, float] = field(default_factory=dict)

    @property
    def num_beams(self) -> int:
        return len(self.elevations)

    @property
    def num_rays(self) -> int:
        return self.num_beams * self.azimuth_steps

    @property
    def elevations_deg(self) -> NDArray[np.float64]:
        return np.degrees(self.elevations)


def _spec(name: str, elev_deg: NDArray[np.float64], steps: int, rate: float, sigma: float, max_range: float,
          **kw: Any) -> LidarSpec:
    return LidarSpec(name, np.radians(np.sort(np.asarray(elev_deg, dtype=np.float64))), steps, rate, sigma, max_range,
                     **kw)


def hdl32e() -> LidarSpec:
    """Velodyne HDL-32E as mounted on nuScenes' LIDAR_TOP: 32 beams −30.67° … +10.67°, 20 Hz, ≈1085 steps."""
    return _spec("HDL-32E", np.linspace(-30.67, 10.67, 32), 1085, 20.0, 0.02, 100.0)


def vlp16() -> LidarSpec:
    """Velodyne VLP-16 (Puck): 16 beams −15° … +15° in 2° steps, 10 Hz at 0.2° azimuth resolution, ±3 cm."""
    return _spec("VLP-16", np.arange(-15.0, 15.1, 2.0), 1800, 10.0, 0.03, 100.0)


def os1_64() -> LidarSpec:
    """Ouster OS1-64 (rev. 6): 64 beams uniformly over 45° (−22.5° … +22.5°), 1024 × 10 Hz, 120 m."""
    return _spec("OS1-64", np.linspace(-22.5, 22.5, 64), 1024, 10.0, 0.03, 120.0)


SENSORS = {"hdl32e": hdl32e, "vlp16": vlp16, "os1-64": os1_64}
"""Sensor presets by CLI name."""


def azimuths(spec: LidarSpec) -> NDArray[np.float64]:
    """Azimuth of every column (radians, −π … π, column centres)."""
    return (-math.pi + (np.arange(spec.azimuth_steps) + 0.5) * (2.0 * math.pi / spec.azimuth_steps)).astype(np.float64)
