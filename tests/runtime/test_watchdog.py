"""The watchdog restarts a service that stopped making progress: it exits non-zero (what supervisord and
systemd restart) after saying so in its heartbeat. Real processes, real Zenoh on loopback; the service's
handler is broken on purpose (``poisoned_service.py``)."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh

from helpers import wait_until
from jitterguard.runtime import build_config, free_tcp_port, loopback_options
from jitterguard.runtime.service import EXIT_NO_PROGRESS
from jitterguard.schemas import decode
from jitterguard.schemas.models import Heartbeat

pytestmark = pytest.mark.integration
SCRIPT = Path(__file__).with_name("poisoned_service.py")


def _run(mode: str, tmp_path: Path) -> tuple[int, list[Heartbeat], str]:
    ns, port = f"wd{mode}{os.getpid()}", free_tcp_port()
    log = tmp_path / f"{mode}.log"
    env = {**os.environ, "JG_WATCHDOG_S": "2", "PYTHONPATH": os.pathsep.join(sys.path)}
    with open(log, "wb") as out:
        proc = subprocess.Popen([sys.executable, str(SCRIPT), mode, ns, str(port)], stdout=out,
                                stderr=subprocess.STDOUT, env=env)
    beats: list[Heartbeat] = []
    try:
        with zenoh.open(build_config(loopback_options(ns, port))) as s:
            s.declare_subscriber(f"jg/{ns}/heartbeat/poisoned",
                                 lambda sample: beats.append(decode(Heartbeat, sample.payload.to_bytes())))
            stop = threading.Event()

            def feed() -> None:  # input keeps arriving, as detections would
                while not stop.wait(0.1):
                    s.put(f"jg/{ns}/input", b"frame")

            feeder = threading.Thread(target=feed, daemon=True)
            feeder.start()
            try:
                proc.wait(timeout=60)
            finally:
                stop.set()
                feeder.join()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc.returncode, beats, log.read_text(errors="replace")


@pytest.mark.parametrize("mode, health", [("fail", "failing"), ("stall", "stalled")])
def test_a_service_that_makes_no_progress_says_so_and_exits_for_its_supervisor(tmp_path, mode, health):
    code, beats, log = _run(mode, tmp_path)
    assert code == EXIT_NO_PROGRESS, log
    reported = [b for b in beats if b.health == health]
    assert reported, [(b.health, b.health_reason) for b in beats]
    assert ("MemoryError" in reported[-1].health_reason) if mode == "fail" else ("no output" in reported[-1].health_reason)
    assert "no progress" in log and f"status {EXIT_NO_PROGRESS}" in log


def test_a_hung_process_is_ended_by_the_timer_that_needs_no_gil(tmp_path):
    t0 = time.monotonic()
    code, _, log = _run("hang", tmp_path)
    assert code == 1, log
    assert "Timeout" in log and "poisoned_service.py" in log, log  # faulthandler's dump: where it hung
    assert time.monotonic() - t0 < 60


@pytest.mark.parametrize("raw", ["inf", "nan", "1e12", "ten"])
def test_a_watchdog_period_no_timer_can_wait_is_a_startup_error(monkeypatch, raw):
    """`JG_WATCHDOG_S=inf` had crashed the heartbeat and main threads with OverflowError while arming faulthandler's
    timer, and the process then hung past SIGTERM: now it is refused at start, like a value that is no number."""
    from jitterguard.runtime.envvars import watchdog_period

    monkeypatch.setenv("JG_WATCHDOG_S", raw)
    with pytest.raises(ValueError, match="JG_WATCHDOG_S"):
        watchdog_period()
    monkeypatch.setenv("JG_WATCHDOG_S", "0")
    assert watchdog_period() is None


def test_a_bad_watchdog_period_is_refused_before_the_service_waits_for_its_router():
    """It had been read once the session was open: with no router up, the service waited on, and a typo in the
    environment showed only when the router came."""
    nobody = free_tcp_port()  # nothing listens there
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "classifier", "--connect",
                          f"tcp/127.0.0.1:{nobody}"], env={**os.environ, "JG_WATCHDOG_S": "ten"},
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2, res.stderr
    assert "JG_WATCHDOG_S='ten' is not a number of seconds" in res.stderr
    assert "cannot open the Zenoh session" not in res.stderr
