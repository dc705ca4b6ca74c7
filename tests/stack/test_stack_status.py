"""`jitterguard status` pieces: the stack spec round trip, health from heartbeats, and a stack with no router."""

from __future__ import annotations

import dataclasses
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
    live = dataclasses.replace(spec, ros2_points="/points", ros2_args=("--middleware", "rmw_zenoh"))
    save_spec(tmp_path, live)
    assert load_spec(tmp_path) == live
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
        return ServiceStatus(**{"name": "tracker", "state": "RUNNING", "alive": True, "heartbeat_pid": 7,
                                "heartbeat_expected": True, **kw})

    assert row().up and row(health="ok").up  # a heartbeat without a verdict yet does not count against it
    # on the bus but silent while `status` listened: frozen (a SIGSTOPped process keeps its token ~10 s)
    assert not row(heartbeat_pid=None).up and not row(heartbeat_pid=None).heard
    assert row(heartbeat_expected=False, heartbeat_pid=None).up  # the router, or a listen shorter than a period
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


def test_a_recycled_supervisord_pid_is_a_stale_stack_not_one_starting(tmp_path):
    """After a reboot or a SIGKILL the pid in supervisord.pid may belong to another program: the stack is stale
    (`down` cleans up after it), not "starting or stopping" for ever with `down` doing nothing."""
    from jitterguard.stack.control import CONFIG, PIDFILE, StackUnavailable, Supervisor

    (tmp_path / CONFIG).write_text("[supervisord]\n")
    (tmp_path / PIDFILE).write_text(str(os.getpid()))  # alive, but pytest, not supervisord
    try:
        Supervisor(tmp_path, "t").call("getState")
        raise AssertionError("no stack answers here")
    except StackUnavailable as exc:
        assert exc.state == "stale"


def test_the_summary_counts_what_feed_tracks_published_as_replayed():
    """At `--input tracks` the program `replay` runs feed-tracks, whose heartbeat says so: its frames are the
    stack's source frames (the summary said "replayed -"), not its puts (a frame's every tracks/{id} and its
    tracked: the summary had said 1,824 replayed for ~150 frames)."""
    from jitterguard.stack import summary

    ledger = summary.Ledger()
    ledger.observe("feed-tracks", 11, {"published": 3252, "frames": 3000}, 1)
    ledger.observe("classifier", 12, {"frames_processed": 3000}, 1)
    built = summary.build(ledger, {}, meta={})
    assert built["frames"]["replayed"] == 3000 and built["frames"]["classified"] == 3000
    # with live ROS 2 in the replay's place the source frames are the scans ros2-in published, and said so
    ros = summary.Ledger()
    ros.observe("ros2-in", 13, {"published": 412, "received": 1236, "tf": 800}, 1)
    built = summary.build(ros, {}, meta={"stack": "car"})
    assert built["frames"]["replayed"] == 412 and built["frames"]["source"] == "ros2-in"
    assert "frames    from ROS 2 412, detected" in summary.render(built)


def test_a_run_dir_whose_files_are_not_what_this_version_wrote_is_read_in_one_line(tmp_path):
    """A stack.json or summary.json that is not a JSON object, or a summary from another version (a part missing):
    `status`, `summary`, `down` and a foreground `up` had ended in a traceback (AttributeError, KeyError)."""
    from jitterguard.stack import summary

    rd = tmp_path / "g"
    rd.mkdir()
    (rd / "stack.json").write_text("[1, 2]\n")
    (rd / "summary.json").write_text("[1]\n")
    assert load_spec(rd) is None and summary.load(rd) is None
    env = {**os.environ, "XDG_RUNTIME_DIR": str(tmp_path)}
    run = [sys.executable, "-m", "jitterguard.cli"]
    res = subprocess.run([*run, "status", "--run-dir", str(rd)], capture_output=True, text=True, env=env, timeout=60)
    assert res.returncode == 3 and "Traceback" not in res.stderr and len(res.stdout.splitlines()) == 1, res.stderr
    (rd / "summary.json").write_text('{"stack": "g", "frames": {"replayed": 7}, "restarts": 3}\n')
    res = subprocess.run([*run, "summary", "--run-dir", str(rd)], capture_output=True, text=True, env=env, timeout=60)
    assert res.returncode == 0 and "Traceback" not in res.stderr, res.stderr
    assert "replayed 7, detected -" in res.stdout and "restarts  none" in res.stdout


def test_the_summary_gives_a_long_run_in_hours_minutes_and_seconds():
    """A day's run had read "(86412.3 s)": from a minute on the length reads as `status`'s uptimes do."""
    from jitterguard.stack import summary

    def head(duration: float) -> str:
        return summary.render({"stack": "s", "duration_s": duration}).splitlines()[0]

    assert head(40.1) == "run summary of stack 's' (40.1 s)"
    assert head(86412.3) == "run summary of stack 's' (24:00:12)"
    assert head(3725.2) == "run summary of stack 's' (1:02:05)"


def test_summary_tells_a_corrupt_summary_and_a_file_run_dir_from_a_missing_one(tmp_path):
    """A summary.json cut short had been reported as "its monitor never wrote one" (sending the reader to the
    monitor's log), and a --run-dir that is a file as "does not exist"."""

    def summary_line(run_dir: Path) -> str:
        res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "summary", "--run-dir", str(run_dir)],
                             capture_output=True, text=True, timeout=60)
        assert res.returncode == 1 and res.stderr.count("\n") == 1, res.stderr
        return res.stderr

    cut = tmp_path / "cut short"
    cut.mkdir()
    (cut / "summary.json").write_text('{"stack": "s", "frames": {"repl')
    line = summary_line(cut)
    assert f"{cut / 'summary.json'} is not a run summary" in line and "never wrote" not in line, line
    a_file = tmp_path / "ü.png"
    a_file.write_bytes(b"\x89PNG\r\n\x1a\n")
    assert f"{a_file} is a file, not a run directory" in summary_line(a_file)
    empty = tmp_path / "empty"
    empty.mkdir()
    assert "its monitor never wrote one" in summary_line(empty)
    assert f"{tmp_path / 'none'} does not exist" in summary_line(tmp_path / "none")
