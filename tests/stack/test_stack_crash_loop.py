"""A program that crashes again and again *after* supervisord called it RUNNING is held back by the monitor
(real supervisord, real router, classifier and stack-monitor; no mocks).

supervisord backs off only a program that dies before its ``startsecs``; one that dies 1.5 s after it started (a
bad weights file read lazily, a bug hit on the first message) it restarts at once, for ever. Here the "detector"
is such a program; the monitor runs with short ``JG_CRASH_LOOP_*`` constants (2 exits in 20 s, holds of 8 s
then 16 s) so the test sees two loops and their holds in well under a minute (~40 s).
"""

from __future__ import annotations

import json
import os
import re
import statistics
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from jitterguard.runtime import free_tcp_port
from jitterguard.stack import summary
from jitterguard.stack.control import StackUnavailable, Supervisor
from jitterguard.stack.status import save_spec
from jitterguard.stack.supervisor import Program, StackSpec, render_config

from helpers import wait_until

pytestmark = pytest.mark.integration

# it writes nothing until it crashes: a run the monitor stops before then (supervisord restarts it at once, the monitor
# may hold it back during that restart's first 1.5 s) adds no line, so its log always ends with the last crash
CRASHER = ("import sys, time; time.sleep(1.5); print('loading weights', flush=True); "
           "sys.exit('RuntimeError: weights file truncated')")
ENV = {"JG_CRASH_LOOP_EXITS": "2", "JG_CRASH_LOOP_WINDOW_S": "20", "JG_CRASH_LOOP_BACKOFF_S": "8",
       "JG_CRASH_LOOP_BACKOFF_MAX_S": "16"}


def _cmd(*args: str) -> tuple[str, ...]:
    return (sys.executable, "-m", "jitterguard.cli", *args)


def _summary(rd: Path) -> dict:
    return summary.load(rd) or {}


@pytest.fixture
def stack(tmp_path):
    rd = tmp_path / "run"
    (rd / "logs").mkdir(parents=True)
    ns = f"crashloop{os.getpid()}"
    spec = StackSpec(ns=ns, name="crashloop", router_port=free_tcp_port(), input="detections", run_dir=str(rd),
                     sidecar=False, extra_env=ENV)
    common = ("--ns", ns, "--connect", spec.endpoint)
    progs = [Program("router", _cmd("router", "--listen", spec.endpoint), priority=10),
             Program("classifier", _cmd("classifier", *common, "--open-config-writes"), priority=20),
             Program("detector", (sys.executable, "-c", CRASHER), priority=35),
             Program("monitor", _cmd("stack-monitor", *common, "--run-dir", str(rd)), priority=5)]
    t0 = time.time()
    with _supervised(rd, spec, progs) as sup:
        yield {"run_dir": rd, "sup": sup, "t0": t0}


@contextmanager
def _supervised(rd: Path, spec: StackSpec, progs: list[Program]) -> Iterator[Supervisor]:
    """``progs`` running under a real supervisord in ``rd`` (daemonised), shut down and gone at the end."""
    conf = rd / "supervisord.conf"
    conf.write_text(render_config(spec, rd, progs, nodaemon=False))
    save_spec(rd, spec)
    res = subprocess.run([sys.executable, "-m", "supervisor.supervisord", "-c", str(conf)], capture_output=True,
                         text=True, timeout=60)
    assert res.returncode == 0, res.stdout + res.stderr
    sup = Supervisor(rd)
    try:
        yield sup
    finally:
        try:
            sup.shutdown()
        except StackUnavailable:
            pass
        sup.wait_gone(60)


def test_a_program_crashing_after_it_started_is_held_back_and_the_rest_keeps_running(stack):
    rd, sup, t0 = stack["run_dir"], stack["sup"], stack["t0"]
    mon_log = rd / "logs" / "monitor.log"

    def backed_off() -> int:
        return _summary(rd).get("restarts", {}).get("backed_off", {}).get("detector", 0)

    # two loops: held 8 s, started again, crashing again, held 16 s
    assert wait_until(lambda: backed_off() >= 2 and "detector" in _summary(rd)["restarts"]["held_back"],
                      timeout=50, period=0.3), (mon_log.read_text()[-3000:], _summary(rd).get("restarts"))
    procs = {p.name: p for p in sup.processes()}
    assert procs["detector"].state in ("STOPPED", "STOPPING"), procs["detector"]

    # `status` says why the program is not running, and when it starts again
    res = subprocess.run([*_cmd("status", "--run-dir", str(rd), "--json", "--listen-s", "0.3")], capture_output=True,
                         text=True, timeout=60)
    assert res.returncode == 3, res.stdout + res.stderr
    rows = {r["name"]: r for r in json.loads(res.stdout)["services"]}
    det = rows["detector"]
    assert det["held_back_s"] is not None and 0 <= det["held_back_s"] <= 16, det
    assert det["problem"].startswith("backoff (crash loop: held back by the monitor, next start in"), det
    assert "weights file truncated" in det["problem"], det
    assert rows["classifier"]["alive"] is True and rows["classifier"]["state"] == "RUNNING", rows["classifier"]

    # one warning per loop, naming the program, the count and the next start; the back-off doubled
    warnings = [ln for ln in mon_log.read_text().splitlines() if "WARNING" in ln and "detector crashed" in ln]
    assert len(warnings) == 2, warnings
    assert re.search(r"detector crashed [23] times within 20 s .*crash loop 1 in a row.*next start in 8 s",
                     warnings[0]), warnings
    assert re.search(r"detector crashed [23] times .*crash loop 2 in a row.*next start in 16 s", warnings[1]), warnings

    # started again once the second hold has run out
    assert wait_until(lambda: "detector" not in _summary(rd)["restarts"]["held_back"], timeout=30, period=0.3)
    assert wait_until(lambda: any(p.name == "detector" and p.state in ("STARTING", "RUNNING", "EXITED", "BACKOFF")
                                  for p in sup.processes()), timeout=10, period=0.2)
    elapsed = time.time() - t0
    final = _summary(rd)
    assert final["restarts"]["backed_off"] == {"detector": 2}, final["restarts"]
    assert final["services"]["monitor"]["counters"].get("backed_off.detector") == 2, final["services"]["monitor"]
    assert "held back after crash loops: detector 2" in summary.render(final)

    # the rest of the stack ran throughout: never restarted
    events = summary.supervisor_events(rd / "logs" / "supervisord.log", since=t0 - 1)
    procs = {p.name: p for p in sup.processes()}
    for name in ("router", "classifier", "monitor"):
        assert procs[name].state == "RUNNING" and len(events[name].spawns) == 1, (name, procs[name])

    # its restarts stay far below those of the loop supervisord alone keeps up (one every ~2 s here), and none
    # comes while it is held
    spawns = events["detector"].spawns
    gaps = [b - a for a, b in zip(spawns, spawns[1:])]
    cycle = statistics.median(g for g in gaps if g < 6.0)
    unthrottled = elapsed / cycle
    assert len(spawns) <= 0.6 * unthrottled, (len(spawns), unthrottled, gaps)
    holds = [g for g in gaps if g >= 6.0]
    # (from a spawn to the next: the hold counts from the monitor's decision, which may come just before
    # supervisord's last restart of it, stopped on the next look)
    assert len(holds) == 2 and holds[0] >= 7.0 and holds[1] >= 15.0 and holds[1] > 1.6 * holds[0], gaps


SLOW_CRASHER = "import sys, time; time.sleep(4); sys.exit('RuntimeError: weights file truncated')"


def test_status_names_a_program_that_keeps_crashing_more_slowly_than_the_guard_acts(tmp_path):
    """A program that dies every few seconds after it was called RUNNING, more slowly than the crash-loop guard acts
    on (here turned off, as JG_CRASH_LOOP_EXITS=0 does; by default a crash every 15 s is never held back): `status`
    had read RUNNING, its uptime and nothing else between two crashes, the restarts only in `summary`. Its row says
    how often it exited unexpectedly of late, and the last exit."""
    rd = tmp_path / "run"
    (rd / "logs").mkdir(parents=True)
    spec = StackSpec(ns=f"slowcrash{os.getpid()}", name="slowcrash", router_port=free_tcp_port(), input="detections",
                     run_dir=str(rd), sidecar=False)
    progs = [Program("router", _cmd("router", "--listen", spec.endpoint), priority=10),
             Program("detector", (sys.executable, "-c", SLOW_CRASHER), priority=35)]
    with _supervised(rd, spec, progs):
        def exits() -> int:
            events = summary.supervisor_events(rd / "logs" / "supervisord.log")
            return len(events["detector"].crashes) if "detector" in events else 0

        assert wait_until(lambda: exits() >= 2, timeout=60, period=0.3)
        out = subprocess.run([*_cmd("status", "--run-dir", str(rd), "--json", "--listen-s", "0.3")],
                             capture_output=True, text=True, timeout=60)
        det = next(r for r in json.loads(out.stdout)["services"] if r["name"] == "detector")
        assert det["recent_exits"] >= 2 and det["last_exit"].startswith("exit status 1, "), det
        table = subprocess.run([*_cmd("status", "--run-dir", str(rd), "--listen-s", "0.3")], capture_output=True,
                               text=True, timeout=60).stdout
        line = next(ln for ln in table.splitlines() if ln.startswith("detector"))
        assert re.search(r"restarted after \d+ unexpected exits in 10 min \(last: exit status 1, \d+ s ago\)", line), \
            table
        router = next(ln for ln in table.splitlines() if ln.startswith("router"))
        assert "restarted" not in router, table
