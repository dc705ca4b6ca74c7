"""Flags every service command shares, and the one way a command reports bad input (one line, exit 2).

Each area of jitterguard registers its own commands with ``register(app)`` in its ``cli.py``; this module
holds what they all reuse so the flags are spelled once.
"""

from __future__ import annotations

import os
import sys
from typing import Annotated, NoReturn

import typer

from .runtime import ZenohOptions, build_config
from .runtime.zenoh_config import ENV_CONFIG, ENV_NS

NsOpt = Annotated[str, typer.Option("--ns", envvar=ENV_NS, help="Namespace: keys live under jg/{ns}/...")]
ZenohConfigOpt = Annotated[
    str | None, typer.Option("--zenoh-config", envvar=ENV_CONFIG, help="Zenoh json5 config file.")
]
ConnectOpt = Annotated[
    list[str] | None, typer.Option("--connect", help="Zenoh endpoint to connect to (repeatable), e.g. tcp/127.0.0.1:7447.")
]
ListenOpt = Annotated[
    list[str] | None, typer.Option("--listen", help="Zenoh endpoint to listen on (repeatable).")
]
LogLevelOpt = Annotated[str, typer.Option("--log-level", help="DEBUG, INFO, WARNING or ERROR.")]
ParamFileOpt = Annotated[str | None, typer.Option(
    "--config", help="Parameter file (flat, or Autoware's ros__parameters form) overriding the service's defaults"
    " in jitterguard/config/<service>.param.yaml; the flags below override it.")]
ProgressOpt = Annotated[
    bool | None, typer.Option("--progress/--no-progress", help="Progress bar on stderr (default: when stderr is a terminal).")
]


def progress_on(flag: bool | None) -> bool:
    """Whether to draw a progress bar: as asked, else only on a terminal (a redirected log gets no carriage
    returns)."""
    return sys.stderr.isatty() if flag is None else flag


def fail(message: str) -> NoReturn:
    """Print a one-line error to stderr and exit with status 2 (bad input)."""
    print(f"jitterguard: error: {message}", file=sys.stderr)
    raise SystemExit(2)


def parse_float(flag: str, text: str, lo: float, hi: float) -> float:
    """``text`` as a number in [lo, hi], or a one-line error naming ``flag`` (exit 2)."""
    try:
        value = float(text)
    except ValueError:
        fail(f"{flag}: {text!r} is not a number")
    if not lo <= value <= hi:
        fail(f"{flag}: {value:g} is outside {lo:g}-{hi:g}")
    return value


def zenoh_options(ns: str, zenoh_config: str | None, connect: list[str] | None, listen: list[str] | None) -> ZenohOptions:
    """Validate the shared flags into :class:`ZenohOptions`, failing with one line on bad input."""
    try:
        opts = ZenohOptions(ns=ns, config_file=zenoh_config, connect=tuple(connect or ()), listen=tuple(listen or ()))
    except ValueError as exc:
        fail(f"--ns: {exc}")
    if zenoh_config and not os.path.isfile(zenoh_config):
        fail(f"--zenoh-config: file not found: {zenoh_config}")
    for ep in (*opts.connect, *opts.listen):
        if "/" not in ep:
            fail(f"endpoint {ep!r} must look like tcp/HOST:PORT")
    try:  # the whole config, now: a bad file or an exposed listener is a one-line error before anything starts
        build_config(opts)
    except ValueError as exc:
        fail(str(exc))
    return opts
