"""The ``jitterguard`` command: one Typer app; each area registers its own sub-commands.

Every area's command bodies import what they run inside the command (the only function-level imports of the
``cli`` modules, and deliberate): start-up time — ``jitterguard --help`` or a one-line usage error must not load
torch, FastAPI or a Zenoh session.

``app`` (imported by the tests and docs checks) has every area registered. A long-running service started by
supervisord (``jitterguard tracker ...``) registers only its own area: seven services importing every area at
once cost seconds of CPU before the first frame on a two-core machine.
"""

from __future__ import annotations

import importlib
import sys
from typing import Any

import typer


def _new_app() -> tuple[typer.Typer, typer.Typer]:
    root = typer.Typer(
        name="jitterguard",
        help="Tell real motion from perception jitter in LiDAR stacks.",
        no_args_is_help=True,
        pretty_exceptions_enable=False,
        add_completion=False,
    )
    bench = typer.Typer(help="Benchmarks; each prints JSON on stdout (tracker, detector and sidecar only with --json:"
                             " a table or one line otherwise).", no_args_is_help=True)
    root.add_typer(bench, name="bench")
    return root, bench


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
    "jitterguard.services.ros2live.cli",
    "jitterguard.sim.cli",
    "jitterguard.stack.cli",
    "jitterguard.stack.monitor",
    "jitterguard.bench.cli",
    "jitterguard.eval.cli",
    "jitterguard.eval.calibrate",
)

SERVICE_AREAS = {
    "router": "jitterguard.services.classifier.cli",
    "classifier": "jitterguard.services.classifier.cli",
    "feed-tracks": "jitterguard.services.classifier.cli",
    "tracker": "jitterguard.services.tracker.cli",
    "detector": "jitterguard.services.detector.cli",
    "replay": "jitterguard.services.replay.cli",
    "sidecar": "jitterguard.services.sidecar.cli",
    "stack-monitor": "jitterguard.stack.monitor",
}
"""The programs ``jitterguard up`` runs, and the one area each needs (a test holds this table to the full app)."""


def build_app(areas: tuple[str, ...] = _AREAS) -> tuple[typer.Typer, typer.Typer]:
    """An app with ``areas`` registered (a missing optional area is skipped, not fatal)."""
    root, bench = _new_app()
    for mod in areas:
        try:
            m = importlib.import_module(mod)
        except ModuleNotFoundError as exc:
            if exc.name and mod.startswith(exc.name):
                continue  # that area is not part of this build
            raise
        m.register(root, bench)
    return root, bench


_full: tuple[typer.Typer, typer.Typer] | None = None


def __getattr__(name: str) -> Any:
    """``app`` and ``bench_app``: the full command tree, built on first use."""
    global _full
    if name in ("app", "bench_app"):
        if _full is None:
            _full = build_app()
        return _full[0] if name == "app" else _full[1]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _plain_flags(command: object) -> None:
    """Blank the type column of on/off flags in ``--help`` (Typer prints ``<bool>`` after ``--detach``, as if it
    took a value), for every command of the tree."""
    for param in getattr(command, "params", ()):
        if getattr(param, "is_flag", False) and getattr(param, "metavar", None) is None:
            param.metavar = ""
    make_help = getattr(command, "get_help_option", None)
    if make_help is not None:  # --help itself is made per context

        def help_option(ctx: object, _make: object = make_help) -> object:
            opt = _make(ctx)  # type: ignore[operator]
            if opt is not None and getattr(opt, "metavar", None) is None:
                opt.metavar = ""
            return opt

        command.get_help_option = help_option  # type: ignore[attr-defined]
    for sub in getattr(command, "commands", {}).values():
        _plain_flags(sub)


def _command_path(command: Any, args: list[str]) -> str:
    """``jitterguard bench classifier`` for the (sub)command words that lead ``args``: click gives a missing option
    value's error no context to name its command by."""
    words = ["jitterguard"]
    for a in args:
        sub = (getattr(command, "commands", None) or {}).get(a)
        if sub is None:
            break
        words.append(a)
        command = sub
    return " ".join(words)


def main(argv: list[str] | None = None) -> None:
    """Console entry point. Bad input (usage errors, bad values) exits 2 with one line on stderr."""
    try:  # typer >= 0.20 vendors click as typer._click; older typer uses click itself
        from typer._click import exceptions as click_exc  # type: ignore[import-not-found]
    except ImportError:  # pragma: no cover - depends on the installed typer
        from click import exceptions as click_exc

    args = sys.argv[1:] if argv is None else list(argv)
    area = SERVICE_AREAS.get(args[0]) if args else None
    root = build_app((area,))[0] if area is not None else __getattr__("app")
    command = typer.main.get_command(root)
    _plain_flags(command)
    try:
        rv = command.main(args=args, standalone_mode=False, prog_name="jitterguard")
    except getattr(click_exc, "NoArgsIsHelpError", ()) as exc:
        print(exc.ctx.get_help())
        sys.exit(0)
    except click_exc.UsageError as exc:
        # the prefix of every refusal (fail()'s), the command in the hint: click's own had been prefixed with the
        # command path ("jitterguard eval: error:"), or not (a missing option value), beside fail()'s plain one
        where = exc.ctx.command_path if exc.ctx is not None else _command_path(command, args)
        msg = " ".join(exc.format_message().split())
        print(f"jitterguard: error: {msg} (see {where} --help)", file=sys.stderr)
        sys.exit(2)
    except (KeyboardInterrupt, getattr(click_exc, "Abort", KeyboardInterrupt)):
        sys.exit(130)
    sys.exit(rv if isinstance(rv, int) else 0)


if __name__ == "__main__":
    main()
