"""Every replay option that says *what* to replay, in one place: ``jitterguard replay`` parses them, and
``jitterguard up`` takes the same ones, checks the source with them before anything starts, and hands them to
the stack's replay program as flags (:meth:`ReplayOptions.argv`).

Why one dataclass: a flag added to the replay must reach the stack too, and a source that ``up`` accepted must
open the same way in the replay process; both follow from the one field list below. What is only about *how* a
standalone replay runs (``--loop``, ``--stamps``, ``--wait-subscriber``, ``--progress``) stays in the replay
command: the stack fixes those.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path

from .frames import SourceError
from .pacing import parse_rate
from .runner import ReplayPlan
from .sources import SYNTHETIC_PREFIX, SourceOptions

PATH_FIELDS = ("poses", "calib", "times")


@dataclass(frozen=True)
class ReplayOptions:
    """The replay's source and pacing options, as the command line spells them (strings where the CLI takes
    strings); defaults are the replay's own."""

    rate: str = "1"
    start: int = 0
    limit: int | None = None
    on_error: str = "skip"
    level: str = "points"
    seed: int = 0
    duration: float = 20.0
    lidar: str = "hdl32e"
    hz: float = 10.0
    scene: str | None = None
    nuscenes_version: str | None = None
    sweeps: bool = False
    poses: str | None = None
    calib: str | None = None
    times: str | None = None
    bin_fields: str | None = None
    topic: str | None = None
    pose_topic: str | None = None

    def flag(self, name: str) -> str:
        """The command-line flag of field ``name`` (``pose_topic`` → ``--pose-topic``)."""
        return "--" + name.replace("_", "-")

    def check(self) -> SourceOptions:
        """Validate the values (not the source itself) and build the readers' options; raises ``ValueError``
        with one line naming the flag."""
        parse_rate(self.rate)
        # from a frame every 1000 s: at --hz 1e-9 a tenth scan's stamp (row × 1e18 ns) outgrew the wire's int64
        # nanoseconds, and the replay ended after its first frame with a multi-line validation error and exit 1
        if not (1e-3 <= self.hz < 1e6):
            raise ValueError(f"--hz must be positive, from 0.001 to below 1e6 frames per second, got {self.hz}")
        self.plan()
        for name in PATH_FIELDS:
            value = getattr(self, name)
            if value is not None and not Path(value).is_file():
                raise ValueError(f"{self.flag(name)}: file not found: {value}")
        fields = tuple(f.strip() for f in self.bin_fields.split(",")) if self.bin_fields else None
        return SourceOptions(
            level=self.level, seed=self.seed, duration_s=self.duration, rate_hz=self.hz, lidar=self.lidar,
            scene=self.scene, nuscenes_version=self.nuscenes_version, sweeps=self.sweeps,
            poses=Path(self.poses) if self.poses else None, calib=Path(self.calib) if self.calib else None,
            times=Path(self.times) if self.times else None, bin_fields=fields, topic=self.topic,
            pose_topic=self.pose_topic, period_ns=int(round(1e9 / self.hz)),
        )

    def plan(self, *, loop: bool = False, stamps: str = "recorded") -> ReplayPlan:
        """The replay loop's plan for these options (raises ``ValueError`` on a bad --start/--limit/--on-error)."""
        return ReplayPlan(rate=parse_rate(self.rate), loop=loop, start=self.start, limit=self.limit,
                          on_error=self.on_error, stamps=stamps)  # type: ignore[arg-type]

    def absolute(self, cwd: str | None = None) -> "ReplayOptions":
        """The same options with every file path made absolute against ``cwd`` (default: the current folder),
        so they mean the same thing to a process started elsewhere (supervisord runs programs from the run
        directory)."""
        base = cwd or os.getcwd()
        return dataclasses.replace(self, **{
            name: os.path.normpath(os.path.join(base, os.path.expanduser(v)))
            for name in PATH_FIELDS if (v := getattr(self, name)) is not None})

    def changed(self) -> list[tuple[str, object]]:
        """(flag, value) for every option that differs from its default, in field order."""
        return [(self.flag(f.name), getattr(self, f.name)) for f in dataclasses.fields(self)
                if getattr(self, f.name) != f.default]

    def argv(self) -> list[str]:
        """The flags that differ from the defaults, in field order (what the stack's replay program gets)."""
        out: list[str] = []
        for flag, value in self.changed():
            out += [flag] if isinstance(value, bool) else [flag, str(value)]
        return out


def absolute_source(source: str, cwd: str | None = None) -> str:
    """SOURCE as a process started elsewhere must read it: synthetic names as they are, paths made absolute."""
    if source.startswith(SYNTHETIC_PREFIX):
        return source
    return os.path.normpath(os.path.join(cwd or os.getcwd(), os.path.expanduser(source)))


__all__ = ["ReplayOptions", "absolute_source", "SourceError"]
