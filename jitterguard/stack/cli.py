"""``jitterguard up / down / status / summary / logs``: the stack under supervisord, from one command.

``up`` checks everything before it writes or starts anything: its arguments (:mod:`.validate`), the source
(opened with its reader, exit 2 with the reader's one-line error), the run directory (one stack per name) and
the ports (one stack per router and sidecar port). In the foreground it then watches the stack: the first
classified objects, a program that keeps crashing (the stack is stopped and that program's last log lines
shown), and at the end it prints the run's summary (:mod:`.summary`).

Exit codes: 0 done; 1 the stack failed (a crash loop, no objects, a stop that did not finish); 2 bad input or a
refused start; ``status`` 3 when the stack or any of its services is not up (see :func:`status_cmd`).

Commands import their implementation when they run (start-up time: see :mod:`jitterguard.cli`).
"""

from __future__ import annotations

import io
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Annotated, Any, NoReturn

import typer

from ..cli_common import NsOpt, check_seed, fail, float_option, hold_lock, new_dir, out_file
from ..runtime import ZenohOptions, build_config, free_tcp_port, open_session
from ..runtime.service import EXIT_BAD_INPUT
from ..runtime.signals import stop_on_signals
from ..schemas import keys
from ..services.classifier.config_writes import api_token_from_env
from ..services.replay import cli as R  # the replay's own option declarations, shared with `up`
from ..services.replay.options import absolute_source
from ..services.replay.sources import SourceError, SourceOptions, probe_source
from ..services.sidecar.core import bind_refusal
from . import summary
from .control import (StackUnavailable, Supervisor, orphans, read_pid, running_run_dirs, stop_lost, stop_orphans,
                      tail)
from .status import collect, load_spec, render_table, save_spec
from .supervisor import DEFAULT_SCENARIO_S, DEFAULT_SOURCE, StackSpec, has_area, input_mode, programs, render_config
from .validate import (RUN_DIR_MODE, ArgumentError, bind_problem, binds_overlap, check_name, check_private_dir,
                       check_run_dir, check_text, port_in_use)
from .watch import WATCH_FILE

RunDirOpt = Annotated[str | None, typer.Option("--run-dir", envvar="JG_RUN_DIR", help="Where config, socket, logs and summary live (default: a folder named after the stack).")]
NameOpt = Annotated[str | None, typer.Option("--name", envvar="JG_STACK", help="The stack's name (default: its --ns); each named stack has its own run directory.")]

FIRST_OBJECTS_WARN_S = 60.0
DETACH_WAIT_S = 60.0
"""How long ``up -d`` waits for the stack to start (:func:`_settled`) before it gives up, leaving it running."""
DETACH_SETTLE_S = 5.0
"""How long, after the stack made progress (the first classified objects; every service heard), every program
must have run without a crash before ``up -d`` calls the stack started; a program that crashed meanwhile must
also outlive its longest earlier life by this much."""
STOP_WAIT_S = 90.0
CRASH_TAIL_LINES = 12


def base_dir() -> Path:
    """Where run directories live: ``$XDG_RUNTIME_DIR/jitterguard`` or ``~/.cache/jitterguard``."""
    base = os.environ.get("XDG_RUNTIME_DIR") or str(Path.home() / ".cache")
    return Path(base) / "jitterguard"


def default_run_dir(name: str) -> Path:
    return base_dir() / name


def resolve(run_dir: str | None, name: str | None, ns: str) -> tuple[Path, str]:
    """(run directory, label for messages) from ``--run-dir`` / ``--name`` / ``--ns``; bad ones exit 2."""
    try:
        stack = check_name(name) if name is not None else check_name(ns, "--ns")
        if run_dir is not None and not run_dir.strip():  # had quietly meant the default stack (`down --run-dir ""`)
            raise ArgumentError("--run-dir: empty path; give a folder")
        rd = check_run_dir(Path(run_dir)) if run_dir is not None else default_run_dir(stack)
    except ArgumentError as exc:
        fail(str(exc))
    return rd, (f"{stack!r}" if not run_dir else f"in {rd}")


def _binds_of(spec: StackSpec) -> set[tuple[str, int]]:
    """The (host, port) binds a stack listens on: its router's (loopback), and its sidecar's (its ``--host``) and
    Foxglove server's (loopback) where it runs them (stack.json keeps the defaults of those it leaves out)."""
    return {("127.0.0.1", spec.router_port)} | ({(spec.sidecar_host, spec.sidecar_port)} if spec.sidecar else set()) | (
        {("127.0.0.1", spec.foxglove_port)} if spec.foxglove else set())


def _port_owner(host: str, port: int, run_dir: Path) -> tuple[str, str] | None:
    """(who, how to stop it) of another running stack that binds ``port`` on an address a bind on ``host`` clashes
    with (:func:`.validate.binds_overlap`) — under :func:`base_dir` or in a run directory of its own
    (``--run-dir``) — if any, whether or not its program listens yet: a stack's router binds its port seconds after
    supervisord starts it (14 s on a loaded machine), and a second ``up`` on that port in between had found it free
    and started a stack whose services ran through the first stack's router while its own waited for the port. The
    port alone had been compared: a sidecar on 127.0.0.1:8000 was refused beside another stack's on 127.0.0.2:8000,
    which the kernel lets both bind."""
    try:
        named = [p for p in base_dir().iterdir() if p.is_dir()]
    except OSError:
        named = []
    live = running_run_dirs()  # every supervisord running on this host, by its command line
    alive = {p.resolve() for p in live}
    seen = {run_dir.resolve()}  # this stack's own, and each other one once
    for other in named + live:
        if other.resolve() in seen:
            continue
        seen.add(other.resolve())
        spec = load_spec(other)
        if spec and any(p == port and binds_overlap(h, host) for h, p in _binds_of(spec)) and (
                other.resolve() in alive or Supervisor(other).running()):
            if other.parent.resolve() == base_dir().resolve():
                return f"the stack {spec.name!r}", f"jitterguard down --name {spec.name}"
            return f"the stack in {other}", f"jitterguard down --run-dir {other}"
    return None


class _ObjectsWatch:
    """Notes when the first classified ``objects`` arrives (seconds since ``t0``), and which process of each
    service was heard on its heartbeat (service → pids), from a Zenoh session opened in the background: the router
    is only now being started, and a client-mode open fails until it listens."""

    def __init__(self, ns: str, endpoint: str, t0: float) -> None:
        self.ns, self.endpoint, self.t0 = ns, endpoint, t0
        self.first: float | None = None
        self.heard: dict[str, set[int]] = {}
        self._stop = threading.Event()
        self._session: Any = None
        self._thread = threading.Thread(target=self._open, name="objects-watch", daemon=True)
        self._thread.start()

    def _open(self) -> None:
        cfg = build_config(ZenohOptions(ns=self.ns, connect=(self.endpoint,)))
        try:
            session = open_session(cfg, stop=self._stop)  # retried until the router listens
        except Exception:  # stopped before the router came up
            return
        session.declare_subscriber(keys.objects(self.ns), self._on)
        session.declare_subscriber(keys.heartbeat_all(self.ns), self._on_beat)
        self._session = session

    def _on(self, _sample: Any) -> None:
        if self.first is None:
            self.first = time.monotonic() - self.t0

    def _on_beat(self, sample: Any) -> None:
        from ..schemas import DecodeError, decode
        from ..schemas.models import Heartbeat
        from ..schemas.wire import HEARTBEAT_BOUNDS

        try:
            hb = decode(Heartbeat, sample.payload.to_bytes(), **HEARTBEAT_BOUNDS)
        except DecodeError:
            return
        pids = self.heard.setdefault(keys.last_chunk(str(sample.key_expr)), set())
        if len(pids) < 64:  # bounded: anyone on the host may publish
            pids.add(hb.pid)

    def heard_from(self, name: str, pid: int | None) -> bool:
        """Whether the program ``name``'s current process (``pid``) has sent a heartbeat: it got through its
        imports, opened its session and runs its loop (the router and the monitor-watch send none: always True)."""
        from .status import OFF_BUS, SERVICE_NAMES

        if name == "router" or name in OFF_BUS:
            return True
        return pid is not None and any(pid in self.heard.get(n, ()) for n in SERVICE_NAMES.get(name, (name,)))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        if self._session is not None:
            try:
                self._session.close()
            except Exception:
                pass


def _quiet_once_stdout_closes() -> None:
    """Keep a foreground ``up`` running its course once its standard output is gone (``up ... | head -1``): a
    print into the closed pipe had raised ``BrokenPipeError`` out of the watch loop, and ``up`` exited 1 leaving
    the whole stack running, ``--duration`` and all. From then on what it prints goes nowhere (standard error is
    kept); it still stops the stack at Ctrl-C, ``--duration`` or a crash loop, and exits with its own status."""
    class _Stdout(io.TextIOWrapper):
        def write(self, text: str) -> int:
            try:
                return super().write(text)
            except BrokenPipeError:
                self._gone()
                return len(text)

        def flush(self) -> None:
            try:
                super().flush()
            except BrokenPipeError:
                self._gone()

        def _gone(self) -> None:  # the descriptor onto /dev/null: what is still buffered, and exit, find no pipe
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, self.fileno())
            os.close(null)

    out = sys.stdout
    if isinstance(out, io.TextIOWrapper) and not isinstance(out, _Stdout):
        sys.stdout = _Stdout(out.detach(), encoding=out.encoding, errors=out.errors, line_buffering=out.line_buffering)


FOREGROUND_STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
"""What stops a foreground stack. SIGHUP too: an SSH session that drops hangs up the terminal, whose SIGHUP had
ended ``up`` at once (Python's default) and reached supervisord, in the same process group, as its "reload"
request: every program restarted and the stack ran on, unwatched, past ``--duration``."""


def _end_with_parent() -> Any:
    """A ``preexec_fn`` that has the kernel send the child SIGTERM when ``up`` dies (Linux's
    ``PR_SET_PDEATHSIG``), or None where that cannot be set. supervisord runs in a session of its own (the
    terminal's Ctrl-C and hangup reach ``up`` alone, which stops it), so a ``kill -9`` of a foreground ``up`` had
    left the stack running for good: now supervisord stops its programs as on ``down``."""
    if not sys.platform.startswith("linux"):
        return None
    import ctypes

    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None
    pr_set_pdeathsig = 1

    def preexec() -> None:
        prctl(pr_set_pdeathsig, int(signal.SIGTERM), 0, 0, 0)

    return preexec


def _stop_supervisord(proc: subprocess.Popen) -> bool:
    """SIGTERM a foreground stack's supervisord (which stops its programs) and wait; kill it after
    ``STOP_WAIT_S``. True if it had to be killed."""
    if proc.poll() is not None:
        return False
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=STOP_WAIT_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        return True
    return False


def _exit_without_finalizing(code: int) -> NoReturn:
    """End a foreground ``up`` once its stack is stopped and its summary printed, skipping interpreter
    finalization: Zenoh's native threads may still call into Python there (dropping the watch's callback), and a
    native thread that meets a finalizing interpreter is ended by ``pthread_exit``, whose unwind through Rust
    aborts the process (SIGABRT, "FATAL: exception not rethrown": pyo3 on Python before 3.14). Seen once in CI,
    after the crash-loop report was out: the exit status 1 became −6."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


DEFERRED_START_S = 10.0
"""A foreground ``up`` starts the deferred programs at the first objects, or after this long without them (the
sidecar is how an operator looks at a stack that does not come up)."""


def _start_deferred(sup: Supervisor, progs: list[Any]) -> None:
    for p in progs:
        if p.deferred:
            try:
                sup.call("startProcess", p.name, False)
            except StackUnavailable:
                pass


SIDECAR_LISTEN_WAIT_S = 30.0
"""How long a foreground ``up`` holds back the sidecar's address after the first objects while the sidecar does
not accept connections yet (it then prints it anyway, saying so)."""


def _sidecar_address(spec: StackSpec, progs: list[Any]) -> tuple[str, int] | None:
    """Where to connect to the stack's sidecar (a wildcard bind is reached on loopback), if it has one."""
    if not any(p.name == "sidecar" for p in progs):
        return None
    host = {"0.0.0.0": "127.0.0.1", "::": "::1", "": "127.0.0.1"}.get(spec.sidecar_host, spec.sidecar_host)
    return host, spec.sidecar_port


def _answers(address: tuple[str, int] | None) -> bool:
    """Whether the sidecar accepts connections (True when there is none). uvicorn listens only once the app's
    startup is done, so a connection accepted means requests are served. The sidecar starts deferred, seconds
    after the rest, and takes seconds more to import and open its session: its address printed before it listens
    had been answered "connection refused"."""
    if address is None:
        return True
    try:
        with socket.create_connection(address, timeout=0.5):
            return True
    except OSError:
        return False


def _addresses(spec: StackSpec, progs: list[Any], picked: bool = False) -> list[str]:
    """Where to look at the stack: the sidecar's page, the Foxglove WebSocket (one line each); the router's
    endpoint too when ``up`` picked its port (``--router-port 0``), since nothing else would say it."""
    names = {p.name for p in progs}
    out = [f"router: {spec.endpoint}"] if picked else []
    if "sidecar" in names:
        out.append(f"sidecar: http://{spec.sidecar_host}:{spec.sidecar_port}/")
    if spec.foxglove:
        out.append(f"foxglove: ws://127.0.0.1:{spec.foxglove_port}  (layout: deploy/foxglove/jitterguard.json)")
    return out


def _crash_report(rd: Path, name: str, events: dict[str, summary.ProgramEvents]) -> str:
    ev = events.get(name, summary.ProgramEvents())
    why = "supervisord gave up on it" if ev.fatal else f"{len(ev.crashes)} unexpected exits"
    last = ev.crashes[-1][1] if ev.crashes else "no exit status"
    lines = [f"jitterguard: error: {name} keeps failing ({why}; last: {last}); the stack is stopped.",
             f"last lines of {rd / 'logs' / (name + '.log')}:"]
    lines += [f"  {ln}" for ln in tail(rd / "logs" / f"{name}.log", CRASH_TAIL_LINES)] or ["  (empty)"]
    return "\n".join(lines)


def _bad_input_report(rd: Path, name: str) -> str:
    """What ``up`` says of a program that stopped on bad input (``--on-error stop``): deliberately, not restarted
    (its ``exitcodes``), with the tail of its log, which names the frame. It had been restarted on exit status 1,
    met the same frame again, and been reported as a program that "keeps failing"."""
    log = rd / "logs" / f"{name}.log"
    lines = [f"jitterguard: error: {name} stopped on bad input (--on-error stop, exit status {EXIT_BAD_INPUT}) and"
             " is not restarted; the stack is stopped.", f"last lines of {log}:"]
    lines += [f"  {ln}" for ln in tail(log, CRASH_TAIL_LINES)] or ["  (empty)"]
    return "\n".join(lines)


def _not_progressing(procs: list[Any], watch: _ObjectsWatch, *, objects: bool) -> str:
    """Why the stack has not made progress yet, in words ("" once it has): a program not RUNNING, a service whose
    current process was not heard on its heartbeat, or (``objects``: a stack fed by its own replay) no classified
    objects yet. Every program RUNNING is supervisord's view (a process that lived ``startsecs``), not the
    program's: one that died after its imports, or at its first frame, seconds later, had been called started."""
    down = [f"{p.name} {p.state}" for p in procs if p.state != "RUNNING"]
    if down:
        return ", ".join(sorted(down))
    unheard = sorted(p.name for p in procs if not watch.heard_from(p.name, p.pid))
    if unheard:
        return f"no heartbeat yet from {', '.join(unheard)}"
    if objects and watch.first is None:
        return "no classified objects yet"
    return ""


def _settled(events: dict[str, summary.ProgramEvents], progress_since: float, now: float) -> str:
    """Why the stack, which has made progress since ``progress_since`` (epoch s), is not yet called started ("" when
    it is): it must then run :data:`DETACH_SETTLE_S` without an unexpected exit, and a program that exited
    unexpectedly while ``up -d`` waited must also have run its longest earlier life here plus that much (one that
    dies 4 s after each start had been called started in the 3 s after each restart)."""
    last_crash = max((t for ev in events.values() for t, _ in ev.crashes), default=0.0)
    if now - max(progress_since, last_crash) < DETACH_SETTLE_S:
        return "settling"
    for name, ev in sorted(events.items()):
        lives = [t - max((s for s in ev.spawns if s <= t), default=t) for t, _ in ev.crashes]
        if lives and ev.spawns and now - ev.spawns[-1] < max(lives) + DETACH_SETTLE_S:
            return f"{name} crashed after {max(lives):.0f} s and was restarted: waiting for it to outlive that"
    return ""


def _print_summary(rd: Path, *, as_json: bool = False) -> bool:
    data = summary.load(rd)
    if data is None:
        return False
    if as_json:
        print(json.dumps({k: v for k, v in data.items() if k != "ledger"}, indent=2, sort_keys=True))
    else:
        print(summary.render(data), flush=True)
    return True


def _why_no_summary(rd: Path) -> str:
    """Why ``rd`` gives no summary, told apart: a corrupt or foreign summary.json, or a ``--run-dir`` that is a
    file, had been reported as "its monitor never wrote one" and "does not exist", sending the reader to the
    monitor's log for a file that was there all along."""
    path = rd / summary.SUMMARY_FILE
    if rd.exists() and not rd.is_dir():
        return f"{rd} is a file, not a run directory"
    if not rd.exists():
        return f"{rd} does not exist"
    if path.exists():
        return f"{path} is not a run summary (not a JSON object: cut short, or written by something else)"
    return f"no {summary.SUMMARY_FILE} in {rd}: its monitor never wrote one; `jitterguard logs monitor`"


STALE_SUMMARY_S = 10.0
"""A running stack's summary.json older than this is not being kept (the monitor writes it every second)."""


def _warn_if_stale(rd: Path, sup: Supervisor) -> None:
    """Say on stderr when a running stack's summary.json has not been rewritten for :data:`STALE_SUMMARY_S`: its
    monitor is stopped, frozen or cannot write, and the counts printed are those of then. `summary` had printed
    a frozen monitor's totals of minutes ago as the run so far, with nothing to tell them apart."""
    try:
        age = time.time() - (rd / summary.SUMMARY_FILE).stat().st_mtime
    except OSError:
        return
    if age > STALE_SUMMARY_S and sup.running():
        print(f"jitterguard: warning: {rd / summary.SUMMARY_FILE} was last written {age:.0f} s ago while the stack "
              "runs: its monitor is not keeping it (`jitterguard status`, `jitterguard logs monitor`); these are the"
              " counts of then", file=sys.stderr)


def _refuse_if_running(sup: Supervisor, rd: Path, label: str, down_hint: str) -> None:
    """Exit 2 unless no stack runs in ``rd``: one that answers, one whose supervisord runs but does not answer
    (starting, shutting down, frozen: a second supervisord would then fight it over the socket and the run
    directory), or one that died leaving its programs running."""
    try:
        sup.call("getState")
    except StackUnavailable as exc:
        if exc.state in ("starting", "shutting_down", "frozen", "lost", "denied", "error"):
            fail(f"{exc}; not starting another stack over it")
        left = orphans(rd)
        if left:
            fail(f"the stack {label} died but its programs still run ({', '.join(sorted(left))}); {down_hint}"
                 " stops them")
        return
    fail(f"the stack {label} is already running (run dir {rd}); {down_hint} stops it")


UP_LOCK = "up.lock"
def _lock_run_dir(rd: Path, label: str) -> None:
    """Take the run directory's ``up`` lock for the rest of this process's life, or exit 2 if another ``up`` holds
    it. Two ``up`` started together on one run directory both found it free, both wrote supervisord.conf and
    stack.json, and one's supervisord ran the other's file: the first said "supervisord did not start" about the
    stack that ran, the second waited 30 s for a sidecar on a port nobody listened on."""
    hold_lock(rd / UP_LOCK, f"another `jitterguard up` is starting the stack {label} right now (run dir {rd})")


LOW_SPACE_BYTES = 64 * 2**20
"""Below this much free space in the run directory ``up`` warns: each program's log may grow to 40 MB (10 MB and 3
backups), and summary.json and the classifier's stores are rewritten while it runs."""


def _warn_low_space(rd: Path) -> None:
    import shutil

    try:
        free = shutil.disk_usage(rd).free
    except OSError:
        return
    if free < LOW_SPACE_BYTES:
        print(f"jitterguard: warning: only {free / 2**20:.1f} MiB free in {rd}: logs, summary.json and the"
              " classifier's stored config and calibration may not be written", file=sys.stderr)


def _pick_ports(wanted: list[tuple[int, str, bool]]) -> list[int]:
    """Each (port, host, used) as given, or for a used port 0 one free on its host now, none the same as another
    one here. ``up`` writes the picked port into supervisord.conf and stack.json, so a restarted program keeps it
    (a program given port 0 itself would bind a new one at each restart, and nothing could tell where), and
    ``status``, ``down``, a second ``up`` and the printed addresses know it. A host that cannot be bound is one
    line and exit 2."""
    taken = {p for p, _, _ in wanted if p > 0}
    out = []
    for port, host, used in wanted:
        if port == 0 and used:
            for _ in range(100):
                try:
                    port = free_tcp_port(host or "0.0.0.0")
                except OSError as exc:
                    fail(f"--host {host}: cannot bind a port there: {exc.strerror or exc}")
                if port not in taken:
                    break
            taken.add(port)
        out.append(port)
    return out


def _own_clash(wanted: list[tuple[int, str, str]]) -> str | None:
    """One line when two of this stack's own (port, host, flag) binds clash (:func:`.validate.binds_overlap`): the
    same port on overlapping addresses. The port alone had been compared, refusing a sidecar on 127.0.0.2 beside
    the router on 127.0.0.1 at one port number."""
    for i, (p, h, flag) in enumerate(wanted):
        for q, g, other in wanted[:i]:
            if p == q and binds_overlap(h, g):
                return f"{flag} {p} is also the {other}; give each its own port"
    return None


SCENARIO_DURATION = "--scenario-duration"
"""``up``'s name for the replay's ``--duration`` (its own ``--duration`` stops a foreground stack)."""


def _check_source(source: str | None, input_level: str, ropts: "R.ReplayOptions"
                  ) -> tuple[str | None, str, "R.ReplayOptions", list[str]]:
    """Resolve and probe SOURCE: (absolute source, input mode, replay options, warnings); bad ones exit 2.

    ``--input auto`` takes a source's own level where it has one (a bag of DetectedObjects), else points with
    the detector (detections without it)."""
    if input_level == "tracks":
        if source is not None or ropts.argv():
            fail("--input tracks feeds the built-in track scenario: SOURCE and replay options do not apply")
        return None, "tracks", ropts, []
    src = absolute_source(source) if source is not None else None
    ropts = ropts.absolute()
    try:
        src_opts = ropts.check()
        # the source's kind first, its seed left out: a nuScenes scene takes --seed only at the level the stack
        # replays it at (detections, for --input detections), judged by the probe below
        kind_opts = replace(src_opts, seed=SourceOptions().seed)
        info = probe_source(src or DEFAULT_SOURCE, kind_opts, start=ropts.start, duration_flag=SCENARIO_DURATION)
        if info.kind == "detections":  # a bag of DetectedObjects: its own level
            if input_level == "points":
                fail(f"{source}: holds detections ({info.name}); --input points needs scans")
            mode = "detections"
        else:
            mode = input_mode(StackSpec(input=input_level))
        if mode == "detections" and info.kind == "points":
            ropts = replace(ropts, level="detections")
        if ropts.level != src_opts.level or kind_opts != src_opts:
            info = probe_source(src or DEFAULT_SOURCE, ropts.check(), start=ropts.start,
                                duration_flag=SCENARIO_DURATION)
    except (ValueError, SourceError) as exc:
        fail(" ".join(str(exc).split()))
    return src, mode, ropts, list(info.warnings)


def _check_environment() -> None:
    """The variables every program of the stack reads at start, read by the programs' own parsers now (one line,
    exit 2): ``JG_WATCHDOG_S``, ``JG_CRASH_LOOP_*`` and a ``JG_ZENOH_CONFIG`` file. A malformed one had let ``up -d``
    say "started" — the monitor fails only after its imports, seconds after supervisord calls it RUNNING — while
    the monitor, or every service, then crash-looped on it."""
    from ..runtime import ENV_CONFIG
    from ..runtime.envvars import watchdog_period
    from .backoff import CrashLoopPolicy

    try:
        watchdog_period()
        CrashLoopPolicy.from_env()
    except ValueError as exc:
        fail(str(exc))
    if os.environ.get(ENV_CONFIG):
        try:
            build_config(ZenohOptions(connect=("tcp/127.0.0.1:7447",)))
        except ValueError as exc:
            fail(f"{ENV_CONFIG}: {exc}")


def _ros2_args(middleware: str, connect: str | None, ns: str) -> tuple[str, ...]:
    """``up --ros2``'s middleware flags as ros2-in / ros2-out take them (checked by their own rules: one line, exit 2);
    under rmw_zenoh the domain ID and the distribution from ``$ROS_DOMAIN_ID`` and ``$ROS_DISTRO`` now, written into
    the programs' command lines."""
    from ..services.ros2live.cli import ros_side

    distro = os.environ.get("ROS_DISTRO", "jazzy")
    naming, _ = ros_side(middleware, os.environ.get("ROS_DOMAIN_ID", "0"), "", [connect] if connect else None, ns,
                         distro=distro, names=("--ros2-middleware", "ROS_DOMAIN_ID", "ROS_DISTRO"))
    args: tuple[str, ...] = ()
    if naming.middleware != "bridge":
        args += ("--middleware", naming.middleware, "--domain-id", str(naming.domain_id), "--ros-distro", distro)
    return args + (("--ros-connect", connect) if connect else ())


def _recording_path(value: str | None, flag: str, folder: bool) -> str | None:
    """An absolute path for a recording (supervisord runs programs in the run dir) that does not exist yet and can
    be made — a ``folder`` (rosbag2) or a file (MCAP), tried and removed again: a folder test passes ``/proc``,
    where the recorder then crash-looped in a stack already started."""
    if value is None:
        return None
    if not value.strip():  # Path("") is the current folder: "--record-mcap:  exists"
        fail(f"{flag}: empty path; give a {'folder' if folder else 'file'}")
    p = Path(value).expanduser().resolve()
    if p.exists():
        fail(f"{flag}: {value} exists")
    if not p.parent.is_dir():
        fail(f"{flag}: no folder {p.parent}")
    (new_dir if folder else out_file)(flag, p)
    return str(p)


PATH_KEYS = {"classifier": ("calibration_file", "config_store", "calibration_store"), "tracker": (),
             "detector": ("weights", "onnx")}
"""Keys of a service's param.yaml that name files: under ``up`` they must be absolute (the programs run in the
stack's run directory, where a relative path would point somewhere else than where the user wrote it from)."""


def _service_configs(given: dict[str, str | None], progs: list[Any]) -> dict[str, str]:
    """Each given ``--<service>-config`` file, checked with the service's own loader before anything starts (a
    bad file had only shown as that program's crash loop), as an absolute path."""
    from ..config import ConfigError, load

    running = {p.name for p in progs}
    out: dict[str, str] = {}
    for service, value in given.items():
        if value is None:
            continue
        flag = f"--{service}-config"
        if service not in running:
            fail(f"{flag}: this stack runs no {service} (its input level leaves it out)")
        path = Path(value).expanduser().resolve()
        try:
            params = load(_param_model(service), str(path), service=service)
        except ConfigError as exc:
            fail(f"{flag}: {exc}")
        for key in PATH_KEYS[service]:
            named = getattr(params, key, None)
            if named and not Path(named).expanduser().is_absolute():
                fail(f"{flag}: {key}: {named} is relative; under `up` the {service} runs in the stack's run"
                     " directory, so give an absolute path")
        if service == "detector":  # what the detector itself refuses at start, refused before anything starts
            from ..services.detector.config import params_refusal

            refused = params_refusal(params)
            if refused is not None:
                fail(f"{flag}: {path}: {refused[0]}: {refused[1]}")
        if service == "classifier" and getattr(params, "calibration", None) == "file":
            from ..services.classifier.calibration_file import CalibrationFileError, read_calibration

            try:
                read_calibration(Path(params.calibration_file).expanduser())
            except CalibrationFileError as exc:
                fail(f"{flag}: calibration_file: {exc}")
        out[service] = str(path)
    return out


def _param_model(service: str) -> type[Any]:
    """The model a service reads its ``--config`` file into (imported only when a file is given)."""
    if service == "classifier":
        from ..services.classifier.config import ClassifierParams

        return ClassifierParams
    if service == "tracker":
        from ..services.tracker.config import TrackerConfig

        return TrackerConfig
    from ..services.detector.config import DetectorParams

    return DetectorParams


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    @app.command("up")
    def up_cmd(
        source: Annotated[str | None, typer.Argument(help="Replay source, as `jitterguard replay` takes it (default: the built-in synthetic scenario, 60 s of synthetic:mixed).")] = None,
        name: NameOpt = None,
        ns: NsOpt = "default",
        detach: Annotated[bool, typer.Option("-d", "--detach", help="Start in the background and return once the stack makes progress (classified objects, every service heard) and has run 5 s more without a crash.")] = False,
        input_level: Annotated[str, typer.Option("--input", help="auto, points, detections or tracks. 'detections' runs sources with ground-truth boxes (synthetic, nuScenes) through the detection-level noise model.")] = "auto",
        router_port: Annotated[int, typer.Option("--router-port", min=0, max=65535, help="The router's port on loopback (0: a free one, printed).")] = 7447,
        host: Annotated[str, typer.Option("--host", help="Sidecar bind address.")] = "127.0.0.1",
        port: Annotated[int | None, typer.Option("--port", min=0, max=65535, help=f"Sidecar port (default {StackSpec.sidecar_port}; 0: a free one, printed; not with --no-sidecar).")] = None,
        run_dir: RunDirOpt = None,
        no_sidecar: Annotated[bool, typer.Option("--no-sidecar", help="Leave the HTTP sidecar out.")] = False,
        duration: Annotated[float | None, float_option("--duration", min=1.0, help="Stop after this many seconds (foreground).")] = None,
        foxglove: Annotated[bool, typer.Option("--foxglove", help="Serve the pipeline to Foxglove (ws://127.0.0.1:PORT).")] = False,
        foxglove_port: Annotated[int, typer.Option("--foxglove-port", min=0, max=65535, help="The Foxglove WebSocket port (0: a free one, printed).")] = StackSpec.foxglove_port,
        record_mcap: Annotated[str | None, typer.Option("--record-mcap", help="Record the Foxglove channels to this MCAP file.")] = None,
        record_ros2: Annotated[str | None, typer.Option("--record-ros2", help="Record a ROS 2 bag for Autoware into this new folder.")] = None,
        ros2: Annotated[str | None, typer.Option("--ros2", help="Live ROS 2 in the replay's place: this PointCloud2 topic (posed by /tf) in — with --input detections this DetectedObjects topic of the vehicle's own detector, tracked without jitterguard's detector — Autoware's TrackedObjects out, through zenoh-bridge-ros2dds as a client of the router (ros2-in, ros2-out).")] = None,
        ros2_middleware: Annotated[str, typer.Option("--ros2-middleware", help="With --ros2: 'bridge' (zenoh-bridge-ros2dds) or 'rmw_zenoh' (ROS 2 nodes on rmw_zenoh, domain $ROS_DOMAIN_ID), as ros2-in's --middleware.")] = "bridge",
        ros2_connect: Annotated[str | None, typer.Option("--ros2-connect", help="With --ros2: the ROS 2 system's own router (rmw_zenohd, or a bridge's), as ros2-in's --ros-connect; then give --router-port another port than its.")] = None,
        rate: R.RateOpt = "1",
        start: R.StartOpt = 0,
        limit: R.LimitOpt = None,
        on_error: R.OnErrorOpt = "skip",
        seed: R.SeedOpt = 0,
        scenario_duration: Annotated[float | None, typer.Option(SCENARIO_DURATION, help="Synthetic sources: scenario length in seconds (the replay's --duration; default 60 for the built-in scenario, 20 otherwise).")] = None,
        lidar: R.LidarOpt = "hdl32e",
        hz: R.HzOpt = 10.0,
        scene: R.SceneOpt = None,
        nuscenes_version: R.NuScenesVersionOpt = None,
        sweeps: R.SweepsOpt = False,
        poses: R.PosesOpt = None,
        calib: R.CalibOpt = None,
        times: R.TimesOpt = None,
        bin_fields: R.BinFieldsOpt = None,
        topic: R.TopicOpt = None,
        pose_topic: R.PoseTopicOpt = None,
        classifier_config: Annotated[str | None, typer.Option("--classifier-config", help="The classifier's param.yaml (as `jitterguard classifier --config`; paths in it absolute).")] = None,
        tracker_config: Annotated[str | None, typer.Option("--tracker-config", help="The tracker's param.yaml (as `jitterguard tracker --config`).")] = None,
        detector_config: Annotated[str | None, typer.Option("--detector-config", help="The detector's param.yaml (as `jitterguard detector --config`; paths in it absolute).")] = None,
    ) -> None:
        """Start router, replay, (detector,) tracker, classifier, sidecar, monitor and monitor-watch under supervisord."""
        t0 = time.monotonic()
        if input_level not in ("auto", "points", "detections", "tracks"):
            fail(f"--input: expected auto, points, detections or tracks, got {input_level!r}")
        check_seed("--seed", seed)
        if detach and duration is not None:
            fail("--duration stops a foreground stack; a detached one (-d) runs until `jitterguard down`")
        if not foxglove and foxglove_port != StackSpec.foxglove_port:  # it had been ignored without a word
            fail("--foxglove-port: only with --foxglove (nothing serves Foxglove without it)")
        if no_sidecar and port is not None:  # the sidecar's port: it too had been ignored without a word
            fail("--port is the sidecar's port; give it or --no-sidecar, not both")
        port = StackSpec.sidecar_port if port is None else port
        ropts = R.ReplayOptions(rate=rate, start=start, limit=limit, on_error=on_error, seed=seed, lidar=lidar,
                                hz=hz, scene=scene, nuscenes_version=nuscenes_version, sweeps=sweeps, poses=poses,
                                calib=calib, times=times, bin_fields=bin_fields, topic=topic, pose_topic=pose_topic)
        if scenario_duration is not None:
            ropts = replace(ropts, duration=scenario_duration)
        try:  # nothing a user typed may change supervisord.conf's structure
            for what, value in (("SOURCE", source), ("--host", host), ("--ns", ns), ("--name", name)):
                if value is not None:
                    check_text(value, what)
            for flag, value in ropts.changed():
                check_text(str(value), flag)
        except ArgumentError as exc:
            fail(str(exc))
        try:
            ZenohOptions(ns=ns)
        except ValueError as exc:
            fail(f"--ns: {exc}")
        _check_environment()
        rd, label = resolve(run_dir, name, ns)
        stack = name or ns
        if ros2 is not None:  # the scans come from the vehicle: no replay, nothing of it to set
            from ..services.ros2live.cli import topic_option

            ros2 = topic_option("--ros2", ros2)
            if source is not None:
                fail("SOURCE is the replay's; --ros2 takes the vehicle's scans in its place: give one of them")
            if input_level not in ("auto", "points", "detections"):
                fail(f"--input {input_level}: --ros2 brings scans (points) for the detector, or with --input"
                     " detections the vehicle's own DetectedObjects for the tracker")
            stray = ropts.changed() + ([(SCENARIO_DURATION, scenario_duration)] if scenario_duration else [])
            if stray:
                fail(f"{stray[0][0]} is the replay's; not with --ros2")
            mode = "detections" if input_level == "detections" else "points"
            if mode == "points" and not has_area("jitterguard.services.detector.service"):
                fail("--ros2: this install has no detector (pip install 'jitterguard[detector]'); a DetectedObjects"
                     " topic needs none: --input detections")
            src, warnings = None, []
            ros2_args = _ros2_args(ros2_middleware, ros2_connect, ns)
        else:
            for flag, value, default in (("--ros2-middleware", ros2_middleware, "bridge"),
                                         ("--ros2-connect", ros2_connect, None)):
                if value != default:
                    fail(f"{flag} is for live ROS 2: give --ros2 TOPIC with it")
            ros2_args = ()
            if source is None and scenario_duration is None and input_level != "tracks":
                ropts = replace(ropts, duration=DEFAULT_SCENARIO_S)
            src, mode, ropts, warnings = _check_source(source, input_level, ropts)
        try:  # the absolute paths add the current folder's name
            for flag, value in ropts.changed() + ([("SOURCE", src)] if src else []):
                check_text(str(value), flag)
        except ArgumentError as exc:
            fail(str(exc))
        for w in warnings:
            print(f"jitterguard: warning: {w}", file=sys.stderr)

        sup = Supervisor(rd, label)
        down_hint = f"`jitterguard down{' --name ' + stack if not run_dir else ' --run-dir ' + str(rd)}`"
        _refuse_if_running(sup, rd, label, down_hint)
        mcap_path, bag_path = (_recording_path(record_mcap, "--record-mcap", folder=False),
                              _recording_path(record_ros2, "--record-ros2", folder=True))
        if mcap_path is not None and mcap_path == bag_path:  # both resolved by _recording_path
            # each alone refuses an existing path, not one the other is about to make: the recorders had raced
            fail(f"--record-ros2: {bag_path} is where --record-mcap writes; give the two recordings two paths")
        try:
            for what, value in (("--record-mcap", mcap_path), ("--record-ros2", bag_path)):
                if value is not None:
                    check_text(value, what)
        except ArgumentError as exc:
            fail(str(exc))
        router_picked = router_port == 0
        # 0: a free port, picked now (the sidecar's on its --host, the Foxglove one only where it is served)
        router_port, port, foxglove_port = _pick_ports([(router_port, "127.0.0.1", True),
                                                        (port, host, not no_sidecar),
                                                        (foxglove_port, "127.0.0.1", foxglove)])
        spec = StackSpec(ns=ns, name=stack, router_port=router_port, sidecar_host=host, sidecar_port=port,
                         source=src, input=mode, sidecar=not no_sidecar, replay_args=tuple(ropts.argv()),
                         run_dir=str(rd), foxglove=foxglove, foxglove_port=foxglove_port, record_mcap=mcap_path,
                         record_ros2=bag_path, ros2_points=ros2, ros2_args=ros2_args)
        configs = _service_configs({"classifier": classifier_config, "tracker": tracker_config,
                                    "detector": detector_config}, programs(spec))
        try:
            for service, path in configs.items():
                check_text(path, f"--{service}-config")
        except ArgumentError as exc:
            fail(str(exc))
        spec = replace(spec, service_configs=configs)
        progs = programs(spec)
        wanted = [(router_port, "127.0.0.1", "--router-port")]
        if any(p.name == "sidecar" for p in progs):
            refusal = bind_refusal(host, api_token_from_env())  # the sidecar's own check, done first
            if refusal:
                fail(f"--host: {refusal}")
            wanted.append((port, host, "--port"))
        if foxglove:
            wanted.append((foxglove_port, "127.0.0.1", "--foxglove-port"))
        clash = _own_clash(wanted)
        if clash:
            fail(clash)
        for p, h, flag in wanted:
            owner = _port_owner(h, p, rd)  # a running stack's port, even while its program does not listen yet
            if owner is not None or port_in_use(h, p):
                fail(f"port {p} on {h} is in use by {owner[0] if owner else 'another program'}; give this stack"
                     f" another {flag}" + (f" (or `{owner[1]}`)" if owner else ""))
            refused = bind_problem(h, p, flag)  # an address not this host's had started the stack to crash-loop
            if refused:
                fail(refused)
        try:
            conf_text = render_config(spec, rd, progs, nodaemon=not detach)
        except ValueError as exc:
            fail(str(exc))
        try:
            check_private_dir(rd)  # before anything is written into it, and again once it is there (made meanwhile)
            rd.mkdir(mode=RUN_DIR_MODE, parents=True, exist_ok=True)
            check_private_dir(rd)
            (rd / "logs").mkdir(mode=RUN_DIR_MODE, exist_ok=True)
            check_private_dir(rd / "logs")
        except ArgumentError as exc:
            fail(str(exc))
        except OSError as exc:
            fail(f"--run-dir: cannot create {rd / 'logs'}: {exc.strerror or exc}")
        _lock_run_dir(rd, label)
        _refuse_if_running(sup, rd, label, down_hint)  # again, under the lock: another `up` may just have started it
        _warn_low_space(rd)
        conf = rd / "supervisord.conf"
        try:
            for stale in (summary.SUMMARY_FILE, WATCH_FILE, "supervisord.pid"):
                (rd / stale).unlink(missing_ok=True)
            conf.write_text(conf_text)
            save_spec(rd, spec)
        except OSError as exc:
            fail(f"--run-dir: cannot write into {rd}: {exc.strerror or exc}")
        cmd = [sys.executable, "-m", "supervisor.supervisord", "-c", str(conf)]
        names = ", ".join(p.name for p in progs)
        wall0 = time.time()
        if detach:
            res = subprocess.run(cmd, capture_output=True, text=True)
            if res.returncode != 0:
                print(f"jitterguard: error: supervisord did not start: {(res.stderr or res.stdout).strip()}",
                      file=sys.stderr)
                raise SystemExit(1)
            watch = _ObjectsWatch(ns, spec.endpoint, t0)
            previous = {s: signal.signal(s, _interrupted) for s in FOREGROUND_STOP_SIGNALS}  # a foreground run's too
            try:
                code = _wait_started(sup, rd, label, names, spec, progs, wall0,
                                     _addresses(spec, progs, router_picked), watch)
            except _Interrupted as stopped:
                # a half-started stack had been left behind, silently: the pipeline running without its monitor
                # and sidecar (started only once the rest runs), no summary, no freeze or crash-loop watch
                print(f"jitterguard: interrupted ({signal.Signals(stopped.signum).name}) while the stack {label} was"
                      " starting; stopping it", file=sys.stderr, flush=True)
                try:
                    _shutdown_when_it_answers(sup)
                    sup.wait_gone(STOP_WAIT_S)
                except StackUnavailable:
                    pass
                code = 128 + stopped.signum
            finally:
                for s, handler in previous.items():
                    signal.signal(s, handler)
                watch.close()
            _exit_without_finalizing(code)

        _quiet_once_stdout_closes()
        proc = subprocess.Popen(cmd, start_new_session=True, preexec_fn=_end_with_parent())
        try:
            _wake(sup, proc)
            stop = threading.Event()
            stop_on_signals(stop.set, FOREGROUND_STOP_SIGNALS)
            print(f"jitterguard: starting {names} (stack {label}, logs in {rd / 'logs'})", flush=True)
            watch = _ObjectsWatch(ns, spec.endpoint, t0)
            code = _foreground(proc, sup, rd, stop, watch, duration, t0, wall0, spec, progs,
                               _addresses(spec, progs, router_picked))
        except BaseException:  # whatever ends `up` unforeseen, it does not leave its stack running on its own
            _stop_supervisord(proc)
            raise
        watch.close()
        _exit_without_finalizing(code)

    def _wake(sup: Supervisor, proc: subprocess.Popen, timeout_s: float = 2.0) -> None:
        """Ask supervisord for its state as soon as it answers. Its main loop starts the programs only after
        its first poll returns, which without a request is a full second after it started; a request returns
        that poll at once (time to the first objects, issue 19)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and proc.poll() is None:
            if sup.running():
                return
            time.sleep(0.02)

    class _Interrupted(Exception):
        def __init__(self, signum: int) -> None:
            super().__init__(signum)
            self.signum = signum

    def _interrupted(signum: int, _frame: Any) -> None:
        raise _Interrupted(signum)

    def _wait_started(sup: Supervisor, rd: Path, label: str, names: str, spec: StackSpec,
                      progs: list[Any], wall0: float, addresses: list[str], watch: _ObjectsWatch) -> int:
        """``up -d``: wait until the stack has started (:func:`_settled`) and the router and the sidecar answer
        (0), or a program keeps crashing or stopped on bad input (stop the stack, 1); after ``DETACH_WAIT_S`` say
        what is missing and leave the stack running (1)."""
        deadline = time.monotonic() + DETACH_WAIT_S
        sidecar = _sidecar_address(spec, progs)
        router = ("127.0.0.1", spec.router_port)  # RUNNING is not listening: a router binds seconds after its start
        procs: list[Any] = []
        events: dict[str, summary.ProgramEvents] = {}
        progress_since: float | None = None
        deferred = {p.name for p in progs if p.deferred}
        started_deferred = False
        waiting = "supervisord"
        while time.monotonic() < deadline:
            time.sleep(0.3)
            events = summary.supervisor_events(rd / "logs" / "supervisord.log", since=wall0 - 1)
            now = time.time()
            bad = summary.crash_loop(events, now)
            if bad is not None:
                print(_crash_report(rd, bad, events), file=sys.stderr)
                _shutdown(sup)
                return 1
            for name in summary.stopped_on_bad_input(events):
                print(_bad_input_report(rd, name), file=sys.stderr)
                _shutdown(sup)
                return 1
            try:
                procs = sup.processes()
            except StackUnavailable as exc:
                if exc.state in ("stopped", "stale", "absent", "shutting_down"):  # `down` from another shell
                    print(f"jitterguard: error: the stack was stopped while it started ({exc.state}: `jitterguard"
                          " down`?); see `jitterguard summary`", file=sys.stderr)
                    return 1  # it had waited its 60 s, then said the stack "is left running"
                continue
            if not started_deferred and procs and all(p.state == "RUNNING" for p in procs if p.name not in deferred):
                _start_deferred(sup, progs)
                started_deferred = True
                continue
            waiting = _not_progressing([p for p in procs if started_deferred or p.name not in deferred], watch,
                                       objects=spec.ros2_points is None)
            if waiting:
                progress_since = None
                continue
            if progress_since is None:
                progress_since = now
            waiting = _settled(events, progress_since, now)
            if waiting:
                continue
            router_answers = _answers(router)  # `status` right after must reach the stack, and the sidecar's
            if not (router_answers and _answers(sidecar)):  # address printed below must answer
                waiting = (f"the router does not listen on {spec.endpoint} yet" if not router_answers else
                           f"the sidecar does not answer on {sidecar[0]}:{sidecar[1]}" if sidecar else "")
                continue
            progress = (f"; first classified objects after {watch.first:.1f} s" if watch.first is not None
                        else "; every service heard")
            print(f"jitterguard: started {names} (stack {label}, run dir {rd}){progress}")
            for line in addresses:
                print(line)
            return 0
        print(f"jitterguard: error: the stack has not started after {DETACH_WAIT_S:.0f} s ({waiting}); it is left"
              " running: see `jitterguard status` and `jitterguard logs NAME`", file=sys.stderr)
        return 1

    def _shutdown_when_it_answers(sup: Supervisor, wait_s: float = 30.0) -> None:
        """``shutdown``, asked again while supervisord runs but does not answer yet (it has just been started, or
        is busy): `down` right after `up` had said "starting or stopping" and done nothing, with exit 0."""
        deadline = time.monotonic() + wait_s
        while True:
            try:
                sup.shutdown()
                return
            except StackUnavailable as exc:
                if exc.state != "starting" or time.monotonic() >= deadline:
                    raise
            time.sleep(0.5)

    def _shutdown(sup: Supervisor) -> None:
        try:
            sup.shutdown()
        except StackUnavailable:
            return
        sup.wait_gone(STOP_WAIT_S)

    def _foreground(proc: subprocess.Popen, sup: Supervisor, rd: Path, stop: threading.Event, watch: _ObjectsWatch,
                    duration: float | None, t0: float, wall0: float, spec: StackSpec, progs: list[Any],
                    addresses: list[str]) -> int:
        """Watch a foreground stack until Ctrl-C, ``--duration`` or a crash loop; stop it; print the summary.

        The addresses (the sidecar's page) are printed once the sidecar accepts connections, not when it is
        started (at the first objects), when it cannot answer yet."""
        sidecar = _sidecar_address(spec, progs)
        announced = addressed = warned = deferred_started = False
        announced_at = 0.0
        crashed: str | None = None
        bad_input: list[str] = []  # programs that stopped on bad input (--on-error stop): not restarted
        events: dict[str, summary.ProgramEvents] = {}
        next_check = 0.0
        while not stop.is_set() and proc.poll() is None:
            now = time.monotonic()
            if duration is not None and now - t0 >= duration:
                break
            if not deferred_started and (watch.first is not None or now - t0 > DEFERRED_START_S):
                deferred_started = True
                _start_deferred(sup, progs)
            if watch.first is not None and not announced:
                announced, announced_at = True, now
                print(f"jitterguard: first classified objects after {watch.first:.1f} s", flush=True)
            if announced and not addressed:
                late = now - announced_at > SIDECAR_LISTEN_WAIT_S
                if late or _answers(sidecar):
                    addressed = True
                    for line in addresses:
                        print(line + ("  (not answering yet: `jitterguard logs sidecar`)"
                                      if late and line.startswith("sidecar:") else ""), flush=True)
                    print("jitterguard: Ctrl-C stops the stack", flush=True)
            if watch.first is None and not warned and now - t0 > FIRST_OBJECTS_WARN_S:
                warned = True
                try:
                    down = [f"{p.name} {p.state}" for p in sup.processes() if p.state != "RUNNING"]
                except StackUnavailable:
                    down = []
                print(f"jitterguard: no classified objects within {FIRST_OBJECTS_WARN_S:.0f} s"
                      + (f" ({', '.join(down)})" if down else "; every program runs")
                      + "; see `jitterguard status` and `jitterguard logs NAME`", file=sys.stderr, flush=True)
            if now >= next_check:
                next_check = now + 0.5
                events = summary.supervisor_events(rd / "logs" / "supervisord.log", since=wall0 - 1)
                crashed = summary.crash_loop(events, time.time())
                bad_input = summary.stopped_on_bad_input(events)
                if crashed is not None or bad_input:
                    break
            stop.wait(0.1)
        died = None  # supervisord ended under this run, not by its stop: killed, or stopped from another shell
        if proc.poll() is None:
            print("jitterguard: stopping the stack", flush=True)
            if _stop_supervisord(proc):
                print(f"jitterguard: error: supervisord did not stop within {STOP_WAIT_S:.0f} s; killed",
                      file=sys.stderr)
        elif not stop.is_set() and (duration is None or time.monotonic() - t0 < duration):
            died = proc.returncode
            if died == 0:  # it shut down cleanly: asked to (`jitterguard down`), its programs stopped with it
                print(f"jitterguard: the stack was stopped from outside this command (`jitterguard down`?) after"
                      f" {time.monotonic() - t0:.0f} s", file=sys.stderr, flush=True)
            else:  # it died: its programs run on without it (a foreground run had printed a summary and exited 0)
                left = stop_orphans(rd)
                print(f"jitterguard: error: supervisord ended with status {died} after {time.monotonic() - t0:.0f} s"
                      + (f"; stopped the programs it left running: {', '.join(left)}" if left else ""),
                      file=sys.stderr, flush=True)
        if crashed is not None:
            print(_crash_report(rd, crashed, events), file=sys.stderr)
        for name in bad_input:
            print(_bad_input_report(rd, name), file=sys.stderr)
        if not _print_summary(rd):
            print(f"jitterguard: no summary was written (see {rd / 'logs' / 'monitor.log'})", file=sys.stderr)
        if crashed is None and not bad_input and watch.first is None:  # exit 1 says why: no classified object came
            print("jitterguard: error: no classified objects came before the stack stopped; see `jitterguard logs "
                  "NAME` for the programs' logs", file=sys.stderr)
        if crashed is not None or bad_input or watch.first is None or died not in (None, 0):
            return 1
        return 0

    @app.command("down")
    def down_cmd(name: NameOpt = None, ns: NsOpt = "default", run_dir: RunDirOpt = None) -> None:
        """Stop a stack started with `jitterguard up -d` (waits until it has stopped), then print its summary."""
        rd, label = resolve(run_dir, name, ns)
        sup = Supervisor(rd, label)
        try:
            _shutdown_when_it_answers(sup)
        except StackUnavailable as exc:
            if exc.state == "frozen":  # stopped by a signal: resume it with the stop already waiting for it
                pid = read_pid(rd)
                if pid is not None:
                    try:
                        os.kill(pid, signal.SIGTERM)
                        os.kill(pid, signal.SIGCONT)
                    except ProcessLookupError:
                        pass
                    print(f"jitterguard: the stack {label}'s supervisord (pid {pid}) was stopped (SIGSTOP?); resumed"
                          " it to stop the stack", flush=True)
                exc = StackUnavailable("shutting_down", str(exc))
            if exc.state == "denied":  # it runs and is not this user's to stop
                print(f"jitterguard: error: {exc}", file=sys.stderr)
                raise SystemExit(1)
            if exc.state == "starting":  # it runs and never answered: a stop still has to reach it
                print(f"jitterguard: error: {exc}; try again, or stop it with `kill {read_pid(rd)}`",
                      file=sys.stderr)
                raise SystemExit(1)
            if exc.state == "lost":  # its run dir deleted under it: no socket to ask, so signal it
                stopped = stop_lost(rd, STOP_WAIT_S)
                if stopped is None:
                    print(f"jitterguard: error: the stack {label} is still stopping after {STOP_WAIT_S:.0f} s",
                          file=sys.stderr)
                    raise SystemExit(1)
                print(f"jitterguard: the stack {label} stopped (supervisord pid {stopped}; its run directory had"
                      " been deleted, so there is no summary)")
                return
            if exc.state == "stale":  # supervisord died; its programs may still run without it
                stopped = stop_orphans(rd)
                print(f"jitterguard: {exc}" + (f"; stopped its programs left running: {', '.join(stopped)}"
                                               if stopped else ""))
                return
            if exc.state != "shutting_down":
                print(f"jitterguard: {exc}")
                return
        print(f"jitterguard: stopping the stack {label}", flush=True)
        if not sup.wait_gone(STOP_WAIT_S):
            print(f"jitterguard: error: the stack {label} is still stopping after {STOP_WAIT_S:.0f} s",
                  file=sys.stderr)
            raise SystemExit(1)
        print(f"jitterguard: the stack {label} stopped")
        if not _print_summary(rd):  # said, not silently left out: the monitor could not write it (a full disk)
            print(f"jitterguard: no summary was written (see {rd / 'logs' / 'monitor.log'})", file=sys.stderr)

    @app.command("status")
    def status_cmd(
        name: NameOpt = None,
        ns: NsOpt = "default",
        run_dir: RunDirOpt = None,
        as_json: Annotated[bool, typer.Option("--json", help="Machine-readable output.")] = False,
        listen: Annotated[float, float_option("--listen-s", min=0.1, max=60.0, help="Seconds to listen for heartbeats (at most 60).")] = 1.5,
    ) -> None:
        """Per service: supervisor state, pid, uptime, liveliness on Zenoh, last frame seq (and health).

        Exit 0 when every program is RUNNING, on the bus and not reporting itself unhealthy; 3 otherwise, and
        when the stack is not running (starting, shutting down, stopped, none); 2 bad input.
        """
        rd, label = resolve(run_dir, name, ns)
        sup = Supervisor(rd, label)
        spec = load_spec(rd)
        try:
            procs = sup.processes()
        except StackUnavailable as exc:
            if as_json:
                print(json.dumps({"stack": spec.name if spec else name or ns, "run_dir": str(rd), "state": exc.state,
                                  "message": str(exc), "services": []}, indent=2))
            else:
                print(f"jitterguard: {exc}")
            raise SystemExit(3) from None
        rows = collect(procs, spec, listen_s=listen)
        healthy = bool(rows) and all(r.up for r in rows)
        if as_json:
            print(json.dumps({"stack": spec.name if spec else name or ns, "ns": spec.ns if spec else ns,
                              "endpoint": spec.endpoint if spec else None, "run_dir": str(rd),
                              "state": "up" if healthy else "degraded",
                              "services": [r.as_dict() for r in rows]}, indent=2))
        else:
            render_table(rows, spec, rd)
        if not healthy:
            raise SystemExit(3)

    @app.command("summary")
    def summary_cmd(
        name: NameOpt = None,
        ns: NsOpt = "default",
        run_dir: RunDirOpt = None,
        as_json: Annotated[bool, typer.Option("--json", help="Machine-readable output.")] = False,
    ) -> None:
        """The run so far (or the last run): frames, tracks born/ended, static/dynamic, rejections, drops, restarts."""
        rd, label = resolve(run_dir, name, ns)
        if _print_summary(rd, as_json=as_json):
            _warn_if_stale(rd, Supervisor(rd, label))
        else:
            running = Supervisor(rd, label).running()
            print(f"jitterguard: no summary for the stack {label} "
                  + ("yet (its monitor writes one every second)" if running else f"({_why_no_summary(rd)})"),
                  file=sys.stderr)
            raise SystemExit(1)

    @app.command("logs")
    def logs_cmd(
        service: Annotated[str, typer.Argument(help="router, replay, detector, tracker, classifier, sidecar, monitor, monitor-watch or supervisord; foxglove, record, ros2-in and ros2-out when up runs them.")],
        name: NameOpt = None,
        ns: NsOpt = "default",
        run_dir: RunDirOpt = None,
        lines: Annotated[int, typer.Option("-n", "--lines", min=1)] = 50,
    ) -> None:
        """Show the last lines of one service's log."""
        rd, _label = resolve(run_dir, name, ns)
        try:
            check_name(service)
        except ArgumentError:
            fail(f"no log for {service!r} in {rd / 'logs'}")
        log = rd / "logs" / f"{service}.log"
        if not log.is_file():
            have = sorted(p.stem for p in (rd / "logs").glob("*.log")) if (rd / "logs").is_dir() else []
            fail(f"no log for {service!r} in {rd / 'logs'}" + (f" (have: {', '.join(have)})" if have else ""))
        print("\n".join(tail(log, lines)))
