"""CLI of the tracker area: ``jitterguard tracker``.

Commands import their implementation when they run (start-up time: see :mod:`jitterguard.cli`).
"""

from __future__ import annotations

from typing import Annotated

import typer

from ...cli_common import ConnectOpt, ListenOpt, LogLevelOpt, NsOpt, ParamFileOpt, ZenohConfigOpt, fail, zenoh_options

MEAS_CHOICES = ("detector", "class")


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    @app.command("tracker")
    def tracker_cmd(
        ns: NsOpt = "default",
        zenoh_config: ZenohConfigOpt = None,
        connect: ConnectOpt = None,
        listen: ListenOpt = None,
        config: ParamFileOpt = None,
        measurement_covariance: Annotated[
            str | None,
            typer.Option("--measurement-covariance",
                         help="detector: the detector's own variances where present; class: class defaults."),
        ] = None,
        static_hints: Annotated[
            bool,
            typer.Option("--static-hints/--no-static-hints",
                         help="Apply the classifier's static decisions (motion/*) to tracks: zero velocity,"
                         " window-mean position (Autoware's setStaticState)."),
        ] = False,
        print_config: Annotated[
            bool, typer.Option("--print-config", help="Print the effective config as YAML and exit.")
        ] = False,
        log_level: LogLevelOpt = "INFO",
    ) -> None:
        """Run the tracker: detections in; tracks/{id} for each track observed this frame, then tracked."""
        from ...config import ConfigError
        from .config import dump_config, load_config

        if measurement_covariance is not None and measurement_covariance not in MEAS_CHOICES:
            fail(f"--measurement-covariance: expected one of {', '.join(MEAS_CHOICES)}, got {measurement_covariance!r}")
        try:
            cfg = load_config(config, measurement_covariance=measurement_covariance)
        except ConfigError as exc:
            fail(f"--config: {exc}")
        if print_config:
            typer.echo(dump_config(cfg), nl=False)
            return
        opts = zenoh_options(ns, zenoh_config, connect, listen)

        from ...runtime import setup_logging
        from .service import TrackerService

        setup_logging(log_level)
        try:
            service = TrackerService(opts, cfg, static_hints=static_hints, manage_gc=True)
        except ValueError as exc:  # build_config names the bad endpoint / setting
            fail(str(exc))
        service.run_forever()

