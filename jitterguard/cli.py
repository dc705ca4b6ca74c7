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
    "jitterguard.services.replay.cli",
    "jitterguard.services.sidecar.cli",
    "jitterguard.sim.cli",
    "jitterguard.stack.cli",
)

for _mod in _AREAS:
    try:
        _m = importlib.import_module(_mod)
    except ModuleNotFoundError as _exc:
        if _exc.name and _mod.startswith(_exc.name):
            continue  # that area is not part of this build
        raise
    _m.register(app, bench_app)


def main() -> None:
    """Console entry point. Usage errors exit 2 with a one-line message (Click's convention)."""
    try:
        app(standalone_mode=True)
    except KeyboardInterrupt:
        sys.exit(130)


if __name__ == "__main__":
    main()
