"""Pure readers, one per recording format, and :func:`open_source` which picks one from a SOURCE argument.

SOURCE forms:

- ``synthetic:SCENARIO`` — the synthetic world (``parking-street``, ``diagonal-lot``, ``intersection``,
  ``mixed``) generated on the fly from ``seed``; ``level='detections'`` replays the synthetic detection model
  instead of ray-cast scans.
- a nuScenes dataroot (a folder holding ``v1.0-*/scene.json``), with ``scene``; ``level='detections'`` replays
  the scene's annotated boxes through the same detection model (:mod:`.groundtruth`).
- a ROS 2 bag folder (``metadata.yaml``), a ``.mcap`` / ``.db3`` file, or a ROS 1 ``.bag``.
- a folder of (or one) KITTI ``.bin`` / nuScenes ``.pcd.bin`` scans, with optional KITTI ``poses``.
- a folder of (or one) ``.pcd`` files.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..frames import (DEFAULT_PERIOD_NS, NO_POSE_YET, FrameError, SourceError, SourceInfo, pose_refusal,
                      scan_refusal)
from .base import MemorySource, Source, check_start, past_end

__all__ = ["Source", "MemorySource", "SourceOptions", "SourceError", "open_source", "probe_source",
           "SYNTHETIC_PREFIX"]

PROBE_FRAMES = 10
"""``probe_source`` reads up to this many frames looking for one that reads: one bad frame is skipped in a
replay, a recording none of whose first frames reads is refused."""
PROBE_BEFORE_POSES = 1200
"""Scans recorded before the first pose (localization started late: 2 min at 10 Hz) that the check reads past, not
counting them as unreadable: the replay skips them and goes on."""

SYNTHETIC_PREFIX = "synthetic:"
BAG_FILE_SUFFIXES = (".mcap", ".db3", ".bag")


@dataclass(frozen=True)
class SourceOptions:
    """Every reader option the CLI exposes; each reader uses the ones that apply to it."""

    level: str = "points"
    seed: int = 0
    duration_s: float = 20.0
    rate_hz: float = 10.0
    scene: str | None = None
    nuscenes_version: str | None = None
    channel: str = "LIDAR_TOP"
    sweeps: bool = False
    poses: Path | None = None
    calib: Path | None = None
    times: Path | None = None
    bin_fields: tuple[str, ...] | None = None
    topic: str | None = None
    pose_topic: str | None = None
    period_ns: int = DEFAULT_PERIOD_NS
    lidar: str = "hdl32e"


_DEFAULTS = SourceOptions()
PACED_BY_HZ = {"--hz"}
"""Readers of recordings without their own clock (KITTI without times.txt, .pcd): ``--hz`` spaces their stamps."""
KITTI_FLAGS = {"--poses", "--calib", "--times", "--bin-fields"} | PACED_BY_HZ
"""What a folder of (or one) KITTI ``.bin`` scan takes."""


def _only_for(opts: SourceOptions, kind: str, allowed: set[str], *, duration_flag: str = "--duration") -> None:
    """Refuse flags that the chosen reader would silently ignore: a typo'd source must not look like success.

    ``--seed``, ``--duration`` and ``--hz`` count as given when they differ from their defaults (the options
    carry values, not where they came from): ``--duration 30`` on a bag had replayed the whole bag in silence."""
    given = {
        "--seed": opts.seed != _DEFAULTS.seed,
        duration_flag: opts.duration_s != _DEFAULTS.duration_s,
        "--hz": opts.rate_hz != _DEFAULTS.rate_hz,
        "--scene": opts.scene is not None,
        "--nuscenes-version": opts.nuscenes_version is not None,
        "--sweeps": opts.sweeps,
        "--poses": opts.poses is not None,
        "--calib": opts.calib is not None,
        "--times": opts.times is not None,
        "--bin-fields": opts.bin_fields is not None,
        "--topic": opts.topic is not None,
        "--pose-topic": opts.pose_topic is not None,
        "--lidar": opts.lidar != "hdl32e",
    }
    stray = sorted(flag for flag, on in given.items() if on and flag not in allowed)
    if stray:
        verb = "does" if len(stray) == 1 else "do"
        raise SourceError(f"{', '.join(stray)} {verb} not apply to a {kind} source")
    if opts.level != "points" and kind not in ("synthetic", "nuScenes"):
        raise SourceError(f"--level {opts.level} needs ground-truth boxes: synthetic and nuScenes sources have"
                          f" them, a {kind} source has not (a bag's topic type decides its level)")


SYNTHETIC_FLAGS = {"--lidar", "--seed", "--hz"}
"""What a synthetic scenario takes besides its length (named by the caller's ``duration_flag``)."""


def open_source(spec: str, opts: SourceOptions | None = None, *, duration_flag: str = "--duration") -> Source:
    """Open SOURCE (see the module docstring). Raises :class:`SourceError` with one line naming the problem;
    ``duration_flag`` is the caller's name for a scenario's length (``up`` calls it ``--scenario-duration``)."""
    opts = opts or SourceOptions()
    if opts.level not in ("points", "detections"):
        raise SourceError(f"--level must be 'points' or 'detections', got {opts.level!r}")
    if spec.startswith(SYNTHETIC_PREFIX):
        _only_for(opts, "synthetic", SYNTHETIC_FLAGS | {duration_flag}, duration_flag=duration_flag)
        from .synthetic import SyntheticSource  # each reader only when its format is asked for

        return SyntheticSource(
            spec[len(SYNTHETIC_PREFIX) :],
            seed=opts.seed,
            duration_s=opts.duration_s,
            rate_hz=opts.rate_hz,
            level=opts.level,
            lidar=opts.lidar,
        )
    path = Path(spec)
    if not path.exists():
        hint = " (synthetic scenarios are spelled synthetic:NAME)" if ":" not in spec and "/" not in spec else ""
        raise SourceError(f"{spec}: no such file or folder{hint}")
    # each reader only when a path is given: rosbags and the nuScenes tables are optional extras
    from .bag import BagSource, is_bag
    from .kitti import BinScanSource
    from .nuscenes import NuScenesSource, is_nuscenes_root
    from .pcd import PcdSource

    if is_nuscenes_root(path):
        # the seed draws the detection model's noise about the annotated boxes; scans have none to draw
        seeded = {"--seed"} if opts.level == "detections" else set()
        _only_for(opts, "nuScenes", {"--scene", "--nuscenes-version", "--sweeps"} | seeded, duration_flag=duration_flag)
        if opts.level == "detections":
            if opts.sweeps:
                raise SourceError("--level detections replays a scene's annotated key frames: --sweeps does not"
                                  " apply")
            from .groundtruth import NuScenesBoxes

            return NuScenesBoxes(path, scene=opts.scene, seed=opts.seed, version=opts.nuscenes_version)
        return NuScenesSource(path, scene=opts.scene, version=opts.nuscenes_version, channel=opts.channel, sweeps=opts.sweeps)
    if is_bag(path):
        _only_for(opts, "bag", {"--topic", "--pose-topic"}, duration_flag=duration_flag)
        return BagSource(path, topic=opts.topic, pose_topic=opts.pose_topic)
    if path.is_dir():
        try:
            names = [p.name for p in path.iterdir() if p.is_file()]
        except OSError as exc:
            raise SourceError(f"{path}: cannot list folder: {exc}") from None
        has_bin = any(n.lower().endswith(".bin") for n in names)
        has_pcd = any(n.lower().endswith(".pcd") for n in names)
        if has_bin and has_pcd:
            raise SourceError(f"{path}: holds both .bin and .pcd files; point SOURCE at one kind")
        if has_pcd:
            _only_for(opts, "PCD", PACED_BY_HZ, duration_flag=duration_flag)
            return PcdSource(path, period_ns=opts.period_ns)
        if has_bin:
            _only_for(opts, "KITTI .bin", KITTI_FLAGS, duration_flag=duration_flag)
            return BinScanSource(
                path, poses=opts.poses, calib=opts.calib, times=opts.times, fields=opts.bin_fields, period_ns=opts.period_ns
            )
        bag_files = sorted(n for n in names if n.lower().endswith(BAG_FILE_SUFFIXES))
        if bag_files:  # a rosbag2 folder whose recorder died before it wrote metadata.yaml (SIGKILL)
            raise SourceError(f"{path}: no metadata.yaml, but it holds {', '.join(bag_files[:3])}"
                              f"{' …' if len(bag_files) > 3 else ''}: give that file as SOURCE (an MCAP cut short has"
                              " no footer either: `mcap recover` rewrites it whole)")
        above = next((up for up in (path.parent, path.parent.parent) if is_nuscenes_root(up)), None)
        if above is not None:  # its table folder (v1.0-mini) or samples/: "no nuScenes tables" had been the answer
            raise SourceError(f"{path}: a folder inside the nuScenes dataroot {above}: give the dataroot as SOURCE")
        raise SourceError(
            f"{path}: cannot tell what this folder is (no nuScenes tables, bag metadata.yaml, .bin or .pcd files)"
        )
    if path.name.lower().endswith(".bin"):  # cameras and Windows tools write .BIN as well
        _only_for(opts, "KITTI .bin", KITTI_FLAGS, duration_flag=duration_flag)
        return BinScanSource(path, poses=opts.poses, calib=opts.calib, times=opts.times, fields=opts.bin_fields, period_ns=opts.period_ns)
    if path.suffix.lower() == ".pcd":
        _only_for(opts, "PCD", PACED_BY_HZ, duration_flag=duration_flag)
        return PcdSource(path, period_ns=opts.period_ns)
    raise SourceError(f"{path}: unknown recording type (expected .bin, .pcd, .mcap, .db3, .bag or a folder)")


def probe_source(spec: str, opts: SourceOptions | None = None, *, start: int = 0,
                 duration_flag: str = "--duration") -> SourceInfo:
    """Check SOURCE without replaying it: what ``jitterguard up`` does before it starts anything.

    A synthetic scenario is checked by name and parameters only (generating it takes seconds, and the replay
    process does that). Anything else is opened with its reader, which checks the kind, tables, topics and
    poses, and read from frame ``start`` (the replay's ``--start``) until a frame reads with an ego pose the replay
    publishes (:func:`~..frames.pose_refusal`; at most :data:`PROBE_FRAMES`). Raises :class:`SourceError` with the reader's own one-line message, or the replay's
    when ``start`` lies past the end; ``duration_flag`` names the option that set a scenario's length.
    """
    opts = opts or SourceOptions()
    if spec.startswith(SYNTHETIC_PREFIX):
        if opts.level not in ("points", "detections"):
            raise SourceError(f"--level must be 'points' or 'detections', got {opts.level!r}")
        _only_for(opts, "synthetic", SYNTHETIC_FLAGS | {duration_flag}, duration_flag=duration_flag)
        from .synthetic import check_synthetic

        info = check_synthetic(spec[len(SYNTHETIC_PREFIX) :], duration_s=opts.duration_s, rate_hz=opts.rate_hz,
                               level=opts.level, lidar=opts.lidar, duration_flag=duration_flag)
        check_start(start, info)
        return info
    try:
        src = open_source(spec, opts, duration_flag=duration_flag)
    except SourceError:
        raise
    except Exception as exc:  # a reader that failed in a way it did not foresee: still one line
        raise SourceError(f"{spec}: cannot open: {type(exc).__name__}: {exc}") from None
    with src:
        errors: list[str] = []
        waited = 0
        try:
            for item in src.frames(start):
                if not isinstance(item, FrameError):
                    # the replay's own rules: a frame it would skip is no frame
                    item = pose_refusal(item) or scan_refusal(item) or item
                if not isinstance(item, FrameError):
                    return src.info
                if item.reason.startswith(NO_POSE_YET):  # localization starts late: the replay skips these too
                    waited += 1
                    if waited < PROBE_BEFORE_POSES:
                        continue
                errors.append(str(item))
                if len(errors) >= PROBE_FRAMES:
                    break
        except SourceError:
            raise
        except Exception as exc:
            raise SourceError(f"{spec}: reading failed: {type(exc).__name__}: {exc}") from None
    if errors:
        raise SourceError(f"none of the first {len(errors)} frame(s) reads; first: {errors[0]}")
    if start:
        raise past_end(start, src.info)
    raise SourceError(f"{spec}: holds no frame")
