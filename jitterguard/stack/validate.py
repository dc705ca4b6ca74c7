"""``jitterguard up``'s arguments, checked before anything is written or started.

Everything a user passes ends up in ``supervisord.conf``, an INI file that supervisord expands with
``%(name)s`` and reads ``;``/``#`` after whitespace as a comment. So a newline in SOURCE would start a new
``[program:...]`` section (run as root, if ``up`` is), a ``%`` is an expansion, and `` ;`` cuts the line. Each
value is therefore checked here (control characters and comment starts refused, with one line naming the
argument) and ``%`` is doubled when the file is rendered (:func:`supervisor_escape`). Paths are made absolute,
because supervisord runs every program from the run directory.
"""

from __future__ import annotations

import errno
import re
import socket
from pathlib import Path

from .control import MAX_SOCKET_PATH, SOCKET

_CONTROL = re.compile(r"[\x00-\x1f\x7f]")
_COMMENT = re.compile(r"\s[;#]")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


class ArgumentError(ValueError):
    """An argument ``up`` refuses; the message is one line naming it."""


def check_text(value: str, what: str) -> str:
    """``value`` if it can go into supervisord.conf as written; else :class:`ArgumentError`."""
    bad = _CONTROL.search(value)
    if bad:
        raise ArgumentError(f"{what}: control character {bad.group()!r} at position {bad.start()} is not allowed")
    if _COMMENT.search(value):
        raise ArgumentError(f"{what}: a space before ';' or '#' is not allowed (supervisord reads the rest of the"
                            " line as a comment); rename the file or use a link")
    return value


def check_name(name: str) -> str:
    """A stack name: letters, digits, ``_``, ``.``, ``-``; it names the run directory."""
    if not _NAME.match(name):
        raise ArgumentError(f"--name: {name!r} is not a stack name (1-64 letters, digits, '_', '.', '-', starting"
                            " with a letter or digit)")
    return name


def supervisor_escape(value: str) -> str:
    """``value`` as supervisord must read it back: ``%`` doubled (it expands ``%(name)s`` in every value)."""
    return value.replace("%", "%%")


def port_in_use(host: str, port: int) -> bool:
    """Whether binding ``host:port`` fails because something already listens there. With SO_REUSEADDR, as the
    router and the sidecar bind: connections of a stack just stopped, left in TIME_WAIT, do not count (without
    it, `up` right after `down` or a finished run was refused)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as exc:
            return exc.errno == errno.EADDRINUSE
    return False


def check_run_dir(run_dir: Path) -> Path:
    """The run directory, absolute; refused if its socket path would not fit a unix socket address."""
    rd = Path(check_text(str(run_dir), "--run-dir")).expanduser().absolute()
    if "%" in str(rd):  # supervisord expands log file names twice: no escaping survives that
        raise ArgumentError(f"--run-dir: {rd}: '%' is not allowed in the run directory (supervisord expands it)")
    if len(str(rd / SOCKET)) > MAX_SOCKET_PATH:
        raise ArgumentError(f"--run-dir: {rd} is too long for supervisord's unix socket (at most"
                            f" {MAX_SOCKET_PATH - len(SOCKET) - 1} characters)")
    return rd
