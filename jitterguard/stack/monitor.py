"""The stack's ``monitor`` program: hears every service's heartbeat and keeps the run's summary in the run
directory (``summary.json``, rewritten atomically every second and once more on shutdown).

Why a program of its own: a detached stack has no ``jitterguard up`` process waiting on it, and each service's
counters start again at zero when supervisord restarts it. The monitor keeps the last counters of every process
(:class:`~.summary.Ledger`), so ``jitterguard summary`` — or the end of a foreground ``up`` — adds up the whole
run, restarts included. It is started first and stopped last, and every service sends a final heartbeat as it
closes, so the file ends with the final counts. If the monitor itself is restarted it reads the file back.
"""

from __future__ import annotations

import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Annotated, Any

import typer
import zenoh

from ..cli_common import ConnectOpt, ListenOpt, LogLevelOpt, NsOpt, ZenohConfigOpt, fail, zenoh_options
from ..runtime import Service, ZenohOptions, setup_logging
from ..schemas import DecodeError, decode, keys
from ..schemas.models import Heartbeat
from . import summary
from .status import SPEC_FILE, load_spec

WRITE_PERIOD_S = 1.0


def _iso(t: float) -> str:
    return datetime.fromtimestamp(t, timezone.utc).isoformat(timespec="seconds")


def _spec_written_at(run_dir: Path) -> float | None:
    """When ``up`` wrote stack.json, just before it started supervisord: the run's start."""
    try:
        return (run_dir / SPEC_FILE).stat().st_mtime
    except OSError:
        return None


class StackMonitor(Service):
    name = "monitor"

    def __init__(self, opts: ZenohOptions, run_dir: Path) -> None:
        self.run_dir = run_dir
        prev = summary.load(run_dir) or {}
        self.ledger = summary.Ledger.from_json(prev.get("ledger", {}))
        self.run_started_at = float(prev.get("started_at_s") or _spec_written_at(run_dir) or time.time())
        self.dirty = True
        super().__init__(opts)
        self._declared.append(self.session.declare_subscriber(keys.heartbeat_all(self.ns), self._on_beat))
        self.spawn(self._writer, "writer")

    def _on_beat(self, sample: zenoh.Sample) -> None:
        try:
            hb = decode(Heartbeat, sample.payload.to_bytes())
        except DecodeError as exc:
            self.reject(exc, keys.heartbeat_all(self.ns), str(sample.key_expr))
            return
        self.counters.inc("received")
        extra = {"last_seq": hb.last_seq, "uptime_s": round(hb.uptime_s, 1)}
        if not self.ledger.observe(hb.service, hb.pid, hb.counters, hb.stamp, extra):
            self.counters.inc("heartbeats_dropped")  # a service beyond the ledger's bound (summary.MAX_SERVICES)
            return
        self.dirty = True

    def snapshot(self) -> dict[str, Any]:
        spec = load_spec(self.run_dir)
        now = time.time()
        # the run's own events: stack.json is written before supervisord starts (the log keeps milliseconds; a
        # look-back of seconds counted the previous run's last crashes in a run dir used again at once)
        events = summary.supervisor_events(self.run_dir / "logs" / "supervisord.log", since=self.run_started_at - 0.01)
        meta = {"stack": spec.name if spec else self.run_dir.name, "ns": self.ns,
                "source": (spec.source if spec else None), "started_at": _iso(self.run_started_at),
                "updated_at": _iso(now), "duration_s": round(now - self.run_started_at, 1)}
        return {**summary.build(self.ledger, events, meta=meta), "started_at_s": self.run_started_at,
                "ledger": self.ledger.as_json()}

    def write(self) -> None:
        summary.save(self.run_dir, self.snapshot())
        self.dirty = False

    def _writer(self) -> None:
        while not self.stop_event.wait(WRITE_PERIOD_S):
            if self.dirty:
                try:
                    self.write()
                except OSError:
                    self.log.exception("cannot write %s", self.run_dir / summary.SUMMARY_FILE)

    def on_close(self) -> None:
        time.sleep(0.3)  # the final heartbeats of the services stopped just before us may still be on the way
        try:
            self.write()
        except OSError:
            self.log.exception("cannot write %s", self.run_dir / summary.SUMMARY_FILE)


def monitor_command(
    run_dir: Annotated[Path, typer.Option("--run-dir", help="The stack's run directory (summary.json goes there).")],
    log_level: LogLevelOpt = "INFO",
    ns: NsOpt = "default",
    zenoh_config: ZenohConfigOpt = None,
    connect: ConnectOpt = None,
    listen: ListenOpt = None,
) -> None:
    """The stack's bookkeeping program (started by `jitterguard up`): heartbeats in, summary.json out."""
    if not run_dir.is_dir():  # bad input first: a one-line error before anything is set up
        fail(f"--run-dir: no such folder: {run_dir}")
    setup_logging(log_level)
    StackMonitor(zenoh_options(ns, zenoh_config, connect, listen), run_dir).run_forever()


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    app.command("stack-monitor", hidden=True)(monitor_command)
