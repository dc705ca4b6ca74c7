"""Flags every service command shares, and the one way a command reports bad input (one line, exit 2).

Each area of jitterguard registers its own commands with ``register(app)`` in its ``cli.py``; this module
holds what they all reuse so the flags are spelled once.
"""

from __future__ import annotations

import atexit
import math
import os
import sys
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Annotated, Any, NoReturn

import typer

from .files import not_a_file
from .runtime import ZenohOptions, build_config
from .runtime.zenoh_config import ENV_CONFIG, ENV_NS, config_endpoints, tls_file_refusal

NsOpt = Annotated[str, typer.Option("--ns", envvar=ENV_NS, help="Namespace: keys live under jg/{ns}/...")]


def _zenoh_config_path(value: str | None) -> str | None:
    """``--zenoh-config`` checked where it is parsed, for every command that takes it: an empty path had quietly
    meant no file (the router started on its default endpoint). An empty ``JG_ZENOH_CONFIG`` stays unset."""
    if value is not None and not value.strip():
        fail("--zenoh-config: empty path; give a file")
    return value


ZenohConfigOpt = Annotated[
    str | None, typer.Option("--zenoh-config", envvar=ENV_CONFIG, help="Zenoh json5 config file.",
                             callback=_zenoh_config_path)
]
ConnectOpt = Annotated[
    list[str] | None, typer.Option("--connect", help="Zenoh endpoint to connect to (repeatable), e.g. tcp/127.0.0.1:7447.")
]
ListenOpt = Annotated[
    list[str] | None, typer.Option("--listen", help="Zenoh endpoint to listen on (repeatable).")
]
LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")


def _log_level(value: str) -> str:
    """``--log-level`` checked where it is parsed, for every command that takes it (one line, exit 2)."""
    if value.upper() not in LOG_LEVELS:
        fail(f"--log-level: {value!r} is not one of {', '.join(LOG_LEVELS)}")
    return value


LogLevelOpt = Annotated[str, typer.Option("--log-level", help="DEBUG, INFO, WARNING or ERROR.",
                                           callback=_log_level)]
ParamFileOpt = Annotated[str | None, typer.Option(
    "--config", help="Parameter file (flat, or Autoware's ros__parameters form) overriding the service's defaults"
    " in jitterguard/config/<service>.param.yaml; the flags below override it.")]
ProgressOpt = Annotated[
    bool | None, typer.Option("--progress/--no-progress", help="Progress bar on stderr (default: when stderr is a terminal).")
]


SensorHeightOpt = Annotated[
    str | None,
    typer.Option("--sensor-height", help="Height of the scans' frame above the road in metres (1.84 nuScenes'"
                 " LIDAR_TOP, 0 a base_link cloud), or 'auto': measured from each scan's ground returns (the"
                 " default)."),
]


SensorTiltOpt = Annotated[
    str | None,
    typer.Option("--sensor-tilt", help="'auto': the road plane's slope measured in each scan and taken out (a"
                 " sensor pitched or rolled against the road; the default), or 'level': the scans' frame is level."),
]


def sensor_tilt_option(text: str | None) -> str | None:
    """``--sensor-tilt``'s value for a config override (None: not given), or a one-line refusal (exit 2)."""
    if text is None:
        return None
    value = text.strip().lower()
    if value not in ("auto", "level"):
        fail(f"--sensor-tilt: expected 'auto' or 'level', got {text!r}")
    return value


def sensor_height_option(text: str | None) -> float | str | None:
    """``--sensor-height``'s value for a config override (None: not given), or a one-line refusal (exit 2)."""
    if text is None:
        return None
    from .services.detector.config import parse_sensor_height

    try:
        return parse_sensor_height(text)
    except ValueError as exc:
        fail(f"--sensor-height: {exc}")


def progress_on(flag: bool | None) -> bool:
    """Whether to draw a progress bar: as asked, else only on a terminal (a redirected log gets no carriage
    returns)."""
    return sys.stderr.isatty() if flag is None else flag


def fail(message: str) -> NoReturn:
    """Print a one-line error to stderr and exit with status 2 (bad input). A message that holds line breaks — a
    library's own, such as a YAML parser's caret display of where a bag's ``metadata.yaml`` breaks — is joined into
    that one line."""
    print(f"jitterguard: error: {' '.join(message.split())}", file=sys.stderr)
    raise SystemExit(2)


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
"""The first eight bytes of every PNG: what a command writing pictures replaces without asking."""


def refuse_foreign_file(flag: str, out: str | os.PathLike[str], is_ours: Callable[[bytes], bool], what: str) -> None:
    """One line and exit 2 when ``out`` is a file that holds something else than this command's kind of output
    (``is_ours`` judges its first 4 KB): re-running a command replaces its earlier output, but a typo'd ``--out``
    must not overwrite a user's notes or config (``sim generate --out notes.txt`` had). An empty file, a device
    (``/dev/stdout``) or a file that cannot be read is not judged."""
    path = Path(out)
    try:
        if not path.is_file() or path.stat().st_size == 0:
            return
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return  # what cannot be read is not ours to judge: writing it says what is wrong
    if not is_ours(head):
        fail(f"{flag}: {out} exists and is not {what}; give a new name or remove it first")


def is_png(head: bytes) -> bool:
    return head.startswith(PNG_SIGNATURE)


def refuse_given(ctx: typer.Context, params: Iterable[str], why: str) -> None:
    """One line and exit 2 if any of ``params`` (the command's parameter names) was given on the command line or
    through its environment variable, not left at its default: a flag the chosen mode does not read (``train
    --nuscenes … --train-seeds 5``) had been ignored without a word. ``why`` ends the line ("… does not apply WHY")."""
    flags = {p.name: (p.opts[0] if p.opts else p.name) for p in ctx.command.params}
    # by name: typer carries its own copy of click, whose ParameterSource is not click's
    given = [flags.get(name, name) for name in params
             if getattr(ctx.get_parameter_source(name), "name", None) in ("COMMANDLINE", "ENVIRONMENT")]
    if given:
        fail(f"{', '.join(given)} {'does' if len(given) == 1 else 'do'} not apply {why}")


def parse_float(flag: str, text: str, lo: float, hi: float) -> float:
    """``text`` as a finite number in [lo, hi], or a one-line error naming ``flag`` (exit 2): the check of
    :func:`float_option`, for a value read from text of the command's own (a list, a range)."""
    return _finite_float(flag, lo, hi)(text)


def float_option(flag: str, *, min: float | None = None, max: float | None = None, **option: Any) -> Any:
    """``typer.Option(flag, min=..., max=..., **option)`` for a float flag in [min, max] (either end open), whose
    value jitterguard checks: one line naming ``flag``, exit 2, for a value that is no number, NaN, infinite or out
    of range. Typer's own check had called NaN out of the other bound (``--rate nan``: "less than or equal to
    1000") and let infinity through a flag without a maximum (``export-onnx --tolerance inf``: every difference
    accepted). The bounds still show in ``--help``; a default is not checked."""
    return typer.Option(flag, min=min, max=max, parser=_finite_float(flag, min, max), **option)


def _finite_float(flag: str, lo: float | None, hi: float | None) -> Callable[[Any], float]:
    """The parser of :func:`float_option`: the flag's text as a finite float in [lo, hi], or :func:`fail`."""

    def parse(text: Any) -> float:
        try:
            value = float(text)
        except (TypeError, ValueError):
            fail(f"{flag}: {text!r} is not a number")
        if math.isnan(value):
            fail(f"{flag}: {text!r} is not a number")
        if math.isinf(value):
            fail(f"{flag}: {text!r} is not a finite number")
        if lo is not None and hi is not None and not lo <= value <= hi:
            fail(f"{flag}: {value:g} is outside {lo:g}-{hi:g}")
        if lo is not None and value < lo:
            fail(f"{flag}: {value:g} is below the minimum {lo:g}")
        if hi is not None and value > hi:
            fail(f"{flag}: {value:g} is above the maximum {hi:g}")
        return value

    return parse


def parse_int(flag: str, text: str, lo: int, hi: int) -> int:
    """``text`` as an integer in [lo, hi] (not ``1.5``, which ``int(float(…))`` had quietly made 1), or a one-line
    error naming ``flag`` (exit 2). For options kept as text so that their errors are jitterguard's one line."""
    try:
        value = int(text)
    except ValueError:
        fail(f"{flag}: {text!r} is not an integer")
    if not lo <= value <= hi:
        fail(f"{flag}: {value} is outside {lo}-{hi}")
    return value


def check_seed(flag: str, value: int) -> int:
    """A seed of the synthetic world (numpy's SeedSequence takes no negative one), or one line and exit 2."""
    if value < 0:
        fail(f"{flag}: {value} is negative; seeds are integers >= 0")
    return value


def seed_range(text: str) -> set[int]:
    """``"0-49"``, ``"3,5,9"`` or a mix (``"0-9,100"``) → the seeds; ``ValueError`` for anything else."""
    seeds: set[int] = set()
    for part in (p.strip() for p in text.split(",") if p.strip()):
        lo, sep, hi = part.partition("-")
        if sep:
            a, b = int(lo), int(hi)
            if b < a or b - a > 100_000:
                raise ValueError(text)
            seeds.update(range(a, b + 1))
        else:
            seeds.add(int(part))
    return seeds


def parse_seeds(text: str, flag: str) -> list[int]:
    """:func:`seed_range` as sorted unique ints; exit 2 naming ``flag`` otherwise (numpy's SeedSequence takes no
    negative seed, and an empty list would score nothing)."""
    try:
        seeds = seed_range(text)
    except ValueError:
        fail(f"{flag}: expected seeds like 0-49 or 1,2,3 (non-negative), got {text!r}")
    if not seeds:
        fail(f"{flag}: give at least one seed")
    if min(seeds) < 0:
        fail(f"{flag}: expected seeds like 0-49 or 1,2,3 (non-negative), got {text!r}")
    return sorted(seeds)


def out_dir(flag: str, path: str | os.PathLike[str]) -> Path:
    """``path`` created as a folder (parents too) before any work is done, or one line naming ``flag`` (exit 2):
    a run must not compute for minutes and then fail to write its result. An empty ``path`` is refused: it would
    quietly mean the current folder."""
    if not os.fspath(path).strip():
        fail(f"{flag}: empty path; give a folder")
    p = Path(path)
    created = [q for q in (p, *p.parents) if not q.exists()]
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        fail(f"{flag}: cannot create the folder {p}: {exc.strerror or exc}")
    if created:
        atexit.register(_remove_if_empty, created)
    if not os.access(p, os.W_OK | os.X_OK):
        fail(f"{flag}: cannot write into {p}")
    return p


def _remove_if_empty(created: list[Path]) -> None:
    """At exit, the folders :func:`out_dir` created (deepest first) that are still empty: a run refused after its
    folder was made (a dataroot that is none, a bad scans folder, Ctrl-C before the first result) had left an empty
    ``--out`` behind, looking like a run that wrote nothing. Never a folder that was there before, nor one with
    anything in it (rmdir refuses)."""
    for q in created:
        try:
            q.rmdir()
        except OSError:
            return


def out_file(flag: str, path: str | os.PathLike[str]) -> Path:
    """``path``'s folder created, ``path`` not a folder and a file there writable — tried by opening it, since a
    folder root may "write" into can still refuse a file (``/proc``) — before any work (one line and exit 2
    otherwise). A file the trial created is removed again."""
    if not str(path).strip():  # Path("") is the current folder: ". is a folder" had named nothing given
        fail(f"{flag}: empty path; give a file name")
    p = Path(path)
    if p.is_dir():
        fail(f"{flag}: {p} is a folder; give a file name")
    out_dir(flag, p.parent)
    try_write(flag, p)
    return p


def try_write(flag: str, p: Path) -> None:
    """``p`` opened for appending and closed again (one line naming ``flag`` and exit 2 if that fails); a file the
    trial created is removed. A folder root may "write" into can still refuse a file (``/proc``)."""
    if p.is_dir():
        fail(f"{flag}: {p} is a folder where a file is to be written; remove or rename it")
    existed = p.exists()
    try:
        with open(p, "ab"):
            pass
    except OSError as exc:
        fail(f"{flag}: cannot write {p}: {exc.strerror or exc}")
    if not existed:
        p.unlink(missing_ok=True)


_held_locks: list[Any] = []
"""The open lock files of this process (kept open, so locked, until it exits)."""


def hold_lock(path: Path, busy: str) -> None:
    """An exclusive ``flock`` on ``path`` (made if missing) for the rest of this process's life — the kernel lets go
    of it when the process dies, however — or one line and exit 2: ``busy`` when another process holds it."""
    import fcntl

    try:
        fh = open(path, "a")
    except OSError as exc:
        fail(f"--run-dir: cannot write into {path.parent}: {exc.strerror or exc}")
    try:
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        fh.close()
        fail(busy)
    _held_locks.append(fh)


def out_files(flag: str, folder: Path, names: Iterable[str]) -> None:
    """Each of ``names`` in ``folder`` (an :func:`out_dir`) writable as a file (:func:`try_write`), before any work:
    a folder of that name (``report.md/``) had failed the run with a traceback after it had computed everything."""
    for name in names:
        try_write(flag, folder / name)


def new_dir(flag: str, path: str | os.PathLike[str]) -> Path:
    """``path`` checked as a new folder that can be made there — tried by making it and removing it again, since a
    folder root may "write" into can still refuse one (``/proc``) — before anything starts (one line naming
    ``flag`` and exit 2 otherwise). For writers that make their own folder and refuse one that exists (rosbag2)."""
    p = Path(path)
    if p.exists():
        fail(f"{flag}: {p} exists (a new folder is written)")
    try:
        p.mkdir()
    except OSError as exc:
        fail(f"{flag}: cannot create the folder {p}: {exc.strerror or exc}")
    p.rmdir()
    return p


def check_endpoints(endpoints: list[str], where: str = "") -> None:
    """Each Zenoh endpoint shaped PROTO/HOST:PORT with a port in 0-65535, or one line and exit 2: Zenoh refuses a
    bad one only when the session opens, and a service retries that for ever (it waits for a router). ``where``
    prefixes the message (``"--zenoh-config FILE: "`` for the endpoints a config file names)."""
    for ep in endpoints:
        if "/" not in ep:
            fail(f"{where}endpoint {ep!r} must look like tcp/HOST:PORT")
        proto, _, address = ep.partition("/")
        port = address.split("#", 1)[0].split("?", 1)[0].rpartition(":")[2]
        if proto in ("tcp", "udp", "tls", "quic", "ws") and not (port.isdigit() and int(port) <= 65535):
            fail(f"{where}endpoint {ep!r}: port {port!r} is not a number in 0-65535")


def zenoh_options(ns: str, zenoh_config: str | None, connect: list[str] | None, listen: list[str] | None) -> ZenohOptions:
    """Validate the shared flags into :class:`ZenohOptions`, failing with one line on bad input."""
    try:
        opts = ZenohOptions(ns=ns, config_file=zenoh_config, connect=tuple(connect or ()), listen=tuple(listen or ()))
    except ValueError as exc:
        fail(f"--ns: {exc}")
    if zenoh_config and (why := not_a_file(zenoh_config)):
        fail(f"--zenoh-config: {why}")
    check_endpoints([*opts.connect, *opts.listen])
    try:  # the whole config, now: a bad file, an exposed listener or a missing TLS file is a one-line error
        cfg = build_config(opts)  # before anything starts (the sidecar's open runs inside uvicorn's startup)
    except ValueError as exc:
        fail(str(exc))
    # the file's own endpoints too: a port of 99999 there had been retried for ever, where the flag is refused
    check_endpoints(config_endpoints(cfg), f"--zenoh-config {zenoh_config}: " if zenoh_config else "")
    reason = tls_file_refusal(cfg)
    if reason:
        fail(f"cannot open the Zenoh session: {reason}")
    return opts
