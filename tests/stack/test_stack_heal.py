"""Faults an operator meets on a running stack, and what the stack then says and does (real supervisord, real
Zenoh on loopback, real uvicorn; no mocks).

One detection-level stack with its sidecar per module, under ``JG_WATCHDOG_S=5`` so that the freeze watch acts
within ~15 s. In turn: a service frozen with SIGSTOP is ended and restarted (no watchdog inside it can run); the
source stopped for good leaves ``/readyz`` ready but saying so, and ``status`` naming it; the monitor that cannot
write ``summary.json`` says so; a frozen router is named as the router, not as six frozen services, and replaced;
and last a frozen supervisord, which ``status`` names at once and ``down`` still stops. Beside it: ``up`` with
port 0, two ``up`` on one run directory, and ``up`` on a full disk.

Nothing here asserts a time: every wait is for a condition, with a generous limit (shared 2-core machines).
"""

from __future__ import annotations

import fcntl
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from jitterguard.runtime import free_tcp_port
from jitterguard.stack.control import ProcessInfo, Supervisor, pid_alive, read_pid
from jitterguard.stack.status import collect

from helpers import freeze_until_replaced, wait_until

pytestmark = pytest.mark.integration

HEAL_TIMEOUT_S = 90.0


def jg(*args: str, env: dict[str, str] | None = None, timeout: float = 120, cwd: Path | None = None
       ) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "jitterguard.cli", *args], capture_output=True, text=True,
                          timeout=timeout, env=env, cwd=cwd)


def pid_of(run_dir: Path, name: str) -> int | None:
    return next((p.pid for p in Supervisor(run_dir).processes() if p.name == name and p.state == "RUNNING"), None)


def status_json(run_dir: Path, env: dict[str, str], listen_s: float = 1.5) -> tuple[int, dict]:
    res = jg("status", "--run-dir", str(run_dir), "--json", "--listen-s", str(listen_s), env=env)
    assert "Traceback" not in res.stdout + res.stderr, res.stdout + res.stderr
    return res.returncode, json.loads(res.stdout) if res.stdout.strip() else {}


def rows_of(run_dir: Path, env: dict[str, str]) -> dict[str, dict]:
    return {r["name"]: r for r in status_json(run_dir, env)[1].get("services", [])}


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("heal") / "run"
    router, http = free_tcp_port(), free_tcp_port()
    env = {**os.environ, "JG_WATCHDOG_S": "5"}
    env.pop("JG_API_TOKEN", None)
    res = jg("up", "-d", "--ns", f"heal{os.getpid()}", "--input", "detections", "--router-port", str(router),
             "--port", str(http), "--run-dir", str(run_dir), env=env)
    assert res.returncode == 0, res.stdout + res.stderr
    info = {"run_dir": run_dir, "env": env, "url": f"http://127.0.0.1:{http}"}
    try:
        assert wait_until(lambda: _classified(info) > 0, timeout=HEAL_TIMEOUT_S, period=1.0)
        yield info
    finally:
        pid = read_pid(run_dir)
        if pid is not None and pid_alive(pid):
            os.kill(pid, signal.SIGCONT)  # a test that failed half-way may have left it stopped
        jg("down", "--run-dir", str(run_dir), env=env)


def _classified(info: dict) -> int:
    return rows_of(info["run_dir"], info["env"]).get("classifier", {}).get("last_seq") or 0


def _readyz(info: dict) -> dict:
    with httpx.Client(base_url=info["url"], timeout=10.0) as c:
        r = c.get("/readyz")
    body = r.json()
    body["status_code"] = r.status_code
    return body


def test_a_frozen_service_is_ended_and_restarted(stack):
    """SIGSTOP stops every thread of the tracker, its watchdog and faulthandler's timer with them: supervisord
    says RUNNING for ever and no frame goes through. The monitor, hearing the others but not it, kills it for
    supervisord to restart it, and frames flow again."""
    rd = stack["run_dir"]
    freeze_until_replaced(lambda: pid_of(rd, "tracker"), rd / "logs" / "monitor.log", HEAL_TIMEOUT_S)
    before = _classified(stack)
    assert wait_until(lambda: _classified(stack) > before + 10, timeout=HEAL_TIMEOUT_S, period=1.0)


def test_a_service_stopped_before_the_monitor_restarted_is_still_ended(stack):
    """A restarted monitor has heard nothing yet: a tracker stopped (SIGSTOP) just before it had never been judged by
    its silence, and stayed frozen for good — every program RUNNING, `status` saying "no heartbeat heard". A program
    this monitor never heard from is judged by the kernel, as the router is: stopped in /proc, ended, restarted."""
    rd = stack["run_dir"]
    tracker, monitor = pid_of(rd, "tracker"), pid_of(rd, "monitor")
    assert tracker and monitor
    os.kill(tracker, signal.SIGSTOP)
    try:
        os.kill(monitor, signal.SIGKILL)  # supervisord starts another, which never heard this tracker
        assert wait_until(lambda: pid_of(rd, "tracker") not in (None, tracker), timeout=HEAL_TIMEOUT_S, period=0.5), \
            (rd / "logs" / "monitor.log").read_text()[-2000:]
    finally:
        if pid_alive(tracker):
            os.kill(tracker, signal.SIGCONT)
    assert pid_of(rd, "monitor") not in (None, monitor)
    log = (rd / "logs" / "monitor.log").read_text()
    assert f"tracker (pid {tracker}) has been stopped for" in log and "never heard it" in log, log[-2000:]
    before = _classified(stack)
    assert wait_until(lambda: _classified(stack) > before + 10, timeout=HEAL_TIMEOUT_S, period=1.0)


def test_summary_says_when_a_running_stacks_summary_is_not_being_kept(stack):
    """A monitor stopped (SIGSTOP: nothing ends it, it is the one that ends frozen programs) keeps no summary: `summary`
    had printed its totals of minutes ago as the run so far. It still prints them, and says on stderr how old they
    are; once the monitor writes again it says nothing."""
    import time

    from jitterguard.stack.cli import STALE_SUMMARY_S

    rd, env = stack["run_dir"], stack["env"]
    assert wait_until(lambda: pid_of(rd, "monitor") and pid_of(rd, "monitor-watch"), timeout=HEAL_TIMEOUT_S, period=0.5)
    monitor, watch = pid_of(rd, "monitor"), pid_of(rd, "monitor-watch")
    path = rd / "summary.json"
    # the monitor-watch stopped too, or it ends the stopped monitor after 20 s — a race with the staleness asked of
    # `summary` (what this test is about: a summary nobody keeps, whatever stopped its keeper)
    os.kill(watch, signal.SIGSTOP)
    os.kill(monitor, signal.SIGSTOP)
    try:
        assert wait_until(lambda: time.time() - path.stat().st_mtime > STALE_SUMMARY_S + 1, timeout=60, period=0.5)
        res = jg("summary", "--run-dir", str(rd), env=env)
        assert res.returncode == 0 and "run summary of stack" in res.stdout, res.stdout + res.stderr
        assert "was last written" in res.stderr and "its monitor is not keeping it" in res.stderr, res.stderr
    finally:  # the watch first: the monitor, resumed, would end a watch it finds stopped
        os.kill(watch, signal.SIGCONT)
        os.kill(monitor, signal.SIGCONT)
    assert wait_until(lambda: time.time() - path.stat().st_mtime < 3, timeout=60, period=0.5)
    res = jg("summary", "--run-dir", str(rd), env=env)
    assert res.returncode == 0 and "last written" not in res.stderr, res.stderr


def test_a_stopped_monitor_is_ended_by_the_monitor_watch_and_counted(stack):
    """The monitor ends every other frozen program, but a monitor stopped itself (SIGSTOP) had been ended by nothing:
    healing stopped for good while supervisord said RUNNING. The monitor-watch, a light supervisord event listener,
    sees it stopped in /proc and kills it for supervisord to restart it; the count reaches `summary` and `status`."""
    rd, env = stack["run_dir"], stack["env"]
    # both RUNNING first: an earlier test's heal may still be restarting one of them (STARTING: no pid yet)
    assert wait_until(lambda: pid_of(rd, "monitor") and pid_of(rd, "monitor-watch"), timeout=HEAL_TIMEOUT_S, period=0.5)
    monitor = pid_of(rd, "monitor")
    before = json.loads((rd / "monitor-watch.json").read_text())["frozen_restarts"]["monitor"] \
        if (rd / "monitor-watch.json").exists() else 0  # a slow host's earlier SIGSTOP of the monitor may count
    os.kill(monitor, signal.SIGSTOP)
    try:
        assert wait_until(lambda: pid_of(rd, "monitor") not in (None, monitor), timeout=HEAL_TIMEOUT_S, period=0.5), \
            (rd / "logs" / "monitor-watch.log").read_text()[-2000:]
    finally:
        if pid_alive(monitor):
            os.kill(monitor, signal.SIGCONT)
    log = (rd / "logs" / "monitor-watch.log").read_text()
    assert f"monitor (pid {monitor}) has been stopped for" in log, log[-2000:]
    assert json.loads((rd / "monitor-watch.json").read_text())["frozen_restarts"] == {"monitor": before + 1}

    def summarised() -> dict:
        res = jg("summary", "--run-dir", str(rd), "--json", env=env)
        return json.loads(res.stdout) if res.returncode == 0 else {}

    assert wait_until(lambda: summarised().get("restarts", {}).get("frozen_restarts", {}).get("monitor") == before + 1,
                      timeout=HEAL_TIMEOUT_S, period=1.0), summarised().get("restarts")
    assert f"ended frozen: monitor {before + 1}" in jg("summary", "--run-dir", str(rd), env=env).stdout
    rows = rows_of(rd, env)
    assert rows["monitor"]["frozen_restarts"] == before + 1 and rows["monitor"]["state"] == "RUNNING", rows["monitor"]
    # the watch is no Zenoh participant: RUNNING is up (not "no heartbeat heard"), and the stack reads up again
    assert rows["monitor-watch"]["state"] == "RUNNING" and not rows["monitor-watch"]["heartbeat_expected"]
    assert wait_until(lambda: status_json(rd, env)[0] == 0, timeout=HEAL_TIMEOUT_S, period=1.0), status_json(rd, env)


def test_a_stopped_monitor_watch_is_ended_by_the_monitor(stack):
    """Who watches the watch: it sends no heartbeat, so the monitor judges it by /proc, as any program it never
    heard from, and ends it stopped for supervisord to restart it."""
    rd = stack["run_dir"]
    assert wait_until(lambda: pid_of(rd, "monitor") and pid_of(rd, "monitor-watch"), timeout=HEAL_TIMEOUT_S, period=0.5)
    watch = pid_of(rd, "monitor-watch")
    os.kill(watch, signal.SIGSTOP)
    try:
        assert wait_until(lambda: pid_of(rd, "monitor-watch") not in (None, watch), timeout=HEAL_TIMEOUT_S,
                          period=0.5), (rd / "logs" / "monitor.log").read_text()[-2000:]
    finally:
        if pid_alive(watch):
            os.kill(watch, signal.SIGCONT)
    log = (rd / "logs" / "monitor.log").read_text()
    assert f"monitor-watch (pid {watch}) has been stopped for" in log, log[-2000:]


def test_a_source_gone_for_good_keeps_readyz_ready_but_named(stack):
    """No input is not a fault (a sensor may be off): `/readyz` stays 200. But a ready sidecar serving no new
    objects now says why under `warnings` (the source left the bus; the classifier's frames stand still), and
    `status` names the program and says that no frames enter the pipeline (its row had read "no heartbeat
    heard", as a frozen process's)."""
    rd, env = stack["run_dir"], stack["env"]
    sup = Supervisor(rd)
    sup.call("stopProcess", "replay", True)
    try:
        def warned() -> dict | None:
            body = _readyz(stack)
            text = " ".join(body.get("warnings", []))
            return body if "replay left the bus" in text and "no input" in text else None

        assert wait_until(lambda: warned() is not None, timeout=HEAL_TIMEOUT_S, period=1.0), _readyz(stack)
        body = warned()
        assert body["status_code"] == 200 and body["ready"] is True and body["reason"] == "ok", body
        code, st = status_json(rd, env)
        assert code == 3 and st["state"] == "degraded"
        replay = next(r for r in st["services"] if r["name"] == "replay")
        assert replay["state"] == "STOPPED" and "no frames enter the pipeline" in replay["problem"], replay
        table = jg("status", "--run-dir", str(rd), env=env).stdout
        line = next(ln for ln in table.splitlines() if ln.startswith("replay"))
        assert "no frames enter the pipeline" in line and "no heartbeat heard" not in line, table
    finally:
        sup.call("startProcess", "replay", True)
    assert wait_until(lambda: _readyz(stack).get("warnings") == [], timeout=HEAL_TIMEOUT_S, period=1.0), \
        _readyz(stack)


def test_a_program_that_is_not_running_says_why_in_one_line(tmp_path):
    """What `status` shows for a program supervisord gave up on: its word for it and the last line of its log."""
    log = tmp_path / "replay.log"
    log.write_text("starting\njitterguard: error: /data/bag: no such file or folder\n\n")
    procs = [ProcessInfo("replay", "FATAL", None, None, 2, "Exited too quickly", str(log))]
    row = collect(procs, None)[0]
    assert row.problem == ("supervisord gave up restarting it; its log ends: jitterguard: error: /data/bag: no such"
                           " file or folder; no frames enter the pipeline")
    assert not row.up


def test_a_monitor_that_cannot_write_the_summary_says_so(stack):
    """A full disk (here: a folder where summary.json goes, which no rename replaces, root or not) had left the
    monitor logging a traceback a second while `status` said ok and `summary` "its monitor writes one every
    second". Its heartbeat now says failing, with the reason; the first write that succeeds clears it."""
    rd, env = stack["run_dir"], stack["env"]
    path = rd / "summary.json"
    for _ in range(100):  # the monitor renames a fresh summary into place every second: it may win the gap once
        path.unlink(missing_ok=True)
        try:
            path.mkdir()
            break
        except FileExistsError:
            continue
    assert path.is_dir()
    try:
        def failing() -> dict | None:
            row = rows_of(rd, env).get("monitor", {})
            return row if row.get("health") == "failing" else None

        assert wait_until(lambda: failing() is not None, timeout=HEAL_TIMEOUT_S, period=1.0)
        row = failing()
        assert f"cannot write {path}" in row["health_reason"], row
        assert status_json(rd, env)[0] == 3
    finally:
        path.rmdir()
    assert wait_until(lambda: rows_of(rd, env).get("monitor", {}).get("health") == "ok", timeout=HEAL_TIMEOUT_S,
                      period=1.0)
    assert path.is_file()
    log = (rd / "logs" / "monitor.log").read_text()
    assert log.count("cannot write") == 1 and "written again" in log, log[-2000:]  # once, not once a second


def test_a_frozen_router_is_named_not_every_service_and_replaced(stack):
    """With the router stopped nothing can be heard on Zenoh: that says nothing of the services, whose rows had
    all read "no heartbeat heard" (frozen) while the router's said nothing. The router sends no heartbeat; the
    monitor sees it stopped in /proc, kills it for supervisord to restart it, and every service reconnects."""
    rd, env = stack["run_dir"], stack["env"]
    router = pid_of(rd, "router")
    assert router
    others = {name: pid_of(rd, name) for name in ("tracker", "classifier", "replay", "sidecar")}
    ended_silent = (rd / "logs" / "monitor.log").read_text().count("has sent no heartbeat for")
    os.kill(router, signal.SIGSTOP)
    try:
        code, st = status_json(rd, env)
        rows = {r["name"]: r for r in st["services"]}
        if rows["router"]["pid"] == router:  # (the monitor may already have replaced it on a very slow machine)
            assert code == 3
            assert "not answering on" in rows["router"]["problem"], rows["router"]
            for name in ("tracker", "classifier", "replay"):
                assert rows[name]["alive"] is False and rows[name]["heartbeat_expected"] is False, rows[name]
        assert wait_until(lambda: pid_of(rd, "router") not in (None, router), timeout=HEAL_TIMEOUT_S, period=0.5), \
            (rd / "logs" / "monitor.log").read_text()[-2000:]
    finally:
        if pid_alive(router):
            os.kill(router, signal.SIGCONT)
    assert f"router (pid {router}) has been stopped for" in (rd / "logs" / "monitor.log").read_text()
    assert wait_until(lambda: status_json(rd, env)[0] == 0, timeout=HEAL_TIMEOUT_S, period=1.0)
    # the services were only cut off, never stopped: none is ended as frozen while it reconnects (the monitor had
    # killed a classifier whose last beat, from before the router stopped, was past the limit when others were back)
    assert {name: pid_of(rd, name) for name in others} == others, (rd / "logs" / "monitor.log").read_text()[-2000:]
    assert (rd / "logs" / "monitor.log").read_text().count("has sent no heartbeat for") == ended_silent


def test_zz_a_frozen_supervisord_is_named_at_once_and_down_still_stops_the_stack(stack):
    """`status`, `down` and `up` had waited for ever on a supervisord stopped with SIGSTOP (its socket accepts,
    nothing answers). `status` says what it is in one line; `up` refuses to start a second stack over it; `down`
    resumes it with the stop waiting, and the stack stops. (Last in the module: it stops the stack.)"""
    rd, env = stack["run_dir"], stack["env"]
    sup_pid = read_pid(rd)
    programs = [p.pid for p in Supervisor(rd).processes() if p.pid]
    os.kill(sup_pid, signal.SIGSTOP)
    try:
        st = jg("status", "--run-dir", str(rd), env=env, timeout=60)
        assert st.returncode == 3 and f"supervisord (pid {sup_pid}) is stopped" in st.stdout, st.stdout + st.stderr
        js = jg("status", "--run-dir", str(rd), "--json", env=env, timeout=60)
        assert json.loads(js.stdout)["state"] == "frozen"
        again = jg("up", "-d", "--run-dir", str(rd), "--input", "detections", "--router-port", str(free_tcp_port()),
                   "--port", str(free_tcp_port()), env=env, timeout=60)
        assert again.returncode == 2 and "is stopped" in again.stderr, again.stdout + again.stderr
        down = jg("down", "--run-dir", str(rd), env=env, timeout=180)
    finally:
        if pid_alive(sup_pid):
            os.kill(sup_pid, signal.SIGCONT)
    assert down.returncode == 0 and "stopped" in down.stdout, down.stdout + down.stderr
    assert wait_until(lambda: not pid_alive(sup_pid) and not any(pid_alive(p) for p in programs), timeout=60)


def test_port_0_picks_a_free_port_and_prints_it(tmp_path):
    """`--router-port 0` / `--port 0` (and `--foxglove-port 0`) pick a port free now, print it, and write it into
    the stack's files, so that a restarted program keeps it and `status` finds it (it had been refused)."""
    rd = tmp_path / "run"
    res = jg("up", "-d", "--ns", f"zero{os.getpid()}", "--input", "tracks", "--router-port", "0", "--port", "0",
             "--run-dir", str(rd))
    try:
        assert res.returncode == 0, res.stdout + res.stderr
        spec = json.loads((rd / "stack.json").read_text())
        assert spec["router_port"] > 0 and spec["sidecar_port"] > 0 and spec["router_port"] != spec["sidecar_port"]
        assert f"router: tcp/127.0.0.1:{spec['router_port']}" in res.stdout
        assert f"sidecar: http://127.0.0.1:{spec['sidecar_port']}/" in res.stdout
        with httpx.Client(timeout=10.0) as c:
            assert c.get(f"http://127.0.0.1:{spec['sidecar_port']}/healthz").status_code == 200
        assert wait_until(lambda: jg("status", "--run-dir", str(rd), "--json").returncode == 0,
                          timeout=HEAL_TIMEOUT_S, period=1.0)
    finally:
        jg("down", "--run-dir", str(rd))


def test_a_second_up_on_a_run_dir_being_started_is_refused(tmp_path):
    """Two `up` at once on one run directory both found it free, both wrote its files, and one's supervisord
    ran the other's: the run-directory lock lets one through; the other says so and starts nothing."""
    rd = tmp_path / "run"
    rd.mkdir()
    with open(rd / "up.lock", "a") as held:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)  # as another `up` holds it while it starts the stack
        res = jg("up", "-d", "--input", "tracks", "--router-port", str(free_tcp_port()), "--no-sidecar",
                 "--run-dir", str(rd))
    try:
        assert res.returncode == 2, res.stdout + res.stderr
        assert "another `jitterguard up` is starting the stack" in res.stderr
        assert not (rd / "supervisord.conf").exists() and read_pid(rd) is None
    finally:
        if res.returncode == 0:
            jg("down", "--run-dir", str(rd))


@pytest.fixture
def full_disk(tmp_path):
    """A 1 MiB tmpfs filled to the last byte (root and a mount namespace that allows it; skipped otherwise)."""
    mnt = tmp_path / "full"
    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mnt)], capture_output=True).returncode:
        pytest.skip("cannot mount a tmpfs here (not root?)")
    try:
        (mnt / "run").mkdir()
        fd = os.open(mnt / "filler", os.O_WRONLY | os.O_CREAT)
        try:
            while os.write(fd, b"\0" * 4096):
                pass
        except OSError:  # no space left: the point
            pass
        finally:
            os.close(fd)
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


def test_up_on_a_full_disk_warns_and_says_it_cannot_write(full_disk):
    """`up` into a run directory with no space left: a warning about the space, then one line that it cannot
    write there, exit 2 (it had ended in a traceback writing supervisord.conf)."""
    rd = full_disk / "run"
    res = jg("up", "-d", "--input", "tracks", "--router-port", str(free_tcp_port()), "--no-sidecar",
             "--run-dir", str(rd))
    try:
        assert res.returncode == 2 and "Traceback" not in res.stderr, res.stdout + res.stderr
        assert "jitterguard: warning: only 0.0 MiB free in" in res.stderr, res.stderr
        assert res.stderr.strip().splitlines()[-1].startswith(f"jitterguard: error: --run-dir: cannot write into {rd}")
    finally:
        if res.returncode == 0:
            jg("down", "--run-dir", str(rd))


def test_the_summary_says_which_program_supervisord_gave_up_on(tmp_path):
    """From supervisord's own log lines: a replay given up on is named as such ("restarts replay 21" had been all
    the summary said of a source dead for the rest of the run); one started again since is not."""
    from jitterguard.stack import summary

    log = tmp_path / "supervisord.log"
    lines = ["2026-12-04 17:50:10,000 INFO spawned: 'replay' with pid 100",
             "2026-12-04 17:50:11,000 INFO spawned: 'tracker' with pid 101",
             "2026-12-04 17:50:20,000 WARN exited: replay (exit status 2; not expected)",
             "2026-12-04 17:50:21,000 INFO spawned: 'replay' with pid 102",
             "2026-12-04 17:50:21,500 WARN exited: replay (exit status 2; not expected)",
             "2026-12-04 17:50:22,000 INFO gave up: replay entered FATAL state, too many start retries too quickly"]
    log.write_text("\n".join(lines) + "\n")
    built = summary.build(summary.Ledger(), summary.supervisor_events(log), meta={"stack": "s"})
    assert built["restarts"]["gave_up"] == ["replay"]
    assert "supervisord gave up on: replay" in summary.render(built)
    log.write_text("\n".join([*lines, "2026-12-04 17:55:00,000 INFO spawned: 'replay' with pid 103"]) + "\n")
    built = summary.build(summary.Ledger(), summary.supervisor_events(log), meta={"stack": "s"})
    assert built["restarts"]["gave_up"] == [] and "gave up" not in summary.render(built)
