"""``jitterguard status``: what supervisord says about each program, plus what Zenoh says about each service.

supervisord knows the process (state, pid, uptime); Zenoh knows whether the service is actually on the bus
(liveliness token on ``alive/{service}``) and whether frames are flowing (``last_seq`` of the heartbeat on
``heartbeat/{service}``). Both views come from a run directory that ``jitterguard up`` wrote, including the
``stack.json`` that records the namespace and router endpoint.
"""

from __future__ import annotations

import dataclasses
import json
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .supervisor import StackSpec

SPEC_FILE = "stack.json"
_LINE = re.compile(r"^(?P<name>\S+)\s+(?P<state>[A-Z]+)\s*(?P<rest>.*)$")
_UPTIME = re.compile(r"uptime (?:(?P<d>\d+) days?, )?(?P<h>\d+):(?P<m>\d+):(?P<s>\d+)")
_PID = re.compile(r"pid (\d+)")


def save_spec(run_dir: Path, spec: StackSpec) -> Path:
    path = run_dir / SPEC_FILE
    path.write_text(json.dumps(dataclasses.asdict(spec), indent=2) + "\n")
    return path


def load_spec(run_dir: Path) -> StackSpec | None:
    path = run_dir / SPEC_FILE
    if not path.is_file():
        return None
    data = json.loads(path.read_text())
    known = {f.name for f in dataclasses.fields(StackSpec)}
    return StackSpec(**{k: v for k, v in data.items() if k in known})


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

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def parse_supervisorctl(text: str) -> list[ServiceStatus]:
    """Parse ``supervisorctl status`` lines: ``name  RUNNING   pid 123, uptime 0:01:02``."""
    out = []
    for line in text.splitlines():
        m = _LINE.match(line.strip())
        if not m:
            continue
        rest = m.group("rest")
        st = ServiceStatus(name=m.group("name"), state=m.group("state"), detail=rest.strip())
        if (p := _PID.search(rest)) is not None:
            st.pid = int(p.group(1))
        if (u := _UPTIME.search(rest)) is not None:
            st.uptime_s = float(int(u.group("d") or 0) * 86400 + int(u.group("h")) * 3600
                                + int(u.group("m")) * 60 + int(u.group("s")))
        out.append(st)
    return out


def probe_zenoh(ns: str, endpoint: str, listen_s: float = 1.5) -> tuple[set[str], dict[str, Any]]:
    """Liveliness tokens present and the latest heartbeat per service, listening ``listen_s`` seconds."""
    import zenoh

    from ..runtime import ZenohOptions, build_config
    from ..schemas import DecodeError, decode, keys
    from ..schemas.models import Heartbeat

    alive: set[str] = set()
    beats: dict[str, Heartbeat] = {}

    def on_beat(sample: Any) -> None:
        try:
            hb = decode(Heartbeat, sample.payload.to_bytes())
        except DecodeError:
            return
        beats[keys.last_chunk(str(sample.key_expr))] = hb

    cfg = build_config(ZenohOptions(ns=ns, connect=(endpoint,), listen=()))
    cfg.insert_json5("mode", json.dumps("client"))
    try:
        session = zenoh.open(cfg)
    except Exception:  # no router reachable: nothing seen on Zenoh
        return alive, beats
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
    return alive, beats


def collect(sup_text: str, spec: StackSpec | None, listen_s: float = 1.5) -> list[ServiceStatus]:
    rows = parse_supervisorctl(sup_text)
    if spec is None:
        return rows
    alive, beats = probe_zenoh(spec.ns, spec.endpoint, listen_s)
    for row in rows:
        if row.name == "router":
            # The router has no token of its own: it is up on Zenoh if anything answered through it.
            row.alive = bool(alive or beats)
            continue
        row.alive = row.name in alive
        hb = beats.get(row.name)
        if hb is not None:
            row.last_seq = hb.last_seq
            row.heartbeat_uptime_s = round(hb.uptime_s, 1)
            row.heartbeat_pid = hb.pid
            row.health, row.health_reason = hb.health, hb.health_reason
            row.counters = dict(hb.counters)
    return rows


def _fmt_uptime(s: float | None) -> str:
    if s is None:
        return "-"
    s = int(s)
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"


def render_table(rows: list[ServiceStatus], spec: StackSpec | None, run_dir: Path) -> None:
    from rich.console import Console
    from rich.table import Table

    title = f"jitterguard stack {spec.ns!r} via {spec.endpoint}" if spec else f"jitterguard stack in {run_dir}"
    console = Console()
    # A terminal gets a boxed table; a pipe gets plain aligned columns, one service per line starting with its
    # name (as `supervisorctl status` prints), so `grep`/`awk` keep working.
    table = Table(title=title) if console.is_terminal else Table(title=title, box=None, pad_edge=False)
    for col in ("service", "state", "pid", "uptime", "zenoh alive", "last seq", "progress"):
        table.add_column(col, justify="right" if col in ("pid", "uptime", "last seq") else "left")
    for r in rows:
        color = "green" if r.state == "RUNNING" else ("yellow" if r.state in ("STARTING", "BACKOFF") else "red")
        alive = "-" if r.alive is None else ("[green]yes[/]" if r.alive else "[red]no[/]")
        seq = "-" if r.last_seq is None else ("none yet" if r.last_seq < 0 else str(r.last_seq))
        progress = "-" if r.health is None else ("[green]ok[/]" if r.health == "ok" else
                                                 f"[red]{r.health}[/]: {r.health_reason}")
        table.add_row(r.name, f"[{color}]{r.state}[/]", str(r.pid or "-"), _fmt_uptime(r.uptime_s), alive, seq,
                      progress)
    console.print(table)
