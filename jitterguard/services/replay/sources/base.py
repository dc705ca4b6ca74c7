"""The one interface every replay source implements: a description and a lazy, restartable frame stream."""

from __future__ import annotations

import re
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from pathlib import Path

from ..frames import Item, SourceError, SourceInfo


class Source(ABC):
    """A recording opened for replay.

    ``frames(start)`` starts a fresh pass at recorded frame ``start`` every time it is called (``--loop``
    calls it once per pass), reads lazily (one frame in memory at a time), and yields a
    :class:`~jitterguard.services.replay.frames.FrameError` naming the file for a frame it cannot read.
    Problems that make the whole recording unusable are raised from the constructor as ``SourceError``.
    """

    info: SourceInfo

    @abstractmethod
    def frames(self, start: int = 0) -> Iterator[Item]:
        """Yield frames (or per-frame errors) from position ``start`` on."""

    def close(self) -> None:
        """Release file handles (bags); the default has nothing to release."""

    def __enter__(self) -> "Source":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class MemorySource(Source):
    """Frames already in memory: for benchmarks (no disk in the measured path) and tests."""

    def __init__(self, items: list[Item], name: str = "memory", kind: str = "points") -> None:
        self.items = list(items)
        self.info = SourceInfo(name=name, kind=kind, num_frames=len(self.items))

    def frames(self, start: int = 0) -> Iterator[Item]:
        yield from self.items[start:]


def natural_key(path: Path) -> list[int | str]:
    """Sort key that orders numbered files by number (``2.bin`` before ``10.bin``, ``frame_9`` before
    ``frame_10``); zero-padded names (KITTI's ``000010.bin``) sort as they do by name. The numbers are the runs of
    decimal digits the split found (odd places): ``str.isdigit`` had taken a superscript (``scan_1²2.bin``) for one,
    and its ``int`` failure refused the whole folder."""
    return [int(t) if i % 2 else t for i, t in enumerate(re.split(r"(\d+)", path.name))]


def listed_scans(folder: Path, is_scan: Callable[[str], bool]) -> list[Path]:
    """The files of ``folder`` whose name ``is_scan``, in numeric order of their names (:func:`natural_key`), hidden
    ones (macOS' ``._*`` companions) left out."""
    return sorted((p for p in folder.iterdir() if is_scan(p.name) and not p.name.startswith(".") and p.is_file()),
                  key=natural_key)


def check_start(start: int, info: SourceInfo) -> None:
    """Raise :func:`past_end`'s error when the source says how many frames it holds and ``start`` is not before the
    last: refused up front, before a session is opened or a detector loaded."""
    if info.num_frames is not None and start >= info.num_frames:
        raise past_end(start, info)


def past_end(start: int, info: SourceInfo) -> SourceError:
    """The error of a ``--start`` at or past the last frame of a source: nothing to replay (the replay's and
    ``jitterguard up``'s probe's one message)."""
    where = f" ({info.num_frames} frames)" if info.num_frames is not None else ""
    return SourceError(f"--start {start} is past the end of {info.name}{where}")
