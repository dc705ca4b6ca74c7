"""The burst logger: one line per burst of a kind, a line a minute at least while a burst goes on, kinds apart."""

from __future__ import annotations

import logging

import pytest

from jitterguard.runtime import service as svc_mod
from jitterguard.runtime.service import _BurstLogger


@pytest.fixture
def clock(monkeypatch):
    now = [1000.0]
    monkeypatch.setattr(svc_mod.time, "monotonic", lambda: now[0])
    return now


def test_a_trickle_of_one_kind_does_not_hide_another_and_still_speaks_each_minute(clock, caplog) -> None:
    """One junk payload a second had kept every later warning of the service out of the log — an unauthorised
    config write among them — and after its first line the trickle itself said nothing more."""
    log = _BurstLogger(logging.getLogger("jitterguard.test-burst"), quiet_s=5.0, summary_s=60.0)
    with caplog.at_level(logging.WARNING, logger="jitterguard.test-burst"):
        for t in range(130):
            clock[0] = 1000.0 + t
            log.warn(f"rejected payload {t}", kind="rejected tracks/*")
            if t == 7:
                log.warn("config write refused: no token", kind="config write refused")
    lines = [r.getMessage() for r in caplog.records]
    assert "config write refused: no token" in lines
    junk = [ln for ln in lines if ln.startswith("rejected payload")]
    assert [ln.split(" (")[0] for ln in junk] == ["rejected payload 0", "rejected payload 60", "rejected payload 120"]
    assert junk[1].endswith("(59 similar since the last message)")


def test_a_burst_that_passed_logs_its_next_event_at_once(clock, caplog) -> None:
    log = _BurstLogger(logging.getLogger("jitterguard.test-burst2"), quiet_s=5.0, summary_s=60.0)
    with caplog.at_level(logging.WARNING, logger="jitterguard.test-burst2"):
        for t in (0.0, 0.5, 1.0, 7.0):
            clock[0] = 1000.0 + t
            log.warn(f"e{t}")
    assert [r.getMessage() for r in caplog.records] == ["e0.0", "e7.0 (2 similar since the last message)"]
