"""``jitterguard calibrate RECORDING --out calibration.yaml``: fit the classifier's variance calibration offline.

Why: the online calibration needs a few hundred track windows before it trusts itself; a vehicle that starts
with last drive's scales decides well from its first frame. This command runs a recording through exactly the
live path — replay source → (scans) the detector service's steps → the tracker core through its wire
conversions → the classifier core with ``calibration: online`` — and writes the scales the online estimator
ends with (no labels anywhere; each block of observations counted once; no forgetting, so every part of the
recording counts the same). The classifier loads the file with ``calibration: file``
(``jitterguard classifier --calibration-file``; ``calibration_file`` in the config).
"""

from __future__ import annotations

import math
import sys
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
from pydantic import ValidationError

from ..cli_common import check_seed, fail, out_file, progress_on, refuse_foreign_file
from ..schemas.models import ClassifierConfig

if TYPE_CHECKING:
    from ..services.classifier.calibration import OnlineCalibration


def calibrate_detections(payloads: Iterable[bytes], config: "ClassifierConfig",
                         ) -> tuple["OnlineCalibration", dict[str, int]]:
    """The online calibration after every ``DetectedObjects`` payload of a recording (in order), and what it saw.

    Pure given its inputs: the payloads go through exactly the services' seams, as in the evaluator
    (:func:`.pipeline.track_and_classify`) — read by the tracker's read function into the tracker core, its
    ``tracks/{id}`` and ``tracked`` payloads into a classifier adapter with ``calibration: online``; the tracks
    still alive at the end give their last observations too (as the live classifier does on eviction).
    """
    from ..schemas import read_detected_objects
    from ..services.classifier.adapter import ClassifierAdapter
    from ..services.classifier.calibration import OnlineCalibration
    from ..services.tracker.adapter import detection_frame, observation_payloads, tracked_payload
    from ..services.tracker.config import default_config
    from ..services.tracker.core import FrameRejected, TrackerCore
    from .pipeline import _classify, _id_factory

    cfg = config.model_copy(update={"calibration": "online", "mode": "z_test"})
    cal = OnlineCalibration(tuple(cfg.calibration_range_bands_m), cfg.calibration_prior_blocks, math.inf,
                            cfg.window_size)
    trk = TrackerCore(default_config(), _id_factory())
    adapter = ClassifierAdapter(cfg, limits=trk.config.limits, calibration=cal)
    frames = detections = observations = 0
    for payload in payloads:
        det = read_detected_objects(payload, trk.config.limits)
        frame = detection_frame(det)
        try:
            result = trk.step(frame)
        except FrameRejected:
            continue
        frames += 1
        detections += len(frame.x)
        obs = [p for _, p in observation_payloads(det, frame, result)]
        observations += len(obs)
        _classify(adapter, obs, tracked_payload(det, frame, result), frame.stamp_ns * 1e-9)
    adapter.core.reset()
    cal.refit()
    return cal, {"frames": frames, "detections": detections, "observations": observations, **cal.counts}


def recording_detections(source: Any, detector: Any, start: int, limit: int | None,
                         errors: list[str]) -> Iterator[bytes]:
    """The ``DetectedObjects`` payload of every frame of a replay source: scans through the detector service's
    steps (``detector``: None for a source of detections), detection-level frames as the replay publishes them.
    Unreadable frames are skipped (appended to ``errors``)."""
    from ..schemas import encode
    from ..services.detector.adapter import detections_payload
    from ..services.replay.adapter import detections_message, point_cloud_message
    from ..services.replay.frames import FrameError, ScanFrame
    from ..services.detector.sweeps import SweepStacker
    from .detector_input import detect_scan

    stacker = SweepStacker(detector.sweeps) if detector is not None and detector.sweeps > 1 else None
    for i, item in enumerate(source.frames(start)):
        if limit is not None and i >= limit:
            return
        if isinstance(item, FrameError):
            errors.append(str(item))
            continue
        if isinstance(item, ScanFrame):
            scan = point_cloud_message(item, i, item.stamp_ns)
            det = detect_scan(detector.detect, scan, uncertainty=detector.config.uncertainty, stacker=stacker,
                              self_crop=detector.self_crop)
            yield detections_payload(det, scan.header, scan.ego_pose, detector.config.class_names)
        else:
            yield encode(detections_message(item, i, item.stamp_ns))


CALIBRATION_FORMAT_LINE = b"format: jitterguard-calibration/"


def is_calibration_file(head: bytes) -> bool:
    """Whether a file's first bytes are a calibration file's (re-running ``calibrate`` replaces its own output)."""
    return any(line.strip().startswith(CALIBRATION_FORMAT_LINE) for line in head.splitlines())


def calibrate_command(
    recording: Annotated[str, typer.Argument(help="Any replay source: synthetic:SCENARIO, a nuScenes dataroot, a "
                                             "bag, a folder of .bin or .pcd scans.")],
    out: Annotated[str, typer.Option("--out", help="The calibration file to write (YAML).")],
    weights: Annotated[Path | None, typer.Option("--weights", help="Detector weights for scan sources (default: the "
                                                 "shipped lite weights).")] = None,
    threads: Annotated[int | None, typer.Option("--threads", min=1, max=1024, help="torch CPU threads of the "
                                                "detector.")] = None,
    window_size: Annotated[int, typer.Option("--window-size", min=5, max=64, help="The classifier's window "
                                             "(blocks are windows; default: the classifier's; a recording slower "
                                             "than 10 Hz gets proportionally shorter ones, at least 10, one at 16 Hz "
                                             "or faster windows of every k-th frame, as the classifier's "
                                             "windows).")] = ClassifierConfig.model_fields["window_size"].default,
    range_bands: Annotated[str, typer.Option("--range-bands", help="Range band edges in metres, comma-separated."
                                             )] = "20,40",
    start: Annotated[int, typer.Option("--start", min=0, help="First frame (0-based).")] = 0,
    limit: Annotated[int | None, typer.Option("--limit", min=1, help="At most this many frames.")] = None,
    level: Annotated[str, typer.Option("--level", help="Synthetic sources: 'points' or 'detections'.")] = "points",
    seed: Annotated[int, typer.Option("--seed", help="Synthetic sources: scenario seed.")] = 0,
    duration: Annotated[float, typer.Option("--duration", help="Synthetic sources: length in seconds.")] = 20.0,
    hz: Annotated[float, typer.Option("--hz", help="Synthetic frame rate; stamp spacing of recordings without "
                                      "time.")] = 10.0,
    scene: Annotated[str | None, typer.Option("--scene", help="nuScenes: scene name or token.")] = None,
    topic: Annotated[str | None, typer.Option("--topic", help="Bags: the PointCloud2 or DetectedObjects "
                                              "topic.")] = None,
    pose_topic: Annotated[str | None, typer.Option("--pose-topic", help="Bags: the ego pose topic (/tf, "
                                                   "Odometry, PoseStamped).")] = None,
    progress: Annotated[bool | None, typer.Option("--progress/--no-progress", help="Progress bar (default: when "
                                                  "stderr is a terminal).")] = None,
) -> None:
    """Fit the classifier's variance calibration from a recording (no labels); write it for calibration: file."""
    if not recording.strip():  # Path("") is the current folder: ".: cannot tell what this folder is" named nothing
        fail("RECORDING: empty path; give a recording")
    out_path = out_file("--out", out)  # before the pass over the recording, not after it (a str: Path("") is ".")
    refuse_foreign_file("--out", out_path, is_calibration_file, "a calibration file")
    from ..services.classifier.calibration_file import write_calibration
    from ..services.replay.frames import SourceError
    from ..services.replay.sources import SourceOptions, open_source
    from ..services.replay.sources.base import check_start

    try:
        bands = [float(x) for x in range_bands.split(",") if x.strip()]
    except ValueError:
        fail(f"--range-bands: {range_bands!r} is not a comma-separated list of distances in metres")
    try:
        cfg = ClassifierConfig(window_size=window_size, calibration_range_bands_m=bands)
    except ValidationError as exc:  # the first error, named by its flag (not pydantic's dump, cut mid-URL)
        err = exc.errors(include_url=False)[0]
        flag = "--range-bands" if err["loc"] and err["loc"][0] == "calibration_range_bands_m" else "--window-size"
        fail(f"{flag}: {err['msg']}")
    if not 0 < hz < 1e6:
        fail(f"--hz: {hz} is out of range: it must be positive and below 1e6")
    if not 0 < duration <= 3600:
        fail(f"--duration: {duration} s is out of range: it must be in (0, 3600]")
    check_seed("--seed", seed)
    opts = SourceOptions(level=level, seed=seed, duration_s=duration, rate_hz=hz, scene=scene, topic=topic,
                         pose_topic=pose_topic, period_ns=int(round(1e9 / hz)))
    try:
        src = open_source(recording, opts)
    except SourceError as exc:
        fail(str(exc))
    except Exception as exc:  # a reader that failed in a way it did not foresee: still one line
        fail(f"{recording}: cannot open: {type(exc).__name__}: {exc}")
    if start:  # past the end: refused before a detector is loaded or a frame read
        try:
            check_start(start, src.info)
        except SourceError as exc:
            fail(str(exc))
    detector = None
    for warning in src.info.warnings:  # e.g. a bag without --pose-topic: its scans all at the identity pose
        print(f"jitterguard: warning: {warning}", file=sys.stderr)
    with src:
        if src.info.kind == "points":
            from .cli import load_detector

            detector, _ = load_detector(weights, threads)
        elif weights is not None or threads is not None:
            fail("--weights and --threads apply to scan sources; this one holds detections")
        errors: list[str] = []
        msgs: Iterable[Any] = recording_detections(src, detector, start, limit, errors)
        if progress_on(progress):
            from tqdm import tqdm  # type: ignore[import-untyped]

            total = src.info.num_frames
            msgs = tqdm(msgs, total=None if total is None else max(0, min(total - start, limit or total)),
                        desc="calibrate", unit="frame", file=sys.stderr)
        cal, seen = calibrate_detections(msgs, cfg)
    if seen["frames"] == 0 and errors:
        fail(f"{recording}: none of its {len(errors)} frame(s) read; first: {errors[0]}")
    # nothing to track: the advice below ("use a longer recording") would not help either
    if seen["frames"] and seen["detections"] == 0:
        fail(f"{recording}: no detections in any of its {seen['frames']} frames (empty scans, or nothing the"
             " detector finds in them): no tracks to calibrate from")
    if seen["detections"] and seen["observations"] == 0:
        fail(f"{recording}: its {seen['detections']} detections in {seen['frames']} frames formed no track (a track"
             " takes an object seen in several frames): no tracks to calibrate from; use a longer recording")
    if seen["blocks"] == 0 and seen["blocks_fast"]:  # "use a longer recording" would not help
        from ..services.classifier.calibration import MAX_BLOCK_SPEED

        fail(f"{recording}: every one of its {seen['blocks_fast']} track windows was of an object moving faster than"
             f" {MAX_BLOCK_SPEED:g} m/s; the calibration learns from objects standing or creeping (parked cars,"
             " standing people): use a recording that has some")
    if seen["blocks"] == 0:
        fail(f"{recording}: no track stood still long enough to calibrate on ({seen['frames']} frames, "
             f"{seen['observations']} observations); use a longer recording")
    if seen["blocks"] < cfg.calibration_prior_blocks:  # a file is applied in full: no prior tempers it there
        print(f"jitterguard: warning: {recording}: only {seen['blocks']} blocks (fewer than the prior's"
              f" {cfg.calibration_prior_blocks:g}); the classifier applies a file's scales in full, so scales fitted on"
              " this little evidence can be far off: use a longer recording", file=sys.stderr)
    source = {"recording": recording, "frames": seen["frames"], "observations": seen["observations"],
              "blocks": seen["blocks"], "blocks_fast": seen["blocks_fast"], "unreadable_frames": len(errors)}
    write_calibration(out_path, cal.model(), window=cal.window, source=source)  # a slow recording's shorter window
    print(f"wrote {out_path}: {seen['blocks']} blocks from {seen['frames']} frames"
          + (f" ({len(errors)} unreadable frames skipped)" if errors else ""))


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add ``calibrate`` (no benchmark)."""
    app.command("calibrate")(calibrate_command)
