"""`jitterguard status` pieces: the stack spec round trip, health from heartbeats, and a stack with no router."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from helpers import wait_until

from jitterguard.stack.control import ProcessInfo, pid_alive
from jitterguard.stack.status import ServiceStatus, collect, load_spec, save_spec
from jitterguard.stack.supervisor import StackSpec


def test_spec_round_trip(tmp_path):
    spec = StackSpec(ns="a", name="b", router_port=1234, sidecar_port=9, input="detections", sidecar=False,
                     replay_args=("--topic", "/x"), run_dir=str(tmp_path))
    save_spec(tmp_path, spec)
    assert load_spec(tmp_path) == spec
    assert load_spec(tmp_path / "missing") is None
    (tmp_path / "stack.json").write_text("{not json")
    assert load_spec(tmp_path) is None


def test_process_info_from_supervisor_rpc():
    p = ProcessInfo.from_rpc({"name": "tracker", "statename": "RUNNING", "pid": 42, "start": 100, "now": 162,
                              "exitstatus": 0, "description": "pid 42, uptime 0:01:02", "stdout_logfile": "/x.log"})
    assert (p.name, p.state, p.pid, p.uptime_s) == ("tracker", "RUNNING", 42, 62.0)
    b = ProcessInfo.from_rpc({"name": "replay", "statename": "BACKOFF", "pid": 0, "start": 100, "now": 162,
                              "exitstatus": 2, "description": "Exited too quickly"})
    assert b.pid is None and b.uptime_s is None and b.state == "BACKOFF"


def test_a_service_is_up_only_when_running_on_the_bus_and_making_progress():
    def row(**kw):
        return ServiceStatus(**{"name": "tracker", "state": "RUNNING", "alive": True, **kw})

    assert row().up and row(health="ok").up  # a heartbeat without a verdict yet does not count against it
    assert not row(health="stalled", health_reason="no output for 5.0 s").up
    assert not row(health="failing").up
    assert not row(alive=False).up and not row(state="BACKOFF").up


def test_collect_without_router_marks_nothing_alive_and_nothing_up():
    from jitterguard.runtime import free_tcp_port

    spec = StackSpec(ns="nobody", router_port=free_tcp_port())
    procs = [ProcessInfo("classifier", "RUNNING", 5, 1.0, None, "", "")]
    rows = collect(procs, spec, listen_s=0.2)
    assert rows[0].alive is False and rows[0].last_seq is None and not rows[0].up


def test_a_killed_supervisord_not_yet_reaped_counts_as_dead():
    """A daemonised supervisord killed by SIGKILL stays a zombie until init reaps it: `status` must not take it
    for a stack that is still starting."""
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    try:
        assert wait_until(lambda: Path(f"/proc/{child.pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z",
                          timeout=30)
        assert not pid_alive(child.pid)
    finally:
        child.wait()
    assert pid_alive(os.getpid()) and not pid_alive(child.pid)
