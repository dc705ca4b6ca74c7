"""The monitor-watch's pure parts and its edges (no supervisord here; tests/stack/test_stack_heal.py runs it for real):
the stopped-clock judge, supervisord's event-listener protocol over real byte streams, the count file, bad input,
and that it stays free of Zenoh (its reason to be a program of its own)."""

from __future__ import annotations

import io
import json
import subprocess
import sys
from pathlib import Path

from jitterguard.stack.supervisor import StackSpec, programs, render_config
from jitterguard.stack.watch import WATCH_FILE, BusSilence, StoppedJudge, freeze_limit, load_counts, save_counts, serve


def test_a_program_is_ended_only_once_stopped_for_the_limit():
    judge = StoppedJudge(limit_s=20.0)
    assert [judge.step(100, True, t) for t in (0.0, 5.0, 10.0, 15.0, 20.0)] == [False] * 4 + [True]


def test_resumed_or_replaced_starts_the_clock_again():
    judge = StoppedJudge(limit_s=20.0)
    judge.step(100, True, 0.0)
    assert not judge.step(100, False, 5.0)  # resumed (SIGCONT)
    assert [judge.step(100, True, t) for t in (10.0, 15.0, 20.0, 25.0)] == [False] * 4
    # a new pid (restarted by someone else) is judged afresh
    assert [judge.step(101, True, t) for t in (30.0, 35.0, 40.0, 45.0, 50.0)] == [False] * 4 + [True]


def test_a_listener_that_stood_still_itself_does_not_judge_its_own_pause():
    judge = StoppedJudge(limit_s=20.0, tick_s=5.0)
    judge.step(100, True, 0.0)
    assert not judge.step(100, True, 60.0)  # 60 s between ticks: the listener was paused, not the monitor watched
    assert [judge.step(100, True, t) for t in (65.0, 70.0, 75.0, 80.0)] == [False] * 3 + [True]


def test_silence_counts_only_while_the_bus_carries_the_others_heartbeats():
    """A router stopped for 25 s silences everyone; once it is back, a service whose last beat is 30 s old but
    that has not reconnected yet is silent only since the bus was heard again, not frozen (the monitor had
    killed a classifier 4 s after the router was replaced)."""
    bus = BusSilence()
    assert bus.carrying(3, 0.0)  # first heard at 0
    assert bus.silent_for(-25.0, 0.0) == 0.0  # a beat older than that: counted from then
    assert bus.carrying(3, 30.0) and bus.silent_for(0.0, 30.0) == 30.0  # silent while others were heard
    assert not bus.carrying(1, 32.0)  # the router is away: judge nothing
    assert bus.silent_for(0.0, 57.0) == 0.0
    assert bus.carrying(2, 57.0)  # back: two services heard again
    assert bus.silent_for(0.0, 59.0) == 2.0  # a third, not yet reconnected, silent for 2 s, not 59 s
    assert bus.silent_for(0.0, 77.0) == 20.0  # still silent 20 s after the others came back: frozen at a 20 s limit


def test_the_limit_is_the_monitors_own_rule():
    assert freeze_limit(10.0) == 20.0 and freeze_limit(None) is None


def test_every_event_is_answered_ok_and_a_closed_stdin_ends_it():
    events = b"".join(b"ver:3.0 server:supervisor serial:%d pool:monitor-watch poolserial:%d eventname:TICK_5 len:15\n"
                      b"when:1700000000" % (i, i) for i in range(3))
    out = io.BytesIO()
    serve(None, io.BytesIO(events), out)
    assert out.getvalue() == b"READY\nRESULT 2\nOK" * 3 + b"READY\n"


def test_the_count_survives_a_restarted_listener_and_garbage_reads_as_none(tmp_path: Path):
    save_counts(tmp_path, {"monitor": 2}, 1234)
    assert load_counts(tmp_path) == {"monitor": 2}
    assert json.loads((tmp_path / WATCH_FILE).read_text())["last_pid"] == 1234
    for junk in ("[]", "{", '{"frozen_restarts": 3}', '{"frozen_restarts": {"monitor": "x"}}'):
        (tmp_path / WATCH_FILE).write_text(junk)
        assert load_counts(tmp_path) == {}


def _watch(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "jitterguard.stack.watch", *args], capture_output=True, text=True,
                          timeout=60, env=env, input="")


def test_bad_input_is_one_line_and_exit_2(tmp_path: Path):
    import os

    env = {k: v for k, v in os.environ.items() if not k.startswith(("SUPERVISOR_", "JG_"))}
    for args, extra, says in (((), {}, "--run-dir"), (("--run-dir", str(tmp_path / "nope")), {}, "no such folder"),
                              (("--run-dir", str(tmp_path)), {}, "SUPERVISOR_SERVER_URL"),
                              (("--run-dir", str(tmp_path), "--supervisor-url", "http://x"), {}, "unix socket"),
                              (("--run-dir", str(tmp_path), "--supervisor-url", "unix:///x.sock"),
                               {"JG_WATCHDOG_S": "soon"}, "JG_WATCHDOG_S")):
        res = _watch(*args, env={**env, **extra})
        assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1 and says in res.stderr, res.stderr
        assert "Traceback" not in res.stderr


def test_it_imports_no_zenoh():
    code = "import sys, jitterguard.stack.watch; print('zenoh' in sys.modules, 'pydantic' in sys.modules)"
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert res.stdout.split() == ["False", "False"], res.stdout + res.stderr


def test_up_runs_it_as_an_event_listener_on_ticks(tmp_path: Path):
    spec = StackSpec(run_dir=str(tmp_path))
    text = render_config(spec, tmp_path, programs(spec), nodaemon=True)
    section = text.split("[eventlistener:monitor-watch]\n", 1)[1].split("\n\n", 1)[0].splitlines()
    assert "events=TICK_5" in section and "redirect_stderr=true" not in section, section
    assert f"stderr_logfile={tmp_path.resolve() / 'logs' / 'monitor-watch.log'}" in section
    assert any(line.startswith("command=") and "jitterguard.stack.watch --run-dir" in line for line in section)
