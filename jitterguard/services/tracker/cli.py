"""CLI of the tracker area: ``jitterguard tracker`` and ``jitterguard bench tracker``."""

from __future__ import annotations

import json
from typing import Annotated

import typer

from ...cli_common import ConnectOpt, ListenOpt, LogLevelOpt, NsOpt, ZenohConfigOpt, fail, zenoh_options

MEAS_CHOICES = ("detector", "class")


def _parse_sizes(text: str) -> tuple[int, ...]:
    try:
        sizes = tuple(int(s) for s in text.split(",") if s.strip())
    except ValueError:
        fail(f"--sizes: expected comma-separated object counts, got {text!r}")
    if not sizes or any(n < 1 or n > 100_000 for n in sizes):
        fail(f"--sizes: each object count must be between 1 and 100000, got {text!r}")
    return sizes


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    @app.command("tracker")
    def tracker_cmd(
        ns: NsOpt = "default",
        zenoh_config: ZenohConfigOpt = None,
        connect: ConnectOpt = None,
        listen: ListenOpt = None,
        config: Annotated[
            str | None,
            typer.Option("--config", help="Parameter file overriding any of the defaults in"
                         " jitterguard/config/tracker.param.yaml (flat, or Autoware's ros__parameters form)."),
        ] = None,
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
        from .bench import run

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
