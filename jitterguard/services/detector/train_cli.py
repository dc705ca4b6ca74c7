"""``jitterguard train`` (train or fine-tune the detector) and ``jitterguard eval-detector`` (score weights).

Synthetic data is ray-cast once into an on-disk cache (``OUT/cache-*``, reused when it exists with the same
recipe), so epochs read numpy files instead of re-casting. Fine-tuning on a nuScenes-format dataroot holds
out each scene's last ``--holdout-last`` keyframes as the validation/test split (the issue's protocol).

Commands import their implementation when they run (start-up time: see :mod:`jitterguard.cli`).
"""

from __future__ import annotations

import json
import logging
import os
import sys
from pathlib import Path
from typing import Annotated, Any

import typer

from ...cli_common import ProgressOpt, fail, progress_on
from .config import PRESETS

log = logging.getLogger(__name__)

DEFAULT_SCENARIOS = "parking-street,diagonal-lot,intersection,mixed"


def parse_seeds(text: str, flag: str) -> list[int]:
    """``"0-49"``, ``"3,5,9"`` or a mix (``"0-9,100"``) → sorted unique ints; exit 2 naming ``flag`` otherwise."""
    seeds: set[int] = set()
    try:
        for part in (p.strip() for p in text.split(",") if p.strip()):
            lo, sep, hi = part.partition("-")
            if sep:
                a, b = int(lo), int(hi)
                if b < a or b - a > 100_000:
                    raise ValueError
                seeds.update(range(a, b + 1))
            else:
                seeds.add(int(part))
    except ValueError:
        fail(f"{flag}: expected seeds like 0-49 or 1,2,3 (non-negative), got {text!r}")
    if not seeds or min(seeds) < 0:
        fail(f"{flag}: expected seeds like 0-49 or 1,2,3 (non-negative), got {text!r}")
    return sorted(seeds)


def _scenarios(text: str) -> list[str]:
    from ...sim.world import SCENARIO_NAMES

    names = [s.strip() for s in text.split(",") if s.strip()]
    bad = [n for n in names if n not in SCENARIO_NAMES]
    if not names or bad:
        fail(f"--scenarios: expected comma-separated names from {', '.join(SCENARIO_NAMES)}, got {text!r}")
    return names


def synthetic_cache(root: Path, scenarios: list[str], seeds: list[int], frames: int, progress: bool) -> Any:
    """The cached synthetic samples for this recipe, ray-casting them first if the cache is missing or stale."""
    from .data import CachedSamples, build_cache, synthetic_samples

    recipe = {"scenarios": scenarios, "seeds": seeds, "frames_per_scenario": frames}
    import hashlib

    name = "cache-" + hashlib.sha1(json.dumps(recipe, sort_keys=True).encode()).hexdigest()[:10]
    path = root / name
    try:
        cached = CachedSamples(path)
        if cached.meta.get("recipe") == recipe:
            return cached
    except Exception:  # noqa: BLE001 - missing or interrupted cache: rebuild
        pass
    total = len(scenarios) * len(seeds) * frames
    build_cache(path, synthetic_samples(scenarios, seeds, frames_per_scenario=frames), total=total,
                progress=progress, meta={"recipe": recipe})
    return CachedSamples(path)


class _Prepared:
    """Range-filtered view of a sample sequence (the network never sees points outside its grid)."""

    def __init__(self, samples: Any, pcr: tuple[float, ...]) -> None:
        self.samples, self.pcr = samples, pcr

    def __len__(self) -> int:
        return len(self.samples)

    def __getitem__(self, i: Any) -> Any:
        from .augment import filter_range

        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        return filter_range(self.samples[i], self.pcr)


def write_report(out: Path, name: str, dets: Any, samples: Any) -> dict[str, Any]:
    """Evaluation JSON plus the PR and calibration PNGs under ``out``."""
    from .evaluate import evaluation_report
    from .plots import calibration_plot, pr_plot

    rep = evaluation_report(dets, samples, include_curves=True)
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


def register(app: typer.Typer, bench_app: typer.Typer) -> None:  # noqa: ARG001 - no benchmark here
    @app.command("train")
    def train_cmd(
        out: Annotated[str, typer.Option("--out", help="Run folder: caches, checkpoint.pt, history.json, weights.pt.")],
        preset: Annotated[str, typer.Option("--preset", help=f"Architecture: {', '.join(PRESETS)}.")] = "lite",
        vanilla: Annotated[bool, typer.Option("--vanilla", help="No variance heads (L1 instead of Gaussian NLL).")] = False,
        scenarios: Annotated[str, typer.Option("--scenarios", help="Synthetic scenarios to train on.")] = DEFAULT_SCENARIOS,
        train_seeds: Annotated[str, typer.Option("--train-seeds", help="Scenario seeds for training, e.g. 0-59.")] = "0-59",
        val_seeds: Annotated[str, typer.Option("--val-seeds", help="Seeds for per-epoch evaluation.")] = "900-901",
        frames: Annotated[int, typer.Option("--frames-per-scenario", min=1, max=600)] = 10,
        nuscenes: Annotated[str | None, typer.Option("--nuscenes", help="Fine-tune on this nuScenes dataroot instead"
                                                      " of synthetic scans.")] = None,
        holdout_last: Annotated[int, typer.Option("--holdout-last", min=1, help="Keyframes held out per scene"
                                                  " (nuScenes).")] = 10,
        init: Annotated[str | None, typer.Option("--init", help="Start from these weights (fine-tuning); the"
                                                 " learning-rate schedule starts afresh.")] = None,
        epochs: Annotated[int, typer.Option("--epochs", min=1, max=1000)] = 10,
        batch_size: Annotated[int, typer.Option("--batch-size", min=1, max=256)] = 4,
        lr: Annotated[float, typer.Option("--lr", min=1e-7, max=1.0)] = 2e-3,
        seed: Annotated[int, typer.Option("--seed", min=0)] = 0,
        threads: Annotated[int | None, typer.Option("--threads", min=1, max=1024)] = None,
        workers: Annotated[int, typer.Option("--workers", min=0, max=64, help="Data-loader processes.")] = 0,
        resume: Annotated[bool, typer.Option("--resume", help="Continue from OUT/checkpoint.pt.")] = False,
        fit_recalibration: Annotated[bool, typer.Option("--fit-recalibration/--no-fit-recalibration",
                                                        help="Fit per-axis variance scales on the validation split"
                                                        " and store them in weights.pt.")] = False,
        progress: ProgressOpt = None,
    ) -> None:
        """Train the detector on synthetic scans, or fine-tune it on a nuScenes dataroot (``--nuscenes``)."""
        progress = progress_on(progress)
        if preset not in PRESETS:
            fail(f"--preset: expected one of {', '.join(PRESETS)}, got {preset!r}")
        if init is not None and not os.path.isfile(init):
            fail(f"--init: file not found: {init}")
        if nuscenes is not None and not os.path.isdir(nuscenes):
            fail(f"--nuscenes: not a directory: {nuscenes}")
        scen = _scenarios(scenarios)
        tr_seeds, va_seeds = parse_seeds(train_seeds, "--train-seeds"), parse_seeds(val_seeds, "--val-seeds")
        if set(tr_seeds) & set(va_seeds) and nuscenes is None:
            fail("--val-seeds: must not overlap --train-seeds")
        logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
        from .cli import passive_openmp, retain_heap

        passive_openmp()  # before torch is imported
        retain_heap()
        import torch

        from .augment import random_augment
        from .evaluate import evaluation_report
        from .evaluate import fit_recalibration as fit_scales  # not `fit_recalibration`: that is the flag
        from .inference import WeightsError, load_weights, save_weights
        from .network import CenterPointNet
        from .train import TrainConfig, predict, train

        if threads:
            torch.set_num_threads(threads)
        root = Path(out)
        root.mkdir(parents=True, exist_ok=True)
        if init is not None:
            try:
                model, _, init_meta = load_weights(init)
            except WeightsError as exc:
                fail(f"--init: {exc}")
            if vanilla == model.config.uncertainty:
                fail("--init: weights are " + ("uncertainty-aware" if model.config.uncertainty else "vanilla")
                     + "; drop or add --vanilla to match")
        else:
            torch.manual_seed(seed)
            model = CenterPointNet(PRESETS[preset].model_copy(update={"uncertainty": not vanilla}))
        pcr = model.config.point_cloud_range
        if nuscenes is not None:
            from ..replay.frames import SourceError
            from .data import nuscenes_samples, split_holdout

            try:
                train_s, val_s = split_holdout(nuscenes_samples(nuscenes), last_n=holdout_last)
            except SourceError as exc:
                fail(f"--nuscenes: {exc}")
            source: dict[str, Any] = {"nuscenes": os.path.abspath(nuscenes), "holdout_last": holdout_last}
        else:
            train_s = synthetic_cache(root, scen, tr_seeds, frames, progress)
            val_s = synthetic_cache(root, scen, va_seeds, frames, progress)
            source = {"scenarios": scen, "train_seeds": train_seeds, "val_seeds": val_seeds,
                      "frames_per_scenario": frames}
        train_v, val_v = _Prepared(train_s, pcr), _Prepared(val_s, pcr)
        tcfg = TrainConfig(epochs=epochs, batch_size=batch_size, lr=lr, seed=seed, num_workers=workers)

        def evaluate(dets: Any, samples: Any) -> dict[str, Any]:
            return evaluation_report(dets, samples)["summary"]

        meta = {"source": source, "init": init, "command": " ".join(["jitterguard", *sys.argv[1:]])}
        state = train(model, train_v, val_v, tcfg, root, augment=random_augment, evaluate=evaluate,
                      resume=resume, progress=progress, meta=meta)
        val_list = [val_v[i] for i in range(len(val_v))]
        dets = predict(model, val_list)
        rec = None
        if fit_recalibration and model.config.uncertainty:
            try:
                rec = fit_scales(dets, val_list)
            except ValueError as exc:  # no true positives yet (a tiny run): keep the raw variances
                log.warning("no recalibration fitted: %s", exc)
        if rec is not None:
            save_weights(root / "weights.pt", model, recalibration=rec,
                         meta={**meta, "epochs": state.epoch, "recalibration_fit_on": "validation split"})
        summary = write_report(root / "report", "validation", dets, val_list)["summary"]
        typer.echo(json.dumps({"weights": str(root / "weights.pt"), "epochs": state.epoch,
                               "recalibration": rec, "validation": summary}))

    @app.command("eval-detector")
    def eval_detector_cmd(
        out: Annotated[str, typer.Option("--out", help="Folder for the JSON report and the PR/calibration PNGs.")],
        weights: Annotated[str | None, typer.Option("--weights", help="Weights file (default: shipped lite).")] = None,
        preset: Annotated[str, typer.Option("--preset")] = "lite",
        scenarios: Annotated[str, typer.Option("--scenarios")] = DEFAULT_SCENARIOS,
        seeds: Annotated[str, typer.Option("--seeds", help="Hold-out seeds (never used in training).")] = "1000-1004",
        frames: Annotated[int, typer.Option("--frames-per-scenario", min=1, max=600)] = 10,
        nuscenes: Annotated[str | None, typer.Option("--nuscenes", help="Evaluate on this dataroot's held-out"
                                                      " keyframes instead.")] = None,
        holdout_last: Annotated[int, typer.Option("--holdout-last", min=1)] = 10,
        recalibrate: Annotated[bool, typer.Option("--recalibrate/--no-recalibrate",
                                                  help="Apply the weights' fitted variance scales.")] = True,
        threads: Annotated[int | None, typer.Option("--threads", min=1, max=1024)] = None,
        name: Annotated[str, typer.Option("--name", help="File stem of the outputs.")] = "holdout",
        progress: ProgressOpt = None,
    ) -> None:
        """Score weights on a hold-out set: nuScenes-style AP, positional ECE; JSON + PNGs."""
        progress = progress_on(progress)
        if preset not in PRESETS:
            fail(f"--preset: expected one of {', '.join(PRESETS)}, got {preset!r}")
        if weights is not None and not os.path.isfile(weights):
            fail(f"--weights: file not found: {weights}")
        scen = _scenarios(scenarios)
        sd = parse_seeds(seeds, "--seeds")
        from .cli import passive_openmp

        passive_openmp()  # before torch is imported
        from .inference import Detector, WeightsError

        try:
            det = Detector.load(weights, preset, threads=threads, recalibrate=recalibrate)
        except WeightsError as exc:
            fail(f"--weights: {exc}")
        if nuscenes is not None:
            from .data import nuscenes_samples, split_holdout

            samples: Any = split_holdout(nuscenes_samples(nuscenes), last_n=holdout_last)[1]
        else:
            samples = synthetic_cache(Path(out), scen, sd, frames, progress)
        view = _Prepared(samples, det.config.point_cloud_range)
        items = [view[i] for i in range(len(view))]
        from tqdm import tqdm

        bar = tqdm(total=len(items), unit="scan", file=sys.stderr, disable=not progress)
        dets = []
        for s in items:
            dets.append(det.detect(s.points))
            bar.update(1)
        bar.close()
        summary = write_report(Path(out), name, dets, items)["summary"]
        typer.echo(json.dumps({"samples": len(items), **summary}))
