"""``jitterguard eval``: the paper's offline validation (§IV-B) on a synthetic scenario or a nuScenes scene.

Runs ground truth → detection-level noise (``--input gt-noise``) or ray-cast / recorded scans → the CenterPoint
detector (``--input detector``) → tracker core → classifier cores in-process, and writes report.md,
metrics.json and figures into ``--out``. With the detector in the loop metrics.json also holds its nuScenes
AP and positional calibration (``detection``), and the calibration and detection PR figures are written.

Commands import their implementation when they run (start-up time: see :mod:`jitterguard.cli`).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from collections.abc import Sequence
from typing import TYPE_CHECKING, Annotated, Any

import typer

from ..cli_common import (SensorHeightOpt, SensorTiltOpt, check_seed, fail, out_dir, out_files, parse_seeds,
                          progress_on, sensor_height_option, sensor_tilt_option)
from ..files import write_atomically

if TYPE_CHECKING:
    from ..services.detector.inference import Detector

INPUTS = ("gt-noise", "detector")
PARTIAL = ".partial"
"""Suffix of a run's MCAP while the run is going (:func:`evaluate` names it ``run-….mcap`` once its metrics are out)."""


def eval_command(
    out: Annotated[str, typer.Option("--out", help="Folder for report.md, metrics.json and the PNGs.")],
    scenario: Annotated[str | None, typer.Option("--scenario", help="Synthetic scenario (default parking-street).")] = None,
    seed: Annotated[int, typer.Option("--seed", help="Seeds the scenario and the noise model.")] = 0,
    input_: Annotated[str, typer.Option("--input", help="gt-noise (ground truth through the noise model) or detector.")] = "gt-noise",
    noise: Annotated[str | None, typer.Option("--noise", help="Noise preset of --input gt-noise: clean, jittery"
                                              " (default), paper or oracle (exact variances: never a headline).")
                     ] = None,
    weights: Annotated[Path | None, typer.Option("--weights", help="Detector weights file for --input detector"
                                                 " (default: the shipped lite weights).")] = None,
    threads: Annotated[int | None, typer.Option("--threads", min=1, max=1024, help="torch CPU threads of the"
                                                " detector (default: the machine's cores).")] = None,
    self_crop: Annotated[bool, typer.Option("--self-crop/--no-self-crop", help="Drop the returns of the vehicle's"
                                            " own body before the detector (the service's default self_crop"
                                            " box), as the live detector does.")] = True,
    detector_flips: Annotated[bool, typer.Option("--detector-flips/--no-detector-flips", help="The detector averages"
                                                 " the scan and its three mirror images (its flips setting).")
                              ] = False,
    sensor_height: SensorHeightOpt = None,
    sensor_tilt: SensorTiltOpt = None,
    nuscenes: Annotated[Path | None, typer.Option("--nuscenes", help="nuScenes dataroot instead of a scenario.")] = None,
    nuscenes_version: Annotated[str | None, typer.Option(
        "--nuscenes-version", help="nuScenes: table folder, e.g. v1.0-trainval (default: the only one).")] = None,
    scene: Annotated[str | None, typer.Option("--scene", help="nuScenes scene name or token; several "
                                              "comma-separated, or 'all', are pooled as one drive.")] = None,
    sweeps: Annotated[bool, typer.Option("--sweeps/--no-sweeps", help="nuScenes with --input detector: run the "
                                         "detector, tracker and classifier on every LiDAR sweep (20 Hz, as "
                                         "`jitterguard replay --sweeps` feeds the live stack) and score the "
                                         "labelled key frames among them.")] = False,
    duration: Annotated[float | None, typer.Option("--duration", help="Synthetic scenario length \\[s] (default 15;"
                                                   " not with --nuscenes).")] = None,
    rate: Annotated[float | None, typer.Option("--rate", help="Synthetic frame rate [Hz] (default 10; not with"
                                               " --nuscenes).")] = None,
    preset: Annotated[str | None, typer.Option("--preset", help="Classifier preset: authors, autoware-sustain, hold, paper (jitterguard/config/classifier.<name>.param.yaml).")] = None,
    alpha: Annotated[float | None, typer.Option("--alpha", help="alpha_default of the z-test (no per-class overrides).")] = None,
    velocity_threshold: Annotated[float | None, typer.Option("--velocity-threshold", help="The baseline's speed"
                                                             " cut-off for every class \\[m/s] (default: Autoware's"
                                                             " per class, 1.0 vehicles and motorcycles, 0.28 others).")] = None,
    runs: Annotated[int, typer.Option("--runs", help="Pool seeds seed … seed+runs-1 into one scored table (one "
                                      "drive: the online calibration carries over).")] = 1,
    variance_scale: Annotated[float, typer.Option("--variance-scale", help="Multiply every reported position "
                                                  "variance by this before the tracker (a detector off by a "
                                                  "constant factor); 0: no covariance reported at all (as "
                                                  "Autoware's lidar_centerpoint).")] = 1.0,
    variance_scale_at: Annotated[str, typer.Option("--variance-scale-at", help="detector (its output: the tracker "
                                                   "sees the scaled variances too) or classifier (only what "
                                                   "the classifier receives).")] = "detector",
    calibration: Annotated[str | None, typer.Option("--calibration", help="online (default), off or file.")] = None,
    calibration_file: Annotated[Path | None, typer.Option("--calibration-file", help="YAML from `jitterguard "
                                                          "calibrate`; implies --calibration file.")] = None,
    mode: Annotated[str | None, typer.Option("--mode", help="The test scored against the speed threshold: z_test "
                                             "(default; the paper's max over two axes) or chi2 (the 2-D statistic "
                                             "at the same nominal rate as one axis).")] = None,
    effective_n: Annotated[str | None, typer.Option("--effective-n", help="measured (default), cluster or "
                                                    "independent.")] = None,
    min_speed: Annotated[float | None, typer.Option("--min-speed", help="The test's H0 speed bound, m/s "
                                                    "(default 0.1).")] = None,
    window_size: Annotated[int | None, typer.Option("--window-size", help="Observations per track window "
                                                    "(default 20 at 10 Hz; a slower stream gets the same span, "
                                                    "at least 10, a faster one every k-th frame; the paper's 10: "
                                                    "--window-size 10).")] = None,
    view_slide: Annotated[float | None, typer.Option("--view-slide", help="The view term for vehicles (car, "
                                                     "truck, bus, trailer): how far a box centre slides per unit "
                                                     "turn of the line of sight, m (0: none; "
                                                     "view_slide_m_per_class).")] = None,
    jump_veto: Annotated[bool, typer.Option("--jump-veto/--no-jump-veto", help="A window the test rejects (a "
                                            "vehicle's from 6 observations, another class's once full) that one "
                                            "jump of the box explains better than steady motion is not called "
                                            "dynamic (jump_veto; --no-jump-veto: the paper's test alone).")] = True,
    fixed_window: Annotated[bool, typer.Option("--fixed-window/--no-fixed-window", help="The window holds "
                                               "window_size observations of every frame at any frame rate "
                                               "(window_reference_hz: null).")] = False,
    speed_sustain: Annotated[bool, typer.Option("--speed-sustain/--no-speed-sustain", help="The baseline holds "
                                                "Autoware's sustain times (2 s vehicles, 1 s others).")] = False,
    tracker_config: Annotated[Path | None, typer.Option("--tracker-config", help="Tracker parameter file (as "
                                                        "`jitterguard tracker --config`; default: the shipped "
                                                        "one).")] = None,
    mcap: Annotated[bool, typer.Option("--mcap/--no-mcap", help="Also record every evaluated frame to "
                                       "OUT/run-SEED.mcap for Foxglove (detections, tracks by the z-test's "
                                       "decision, motion states, ground truth); pooled nuScenes scenes: "
                                       "OUT/run-SCENE.mcap, named so once metrics.json is written (an "
                                       "interrupted run leaves none). An earlier run's run-*.mcap in OUT are "
                                       "removed, with or without it: they would not match the new metrics.")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Also print metrics.json to stdout.")] = False,
) -> None:
    """Evaluate (detector →) tracker → motion classifier offline against ground truth."""
    from ..schemas.models import ClassifierConfig
    from ..services.classifier.config import PRESETS
    from .pipeline import NOISE_PRESETS

    check_seed("--seed", seed)
    if input_ not in INPUTS:
        fail(f"--input: unknown input {input_!r}; expected one of {', '.join(INPUTS)}")
    if input_ == "detector":
        if noise is not None:
            fail("--noise applies to --input gt-noise; the detector's errors are its own")
        if nuscenes is not None and runs > 1:
            fail("--runs pools noise draws or synthetic seeds; with --input detector a nuScenes scene gives the "
                 "same run every time")
    else:
        if (weights is not None or threads is not None or not self_crop or detector_flips or sensor_height is not None
                or sensor_tilt is not None):
            fail("--weights, --threads, --no-self-crop, --detector-flips, --sensor-height and --sensor-tilt need"
                 " --input detector")
        noise = noise or "jittery"
    if noise is not None and noise not in NOISE_PRESETS:
        fail(f"--noise: unknown preset {noise!r}; expected one of {', '.join(NOISE_PRESETS)}")
    if nuscenes is not None and scenario is not None:
        fail("give --scenario or --nuscenes, not both")
    if scene is not None and nuscenes is None:
        fail("--scene needs --nuscenes")
    if nuscenes_version is not None and nuscenes is None:
        fail("--nuscenes-version needs --nuscenes")
    if sweeps and (nuscenes is None or input_ != "detector"):
        fail("--sweeps needs --nuscenes and --input detector (nuScenes labels only its key frames, so the noise "
             "model has no boxes to draw from between them)")
    if preset is not None and preset not in PRESETS:
        fail(f"--preset: unknown preset {preset!r}; expected one of {', '.join(PRESETS)}")
    if nuscenes is not None and (duration is not None or rate is not None):
        fail("--duration and --rate set a synthetic scenario; a --nuscenes scene is scored whole, at its own rate")
    duration = 15.0 if duration is None else duration
    rate = 10.0 if rate is None else rate
    if not 0 < duration <= 600 or not 0 < rate <= 100:
        fail("--duration must be in (0, 600] and --rate in (0, 100]")
    if nuscenes is None:
        check_whole_frame(duration, rate)
    if not 1 <= runs <= 50:
        fail("--runs must be in [1, 50]")
    if not (1e-3 <= variance_scale <= 1e3 or variance_scale == 0.0):
        fail("--variance-scale must be in [0.001, 1000], or 0 (no covariance reported)")
    if variance_scale_at not in ("detector", "classifier"):
        fail(f"--variance-scale-at: expected detector or classifier, got {variance_scale_at!r}")
    if mode is not None and mode not in ("z_test", "chi2"):
        fail(f"--mode: expected z_test or chi2, got {mode!r} (the speed threshold is always scored beside it)")
    upd: dict[str, Any] = dict(PRESETS[preset]) if preset else {}
    flag_of: dict[str, str] = {}  # config key → the flag that set it: a refusal names what the user typed
    if mode is not None:
        upd["mode"] = mode
        flag_of["mode"] = "--mode"
    if alpha is not None:
        upd.update(alpha_default=alpha, alpha_per_class={})
        flag_of.update(alpha_default="--alpha", alpha_per_class="--alpha")
    if velocity_threshold is not None:  # every class, as --alpha: it had left the 0.28 m/s of the others in force
        upd.update(velocity_threshold=velocity_threshold, velocity_threshold_per_class={})
        flag_of.update(velocity_threshold="--velocity-threshold", velocity_threshold_per_class="--velocity-threshold")
    if calibration_file is not None and calibration is None:
        calibration = "file"
    if calibration_file is not None and calibration != "file":
        fail(f"--calibration-file is read with --calibration file, not {calibration}")
    if calibration == "file" and calibration_file is None:  # as the classifier's CLI says it (had named no flag)
        fail("--calibration file: needs --calibration-file FILE (a YAML from `jitterguard calibrate`)")
    for key, flag, value in (("calibration", "--calibration", calibration),
                             ("effective_n", "--effective-n", effective_n),
                             ("min_speed_mps", "--min-speed", min_speed), ("window_size", "--window-size", window_size),
                             ("calibration_file", "--calibration-file",
                              None if calibration_file is None else str(calibration_file))):
        if value is not None:
            upd[key] = value
            flag_of[key] = flag
    if view_slide is not None:  # its bounds are the config's: a bad value fails its validation below, by name
        from ..services.classifier.calibration import vehicle_class_names
        upd["view_slide_m_per_class"] = {} if view_slide == 0 else dict.fromkeys(vehicle_class_names(), view_slide)
        flag_of["view_slide_m_per_class"] = "--view-slide"
    if fixed_window:
        upd["window_reference_hz"] = None
    if not jump_veto:
        upd["jump_veto"] = False
    if speed_sustain:
        upd.update(PRESETS["autoware-sustain"])
    try:
        cfg = ClassifierConfig.model_validate({**ClassifierConfig().model_dump(), **upd})
    except ValueError as exc:
        err = exc.errors()[0] if hasattr(exc, "errors") else None
        loc = tuple(err["loc"]) if err and err.get("loc") else ()
        where = ".".join(str(x) for x in loc) if loc else "classifier config"
        if loc and str(loc[0]) in flag_of:  # the flag the user typed, the key beside it (as the docs name both)
            where = f"{flag_of[str(loc[0])]} ({where})"
        fail(f"{where}: {err['msg'] if err else str(exc).splitlines()[0]}")
    from ..config import ConfigError
    from ..services.tracker.config import load_config

    try:
        tracker = load_config(tracker_config)
    except ConfigError as exc:
        fail(f"--tracker-config: {exc}")
    model = None
    if cfg.calibration == "file":
        from ..services.classifier.calibration_file import CalibrationFileError, read_calibration

        try:
            model = read_calibration(cfg.calibration_file or "")
        except CalibrationFileError as exc:
            fail(f"--calibration-file: {exc}")
    height, tilt = sensor_height_option(sensor_height), sensor_tilt_option(sensor_tilt)
    detector, weights_desc = (load_detector(weights, threads, self_crop, detector_flips, height, tilt)
                              if input_ == "detector" else (None, None))

    if nuscenes is None:  # checked before --out is made: a refused run had left an empty folder behind
        from ..sim.world import SCENARIO_NAMES

        if scenario is not None and scenario not in SCENARIO_NAMES:
            fail(f"--scenario: unknown scenario {scenario!r}; expected one of {', '.join(SCENARIO_NAMES)}")
    else:
        from .groundtruth import NuScenesError, nuscenes_scene_names

        try:
            nuscenes_scene_names(nuscenes, scene, nuscenes_version)
        except NuScenesError as exc:
            fail(f"--nuscenes: {exc}")
    # before the run: it must not compute for minutes and then fail to write (a str, not a Path: Path("") is ".")
    out = out_dir("--out", out)
    from .report import FIGURES, OUTPUTS

    out_files("--out", out, (*OUTPUTS, *FIGURES))
    for stale in _stale_frames(Path(out)):
        if stale.is_dir():  # no run's frames: not ours to delete, and unlink would raise
            fail(f"--out: {stale} is a folder where a run's frames go; remove or rename it")
    try:
        metrics = evaluate(out, scenario=scenario, seed=seed, noise=noise, nuscenes=nuscenes, scene=scene,
                           nuscenes_version=nuscenes_version,
                           sweeps=sweeps, duration=duration, rate=rate, classifier=cfg,
                           extra_seeds=tuple(range(seed + 1, seed + runs)), detector=detector,
                           weights_desc=weights_desc, variance_scale=variance_scale, calibration_model=model,
                           variance_scale_at=variance_scale_at, tracker=tracker, mcap=mcap,
                           run_info={"preset": preset, "tracker_config": None if tracker_config is None
                                     else described_file(tracker_config)})
    except BaseException:  # Ctrl-C, an error: the frames recorded so far are no run's (evaluate names them at its end)
        for partial in Path(out).glob(f"run-*.mcap{PARTIAL}"):
            partial.unlink(missing_ok=True)
        raise
    if as_json:
        sys.stdout.write(json.dumps(metrics, indent=2, sort_keys=True) + "\n")
    else:
        figures = sum((out / name).is_file() for name in FIGURES)  # this run's, not any PNG the folder holds
        print(f"wrote {out / 'report.md'}, metrics.json and {figures} figures"
              + (" and the frames as MCAP (run-*.mcap)" if mcap else ""))


def _stale_frames(out: Path) -> list[Path]:
    """An earlier run's recorded frames in ``out`` (and a killed run's unfinished ones): beside this run's
    metrics.json they would look like its own (they had stayed, unannounced, matching nothing the new report
    scored), so :func:`evaluate` removes them — once its own report is written, not before: a run refused for its
    input (``--runs`` with several scenes, a broken annotation table, a scan missing from the dataroot) had deleted
    them and written nothing."""
    return sorted(out.glob("run-*.mcap")) + sorted(out.glob(f"run-*.mcap{PARTIAL}"))


def check_whole_frame(duration: float, rate: float, at: str = "--rate") -> None:
    """Refuse (exit 2) a synthetic run of no whole frame, counted as the world counts them, as ``sim generate``
    refuses one: it had run, scored nothing and written a report of 0 frames with exit 0."""
    from ..sim.world import frame_count

    if frame_count(duration, rate) < 1:
        fail(f"--duration {duration:g} s at {at} {rate:g} Hz holds no whole frame; make duration × rate at least 1")


def load_detector(weights: Path | None, threads: int | None, self_crop: bool = True,
                  flips: bool = False, sensor_height: float | str | None = None,
                  sensor_tilt: str | None = None) -> tuple["Detector", str | None]:
    """The detector the live service would load for the same flags (``--weights``, else the shipped lite
    weights, else a random network, which ``Detector.load`` warns about; the service's default self-crop box
    unless ``self_crop`` is false; test-time ``flips``, ``sensor_height`` — metres, ``auto`` or None for the
    service's default — and ``sensor_tilt`` — ``auto``, ``level`` or None — as the service's settings) and a
    description of the file (name and the first 12 hex digits of its SHA-256, so a metrics.json names the exact
    weights; None for random initialisation). A missing or unusable file fails with one line."""
    from ..services.detector.config import SELF_CROP_M, declared_height, measures_tilt
    from ..services.detector.inference import Detector, WeightsError, shipped_weights

    if weights is not None and not weights.is_file():
        fail(f"--weights: file not found: {weights}")
    path = weights if weights is not None else shipped_weights("lite")
    try:
        det = Detector.load(weights, "lite", threads=threads, self_crop=SELF_CROP_M if self_crop else None,
                            flips=flips, sensor_height_m=declared_height(sensor_height),
                            sensor_tilt=measures_tilt(sensor_tilt))
    except WeightsError as exc:
        fail(f"--weights: {' '.join(str(exc).split())[:240]}")
    except ValueError as exc:  # flips on weights whose grid is not symmetric about the sensor
        fail(f"--detector-flips: {exc}")
    if det.meta.get("random_init"):
        return det, None
    return det, described_file(path, path if weights is not None else f"shipped {path.name}")


def described_file(path: Path, name: str | Path | None = None) -> str:
    """``name`` (default: the path) and the first 12 hex digits of the file's SHA-256: what a metrics.json says of
    an input file, so the run names the exact bytes it used."""
    import hashlib

    return f"{name or path} (sha256 {hashlib.sha256(path.read_bytes()).hexdigest()[:12]})"


def detector_run_info(detector: "Detector", weights_desc: str | None,
                      seen: dict[str, Any] | None = None) -> dict[str, Any]:
    """metrics.json's ``run.detector``: which network produced the detections (scalar training meta) and what the
    weights have seen of the scored data (``seen``: :func:`weights_saw_scored_data`)."""
    meta = {k: v for k, v in detector.meta.items() if isinstance(v, (str, int, float, bool)) and k != "random_init"}
    import torch

    return {"weights": weights_desc, "preset": detector.config.name, "random_init": weights_desc is None,
            "threads": torch.get_num_threads(),  # the run's detections, hence its figures, depend on it
            "uncertainty": detector.config.uncertainty,
            "self_crop": list(detector.self_crop) if detector.self_crop is not None else None,
            "flips": detector.flips,
            "sensor_height_m": "auto" if detector.sensor_height_m is None else detector.sensor_height_m,
            "sensor_tilt": "auto" if detector.sensor_tilt else "level",
            "score_threshold": detector.score_threshold if detector.score_threshold is not None
            else detector.config.score_threshold, "meta": meta, **(seen or weights_saw_scored_data(detector.meta, None))}


def software_versions(with_torch: bool = False) -> dict[str, Any]:
    """metrics.json's ``run.software``: what computed the run — jitterguard's version and, where it runs from a git
    checkout, the commit and whether tracked files differ from it (the version alone names every commit alike),
    Python's, numpy's and, with the detector, torch's."""
    import platform
    import subprocess

    import numpy as np

    from .. import __version__

    out: dict[str, Any] = {"jitterguard": __version__, "git_commit": None, "git_dirty": None,
                           "python": platform.python_version(), "numpy": np.__version__}
    if with_torch:
        import torch

        out["torch"] = torch.__version__
    src = Path(__file__).resolve().parents[1]
    try:
        head = subprocess.run(["git", "-C", str(src), "rev-parse", "HEAD"], capture_output=True, text=True,
                              timeout=10)
        if head.returncode == 0:
            out["git_commit"] = head.stdout.strip()
            dirty = subprocess.run(["git", "-C", str(src), "status", "--porcelain", "--untracked-files=no", "."],
                                   capture_output=True, text=True, timeout=30)
            out["git_dirty"] = bool(dirty.stdout.strip()) if dirty.returncode == 0 else None
    except (OSError, subprocess.SubprocessError):  # no git on the machine, or an installed copy: the version stands
        pass
    return out


def weights_saw_scored_data(meta: dict[str, Any], nuscenes: Path | None,
                            scenes: Sequence[str] = ()) -> dict[str, Any]:
    """What the weights' metadata (their lineage: :mod:`~jitterguard.services.detector.provenance`, as
    ``eval-detector`` reads it) says of the nuScenes ``scenes`` this run scores: the training source as recorded
    (``trained_on``); ``weights_trained_on_this_dataroot``: their labels trained the weights on a scored scene;
    ``weights_adapted_on_its_scans``: adapted on its unlabelled scans (test-time adaptation). Both None for a
    synthetic run. (The scalar ``run.detector.meta`` drops these records, so a run scored on a scene the weights had
    seen had not said so.)"""
    source = meta.get("source") if isinstance(meta.get("source"), dict) else None
    out: dict[str, Any] = {"trained_on": json.loads(json.dumps(source, default=str)) if source else None,
                           "weights_trained_on_this_dataroot": None, "weights_adapted_on_its_scans": None}
    if nuscenes is None:
        return out
    from ..services.detector.provenance import adapted_on_scans, seen_scenes

    out["weights_trained_on_this_dataroot"] = bool(seen_scenes(meta, nuscenes, scenes))
    out["weights_adapted_on_its_scans"] = adapted_on_scans(meta, nuscenes)
    return out


def warn_seen(seen: dict[str, Any], nuscenes: Path | None) -> None:
    """One stderr line per way the weights have seen the scored data (metrics.json records it too)."""
    if seen.get("weights_trained_on_this_dataroot"):
        print(f"warning: the detector's weights were trained on {nuscenes} (their metadata's source): this run scores"
              " a scene whose labels trained them, not an unseen scene", file=sys.stderr)
    if seen.get("weights_adapted_on_its_scans"):
        print(f"warning: the detector's weights were adapted on {nuscenes}'s unlabelled scans: this run scores"
              " test-time adaptation, not an unseen scene", file=sys.stderr)


def evaluate(out: Path, *, scenario: str | None, seed: int, noise: str | None, nuscenes: Path | None,
             scene: str | None, duration: float, rate: float, classifier: Any,
             extra_seeds: tuple[int, ...] = (), detector: "Detector | None" = None,
             weights_desc: str | None = None, variance_scale: float = 1.0,
             calibration_model: Any = None, variance_scale_at: str = "detector",
             tracker: Any = None, mcap: bool = False, sweeps: bool = False,
             nuscenes_version: str | None = None, run_info: dict[str, Any] | None = None) -> dict[str, Any]:
    """Load the frames, run the pipeline, score, write the outputs; returns metrics.json's content.

    ``extra_seeds`` pools more runs (a fresh scenario and noise draw per seed; for nuScenes only the noise
    changes) into one scored table, because one 15 s scene holds few moving objects and single-seed rates
    swing by tens of points. The pooled runs are one drive: the online variance calibration carries from each
    run to the next (only the first starts cold). ``scene`` may name several nuScenes scenes (comma-separated,
    or ``all``): they are pooled the same way, as one drive of the same sensor and detector, the calibration
    carried from scene to scene (repeated noise draws of one scene each start cold instead: carrying over
    would learn that scene's own boxes). With ``detector`` the detections come from it (``noise`` is
    unused) and its AP / calibration over all pooled scans go into ``detection``; ``sweeps`` feeds it every
    nuScenes LiDAR sweep and scores the labelled key frames among them. ``mcap`` records each run's
    frames to ``out/run-SEED.mcap`` (pooled scenes: ``run-SCENE.mcap``) through the Foxglove bridge's own sink
    (one file per run: each run's clock starts again), each written as ``….mcap.partial`` and named ``….mcap`` only
    once metrics.json and report.md are: an interrupted run had closed its recording into a whole, valid MCAP of the
    frames run so far, which sat beside the metrics of an earlier run in ``out`` and looked like theirs (``eval``
    removes the ``.partial`` files of a run that raised or was interrupted; a killed run leaves them so named).
    ``run_info`` adds to metrics.json's ``run`` what only the command knows (the preset's name, the tracker file)."""
    from tqdm import tqdm  # type: ignore[import-untyped]

    from .groundtruth import NuScenesError, nuscenes_scenes
    from ..services.classifier.calibration import OnlineCalibration
    from ..services.classifier.core import MotionClassifierCore
    from .metrics import (REPORT_GROUPS, alpha_from_labels, compute_metrics, planner_metrics, run_metrics,
                          vetoed_rows)
    from .pipeline import MATCH_DISTANCE_M, NOISE_PRESETS, Records, concat_records, run_pipeline, scored_test
    from .report import write_outputs
    from ..services.tracker.config import default_config as default_tracker_config

    scenes: list[tuple[str, Any]] = []  # (name, frames) of each nuScenes scene, pooled in this order
    if nuscenes is not None:
        try:
            scenes = nuscenes_scenes(nuscenes, scene, nuscenes_version)  # each table read once for all of them
        except NuScenesError as exc:
            fail(f"--nuscenes: {exc}")
        if len(scenes) > 1 and extra_seeds:
            fail("--runs pools noise draws of one scene; give one --scene with it, or several scenes without it")
        source = f"nuScenes {', '.join(n for n, _ in scenes)} ({nuscenes})"
        frames = scenes[0][1]
        total = sum(len(f) for _, f in scenes)
    else:
        from ..sim.world import SCENARIO_NAMES, make_scenario

        scenario = scenario or "parking-street"
        if scenario not in SCENARIO_NAMES:
            fail(f"--scenario: unknown scenario {scenario!r}; expected one of {', '.join(SCENARIO_NAMES)}")
        sc = make_scenario(scenario, seed, duration, rate)
        frames = sc  # type: ignore[assignment]
        source = f"scenario {scenario} seed {seed} ({duration:g} s @ {rate:g} Hz)"
        total = len(sc)

    seen = weights_saw_scored_data(detector.meta, nuscenes, [n for n, _ in scenes]) if detector is not None else None
    if seen is not None:  # before the run: said where it is seen, not only in metrics.json
        warn_seen(seen, nuscenes)
    predictions: list[Any] = []
    samples: list[Any] = []
    recorded: list[tuple[Path, Path]] = []  # (written, final name) of each run's MCAP
    scans_fed = 0  # frames the tracker and classifier ran on (more than the scored ones with sweeps)
    drive = MotionClassifierCore.make_online(classifier)

    def calibration_for_run(cold: bool) -> OnlineCalibration:
        nonlocal drive
        if cold:
            drive = MotionClassifierCore.make_online(classifier)
        return drive

    def bar(it: Any, tag: str, n: int) -> Any:
        desc = f"eval {tag}" + (" (detector)" if detector is not None else "")
        return tqdm(it, total=n, desc=desc, unit="frame", file=sys.stderr, leave=False,
                    disable=not progress_on(None))  # a bar on a terminal only: no carriage returns in a log

    def one(fr: Any, s: int, scene_name: str | None = None, cold: bool = False) -> Records:
        """One run: seed ``s``'s noise draw (or detections) over ``fr``; ``cold`` starts the calibration anew."""
        tag = f"seed {s}" if scene_name is None else f"{scene_name} seed {s}"
        if not mcap:
            return one_run(fr, s, scene_name, cold, tag, None)
        from ..services.foxglove.service import FoxgloveSink

        out.mkdir(parents=True, exist_ok=True)
        stem = f"run-{s}" if scene_name is None or len(scenes) == 1 else f"run-{scene_name}"
        final = out / f"{stem}.mcap"
        recorded.append((final.with_name(final.name + PARTIAL), final))
        sink = FoxgloveSink(port=None, mcap_path=recorded[-1][0], overwrite=True)
        try:
            return one_run(fr, s, scene_name, cold, tag, sink.write)
        finally:
            sink.close()

    def named(written: dict[str, Any]) -> dict[str, Any]:
        """``written`` (metrics.json's content, written) passed on, each run's recording now under its name and
        an earlier run's gone (:func:`_stale_frames`)."""
        ours = {p for pair in recorded for p in pair}
        for stale in _stale_frames(Path(out)):
            if stale not in ours and not stale.is_dir():
                stale.unlink()
        for partial, final in recorded:
            partial.replace(final)
        return written

    def one_run(fr: Any, s: int, scene_name: str | None, cold: bool, tag: str, on_frame: Any) -> Records:
        nonlocal scans_fed
        carry = calibration_for_run(cold)
        if detector is None:
            scans_fed += len(fr)
            return run_pipeline(fr, NOISE_PRESETS[noise or "jittery"](), s, classifier, tracker,
                                progress=lambda it: bar(it, tag, len(fr)), calibration=carry,
                                variance_scale=variance_scale, calibration_model=calibration_model,
                                variance_scale_at=variance_scale_at, on_frame=on_frame)
        from .detector_input import detector_frames, nuscenes_scans, run_detector_pipeline, synthetic_scans

        if nuscenes is not None:
            try:
                scans: Any = nuscenes_scans(nuscenes, scene_name, fr, sweeps=sweeps, version=nuscenes_version)
            except NuScenesError as exc:
                fail(f"--nuscenes: {exc}")
        else:
            scans = synthetic_scans(fr, s)
        n_scans = len(scans) if isinstance(scans, list) else len(fr)
        scans_fed += n_scans
        det_frames = detector_frames(bar(scans, tag, n_scans), detector.detect,
                                     class_names=detector.config.class_names,
                                     uncertainty=detector.config.uncertainty, sweeps=detector.sweeps,
                                     self_crop=detector.self_crop)
        rec_s, preds, smp = run_detector_pipeline(det_frames, classifier, tracker, calibration=carry,
                                                  variance_scale=variance_scale,
                                                  calibration_model=calibration_model,
                                                  variance_scale_at=variance_scale_at, on_frame=on_frame)
        predictions.extend(preds)
        samples.extend(smp)
        return rec_s

    run_tags: list[str] = []  # the pooled runs, as their rows' track-ID prefixes
    if len(scenes) > 1:  # several real scenes: one drive, the calibration carried from scene to scene
        run_tags = [name for name, _ in scenes]
        rec = concat_records([one(fr, seed, name) for name, fr in scenes], run_tags)
        source += " pooled"
    else:
        # synthetic seeds are different streets of one drive; repeated noise draws of one nuScenes scene are
        # not, and carrying over would learn that scene's own boxes: each of them starts cold
        scene_name = scenes[0][0] if scenes else None
        rec = one(frames, seed, scene_name)
        if extra_seeds:
            parts = [rec]
            for s in extra_seeds:
                fr = frames if nuscenes is not None else make_scenario(scenario or "", s, duration, rate)
                parts.append(one(fr, s, scene_name, cold=nuscenes is not None))
            run_tags = [str(s) for s in (seed, *extra_seeds)]
            rec = concat_records(parts, run_tags)
            source += f" + seeds {', '.join(map(str, extra_seeds))} pooled"
            total *= 1 + len(extra_seeds)
    alpha_desc = classifier.alpha_default if not classifier.alpha_per_class else dict(
        classifier.alpha_per_class, default=classifier.alpha_default)
    metrics: dict[str, Any] = {
        "run": {"source": source, "input": "gt-noise" if detector is None else "detector",
                "scenes": [name for name, _ in scenes] or None, "sweeps": sweeps, "scans": scans_fed,
                "nuscenes_version": nuscenes_version,
                "noise": noise if detector is None else None, "seed": seed, "frames": total,
                "rows": len(rec), "matched_rows": int((rec.gt_instance >= 0).sum()),
                "match_distance_m": MATCH_DISTANCE_M, "alpha": alpha_desc,
                "velocity_threshold": classifier.velocity_threshold,
                "velocity_threshold_per_class": dict(classifier.velocity_threshold_per_class),
                "velocity_sustain_s_per_class": dict(classifier.velocity_sustain_s_per_class),
                "dynamic_hold_s_per_class": dict(classifier.dynamic_hold_s_per_class),
                "view_slide_m_per_class": dict(classifier.view_slide_m_per_class),
                "jump_veto": classifier.jump_veto, "vetoed_rows": vetoed_rows(rec),
                "min_window": classifier.min_window, "window_size": rec.window_size,
                "window_stride": rec.window_stride, "window_reference_hz": classifier.window_reference_hz,
                "mode": scored_test(classifier),
                "calibration": classifier.calibration,
                "calibration_file": described_file(Path(classifier.calibration_file))
                if classifier.calibration == "file" and classifier.calibration_file else None,
                "effective_n": classifier.effective_n,
                "min_speed_mps": classifier.min_speed_mps, "variance_scale": variance_scale,
                "variance_scale_at": variance_scale_at,
                "tracker_measurement_scale": (tracker or default_tracker_config()).measurement_scale,
                "seeds": [seed, *extra_seeds], "scenario": None if nuscenes is not None else scenario,
                "duration_s": None if nuscenes is not None else duration,
                "rate_hz": None if nuscenes is not None else rate,
                "classifier": classifier.model_dump(mode="json"),
                "tracker": (tracker or default_tracker_config()).model_dump(mode="json"),
                "tracker_config": None, "preset": None, "software": software_versions(detector is not None),
                **(run_info or {})},
        "motion": compute_metrics(rec),
        **planner_metrics(rec),
        "by_run": run_metrics(rec, run_tags) if run_tags else None,
        "calibration": drive.snapshot(rec.window_size) if classifier.calibration == "online" else None,
        "alpha_from_labels": {g: alpha_from_labels(rec, g) for g in REPORT_GROUPS},
    }
    metrics["alpha_from_labels_preset"] = labels_preset(metrics["alpha_from_labels"])
    # decided rows: a run whose every row was still undecided (windows shorter than min_window) decided nothing
    metrics["run"]["no_decision"] = no_decision(int((rec.window >= rec.min_window).sum()), total,
                                                classifier, tracker)
    if detector is None:
        return named(write_outputs(out, rec, metrics))
    from .detector_input import detection_metrics
    from .report import DETECTION_FIGURES

    metrics["detection"], det_report = detection_metrics(predictions, samples, detector.config.class_names)
    metrics["run"]["detector"] = detector_run_info(detector, weights_desc, seen)
    metrics["run"]["detector"]["figures"] = [f for f in DETECTION_FIGURES
                                             if f != DETECTION_FIGURES[0] or det_report["calibration"] is not None]
    return named(write_outputs(out, rec, metrics, det_report))


def study_command(
    out: Annotated[str, typer.Option("--out", help="Folder for study.md, study.json and one folder per run.")],
    seeds: Annotated[str, typer.Option("--seeds", help="Seeds pooled per run: a range (2000-2009), a list (1,2,5)"
                                       " or both (1,2,5-7).")] = "0,1,2",
    duration: Annotated[float, typer.Option("--duration", help="Scenario length \\[s].")] = 15.0,
    as_json: Annotated[bool, typer.Option("--json", help="Also print study.json to stdout.")] = False,
) -> None:
    """The jitter-band study: parking-street and diagonal-lot under clean, jittery and paper-like noise."""
    from ..schemas.models import ClassifierConfig
    from .study import STUDY_RUNS, study_markdown, summarize

    if not 0 < duration <= 600:
        fail("--duration must be in (0, 600]")
    check_whole_frame(duration, 10.0, at="the study's")
    seed_list = tuple(parse_seeds(seeds, "--seeds"))  # as every other command's --seeds: 2000-2009, 1,2,5-7
    out = out_dir("--out", out)  # a str, not a Path: Path("") is "." and the study went into the current folder
    from .report import FIGURES, OUTPUTS

    out_files("--out", out, ("study.json", "study.md"))
    for scenario, noise in STUDY_RUNS:  # each run's folder and files, before the first run
        run_dir = out_dir("--out", out / f"{scenario}-{noise}")
        out_files("--out", run_dir, (*OUTPUTS, *FIGURES))
    seed = seed_list[0]
    results = {}
    for scenario, noise in STUDY_RUNS:
        key = f"{scenario}/{noise}"
        results[key] = evaluate(out / f"{scenario}-{noise}", scenario=scenario, seed=seed, noise=noise,
                                nuscenes=None, scene=None, duration=duration, rate=10.0,
                                classifier=ClassifierConfig(), extra_seeds=seed_list[1:])
    summary: dict[str, Any] = {"seeds": list(seed_list), "duration_s": duration, "runs": summarize(results)}
    write_atomically(out / "study.json", (json.dumps(summary, indent=2, sort_keys=True) + "\n").encode())
    write_atomically(out / "study.md", (f"# Jitter-band study (seeds {seeds}, pooled, {duration:g} s each, vehicles)"
                                        f"\n\n" + study_markdown(summary["runs"])).encode())
    if as_json:
        sys.stdout.write(json.dumps(summary, indent=2, sort_keys=True) + "\n")
    else:
        sys.stdout.write(study_markdown(summary["runs"]))


def no_decision(rows: int, frames: int, classifier: Any, tracker: Any) -> str | None:
    """Why the run scored nothing, when it did not (no (frame, track) row: no track was confirmed and decided),
    else None: metrics.json and report.md say so, where their empty tables had read like any run's. A track is
    decided once confirmed (``confirm_hits`` detections) and observed ``min_window`` times."""
    if rows:
        return None
    from ..services.tracker.config import default_config as default_tracker_config

    hits = (tracker or default_tracker_config()).confirm_hits
    return (f"no track was decided in {frames} frame(s): a track is decided once confirmed ({hits} detections) and"
            f" observed min_window {classifier.min_window} times; run longer (--duration) or on more frames")


LABEL_CLASSES = {"vehicle": ("car", "truck", "bus", "trailer"), "pedestrian": ("pedestrian",),
                 "bicycle": ("bicycle", "motorcycle")}


def labels_preset(alphas: dict[str, float | None]) -> dict[str, Any]:
    """A ClassifierConfig update (like ``PRESETS``) with each group's alpha-from-labels on its classes,
    rounded to 2 decimals and clamped to the config's (0, 100] range; groups without labels are left out."""
    per_class = {}
    for g, a in alphas.items():
        if a is None:
            continue
        for c in LABEL_CLASSES[g]:
            per_class[c] = round(min(max(float(a), 0.01), 100.0), 2)
    return {"alpha_default": 1.96, "alpha_per_class": per_class}


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add ``eval`` and ``eval-study`` (no benchmark: evaluation measures quality, not speed)."""
    app.command("eval")(eval_command)
    app.command("eval-study")(study_command)
