"""CLI of the classifier area: ``jitterguard classifier``, ``jitterguard feed-tracks``, ``jitterguard router``.
Commands import their implementation when they run (start-up time: see :mod:`jitterguard.cli`)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated

import typer

from ...cli_common import (
    ConnectOpt,
    check_seed,
    ListenOpt,
    LogLevelOpt,
    NsOpt,
    ParamFileOpt,
    ZenohConfigOpt,
    check_endpoints,
    fail,
    float_option,
    try_write,
    zenoh_options,
)
from ...config import ConfigError, load
from .config import PRESETS, ClassifierParams


def _load_config(path: str | None, preset: str | None, overrides: dict[str, object]) -> ClassifierParams:
    try:
        return load(ClassifierParams, path, service="classifier", preset=preset, overrides=overrides,
                    flags={"alpha_default": "--alpha"})
    except ConfigError as exc:  # the file's, or the preset's (its message names --preset)
        fail(f"--config: {exc}" if path is not None and not str(exc).startswith("--preset:") else str(exc))


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    @app.command("classifier")
    def classifier_cmd(
        ns: NsOpt = "default",
        zenoh_config: ZenohConfigOpt = None,
        connect: ConnectOpt = None,
        listen: ListenOpt = None,
        config: ParamFileOpt = None,
        preset: Annotated[str | None, typer.Option("--preset", help=f"Named preset: {', '.join(PRESETS)}.")] = None,
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
        calibration_store: Annotated[str | None, typer.Option(
            "--calibration-store", envvar="JG_CALIBRATION_STORE",
            help="File (.npz) keeping the online calibration across restarts.")] = None,
        open_config_writes: Annotated[bool, typer.Option(
            "--open-config-writes", help="Accept config writes over Zenoh without a token (when JG_API_TOKEN is "
                                         "unset). Only where the router listens on loopback alone.")] = False,
        log_level: LogLevelOpt = "INFO",
    ) -> None:
        """Run the motion classifier service: tracks/* + tracked in, motion/{id} + objects out."""
        from ...runtime import setup_logging
        from .calibration_file import CalibrationFileError, read_calibration
        from .calibration_store import CalibrationStore
        from .config_store import ConfigStore
        from .config_writes import ConfigWritePolicy
        from .service import ClassifierService

        opts = zenoh_options(ns, zenoh_config, connect, listen)
        if calibration_file is not None and calibration is None:
            calibration = "file"
        elif calibration_file is not None and calibration != "file":
            fail(f"--calibration-file is read with --calibration file, not --calibration {calibration}")
        elif calibration == "file" and calibration_file is None and config is None:  # had named no flag
            fail("--calibration file: needs --calibration-file FILE (a YAML from `jitterguard calibrate`)")
        params = _load_config(config, preset, {"alpha_default": alpha, "window_size": window_size,
                                               "min_window": min_window, "mode": mode, "effective_n": effective_n,
                                               "calibration": calibration, "calibration_file": calibration_file,
                                               "config_store": config_store, "calibration_store": calibration_store,
                                               "open_config_writes": open_config_writes or None})
        model = None
        if params.calibration == "file":
            try:
                model = read_calibration(params.calibration_file or "")
            except CalibrationFileError as exc:
                fail(f"{'--calibration-file' if calibration_file else 'calibration_file'}: {exc}")
        def writable_file(value: str | None, flag: str, key: str, given: str | None) -> Path | None:
            if not value:
                return None
            path = Path(value).absolute()
            if path.is_dir() or not path.parent.is_dir() or not os.access(path.parent, os.W_OK):
                fail(f"{flag if given else key}: {value} must be a file in a writable directory")
            # tried by opening it: the store had otherwise failed only at the first config write, long after start
            try_write(flag if given else key, Path(value))
            return path

        store_path = writable_file(params.config_store, "--config-store", "config_store", config_store)
        cal_path = writable_file(params.calibration_store, "--calibration-store", "calibration_store",
                                 calibration_store)
        store = ConfigStore(store_path) if store_path else None
        setup_logging(log_level)
        ClassifierService(opts, params.wire(), straggler_timeout_s=params.straggler_timeout_s, limits=params.limits,
                          stream=params.stream, manage_gc=True, config_store=store, calibration_model=model,
                          calibration_store=CalibrationStore(cal_path) if cal_path else None,
                          config_writes=ConfigWritePolicy.from_env(open_writes=params.open_config_writes)
                          ).run_forever()

    @app.command("feed-tracks")
    def feed_tracks_cmd(
        ns: NsOpt = "default",
        zenoh_config: ZenohConfigOpt = None,
        connect: ConnectOpt = None,
        listen: ListenOpt = None,
        frames: Annotated[int, typer.Option("--frames", min=1, help="Frames per loop.")] = 200,
        rate: Annotated[float, float_option("--rate", min=0.1, max=1000.0, help="Frames per second.")] = 10.0,
        loop: Annotated[bool, typer.Option("--loop/--no-loop", help="Start over (new track IDs) at the end.")] = False,
        seed: Annotated[int, typer.Option("--seed")] = 0,
        log_level: LogLevelOpt = "INFO",
    ) -> None:
        """Publish the built-in track-level scenario, as a tracker would (runs the classifier alone)."""
        from ...runtime import setup_logging
        from .feeder import TrackFeeder

        check_seed("--seed", seed)  # numpy refuses a negative one in the feeder's thread, which then ran on idle
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
        from ...runtime.zenoh_config import UnusableConfig, config_endpoints

        check_endpoints(list(listen or ()))
        try:
            cfg = router_config(list(listen or ()), zenoh_config)
        except ValueError as exc:
            fail(str(exc))
        # the file's endpoints too (a port of 99999 had come out as a log line, "invalid port value")
        check_endpoints(config_endpoints(cfg), f"--zenoh-config {zenoh_config}: " if zenoh_config else "")
        setup_logging(log_level)
        try:
            run_router(list(listen or ()), zenoh_config)
        except UnusableConfig as exc:  # a TLS file or setting missing, or zenoh's own refusal: one line, exit 2
            fail(str(exc))

