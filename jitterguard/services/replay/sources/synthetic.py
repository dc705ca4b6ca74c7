"""The synthetic world as a replay source: ray-cast scans (``points``) or the detection model's output
(``detections``), generated frame by frame from a scenario name and a seed — nothing is precomputed, so
an hour-long ``--loop`` costs no memory, and the same seed replays the same frames.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np

from ..frames import EgoPose, FrameError, Item, ScanFrame, SourceError, SourceInfo, finite_rows
from ....sim.world import SCENARIO_NAMES
from ..truth import truth_message
from .base import Source

SCENARIOS = SCENARIO_NAMES  # the world's own list: one place names the scenarios
MAX_DURATION_S = 600.0
"""The longest scenario the world generator makes."""
SCAN_FIELDS = ("x", "y", "z", "intensity", "ring")
"""nuScenes' LIDAR_TOP columns: a detector trained on either reads both the same way."""


def _world() -> Any:
    try:
        from ....sim import world
    except ImportError as exc:
        raise SourceError(f"synthetic sources need jitterguard.sim ({exc})") from None
    return world


def _lidar() -> Any:
    try:
        from ....sim import lidar
    except ImportError as exc:
        raise SourceError(f"synthetic scans need the ray-cast LiDAR jitterguard.sim.lidar ({exc})") from None
    return lidar


def check_synthetic(name: str, *, duration_s: float = 20.0, rate_hz: float = 10.0, level: str = "points",
                    lidar: str = "hdl32e", duration_flag: str = "--duration") -> SourceInfo:
    """What :class:`SyntheticSource` would say about these parameters, without generating the scenario; raises
    :class:`SourceError` for the ones it would refuse — among them a scenario shorter than one frame, which
    would publish nothing while the stack that checked it came up as if it were replaying. ``duration_flag``:
    the option the caller's user set ``duration_s`` with (``jitterguard up``'s ``--scenario-duration``)."""
    if name not in SCENARIOS:
        raise SourceError(f"synthetic:{name}: unknown scenario (have: {', '.join(SCENARIOS)})")
    if not (0 < duration_s <= MAX_DURATION_S) or not (rate_hz > 0):
        raise SourceError(f"synthetic:{name}: {duration_flag} must be in (0, {MAX_DURATION_S:g}] s and the frame rate"
                          " positive")
    _world()
    if level == "points":
        _lidar()
        from ....sim.sensors import SENSORS

        if lidar not in SENSORS:
            raise SourceError(f"--lidar {lidar!r}: unknown sensor (have: {', '.join(sorted(SENSORS))})")
    from ....sim.world import frame_count

    # the world's own count (whole frames only): a rounded count announced frames the source never yielded
    n = frame_count(duration_s, rate_hz)
    if n < 1:
        raise SourceError(f"synthetic:{name}: {duration_s:g} s at {rate_hz:g} Hz holds no whole frame; make"
                          f" {duration_flag} × the frame rate at least 1")
    return SourceInfo(name=f"synthetic:{name}", kind=level, num_frames=n,
                      notes=[f"{n} frames at {rate_hz:g} Hz" + (f", {lidar}" if level == "points" else "")])


class SyntheticSource(Source):
    """``synthetic:NAME`` for one of :data:`SCENARIOS`."""

    def __init__(
        self,
        name: str,
        *,
        seed: int = 0,
        duration_s: float = 20.0,
        rate_hz: float = 10.0,
        level: str = "points",
        lidar: str = "hdl32e",
    ) -> None:
        check_synthetic(name, duration_s=duration_s, rate_hz=rate_hz, level=level, lidar=lidar)
        world = _world()
        self._lidar = _lidar() if level == "points" else None
        self._spec = None
        self._sensor_z = float(getattr(world, "SENSOR_HEIGHT_M", 0.0))
        if self._lidar is not None:
            from ....sim.sensors import SENSORS

            self._spec = SENSORS[lidar]()
            self._sensor_z = float(self._spec.mount_height_m)
        self.name, self.seed, self.level = name, seed, level
        try:
            self.scenario = world.make_scenario(name, seed, duration_s=duration_s, rate_hz=rate_hz)
        except (ValueError, KeyError) as exc:
            raise SourceError(f"synthetic:{name}: {exc}") from None
        self.info = SourceInfo(
            name=f"synthetic:{name} (seed {seed})",
            kind=level,
            num_frames=int(self.scenario.num_frames),
            notes=[f"{self.scenario.num_frames} frames at {rate_hz:g} Hz" + (f", {lidar}" if level == "points" else "")],
            period_ns=int(round(1e9 / rate_hz)),
        )

    def frames(self, start: int = 0) -> Iterator[Item]:
        if self.level == "detections":
            yield from self._detections(start)
        else:
            yield from self._scans(start)

    def _scans(self, start: int) -> Iterator[Item]:
        for i in range(start, self.scenario.num_frames):
            gt = self.scenario.frame(i)
            origin = f"synthetic:{self.name}#{i}"
            try:
                res, _ = self._lidar.cast_frame(gt, self._spec, self.seed)
            except Exception as exc:  # a ray-cast failure is one bad frame, not the end of the replay
                yield FrameError(origin, f"ray-cast failed: {type(exc).__name__}: {exc}")
                continue
            pts = np.empty((res.points.shape[0], 5), dtype=np.float32)
            pts[:, :4] = res.points
            pts[:, 4] = res.ring
            pts, _ = finite_rows(pts)
            pose = EgoPose.from_yaw(float(gt.ego_x), float(gt.ego_y), float(gt.ego_yaw), z=self._sensor_z)
            yield ScanFrame(int(gt.stamp_ns), pose, pts, SCAN_FIELDS, origin, "lidar", truth=truth_message(gt))

    def _detections(self, start: int) -> Iterator[Item]:
        from .groundtruth import noisy_detections

        yield from noisy_detections(self.scenario.frame, self.scenario.num_frames, self.seed, start,
                                    f"synthetic:{self.name}")
