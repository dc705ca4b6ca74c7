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
import ipaddress
import os
import re
import socket
import stat
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


def check_name(name: str, flag: str = "--name") -> str:
    """A stack name: letters, digits, ``_``, ``.``, ``-``; it names the run directory. ``flag``: the option it came
    from (``--ns`` names the stack when ``--name`` is not given: a bad one had been blamed on ``--name``)."""
    if not _NAME.match(name):
        raise ArgumentError(f"{flag}: {name!r} is not a stack name (1-64 letters, digits, '_', '.', '-', starting"
                            " with a letter or digit)")
    return name


def supervisor_escape(value: str) -> str:
    """``value`` as supervisord must read it back: ``%`` doubled (it expands ``%(name)s`` in every value)."""
    return value.replace("%", "%%")


def bind_error(host: str, port: int) -> OSError | None:
    """Why binding ``host:port`` fails (None if it does not). With SO_REUSEADDR, as the router and the sidecar
    bind: connections of a stack just stopped, left in TIME_WAIT, do not count (without it, `up` right after
    `down` or a finished run was refused)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    try:
        with socket.socket(family, socket.SOCK_STREAM) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind((host, port))
    except OSError as exc:  # a name that does not resolve too (socket.gaierror)
        return exc
    return None


def _bind_address(host: str) -> ipaddress.IPv4Address | ipaddress.IPv6Address | None:
    """The address a bind on ``host`` takes, as the router and the sidecar bind it (IPv6 when the host holds a
    ``:``, else IPv4; a name resolved in that family; no host: the IPv4 wildcard); an IPv4-mapped IPv6 address
    as its IPv4 one. None for a name that does not resolve."""
    if not host:
        return ipaddress.IPv4Address("0.0.0.0")
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    try:
        addr = ipaddress.ip_address(host.split("%")[0])
    except ValueError:
        try:
            addr = ipaddress.ip_address(socket.getaddrinfo(host, None, family, socket.SOCK_STREAM)[0][4][0]
                                        .split("%")[0])
        except (OSError, IndexError, ValueError):
            return None
    if isinstance(addr, ipaddress.IPv6Address) and addr.ipv4_mapped is not None:
        return addr.ipv4_mapped
    return addr


def binds_overlap(a: str, b: str) -> bool:
    """Whether binds on hosts ``a`` and ``b`` on one port clash, as the kernel judges it: the same address, or
    either one a wildcard that covers the other — ``0.0.0.0`` every IPv4 address, ``::`` every address of either
    family (a dual-stack socket, Linux's default) — but not two different specific addresses (127.0.0.1 and
    127.0.0.2, or 127.0.0.1 and ::1). A host that cannot be resolved clashes with everything (it cannot be told
    apart; ``up`` refuses it anyway, :func:`bind_problem`)."""
    x, y = _bind_address(a), _bind_address(b)
    if x is None or y is None or x == y:
        return True
    if any(isinstance(z, ipaddress.IPv6Address) and z.is_unspecified for z in (x, y)):
        return True  # :: takes the port on every address, IPv4 too
    if x.version != y.version:
        return False
    return x.is_unspecified or y.is_unspecified


def port_in_use(host: str, port: int) -> bool:
    """Whether binding ``host:port`` fails because something already listens there."""
    exc = bind_error(host, port)
    return exc is not None and exc.errno == errno.EADDRINUSE


def bind_problem(host: str, port: int, port_flag: str, host_flag: str = "--host") -> str | None:
    """One line naming the flag to change when ``host:port`` cannot be bound for another reason than a listener
    there (see :func:`port_in_use`): an address that is not this host's or a name that does not resolve (the
    host's flag), a port this user may not bind (the port's flag); else None. ``up`` had started the whole stack
    on a sidecar ``--host`` that is not this host's address, and stopped it on the sidecar's crash loop."""
    exc = bind_error(host, port)
    if exc is None or exc.errno == errno.EADDRINUSE:
        return None
    host_side = isinstance(exc, socket.gaierror) or exc.errno == errno.EADDRNOTAVAIL
    return (f"{host_flag if host_side else port_flag}: cannot bind {host}:{port}: {exc.strerror or exc}"
            + (" (not an address of this host)" if exc.errno == errno.EADDRNOTAVAIL else ""))


def check_run_dir(run_dir: Path) -> Path:
    """The run directory, absolute; refused if its socket path would not fit a unix socket address."""
    rd = Path(check_text(str(run_dir), "--run-dir")).expanduser().absolute()
    if "%" in str(rd):  # supervisord expands log file names twice: no escaping survives that
        raise ArgumentError(f"--run-dir: {rd}: '%' is not allowed in the run directory (supervisord expands it)")
    if len(str(rd / SOCKET)) > MAX_SOCKET_PATH:
        raise ArgumentError(f"--run-dir: {rd} is too long for supervisord's unix socket (at most"
                            f" {MAX_SOCKET_PATH - len(SOCKET) - 1} characters)")
    return rd


RUN_DIR_MODE = 0o700
"""The mode ``up`` creates a run directory and its ``logs`` folder with: only the stack's user may write there."""


def check_private_dir(path: Path, what: str = "--run-dir") -> None:
    """:class:`ArgumentError` when the folder ``path`` (if it exists) is not this user's alone to write: another
    user who owns it, or may write in it, could replace ``supervisord.conf`` between its write and supervisord's
    read, or put a link where a log goes, so that supervisord — root, if ``up`` is — appends to any file
    (sshd's StrictModes rule). A link to such a folder counts as that folder."""
    try:
        st = path.stat()
    except FileNotFoundError:
        return
    except OSError as exc:
        raise ArgumentError(f"{what}: cannot read {path}: {exc.strerror or exc}") from None
    if not stat.S_ISDIR(st.st_mode):
        raise ArgumentError(f"{what}: {path} is not a folder")
    uid = os.geteuid()
    if st.st_uid != uid:
        raise ArgumentError(f"{what}: {path} belongs to uid {st.st_uid}, not to you (uid {uid}): another user could"
                            " change the stack's files there; give a folder of your own")
    # a folder writable by its group counts as another user's unless that group is the user's own primary one (the
    # user-private group of a umask 002: Ubuntu's default, where every folder the user made is 0775)
    if st.st_mode & stat.S_IWOTH or (st.st_mode & stat.S_IWGRP and st.st_gid != os.getegid()):
        raise ArgumentError(f"{what}: {path} is writable by other users (mode {stat.S_IMODE(st.st_mode):04o}): they"
                            f" could change the stack's files there; `chmod go-w {path}` or give another folder")
