"""The run's summary: frames, tracks born and ended, static/dynamic decisions, rejections, drops and restarts.

Built from what the services themselves report (health means progress): every service's heartbeat carries its
counters, which start again at zero when the process restarts. :class:`Ledger` keeps the last counters of every
process (by pid) and sums them per service, so a service restarted five times still adds up to the whole run.
The stack's ``monitor`` program (:mod:`.monitor`) feeds one and keeps it in ``summary.json`` in the run
directory; supervisord's own log says how often each program was started and how often it died unexpectedly.

Pure apart from :func:`supervisor_events` (reads the log) and :func:`load` / :func:`save` (the file).
"""

from __future__ import annotations

import json
import re
import threading
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

from ..files import write_atomically
from ..runtime.exit_codes import EXIT_BAD_INPUT

SUMMARY_FILE = "summary.json"
GAUGE_PREFIXES = ("now.",)
GAUGE_SUFFIXES = ("_last",)
"""Counters that are a current value, not a running count: the newest process's value, never summed."""
DROP_WORDS = frozenset({"dropped", "skipped", "shed", "late", "orphaned", "missing", "overflow"})
"""A counter whose name holds one of these words (split at ``.`` and ``_``) counts something lost."""
_WORD = re.compile(r"[._]")


def is_gauge(name: str) -> bool:
    return name.startswith(GAUGE_PREFIXES) or name.endswith(GAUGE_SUFFIXES)


def is_drop(name: str) -> bool:
    return not is_gauge(name) and bool(DROP_WORDS.intersection(_WORD.split(name)))


def is_error(name: str) -> bool:
    return name.endswith("errors")


MAX_SERVICES = 64
"""Services a ledger keeps (a stack has about ten): heartbeats of further names are refused, so that a flood of
made-up names (anyone on the host may publish) cannot grow the monitor or ``summary.json`` without bound."""
MAX_PROCESSES = 32
"""Processes kept one by one per service; the counters of older ones are folded into one record (:data:`RETIRED`),
so a service restarted a thousand times still adds up exactly, in bounded memory."""
MAX_COUNTER_NAMES = 512
"""Counter names a service's :data:`RETIRED` record keeps (a service reports a few dozen): each process's own
record is bounded by its heartbeat's size, but the retired one took every name any process had ever sent, and a
made-up service whose every heartbeat came from a new pid with new names grew it by megabytes. Counts of names
beyond the bound are added to ``counts_of_unkept_names``."""
RETIRED = -1
"""The pseudo-pid under which a service's retired processes' running counters are summed (no real pid is < 0)."""
MAX_LEDGER_BYTES = 2 * 2**20
"""About the most the ledger's counters may take in ``summary.json`` (names and values, every process's record and
every retired one; a real stack's take a few KB, ~300 KB with every service restarted 32 times). Beyond it a
heartbeat that would add a process, or grow one's record by more than :data:`GROWTH_SLACK_BYTES`, is refused. The
bounds on services, processes and heartbeat entries alone had let 64 made-up services of 32 pids each, 512 counters
of 490-character names apiece, make a 530 MB ``summary.json``, rewritten every second."""
GROWTH_SLACK_BYTES = 1024
"""How much a process's record may still grow past :data:`MAX_LEDGER_BYTES` (a real service's new counter names)."""
_ENTRY_BYTES = 24  # a counter's value and JSON punctuation, beside its name
_RECORD_BYTES = 96  # a record's stamp, last seq, uptime and JSON punctuation


def _cost(rec: dict[str, Any]) -> int:
    return _RECORD_BYTES + sum(len(k) + _ENTRY_BYTES for k in rec.get("counters", {}))


RESTART_UPTIME_SLACK_S = 1.0
"""A heartbeat of a known pid whose uptime is this much below the last one's is a new process's (uptimes are kept
to 0.1 s)."""


def _restarted(last_uptime: Any, uptime: Any) -> bool:
    try:
        return float(uptime) + RESTART_UPTIME_SLACK_S < float(last_uptime)
    except (TypeError, ValueError):
        return False


@dataclass
class Ledger:
    """Per service and process: the last heartbeat counters seen (and when); bounded (:data:`MAX_SERVICES`,
    :data:`MAX_PROCESSES`)."""

    procs: dict[str, dict[int, dict[str, Any]]] = field(default_factory=dict)
    size: int = 0  # what its records take (:func:`_cost`), kept against MAX_LEDGER_BYTES
    own: set[str] = field(default_factory=set)  # services heard with ``own=True``: never evicted
    evicted: int = 0  # services evicted to make room for the stack's own (:meth:`observe`)

    def observe(self, service: str, pid: int, counters: dict[str, int], stamp_ns: int,
                extra: dict[str, Any] | None = None, own: bool = False) -> bool:
        """Record one heartbeat; an older one than the last seen for that process is ignored. False when it is
        refused: a new service beyond :data:`MAX_SERVICES`, or a record past :data:`MAX_LEDGER_BYTES`. A newer
        heartbeat of the same pid whose ``uptime_s`` (in ``extra``) is smaller than the last one's comes from a new
        process that was given the old one's pid (a container's service runs as pid 1 every time; a pid space that
        wrapped): the old process is retired, its counts kept, before the new one is recorded. It had replaced the
        old record, every count before the restart lost from the run's totals.

        ``own``: the service is one of the stack's programs. Where a bound would refuse its heartbeat, the services
        not heard as the stack's own are evicted, first heard first, until it fits (counted in :attr:`evicted`). A
        flood of made-up names (anyone on the host may publish a heartbeat) had filled both bounds, and every
        process of a real service started after it — a restarted classifier — was refused: its counts, and the
        restart, missing from the run's summary."""
        if own:
            self.own.add(service)
        slot = self.procs.get(service)
        if slot is None and len(self.procs) >= MAX_SERVICES and not (own and self._evict_one()):
            return False
        last = slot.get(pid) if slot is not None else None
        if last is not None and last["stamp_ns"] > stamp_ns:
            return True
        restarted = last is not None and _restarted(last.get("uptime_s"), (extra or {}).get("uptime_s"))
        rec = {"stamp_ns": int(stamp_ns), "counters": dict(counters), **(extra or {})}
        added = _cost(rec) - (_cost(last) if last is not None and not restarted else 0)
        while self.size + added > MAX_LEDGER_BYTES and (last is None or restarted or added > GROWTH_SLACK_BYTES):
            if not (own and self._evict_one()):
                return False
        if slot is None:
            slot = self.procs[service] = {}
        if restarted:
            self._retire(slot, pid)
            last = None
        if last is None and sum(1 for p in slot if p != RETIRED) >= MAX_PROCESSES:
            self._retire(slot, min((p for p in slot if p != RETIRED), key=lambda p: slot[p]["stamp_ns"]))
        self.size += _cost(rec) - (_cost(last) if last is not None else 0)
        slot[pid] = rec
        return True

    def _evict_one(self) -> bool:
        """Drop the service first heard of those not the stack's own (:meth:`observe`), with every record it has;
        False when there is none."""
        victim = next((svc for svc in self.procs if svc not in self.own), None)
        if victim is None:
            return False
        self.size -= sum(_cost(rec) for rec in self.procs.pop(victim).values())
        self.evicted += 1
        return True

    def _retire(self, slot: dict[int, dict[str, Any]], pid: int) -> None:
        """Fold a process that has ended (the one heard from longest ago, or one whose pid a new process now has)
        into the service's :data:`RETIRED` record (which never takes more than the record folded into it did)."""
        rec = slot.pop(pid)
        ret = slot.setdefault(RETIRED, {"stamp_ns": 0, "counters": {}, "processes": 0})
        self.size -= _cost(rec) + _cost(ret)
        kept = ret["counters"]
        for k, v in rec["counters"].items():
            if is_gauge(k):
                continue
            if k not in kept and len(kept) >= MAX_COUNTER_NAMES:
                k = "counts_of_unkept_names"
            kept[k] = kept.get(k, 0) + int(v)
        ret["processes"] = int(ret.get("processes", 0)) + int(rec.get("processes", 1))
        self.size += _cost(ret)

    def totals(self, service: str) -> dict[str, int]:
        """Running counters summed over the service's processes; gauges from its newest process."""
        slot = self.procs.get(service, {})
        out: dict[str, int] = {}
        newest = max(slot.values(), key=lambda r: r["stamp_ns"], default=None)
        for rec in slot.values():
            for k, v in rec["counters"].items():
                if not is_gauge(k):
                    out[k] = out.get(k, 0) + int(v)
        if newest is not None:
            out.update({k: int(v) for k, v in newest["counters"].items() if is_gauge(k)})
        return out

    def processes(self, service: str) -> int:
        return sum(int(r.get("processes", 1)) for r in self.procs.get(service, {}).values())

    def as_json(self) -> dict[str, Any]:
        return {svc: {str(pid): rec for pid, rec in slot.items()} for svc, slot in self.procs.items()}

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> "Ledger":
        led = cls()
        for svc, slot in data.items():
            led.procs[svc] = {int(pid): dict(rec) for pid, rec in slot.items()}
            led.size += sum(_cost(rec) for rec in led.procs[svc].values())
        return led


_LOG_TIME = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d),(\d{3}) ")
SPAWNED = re.compile(r"spawned: '([^']+)' with pid (\d+)")
_EXITED = re.compile(r"exited: (\S+) \((.*); not expected\)")
_EXITED_EXPECTED = re.compile(r"exited: (\S+) \((.*); expected\)")
_FATAL = re.compile(r"gave up: (\S+) entered FATAL state")
_RUNNING = re.compile(r"success: (\S+) entered RUNNING state")


@dataclass
class ProgramEvents:
    """From supervisord's log: when each program was spawned, died unexpectedly, or was given up on."""

    spawns: list[float] = field(default_factory=list)
    crashes: list[tuple[float, str]] = field(default_factory=list)  # (time, "exit status 1") of unexpected exits
    fatal: bool = False
    running_crashes: list[float] = field(default_factory=list)
    """The times of the unexpected exits of a process that had reached RUNNING (lived ``startsecs``): those that
    supervisord's own back-off does not cover (it restarts such a program at once, for ever); the stack's monitor
    holds a program back when they come too often (:mod:`.backoff`)."""
    running: bool = False  # its current process has reached RUNNING (what the log said last)
    exited_as_expected: str | None = None
    """Its current process exited with a status its ``exitcodes`` list ("exit status 65"), and it has not been
    spawned since: with ``autorestart=unexpected`` it stays down (the stack's replay stopped on bad input)."""

    @property
    def restarts(self) -> int:
        return max(0, len(self.spawns) - 1)


def log_files(log_path: Path) -> list[Path]:
    """supervisord's log and the rotated copies it keeps (``.3`` oldest), oldest first."""
    return [log_path.with_name(f"{log_path.name}.{i}") for i in (3, 2, 1)] + [log_path]


def supervisor_events(log_path: Path, since: float = 0.0) -> dict[str, ProgramEvents]:
    """Parse supervisord's log (and its rotated ``.1``–``.3``) for events at or after ``since`` (epoch s)."""
    out: dict[str, ProgramEvents] = {}
    for path in log_files(log_path):
        try:
            text = path.read_text(errors="replace")
        except OSError:
            continue
        for line in text.splitlines():
            m = _LOG_TIME.match(line)
            if not m:
                continue
            t = datetime.strptime(m.group(1), "%Y-%m-%d %H:%M:%S").timestamp() + int(m.group(2)) / 1000
            if t < since:
                continue
            if (s := SPAWNED.search(line)) is not None:
                ev = out.setdefault(s.group(1), ProgramEvents())
                ev.spawns.append(t)
                ev.fatal = False  # started again since supervisord gave up on it (`supervisorctl start`)
                ev.running = False
                ev.exited_as_expected = None
            elif (r := _RUNNING.search(line)) is not None:
                out.setdefault(r.group(1), ProgramEvents()).running = True
            elif (e := _EXITED.search(line)) is not None:
                ev = out.setdefault(e.group(1), ProgramEvents())
                ev.crashes.append((t, e.group(2)))
                if ev.running:
                    ev.running_crashes.append(t)
                ev.running = False
            elif (x := _EXITED_EXPECTED.search(line)) is not None:
                ev = out.setdefault(x.group(1), ProgramEvents())
                ev.exited_as_expected = x.group(2)
                ev.running = False
            elif (f := _FATAL.search(line)) is not None:
                out.setdefault(f.group(1), ProgramEvents()).fatal = True
    return out


class SupervisorLog:
    """supervisord's log, parsed again only when it changed: the monitor asks for its events from two threads (the
    summary writer every second, the crash-loop look every two), and a log unchanged since the last look — nearly
    every look — costs four ``stat`` calls instead of a parse of up to four rotated files."""

    def __init__(self, log_path: Path, since: float = 0.0) -> None:
        self.log_path, self.since = log_path, since
        self._paths = log_files(log_path)
        self._lock = threading.Lock()
        self._key: tuple[tuple[int, int] | None, ...] | None = None
        self._events: dict[str, ProgramEvents] = {}

    def _stat_key(self) -> tuple[tuple[int, int] | None, ...]:
        out: list[tuple[int, int] | None] = []
        for path in self._paths:
            try:
                st = path.stat()
            except OSError:
                out.append(None)
            else:
                out.append((st.st_size, st.st_mtime_ns))
        return tuple(out)

    def events(self) -> dict[str, ProgramEvents]:
        """:func:`supervisor_events` of the log since ``since`` (the same dict while the files are unchanged: read it,
        do not change it)."""
        with self._lock:
            key = self._stat_key()
            if key != self._key:
                self._events, self._key = supervisor_events(self.log_path, since=self.since), key
            return self._events


def crash_loop(events: dict[str, ProgramEvents], now: float, *, crashes: int = 3, window_s: float = 60.0
               ) -> str | None:
    """The name of a program that supervisord gave up on, or that died unexpectedly ``crashes`` times within
    the last ``window_s`` seconds (a SIGKILL now and then is healing, not a loop); None if there is none."""
    for name, ev in sorted(events.items()):
        if ev.fatal or sum(1 for t, _ in ev.crashes if now - t <= window_s) >= crashes:
            return name
    return None


BAD_INPUT_EXIT = f"exit status {EXIT_BAD_INPUT}"


def stopped_on_bad_input(events: dict[str, ProgramEvents]) -> list[str]:
    """The programs that stopped on bad input (exit status :data:`~jitterguard.runtime.service.EXIT_BAD_INPUT`,
    ``replay --on-error stop``) and were not started since: down for good, deliberately, not crashed."""
    return sorted(name for name, ev in events.items() if ev.exited_as_expected == BAD_INPUT_EXIT)


def _pick(totals: dict[str, int] | None, name: str) -> int | None:
    """A service's counter; 0 if the service reported but never counted it, None if it never reported."""
    return None if totals is None else int(totals.get(name, 0))


def frozen_restarts(monitor_counters: dict[str, int] | None, watched: dict[str, int] | None) -> dict[str, int]:
    """Program → how often it was ended frozen this run: the monitor's ``frozen_restarts.<program>`` counters (every
    monitor process of the run, summed by the ledger) and the monitor-watch's count of monitors ended stopped
    (:func:`.watch.load_counts`). One place to read both: the monitor's own had been only among its raw counters."""
    out = {k.split(".", 1)[1]: int(v) for k, v in (monitor_counters or {}).items()
           if k.startswith("frozen_restarts.") and v}
    for name, n in (watched or {}).items():
        if n:
            out[name] = out.get(name, 0) + int(n)
    return dict(sorted(out.items()))


def build(ledger: Ledger, events: dict[str, ProgramEvents], *, meta: dict[str, Any],
          backoff: dict[str, Any] | None = None, watched: dict[str, int] | None = None) -> dict[str, Any]:
    """The summary as a JSON-able dict (``meta``: stack name, ns, source, start and end times…; ``backoff``: the
    monitor's crash-loop guard, :meth:`.backoff.CrashLoopGuard.as_json`; ``watched``: the monitor-watch's counts,
    :func:`.watch.load_counts`)."""
    backoff = backoff or {}
    held = dict(backoff.get("held_back_until_s") or {})
    t = {svc: ledger.totals(svc) for svc in ledger.procs}
    # the source's frames: the replay's puts (one per frame), or feed-tracks' frames at --input tracks (its puts
    # are a frame's every tracks/{id} and its tracked: 1,824 "replayed" for ~150 frames)
    # (or, with live ROS 2 in the replay's place, the scans ros2-in published)
    source = next((svc for svc in ("replay", "ros2-in", "feed-tracks") if svc in t), None)
    replayed = _pick(t.get(source), "frames" if source == "feed-tracks" else "published")
    det, trk, cls = (t.get(s) for s in ("detector", "tracker", "classifier"))
    rejected = {svc: c["rejected"] for svc, c in sorted(t.items()) if c.get("rejected")}
    dropped = {f"{svc}.{k}": v for svc, c in sorted(t.items()) for k, v in sorted(c.items()) if v and is_drop(k)}
    errors = {f"{svc}.{k}": v for svc, c in sorted(t.items()) for k, v in sorted(c.items()) if v and is_error(k)}
    programs = {name: ev.restarts for name, ev in sorted(events.items()) if ev.restarts}
    crashes = {name: len(ev.crashes) for name, ev in sorted(events.items()) if ev.crashes}
    return {
        **meta,
        "frames": {"replayed": replayed, "source": source, "detected": _pick(det, "scans"),
                   "tracked": _pick(trk, "frames"), "classified": _pick(cls, "frames_processed")},
        # born/ended count tentative tracks too — a detector's low-score clutter starts dozens a frame that never
        # reach the output — so the confirmed ones are said beside them (an operator read "born 11,944" in a
        # 37 s run of ~70 objects as a tracker losing its objects)
        "tracks": {"born": _pick(trk, "tracks_born"), "ended": _pick(trk, "tracks_deleted"),
                   "confirmed": _pick(trk, "tracks_confirmed"), "confirmed_ended": _pick(trk, "confirmed_tracks_deleted")},
        "objects": {"static": _pick(cls, "objects.static"), "dynamic": _pick(cls, "objects.dynamic"),
                    "undecided": _pick(cls, "objects.undecided"), "vetoed": _pick(cls, "objects.vetoed"),
                    "static_now": _pick(cls, "now.static"), "dynamic_now": _pick(cls, "now.dynamic")},
        "rejected": rejected,
        "rejected_total": sum(rejected.values()),
        "dropped": dropped,
        "dropped_total": sum(dropped.values()),
        "errors": errors,
        "restarts": {
            "programs": programs,
            "unexpected_exits": crashes,
            # programs supervisord gave up on and that have not been started since: dead for the rest of the run
            # (the counts above had said "replay 21" for a source that had stopped for good)
            "gave_up": sorted(name for name, ev in events.items() if ev.fatal),
            # programs that stopped on bad input (replay --on-error stop) and are deliberately not restarted
            "stopped_on_bad_input": stopped_on_bad_input(events),
            # the monitor's crash-loop guard: how often each program was held back after crashing again and again
            # once RUNNING, which are held back now and when each is started again (epoch s)
            "backed_off": dict(backoff.get("backed_off") or {}),
            "held_back": sorted(held),
            "held_back_until_s": held,
            # programs ended frozen (SIGSTOP, a freezer): by the monitor, and the monitor by the monitor-watch
            "frozen_restarts": frozen_restarts(t.get("monitor"), watched),
            "source_restarts": _pick(trk, "source_restarts"),
            "tracker_resets": _pick(trk, "resets"),
            "classifier_upstream_restarts": _pick(cls, "frames.upstream_restarts"),
        },
        "services": {svc: {"processes": ledger.processes(svc), "counters": c} for svc, c in sorted(t.items())},
    }


def hms(s: float) -> str:
    """A duration as hours, minutes and seconds (``2:03:07``): `status`'s uptimes, a summary's run of a minute or
    more."""
    t = int(s)
    return f"{t // 3600}:{t % 3600 // 60:02d}:{t % 60:02d}"


def render(summary: dict[str, Any]) -> str:
    """The summary as a few lines for a terminal or a log."""

    def n(v: Any) -> str:
        return "-" if v is None else f"{v:,}" if isinstance(v, int) else str(v)

    def kv(d: dict[str, Any]) -> str:
        return ", ".join(f"{k} {n(v)}" for k, v in d.items()) or "none"

    def section(name: str, within: dict[str, Any] = summary) -> dict[str, Any]:
        """One part; missing or not a mapping (another version's file, one edited by hand) it shows as "-"s: a
        KeyError or TypeError had ended `summary`, `down` and a foreground `up` in a traceback."""
        value = within.get(name)
        return value if isinstance(value, dict) else {}

    fr, tr, ob, rs = section("frames"), section("tracks"), section("objects"), section("restarts")
    exits = section("unexpected_exits", rs)
    dur = summary.get("duration_s")
    dur = dur if isinstance(dur, (int, float)) else None
    head = f"run summary of stack {summary.get('stack', '?')!r}" + (f" ({dur:.1f} s)" if dur is not None and dur < 59.95
                                                                     else f" ({hms(dur)})" if dur is not None else "")
    lines = [
        head,
        f"  frames    {'from ROS 2' if fr.get('source') == 'ros2-in' else 'replayed'} {n(fr.get('replayed'))},"
        f" detected {n(fr.get('detected'))}, tracked {n(fr.get('tracked'))},"
        f" classified {n(fr.get('classified'))}",
        f"  tracks    born {n(tr.get('born'))} ({n(tr.get('confirmed'))} confirmed), ended {n(tr.get('ended'))}"
        f" ({n(tr.get('confirmed_ended'))} confirmed)",
        f"  objects   static {n(ob.get('static'))} (jump veto {n(ob.get('vetoed'))}), dynamic {n(ob.get('dynamic'))},"
        f" undecided {n(ob.get('undecided'))} (object-frames)"
        + (f"; last frame: {n(ob.get('static_now'))} static, {n(ob.get('dynamic_now'))} dynamic"
           if ob.get("static_now") is not None else ""),
        f"  rejected  {kv(section('rejected'))}",
        f"  dropped   {kv(section('dropped'))}",
        f"  restarts  {kv(section('programs', rs))}" + (f"; unexpected exits: {kv(exits)}" if exits else "")
        + (f"; supervisord gave up on: {', '.join(rs['gave_up'])}" if rs.get("gave_up") else "")
        + (f"; stopped on bad input (not restarted): {', '.join(rs['stopped_on_bad_input'])}"
           if rs.get("stopped_on_bad_input") else "")
        + (f"; held back after crash loops: {kv(rs['backed_off'])}" if rs.get("backed_off") else "")
        + (f" (now: {', '.join(rs['held_back'])})" if rs.get("held_back") else "")
        + (f"; ended frozen: {kv(rs['frozen_restarts'])}" if isinstance(rs.get("frozen_restarts"), dict)
           and rs["frozen_restarts"] else "")
        + f"; source restarts {n(rs.get('source_restarts'))}, tracker resets {n(rs.get('tracker_resets'))}",
    ]
    if section("errors"):
        lines.append(f"  errors    {kv(section('errors'))}")
    return "\n".join(lines)


def save(run_dir: Path, data: dict[str, Any]) -> None:
    """Write ``summary.json`` atomically (a reader never sees half a file)."""
    write_atomically(run_dir / SUMMARY_FILE, (json.dumps(data, indent=2, sort_keys=True) + "\n").encode(),
                     durable=False)


def load(run_dir: Path) -> dict[str, Any] | None:
    """``summary.json`` of ``run_dir``; None if there is none, or it is not a JSON object (`status` and `summary`
    had ended in a traceback on one)."""
    try:
        data = json.loads((run_dir / SUMMARY_FILE).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None
