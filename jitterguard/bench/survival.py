"""``jitterguard bench track-survival``: :func:`jitterguard.eval.survival.survival` with the shipped detector on
ray-cast scans.

The scans are built as ``jitterguard replay synthetic:NAME`` publishes them and the detector runs as its service
does (:mod:`jitterguard.eval.detector_input`), so the figure is the live stack's. Imports are deferred: the
``bench`` area imports this module to register it, and torch and the simulator cost seconds.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Iterable, Iterator
from typing import TYPE_CHECKING, Annotated, Any

import typer

from ..cli_common import fail, parse_seeds, progress_on
from ..sim.cli import check_scenario_options

if TYPE_CHECKING:
    from ..schemas.models import DetectedObjects
    from ..sim.world import GroundTruthFrame

DEFAULT_MIN_POINTS = 5  # keep in step with survival.DEFAULT_MIN_POINTS (checked by a test)


def detector_frames_for(scenario: str, seed: int, duration_s: float, rate_hz: float, threads: int | None,
                        progress: bool) -> Iterator[tuple[GroundTruthFrame, bytes]]:
    """The shipped detector on ray-cast scans of ``scenario``, as the ``DetectedObjects`` payloads the detector
    service publishes."""
    from ..services.detector.inference import Detector
    from ..sim.world import make_scenario
    from ..eval.detector_input import detector_frames, synthetic_scans

    detector = Detector.load(None, "lite", threads=threads)
    sc = make_scenario(scenario, seed, duration_s, rate_hz)
    scans: Iterable[Any] = synthetic_scans(sc, seed)
    if progress:
        from tqdm import tqdm  # type: ignore[import-untyped]

        scans = tqdm(scans, total=len(sc), desc=f"{scenario} seed {seed}", unit="scan", file=sys.stderr, leave=False)
    for f in detector_frames(scans, detector.detect, class_names=detector.config.class_names,
                             uncertainty=detector.config.uncertainty, sweeps=detector.sweeps):
        yield f.gt, f.detections


def survival_command(
    scenario: Annotated[str, typer.Option("--scenario", help="Synthetic scenario.")] = "mixed",
    seeds: Annotated[str, typer.Option("--seeds", help="Seeds, each one scenario run: a range (0-4), a list (0,2,5) or both.")] = "0,1,2,3,4",
    duration: Annotated[float, typer.Option("--duration", help="Scenario length \\[s].")] = 30.0,
    rate: Annotated[float, typer.Option("--rate", help="Frame rate [Hz] (the stack's replay runs 10 Hz).")] = 10.0,
    horizon: Annotated[float, typer.Option("--horizon", help="Seconds a track ID must survive (shorter than --duration).")] = 1.0,
    min_points: Annotated[int, typer.Option("--min-points", help="LiDAR returns for an object to be in view.")] = DEFAULT_MIN_POINTS,
    tracker_config: Annotated[str | None, typer.Option("--tracker-config", help="Tracker YAML (as `jitterguard tracker --config`).")] = None,
    threads: Annotated[int | None, typer.Option("--threads", min=1, max=1024, help="torch CPU threads of the detector.")] = None,
) -> None:
    """Track-ID survival with the shipped detector on a synthetic scenario, as JSON (pooled and per seed)."""
    seed_list = parse_seeds(seeds, "--seeds")
    if not 0 < duration <= 600 or not 0 < rate <= 100 or not horizon > 0 or min_points < 0:
        fail("--duration must be in (0, 600], --rate in (0, 100], --horizon > 0 and --min-points >= 0")
    # an unknown scenario had been a ValueError from make_scenario
    check_scenario_options(scenario, duration, rate, flag="--scenario")
    if horizon >= duration:  # no track could be followed that long: every figure had come out null, exit 0
        fail(f"--horizon {horizon:g} s must be shorter than --duration {duration:g} s")
    from ..config import ConfigError
    from ..eval.survival import score, survival_run
    from ..services.tracker.config import default_config, load_config

    try:
        cfg = load_config(tracker_config) if tracker_config else default_config()
    except ConfigError as exc:
        fail(f"--tracker-config: {exc}")
    runs = []
    per_seed: dict[str, Any] = {}
    for s in seed_list:
        run = survival_run(detector_frames_for(scenario, s, duration, rate, threads, progress_on(None)), cfg,
                           horizon_s=horizon, min_points=min_points)
        runs.append(run)
        per_seed[f"seed_{s}"] = score([run])
    pooled = {
        **score(runs),
        "survival_min_seed": min((r["survival"] for r in per_seed.values() if r["survival"] is not None),
                                 default=None),
        "seeds": seed_list, "scenario": scenario, "duration_s": duration, "rate_hz": rate,
        "confirm_hits": cfg.confirm_hits, "confirm_min_existence": cfg.confirm_min_existence,
        "max_coast_s": cfg.max_coast_s,
    }
    print(json.dumps({"pooled": pooled, **per_seed}, indent=2))

