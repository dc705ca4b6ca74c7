"""Talking to a stack's supervisord over its unix socket (XML-RPC), with one line for every state it can be in.

Why not ``supervisorctl``: it is a second Python start-up per call (slow to poll), and when there is no
supervisord, or one that is shutting down, it prints raw XML-RPC tracebacks. Here every such state is a
:class:`StackUnavailable` whose message is one line a user can act on.
"""

from __future__ import annotations

import os
import signal
import socket
import time
import xmlrpc.client
from dataclasses import dataclass
from pathlib import Path
from typing import Any

SOCKET = "supervisor.sock"
PIDFILE = "supervisord.pid"
CONFIG = "supervisord.conf"
MAX_SOCKET_PATH = 100
"""A unix socket path longer than this does not fit ``sockaddr_un`` (108 bytes on Linux, 104 on macOS)."""
SERVER_URL_ENV = "SUPERVISOR_SERVER_URL"
"""supervisord puts its own XML-RPC address into every program's environment under this name: how a program (the
monitor) finds the supervisord that started it, and how it tells that supervisord's programs from other processes."""
RPC_TIMEOUT_S = 15.0
"""How long one XML-RPC call waits for supervisord. It answers in milliseconds even on a loaded machine (its calls
never block: a program's stop goes on in its event loop); one that does not answer within this is frozen
(SIGSTOP, a debugger) or hung, and ``status``, ``down`` and ``up`` had waited on it for ever."""


class StackUnavailable(Exception):
    """No supervisord answers for this run directory; ``state`` says why: ``absent`` (nothing was ever started
    there), ``stopped`` (it ran and has exited), ``stale`` (it died without cleaning up), ``shutting_down``,
    ``starting`` (it runs but does not answer yet), ``frozen`` (it runs but is stopped by a signal or a tracer:
    it will not answer until resumed), ``lost`` (it runs, its run directory was deleted), ``denied`` (its socket
    refuses this user: the ``chown=``/``chmod=`` of supervisord's ``[unix_http_server]``), ``error`` (a fault)."""

    def __init__(self, state: str, message: str) -> None:
        self.state = state
        super().__init__(message)


@dataclass(frozen=True)
class ProcessInfo:
    """What supervisord says about one program."""

    name: str
    state: str  # RUNNING, STARTING, BACKOFF, STOPPING, STOPPED, EXITED, FATAL, UNKNOWN
    pid: int | None
    uptime_s: float | None
    exitstatus: int | None
    description: str
    logfile: str

    @classmethod
    def from_rpc(cls, d: dict[str, Any]) -> "ProcessInfo":
        running = d.get("statename") == "RUNNING" and d.get("pid")
        return cls(name=str(d.get("name")), state=str(d.get("statename")), pid=int(d["pid"]) if d.get("pid") else None,
                   uptime_s=float(d["now"] - d["start"]) if running and d.get("start") else None,
                   exitstatus=d.get("exitstatus"), description=str(d.get("description", "")),
                   # an event listener (the monitor-watch) logs only its stderr: its stdout is supervisord's protocol
                   logfile=str(d.get("stdout_logfile") or d.get("stderr_logfile") or ""))


def pid_alive(pid: int) -> bool:
    """Whether ``pid`` is a running process. A zombie (killed, not yet reaped by its parent — for a daemonised
    supervisord that is init, which may take its time or, in some containers, never come) counts as dead."""
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, OverflowError):  # gone, or a number no kernel hands out
        return False
    except PermissionError:
        pass
    try:  # /proc/PID/stat: "pid (comm) STATE ..."; comm may itself hold spaces and parentheses
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return True  # no /proc (not Linux) or it went away meanwhile: what kill said


def process_stopped(pid: int) -> bool:
    """Whether ``pid`` is stopped by a signal or a tracer (``T`` / ``t`` in ``/proc/PID/stat``)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] in ("T", "t")
    except (OSError, IndexError):
        return False


def read_pid(run_dir: Path) -> int | None:
    try:
        return int((run_dir / PIDFILE).read_text().strip())
    except (OSError, ValueError):
        return None


def socket_of(url: str) -> Path:
    """The socket path of a supervisord XML-RPC address (``unix:///run/jitterguard/supervisor.sock``); a
    ValueError naming what is wrong for any other (an ``http://`` server, which the stack never configures)."""
    if not url.startswith("unix://") or len(url) == len("unix://"):
        raise ValueError(f"{url!r} is not a unix socket address (unix:///path/to/supervisor.sock)")
    return Path(url[len("unix://"):])


class Supervisor:
    """The supervisord of one run directory — or, with ``sock``, the one listening there (a supervisord an operator
    runs on their own config, ``deploy/supervisord.conf``)."""

    def __init__(self, run_dir: Path, label: str | None = None, sock: Path | None = None) -> None:
        self.run_dir = run_dir
        self.label = label or f"in {run_dir}"
        self.sock = sock if sock is not None else run_dir / SOCKET

    def started(self, pid: int) -> bool:
        """Whether ``pid`` is a program this supervisord started: its environment names this supervisord's socket
        (:data:`SERVER_URL_ENV`). A pid recycled by another process since supervisord reported it, or a process of
        another stack, is never taken for one; a process whose environment cannot be read is not either."""
        try:
            env = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
        except OSError:
            return False
        prefix = f"{SERVER_URL_ENV}=".encode()
        url = next((e[len(prefix):].decode(errors="replace") for e in env if e.startswith(prefix)), None)
        try:
            return url is not None and os.path.realpath(socket_of(url)) == os.path.realpath(self.sock)
        except ValueError:
            return False

    def kill(self, pid: int) -> bool:
        """SIGKILL a program of this supervisord (its process group), once :meth:`started` says it is one; whether
        it was signalled. For a program no gentler signal reaches: a stopped process holds SIGTERM until resumed."""
        if not self.started(pid):
            return False
        _signal_program(pid, signal.SIGKILL)
        return True

    def _proxy(self) -> Any:
        # supervisor comes with the `deploy` extra: the rest of the CLI must work without it
        from supervisor.xmlrpc import SupervisorTransport, UnixStreamHTTPConnection

        class _Connection(UnixStreamHTTPConnection):
            """supervisor's own unix-socket connection ignores ``timeout``: a frozen supervisord (it accepts the
            connection in the kernel's backlog, then never reads) left every caller blocked in ``recv``."""

            def connect(self) -> None:
                self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
                self.sock.settimeout(RPC_TIMEOUT_S)
                self.sock.connect(self.socketfile)

        def connection() -> Any:
            conn = _Connection("localhost", timeout=RPC_TIMEOUT_S)
            conn.socketfile = str(self.sock)
            return conn

        transport = SupervisorTransport(None, None, f"unix://{self.sock}")
        transport._get_connection = connection
        return xmlrpc.client.ServerProxy("http://127.0.0.1", transport=transport)

    def _unavailable(self) -> StackUnavailable:
        pid = read_pid(self.run_dir)
        if pid is not None and pid_alive(pid) and _is_supervisord(pid, self.run_dir):
            if process_stopped(pid):
                return StackUnavailable("frozen", f"the stack {self.label} does not answer: its supervisord (pid"
                                        f" {pid}) is stopped (SIGSTOP, a debugger); `kill -CONT {pid}` resumes it")
            return StackUnavailable("starting", f"the stack {self.label} is starting or stopping (supervisord pid"
                                    f" {pid} does not answer yet)")
        if pid is not None:  # dead, or its pid recycled by another program since (a reboot, a SIGKILL)
            return StackUnavailable("stale", f"the stack {self.label} is not running: its supervisord (pid {pid})"
                                    " died without cleaning up; `jitterguard down` stops what it left running")
        if (self.run_dir / CONFIG).is_file():
            return StackUnavailable("stopped", f"the stack {self.label} is not running")
        lost = supervisord_of(self.run_dir)
        if lost is not None:
            return StackUnavailable("lost", f"the stack {self.label} runs (supervisord pid {lost}) but its run"
                                    f" directory {self.run_dir} was deleted; `jitterguard down` stops it")
        return StackUnavailable("absent", f"no stack {self.label} (start one with `jitterguard up`)")

    def call(self, method: str, *args: Any) -> Any:
        """One XML-RPC call (``supervisor.<method>``); raises :class:`StackUnavailable` with one line."""
        if not self.sock.exists():
            raise self._unavailable()
        pid = read_pid(self.run_dir)
        if pid is not None and process_stopped(pid):  # say so now, not after RPC_TIMEOUT_S without an answer
            raise self._unavailable()
        try:
            return getattr(self._proxy().supervisor, method)(*args)
        except xmlrpc.client.Fault as exc:
            if "SHUTDOWN_STATE" in exc.faultString:
                raise StackUnavailable("shutting_down", f"the stack {self.label} is shutting down") from None
            raise StackUnavailable("error", f"supervisord {self.label}: {exc.faultString}") from None
        except PermissionError:  # a live supervisord whose socket is not this user's: not "starting" for ever
            raise StackUnavailable("denied", f"the stack {self.label}: this user (uid {os.geteuid()}) may not use "
                                   f"supervisord's socket {self.sock}; its [unix_http_server] chown=/chmod= must "
                                   "give this user (or its group) access") from None
        except (OSError, socket.error, xmlrpc.client.ProtocolError, ConnectionError):
            raise self._unavailable() from None

    def running(self) -> bool:
        try:
            return self.call("getState").get("statename") == "RUNNING"
        except StackUnavailable:
            return False

    def processes(self) -> list[ProcessInfo]:
        return [ProcessInfo.from_rpc(d) for d in self.call("getAllProcessInfo")]

    def shutdown(self) -> None:
        self.call("shutdown")

    def wait_gone(self, timeout: float) -> bool:
        """Wait until supervisord has exited (its pid file is gone or its process is); True if it did."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            pid = read_pid(self.run_dir)
            if pid is None or not pid_alive(pid):
                return True
            time.sleep(0.1)
        return False


def tail(path: Path | str, lines: int) -> list[str]:
    """The last ``lines`` lines of a text file ([] if it cannot be read)."""
    try:
        with open(path, "rb") as fh:
            fh.seek(0, os.SEEK_END)
            size = fh.tell()
            fh.seek(max(0, size - 64 * 1024 * max(1, lines // 50)))
            data = fh.read()
    except OSError:
        return []
    return data.decode(errors="replace").splitlines()[-lines:]


def _is_supervisord(pid: int, run_dir: Path) -> bool:
    """Whether ``pid`` runs the supervisord of ``run_dir`` (after a reboot or a SIGKILL, supervisord.pid may name a
    recycled pid). One that runs another config than the run dir's own ``supervisord.conf`` (``up`` writes one into
    each run dir and starts supervisord on it by its absolute path) is another stack's: a container restarted, or a
    host rebooted, hands the same pids out in the same order, and the stale run dir's pid had been taken for a stack
    "starting or stopping" — ``up`` refused to start, and ``down`` told the operator to ``kill`` the other stack's
    supervisord. A config given by a relative path, or a run dir without its own file (a hand-run supervisord's,
    ``deploy/supervisord.conf``), cannot be told apart: the pid file is trusted."""
    try:
        args = [os.fsdecode(a) for a in Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")]
    except OSError:
        return True  # cannot tell (no /proc): trust the pid file, as before
    if not any("supervisord" in a for a in args[:3]):
        return False
    own = run_dir / CONFIG
    confs = [b for a, b in zip(args, args[1:]) if a in ("-c", "--configuration")]
    confs += [a.split("=", 1)[1] for a in args if a.startswith("--configuration=")]
    if not confs or not own.is_file() or not os.path.isabs(confs[-1]):
        return True
    try:
        return os.path.samefile(confs[-1], own)
    except OSError:  # its config is gone: not the run dir's, which is there
        return False


def live_supervisords() -> dict[int, list[bytes]]:
    """Every live supervisord process of this host (what ``/proc`` shows), pid → command line; empty where there
    is no ``/proc`` to look in."""
    try:
        entries = [e for e in os.listdir("/proc") if e.isdigit()]
    except OSError:
        return {}
    found = {}
    for entry in entries:
        try:
            args = Path(f"/proc/{entry}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if any(b"supervisord" in a for a in args[:3]) and pid_alive(int(entry)):
            found[int(entry)] = args
    return found


def supervisord_of(run_dir: Path) -> int | None:
    """The pid of a live supervisord started on ``run_dir``'s config, found by its command line — for a run
    directory deleted under a running stack (``$XDG_RUNTIME_DIR`` is removed at logout), whose pid file and
    socket went with it; None if there is none or no ``/proc`` to look in."""
    conf = str(run_dir / CONFIG).encode()
    return next((pid for pid, args in live_supervisords().items() if conf in args), None)


def running_run_dirs() -> list[Path]:
    """The run directories of every stack whose supervisord runs on this host, wherever they are (a stack started
    with ``--run-dir`` is not under :func:`base_dir`)."""
    suffix = ("/" + CONFIG).encode()
    dirs = {Path(os.fsdecode(a[: -len(suffix)])) for args in live_supervisords().values() for a in args
            if a.endswith(suffix)}
    return sorted(dirs)


def orphans(run_dir: Path) -> dict[str, int]:
    """Programs of this run directory still alive after their supervisord died: the last pid supervisord's log
    says it spawned for each program, if that process is alive and is a jitterguard command of this stack (its
    command line holds the run's router endpoint or run directory, so a recycled pid is never taken)."""
    from .summary import SPAWNED

    last: dict[str, int] = {}
    try:
        text = (run_dir / "logs" / "supervisord.log").read_text(errors="replace")
    except OSError:
        return {}
    for m in SPAWNED.finditer(text):
        last[m.group(1)] = int(m.group(2))
    return {name: pid for name, pid in last.items() if _is_program_of(run_dir, pid)}


def _is_program_of(run_dir: Path, pid: int) -> bool:
    """Whether ``pid`` runs a jitterguard command of this stack: its command line holds the run's router endpoint
    or run directory (so a recycled pid is never taken for one)."""
    from .status import load_spec  # status imports this module

    spec = load_spec(run_dir)
    marks = [m for m in ((spec.endpoint if spec else ""), str(run_dir)) if m]
    try:
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return False
    return "jitterguard" in cmdline and any(mark in cmdline for mark in marks)


def _signal_program(pid: int, sig: int) -> None:
    try:  # supervisord makes every program a process-group leader; only then take the group
        if os.getpgid(pid) == pid:
            os.killpg(pid, sig)
        else:
            os.kill(pid, sig)
    except (ProcessLookupError, PermissionError):
        pass


def stop_lost(run_dir: Path, timeout: float) -> int | None:
    """SIGTERM the supervisord of a deleted ``run_dir`` (:func:`supervisord_of`; it stops its programs as on
    ``shutdown``) and wait for it to exit; its pid, or None if it is still running after ``timeout``."""
    pid = supervisord_of(run_dir)
    if pid is None:
        return 0
    try:
        os.kill(pid, signal.SIGTERM)
    except ProcessLookupError:
        return pid
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if not pid_alive(pid):
            return pid
        time.sleep(0.1)
    return None


def stop_orphans(run_dir: Path, timeout: float = 15.0) -> list[str]:
    """SIGTERM each orphan's process group (SIGKILL after ``timeout``); returns the programs stopped."""
    found = orphans(run_dir)
    for pid in found.values():
        _signal_program(pid, signal.SIGTERM)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and any(pid_alive(p) for p in found.values()):
        time.sleep(0.1)
    for pid in found.values():
        if pid_alive(pid):
            _signal_program(pid, signal.SIGKILL)
    (run_dir / PIDFILE).unlink(missing_ok=True)
    return sorted(found)
