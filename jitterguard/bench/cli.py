"""``jitterguard bench …``: every benchmark behind one command group. Each prints JSON on stdout
(tracker, detector and sidecar only with ``--json``: a table or one line otherwise).

The benchmark modules themselves import what they time (the services, torch for the detector) only when their
command runs: ``jitterguard --help`` must not pay for torch or a Zenoh session.
"""

from __future__ import annotations

import json
import os
import sys
from typing import Annotated

import typer

from ..cli_common import (ProgressOpt, check_seed, fail, float_option, out_dir, parse_float, parse_int, parse_seeds,
                          progress_on, refuse_given)
from ..services.detector.cli import ThreadsOpt, _one_line, passive_openmp
from ..services.detector.config import PRESETS
from ..services.replay.frames import SourceError
from ..sim.cli import LidarOpt, check_scenario_options
from .survival import survival_command


def _parse_sizes(text: str) -> tuple[int, ...]:
    try:
        sizes = tuple(int(s) for s in text.split(",") if s.strip())
    except ValueError:
        fail(f"--sizes: expected comma-separated object counts, got {text!r}")
    if not sizes or any(n < 1 or n > 100_000 for n in sizes):
        fail(f"--sizes: each object count must be between 1 and 100000, got {text!r}")
    return sizes


def _parse_presets(text: str) -> tuple[str, ...]:
    names = tuple(s.strip() for s in text.split(",") if s.strip())
    unknown = [n for n in names if n not in PRESETS]
    if not names or unknown:
        fail(f"--presets: expected comma-separated names from {', '.join(PRESETS)}, got {text!r}")
    return tuple(dict.fromkeys(names))


def result_threads(result: dict) -> str:
    return ",".join(sorted({str(r["threads"]) for r in result.values()}))


MAX_BENCH_S = 3600.0
"""The longest timed run a benchmark takes, s: without a bound ``--duration inf`` had reached ``int(inf)`` (a
traceback) only after the services were started."""

MAX_REPLAY_POINTS = 4_000_000
"""Points per in-memory scan of ``bench replay``: the detector's default ``max_scan_bytes`` (64 MiB, four float32
fields). Unbounded, 10 billion had been a numpy MemoryError traceback while the clouds were made."""

MAX_REPLAY_FRAMES = 10_000_000
"""Scans per ``bench replay`` run: every one is listed in memory before the clock starts."""


def check_tracks_fit(tracks: int) -> None:
    """``bench classifier --tracks`` within what the classifier reads in one frame, or one line and exit 2: more
    than its ``limits.max_objects`` had been a LimitExceeded traceback from the frame-cost bench, after the core's
    seconds of timing."""
    from ..schemas.wire import LIMITS

    if tracks > LIMITS.max_objects:
        fail(f"--tracks {tracks} exceeds the classifier's limits.max_objects {LIMITS.max_objects}: every frame"
             " would be refused")  # bench sidecar: --state-source synthetic serves more, without a classifier


def register(app: typer.Typer, bench_app: typer.Typer) -> None:  # noqa: ARG001 - only bench commands here
    """Add every benchmark to ``jitterguard bench``."""
    bench_app.command("track-survival")(survival_command)

    @bench_app.command("classifier")
    def bench_classifier_cmd(
        as_json: Annotated[bool, typer.Option("--json", help="Print JSON (the only format).")] = True,
        duration: Annotated[float, float_option("--duration", min=1.0, max=MAX_BENCH_S,
                                                help="Service run, seconds.")] = 60.0,
        tracks: Annotated[int, typer.Option("--tracks", min=1, help="Tracks in every frame (at most the"
                                            " classifier's limits.max_objects, 1000).")] = 200,
        rate: Annotated[float, float_option("--rate", min=1.0, max=1000.0, help="Frames per second.")] = 20.0,
        skip_service: Annotated[bool, typer.Option("--core-only", help="Skip the 60 s service run.")] = False,
    ) -> None:
        """Time the core (10/100/1000 tracks), the per-frame work in-process and the live service over Zenoh;
        prints JSON."""
        check_tracks_fit(tracks)
        from .classifier import bench_core, bench_frame_cost, bench_service

        result: dict[str, object] = {"core": bench_core(), "frame_cost": bench_frame_cost(tracks=tracks)}
        if not skip_service:
            result["service"] = bench_service(tracks=tracks, rate_hz=rate, duration_s=duration)
        print(json.dumps(result, indent=2))
    @bench_app.command("tracker")
    def bench_tracker_cmd(
        json_out: Annotated[bool, typer.Option("--json", help="Print the result as one JSON document.")] = False,
        sizes: Annotated[str, typer.Option("--sizes", help="Comma-separated object counts.")] = "50,200,500",
        frames: Annotated[int, typer.Option("--frames", min=5, max=10_000, help="Timed frames per size.")] = 60,
        warmup: Annotated[int, typer.Option("--warmup", min=3, max=10_000, help="Untimed frames first.")] = 20,
        seed: Annotated[int, typer.Option("--seed")] = 0,
        pin: Annotated[bool, typer.Option("--pin/--no-pin", help="Pin to one CPU while timing.")] = True,
    ) -> None:
        """Time one frame's tracker update (core only, after warm-up) at several object counts."""
        from .tracker import run

        check_seed("--seed", seed)
        result = run(_parse_sizes(sizes), frames=frames, warmup=warmup, seed=seed, pin=pin)
        if json_out:
            typer.echo(json.dumps(result))
            return
        from rich.console import Console
        from rich.table import Table

        table = Table(title="tracker core: one frame's update")
        for col in ("objects", "median ms", "p90 ms", "max ms", "confirmed tracks"):
            table.add_column(col, justify="right")
        for key, row in result.items():
            table.add_row(key.split("_", 1)[1], f"{row['median_ms']:.3f}", f"{row['p90_ms']:.3f}",
                          f"{row['max_ms']:.3f}", str(row["confirmed_tracks"]))
        Console().print(table)
    @bench_app.command("detector")
    def bench_detector_cmd(
        json_out: Annotated[bool, typer.Option("--json", help="Print the result as one JSON document.")] = False,
        presets: Annotated[str, typer.Option("--presets", help="Comma-separated presets to time.")] = "lite,paper",
        scans: Annotated[int, typer.Option("--scans", min=1, max=10_000, help="Timed scans per preset.")] = 40,
        warmup: Annotated[int, typer.Option("--warmup", min=0, max=1000, help="Untimed scans first.")] = 3,
        threads: ThreadsOpt = None,
        weights: Annotated[
            list[str] | None,
            typer.Option("--weights", help="PRESET=FILE: time these weights for PRESET (repeatable; PRESET among"
                         " --presets, FILE a network of that preset); default the shipped weights, else random"
                         " init (same cost)."),
        ] = None,
        scenario: Annotated[str, typer.Option("--scenario", help="Synthetic scenario the scans come from.")] = "mixed",
        seed: Annotated[int, typer.Option("--seed")] = 0,
        progress: ProgressOpt = None,
        backends: Annotated[
            str | None,
            typer.Option("--backends", help="torch or torch,onnxruntime (timed side by side in this process, scan"
                         " by scan). Default: both when onnxruntime is installed (torch alone with"
                         " --sweeps > 1: stacked-sweep networks are not exported to ONNX)."),
        ] = None,
        device: Annotated[str, typer.Option("--device", help="cpu, or cuda / cuda:N: torch's voxelisation and"
                                            " network on that GPU.")] = "cpu",
        sweeps: Annotated[int, typer.Option("--sweeps", min=1, max=20, help="Time stacks of this many sweeps (20 Hz,"
                                            " one spin apart) on five-field networks (single-sweep weights widened"
                                            " by a zero time-lag input: the same cost).")] = 1,
        flips: Annotated[bool, typer.Option("--flips/--no-flips", help="Time the detector with test-time flips"
                                            " (the scan and its three mirror images).")] = False,
    ) -> None:
        """Time the detector end to end per HDL-32E scan (voxelisation, network, decode, NMS)."""
        progress = progress_on(progress)
        from .detector import SCENARIOS, available_backends, run

        check_seed("--seed", seed)
        chosen = available_backends() if backends is None else tuple(dict.fromkeys(
            b.strip() for b in backends.split(",") if b.strip()))
        if "torch" not in chosen or any(b not in ("torch", "onnxruntime") for b in chosen):
            fail(f"--backends: expected torch or torch,onnxruntime, got {backends!r}")
        if "onnxruntime" in chosen and "onnxruntime" not in available_backends():
            fail("--backends: onnxruntime needs the onnxruntime, onnx and onnxscript packages (pip install 'jitterguard[onnx]')")
        if sweeps > 1 and "onnxruntime" in chosen:  # stacked-sweep networks are not exported to ONNX (ExportError)
            if backends is not None:  # asked for both: refuse before the scans are ray-cast
                fail(f"--backends: onnxruntime cannot time --sweeps {sweeps} (stacked-sweep networks are not"
                     " exported to ONNX yet); give --backends torch")
            chosen = ("torch",)  # the default only: time what can be timed, and say so
            print(f"jitterguard: note: --sweeps {sweeps}: timing torch only (stacked-sweep networks are not"
                  " exported to ONNX yet)", file=sys.stderr)
        names = _parse_presets(presets)
        if device != "cpu":
            import torch

            try:
                if torch.device(device).type != "cuda":
                    raise ValueError
            except (RuntimeError, ValueError):
                fail(f"--device: expected cpu, cuda or cuda:N, got {device!r}")
            if not torch.cuda.is_available():
                fail(f"--device: {device} asked for, but torch sees no CUDA device on this machine")
        if scenario not in SCENARIOS:
            fail(f"--scenario: expected one of {', '.join(SCENARIOS)}, got {scenario!r}")
        files: dict[str, str] = {}
        for item in weights or []:
            name, sep, path = item.partition("=")
            if not sep or name not in PRESETS or not path:
                fail(f"--weights: expected PRESET=FILE with PRESET one of {', '.join(PRESETS)}, got {item!r}")
            if not os.path.isfile(path):
                fail(f"--weights: file not found: {path}")
            files[name] = path
        extra = [n for n in files if n not in names]
        if extra:  # it had been ignored without a word
            fail(f"--weights: {', '.join(extra)} is not among --presets {','.join(names)}; add it there or drop"
                 " its --weights")
        passive_openmp()
        from ..services.detector.inference import WeightsError, load_weights

        for name, path in files.items():  # a weights file fixes its network: its row must time the preset it names
            try:
                arch = load_weights(path)[0].config.name
            except WeightsError as exc:
                fail(f"--weights: {_one_line(exc)}")
            if arch != name:
                fail(f"--weights: {path} is a {arch!r} network, not {name!r}; give it as {arch}={path}")
        try:
            result = run(names, scans=scans, warmup=warmup, threads=threads, weights=files, scenario=scenario,
                         seed=seed, progress=progress, backends=chosen, device=device, sweeps=sweeps, flips=flips)
        except WeightsError as exc:
            fail(f"--weights: {_one_line(exc)}")
        except ValueError as exc:  # flips on weights whose grid is not symmetric about the sensor
            if not flips:
                raise
            fail(f"--flips: {_one_line(exc)}")
        if json_out:
            typer.echo(json.dumps(result))
            return
        from rich.console import Console
        from rich.table import Table

        table = Table(title=f"detector end to end per scan ({result_threads(result)} threads)")
        for col in ("preset", "points", "p50 ms", "p99 ms", "voxelize", "network", "decode", "detections"):
            table.add_column(col, justify="right")
        for name, row in result.items():
            for label, r in ((name, row), (f"{name} (onnxruntime)", row.get("onnxruntime"))):
                if r is None:
                    continue
                st = r["stages_ms"]
                table.add_row(label, f"{r['points']:.0f}", f"{r['p50_ms']:.1f}", f"{r['p99_ms']:.1f}",
                              f"{st['voxelize']:.1f}", f"{st['network']:.1f}", f"{st['decode']:.1f}",
                              f"{r['detections']:.0f}")
        Console().print(table)

    @bench_app.command("sidecar")
    def bench_sidecar(
        as_json: Annotated[bool, typer.Option("--json", help="Print the result as JSON only.")] = False,
        tracks: Annotated[str, typer.Option("--tracks", help="Live tracks in every frame (with the pipeline at most the classifier's limits.max_objects, 1000; up to 20000 with --state-source synthetic).")] = "500",
        rate: Annotated[str, typer.Option("--rate", help="Pipeline frame rate, Hz.")] = "20",
        duration: Annotated[str, typer.Option("--duration", help="Measured seconds.")] = "15",
        warmup: Annotated[str, typer.Option("--warmup", help="Seconds of load before measuring.")] = "3",
        request_rate: Annotated[str, typer.Option(
            "--request-rate", help="GET /v1/state per second from the load client (0: back to back).")] = "50",
        seed: Annotated[str, typer.Option("--seed", help="Scenario seed.")] = "0",
        state_source: Annotated[str, typer.Option(
            "--state-source", help="pipeline: the real classifier fed by a track feeder; synthetic: a stand-in "
                                   "serving the classifier's state queryable at --rate (isolates the sidecar).")
        ] = "pipeline",
    ) -> None:
        """GET /v1/state latency with N live tracks while the classifier runs at the given rate."""
        from .sidecar import BenchParams, run_bench

        if state_source not in ("pipeline", "synthetic"):
            fail(f"--state-source: {state_source!r} is not one of pipeline, synthetic")
        params = BenchParams(
            tracks=parse_int("--tracks", tracks, 1, 20_000), rate_hz=parse_float("--rate", rate, 0.5, 100.0),
            duration_s=parse_float("--duration", duration, 1.0, 3600.0),
            warmup_s=parse_float("--warmup", warmup, 0.0, 600.0),
            request_rate_hz=parse_float("--request-rate", request_rate, 0.0, 10_000.0),
            seed=check_seed("--seed", parse_int("--seed", seed, -(2**31), 2**31 - 1)), state_source=state_source)
        if state_source == "pipeline":  # the classifier refuses a frame of more (`--state-source synthetic` has none)
            check_tracks_fit(params.tracks)  # it had waited 120 s for tracks that never came, then a traceback
        try:
            result = run_bench(params)
        except RuntimeError as exc:
            print(f"jitterguard: error: bench failed: {exc}", file=sys.stderr)
            raise typer.Exit(1) from None
        if as_json:
            print(json.dumps(result, indent=2))
        else:
            lat = result["get_state_ms"]
            print(f"GET /v1/state, {result['tracks_seen']} tracks, pipeline {result['pipeline_hz']:.1f} Hz: "
                  f"p50 {lat['p50']:.2f} ms, p99 {lat['p99']:.2f} ms, max {lat['max']:.2f} ms "
                  f"over {lat['n']} requests")


    @bench_app.command("pipeline")
    def pipeline_cmd(
        objects: Annotated[int, typer.Option("--objects", min=1, help="Detections per frame (at most the services'"
                                             " limits.max_objects, 1000 by default).")] = 200,
        rate: Annotated[float, float_option("--rate", min=0.1, max=1000.0, help="Frames per second.")] = 20.0,
        duration: Annotated[float, float_option("--duration", min=1.0, max=MAX_BENCH_S,
                                                help="Seconds of load.")] = 60.0,
        seed: Annotated[int, typer.Option("--seed")] = 0,
        churn: Annotated[int, typer.Option("--churn", min=0, help="Objects moved to a new place each frame, so N "
                                                                  "new track IDs a frame (default 0).")] = 0,
        split: Annotated[bool, typer.Option("--split", help="Also time detections -> tracked (to_tracked_ms); "
                                                              "the extra subscriber adds load.")] = False,
        classifier_config: Annotated[str | None, typer.Option(
            "--classifier-config", help="Classifier parameter file (as `jitterguard classifier --config`).")] = None,
        tracker_config: Annotated[str | None, typer.Option(
            "--tracker-config", help="Tracker parameter file (as `jitterguard tracker --config`).")] = None,
        log_dir: Annotated[str | None, typer.Option(
            "--log-dir", help="Where the services' logs go (default: a new temporary folder; the JSON's `logs`).")] = None,
        as_json: Annotated[bool, typer.Option("--json", help="JSON on stdout (the only output format).")] = True,
    ) -> None:
        """Detections -> tracker -> classifier -> objects through real processes: latency, losses, RSS growth."""
        from .pipeline import bench_pipeline

        check_seed("--seed", seed)
        if churn > objects:  # had run and reported the churn asked for, though at most --objects can move
            fail(f"--churn {churn} exceeds --objects {objects}: at most every object can move each frame")

        from ..config import ConfigError, load
        from ..services.classifier.config import ClassifierParams
        from ..services.tracker.config import TrackerConfig

        # checked with each service's own loader before anything starts (a bad file is a one-line error, exit 2)
        for flag, path, model in (("--classifier-config", classifier_config, ClassifierParams),
                                  ("--tracker-config", tracker_config, TrackerConfig)):
            try:
                params = load(model, path)  # a missing file is its ConfigError too
            except ConfigError as exc:
                fail(f"{flag}: {exc}")
            cap = params.limits.max_objects
            if objects > cap:  # every frame had been dropped unread, and the run reported 0 frames out, exit 0
                fail(f"--objects {objects} exceeds the {flag[2:-7]}'s limits.max_objects {cap}: every frame would be"
                     f" refused; raise it in a {flag} file")
        # before the services start (its mkdir had been a traceback), after the flags (a refused run had left it
        # behind); a str, not a Path: Path("") is "." and the logs went into the current folder
        log_path = out_dir("--log-dir", log_dir) if log_dir is not None else None
        res = bench_pipeline(objects, rate, duration, seed, log_dir=log_path, split=split, churn=churn,
                             classifier_config=classifier_config, tracker_config=tracker_config)
        print(json.dumps(res, indent=None if as_json else 2))

    @bench_app.command("tracker-mot")
    def bench_tracker_mot_cmd(
        seeds: Annotated[str, typer.Option("--seeds", help="Comma-separated sequence seeds.")] = "0,1,2,3,4",
        frames: Annotated[int, typer.Option("--frames", min=10, max=10_000, help="Frames per sequence.")] = 150,
        measurement_covariance: Annotated[str, typer.Option(
            "--measurement-covariance", help="detector or class.")] = "detector",
    ) -> None:
        """Tracking quality of the tracker core on the seeded synthetic sequences (MOTA, IDF1, ID switches);
        the sequences and harness the tracker's tests assert on (MOTA >= 0.9, IDF1 >= 0.9)."""
        if measurement_covariance not in ("detector", "class"):
            fail(f"--measurement-covariance: expected detector or class, got {measurement_covariance!r}")
        seed_list = parse_seeds(seeds, "--seeds")  # as track-survival's: none had divided by zero
        from .tracker_mot import mot_summary  # motmetrics and pandas: seconds, after the flags are checked

        print(json.dumps(mot_summary(seed_list, frames, measurement_covariance), indent=2))

    bench_app.command("replay")(bench_replay_cmd)
    bench_app.command("sim")(bench_sim_cmd)


def bench_replay_cmd(
    ctx: typer.Context,
    json_out: Annotated[bool, typer.Option("--json", help="Print the figures as one JSON object (the default output).")] = True,
    frames: Annotated[int, typer.Option("--frames", help="Scans to publish.")] = 600,
    points: Annotated[int, typer.Option("--points", help="Points per in-memory scan.")] = 35_000,
    source: Annotated[str | None, typer.Option("--source", help="Bench a real recording (looped) instead of in-memory scans.")] = None,
    no_decode: Annotated[bool, typer.Option("--no-decode", help="Subscriber counts raw payloads instead of decoding them.")] = False,
    repeat: Annotated[int, typer.Option("--repeat", help="Runs; the median one is reported with every run's scans/s.")] = 3,
) -> None:
    """Replay --rate max into an in-process subscriber: scans/s and dropped count, as JSON."""
    if frames < 1 or points < 1 or repeat < 1:
        fail("--frames, --points and --repeat must be >= 1")
    if frames > MAX_REPLAY_FRAMES:
        fail(f"--frames: {frames} is more than {MAX_REPLAY_FRAMES:,} scans")
    if points > MAX_REPLAY_POINTS:
        fail(f"--points: {points} is more than {MAX_REPLAY_POINTS:,}, the detector's largest scan (max_scan_bytes)")
    if source is not None:  # a recording's scans have their own points: it had been ignored without a word
        refuse_given(ctx, ("points",), "to --source (the recording's scans are replayed as recorded)")
    from .replay import bench_replay_repeated

    try:
        result = bench_replay_repeated(repeat, frames=frames, points=points, source=source, decode_payloads=not no_decode)
    except SourceError as exc:
        fail(str(exc))
    except RuntimeError as exc:
        print(f"jitterguard: error: bench failed: {exc}", file=sys.stderr)
        raise typer.Exit(1) from None
    print(json.dumps(result, indent=None if json_out else 2))


def bench_sim_cmd(
    json_out: Annotated[bool, typer.Option("--json", help="Print the figures as one JSON object (the default output).")] = True,
    scans: Annotated[int, typer.Option("--scans", help="Scans per run.")] = 40,
    objects: Annotated[int, typer.Option("--objects", help="Road users in the scene (nearest kept).")] = 60,
    scenario: Annotated[str, typer.Option("--scenario", help="Scenario the scene comes from.")] = "parking-street",
    lidar: LidarOpt = "hdl32e",
    repeat: Annotated[int, typer.Option("--repeat", help="Runs; the median is reported with every run.")] = 3,
    replay_scans: Annotated[int, typer.Option("--replay-scans", help="Scans for the replay part (0 skips it).")] = 600,
) -> None:
    """Ray-casting throughput (full scans/s on one core) and replay at --rate max of 35k-point scans, as JSON:
    ``{"raycast": {"sensor", "rays", "objects", "scans_per_s", ...}, "replay": {"points_per_scan",
    "scans_per_s", "dropped", ...}}``."""
    check_scenario_options(scenario, 10.0, 10.0, lidar, flag="--scenario")
    if scans < 1 or objects < 0 or repeat < 1 or replay_scans < 0:
        fail("--scans and --repeat must be >= 1, --objects and --replay-scans >= 0")
    from .sim import bench_raycast

    rc = bench_raycast(lidar, scenario, objects, scans, repeat)
    out: dict[str, object] = {"raycast": {"sensor": lidar, "rays": rc["rays_per_scan"], "objects": rc["objects"],
                                          "scans_per_s": rc["scans_per_s"],
                                          **{k: v for k, v in rc.items() if k != "sensor"}, "sensor_name": rc["sensor"]}}
    if replay_scans:
        from .replay import bench_replay_repeated

        rp = bench_replay_repeated(repeat=repeat, frames=replay_scans, points=35_000)
        out["replay"] = {"points_per_scan": rp["points_per_scan"], "scans_per_s": rp["scans_per_s"],
                         "dropped": rp["dropped_all_runs"], **{k: v for k, v in rp.items() if k != "dropped"}}
    print(json.dumps(out, indent=None if json_out else 2))
