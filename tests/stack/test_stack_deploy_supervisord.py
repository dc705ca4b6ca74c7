"""deploy/supervisord.conf, the file an operator runs under their own supervisord, runs as shipped (real
supervisord, real router, services and uvicorn; no mocks).

Only what a test host cannot have is changed: the system folders (/run, /var/log, /var/lib) become temporary ones,
the venv path the one running this test, the ports free ones, ``user=`` / ``chown=`` go (no ``jitterguard`` user
here), and ``JG_WATCHDOG_S`` is short so that the freeze watch acts within ~15 s. Every program starts, the
sidecar comes ready, the monitor writes the run's summary into /var/lib/jitterguard's stand-in (and the classifier
its compiled statistic's cache, NUMBA_CACHE_DIR), and a service
frozen with SIGSTOP is ended by the monitor and restarted by supervisord. Before, this file had no monitor: a
frozen process stayed frozen for good under plain supervisord, every program RUNNING.

Nothing here asserts a time: every wait is for a condition, with a generous limit (shared 2-core machines).
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from jitterguard.runtime import free_tcp_port
from jitterguard.stack.control import StackUnavailable, Supervisor, pid_alive

from helpers import wait_until

pytestmark = pytest.mark.integration

SHIPPED = Path(__file__).resolve().parents[2] / "deploy" / "supervisord.conf"
PROGRAMS = {"monitor", "router", "classifier", "tracker", "detector", "sidecar"}
TIMEOUT_S = 120.0


def _localise(text: str, root: Path, router: int, http: int, ns: str) -> str:
    """The shipped file with this host's folders, venv, ports and namespace; nothing else changed."""
    bin_dir = Path(sys.executable).parent
    for system, here in (("/run/jitterguard", root / "run"), ("/var/log/jitterguard", root / "log"),
                         ("/var/lib/jitterguard", root / "lib"), ("/opt/jitterguard/venv/bin", bin_dir)):
        text = text.replace(system, str(here))
    text = text.replace("tcp/127.0.0.1:7447", f"tcp/127.0.0.1:{router}").replace("--port 8000", f"--port {http}")
    text = text.replace('JG_NS="default"', f'JG_NS="{ns}",JG_WATCHDOG_S="3"')
    return "\n".join(line for line in text.splitlines() if not line.startswith(("user=", "chown=")))


def _pid(sup: Supervisor, name: str) -> int | None:
    try:
        return next((p.pid for p in sup.processes() if p.name == name and p.state == "RUNNING"), None)
    except StackUnavailable:
        return None


def _ready(url: str) -> bool:
    try:
        return httpx.get(f"{url}/readyz", timeout=5.0).status_code == 200
    except httpx.HTTPError:
        return False


@pytest.fixture(scope="module")
def deployed(tmp_path_factory):
    root = tmp_path_factory.mktemp("deploy")
    for sub in ("run", "log", "lib"):
        (root / sub).mkdir()
    router, http = free_tcp_port(), free_tcp_port()
    conf = root / "supervisord.conf"
    text = _localise(SHIPPED.read_text(), root, router, http, f"deploy{os.getpid()}")
    settings = "\n".join(line for line in text.splitlines() if not line.startswith(";"))
    assert not re.search(r"(/var/(log|lib)|/run|/opt)/jitterguard", settings), settings
    conf.write_text(text)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("SUPERVISOR_", "JG_"))}
    res = subprocess.run([str(Path(sys.executable).parent / "supervisord"), "-c", str(conf)], env=env,
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stdout + res.stderr
    sup = Supervisor(root, label="deploy", sock=root / "run" / "supervisor.sock")
    info = {"root": root, "sup": sup, "url": f"http://127.0.0.1:{http}"}
    try:
        yield info
    finally:
        try:
            sup.shutdown()
        except StackUnavailable:
            pass
        pidfile = root / "run" / "supervisord.pid"
        wait_until(lambda: not pidfile.exists(), timeout=60, period=0.5)


def test_every_program_of_the_shipped_file_runs_and_the_monitor_keeps_the_summary(deployed):
    sup, root = deployed["sup"], deployed["root"]

    def all_running() -> bool:
        try:
            return {p.name for p in sup.processes() if p.state == "RUNNING"} >= PROGRAMS
        except StackUnavailable:
            return False

    assert wait_until(all_running, timeout=TIMEOUT_S, period=0.5), [(p.name, p.state) for p in sup.processes()]
    # the live ROS 2 programs wait for an operator on a vehicle (autostart=false), and then start
    assert {p.name: p.state for p in sup.processes() if p.name.startswith("ros2-")} == {"ros2-in": "STOPPED",
                                                                                        "ros2-out": "STOPPED"}
    for name in ("ros2-in", "ros2-out"):
        sup.call("startProcess", name, True)
    assert {p.name: p.state for p in sup.processes() if p.name.startswith("ros2-")} == {"ros2-in": "RUNNING",
                                                                                        "ros2-out": "RUNNING"}
    assert wait_until(lambda: _ready(deployed["url"]), timeout=TIMEOUT_S, period=1.0), \
        httpx.get(f"{deployed['url']}/readyz", timeout=5.0).text

    def summarised() -> dict | None:
        try:
            body = json.loads((root / "lib" / "summary.json").read_text())
        except (OSError, ValueError):
            return None
        return body if {"classifier", "tracker", "detector"} <= set(body.get("ledger", {})) else None

    assert wait_until(lambda: summarised() is not None, timeout=TIMEOUT_S, period=1.0), \
        (root / "log" / "monitor.log").read_text()[-2000:]
    # the operator's view of it, as the deployment page says: a second reader of the same file
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "summary", "--run-dir", str(root / "lib"),
                          "--json"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stdout + res.stderr
    assert json.loads(res.stdout)["stack"] == "lib"
    # the classifier caches its compiled statistic where the file's NUMBA_CACHE_DIR says, the one folder its user may
    # write (under user=jitterguard neither the root-owned venv nor root's HOME is writable: each start recompiled)
    cache = root / "lib" / "numba-cache"
    assert wait_until(lambda: any(cache.rglob("*.nbi")), timeout=TIMEOUT_S, period=1.0), \
        (root / "log" / "classifier.log").read_text()[-2000:]
    assert "no writable numba cache" not in (root / "log" / "classifier.log").read_text()


def test_a_frozen_service_is_ended_and_restarted_under_plain_supervisord(deployed):
    """The tracker stopped with SIGSTOP runs no thread, neither its watchdog nor faulthandler's timer; the monitor
    (which found this supervisord by SUPERVISOR_SERVER_URL and knows the tracker for one of its programs by the
    same variable in the tracker's environment) kills it, and supervisord starts it again."""
    sup, root = deployed["sup"], deployed["root"]
    assert wait_until(lambda: _pid(sup, "tracker") is not None and _ready(deployed["url"]),
                      timeout=TIMEOUT_S, period=1.0)
    frozen = _pid(sup, "tracker")
    os.kill(frozen, signal.SIGSTOP)
    try:
        assert wait_until(lambda: _pid(sup, "tracker") not in (None, frozen), timeout=TIMEOUT_S, period=0.5), \
            (root / "log" / "monitor.log").read_text()[-2000:]
    finally:
        if pid_alive(frozen):
            os.kill(frozen, signal.SIGCONT)
    log = (root / "log" / "monitor.log").read_text()
    assert re.search(rf"tracker \(pid {frozen}\) has sent no heartbeat for \d+ s .*frozen", log), log[-2000:]
    assert wait_until(lambda: _ready(deployed["url"]), timeout=TIMEOUT_S, period=1.0)


def test_the_monitor_takes_for_a_program_only_what_its_supervisord_started(tmp_path):
    """The monitor SIGKILLs by pid; a pid is taken for a program only if the process's environment names this
    supervisord's socket (supervisord gives every program SUPERVISOR_SERVER_URL): a process of another
    supervisord, one started by hand, and a pid gone are never signalled."""
    sock = tmp_path / "supervisor.sock"
    sup = Supervisor(tmp_path, sock=sock)
    env = {k: v for k, v in os.environ.items() if not k.startswith("SUPERVISOR_")}
    sleep = [sys.executable, "-c", "import time; time.sleep(60)"]
    ours = subprocess.Popen(sleep, env={**env, "SUPERVISOR_SERVER_URL": f"unix://{tmp_path}/./supervisor.sock"})
    other = subprocess.Popen(sleep, env={**env, "SUPERVISOR_SERVER_URL": f"unix://{tmp_path}/other.sock"})
    by_hand = subprocess.Popen(sleep, env=env)
    try:
        assert sup.started(ours.pid)  # the same socket, however the path was spelled
        assert not sup.started(other.pid) and not sup.started(by_hand.pid)
        assert not sup.kill(other.pid) and not sup.kill(by_hand.pid)
        assert other.poll() is None and by_hand.poll() is None
        assert sup.kill(ours.pid)
        assert ours.wait(timeout=30) == -signal.SIGKILL
        assert not sup.started(ours.pid) and not sup.kill(ours.pid)  # reaped: no such pid any more
    finally:
        for proc in (ours, other, by_hand):
            proc.kill()
            proc.wait(timeout=30)


def test_the_monitor_refuses_an_address_that_is_not_a_unix_socket(tmp_path):
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "stack-monitor", "--run-dir", str(tmp_path),
                          "--supervisor-url", "http://127.0.0.1:9001"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 2
    assert res.stderr.strip() == ("jitterguard: error: --supervisor-url: 'http://127.0.0.1:9001' is not a unix "
                                  "socket address (unix:///path/to/supervisor.sock)")
