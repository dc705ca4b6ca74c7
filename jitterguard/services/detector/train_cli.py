"""``jitterguard train`` (train or fine-tune the detector) and ``jitterguard eval-detector`` (score weights).

Synthetic data is ray-cast once into an on-disk cache (``OUT/cache-*``, reused when it exists with the same
recipe), so epochs read numpy files instead of re-casting. Fine-tuning on a nuScenes-format dataroot holds
out each scene's last ``--holdout-last`` keyframes as the validation/test split (the issue's protocol).

Commands import their implementation when they run (start-up time: see :mod:`jitterguard.cli`).
"""

from __future__ import annotations

import hashlib
import itertools
import json
import logging
import os
import sys
from pathlib import Path
from typing import Annotated, Any

import typer

from ...cli_common import (ProgressOpt, SensorHeightOpt, SensorTiltOpt, fail, float_option, out_dir, out_files,
                           parse_seeds, progress_on, refuse_given, sensor_height_option, sensor_tilt_option)
from ...files import not_a_file, not_a_folder
from .augment import CENTERPOINT_SAMPLE_COUNTS
from .config import CLASS_NAMES, PRESETS
from .provenance import init_provenance, seeds_refusal

log = logging.getLogger(__name__)

DEFAULT_SCENARIOS = "parking-street,diagonal-lot,intersection,mixed"
RECALIBRATION_BINS = 5
HOLDOUT_SEEDS_FROM = 1000
"""Synthetic seeds from here on are the detector's hold-out (``eval-detector``'s default 1000-1004): nothing that
fits weights or their recalibration may draw scans from them, or the hold-out figures would score seen scans."""
"""Score bins of a fitted variance recalibration (docs/detector.md, "The variance recalibration")."""


def _class_values(items: list[str] | None, option: str, defaults: Any, convert: Any, ok: Any, what: str,
                  condition: str) -> list:
    """``CLASS=VALUE`` items (a repeatable option) over per-class ``defaults``; a malformed item, an unknown class
    or a value ``ok`` refuses is a one-line error naming ``option``."""
    out = list(defaults)
    for item in items or []:
        name, sep, val = item.partition("=")
        try:
            value = convert(val)
        except ValueError:
            value = None
        if not sep or name not in CLASS_NAMES or value is None or not ok(value):
            fail(f"{option}: expected CLASS={what} with CLASS one of {', '.join(CLASS_NAMES)}{condition}, got {item!r}")
        out[CLASS_NAMES.index(name)] = value
    return out


def _scenarios(text: str) -> list[str]:
    from ...sim.world import SCENARIO_NAMES

    names = [s.strip() for s in text.split(",") if s.strip()]
    bad = [n for n in names if n not in SCENARIO_NAMES]
    if not names or bad:
        fail(f"--scenarios: expected comma-separated names from {', '.join(SCENARIO_NAMES)}, got {text!r}")
    return names


def synthetic_cache(root: Path, scenarios: list[str], seeds: list[int], frames: int, progress: bool,
                    effects: str = "none", workers: int = 0, sweeps: int = 1) -> Any:
    """The cached synthetic samples for this recipe, ray-casting them first (in ``workers`` processes when > 0)
    if the cache is missing or stale; ``sweeps`` > 1 stacks each with earlier sweeps (a five-field model's
    input, :func:`~.data.synthetic_samples`)."""
    from .data import CachedSamples, build_cache, synthetic_samples

    from ...sim.effects import EFFECTS_VERSION, parse_components
    from ...sim.world import WORLD_VERSION

    recipe: dict[str, Any] = {"scenarios": scenarios, "seeds": seeds, "frames_per_scenario": frames,
                              "world_version": WORLD_VERSION}
    components = parse_components(effects)
    if components:  # (keeps the name of caches written before effects existed)
        recipe["effects"] = ",".join(components)
        recipe["effects_version"] = EFFECTS_VERSION
    if sweeps > 1:  # (keeps the name of single-sweep caches)
        recipe["sweeps"] = sweeps

    name = "cache-" + hashlib.sha1(json.dumps(recipe, sort_keys=True).encode()).hexdigest()[:10]
    path = root / name
    try:
        cached = CachedSamples(path)
        if cached.meta.get("recipe") == recipe:
            return cached
    except Exception:  # noqa: BLE001 - missing or interrupted cache: rebuild
        pass
    total = len(scenarios) * len(seeds) * frames
    build_cache(path, synthetic_samples(scenarios, seeds, frames_per_scenario=frames, effects=effects,
                                       workers=workers, sweeps=sweeps), total=total,
                progress=progress, meta={"recipe": recipe})
    return CachedSamples(path)


def _effects(spec: str) -> tuple[str, ...]:
    from ...sim.effects import parse_components

    try:
        return parse_components(spec)
    except ValueError as exc:
        fail(f"--effects: {exc}")


class _Joined:
    """Several sample sequences as one, in order (the scans of each ``--effects`` set of a mixed recipe)."""

    def __init__(self, parts: list[Any]) -> None:
        self.parts = parts
        self.ends = list(itertools.accumulate(len(p) for p in parts))

    def __len__(self) -> int:
        return self.ends[-1] if self.ends else 0

    def __getitem__(self, i: int) -> Any:
        if not 0 <= i < len(self):
            raise IndexError(i)
        k = next(j for j, end in enumerate(self.ends) if i < end)
        return self.parts[k][i - (self.ends[k - 1] if k else 0)]


def _present(dataroot: str, version: str | None, names: list[str], flag: str = "--split") -> list[str]:
    """The scenes of an official split that this dataroot holds (a partial download trains on what is there);
    none is a one-line error naming ``flag`` (the option that named the split)."""
    from ..replay.sources.nuscenes import _load_table, find_version

    have = {s["name"] for s in _load_table(Path(dataroot) / find_version(Path(dataroot), version), "scene")}
    kept = [n for n in names if n in have]
    if not kept:
        fail(f"{flag}: none of the split's {len(names)} scenes is in {dataroot}")
    return kept


def _split_scenes(name: str, flag: str) -> list[str]:
    """The scene names of official split ``name``, or one line naming ``flag`` (an unknown split, no devkit)."""
    from ..replay.frames import SourceError
    from .data import official_split

    try:
        return official_split(name)
    except SourceError as exc:
        fail(f"{flag}: {exc}")


def check_preset(preset: str | None, weights: str | None, architecture: str) -> None:
    """``--preset`` together with ``--weights`` must name the weights' own architecture, or one line and exit 2:
    a weights file fixes its network, so a different preset would otherwise be silently ignored and the report
    would not score what the user asked for."""
    if preset is not None and weights is not None and preset != architecture:
        fail(f"--preset: {preset!r} contradicts --weights {weights}, a {architecture!r} network; drop --preset"
             " (the weights file fixes the architecture) or drop --weights (the shipped weights of --preset)")


def check_not_overwritten(flag: str, source: str | None, out: str) -> None:
    """``source`` (the weights a command reads) must not be ``OUT/weights.pt`` (what it writes), or one line naming
    ``flag`` and exit 2: the run had replaced its own input, losing it, and the new file's provenance
    (``init``, ``recalibrated_from``, ``adapted_from``) named a file that no longer held it."""
    target = Path(out) / "weights.pt"
    if source is None or not target.is_file() or not os.path.isfile(source):
        return
    if os.path.samefile(source, target):
        fail(f"{flag}: {source} is the {target} this run writes; write into another --out (it would be replaced)")


def _check_fill(n: int, micro: int, flag: str, world: int) -> None:
    """Enough training samples for one optimiser step's ``micro`` micro-batches (processes × --accumulate), or one
    line naming ``flag`` (exit 2) before any training: :func:`~.train.step_schedule` would fail only then."""
    if n < micro:
        fail(f"{flag}: {n} training sample{'s' if n != 1 else ''} cannot fill one optimiser step of {micro}"
             f" micro-batch{'es' if micro != 1 else ''} ({world} process{'es' if world != 1 else ''} x --accumulate"
             f" {micro // world})")


def dataclasses_asdict(obj: Any) -> dict[str, Any]:
    import dataclasses

    return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(obj).items()}


class _Prepared:
    """Range-filtered view of a sample sequence (the network never sees points outside its grid); with ``level``
    each sample is first moved, labels and all, to the level frame and height the detector moves every scan to at
    inference (:func:`~.ground.scan_ground`, ``train --level-scans``). Evaluation views leave that to the
    detector."""

    def __init__(self, samples: Any, pcr: tuple[float, ...], level: bool = False) -> None:
        self.samples, self.pcr, self.level = samples, pcr, level

    def __len__(self) -> int:
        return len(self.samples)

    def __getitem__(self, i: Any) -> Any:
        from .augment import filter_range

        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        sample = self.samples[i]
        if self.level:
            from dataclasses import replace

            from .ground import boxes_to_trained_frame, scan_ground, to_trained_frame

            ground = scan_ground(sample.points, None, True)
            sample = replace(sample, points=to_trained_frame(sample.points, ground),
                             boxes=boxes_to_trained_frame(sample.boxes, ground))
        return filter_range(sample, self.pcr)


def write_report(out: Path, name: str, dets: Any, samples: Any, *, bootstrap: int = 0,
                 extra: dict[str, Any] | None = None, progress: bool = False) -> dict[str, Any]:
    """Evaluation JSON plus the PR and calibration PNGs under ``out``; ``bootstrap`` resamples of the frames
    give 90 % intervals of the per-class AP and the ±1σ coverage (``summary["intervals"]``), with a bar when
    ``progress`` (a thousand resamples of a real scene take minutes after the detection bar has finished)."""
    from .evaluate import bootstrap_intervals, evaluation_report
    from .plots import calibration_plot, pr_plot
    from .train import progress_bar

    rep = evaluation_report(dets, samples, include_curves=True)
    if bootstrap:
        bar = progress_bar(progress, bootstrap, unit="resample", desc="bootstrap intervals")
        rep["summary"]["intervals"] = bootstrap_intervals(dets, samples, resamples=bootstrap,
                                                          progress=bar.update if bar is not None else None)
        if bar is not None:
            bar.close()
    if extra:
        rep.update(extra)
    out.mkdir(parents=True, exist_ok=True)
    pr_plot(rep["detection"], out / f"{name}_pr.png")
    if rep["calibration"] is not None:
        calibration_plot(rep["calibration"], out / f"{name}_calibration.png", title=name)
    slim = {k: v for k, v in rep.items() if k != "detection"}
    slim["detection"] = {k: v for k, v in rep["detection"].items() if k != "recall"}
    slim["detection"]["classes"] = {c: {k: v for k, v in d.items() if k != "precision"}
                                    for c, d in rep["detection"]["classes"].items()}
    (out / f"{name}.json").write_text(json.dumps(slim, indent=1))
    return slim


TRAINING_META = ("source", "augment", "init", "epochs", "recipe", "recipe_note", "train_config", "world_size",
                 "gt_sample", "launcher", "init_provenance")
"""Metadata of how a network was trained that ``adapt`` carries from the source weights into the adapted ones."""

def adapted_note(source_note: Any, weights: str, sha: str, scans: int, rounds: int, recalibration: str) -> str:
    """The ``recipe_note`` of adapted weights: that they were adapted, from what and how, then the source's own note
    (which describes the source weights, not these)."""
    scales = {"synthetic": "refitted per score bin on labelled synthetic scans after adapting",
              "tracked": "fitted from tracked residuals of the real scans",
              "keep": "kept from the source weights"}.get(recalibration, recalibration)
    note = (f"adapted by `jitterguard adapt` from {os.path.basename(weights)} (sha256 {sha[:12]}) to {scans} unlabelled"
            f" real scans (labels never read): {rounds} self-training round(s), variance scales {scales}")
    return f"{note}. The source weights' recipe: {source_note}" if isinstance(source_note, str) and source_note else note


RECALIBRATION_MODES = ("synthetic", "tracked", "keep")
"""Where ``adapt`` takes the adapted weights' variance scales from: refitted per score bin on labelled synthetic
scans (the default: the recalibration that holds on real scans, docs/detector.md), fitted from tracked
residuals of the real scans (label-free, one scale per axis), or kept from the source weights."""


def fit_seeds(text: str, flag: str) -> list[int]:
    """:func:`parse_seeds` for seeds whose labels fit something (network, recalibration): one line naming ``flag``
    and exit 2 when any is a hold-out seed (≥ :data:`HOLDOUT_SEEDS_FROM`)."""
    seeds = parse_seeds(text, flag)
    if seeds[-1] >= HOLDOUT_SEEDS_FROM:
        fail(f"{flag}: seeds {HOLDOUT_SEEDS_FROM}+ are the detector's hold-out (eval-detector scores them);"
             f" fit on lower seeds, got {text!r}")
    return seeds


def warn_thin_fit(rec: Any, bins: int, dets: list[Any], items: list[Any]) -> int:
    """Warn when a recalibration came out in fewer score bins than asked, or on few matched boxes (it had been said
    only by "bins" in the report; `train --fit-recalibration` had said nothing at all); returns the matches."""
    from .evaluate import RECALIBRATION_MIN_PER_BIN, matched_residuals

    matches = len(matched_residuals(dets, items))
    if len(rec.scales) < bins or matches < RECALIBRATION_MIN_PER_BIN:
        log.warning("the variance scales were fitted in %d score bin(s), %d asked, on %d matched boxes of %d scans"
                    " (%d a bin wanted): more seeds or frames per scenario give a steadier fit", len(rec.scales),
                    bins, matches, len(items), RECALIBRATION_MIN_PER_BIN)
    return matches


def fit_synthetic_recalibration(det: Any, root: Path, scenarios: list[str], seeds_text: str, frames: int,
                                effect_sets: list[str], bins: int, progress: bool,
                                workers: int = 0) -> tuple[Any, dict[str, Any]]:
    """Score-binned variance scales for ``det`` (a :class:`~.inference.Detector` without recalibration) fitted
    on labelled synthetic scans cast once into ``root`` (one cache per ``effect_sets`` recipe, in ``workers``
    processes when > 0); also writes
    ``root/before*`` and ``root/after*`` (calibration JSON + PNGs on those scans). Returns the
    :class:`~.evaluate.Recalibration` and a report: what it was fitted on, ECE / coverage / NLL before and
    after. Raises ValueError when nothing matches."""
    from tqdm import tqdm

    from .evaluate import apply_recalibration, fit_recalibration

    seeds = parse_seeds(seeds_text, "--seeds")
    items: list[Any] = []
    for e in effect_sets:
        view = _Prepared(synthetic_cache(root, scenarios, seeds, frames, progress, e, workers, det.sweeps),
                         det.config.point_cloud_range)
        items += [view[i] for i in range(len(view))]
    dets = [det.detect(s.points) for s in tqdm(items, unit="scan", file=sys.stderr, disable=not progress)]
    rec = fit_recalibration(dets, items, bins=bins)
    matches = warn_thin_fit(rec, bins, dets, items)
    before = write_report(root, "before", dets, items)["summary"]
    after = write_report(root, "after", [apply_recalibration(d, rec) for d in dets], items)["summary"]
    keys = ("positional_ece", "coverage_1sigma", "nll")
    fit_on = {"scenarios": scenarios, "seeds": seeds_text, "frames_per_scenario": frames,
              "effects": "+".join(",".join(_effects(e)) or "none" for e in effect_sets), "scans": len(items),
              "matches": matches, "bins": len(rec.scales)}
    return rec, {"fit_on": fit_on, "before": {k: before[k] for k in keys}, "after": {k: after[k] for k in keys}}


def register(app: typer.Typer, bench_app: typer.Typer) -> None:  # noqa: ARG001 - no benchmark here
    @app.command("train")
    def train_cmd(
        ctx: typer.Context,
        out: Annotated[str, typer.Option("--out", help="Run folder: caches, checkpoint.pt, history.json, weights.pt.")],
        preset: Annotated[str | None, typer.Option("--preset", help=f"Architecture: {', '.join(PRESETS)} (default"
                                                   " lite); with --init only the init weights' own.")] = None,
        vanilla: Annotated[bool, typer.Option("--vanilla", help="No variance heads (L1 instead of Gaussian NLL).")] = False,
        scenarios: Annotated[str, typer.Option("--scenarios", help="Synthetic scenarios to train on.")] = DEFAULT_SCENARIOS,
        train_seeds: Annotated[str, typer.Option("--train-seeds", help="Scenario seeds for training, e.g. 0-59.")] = "0-59",
        val_seeds: Annotated[str, typer.Option("--val-seeds", help="Seeds for per-epoch evaluation.")] = "900-901",
        frames: Annotated[int, typer.Option("--frames-per-scenario", min=1, max=600)] = 10,
        effects: Annotated[str, typer.Option("--effects", help="Sim-to-real effects of the synthetic scans, drawn"
                                             " per scan: 'random' (all), 'none' (ideal scans), or a comma list of"
                                             " ground, glass, dropout, noise, roof, mixed, clutter, open, motion,"
                                             " intensity, and the opt-in no-intensity, vegetation, limbs, pedal,"
                                             " clear-glass, kerb-trees, incidence and street-objects (not in 'random':"
                                             " random,vegetation,limbs,pedal); several sets joined by '+' (e.g."
                                             " none+random) train on the seeds cast once per set, validate on the"
                                             " first set.")] = "random",
        rotation: Annotated[float, float_option("--rotation", min=0.0, max=180.0, help="Global rotation"
                                                " augmentation: uniform in ± this many degrees.")] = 45.0,
        intensity: Annotated[bool | None, typer.Option("--intensity/--no-intensity", help="Feed the points'"
                                                       " intensity to the network (--no-intensity: 0 in training"
                                                       " and inference, stored in the weights); default: as"
                                                       " --init's weights, else fed.")] = None,
        tilt_aug: Annotated[float, float_option("--tilt-aug", min=0.0, max=10.0, help="Pitch/roll augmentation SD"
                                                " in degrees (and 0.05 m per degree of height).")] = 0.0,
        level_scans: Annotated[bool, typer.Option("--level-scans/--no-level-scans", help="Move every training and"
                                                  " validation scan, labels and all, to the level frame and height"
                                                  " the detector moves scans to at inference (its measured road"
                                                  " plane: sensor_height_m and sensor_tilt auto).")] = False,
        gt_sample: Annotated[bool, typer.Option("--gt-sample/--no-gt-sample", help="CenterPoint's ground-truth"
                                                " sampling: paste objects (≥ 5 returns) cut from other training"
                                                " scans where those scans had them.")] = False,
        gt_sample_count: Annotated[list[str] | None, typer.Option("--gt-sample-count", help="CLASS=N objects of a"
                                                                  " class pasted per scan with --gt-sample"
                                                                  " (repeatable; default CenterPoint's car=2,"
                                                                  " truck=3, bus=4, bicycle=6, pedestrian=2).")] = None,
        nuscenes: Annotated[str | None, typer.Option("--nuscenes", help="Train on this nuScenes dataroot instead of"
                                                      " synthetic scans (with --init: fine-tune).")] = None,
        nuscenes_version: Annotated[str | None, typer.Option("--nuscenes-version", help="Table folder, e.g."
                                                              " v1.0-trainval (default: the only one).")] = None,
        split: Annotated[str | None, typer.Option("--split", help="Official nuScenes split to train on (train,"
                                                  " mini_train, ...); default: every scene minus --holdout-last.")] = None,
        val_split: Annotated[str | None, typer.Option("--val-split", help="Official split to validate on (val,"
                                                      " mini_val); with --split.")] = None,
        sweeps: Annotated[int, typer.Option("--sweeps", min=1, max=20, help="Sweeps stacked per sample with a time"
                                            " channel (CenterPoint uses 10): nuScenes' LIDAR_TOP sweeps, or synthetic"
                                            " sweeps 1–10 spins apart; with a single-sweep --init its weights are"
                                            " widened by a zero time-lag input.")] = 1,
        holdout_last: Annotated[int, typer.Option("--holdout-last", min=1, help="Keyframes held out per scene"
                                                  " (nuScenes without --split).")] = 10,
        init: Annotated[str | None, typer.Option("--init", help="Start from these weights (fine-tuning); the"
                                                 " learning-rate schedule starts afresh.")] = None,
        distill_from: Annotated[str | None, typer.Option("--distill-from", help="Teacher weights (e.g. the"
                                                         " --init ones): the --distill-classes heatmaps are held to"
                                                         " its by a KL term, so that a fine-tune keeps what it"
                                                         " would forget of them.")] = None,
        distill_classes: Annotated[str | None, typer.Option("--distill-classes", help="Classes held to"
                                                            " --distill-from's heatmaps, comma-separated (default:"
                                                            " pedestrian).")] = None,
        distill_weight: Annotated[float | None, float_option("--distill-weight", min=0.0, max=1000.0, help="Weight"
                                                             " of that term against the heatmap loss (default:"
                                                             " 1).")] = None,
        epochs: Annotated[int, typer.Option("--epochs", min=1, max=1000)] = 10,
        batch_size: Annotated[int, typer.Option("--batch-size", min=1, max=256, help="Per process and"
                                                " micro-batch.")] = 4,
        accumulate: Annotated[int, typer.Option("--accumulate", min=1, max=256, help="Micro-batches per optimiser"
                                                " step (gradient accumulation).")] = 1,
        lr: Annotated[float, float_option("--lr", min=1e-7, max=1.0)] = 2e-3,
        seed: Annotated[int, typer.Option("--seed", min=0)] = 0,
        threads: Annotated[int | None, typer.Option("--threads", min=1, max=1024)] = None,
        workers: Annotated[int, typer.Option("--workers", min=0, max=64, help="Data-loader processes; they also ray-cast the synthetic caches.")] = 0,
        amp: Annotated[bool, typer.Option("--amp/--no-amp", help="Mixed precision (CUDA only).")] = True,
        sync_bn: Annotated[bool, typer.Option("--sync-bn/--no-sync-bn", help="Synchronise BatchNorm across"
                                              " GPUs (CUDA, several processes).")] = True,
        checkpoint_every: Annotated[int, typer.Option("--checkpoint-every", min=0, help="Also checkpoint every N"
                                                      " steps within an epoch (0: per epoch).")] = 0,
        max_steps: Annotated[int | None, typer.Option("--max-steps-per-epoch", min=1, help="Cut epochs short"
                                                      " (quick runs, tests).")] = None,
        resume: Annotated[bool, typer.Option("--resume", help="Continue from OUT/checkpoint.pt: the same command"
                                             " (a checkpoint of another model, data, schedule or number of processes"
                                             " is refused).")] = False,
        fit_recalibration: Annotated[bool, typer.Option("--fit-recalibration/--no-fit-recalibration",
                                                        help="Fit per-axis variance scales on the validation split"
                                                        " (synthetic: its scans of every --effects set) and store"
                                                        " them in weights.pt.")] = False,
        recalibration_bins: Annotated[int, typer.Option("--recalibration-bins", min=1, max=20, help="Score bins"
                                                        " of the fitted variance scales (1: one global scale"
                                                        " per axis).")] = RECALIBRATION_BINS,
        progress: ProgressOpt = None,
    ) -> None:
        """Train the detector on synthetic scans or a nuScenes dataroot; runs unchanged under ``torchrun``."""
        progress = progress_on(progress)
        if preset is not None and preset not in PRESETS:
            fail(f"--preset: expected one of {', '.join(PRESETS)}, got {preset!r}")
        effect_sets = effects.split("+")
        for e in effect_sets:
            _effects(e)
        if init is not None and (why := not_a_file(init)):
            fail(f"--init: {why}")
        if nuscenes is not None and (why := not_a_folder(nuscenes)):
            fail(f"--nuscenes: {why}")
        if distill_from is not None and (why := not_a_file(distill_from)):
            fail(f"--distill-from: {why}")
        if distill_from is None and (distill_classes is not None or distill_weight is not None):
            fail("--distill-classes/--distill-weight: only with --distill-from")
        distill_names = [c.strip() for c in (distill_classes or "pedestrian").split(",") if c.strip()]
        if not distill_names or set(distill_names) - set(CLASS_NAMES):
            fail(f"--distill-classes: expected some of {', '.join(CLASS_NAMES)}, got {distill_classes!r}")
        distill_weight = 1.0 if distill_weight is None else distill_weight
        if (split or val_split) and nuscenes is None:
            fail("--split/--val-split: need --nuscenes")
        # flags of the other data source: each had been ignored without a word
        if nuscenes is not None:
            refuse_given(ctx, ("scenarios", "train_seeds", "val_seeds", "frames", "effects"),
                         "to a --nuscenes run (its scenes are the data; these choose synthetic scans)")
        else:
            refuse_given(ctx, ("nuscenes_version", "holdout_last"), "without --nuscenes")
        if split:
            refuse_given(ctx, ("holdout_last",), "with --split (the official split says what is held out)")
        if not fit_recalibration:
            refuse_given(ctx, ("recalibration_bins",), "without --fit-recalibration")
        if val_split and not split:
            fail("--val-split: needs --split")
        split_scenes = _split_scenes(split, "--split") if split else None
        val_scenes = _split_scenes(val_split, "--val-split") if val_split else None
        scen = _scenarios(scenarios)
        tr_seeds, va_seeds = fit_seeds(train_seeds, "--train-seeds"), fit_seeds(val_seeds, "--val-seeds")
        if set(tr_seeds) & set(va_seeds) and nuscenes is None:
            fail("--val-seeds: must not overlap --train-seeds")
        if gt_sample_count and not gt_sample:
            fail("--gt-sample-count: only with --gt-sample")
        if level_scans and gt_sample:  # objects cut from one levelled scan would be pasted into another's plane
            fail("--level-scans: not with --gt-sample")
        gt_counts = _class_values(gt_sample_count, "--gt-sample-count", CENTERPOINT_SAMPLE_COUNTS, int,
                                  lambda v: 0 <= v <= 100, "N", " and 0 ≤ N ≤ 100")
        if not resume:  # a resumed run reads its checkpoint, not --init, and writes the same weights.pt again
            check_not_overwritten("--init", init, out)
            if os.path.isfile(os.path.join(out, "checkpoint.pt")):  # an interrupted run's, had been replaced unasked
                fail(f"--out: {out} holds a training run (checkpoint.pt): --resume continues it; to start afresh,"
                     " give another --out or remove that folder")
        elif os.path.isfile(os.path.join(out, "checkpoint.pt")):  # before the data are prepared: minutes of work
            from .train import CheckpointError, read_checkpoint

            try:
                read_checkpoint(Path(out) / "checkpoint.pt")
            except CheckpointError as exc:
                fail(f"--resume: {exc}")
        # after the flags are checked (bad input must not leave an empty run folder behind), before any work (a
        # run must not fail to write its result at the end)
        out_files("--out", out_dir("--out", out), ("weights.pt", "history.json", "checkpoint.pt"))
        logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
        from .cli import passive_openmp, retain_heap

        passive_openmp()  # before torch is imported
        retain_heap()
        import torch

        from .augment import TrainAugment
        from .evaluate import evaluation_report
        from .evaluate import fit_recalibration as fit_scales  # not `fit_recalibration`: that is the flag
        from .inference import WeightsError, load_weights, save_weights
        from .network import CenterPointNet
        from .train import CheckpointError, TrainConfig, init_distributed, predict, train

        if threads:
            torch.set_num_threads(threads)
        dc = init_distributed()
        root = Path(out)
        root.mkdir(parents=True, exist_ok=True)
        if init is not None:
            try:
                model, _, init_meta = load_weights(init)
            except WeightsError as exc:
                fail(f"--init: {exc}")
            if preset is not None and preset != model.config.name:  # it had been ignored: the init network trained
                fail(f"--preset: {preset!r} contradicts --init {init}, a {model.config.name!r} network; drop --preset"
                     " (the --init weights fix the architecture) or drop --init (a fresh --preset network)")
            if vanilla == model.config.uncertainty:
                fail("--init: weights are " + ("uncertainty-aware" if model.config.uncertainty else "vanilla")
                     + "; drop or add --vanilla to match")
            if sweeps == 1 and model.config.num_point_features == 5:
                fail(f"--init: weights take 5 point fields (stacked sweeps); --sweeps {sweeps} gives 4")
            if sweeps > 1 and model.config.num_point_features == 4:  # fine-tune single-sweep weights on stacks
                from .network import with_time_lag

                model = with_time_lag(model)
        else:
            torch.manual_seed(seed)
            model = CenterPointNet(PRESETS[preset or "lite"].model_copy(update={"uncertainty": not vanilla,
                                                                       "num_point_features": 5 if sweeps > 1 else 4}))
        if intensity is not None and intensity != model.config.use_intensity:  # same layers, what is fed changes
            state = model.state_dict()
            model = CenterPointNet(model.config.model_copy(update={"use_intensity": intensity}))
            model.load_state_dict(state)
        teacher, distill = None, {}
        if distill_from is not None:
            try:
                teacher = load_weights(distill_from)[0]
            except WeightsError as exc:
                fail(f"--distill-from: {exc}")
            grid = ("class_names", "num_point_features", "point_cloud_range", "voxel_size", "out_size_factor")
            if any(getattr(teacher.config, k) != getattr(model.config, k) for k in grid):
                fail("--distill-from: the teacher's classes, input or output grid differ from the network's ("
                     + ", ".join(grid) + ")")
            distill = {"from": distill_from, "classes": distill_names, "weight": distill_weight,
                       "sha256_16": hashlib.sha256(Path(distill_from).read_bytes()).hexdigest()[:16]}
        pcr = model.config.point_cloud_range
        recal_extra: list[Any] = []  # validation scans of the other --effects sets, for the recalibration
        if nuscenes is not None:
            from ..replay.frames import SourceError
            from .data import NuScenesKeyframes, split_holdout

            try:
                if split_scenes is not None:
                    train_s: Any = NuScenesKeyframes(nuscenes, nuscenes_version, _present(nuscenes, nuscenes_version,
                                                     split_scenes), sweeps=sweeps)
                    val_s: Any = NuScenesKeyframes(nuscenes, nuscenes_version, _present(
                        nuscenes, nuscenes_version, val_scenes, "--val-split"), sweeps=sweeps) if val_scenes else []
                else:
                    train_s, val_s = split_holdout(NuScenesKeyframes(nuscenes, nuscenes_version, sweeps=sweeps),
                                                   last_n=holdout_last)
            except SourceError as exc:
                fail(f"--nuscenes: {exc}")
            # resolved: eval-detector recognises the dataroot however it is named later (a symlink, a relative path)
            source: dict[str, Any] = {"nuscenes": str(Path(nuscenes).resolve()), "version": nuscenes_version,
                                      "split": split, "val_split": val_split, "sweeps": sweeps,
                                      "holdout_last": None if split else holdout_last}
        else:
            _check_fill(len(scen) * len(tr_seeds) * frames * len(effect_sets), dc.world * accumulate,
                        "--train-seeds", dc.world)
            if dc.main:  # one process casts the caches, the others wait for them
                for e in effect_sets:
                    synthetic_cache(root, scen, tr_seeds, frames, progress, e, workers, sweeps)
                for e in effect_sets[: len(effect_sets) if fit_recalibration else 1]:
                    synthetic_cache(root, scen, va_seeds, frames, progress, e, workers, sweeps)
            dc.barrier()
            parts = [synthetic_cache(root, scen, tr_seeds, frames, False, e, sweeps=sweeps) for e in effect_sets]
            train_s = parts[0] if len(parts) == 1 else _Joined(parts)
            val_s = synthetic_cache(root, scen, va_seeds, frames, False, effect_sets[0], sweeps=sweeps)
            if fit_recalibration:  # the scales are fitted on scans like the training mix, every effect set
                recal_extra = [synthetic_cache(root, scen, va_seeds, frames, False, e, sweeps=sweeps)
                               for e in effect_sets[1:]]
            source = {"scenarios": scen, "train_seeds": train_seeds, "val_seeds": val_seeds,
                      "frames_per_scenario": frames,
                      "effects": "+".join(",".join(_effects(e)) or "none" for e in effect_sets)}
            if sweeps > 1:
                source["sweeps"] = sweeps
        if nuscenes is not None:
            _check_fill(len(train_s), dc.world * accumulate, "--split" if split else "--holdout-last", dc.world)
        train_v, val_v = _Prepared(train_s, pcr, level_scans), _Prepared(val_s, pcr, level_scans)
        tcfg = TrainConfig(epochs=epochs, batch_size=batch_size, lr=lr, seed=seed, num_workers=workers,
                           accumulate=accumulate, amp=amp, sync_bn=sync_bn, checkpoint_every=checkpoint_every,
                           max_steps_per_epoch=max_steps,
                           distill_channels=tuple(model.config.class_names.index(c) for c in distill.get("classes", ())),
                           distill_weight=distill_weight)

        def evaluate(dets: Any, samples: Any) -> dict[str, Any]:
            return evaluation_report(dets, samples)["summary"]

        meta = {"source": source, "init": init, "command": " ".join(["jitterguard", *sys.argv[1:]])}
        if init is not None and (carried := init_provenance(init_meta)) is not None:
            meta["init_provenance"] = carried  # what the init network saw stays on record (eval-detector reads it)
        if dc.distributed:
            meta["launcher"] = f"torchrun, {dc.world} processes"
        gt_db = None
        if gt_sample:
            from .augment import build_gt_database

            gt_db = build_gt_database(train_v[i] for i in range(len(train_v)))
            log.info("ground-truth sampling from %d objects", len(gt_db))
        augment = TrainAugment(rotation, tilt_aug, gt_db, tuple(gt_counts))
        if gt_db is not None:
            meta["gt_sample"] = {"objects": len(gt_db), "per_scan": list(augment.gt_counts)}
        meta["augment"] = {"rotation_deg": rotation, "tilt_deg": tilt_aug}
        if level_scans:
            meta["level_scans"] = True
        if distill:
            meta["distilled"] = distill
        try:  # with --fit-recalibration weights.pt is written once, below, with the fitted scales
            state = train(model, train_v, val_v, tcfg, root, augment=augment, evaluate=evaluate, resume=resume,
                          progress=progress, meta=meta, dist_ctx=dc, write_weights=not fit_recalibration,
                          teacher=teacher)
        except CheckpointError as exc:
            fail(f"--resume: {exc}")
        if not dc.main:
            return
        model.cpu()
        val_list = [val_v[i] for i in range(min(len(val_v), tcfg.max_eval_samples * 5))]
        dets = predict(model, val_list)
        rec = None
        if fit_recalibration and model.config.uncertainty:
            fit_list = val_list + [_Prepared(part, pcr, level_scans)[i] for part in recal_extra for i in range(len(part))]
            try:
                fit_dets = dets + predict(model, fit_list[len(val_list):])
                rec = fit_scales(fit_dets, fit_list, bins=recalibration_bins)
                warn_thin_fit(rec, recalibration_bins, fit_dets, fit_list)
            except ValueError as exc:  # no true positives yet (a tiny run): keep the raw variances
                log.warning("no recalibration fitted: %s", exc)
        if fit_recalibration:  # train() left weights.pt to us: its metadata (train_config, world_size) plus the fit
            extra = {"recalibration_fit_on": f"validation split ({len(fit_list)} scans)"} if rec is not None else {}
            save_weights(root / "weights.pt", model, recalibration=rec, meta={**(state.meta or meta), **extra})
        summary = write_report(root / "report", "validation", dets, val_list)["summary"] if val_list else None
        typer.echo(json.dumps({"weights": str(root / "weights.pt"), "epochs": state.epoch,
                               "recalibration": rec.to_payload() if rec else None, "validation": summary}))

    @app.command("adapt")
    def adapt_cmd(
        weights: Annotated[str, typer.Option("--weights", help="Weights to adapt (e.g. the shipped synthetic ones).")],
        out: Annotated[str, typer.Option("--out", help="Run folder: rounds, weights.pt, adapt.json.")],
        scans: Annotated[list[str], typer.Option("--scans", help="Unlabelled real recordings (repeatable): a nuScenes"
                                                 " dataroot, KITTI .bin folder or file, PCD, bag. Labels are never"
                                                 " read.")],
        rounds: Annotated[int, typer.Option("--rounds", min=0, max=20, help="Self-training rounds (0: only"
                                            " normalisation statistics and recalibration).")] = 2,
        epochs: Annotated[int, typer.Option("--epochs", min=1, max=100, help="Epochs per round.")] = 2,
        batch_size: Annotated[int, typer.Option("--batch-size", min=1, max=64)] = 2,
        lr: Annotated[float, float_option("--lr", min=1e-7, max=1.0)] = 5e-4,
        scenarios: Annotated[str, typer.Option("--scenarios", help="Synthetic scenarios mixed in.")] = DEFAULT_SCENARIOS,
        synthetic_seeds: Annotated[str, typer.Option("--synthetic-seeds", help="Labelled synthetic scans mixed into"
                                                     " self-training (seeds).")] = "0-9",
        frames: Annotated[int, typer.Option("--frames-per-scenario", min=1, max=600)] = 5,
        effects: Annotated[str, typer.Option("--effects")] = "random",
        real_repeat: Annotated[int, typer.Option("--real-repeat", min=1, max=100, help="Times each real scan is"
                                                 " seen per epoch.")] = 2,
        threshold: Annotated[list[str] | None, typer.Option("--threshold", help="CLASS=SCORE minimum score of a"
                                                            " pseudo-label (repeatable).")] = None,
        max_scans: Annotated[int | None, typer.Option("--max-scans", min=1)] = None,
        recalibration: Annotated[str, typer.Option("--recalibration", help="The adapted weights' variance scales:"
                                                   " synthetic (refitted per score bin on labelled synthetic scans"
                                                   " after adaptation), tracked (from tracked residuals of the real"
                                                   " scans, recordings with poses) or keep (the source"
                                                   " weights').")] = "synthetic",
        recalibration_seeds: Annotated[str, typer.Option("--recalibration-seeds", help="Synthetic seeds of"
                                                         " --recalibration synthetic (ideal and effect scans; not"
                                                         " the weights' training seeds).")
                                       ] = "60-79",
        self_crop: Annotated[bool, typer.Option("--self-crop/--no-self-crop", help="Drop the returns of the"
                                                " vehicle's own body from the real scans first (the service's"
                                                " default self_crop).")] = True,
        flips: Annotated[bool, typer.Option("--flips/--no-flips", help="Pseudo-label with the network averaged"
                                            " over each scan's three mirror images (test-time flips).")] = False,
        propagate: Annotated[bool, typer.Option("--propagate/--no-propagate", help="Carry the pseudo-labels of"
                                                " static objects (one place, one class, in 3 or more scans) to the"
                                                " scans of the same recording where the model missed them"
                                                " (recordings with ego poses).")] = False,
        sensor_height: SensorHeightOpt = None,
        sensor_tilt: SensorTiltOpt = None,
        seed: Annotated[int, typer.Option("--seed", min=0)] = 0,
        threads: Annotated[int | None, typer.Option("--threads", min=1, max=1024)] = None,
        progress: ProgressOpt = None,
    ) -> None:
        """Adapt weights to unlabelled real scans: normalisation statistics, self-training, recalibration."""
        progress = progress_on(progress)
        height, tilt = sensor_height_option(sensor_height), sensor_tilt_option(sensor_tilt)
        from .adapt import DEFAULT_PSEUDO_THRESHOLDS
        from .config import SELF_CROP_M, declared_height, measures_tilt

        if why := not_a_file(weights):
            fail(f"--weights: {why}")
        _effects(effects)
        if recalibration not in RECALIBRATION_MODES:
            fail(f"--recalibration: expected one of {', '.join(RECALIBRATION_MODES)}, got {recalibration!r}")
        recal_seeds = fit_seeds(recalibration_seeds, "--recalibration-seeds")
        thr = _class_values(threshold, "--threshold", DEFAULT_PSEUDO_THRESHOLDS, float, lambda v: 0.0 < v < 1.0,
                            "SCORE", " and 0 < SCORE < 1")
        scen = _scenarios(scenarios)
        syn_seeds = fit_seeds(synthetic_seeds, "--synthetic-seeds")
        check_not_overwritten("--weights", weights, out)
        logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
        from .cli import passive_openmp, retain_heap

        passive_openmp()  # before torch is imported
        retain_heap()

        import torch

        from ..replay.frames import SourceError
        from .adapt import AdaptConfig, adapt, describe, read_unlabelled
        from .augment import TrainAugment
        from .inference import WeightsError, load_weights, save_weights

        if threads:
            torch.set_num_threads(threads)
        try:
            model, source_rec, source_meta = load_weights(weights)
        except WeightsError as exc:
            fail(f"--weights: {exc}")
        # scales fitted on scans the network learnt come out too small for the scans it has not
        if recalibration == "synthetic" and (why := seeds_refusal("--recalibration-seeds", recal_seeds, source_meta)):
            fail(why)
        if flips:
            from .flips import check_symmetric

            try:
                check_symmetric(model.config)
            except ValueError as exc:
                fail(f"--flips: {exc}")
        if model.config.num_point_features != 4:  # its real scans would have to be stacked too: not built
            fail(f"--weights: the model takes stacked sweeps ({model.config.num_point_features} point fields); adapt"
                 " works on single-sweep weights: adapt those, then widen them with `train --init W --sweeps N`")
        for recording in scans:  # what a path holds is read later; one that names nothing is refused now
            if not os.path.exists(recording):
                fail(f"--scans: {recording}: no such file or folder")
        out_files("--out", out_dir("--out", out), ("weights.pt", "adapt.json"))  # after the flags and weights are checked, before the scans are read
        from .train import progress_bar

        bar = progress_bar(progress, max_scans, unit="scan", desc="reading scans")
        try:
            real = read_unlabelled(scans, max_scans=max_scans, progress=bar.update if bar is not None else None)
        except SourceError as exc:
            if bar is not None:
                bar.close()  # before the error line, which must stand on its own
            fail(f"--scans: {exc}")
        if bar is not None:
            bar.close()
        root = Path(out)
        root.mkdir(parents=True, exist_ok=True)
        synthetic = _Prepared(synthetic_cache(root, scen, syn_seeds, frames, progress, effects),
                              model.config.point_cloud_range) if rounds else []
        cfg = AdaptConfig(rounds=rounds, epochs=epochs, batch_size=batch_size, lr=lr, seed=seed, thresholds=tuple(thr),
                          real_repeat=real_repeat, recalibrate=recalibration == "tracked",
                          self_crop=SELF_CROP_M if self_crop else None, flips=flips, propagate=propagate,
                          sensor_height_m=declared_height(height), sensor_tilt=measures_tilt(tilt))
        aug = TrainAugment(**(source_meta.get("augment") or {}))  # as the source weights were trained
        report = adapt(model, real, synthetic, cfg, root, augment=aug, progress=progress)
        rec = report["recalibration"]
        scales = tuple(rec["scales"]) if rec else source_rec
        fit_on: Any = rec["fit_on"] if rec else "unchanged from the source weights"
        if recalibration == "synthetic" and model.config.uncertainty:  # fitted where it will be used: after adapting
            from .inference import Detector

            det = Detector(model, threads=threads, self_crop=SELF_CROP_M)
            try:
                scales, fitted = fit_synthetic_recalibration(det, root / "recalibration", scen, recalibration_seeds,
                                                             frames, ["none", "random"], RECALIBRATION_BINS, progress)
            except ValueError as exc:
                fail(f"--recalibration-seeds: {exc}")
            report["recalibration"] = {"scales": scales.to_payload(), **fitted}
            fit_on = fitted["fit_on"]
        sha = hashlib.sha256(Path(weights).read_bytes()).hexdigest()[:16]
        # what the network was trained on stays true of the adapted one: eval-detector reads "source" to hold out
        # the frames it trained on, and a second adapt its "augment"
        trained = {k: source_meta[k] for k in TRAINING_META if k in source_meta}
        command = " ".join(["jitterguard", *sys.argv[1:]])
        if isinstance(trained.get("recipe"), list):  # the commands that made these weights: this one last
            trained["recipe"] = [*trained["recipe"], command]
        # the source's note describes the source (the shipped one: "synthetic scans only ... refits the variances
        # on synthetic seeds"); kept as it was, the adapted weights had claimed that recipe as their own
        trained["recipe_note"] = adapted_note(source_meta.get("recipe_note"), weights, sha, len(real), rounds,
                                              recalibration)
        meta = {**trained, "command": command,
                "adapted_from": {"path": os.path.abspath(weights), "sha256_16": sha, "source": source_meta.get("source")},
                # adapting adapted weights: they have seen the earlier adaptation's scans too
                "unlabelled_scans": [*(source_meta.get("unlabelled_scans") or []), *describe(real)],
                "labels_read": False, "adapt": {**dataclasses_asdict(cfg), "synthetic_seeds": synthetic_seeds,
                                                "scenarios": scen, "effects": effects},
                "report": report,
                "recalibration_fit_on": fit_on}
        save_weights(root / "weights.pt", model, recalibration=scales, meta=meta)
        (root / "adapt.json").write_text(json.dumps(meta, indent=1))
        typer.echo(json.dumps({"weights": str(root / "weights.pt"), "scans": len(real), "report": report}))

    @app.command("domain-gap")
    def domain_gap_cmd(
        out: Annotated[str, typer.Option("--out", help="Folder for domain_gap.json and domain_gap.png.")],
        nuscenes: Annotated[str, typer.Option("--nuscenes", help="Real nuScenes dataroot (its boxes give the"
                                              " per-car figures).")],
        effects: Annotated[list[str] | None, typer.Option("--effects", help="Synthetic scans to compare, one set per"
                                                          " flag (see train --effects).")] = None,
        scenarios: Annotated[str, typer.Option("--scenarios")] = DEFAULT_SCENARIOS,
        seeds: Annotated[str, typer.Option("--seeds")] = "1000-1001",
        frames: Annotated[int, typer.Option("--frames-per-scenario", min=1, max=600)] = 5,
    ) -> None:
        """Measure how real scans differ from synthetic ones (returns by range, on cars, road height)."""
        specs = effects or ["none", "random"]
        for e in specs:
            _effects(e)
        scen = _scenarios(scenarios)
        sd = parse_seeds(seeds, "--seeds")
        if not os.path.isdir(nuscenes):
            fail(f"--nuscenes: not a directory: {nuscenes}")
        # before any work (a run must not fail to write its result at the end), after the flags (a refused run
        # had left the folder behind)
        out_files("--out", out_dir("--out", out), ("domain_gap.json", "domain_gap.png"))
        from ..replay.frames import SourceError
        from .data import nuscenes_samples, synthetic_samples
        from .domain_gap import comparison_plot, scan_statistics

        try:
            real = nuscenes_samples(nuscenes)
        except SourceError as exc:
            fail(f"--nuscenes: {exc}")
        stats = {f"real ({Path(nuscenes).name})": scan_statistics(real)}
        for e in specs:
            stats[f"synthetic, effects {e}"] = scan_statistics(
                list(synthetic_samples(scen, sd, frames_per_scenario=frames, effects=e)))
        root = Path(out)
        (root / "domain_gap.json").write_text(json.dumps(stats, indent=1))
        comparison_plot(stats, str(root / "domain_gap.png"))
        typer.echo(json.dumps({name: {"valid_returns_per_scan": round(st["valid_returns_per_scan"]),
                                      "car_intensity_p10_50_90": st["car_intensity_p10_50_90"],
                                      "returns_per_car_10_20m": st["bands"][2]["returns_per_car_median"]}
                               for name, st in stats.items()}))

    @app.command("eval-detector")
    def eval_detector_cmd(
        ctx: typer.Context,
        out: Annotated[str, typer.Option("--out", help="Folder for the JSON report and the PR/calibration PNGs;"
                                         " synthetic scans are cast into a cache-HASH folder there (about 0.5 MB a"
                                         " scan), which a rerun with the same scans reuses.")],
        weights: Annotated[str | None, typer.Option("--weights", help="Weights file (default: the shipped weights"
                                                     " of --preset).")] = None,
        preset: Annotated[str | None, typer.Option("--preset", help="Shipped weights to score (default lite); with"
                                                   " --weights only the weights' own architecture.")] = None,
        scenarios: Annotated[str, typer.Option("--scenarios")] = DEFAULT_SCENARIOS,
        seeds: Annotated[str, typer.Option("--seeds", help="Hold-out seeds (never used in training).")] = "1000-1004",
        frames: Annotated[int, typer.Option("--frames-per-scenario", min=1, max=600)] = 10,
        effects: Annotated[str, typer.Option("--effects", help="Sim-to-real effects of the synthetic hold-out scans"
                                             " (as train's --effects, one set): 'none' (ideal, the quality bar's)"
                                             " or e.g. 'random,vegetation'.")] = "none",
        nuscenes: Annotated[str | None, typer.Option("--nuscenes", help="Evaluate on this nuScenes dataroot's key"
                                                      " frames instead: those of the scenes whose labels never"
                                                      " trained the weights (refused when there are none).")] = None,
        holdout_last: Annotated[int | None, typer.Option("--holdout-last", min=1, help="With --nuscenes: score"
                                                         " each scene's last N key frames instead, seen scenes"
                                                         " too (reported: not a cross-scene figure).")] = None,
        bootstrap: Annotated[int, typer.Option("--bootstrap", min=0, max=10000, help="Resamples over frames for"
                                               " 90 % intervals of AP and coverage (0: none).")] = 1000,
        recalibrate: Annotated[bool, typer.Option("--recalibrate/--no-recalibrate",
                                                  help="Apply the weights' fitted variance scales.")] = True,
        self_crop: Annotated[bool, typer.Option("--self-crop/--no-self-crop", help="Drop the returns of the"
                                                " vehicle's own body first (the service's default self_crop).")
                             ] = True,
        threads: Annotated[int | None, typer.Option("--threads", min=1, max=1024)] = None,
        name: Annotated[str, typer.Option("--name", help="File stem of the outputs.")] = "holdout",
        sweeps: Annotated[int | None, typer.Option("--sweeps", min=1, max=20, help="Sweeps stacked per scan for"
                                                   " weights trained on stacks (default: as trained; 1: the newest"
                                                   " alone).")] = None,
        flips: Annotated[bool, typer.Option("--flips/--no-flips", help="Average the network over the scan and its"
                                            " three mirror images (test-time flips; ~4x the network's time).")
                         ] = False,
        sensor_height: SensorHeightOpt = None,
        sensor_tilt: SensorTiltOpt = None,
        progress: ProgressOpt = None,
    ) -> None:
        """Score weights on a hold-out set: nuScenes-style AP, positional ECE; JSON + PNGs."""
        # a stem with a folder in it (or none at all) failed, or wrote hidden files, only after the whole scoring
        if not name.strip() or name != Path(name).name or name in (".", ".."):
            fail(f"--name: expected a file-name stem (no folder, not empty), got {name!r}")
        progress = progress_on(progress)
        if preset is not None and preset not in PRESETS:
            fail(f"--preset: expected one of {', '.join(PRESETS)}, got {preset!r}")
        if weights is not None and (why := not_a_file(weights)):
            fail(f"--weights: {why}")
        scen = _scenarios(scenarios)
        sd = parse_seeds(seeds, "--seeds")
        if "+" in effects:
            fail(f"--effects: one set of effects to score on, got {effects!r}")
        _effects(effects)
        if nuscenes is not None and (why := not_a_folder(nuscenes)):
            fail(f"--nuscenes: {why}")
        if holdout_last is not None and nuscenes is None:  # it had been ignored without a word
            fail("--holdout-last: only with --nuscenes (synthetic hold-out seeds are scored whole)")
        if nuscenes is not None:  # the synthetic hold-out's flags: ignored without a word too
            refuse_given(ctx, ("scenarios", "seeds", "frames", "effects"),
                         "to --nuscenes (its key frames are scored; these choose synthetic hold-out scans)")
        height, tilt = sensor_height_option(sensor_height), sensor_tilt_option(sensor_tilt)
        from .cli import passive_openmp

        passive_openmp()  # before torch is imported
        from .config import SELF_CROP_M, declared_height, measures_tilt
        from .inference import Detector, WeightsError

        try:
            det = Detector.load(weights, preset or "lite", threads=threads, recalibrate=recalibrate,
                                self_crop=SELF_CROP_M if self_crop else None, flips=flips,
                                sensor_height_m=declared_height(height), sensor_tilt=measures_tilt(tilt))
        except WeightsError as exc:
            fail(f"--weights: {exc}")
        except ValueError as exc:  # flips on a grid that is not symmetric about the sensor
            fail(f"--flips: {exc}")
        check_preset(preset, weights, det.config.name)
        # a hold-out score on scans the network learnt is no hold-out score
        if nuscenes is None and (why := seeds_refusal("--seeds", sd, det.meta)):
            fail(why)
        if sweeps is not None:
            if sweeps > 1 and det.config.num_point_features < 5:
                fail(f"--sweeps: these weights take one sweep (4 point fields), got {sweeps}")
            det.sweeps = sweeps
        # after the flags and weights are checked (bad input must not leave an empty folder behind), before any
        # work (a run must not fail to write its result at the end)
        out_files("--out", out_dir("--out", out), (f"{name}.json", f"{name}_pr.png", f"{name}_calibration.png"))
        scored_on: dict[str, Any] = {}
        if nuscenes is not None:
            from ..replay.frames import SourceError
            from .data import nuscenes_samples, scene_of, split_holdout
            from .provenance import adapted_on_scans, seen_scenes

            if not os.path.isdir(nuscenes):
                fail(f"--nuscenes: not a directory: {nuscenes}")
            try:
                every = nuscenes_samples(nuscenes, sweeps=det.sweeps)
            except SourceError as exc:
                fail(f"--nuscenes: {exc}")
            scenes = list(dict.fromkeys(scene_of(s.token) for s in every))
            # the weights' lineage, resolved paths on both sides (a symlink or another spelling is the same dataroot)
            seen = seen_scenes(det.meta, nuscenes, scenes)
            if holdout_last:  # asked for: the tail of every scene, seen ones too (said in scored_on and the log)
                samples: Any = split_holdout(every, last_n=holdout_last)[1]
            else:
                samples = [s for s in every if scene_of(s.token) not in seen]
                if not samples:
                    fail(f"--nuscenes: the weights were trained on the labels of every scene of {nuscenes}"
                         f" ({', '.join(seen[:5])}{' …' if len(seen) > 5 else ''}; their metadata's source): score"
                         " a dataroot they never saw, or give --holdout-last N to score each scene's last N key"
                         " frames (frames of scenes that trained them: not a cross-scene figure)")
            scored = list(dict.fromkeys(scene_of(s.token) for s in samples))
            transductive = adapted_on_scans(det.meta, nuscenes)
            scored_on = {"nuscenes": str(Path(nuscenes).resolve()), "key_frames": len(samples), "sweeps": det.sweeps,
                         "holdout_last": holdout_last, "scenes": scored, "weights_trained_on_it": bool(seen),
                         "scored_scenes_trained_on": [s for s in scored if s in seen],
                         "weights_adapted_on_its_scans": transductive}
            if transductive:
                log.warning("these weights were adapted on %s's unlabelled scans: this scores test-time adaptation,"
                            " not a scene the weights have never seen", nuscenes)
            if scored_on["scored_scenes_trained_on"]:
                log.warning("these weights were trained on the labels of %d of the scored scenes: their last %d key"
                            " frames are scored, a within-scene figure, not a cross-scene one",
                            len(scored_on["scored_scenes_trained_on"]), holdout_last)
            elif seen:
                log.warning("these weights were trained on %d scenes of %s: scoring only the %d they never saw",
                            len(seen), nuscenes, len(scored))
        else:
            samples = synthetic_cache(Path(out), scen, sd, frames, progress, effects, sweeps=det.sweeps)
            scored_on = {"synthetic": {"scenarios": scen, "seeds": seeds, "frames_per_scenario": frames,
                                       "effects": ",".join(_effects(effects)) or "none", "sweeps": det.sweeps}}
        view = _Prepared(samples, det.config.point_cloud_range)
        items = [view[i] for i in range(len(view))]
        from tqdm import tqdm

        bar = tqdm(total=len(items), unit="scan", file=sys.stderr, disable=not progress)
        dets = []
        for s in items:
            dets.append(det.detect(s.points))
            bar.update(1)
        bar.close()
        summary = write_report(Path(out), name, dets, items, bootstrap=bootstrap, progress=progress, extra={
                               "scored_on": scored_on,
                               "weights": os.path.abspath(weights) if weights else "shipped " + (preset or "lite"),
                               "recalibrated": det.recalibration is not None, "flips": det.flips,
                               "sensor_height_m": "auto" if det.sensor_height_m is None else det.sensor_height_m,
                               "sensor_tilt": "auto" if det.sensor_tilt else "level",
                               "self_crop": list(det.self_crop) if det.self_crop is not None else None})["summary"]
        typer.echo(json.dumps({"samples": len(items), **summary}))

    @app.command("recalibrate-detector")
    def recalibrate_detector_cmd(
        weights: Annotated[str, typer.Option("--weights", help="Weights file whose variance recalibration is"
                                             " refitted (its network is copied unchanged).")],
        out: Annotated[str, typer.Option("--out", help="Folder for weights.pt, recalibration.json, the scans'"
                                         " cache and the calibration PNGs.")],
        scenarios: Annotated[str, typer.Option("--scenarios")] = DEFAULT_SCENARIOS,
        seeds: Annotated[str, typer.Option("--seeds", help="Synthetic seeds to fit on: neither the weights'"
                                           " training seeds (refused) nor the hold-out seeds 1000+.")] = "60-79",
        frames: Annotated[int, typer.Option("--frames-per-scenario", min=1, max=600)] = 10,
        effects: Annotated[str, typer.Option("--effects", help="Scan recipes, '+'-joined (as train's --effects):"
                                             " fit on scans like the training mix.")] = "none+random",
        bins: Annotated[int, typer.Option("--bins", min=1, max=20, help="Score bins (1: one global scale per"
                                          " axis).")] = RECALIBRATION_BINS,
        threads: Annotated[int | None, typer.Option("--threads", min=1, max=1024)] = None,
        workers: Annotated[int, typer.Option("--workers", min=0, max=64, help="Processes that ray-cast the"
                                             " scans (0: this one).")] = 0,
        progress: ProgressOpt = None,
    ) -> None:
        """Refit a weights file's per-axis variance scales, per detection-score bin, on labelled synthetic scans."""
        progress = progress_on(progress)
        if why := not_a_file(weights):
            fail(f"--weights: {why}")
        scen = _scenarios(scenarios)
        fit_on_seeds = fit_seeds(seeds, "--seeds")
        effect_sets = effects.split("+")
        for e in effect_sets:
            _effects(e)
        check_not_overwritten("--weights", weights, out)
        from .cli import passive_openmp

        passive_openmp()  # before torch is imported
        from .config import SELF_CROP_M
        from .inference import Detector, WeightsError, save_weights

        try:
            det = Detector.load(weights, threads=threads, recalibrate=False, self_crop=SELF_CROP_M)
        except WeightsError as exc:
            fail(f"--weights: {exc}")
        if not det.config.uncertainty:
            fail("--weights: a vanilla model predicts no variances to recalibrate")
        if why := seeds_refusal("--seeds", fit_on_seeds, det.meta):  # scales fitted on scans the network learnt
            fail(why)  # come out too small for the scans it has not
        out_files("--out", out_dir("--out", out), ("weights.pt", "recalibration.json"))  # after the flags and weights are checked, before any work
        try:
            rec, fitted = fit_synthetic_recalibration(det, Path(out), scen, seeds, frames, effect_sets, bins, progress,
                                                      workers)
        except ValueError as exc:  # no true positives: the weights' doing as much as the seeds' (the scans stay cached)
            fail(f"--weights {weights} on --seeds {seeds}: {exc}")

        root = Path(out)
        fit_on = fitted["fit_on"]
        meta = {**det.meta, "recalibration_fit_on": fit_on,
                "recalibrated_from": {"path": os.path.abspath(weights),
                                      "sha256_16": hashlib.sha256(Path(weights).read_bytes()).hexdigest()[:16],
                                      "recalibration": det.meta.get("recalibration_fit_on")},
                "recalibrate_command": " ".join(["jitterguard", *sys.argv[1:]])}
        save_weights(root / "weights.pt", det.model, recalibration=rec, meta=meta)
        report = {"weights": str(root / "weights.pt"), "recalibration": rec.to_payload(), **fitted}
        (root / "recalibration.json").write_text(json.dumps(report, indent=1))
        typer.echo(json.dumps(report))
