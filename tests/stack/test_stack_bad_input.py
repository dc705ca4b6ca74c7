"""`up --on-error stop`: a replay that stops on a bad frame is not restarted, and the operator is told why.

The replay stops on an unreadable frame with status 65 (``EXIT_BAD_INPUT``). The stack's replay program takes that
status as expected (``exitcodes=65``, ``autorestart=unexpected``), so supervisord leaves it stopped: with status 1
it had been started again, met the same frame, and so on — a crash loop made of a deliberate stop. ``up`` says in
one line that the replay stopped on bad input (the tail of its log names the frame) and stops the stack; ``status``
and ``summary`` of a detached stack say it too.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from jitterguard.runtime import free_tcp_port
from jitterguard.runtime.service import EXIT_BAD_INPUT
from jitterguard.stack import summary
from jitterguard.stack.control import ProcessInfo, Supervisor
from jitterguard.stack.status import _not_running
from jitterguard.stack.supervisor import StackSpec, programs, render_config

from replay.bagfixture import DET_TOPIC, write_bag


def _sections(text: str) -> dict[str, dict[str, str]]:
    out: dict[str, dict[str, str]] = {}
    cur: dict[str, str] | None = None
    for line in text.splitlines():
        if line.startswith("[program:"):
            cur = out.setdefault(line[len("[program:"):-1], {})
        elif cur is not None and "=" in line:
            k, v = line.split("=", 1)
            cur[k] = v
    return out


@pytest.mark.parametrize("level", ["points", "detections"])
def test_the_stacks_replay_is_not_restarted_after_a_stop_on_bad_input_and_the_rest_are(tmp_path, level):
    spec = StackSpec(input=level, run_dir=str(tmp_path))
    conf = _sections(render_config(spec, tmp_path, programs(spec), nodaemon=True))
    assert conf["replay"]["autorestart"] == "unexpected"
    assert conf["replay"]["exitcodes"] == str(EXIT_BAD_INPUT)  # 0 is still unexpected: restarted, as before
    assert int(conf["replay"]["startsecs"]) < 3  # below SUPERVISED_STOP_AFTER_S (test_replay_zenoh)
    for name, section in conf.items():
        if name != "replay":
            assert section["autorestart"] == "true" and section["exitcodes"] == "0", name
    tracks = StackSpec(input="tracks", run_dir=str(tmp_path))  # feed-tracks has no --on-error: as before
    assert _sections(render_config(tracks, tmp_path, programs(tracks), nodaemon=True))["replay"]["autorestart"] == "true"


LOG = """\
2026-12-04 17:50:10,000 INFO spawned: 'replay' with pid 100
2026-12-04 17:50:12,000 INFO success: replay entered RUNNING state, process has stayed up for > than 2 seconds (startsecs)
2026-12-04 17:50:14,000 INFO exited: replay (exit status 65; expected)
"""


def test_a_stop_on_bad_input_is_read_from_supervisords_log_and_is_no_crash(tmp_path):
    log = tmp_path / "supervisord.log"
    log.write_text(LOG)
    events = summary.supervisor_events(log)
    assert events["replay"].crashes == [] and events["replay"].running_crashes == []
    assert summary.stopped_on_bad_input(events) == ["replay"]
    assert summary.crash_loop(events, events["replay"].spawns[0] + 5) is None
    built = summary.build(summary.Ledger(), events, meta={"stack": "s"})
    assert built["restarts"]["stopped_on_bad_input"] == ["replay"]
    assert "stopped on bad input (not restarted): replay" in summary.render(built)
    # started again by hand (`supervisorctl start replay`): no longer stopped
    log.write_text(LOG + "2026-12-04 17:51:00,000 INFO spawned: 'replay' with pid 101\n")
    assert summary.stopped_on_bad_input(summary.supervisor_events(log)) == []
    # an exit of another status that supervisord expected (0 under a hand-written config) is no stop on bad input
    log.write_text(LOG.replace("exit status 65", "exit status 0"))
    assert summary.stopped_on_bad_input(summary.supervisor_events(log)) == []


def test_status_says_why_a_replay_stopped_on_bad_input(tmp_path):
    log = tmp_path / "replay.log"
    log.write_text("jitterguard: error: stopped at unreadable frame bag: message 1: label 42\n")
    proc = ProcessInfo("replay", "EXITED", None, None, EXIT_BAD_INPUT, "", str(log))
    assert _not_running(proc) == ("stopped on bad input (exit status 65, --on-error stop): not restarted; its log"
                                  " ends: jitterguard: error: stopped at unreadable frame bag: message 1: label 42;"
                                  " no frames enter the pipeline")


def jg(*args: str, cwd: Path, env: dict[str, str], timeout: float = 180) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "jitterguard.cli", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=cwd, env=env)


@pytest.mark.integration
@pytest.mark.parametrize("detach", [True, False])
def test_up_with_on_error_stop_and_an_early_bad_frame_says_so_and_restarts_nothing(tmp_path, detach):
    """A bag whose second detection message fails validation (the probe reads the first, good one): the replay
    stops on it, once; `up` says why and stops the stack (exit 1), in the background and in the foreground."""
    write_bag(tmp_path / "bag", n=20, bad_label_at=1)
    env = {**os.environ, "XDG_RUNTIME_DIR": str(tmp_path / "xdg")}
    rd = tmp_path / "xdg" / "jitterguard" / "bad"
    res = jg("up", "bag", *(["-d"] if detach else ["--duration", "120"]), "--name", "bad", "--ns",
             f"bad{os.getpid()}", "--router-port", str(free_tcp_port()), "--no-sidecar", "--topic", DET_TOPIC,
             "--on-error", "stop", cwd=tmp_path, env=env)
    try:
        assert res.returncode == 1, res.stdout + res.stderr
        assert "jitterguard: error: replay stopped on bad input (--on-error stop, exit status 65) and is not " \
               "restarted; the stack is stopped." in res.stderr, res.stderr
        assert "stopped at unreadable frame" in res.stderr and "label" in res.stderr, res.stderr
        assert "keeps failing" not in res.stderr and "jitterguard: started" not in res.stdout, res.stdout + res.stderr
        events = summary.supervisor_events(rd / "logs" / "supervisord.log")
        assert len(events["replay"].spawns) == 1 and events["replay"].crashes == [], events["replay"]
    finally:
        if Supervisor(rd).running():
            jg("down", "--name", "bad", cwd=tmp_path, env=env)
    assert not Supervisor(rd).running()


@pytest.mark.parametrize("module", ["jitterguard.stack.summary", "jitterguard.stack.status",
                                    "jitterguard.stack.supervisor"])
def test_the_stacks_readers_of_the_exit_status_import_no_zenoh(module: str):
    """summary, status and supervisor need the number 65, not the service runtime: taken from
    :mod:`jitterguard.runtime.service` it had brought Zenoh and pydantic along. The runtime still offers the name,
    the same number."""
    from jitterguard.runtime import exit_codes

    code = f"import sys, {module}; print('zenoh' in sys.modules, 'pydantic' in sys.modules)"
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert res.stdout.split() == ["False", "False"], res.stdout + res.stderr
    assert EXIT_BAD_INPUT == exit_codes.EXIT_BAD_INPUT == 65
