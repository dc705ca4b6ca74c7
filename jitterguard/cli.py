"""The ``jitterguard`` command: one Typer app; each area registers its own sub-commands."""

from __future__ import annotations

import importlib
import sys

import typer

app = typer.Typer(
    name="jitterguard",
    help="Tell real motion from perception jitter in LiDAR stacks.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)
bench_app = typer.Typer(help="Benchmarks; each prints JSON.", no_args_is_help=True)
app.add_typer(bench_app, name="bench")

# Modules exposing ``register(app, bench_app)``; a missing optional area is skipped, not fatal.
_AREAS = (
    "jitterguard.services.classifier.cli",
    "jitterguard.services.tracker.cli",
    "jitterguard.services.detector.cli",
    "jitterguard.services.detector.train_cli",
    "jitterguard.services.detector.onnx_cli",
    "jitterguard.services.replay.cli",
    "jitterguard.services.sidecar.cli",
    "jitterguard.services.foxglove.cli",
    "jitterguard.services.recorder.cli",
    "jitterguard.sim.cli",
    "jitterguard.stack.cli",
    "jitterguard.stack.bench",
    "jitterguard.eval.cli",
    "jitterguard.eval.calibrate",
)

for _mod in _AREAS:
    try:
        _m = importlib.import_module(_mod)
    except ModuleNotFoundError as _exc:
        if _exc.name and _mod.startswith(_exc.name):
            continue  # that area is not part of this build
        raise
    _m.register(app, bench_app)


def main(argv: list[str] | None = None) -> None:
    """Console entry point. Bad input (usage errors, bad values) exits 2 with one line on stderr."""
    try:  # typer >= 0.20 vendors click as typer._click; older typer uses click itself
        from typer._click import exceptions as click_exc  # type: ignore[import-not-found]
    except ImportError:  # pragma: no cover - depends on the installed typer
        from click import exceptions as click_exc

    try:
        rv = app(args=argv, standalone_mode=False)
    except getattr(click_exc, "NoArgsIsHelpError", ()) as exc:
        print(exc.ctx.get_help())
        sys.exit(0)
    except click_exc.UsageError as exc:
        where = exc.ctx.command_path if exc.ctx is not None else "jitterguard"
        msg = exc.format_message().replace("\n", " ")
        print(f"{where}: error: {msg} (see --help)", file=sys.stderr)
        sys.exit(2)
    except (KeyboardInterrupt, getattr(click_exc, "Abort", KeyboardInterrupt)):
        sys.exit(130)
    sys.exit(rv if isinstance(rv, int) else 0)


if __name__ == "__main__":
    main()
