"""``jitterguard status``: what supervisord says about each program, plus what Zenoh says about each service.

supervisord knows the process (state, pid, uptime); Zenoh knows whether the service is actually on the bus
(liveliness token on ``alive/{service}``) and whether frames are flowing (``last_seq`` of the heartbeat on
``heartbeat/{service}``, and any health verdict the heartbeat carries). Both views come from a run directory
that ``jitterguard up`` wrote, including the ``stack.json`` that records the namespace and router endpoint.

A service is *up* when supervisord says RUNNING, its token is visible through the router, and its heartbeat
does not report it unhealthy; ``jitterguard status`` exits 3 unless every service is up.
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..runtime.exit_codes import EXIT_BAD_INPUT
from .control import ProcessInfo
from .supervisor import StackSpec

SPEC_FILE = "stack.json"


def save_spec(run_dir: Path, spec: StackSpec) -> Path:
    path = run_dir / SPEC_FILE
    path.write_text(json.dumps(dataclasses.asdict(spec), indent=2) + "\n")
    return path


def load_spec(run_dir: Path) -> StackSpec | None:
    """The spec ``up`` wrote into ``run_dir`` (None if there is none or it cannot be read)."""
    path = run_dir / SPEC_FILE
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict):  # a stack.json that is not an object: `status` had ended in a traceback
        return None
    known = {f.name for f in dataclasses.fields(StackSpec)}
    values = {k: v for k, v in data.items() if k in known}
    for name in ("replay_args", "ros2_args"):  # JSON has lists where the spec holds tuples
        if isinstance(values.get(name), list):
            values[name] = tuple(values[name])
    try:
        return StackSpec(**values)
    except TypeError:
        return None


@dataclass
class ServiceStatus:
    name: str
    state: str
    pid: int | None = None
    uptime_s: float | None = None
    alive: bool | None = None  # liveliness token seen on Zenoh (None: not probed)
    last_seq: int | None = None  # from the latest heartbeat
    heartbeat_uptime_s: float | None = None
    heartbeat_pid: int | None = None
    health: str | None = None  # ok | failing | stalled, from the heartbeat (jitterguard.runtime.progress)
    health_reason: str = ""
    counters: dict[str, int] = dataclasses.field(default_factory=dict)
    detail: str = ""
    heartbeat_expected: bool = False  # `status` listened long enough to hear one (not the router, which sends none)
    problem: str = ""  # why a program is not up, in words: not running (and its log's last line), unreachable
    held_back_s: float | None = None  # held back by the monitor after a crash loop: seconds to its next start
    recent_exits: int = 0  # unexpected exits within the last RECENT_EXITS_S (supervisord's log): restarted, not steady
    last_exit: str = ""  # the last of them: "exit status 1, 12 s ago"
    frozen_restarts: int = 0  # ended frozen this run (by the monitor; the monitor itself by the monitor-watch)

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @property
    def heard(self) -> bool:
        """A heartbeat was heard while listening — or none was to be expected (Zenoh not probed, a listen shorter
        than the heartbeat period, the router). A service alive on the bus but silent is frozen (a stopped process
        keeps its token for a while)."""
        return self.heartbeat_pid is not None or not self.heartbeat_expected

    @property
    def up(self) -> bool:
        """RUNNING, on the bus, heard from, and not reporting itself unhealthy."""
        return self.state == "RUNNING" and self.alive is not False and self.heard and self.health in (None, "ok")


SERVICE_NAMES = {"replay": ("replay", "feed-tracks")}
"""The service names a supervisord program may announce itself under on Zenoh (its token, its heartbeat)."""
OFF_BUS = frozenset({"monitor-watch"})
"""Programs that are no Zenoh participant (no token, no heartbeat): up when RUNNING. The router is one too, but is
judged by whether anything answers through it."""


def rows_from_processes(procs: list[ProcessInfo]) -> list[ServiceStatus]:
    return [ServiceStatus(name=p.name, state=p.state, pid=p.pid, uptime_s=p.uptime_s, detail=p.description)
            for p in procs]


def probe_zenoh(ns: str, endpoint: str, listen_s: float = 1.5) -> tuple[set[str], dict[str, Any], str | None]:
    """Liveliness tokens present and the latest heartbeat per service, listening ``listen_s`` seconds, and why no
    session could be opened through the router (None when one was)."""
    import zenoh  # start-up time: `jitterguard status` renders its table without a session where it can

    from ..runtime import ZenohOptions, build_config
    from ..schemas import DecodeError, decode, keys
    from ..schemas.models import Heartbeat
    from ..schemas.wire import HEARTBEAT_BOUNDS

    alive: set[str] = set()
    beats: dict[str, Heartbeat] = {}

    def on_beat(sample: Any) -> None:
        try:
            hb = decode(Heartbeat, sample.payload.to_bytes(), **HEARTBEAT_BOUNDS)
        except DecodeError:
            return
        beats[keys.last_chunk(str(sample.key_expr))] = hb

    cfg = build_config(ZenohOptions(ns=ns, connect=(endpoint,), listen=()))
    cfg.insert_json5("mode", json.dumps("client"))
    try:
        session = zenoh.open(cfg)
    except Exception as exc:  # no router reachable: nothing seen on Zenoh
        return alive, beats, (str(exc).splitlines() or [type(exc).__name__])[0].split(" at ")[0]
    try:
        sub = session.declare_subscriber(keys.heartbeat_all(ns), on_beat)
        for reply in session.liveliness().get(keys.alive_all(ns), timeout=min(listen_s, 1.0)):
            if reply.ok is not None:
                alive.add(keys.last_chunk(str(reply.ok.key_expr)))
        deadline = time.monotonic() + listen_s
        while time.monotonic() < deadline:
            time.sleep(0.05)
        sub.undeclare()
    finally:
        session.close()
    return alive, beats, None


SOURCE_PROGRAMS = frozenset({"replay"})
"""Programs that feed the pipeline: while one is not running, no frame enters it. A sensor that is off is no fault
of the services, which stay healthy and ready, so the source's own row says it (and the sidecar's ``/readyz``,
under ``warnings``)."""


def _not_running(proc: ProcessInfo, held_in_s: float | None = None) -> str:
    """Why a program that is not RUNNING is not, in one line: supervisord's state and word for it — or, for one the
    monitor holds back after a crash loop, when it starts again (``held_in_s``: seconds to its next start, negative
    when overdue) —, the last line of its log, and for the source that nothing enters the pipeline. Its progress
    column had said "no heartbeat heard", as of a frozen process, for a replay supervisord had given up on."""
    from .control import tail

    if held_in_s is not None:
        what = (f"backoff (crash loop: held back by the monitor, next start in {held_in_s:.0f} s)" if held_in_s >= 0
                else f"backoff (crash loop: held back by the monitor, its start {-held_in_s:.0f} s overdue)"
                if held_in_s > -HELD_OVERDUE_S else
                f"backoff (crash loop: held back, its start {-held_in_s:.0f} s overdue: is the monitor running?)")
    else:
        what = {"FATAL": "supervisord gave up restarting it", "BACKOFF": "restarting after it exited too quickly",
                "STARTING": "starting", "STOPPED": "stopped", "STOPPING": "stopping",
                "EXITED": "exited"}.get(proc.state, proc.state.lower())
        if proc.state == "EXITED" and proc.exitstatus == EXIT_BAD_INPUT:
            what = f"stopped on bad input (exit status {EXIT_BAD_INPUT}, --on-error stop): not restarted"
        elif proc.state == "EXITED" and proc.exitstatus is not None:
            what += f" (status {proc.exitstatus})"
    last = next((ln.strip() for ln in reversed(tail(proc.logfile, 5)) if ln.strip()), "") if proc.logfile else ""
    if last:
        what += f"; its log ends: {last[:200]}"
    if proc.name in SOURCE_PROGRAMS and proc.state != "STARTING":
        what += "; no frames enter the pipeline"
    return what


HELD_OVERDUE_S = 10.0
"""A held-back program whose next start is this far past was not started by the monitor: it is likely not running."""


def held_back(run_dir: Path | str | None, now: float | None = None) -> dict[str, float]:
    """Program → seconds to its next start (negative: overdue), for each program the monitor holds back after a
    crash loop, as its ``summary.json`` says ({} without one)."""
    if not run_dir:
        return {}
    from .summary import load

    data = load(Path(run_dir)) or {}
    until = (data.get("restarts") or {}).get("held_back_until_s") or {}
    now = time.time() if now is None else now
    try:
        return {str(name): float(t) - now for name, t in until.items()}
    except (TypeError, ValueError):
        return {}


RECENT_EXITS_S = 600.0
"""How far back ``status`` counts a program's unexpected exits (supervisord's log): one that keeps crashing more slowly
than the monitor's crash-loop guard acts on (5 within 60 s) reads RUNNING and ok between its crashes."""


def recent_exits(run_dir: Path | str | None, now: float | None = None) -> dict[str, tuple[int, str]]:
    """Program → (its unexpected exits in the last :data:`RECENT_EXITS_S` of this run, the last one as "exit status
    1, 12 s ago"), from the run directory's ``logs/supervisord.log`` ({} without one)."""
    if not run_dir:
        return {}
    from .summary import supervisor_events

    now = time.time() if now is None else now
    try:
        started = (Path(run_dir) / SPEC_FILE).stat().st_mtime  # the run's own events, not a previous run's
    except OSError:
        return {}
    out: dict[str, tuple[int, str]] = {}
    for name, ev in supervisor_events(Path(run_dir) / "logs" / "supervisord.log", since=started - 0.01).items():
        recent = [(t, why) for t, why in ev.crashes if now - t <= RECENT_EXITS_S]
        if recent:
            t, why = recent[-1]
            out[name] = (len(recent), f"{why}, {max(0.0, now - t):.0f} s ago")
    return out


def frozen_counts(run_dir: Path | str | None) -> dict[str, int]:
    """Program → how often it was ended frozen this run: ``summary.json``'s ``restarts.frozen_restarts``, with the
    monitor's own count read from the monitor-watch's file (the summary has it only once a new monitor writes)."""
    if not run_dir:
        return {}
    from .summary import load
    from .watch import load_counts

    restarts = (load(Path(run_dir)) or {}).get("restarts")
    counts = restarts.get("frozen_restarts") if isinstance(restarts, dict) else None
    try:
        out = {str(k): int(v) for k, v in counts.items()} if isinstance(counts, dict) else {}
    except (TypeError, ValueError):
        out = {}
    out.update(load_counts(Path(run_dir)))
    return out


def collect(procs: list[ProcessInfo], spec: StackSpec | None, listen_s: float = 1.5) -> list[ServiceStatus]:
    rows = rows_from_processes(procs)
    held = held_back(spec.run_dir if spec else None)
    exits = recent_exits(spec.run_dir if spec else None)
    frozen = frozen_counts(spec.run_dir if spec else None)
    for row in rows:
        row.recent_exits, row.last_exit = exits.get(row.name, (0, ""))
        row.frozen_restarts = frozen.get(row.name, 0)
    for row, proc in zip(rows, procs):
        if proc.state in ("STOPPED", "STOPPING") and proc.name in held:
            row.held_back_s = round(held[proc.name], 1)
            row.problem = _not_running(proc, held[proc.name])
        elif proc.state != "RUNNING":
            row.problem = _not_running(proc)
    if spec is None:
        return rows
    from ..runtime.service import HEARTBEAT_PERIOD_S

    alive, beats, unreachable = probe_zenoh(spec.ns, spec.endpoint, listen_s)
    for row in rows:
        if row.name == "router":
            # The router has no token of its own: it is up on Zenoh if anything answered through it.
            row.alive = bool(alive or beats)
            if unreachable is not None and not row.problem:
                row.problem = f"not answering on {spec.endpoint}: no Zenoh session through it ({unreachable})"
            continue
        if row.name in OFF_BUS:
            continue
        # a service cannot be heard through a router that cannot be reached: that says nothing of the service
        # itself (every one had read "no heartbeat heard", as if frozen, while the router was the one stopped)
        row.heartbeat_expected = unreachable is None and listen_s >= 1.2 * HEARTBEAT_PERIOD_S
        names = SERVICE_NAMES.get(row.name, (row.name,))  # the program `replay` runs feed-tracks at --input tracks
        row.alive = any(n in alive for n in names)
        hb = next((beats[n] for n in names if n in beats), None)
        if hb is not None:
            row.last_seq = hb.last_seq
            row.heartbeat_uptime_s = round(hb.uptime_s, 1)
            row.heartbeat_pid = hb.pid
            row.health, row.health_reason = hb.health, hb.health_reason
            row.counters = dict(hb.counters)
    return rows


def _fmt_uptime(s: float | None) -> str:
    from .summary import hms

    return "-" if s is None else hms(s)


def render_table(rows: list[ServiceStatus], spec: StackSpec | None, run_dir: Path) -> None:
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    title = (f"jitterguard stack {spec.name!r} (ns {spec.ns}) via {spec.endpoint}" if spec
             else f"jitterguard stack in {run_dir}")
    console = Console()
    if not console.is_terminal:  # one line per service however long its reason: `grep`/`awk` read the pipe
        console = Console(width=4096)
    # A terminal gets a boxed table; a pipe gets plain aligned columns, one service per line starting with its
    # name (as `supervisorctl status` prints), so `grep`/`awk` keep working.
    table = Table(title=title) if console.is_terminal else Table(title=title, box=None, pad_edge=False)
    for col in ("service", "state", "pid", "uptime", "zenoh alive", "last seq", "progress"):
        table.add_column(col, justify="right" if col in ("pid", "uptime", "last seq") else "left")
    for r in rows:
        color = ("green" if r.state == "RUNNING" else
                 "yellow" if r.state in ("STARTING", "BACKOFF") or r.held_back_s is not None else "red")
        alive = "-" if r.alive is None else ("[green]yes[/]" if r.alive else "[red]no[/]")
        seq = "-" if r.last_seq is None else ("none yet" if r.last_seq < 0 else str(r.last_seq))
        # a problem: a program not running, or (running, no health of its own) the router not answering
        progress = (f"[red]{escape(r.problem)}[/]" if r.problem and (r.state != "RUNNING" or r.health is None) else
                    ("-" if r.heard else "[red]no heartbeat heard[/]") if r.health is None else
                    ("[green]ok[/]" if r.health == "ok" else f"[red]{r.health}[/]: {escape(r.health_reason)}"))
        if r.recent_exits:  # restarted: said beside its progress, not only in the summary
            progress += (f"; [yellow]restarted after {r.recent_exits} unexpected exit"
                         f"{'s' if r.recent_exits > 1 else ''} in {RECENT_EXITS_S / 60:.0f} min "
                         f"(last: {escape(r.last_exit)})[/]")
        if r.frozen_restarts:
            progress += (f"; [yellow]ended frozen {r.frozen_restarts} time{'s' if r.frozen_restarts > 1 else ''} "
                         "this run[/]")
        table.add_row(r.name, f"[{color}]{r.state}[/]", str(r.pid or "-"), _fmt_uptime(r.uptime_s), alive, seq,
                      progress)
    console.print(table)
