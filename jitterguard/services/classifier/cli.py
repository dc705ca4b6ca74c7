"""CLI of the classifier area: ``jitterguard classifier``, ``jitterguard feed-tracks``, ``jitterguard router``
and ``jitterguard bench classifier``."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Annotated

import typer

from ...cli_common import ConnectOpt, ListenOpt, LogLevelOpt, NsOpt, ZenohConfigOpt, fail, zenoh_options
from ...schemas.models import PRESETS, ClassifierConfig


def _load_config(path: str | None, preset: str | None, overrides: dict[str, object]) -> ClassifierConfig:
    base: dict[str, object] = {}
    if path:
        p = Path(path)
        if not p.is_file():
            fail(f"--config: file not found: {path}")
        try:
            import yaml

            loaded = yaml.safe_load(p.read_text()) or {}
        except Exception as exc:
            fail(f"--config: {path}: cannot parse: {exc}")
        if not isinstance(loaded, dict):
            fail(f"--config: {path}: expected a mapping of ClassifierConfig fields")
        base.update(loaded)
    if preset:
        if preset not in PRESETS:
            fail(f"--preset: unknown preset {preset!r}; choose from {sorted(PRESETS)}")
        base.update(PRESETS[preset])
    base.update({k: v for k, v in overrides.items() if v is not None})
    try:
        return ClassifierConfig.model_validate(base)
    except Exception as exc:
        err = exc.errors()[0] if hasattr(exc, "errors") else {"loc": (), "msg": str(exc)}
        field = ".".join(str(x) for x in err["loc"]) or "config"
        fail(f"{field}: {err['msg']}")


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    @app.command("classifier")
    def classifier_cmd(
        ns: NsOpt = "default",
        zenoh_config: ZenohConfigOpt = None,
        connect: ConnectOpt = None,
        listen: ListenOpt = None,
        config: Annotated[str | None, typer.Option("--config", help="YAML file of ClassifierConfig fields.")] = None,
        preset: Annotated[str | None, typer.Option("--preset", help="Named alpha preset: paper or authors.")] = None,
        alpha: Annotated[float | None, typer.Option("--alpha", help="Default alpha (z threshold).")] = None,
        window_size: Annotated[int | None, typer.Option("--window-size")] = None,
        min_window: Annotated[int | None, typer.Option("--min-window")] = None,
        mode: Annotated[str | None, typer.Option("--mode", help="z_test, chi2 or velocity_threshold.")] = None,
        effective_n: Annotated[str | None, typer.Option("--effective-n", help="measured (default), cluster or "
                                                        "independent.")] = None,
        calibration: Annotated[str | None, typer.Option("--calibration", help="online (default), off or file "
                                                        "(with --calibration-file).")] = None,
        calibration_file: Annotated[str | None, typer.Option("--calibration-file", help="YAML from `jitterguard "
                                                             "calibrate`; implies --calibration file.")] = None,
        config_store: Annotated[str | None, typer.Option(
            "--config-store", envvar="JG_CONFIG_STORE",
            help="JSON file keeping config writes across restarts (restored while the flags stay the same).")] = None,
        open_config_writes: Annotated[bool, typer.Option(
            "--open-config-writes", help="Accept config writes over Zenoh without a token (when JG_API_TOKEN is "
                                         "unset). Only where the router listens on loopback alone.")] = False,
        log_level: LogLevelOpt = "INFO",
    ) -> None:
        """Run the motion classifier service: tracks/* + tracked in, motion/{id} + objects out."""
        from ...runtime import setup_logging
        from .calibration_file import CalibrationFileError, read_calibration
        from .config_store import ConfigStore
        from .config_writes import ConfigWritePolicy
        from .service import ClassifierService

        opts = zenoh_options(ns, zenoh_config, connect, listen)
        if calibration_file is not None and calibration is None:
            calibration = "file"
        cfg = _load_config(config, preset, {"alpha_default": alpha, "window_size": window_size,
                                             "min_window": min_window, "mode": mode, "effective_n": effective_n,
                                             "calibration": calibration, "calibration_file": calibration_file})
        model = None
        if cfg.calibration == "file":
            try:
                model = read_calibration(cfg.calibration_file or "")
            except CalibrationFileError as exc:
                fail(f"--calibration-file: {exc}")
        store = None
        if config_store:
            parent = Path(config_store).absolute().parent
            if Path(config_store).is_dir() or not parent.is_dir() or not os.access(parent, os.W_OK):
                fail(f"--config-store: {config_store} must be a file in a writable directory")
            store = ConfigStore(Path(config_store).absolute())
        setup_logging(log_level)
        ClassifierService(opts, cfg, manage_gc=True, calibration_model=model, config_store=store,
                          config_writes=ConfigWritePolicy.from_env(open_writes=open_config_writes)).run_forever()

    @app.command("feed-tracks")
    def feed_tracks_cmd(
        ns: NsOpt = "default",
        zenoh_config: ZenohConfigOpt = None,
        connect: ConnectOpt = None,
        listen: ListenOpt = None,
        frames: Annotated[int, typer.Option("--frames", min=1, help="Frames per loop.")] = 200,
        rate: Annotated[float, typer.Option("--rate", min=0.1, max=1000.0, help="Frames per second.")] = 10.0,
        loop: Annotated[bool, typer.Option("--loop/--no-loop", help="Start over (new track IDs) at the end.")] = False,
        seed: Annotated[int, typer.Option("--seed")] = 0,
        log_level: LogLevelOpt = "INFO",
    ) -> None:
        """Publish the built-in track-level scenario, as a tracker would (runs the classifier alone)."""
        from ...runtime import setup_logging
        from .feeder import TrackFeeder

        opts = zenoh_options(ns, zenoh_config, connect, listen)
        setup_logging(log_level)
        TrackFeeder(opts, frames=frames, rate_hz=rate, loop=loop, seed=seed).run_forever()

    @app.command("router")
    def router_cmd(
        listen: Annotated[list[str] | None, typer.Option(
            "--listen", help="Endpoint(s); default: the config file's, else tcp/127.0.0.1:7447. Off loopback only "
                             "tls/ with mutual TLS.")] = None,
        zenoh_config: ZenohConfigOpt = None,
        log_level: LogLevelOpt = "INFO",
    ) -> None:
        """Run a Zenoh router in this Python process (no separate zenohd binary needed)."""
        from ...runtime import setup_logging
        from ...runtime.router import router_config, run_router

        try:
            router_config(list(listen or ()), zenoh_config)
        except ValueError as exc:
            fail(str(exc))
        setup_logging(log_level)
        run_router(list(listen or ()), zenoh_config)

    @bench_app.command("classifier")
    def bench_classifier_cmd(
        as_json: Annotated[bool, typer.Option("--json", help="Print JSON (the only format).")] = True,
        duration: Annotated[float, typer.Option("--duration", min=1.0, help="Service run, seconds.")] = 60.0,
        tracks: Annotated[int, typer.Option("--tracks", min=1)] = 200,
        rate: Annotated[float, typer.Option("--rate", min=1.0)] = 20.0,
        skip_service: Annotated[bool, typer.Option("--core-only", help="Skip the 60 s service run.")] = False,
    ) -> None:
        """Time the core (10/100/1000 tracks), the per-frame work in-process and the live service over Zenoh;
        prints JSON."""
        from .bench import bench_core, bench_frame_cost, bench_service

        result: dict[str, object] = {"core": bench_core(), "frame_cost": bench_frame_cost(tracks=tracks)}
        if not skip_service:
            result["service"] = bench_service(tracks=tracks, rate_hz=rate, duration_s=duration)
        print(json.dumps(result, indent=2))
