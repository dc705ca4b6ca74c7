"""`jitterguard status` pieces: supervisorctl parsing, the stack spec round trip, and a stopped stack."""

from __future__ import annotations

from jitterguard.stack.status import collect, load_spec, parse_supervisorctl, save_spec
from jitterguard.stack.supervisor import StackSpec


def test_parse_supervisorctl_lines():
    text = ("classifier                       RUNNING   pid 123, uptime 0:01:02\n"
            "router                           RUNNING   pid 7, uptime 2 days, 3:04:05\n"
            "tracker                          BACKOFF   Exited too quickly (process log may have details)\n"
            "replay                           STOPPED   Not started\n")
    rows = {r.name: r for r in parse_supervisorctl(text)}
    assert rows["classifier"].pid == 123 and rows["classifier"].uptime_s == 62
    assert rows["router"].uptime_s == 2 * 86400 + 3 * 3600 + 4 * 60 + 5
    assert rows["tracker"].state == "BACKOFF" and rows["tracker"].pid is None
    assert rows["replay"].state == "STOPPED" and rows["replay"].uptime_s is None


def test_spec_round_trip(tmp_path):
    spec = StackSpec(ns="a", router_port=1234, sidecar_port=9, input="detections", sidecar=False)
    save_spec(tmp_path, spec)
    assert load_spec(tmp_path) == spec
    assert load_spec(tmp_path / "missing") is None


def test_collect_without_router_marks_nothing_alive():
    from jitterguard.runtime import free_tcp_port

    spec = StackSpec(ns="nobody", router_port=free_tcp_port())
    rows = collect("classifier   RUNNING   pid 5, uptime 0:00:01\n", spec, listen_s=0.2)
    assert rows[0].alive is False and rows[0].last_seq is None
