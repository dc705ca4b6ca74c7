"""Small builders shared by the replay tests (frames in memory, files on disk)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from jitterguard.services.replay.frames import EgoPose, FrameError, Item, ScanFrame
from jitterguard.services.replay.sources.base import MemorySource, Source

FIELDS4 = ("x", "y", "z", "intensity")
MS = 1_000_000


def scan(i: int, n: int = 16, stamp_ns: int | None = None, seed: int | None = None) -> ScanFrame:
    rng = np.random.default_rng(i if seed is None else seed)
    pts = rng.normal(size=(n, 4)).astype(np.float32)
    stamp = i * 100 * MS if stamp_ns is None else stamp_ns
    return ScanFrame(stamp, EgoPose.from_yaw(float(i), -float(i), 0.1 * i), pts, FIELDS4, f"mem#{i}")


def memory(n: int, errors: tuple[int, ...] = ()) -> MemorySource:
    items: list[Item] = [FrameError(f"bad{i}.bin", "corrupt") if i in errors else scan(i) for i in range(n)]
    return MemorySource(items)


class ExplodingSource(Source):
    """Yields two good frames, then its generator raises: how an unforeseen reader bug looks."""

    def __init__(self) -> None:
        from jitterguard.services.replay.frames import SourceInfo

        self.info = SourceInfo(name="exploding", kind="points", num_frames=5)

    def frames(self, start: int = 0) -> Iterator[Item]:
        yield scan(0)
        yield scan(1)
        raise OSError("disk went away")


def write_bin(path: Path, pts: np.ndarray) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.asarray(pts, dtype="<f4").tofile(path)
    return path


class FakeClock:
    """A clock that only moves when slept on (or advanced by hand); records every sleep."""

    def __init__(self, start: float = 1000.0) -> None:
        self.t = start
        self.sleeps: list[float] = []

    def now(self) -> float:
        return self.t

    def sleep(self, seconds: float) -> bool:
        self.sleeps.append(seconds)
        self.t += max(0.0, seconds)
        return True

    def advance(self, seconds: float) -> None:
        self.t += seconds
