"""The monitor's crash-loop guard, its pure part (:mod:`jitterguard.stack.backoff`): when a program that keeps
crashing after it started is held back, for how long, when it is started again, and what it leaves alone; and
what supervisord's log, the summary and ``status`` make of it."""

from __future__ import annotations

import json

import pytest

from jitterguard.stack import summary
from jitterguard.stack.backoff import CrashLoopGuard, CrashLoopPolicy
from jitterguard.stack.control import ProcessInfo
from jitterguard.stack.status import _not_running, held_back

POLICY = CrashLoopPolicy(exits=5, window_s=60.0, backoff_s=10.0, backoff_max_s=300.0)


def crashing(guard: CrashLoopGuard, name: str, t0: float, n: int, every: float = 2.0, crashes=None):
    """``n`` crashes ``every`` s apart from ``t0``, the guard asked after each (state RUNNING, as supervisord
    restarts such a program at once); the action of the last step that gave one, and the crash list."""
    crashes = [] if crashes is None else crashes
    got = None
    for i in range(n):
        crashes.append(t0 + i * every)
        action = guard.step(name, "RUNNING", crashes, t0 + i * every + 0.5)
        got = action or got
    return got, crashes


def release(guard: CrashLoopGuard, name: str, crashes: list[float], until: float) -> float:
    """Stopped, then started when the hold has run out; the time it was started."""
    assert guard.step(name, "STOPPED", crashes, until - 1) is None
    start = guard.step(name, "STOPPED", crashes, until)
    assert start is not None and start.kind == "start"
    assert guard.step(name, "STARTING", crashes, until + 2) is None  # seen started: the hold is over
    assert guard.held_back() == {}
    return until


def test_five_crashes_within_the_window_hold_it_back_once():
    guard = CrashLoopGuard(POLICY, since=0.0)
    action, crashes = crashing(guard, "detector", 100.0, 4)
    assert action is None  # four are no loop
    action = guard.step("detector", "RUNNING", [*crashes, 108.0], 108.5)
    assert action is not None and action.kind == "stop" and action.warn
    assert (action.crashes, action.loop, action.hold_s, action.until) == (5, 1, 10.0, 118.5)
    assert guard.held_back() == {"detector": 118.5} and guard.backed_off() == {"detector": 1}
    # the stop has not taken yet (supervisord refused it while the program was EXITED): asked again, quietly
    again = guard.step("detector", "EXITED", [*crashes, 108.0], 110.5)
    assert again is not None and again.kind == "stop" and not again.warn
    assert guard.step("detector", "STOPPING", [*crashes, 108.0], 111.0) is None
    assert guard.step("detector", "STOPPED", [*crashes, 108.0], 112.0) is None
    assert guard.backed_off() == {"detector": 1}


def test_crashes_spread_wider_than_the_window_are_no_loop():
    guard = CrashLoopGuard(POLICY, since=0.0)
    action, _ = crashing(guard, "detector", 100.0, 20, every=16.0)  # four within any 60 s
    assert action is None and guard.held_back() == {}


def test_crashes_before_the_run_or_the_monitor_are_not_counted():
    guard = CrashLoopGuard(POLICY, since=1000.0)
    old = [990.0, 992.0, 994.0, 996.0]
    assert guard.step("detector", "RUNNING", [*old, 1001.0], 1001.5) is None


def test_the_back_off_doubles_per_loop_up_to_the_cap():
    guard = CrashLoopGuard(POLICY, since=0.0)
    t, crashes, holds = 100.0, [], []
    for _ in range(8):
        action, crashes = crashing(guard, "detector", t, 5, crashes=crashes)
        assert action is not None and action.kind == "stop" and action.warn
        holds.append(action.hold_s)
        t = release(guard, "detector", crashes, action.until) + 1.0
    assert holds == [10, 20, 40, 80, 160, 300, 300, 300]
    assert guard.backed_off() == {"detector": 8}


def test_after_a_start_only_new_crashes_count():
    """The crashes that made the last loop are still within the window when the program is started again: the
    first new one must not hold it back at once."""
    guard = CrashLoopGuard(POLICY, since=0.0)
    action, crashes = crashing(guard, "detector", 100.0, 5)
    started = release(guard, "detector", crashes, action.until)
    crashes.append(started + 1.5)
    assert guard.step("detector", "RUNNING", crashes, started + 2.0) is None
    action, crashes = crashing(guard, "detector", started + 3.5, 4, crashes=crashes)
    assert action is not None and action.crashes == 5 and action.loop == 2 and action.hold_s == 20.0


def test_the_back_off_starts_again_once_the_program_stayed_up_for_a_window():
    guard = CrashLoopGuard(POLICY, since=0.0)
    action, crashes = crashing(guard, "detector", 100.0, 5)
    started = release(guard, "detector", crashes, action.until)
    assert guard.step("detector", "RUNNING", crashes, started + 30.0) is None  # up half a window: no reset yet
    assert guard.programs["detector"].loop == 1
    assert guard.step("detector", "RUNNING", crashes, started + 61.0) is None
    assert guard.programs["detector"].loop == 0
    action, crashes = crashing(guard, "detector", started + 100.0, 5, crashes=crashes)
    assert action is not None and action.loop == 1 and action.hold_s == 10.0


def test_a_crash_after_the_start_delays_the_reset_until_a_quiet_window():
    guard = CrashLoopGuard(POLICY, since=0.0)
    action, crashes = crashing(guard, "detector", 100.0, 5)
    started = release(guard, "detector", crashes, action.until)
    crashes.append(started + 40.0)
    assert guard.step("detector", "RUNNING", crashes, started + 70.0) is None
    assert guard.programs["detector"].loop == 1  # 30 s since its last crash
    assert guard.step("detector", "RUNNING", crashes, started + 101.0) is None
    assert guard.programs["detector"].loop == 0


@pytest.mark.parametrize("state", ["STOPPED", "FATAL"])
def test_a_program_stopped_by_an_operator_or_given_up_on_is_left_alone(state):
    guard = CrashLoopGuard(POLICY, since=0.0)
    _, crashes = crashing(guard, "detector", 100.0, 4)
    assert guard.step("detector", state, [*crashes, 108.0], 108.5) is None
    assert guard.step("detector", state, [*crashes, 108.0], 500.0) is None  # never started again by the guard
    assert guard.held_back() == {} and guard.backed_off() == {}
    # started again by the operator: its crashes before are forgotten, new ones count from one
    assert guard.step("detector", "RUNNING", [*crashes, 108.0, 501.0], 501.5) is None


def test_an_operator_starting_a_held_program_ends_the_hold():
    guard = CrashLoopGuard(POLICY, since=0.0)
    action, crashes = crashing(guard, "detector", 100.0, 5)
    assert guard.step("detector", "STOPPED", crashes, action.until - 5) is None
    assert guard.step("detector", "RUNNING", crashes, action.until - 4) is None  # `supervisorctl start detector`
    assert guard.held_back() == {}
    assert guard.step("detector", "RUNNING", crashes, action.until) is None  # and not stopped again


def test_a_failed_start_is_asked_for_again():
    guard = CrashLoopGuard(POLICY, since=0.0)
    action, crashes = crashing(guard, "detector", 100.0, 5)
    assert guard.step("detector", "STOPPED", crashes, action.until - 1) is None
    assert guard.step("detector", "STOPPED", crashes, action.until).kind == "start"
    assert guard.step("detector", "STOPPED", crashes, action.until + 2).kind == "start"  # supervisord refused it
    assert guard.held_back() == {"detector": action.until}


def test_the_monitor_never_holds_itself_back_and_the_router_is_held_as_any():
    guard = CrashLoopGuard(POLICY, since=0.0)
    assert crashing(guard, "monitor", 100.0, 10)[0] is None
    assert crashing(guard, "router", 100.0, 5)[0].kind == "stop"


def test_zero_exits_turns_the_guard_off():
    guard = CrashLoopGuard(CrashLoopPolicy(exits=0), since=0.0)
    assert crashing(guard, "detector", 100.0, 50, every=0.5)[0] is None


def test_a_restarted_monitor_keeps_the_hold_and_the_counts():
    guard = CrashLoopGuard(POLICY, since=0.0)
    action, crashes = crashing(guard, "detector", 100.0, 5)
    saved = json.loads(json.dumps(guard.as_json()))
    again = CrashLoopGuard(POLICY, since=0.0)
    again.restore(saved, now=111.0)
    assert again.held_back() == {"detector": action.until} and again.backed_off() == {"detector": 1}
    assert again.step("detector", "STOPPED", crashes, action.until).kind == "start"
    assert again.step("detector", "STARTING", crashes, action.until + 2) is None
    action, crashes = crashing(again, "detector", action.until + 3, 5, crashes=crashes)
    assert action.loop == 2 and action.hold_s == 20.0 and again.backed_off() == {"detector": 2}


def test_the_policy_reads_its_environment():
    assert CrashLoopPolicy.from_env({}) == CrashLoopPolicy(5, 60.0, 10.0, 300.0)
    env = {"JG_CRASH_LOOP_EXITS": "3", "JG_CRASH_LOOP_WINDOW_S": "20", "JG_CRASH_LOOP_BACKOFF_S": "4",
           "JG_CRASH_LOOP_BACKOFF_MAX_S": "30"}
    assert CrashLoopPolicy.from_env(env) == CrashLoopPolicy(3, 20.0, 4.0, 30.0)
    for bad in ({"JG_CRASH_LOOP_EXITS": "many"}, {"JG_CRASH_LOOP_EXITS": "2.5"}, {"JG_CRASH_LOOP_WINDOW_S": "0"},
                {"JG_CRASH_LOOP_BACKOFF_S": "nan"}, {"JG_CRASH_LOOP_BACKOFF_MAX_S": "inf"}):
        with pytest.raises(ValueError, match="JG_CRASH_LOOP_"):
            CrashLoopPolicy.from_env(bad)



def test_the_environment_numbers_say_one_line_each_what_is_wrong(monkeypatch):
    """JG_CRASH_LOOP_* and JG_WATCHDOG_S go through one parser (runtime.envvars.env_number): the variable, its
    value and the range it must be in."""
    from jitterguard.runtime.envvars import watchdog_period

    with pytest.raises(ValueError) as err:
        CrashLoopPolicy.from_env({"JG_CRASH_LOOP_WINDOW_S": "0.5"})
    assert str(err.value) == "JG_CRASH_LOOP_WINDOW_S='0.5': expected a number from 1 to 1e9"
    with pytest.raises(ValueError) as err:
        CrashLoopPolicy.from_env({"JG_CRASH_LOOP_BACKOFF_S": "soon"})
    assert str(err.value) == "JG_CRASH_LOOP_BACKOFF_S='soon' is not a number"
    monkeypatch.setenv("JG_WATCHDOG_S", "1e12")
    with pytest.raises(ValueError) as err:
        watchdog_period()
    assert str(err.value) == "JG_WATCHDOG_S='1e12': expected at most 1e9 s (0 turns the watchdog off)"
    monkeypatch.setenv("JG_WATCHDOG_S", " -1 ")
    assert watchdog_period() is None
    monkeypatch.setenv("JG_WATCHDOG_S", "")
    assert watchdog_period() == 10.0


def test_only_exits_after_running_are_crash_loop_exits(tmp_path):
    """supervisord backs off (and gives up on) a program that dies before its startsecs by itself: only the exits
    of a process that had reached RUNNING are the guard's."""
    log = tmp_path / "supervisord.log"
    log.write_text("\n".join([
        "2026-12-04 17:50:10,000 INFO spawned: 'detector' with pid 100",
        "2026-12-04 17:50:11,000 INFO success: detector entered RUNNING state, process has stayed up for > than 1"
        " seconds (startsecs)",
        "2026-12-04 17:50:11,500 WARN exited: detector (exit status 1; not expected)",
        "2026-12-04 17:50:12,000 INFO spawned: 'detector' with pid 101",
        "2026-12-04 17:50:12,400 WARN exited: detector (exit status 1; not expected)",  # too quickly: BACKOFF
        "2026-12-04 17:50:13,000 INFO spawned: 'detector' with pid 102",
        "2026-12-04 17:50:14,000 INFO success: detector entered RUNNING state, process has stayed up for > than 1"
        " seconds (startsecs)",
        "2026-12-04 17:50:15,000 INFO stopped: detector (terminated by SIGTERM)",
    ]) + "\n")
    ev = summary.supervisor_events(log)["detector"]
    assert len(ev.crashes) == 2 and len(ev.running_crashes) == 1
    assert ev.running_crashes[0] == ev.crashes[0][0]


def test_the_monitor_parses_supervisords_log_again_only_when_it_changed(tmp_path):
    """Two threads ask for the events every second or two; an unchanged log is not parsed again, a grown or rotated
    one is, and what is read is what supervisor_events reads."""
    import os

    log = tmp_path / "supervisord.log"
    lines = ["2026-12-04 17:50:10,000 INFO spawned: 'detector' with pid 100",
             "2026-12-04 17:50:11,000 INFO success: detector entered RUNNING state, process has stayed up for > than 1"
             " seconds (startsecs)"]
    log.write_text("\n".join(lines) + "\n")
    reader = summary.SupervisorLog(log)
    first = reader.events()
    assert first["detector"].running and reader.events() is first  # unchanged: the same parse
    with log.open("a") as f:
        f.write("2026-12-04 17:50:11,500 WARN exited: detector (exit status 1; not expected)\n")
    grown = reader.events()
    assert grown is not first and grown["detector"].running_crashes == [summary.supervisor_events(log)["detector"].running_crashes[0]]
    os.replace(log, tmp_path / "supervisord.log.1")  # rotated: the old text moves, a new log starts
    log.write_text("2026-12-04 17:50:12,000 INFO spawned: 'detector' with pid 101\n")
    rotated = reader.events()
    assert rotated is not grown and rotated["detector"].spawns[-1] > grown["detector"].spawns[-1]
    assert len(rotated["detector"].crashes) == 1  # the rotated file is still read
    late = summary.SupervisorLog(log, since=1e12)  # the run's own events only
    assert late.events() == {}


def test_the_summary_and_status_name_a_held_back_program(tmp_path):
    built = summary.build(summary.Ledger(), {}, meta={"stack": "s"},
                          backoff={"held_back_until_s": {"detector": 1117.0}, "backed_off": {"detector": 2}})
    rs = built["restarts"]
    assert rs["backed_off"] == {"detector": 2} and rs["held_back"] == ["detector"]
    assert "held back after crash loops: detector 2 (now: detector)" in summary.render(built)
    plain = summary.build(summary.Ledger(), {}, meta={"stack": "s"})
    assert plain["restarts"]["held_back"] == [] and "held back" not in summary.render(plain)

    summary.save(tmp_path, built)
    assert held_back(tmp_path, now=1100.0) == {"detector": 17.0}
    assert held_back(tmp_path / "nowhere") == {} and held_back(None) == {}
    log = tmp_path / "detector.log"
    log.write_text("RuntimeError: weights file truncated\n")
    proc = ProcessInfo("detector", "STOPPED", None, None, 0, "", str(log))
    assert _not_running(proc, 17.0) == ("backoff (crash loop: held back by the monitor, next start in 17 s); its log"
                                      " ends: RuntimeError: weights file truncated")
    assert "overdue: is the monitor running?" in _not_running(proc, -60.0)
