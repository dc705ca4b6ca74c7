"""`jitterguard status` pieces: the stack spec round trip, health from heartbeats, and a stack with no router."""

from __future__ import annotations

from types import SimpleNamespace

from jitterguard.stack.control import ProcessInfo
from jitterguard.stack.status import collect, heartbeat_health, load_spec, save_spec
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


def test_heartbeat_health_reads_whatever_verdict_the_heartbeat_carries():
    assert heartbeat_health(SimpleNamespace(last_seq=3)) == (None, "")
    assert heartbeat_health(SimpleNamespace(healthy=False, problems=["frames failing", "output stalled"])) == (
        False, "frames failing, output stalled")
    assert heartbeat_health(SimpleNamespace(ok=True)) == (True, "")
    assert heartbeat_health(SimpleNamespace(health="ok", health_reason="")) == (True, "")
    assert heartbeat_health(SimpleNamespace(health="stalled", health_reason="no output for 5 s")) == (
        False, "stalled: no output for 5 s")


def test_collect_without_router_marks_nothing_alive_and_nothing_up():
    from jitterguard.runtime import free_tcp_port

    spec = StackSpec(ns="nobody", router_port=free_tcp_port())
    procs = [ProcessInfo("classifier", "RUNNING", 5, 1.0, None, "", "")]
    rows = collect(procs, spec, listen_s=0.2)
    assert rows[0].alive is False and rows[0].last_seq is None and not rows[0].up
