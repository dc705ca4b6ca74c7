"""The stack's ``monitor`` program: hears every service's heartbeat and keeps the run's summary in the run
directory (``summary.json``, rewritten atomically every second and once more on shutdown).

Why a program of its own: a detached stack has no ``jitterguard up`` process waiting on it, and each service's
counters start again at zero when supervisord restarts it. The monitor keeps the last counters of every process
(:class:`~.summary.Ledger`), so ``jitterguard summary`` — or the end of a foreground ``up`` — adds up the whole
run, restarts included. It is started first and stopped last, and every service sends a final heartbeat as it
closes, so the file ends with the final counts. If the monitor itself is restarted it reads the file back.

It also polls supervisord (XML-RPC, every :data:`FREEZE_CHECK_S`) for what supervisord cannot see or does not do by
itself: a program frozen while RUNNING (:meth:`StackMonitor._end_frozen`) and a program that crashes again and
again after it was called RUNNING, which supervisord restarts at once for ever: it is held back, stopped, and
started again after a doubling back-off (:mod:`.backoff`, ``JG_CRASH_LOOP_*``). The monitor itself, stopped, is
ended by the stack's ``monitor-watch`` (:mod:`.watch`), whose count it adds to the summary.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from datetime import datetime, timezone
from pathlib import Path
from collections.abc import Iterable
from typing import Annotated, Any

import typer
import zenoh

from ..cli_common import ConnectOpt, ListenOpt, LogLevelOpt, NsOpt, ZenohConfigOpt, fail, hold_lock, zenoh_options
from ..runtime import Service, ZenohOptions, setup_logging
from ..runtime.progress import FAILING, Health
from ..runtime.service import HEARTBEAT_PERIOD_S
from ..schemas import DecodeError, decode, keys
from ..schemas.models import Heartbeat
from ..schemas.wire import HEARTBEAT_BOUNDS
from . import summary
from .backoff import Action, CrashLoopGuard, CrashLoopPolicy
from .control import SERVER_URL_ENV, StackUnavailable, Supervisor, socket_of
from .status import SERVICE_NAMES, SPEC_FILE, load_spec
from .supervisor import programs
from .watch import BusSilence, freeze_limit, load_counts

WRITE_PERIOD_S = 1.0
FREEZE_CHECK_S = 2.0
"""How often the monitor asks supervisord about its programs (frozen ones, crash loops)."""
MAX_BEAT_PIDS = 256


def _iso(t: float) -> str:
    return datetime.fromtimestamp(t, timezone.utc).isoformat(timespec="seconds")


def _spec_written_at(run_dir: Path) -> float | None:
    """When ``up`` wrote stack.json, just before it started supervisord: the run's start."""
    try:
        return (run_dir / SPEC_FILE).stat().st_mtime
    except OSError:
        return None


def stack_services(program_names: Iterable[str]) -> frozenset[str]:
    """The service names the stack's programs announce themselves under (:data:`.status.SERVICE_NAMES`)."""
    return frozenset(n for p in program_names for n in SERVICE_NAMES.get(p, (p,)))


class StackMonitor(Service):
    name = "monitor"

    def __init__(self, opts: ZenohOptions, run_dir: Path, supervisor_sock: Path | None = None,
                 supervisord_log: Path | None = None) -> None:
        """``run_dir``: where summary.json goes (a stack's run directory). Under an operator's own supervisord
        (``deploy/supervisord.conf``) its socket and log are elsewhere: ``supervisor_sock`` and
        ``supervisord_log`` name them (by default the run directory's, as ``jitterguard up`` lays it out)."""
        self.run_dir = run_dir
        prev = summary.load(run_dir) or {}
        self.ledger = summary.Ledger.from_json(prev.get("ledger", {}))
        self.run_started_at = float(prev.get("started_at_s") or _spec_written_at(run_dir) or time.time())
        self.dirty = True
        self.write_error: str | None = None  # why summary.json could not be written, until it is again
        self.supervisor_error: str | None = None  # why supervisord cannot be asked (its socket refuses us, …)
        self._beat_at: dict[int, tuple[str, float]] = {}  # pid -> (service, monotonic time of its last heartbeat)
        self._beat_lock = threading.Lock()
        self._ledger_lock = threading.Lock()
        self._stopped_since: dict[int, float] = {}  # a router or unheard pid seen stopped (SIGSTOP), since when
        self._bus = BusSilence()  # silence counts only while the bus carries the others' heartbeats
        self.supervisor = Supervisor(run_dir, sock=supervisor_sock)
        spec = load_spec(run_dir)
        # the services the stack runs, whose heartbeats a flood of made-up names may not crowd out of the ledger:
        # from the spec `up` wrote, then from supervisord's programs (an operator's own supervisord.conf)
        self._own_services = stack_services(p.name for p in programs(spec)) if spec is not None else frozenset()
        # the run's own events: stack.json is written before supervisord starts (the log keeps milliseconds; a
        # look-back of seconds counted the previous run's last crashes in a run dir used again at once)
        self.supervisord_log = summary.SupervisorLog(supervisord_log or run_dir / "logs" / "supervisord.log",
                                                     since=self.run_started_at - 0.01)
        try:  # read before the session opens, as JG_WATCHDOG_S is: a bad value is a one-line startup error
            policy = CrashLoopPolicy.from_env()
        except ValueError as exc:
            logging.getLogger(f"jitterguard.{self.name}").error("%s", exc)
            raise SystemExit(2) from None
        # crashes before the run (or before this monitor, when it was restarted) are not counted again
        self.guard = CrashLoopGuard(policy, since=self.run_started_at - 0.01)
        if prev.get("crash_loop_guard"):
            self.guard.restore(prev["crash_loop_guard"], time.time())
        self._guard_lock = threading.Lock()
        super().__init__(opts)
        self._declared.append(self.session.declare_subscriber(keys.heartbeat_all(self.ns), self._on_beat))
        self.spawn(self._writer, "writer")
        # JG_WATCHDOG_S=0 turns every watchdog off, the freeze watch too; JG_CRASH_LOOP_EXITS=0 the crash-loop guard
        if self._watchdog_env is not None or policy.enabled:
            self.spawn(self._supervisord_watch, "supervisord-watch")

    def _on_beat(self, sample: zenoh.Sample) -> None:
        try:
            hb = decode(Heartbeat, sample.payload.to_bytes(), **HEARTBEAT_BOUNDS)
        except DecodeError as exc:
            self.reject(exc, keys.heartbeat_all(self.ns), str(sample.key_expr))
            return
        self.counters.inc("received")
        named = keys.last_chunk(str(sample.key_expr))
        if hb.service != named:  # sums go by the key, as the sidecar reads it: a heartbeat put on another service's
            # key had been summed as the service it names (counters of 10^15 into the classifier's totals)
            self.reject(DecodeError("Heartbeat", "service", f"{hb.service!r} is not the service its key names "
                                                            f"({named!r})"), keys.heartbeat_all(self.ns),
                        str(sample.key_expr))
            return
        with self._beat_lock:
            self._beat_at[hb.pid] = (hb.service, time.monotonic())
            if len(self._beat_at) > MAX_BEAT_PIDS:  # bounded: made-up pids (anyone may publish) push out the oldest
                self._beat_at.pop(min(self._beat_at, key=lambda p: self._beat_at[p][1]))
        extra = {"last_seq": hb.last_seq, "uptime_s": round(hb.uptime_s, 1)}
        with self._ledger_lock:
            evicted = self.ledger.evicted
            kept = self.ledger.observe(hb.service, hb.pid, hb.counters, hb.stamp, extra,
                                       own=hb.service in self._own_services)
            evicted = self.ledger.evicted - evicted
        if evicted:  # made-up services dropped to keep the stack's own
            self.counters.inc("ledger_services_evicted", evicted)
        if not kept:
            self.counters.inc("heartbeats_dropped")  # past the ledger's bounds (MAX_SERVICES, MAX_LEDGER_BYTES)
            return
        self.dirty = True

    def snapshot(self) -> dict[str, Any]:
        spec = load_spec(self.run_dir)
        now = time.time()
        events = self.supervisord_log.events()
        meta = {"stack": spec.name if spec else self.run_dir.name, "ns": self.ns,
                "source": (spec.source if spec else None), "started_at": _iso(self.run_started_at),
                "updated_at": _iso(now), "duration_s": round(now - self.run_started_at, 1)}
        with self._guard_lock:
            guard = self.guard.as_json()
        watched = load_counts(self.run_dir)  # the monitor-watch's: how often this monitor was ended stopped
        with self._ledger_lock:  # heartbeats change it on Zenoh's thread: the writer had died of "dictionary
            # changed size during iteration" within seconds of a burst of new processes, summary.json frozen
            return {**summary.build(self.ledger, events, meta=meta, backoff=guard, watched=watched),
                    "started_at_s": self.run_started_at, "ledger": self.ledger.as_json(), "crash_loop_guard": guard}

    def write(self) -> None:
        """Write summary.json; a failure (a full disk, a run directory gone read-only) is logged once, counted,
        and reported in the heartbeat until a write succeeds again."""
        path = self.run_dir / summary.SUMMARY_FILE
        try:
            summary.save(self.run_dir, self.snapshot())
        except OSError as exc:
            self.counters.inc("summary_write_errors")
            error = f"cannot write {path}: {exc.strerror or exc}"
            if error != self.write_error:
                self.log.error("%s; the summary stays as last written until a write succeeds", error)
            self.write_error = error
            return
        if self.write_error is not None:
            self.log.info("%s written again", path)
        self.write_error = None
        self.dirty = False

    def health(self) -> Health:
        """``failing`` while summary.json cannot be written: the monitor's one job. It had logged a traceback a
        second (into the same full disk) while ``status`` said ok and ``summary`` "its monitor writes one every
        second". Not a case for the watchdog (``unhealthy_for_s`` stays 0): a restart frees no disk, and the
        ledger in memory is all that keeps the counts of processes that end meanwhile. Also ``failing`` while
        supervisord cannot be asked about its programs for a reason that will not pass by itself
        (:meth:`_supervisor_unreachable`): the monitor's other job, healing, is then undone."""
        error = self.write_error or self.supervisor_error
        return Health(FAILING, error) if error is not None else super().health()

    def _supervisord_watch(self) -> None:
        """Every :data:`FREEZE_CHECK_S`: ask supervisord for its programs, once, then end the frozen ones
        (:meth:`_end_frozen`, unless ``JG_WATCHDOG_S=0``) and hold back those in a crash loop
        (:meth:`_hold_crash_loops`, unless ``JG_CRASH_LOOP_EXITS=0``)."""
        limit = freeze_limit(self._watchdog_env)  # the rule the monitor-watch holds the monitor itself to
        last_tick = time.monotonic()
        while not self.stop_event.wait(FREEZE_CHECK_S):
            now = time.monotonic()
            if now - last_tick > 3 * FREEZE_CHECK_S:  # the monitor itself was paused: start every clock again
                with self._beat_lock:
                    self._beat_at = {pid: (svc, now) for pid, (svc, _) in self._beat_at.items()}
                self._stopped_since = {pid: now for pid in self._stopped_since}
            last_tick = now
            try:
                procs = self.supervisor.processes()
            except StackUnavailable as exc:
                self._supervisor_unreachable(exc)
                continue
            except Exception:  # never let the watch die; say why
                self.log.exception("cannot ask supervisord about its programs")
                continue
            self._own_services = self._own_services | stack_services(p.name for p in procs)
            if self.supervisor_error is not None:
                self.log.info("supervisord answers again: frozen programs and crash loops are watched again")
                self.supervisor_error = None
            if limit is not None:
                try:
                    self._end_frozen(procs, now, limit)
                except Exception:
                    self.log.exception("freeze watch failed")
            if self.guard.policy.enabled:
                try:
                    self._hold_crash_loops(procs)
                except Exception:
                    self.log.exception("crash-loop guard failed")

    def _supervisor_unreachable(self, exc: StackUnavailable) -> None:
        """Say once, and in the heartbeat's health until supervisord answers again, why it cannot be asked when
        that will not pass by itself: a socket that refuses this user (a deployment whose ``chown=`` leaves the
        monitor's user out), a supervisord stopped by a signal, a fault. Without this the watch had skipped every
        look in silence — ``monitor up`` the last line of its log — while a frozen service stayed frozen.
        Starting and shutting down pass by themselves and stay quiet."""
        if exc.state not in ("denied", "frozen", "error"):
            return
        error = f"cannot ask supervisord about its programs, so frozen programs and crash loops go unhandled: {exc}"
        if error != self.supervisor_error:
            self.log.error("%s", error)
        self.supervisor_error = error

    def _end_frozen(self, procs: list[Any], now: float, limit: float) -> None:
        """End a program that supervisord says is RUNNING but that has sent no heartbeat for
        ``JG_WATCHDOG_S`` + 10 s (:func:`.watch.freeze_limit`: 20 s by default).

        A stopped process (SIGSTOP, a cgroup freezer, a debugger that left it stopped) runs no thread at all: its
        own watchdog and faulthandler's timer wait with it, supervisord sees a live pid, and the stack had stood
        still for good with every program RUNNING. Only a process heard from before (with its current pid) is
        judged, only while other services are heard (a router down or restarting silences everyone: not a
        freeze), its silence counted from no earlier than when they were heard again (:class:`.watch.BusSilence`:
        services reconnect one by one after a router's restart), and never after the monitor itself stood still
        (it would then judge its own pause). It is ended with SIGKILL, which a stopped process cannot hold off, for
        supervisord to start it again. The router, which sends no heartbeat, is judged by whether the kernel says
        it is stopped (:meth:`_end_stopped_unheard`), as is a program this monitor never heard from (stopped before
        this monitor started, or before its first beat)."""
        from .status import SERVICE_NAMES

        with self._beat_lock:
            beats = dict(self._beat_at)
        self._end_stopped_unheard(procs, beats, now, limit)
        own = os.getpid()
        recent = {svc for pid, (svc, t) in beats.items() if now - t <= 3 * HEARTBEAT_PERIOD_S and pid != own}
        if not self._bus.carrying(len(recent), now):  # not carrying heartbeats now (the router is away): judge nothing
            return
        for proc in procs:
            if proc.state != "RUNNING" or proc.pid is None or proc.pid == own:
                continue
            seen = beats.get(proc.pid)
            if seen is None or seen[0] not in SERVICE_NAMES.get(proc.name, (proc.name,)):
                continue
            silent = self._bus.silent_for(seen[1], now)
            if silent < limit:
                continue
            self.log.error("%s (pid %d) has sent no heartbeat for %.0f s while supervisord says RUNNING and the "
                           "other services are heard: frozen (stopped, or hung where no watchdog inside it runs);"
                           " killing it for supervisord to restart it", proc.name, proc.pid, silent)
            if self.supervisor.kill(proc.pid):
                self.counters.inc(f"frozen_restarts.{proc.name}")
            with self._beat_lock:
                self._beat_at.pop(proc.pid, None)

    def _end_stopped_unheard(self, procs: list[Any], beats: dict[int, tuple[str, float]], now: float,
                             limit: float) -> None:
        """The router sends no heartbeat, and while it stands still nobody is heard: judged by the kernel instead
        (``/proc``: stopped by a signal) for as long as the others are by their silence. A router stopped had left
        the whole stack silent for good, every program RUNNING. So is a program whose current pid this monitor has
        never heard from: one stopped before this monitor started (a monitor restarted mid-run, or started after
        the pipeline) or before its first heartbeat, which silence cannot judge — a tracker stopped just before the
        monitor was restarted had stayed frozen for good, `status` saying "no heartbeat heard"."""
        from .control import process_stopped
        from .status import SERVICE_NAMES

        own = os.getpid()
        seen = set()
        for proc in procs:
            if proc.state != "RUNNING" or proc.pid is None or proc.pid == own:
                continue
            heard = beats.get(proc.pid)
            if proc.name != "router" and heard is not None and heard[0] in SERVICE_NAMES.get(proc.name, (proc.name,)):
                continue  # judged by its silence (_end_frozen)
            if not process_stopped(proc.pid):
                continue
            seen.add(proc.pid)
            since = self._stopped_since.setdefault(proc.pid, now)
            if now - since >= limit:
                what = ("no service can be heard through it" if proc.name == "router"
                        else "this monitor never heard it, and nothing inside it runs")
                self.log.error("%s (pid %d) has been stopped for %.0f s (SIGSTOP?): %s; killing it for supervisord "
                               "to restart it", proc.name, proc.pid, now - since, what)
                if self.supervisor.kill(proc.pid):
                    self.counters.inc(f"frozen_restarts.{proc.name}")
                seen.discard(proc.pid)
        self._stopped_since = {pid: t for pid, t in self._stopped_since.items() if pid in seen}

    def _hold_crash_loops(self, procs: list[Any]) -> None:
        """Hold back a program that keeps dying after supervisord called it RUNNING (:class:`.backoff.CrashLoopGuard`
        decides, from supervisord's log; here only its answers are carried out): stopped through supervisord, one
        warning, started again when its back-off has passed. A stop or start that supervisord refuses (a program
        EXITED between two looks cannot be stopped) is asked for again on the next look."""
        events = self.supervisord_log.events()
        now = time.time()
        actions: list[Action] = []
        with self._guard_lock:
            for proc in procs:
                ev = events.get(proc.name)
                action = self.guard.step(proc.name, proc.state, ev.running_crashes if ev else (), now)
                if action is not None:
                    actions.append(action)
            held = len(self.guard.held_back())
        self.counters.set("now.held_back", held)
        for action in actions:
            self.dirty = True
            if action.kind == "stop":
                if action.warn:
                    self.counters.inc(f"backed_off.{action.name}")
                    self.log.warning("%s crashed %d times within %.0f s after it had started (crash loop %d in a "
                                     "row): holding it back; next start in %.0f s (at %s)", action.name,
                                     action.crashes, self.guard.policy.window_s, action.loop, action.hold_s,
                                     _iso(action.until))
                method = "stopProcess"
            else:
                method = "startProcess"
            try:
                self.supervisor.call(method, action.name, False)
            except StackUnavailable as exc:  # asked again on the next look
                self.log.debug("%s %s: %s", method, action.name, exc)
                continue
            if action.kind == "start":
                self.log.info("starting %s again after its crash-loop back-off", action.name)

    def _writer(self) -> None:
        while not self.stop_event.wait(WRITE_PERIOD_S):
            if self.dirty or self.write_error is not None:
                try:
                    self.write()
                except Exception as exc:  # the writer is the monitor's one job: it must not end, and it says why
                    self.counters.inc("summary_write_errors")
                    self.write_error = f"cannot build the summary: {type(exc).__name__}: {exc}"
                    self.log.exception("summary not written")

    def on_close(self) -> None:
        time.sleep(0.3)  # the final heartbeats of the services stopped just before us may still be on the way
        self.write()


def monitor_command(
    run_dir: Annotated[str, typer.Option("--run-dir", help="The stack's run directory (summary.json goes there); "
                                         "under your own supervisord, a folder the monitor may write.")],
    supervisor_url: Annotated[str | None, typer.Option(
        "--supervisor-url", envvar=SERVER_URL_ENV, show_envvar=False,
        help="supervisord's XML-RPC socket (unix:///…/supervisor.sock). supervisord gives every program its own in "
             "SUPERVISOR_SERVER_URL, which is the default; without either, the run directory's.")] = None,
    supervisord_log: Annotated[Path | None, typer.Option(
        "--supervisord-log", help="supervisord's own log (crash loops are read from it); default: the run "
                                  "directory's logs/supervisord.log.")] = None,
    log_level: LogLevelOpt = "INFO",
    ns: NsOpt = "default",
    zenoh_config: ZenohConfigOpt = None,
    connect: ConnectOpt = None,
    listen: ListenOpt = None,
) -> None:
    """The stack's bookkeeping and healing program (started by `jitterguard up`, or a program of your own
    supervisord): heartbeats in, summary.json out; ends frozen programs and holds back crash loops."""
    if not run_dir.strip():  # Path("") is the current folder: summary.json had gone wherever it was started
        fail("--run-dir: empty path; give a folder")
    rd = Path(run_dir)
    if not rd.is_dir():  # bad input first: a one-line error before anything is set up
        fail(f"--run-dir: no such folder: {rd}")
    try:
        sock = socket_of(supervisor_url) if supervisor_url else None
    except ValueError as exc:
        fail(f"--supervisor-url: {exc}")
    if supervisord_log is not None and not supervisord_log.parent.is_dir():
        fail(f"--supervisord-log: no such folder: {supervisord_log.parent}")
    _hold_monitor_lock(rd)
    setup_logging(log_level)
    StackMonitor(zenoh_options(ns, zenoh_config, connect, listen), rd, sock, supervisord_log).run_forever()


MONITOR_LOCK = "monitor.lock"


def _hold_monitor_lock(rd: Path) -> None:
    """Take the run directory's monitor lock for this process's life, or one line and exit 2: a second monitor on one
    run directory ended frozen programs and held back crash loops on its own as well, so one freeze was counted
    twice in ``frozen_restarts``."""
    hold_lock(rd / MONITOR_LOCK, f"another stack monitor keeps {rd} (it holds {rd / MONITOR_LOCK}); one monitor a "
                                 "run directory")


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    app.command("stack-monitor", hidden=True)(monitor_command)
