"""What the ghost rows of `jitterguard eval` are: tracks that never met an object, or real objects' tracks in
the frames where the detector's box sat more than 2 m off the object's centre (docs/results.md, "Ghost tracks").

    .venv/bin/python scripts/ghost_breakdown.py --scenario mixed --seeds 0-3 [--input detector] [--threads 1]
    .venv/bin/python scripts/ghost_breakdown.py --nuscenes ../shared/data/nuscenes-scene-0523
    ... [--tracker-config FILE] [--cache DIR] [--weights W]

Runs the evaluator's pipeline (the live tracker and classifier cores; the detector service's steps with
``--input detector``) over the seeds as one drive, exactly like ``jitterguard eval --runs``, and splits
metrics.json's ``ghost.{vehicle,pedestrian}`` rows (a row whose track is matched to no object in that frame) by
what the track is over its whole life:

* ``never matched``: a track matched to no object in any frame — a ghost in the plain sense;
* ``matched elsewhere``: a track matched to an object in other frames (most often a bus, a truck or a car
  whose detected box was 2–4 m off its centre in this frame), and the part of them matched to a moving object
  in their other frames — rows scored as static truth although the object they follow moves.

Also prints the tracker's births and confirmed tracks per frame. ``--cache DIR`` keeps each seed's detector
payloads (pickled, with the ground truth) so a second run with another ``--tracker-config`` skips the network.
For diagnosis; the figures it prints for the pooled run are metrics.json's own (same pipeline, same scorer).
"""

from __future__ import annotations

import argparse
import pickle
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from jitterguard.eval.metrics import TrackBootstrap, ghost_rows, planner_metrics, scored_rows
from jitterguard.eval.pipeline import NOISE_PRESETS, Records, concat_records, track_and_classify
from jitterguard.schemas import encode, read_detected_objects
from jitterguard.schemas.models import ClassifierConfig
from jitterguard.services.classifier.core import DYNAMIC, MotionClassifierCore
from jitterguard.services.tracker.adapter import detection_frame
from jitterguard.services.tracker.config import TrackerConfig, default_config, load_config
from jitterguard.services.tracker.core import FrameRejected, TrackerCore
from jitterguard.sim.detection_model import DetectionModel


def _seeds(text: str) -> list[int]:
    lo, _, hi = text.partition("-")
    return list(range(int(lo), int(hi or lo) + 1))


def input_arguments(ap: argparse.ArgumentParser, default_input: str = "detector") -> None:
    """The options :func:`detection_pairs` reads: what to run (a scenario's seeds or a nuScenes scene), on which
    input (the detector or the noise model and its preset), with how many threads, cached where."""
    ap.add_argument("--scenario", default="mixed")
    ap.add_argument("--seeds", default="0-3")
    ap.add_argument("--nuscenes", default=None, help="nuScenes dataroot instead of a scenario (one run)")
    ap.add_argument("--input", default=default_input, choices=("detector", "gt-noise"))
    ap.add_argument("--noise", default="jittery", help="noise preset of --input gt-noise")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--cache", default=None, help="folder for the per-seed detector payloads")
    ap.add_argument("--weights", type=Path, default=None, help="detector weights of --input detector (default: the shipped)")
    ap.add_argument("--no-jump-veto", action="store_true",
                    help="the classifier without its jump veto (every figure measured before 3 Dec 2026)")


def seed_pairs(args: argparse.Namespace) -> dict[int, list[tuple[Any, bytes]]]:
    """:func:`detection_pairs` of every run the options name: each of ``--seeds``, or the one ``--nuscenes`` scene."""
    return {s: detection_pairs(args, s) for s in ([0] if args.nuscenes else _seeds(args.seeds))}


def rates_line(rec: Records) -> str:
    """Vehicle and pedestrian z-test rates of scored rows, as ``jitterguard eval`` reports them: static called moving,
    moving missed, ghosts called moving (rows in brackets)."""
    out = []
    for group in ("vehicle", "pedestrian"):
        m = scored_rows(rec, group)
        static, moving, ghost = m & ~rec.gt_dynamic, m & rec.gt_dynamic, ghost_rows(rec, group)

        def rate(mask: np.ndarray, dynamic: bool) -> str:
            if not mask.any():
                return "-"
            hit = (rec.state_z[mask] == DYNAMIC) == dynamic
            return f"{hit.mean():.4f} ({int(hit.sum())}/{int(mask.sum())})"

        out.append(f"{group[0].upper()} false {rate(static, True)} missed {rate(moving, False)} "
                   f"ghost {rate(ghost, True)}")
    return " | ".join(out)


def classifier_config(args: argparse.Namespace, **updates: Any) -> ClassifierConfig:
    """The shipped classifier config with ``updates``, and without the jump veto where ``--no-jump-veto`` asks."""
    return ClassifierConfig(**({"jump_veto": False} if args.no_jump_veto else {}), **updates)


def classify_seeds(pairs: dict[int, list[tuple[Any, bytes]]], clf: ClassifierConfig,
                   tracker: TrackerConfig | None = None,
                   on_run: Callable[[int], None] | None = None) -> list[Records]:
    """The evaluator's tracker and classifier over each seed's detections (:func:`detection_pairs`) as one drive —
    one online calibration carried from seed to seed, as ``jitterguard eval --runs`` does; ``on_run(i)`` is called
    before the i-th seed (for a diagnosis that hooks the cores and keys what it logs by run)."""
    drive = MotionClassifierCore.make_online(clf)
    out = []
    for i, s in enumerate(pairs):
        if on_run is not None:
            on_run(i)
        out.append(track_and_classify(iter(pairs[s]), clf, tracker or default_config(), calibration=drive))
    return out


def detection_pairs(args: argparse.Namespace, seed: int) -> list[tuple[Any, bytes]]:
    """(ground truth, DetectedObjects payload) of every frame of one run, from the cache if it holds them."""
    tag = "nuscenes" if args.nuscenes else f"{args.scenario}-{seed}"
    noise = args.noise  # the noise model's preset, for --input gt-noise
    kind = args.input if args.input == "detector" or noise == "jittery" else f"{args.input}-{noise}"
    if args.input == "detector" and args.weights:
        kind += "-" + args.weights.parent.name  # a cache per weights file
    path = Path(args.cache) / f"{tag}-{kind}.pkl" if args.cache else None
    if path is not None and path.exists():
        with path.open("rb") as fh:
            return pickle.load(fh)
    if args.nuscenes:
        from jitterguard.eval.groundtruth import load_nuscenes_frames

        frames: Any = load_nuscenes_frames(Path(args.nuscenes), None)[1]
    else:
        from jitterguard.sim.world import make_scenario

        frames = make_scenario(args.scenario, seed, 15.0, 10.0)
    if args.input == "gt-noise":
        model = DetectionModel(NOISE_PRESETS[noise](), seed)
        pairs = [(gt, encode(model.detect(gt).detections)) for gt in frames]
    else:
        from jitterguard.eval.cli import load_detector
        from jitterguard.eval.detector_input import detector_frames, nuscenes_scans, synthetic_scans

        det, _ = load_detector(args.weights, args.threads)
        scans = nuscenes_scans(Path(args.nuscenes), None, frames) if args.nuscenes else synthetic_scans(frames, seed)
        pairs = [(f.gt, f.detections) for f in detector_frames(scans, det.detect, class_names=det.config.class_names,
                                                                 uncertainty=det.config.uncertainty)]
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        with path.open("wb") as fh:
            pickle.dump(pairs, fh)
    return pairs


def _births(pairs: list[tuple[Any, bytes]], cfg: TrackerConfig) -> tuple[int, int, int]:
    """(frames, tracks born, confirmed tracks summed over frames) of the tracker core alone."""
    core = TrackerCore(cfg)
    frames = born = confirmed = 0
    for _, payload in pairs:
        try:
            res = core.step(detection_frame(read_detected_objects(payload)))
        except FrameRejected:
            continue
        frames += 1
        born += len(res.born)
        confirmed += len(res.tracks.ids)
    return frames, born, confirmed


def _fmt(rec: Records, mask: np.ndarray, boot: TrackBootstrap) -> str:
    if not mask.any():
        return "—"
    out = []
    for name, state in (("z", rec.state_z), ("speed", rec.state_v)):
        hit = state == DYNAMIC
        lo, hi = boot.rate(mask, hit) or (float("nan"), float("nan"))
        out.append(f"{name} {hit[mask].mean():.3f} [{lo:.3f}, {hi:.3f}]")
    return " / ".join(out) + f" ({mask.sum()} rows, {len(np.unique(rec.track_id[mask]))} tracks)"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    input_arguments(ap)
    ap.add_argument("--tracker-config", default=None, help="tracker YAML (as `jitterguard tracker --config`)")
    args = ap.parse_args()
    cfg = load_config(args.tracker_config)
    pairs = seed_pairs(args)
    seeds = list(pairs)
    rec = concat_records(classify_seeds(pairs, classifier_config(args), cfg), [str(s) for s in seeds])
    frames = born = confirmed = 0
    for s in seeds:
        f, b, c = _births(pairs[s], cfg)
        frames, born, confirmed = frames + f, born + b, confirmed + c
    boot = TrackBootstrap(rec.track_id)
    ghost = planner_metrics(rec, intervals=False)["ghost"]
    print(f"births per frame {born / frames:.2f}, confirmed tracks per frame {confirmed / frames:.2f} ({frames} frames)")
    matched_tracks = set(np.unique(rec.track_id[rec.gt_instance >= 0]).tolist())
    moving_tracks = set(np.unique(rec.track_id[(rec.gt_instance >= 0) & rec.gt_dynamic]).tolist())
    for group in ("vehicle", "pedestrian"):
        g = ghost_rows(rec, group)
        elsewhere = np.array([t in matched_tracks for t in rec.track_id.tolist()], dtype=bool)
        moving = np.array([t in moving_tracks for t in rec.track_id.tolist()], dtype=bool)
        gm = ghost[group]
        print(f"ghost {group} (metrics.json): z {gm.get('false_dynamic_z')} / speed {gm.get('false_dynamic_speed')}")
        print(f"   all ghost rows:      {_fmt(rec, g, boot)}")
        print(f"   never matched:       {_fmt(rec, g & ~elsewhere, boot)}")
        print(f"   matched elsewhere:   {_fmt(rec, g & elsewhere, boot)}")
        print(f"   … to a moving object: {_fmt(rec, g & moving, boot)}")


if __name__ == "__main__":
    main()
