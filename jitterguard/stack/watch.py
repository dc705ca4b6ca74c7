"""The stack's ``monitor-watch``: a supervisord event listener that ends a stopped monitor.

Why: the monitor (:mod:`.monitor`) ends every other frozen program, but a monitor stopped itself (SIGSTOP, a cgroup
freezer, a debugger left attached) was ended by nothing — supervisord sees a live pid, so healing stopped for good and
``summary`` only said its counts were old. This listener wakes on supervisord's ``TICK_5`` events, asks supervisord
for the monitor's pid, reads the kernel's word on it (``/proc/PID/stat``: ``T``), and once it has been stopped for as
long as the monitor gives any other program (:func:`freeze_limit`: ``JG_WATCHDOG_S`` + 10 s, 20 s by default) SIGKILLs
it for supervisord to start it again; logged on stderr and counted in :data:`WATCH_FILE` in the run directory, which
the restarted monitor adds to the summary (``restarts.frozen_restarts``) and ``status`` shows.

Who watches the watch: the monitor judges every program it never hears a heartbeat from by ``/proc`` too
(:meth:`.monitor.StackMonitor._end_stopped_unheard`), and this one sends none. Deliberately light: no Zenoh, no
pydantic, no typer (~20 MB, not ~60), since it runs for the whole life of the stack on hosts short of memory.

Run as ``python -m jitterguard.stack.watch --run-dir DIR`` from ``[eventlistener:monitor-watch]`` with
``events=TICK_5``; stdout is supervisord's event-listener protocol, so everything it says goes to stderr.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import IO, NoReturn

from ..files import write_atomically
from ..runtime.envvars import HANG_GRACE_S, watchdog_period
from .control import SERVER_URL_ENV, ProcessInfo, StackUnavailable, Supervisor, process_stopped, socket_of

FREEZE_MARGIN_S = 5.0
"""A program silent (or stopped) this much longer than its own last resort (``JG_WATCHDOG_S`` + the hang grace, when
faulthandler ends a process hung with its heartbeat thread) is one that no watchdog inside it can end."""
WATCH_FILE = "monitor-watch.json"
"""In the run directory: how often this listener ended a stopped program, ``{"frozen_restarts": {"monitor": N}}``."""
TICK_S = 5.0
"""supervisord's TICK_5 period: the listener's clock."""
PROGRAM = "monitor"


def freeze_limit(watchdog_s: float | None) -> float | None:
    """How long a program may stand still (silent, or stopped in ``/proc``) before it is ended: one rule for the
    monitor and this listener, so a stopped monitor gets no more and no less time than any program it judges.
    None when the watchdogs are off (``JG_WATCHDOG_S=0``)."""
    return None if watchdog_s is None else watchdog_s + HANG_GRACE_S + FREEZE_MARGIN_S


@dataclass
class StoppedJudge:
    """Pure: given, on each tick, the watched program's pid and whether the kernel says it is stopped, say when it has
    been stopped for ``limit_s``. A gap between ticks of more than three periods means this listener stood still
    itself (it was stopped, or the host slept): it then starts its clock again rather than judge its own pause."""

    limit_s: float
    tick_s: float = TICK_S
    since: dict[int, float] = field(default_factory=dict)
    last_tick: float | None = None

    def step(self, pid: int | None, stopped: bool, now: float) -> bool:
        """Whether ``pid`` is to be ended now (stopped for at least ``limit_s``, as far as this judge has seen)."""
        paused = self.last_tick is not None and now - self.last_tick > 3 * self.tick_s
        self.last_tick = now
        if pid is None or not stopped:
            self.since.clear()
            return False
        if paused:
            self.since.clear()
        since = self.since.setdefault(pid, now)
        self.since = {pid: since}  # another pid (restarted meanwhile) starts afresh
        return now - since >= self.limit_s


@dataclass
class BusSilence:
    """Pure: how long a program has been silent on the heartbeat bus, counted only while the bus carries the
    others' heartbeats. A router stopped or restarting silences every service at once; when it is back, the
    services reconnect one by one, and silence counted from each one's last beat had judged a service that had
    not yet reconnected frozen (the monitor killed a classifier and a sidecar that were never stopped, seconds
    after the router was replaced). Silence is therefore counted from the later of its last beat and the moment
    the bus was last heard to carry beats again."""

    back_at: float | None = None  # since when the bus has carried heartbeats (None: not now)

    def carrying(self, heard: int, now: float) -> bool:
        """Record, at ``now``, whether the bus carries heartbeats: ``heard`` services (the judge's own aside) were
        heard within the last few periods, at least two of them. False: judge nothing."""
        if heard < 2:
            self.back_at = None
            return False
        if self.back_at is None:
            self.back_at = now
        return True

    def silent_for(self, last_beat: float, now: float) -> float:
        """Seconds a program whose last heartbeat came at ``last_beat`` has been silent while the bus carried
        others' (0 while it carries none)."""
        if self.back_at is None:
            return 0.0
        return now - max(last_beat, self.back_at)


def load_counts(run_dir: Path) -> dict[str, int]:
    """Program → how often this listener ended it stopped, from :data:`WATCH_FILE` ({} without a readable one)."""
    try:
        data = json.loads((run_dir / WATCH_FILE).read_text())
        counts = data.get("frozen_restarts") or {}
        return {str(k): int(v) for k, v in counts.items()}
    except (OSError, ValueError, AttributeError, TypeError):
        return {}


def save_counts(run_dir: Path, counts: dict[str, int], pid: int) -> None:
    """Write :data:`WATCH_FILE` atomically (a reader never sees half of it); raises OSError."""
    data = {"frozen_restarts": counts, "last_pid": pid,
            "last_at": datetime.now(timezone.utc).isoformat(timespec="seconds")}
    write_atomically(run_dir / WATCH_FILE, (json.dumps(data, sort_keys=True) + "\n").encode(), durable=False)


class MonitorWatch:
    """The adapter: supervisord's answer and ``/proc`` in, a SIGKILL and the count file out."""

    def __init__(self, run_dir: Path, supervisor: Supervisor, limit_s: float, program: str = PROGRAM) -> None:
        self.run_dir, self.supervisor, self.program = run_dir, supervisor, program
        self.judge = StoppedJudge(limit_s)
        self.counts = load_counts(run_dir)  # a restarted listener goes on counting
        self.log = logging.getLogger("jitterguard.monitor-watch")
        self._said: str | None = None

    def tick(self, now: float) -> None:
        """One look: end the program if it has been stopped for the limit. Never raises (a listener that dies is
        restarted by supervisord, but says nothing useful meanwhile)."""
        try:
            info = ProcessInfo.from_rpc(self.supervisor.call("getProcessInfo", self.program))
        except StackUnavailable as exc:
            self._say(f"cannot ask supervisord about {self.program}: {exc}")
            self.judge.step(None, False, now)
            return
        if self._said is not None:
            self.log.info("supervisord answers again")
            self._said = None
        pid = info.pid if info.state == "RUNNING" else None
        stopped = pid is not None and process_stopped(pid)
        if not self.judge.step(pid, stopped, now) or pid is None:
            return
        self.log.error("%s (pid %d) has been stopped for %.0f s (SIGSTOP?): nothing heals the stack meanwhile; killing "
                       "it for supervisord to restart it", self.program, pid, now - self.judge.since[pid])
        if not self.supervisor.kill(pid):
            self.log.error("pid %d is not a program of this supervisord any more: left alone", pid)
            return
        self.judge.since.clear()
        self.counts[self.program] = self.counts.get(self.program, 0) + 1
        try:
            save_counts(self.run_dir, self.counts, pid)
        except OSError as exc:
            self.log.error("cannot write %s: %s (the count is kept in memory)", self.run_dir / WATCH_FILE,
                           exc.strerror or exc)

    def _say(self, what: str) -> None:
        if what != self._said:
            self.log.warning("%s", what)
        self._said = what


def serve(watch: MonitorWatch | None, stdin: IO[bytes], stdout: IO[bytes]) -> None:
    """supervisord's event-listener protocol: READY, one event (a header line, then ``len`` bytes), RESULT. Every
    event is answered OK, whatever the look found: a FAIL makes supervisord send the same event again. With
    ``watch`` None (watchdogs off) it only answers, so supervisord keeps it RUNNING and quiet."""
    while True:
        stdout.write(b"READY\n")
        stdout.flush()
        line = stdin.readline()
        if not line:
            return  # supervisord closed our stdin: it is stopping us
        header = dict(tok.split(":", 1) for tok in line.decode(errors="replace").split() if ":" in tok)
        stdin.read(int(header.get("len", "0")))  # bytes, as supervisord counts them
        if watch is not None and header.get("eventname", "").startswith("TICK"):
            watch.tick(time.monotonic())
        stdout.write(b"RESULT 2\nOK")
        stdout.flush()


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        """Bad input: one line and exit 2 (argparse's own prints the whole usage first)."""
        print(f"{self.prog}: error: {message} (see --help)", file=sys.stderr)
        raise SystemExit(2)


def _fail(message: str) -> NoReturn:
    print(f"jitterguard monitor-watch: {message}", file=sys.stderr)
    raise SystemExit(2)


def main(argv: list[str] | None = None) -> None:
    parser = _Parser(prog="python -m jitterguard.stack.watch",
                     description="supervisord event listener (events=TICK_5): SIGKILLs the stack's monitor once it "
                                 "has been stopped (SIGSTOP) for JG_WATCHDOG_S + 10 s, for supervisord to restart it.")
    parser.add_argument("--run-dir", required=True,
                        help=f"the monitor's run directory (its --run-dir): the count goes to {WATCH_FILE} there")
    parser.add_argument("--supervisor-url", default=os.environ.get(SERVER_URL_ENV),
                        help=f"supervisord's XML-RPC socket (unix:///…/supervisor.sock); default: {SERVER_URL_ENV}, "
                             "which supervisord gives every program")
    args = parser.parse_args(argv)
    rd = Path(args.run_dir)
    if not args.run_dir.strip() or not rd.is_dir():
        _fail(f"--run-dir: no such folder: {args.run_dir!r}")
    if not args.supervisor_url:
        _fail(f"--supervisor-url: not given and no {SERVER_URL_ENV} (run it as a supervisord event listener)")
    try:
        sock = socket_of(args.supervisor_url)
    except ValueError as exc:
        _fail(f"--supervisor-url: {exc}")
    try:
        limit = freeze_limit(watchdog_period())
    except ValueError as exc:
        _fail(str(exc))
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    log = logging.getLogger("jitterguard.monitor-watch")
    if limit is None:
        log.info("JG_WATCHDOG_S=0: watchdogs are off; a stopped monitor is left alone")
        watch = None
    else:
        log.info("watching the monitor: ended once stopped for %.0f s", limit)
        watch = MonitorWatch(rd, Supervisor(rd, sock=sock), limit)
    try:
        serve(watch, sys.stdin.buffer, sys.stdout.buffer)
    except KeyboardInterrupt:
        pass


if __name__ == "__main__":
    main()
