"""The stack's monitor stays bounded under a flood of heartbeats, and still adds up a much-restarted service.

A real router and a real `stack-monitor` process; heartbeats are published by a Zenoh client of the router, as
any process on the host may. Heartbeats of 200 made-up services (each a new pid) had each got a ledger entry,
written into ``summary.json`` every second and listed on the summary's ``dropped`` line: 20,000 of them made a
3.3 MB file and a summary line thousands of characters long, growing without bound.
"""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import time
from collections.abc import Iterator

import pytest
import zenoh

from jitterguard.runtime import ZenohOptions, build_config, free_tcp_port, open_session
from jitterguard.schemas import encode, keys
from jitterguard.schemas.models import Heartbeat
from jitterguard.schemas.wire import MAX_HEARTBEAT_BYTES, MAX_HEARTBEAT_ENTRIES
from jitterguard.stack import summary

from helpers import stop_process, wait_until

pytestmark = pytest.mark.integration


def _cli(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "jitterguard.cli", *args], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)


@contextlib.contextmanager
def _monitor(run_dir, ns: str) -> Iterator[zenoh.Session]:
    """A real router and a real `stack-monitor` on ``run_dir``; yields a client session once the monitor is heard."""
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    procs = [_cli("router", "--listen", endpoint)]
    procs.append(_cli("stack-monitor", "--ns", ns, "--connect", endpoint, "--run-dir", str(run_dir)))
    session = None
    try:
        # retried until the router is up; a router that never comes up fails here, not at pytest's timeout
        session = open_session(build_config(ZenohOptions(ns=ns, connect=(endpoint,))), timeout_s=60)
        heard: list[str] = []
        session.declare_subscriber(keys.heartbeat(ns, "monitor"), lambda s: heard.append("monitor"))
        assert wait_until(lambda: bool(heard), timeout=60, period=0.2), "the monitor never sent a heartbeat"
        yield session
    finally:
        if session is not None:
            session.close()
        for p in reversed(procs):
            stop_process(p)


def _flood_of_made_up_names(session: zenoh.Session, ns: str, t0: int, n: int = 200) -> None:
    """Heartbeats of ``n`` services nobody runs, each on its own key, as any process on the host may put them."""
    for i in range(n):
        session.put(keys.heartbeat(ns, f"ghost{i}"), encode(Heartbeat(service=f"ghost{i}", pid=50000 + i,
                                                                      stamp=t0 + i, counters={"x_dropped": 1})),
                    congestion_control=zenoh.CongestionControl.BLOCK)
        time.sleep(0.005)


def test_the_monitor_is_bounded_and_folds_restarted_processes_exactly(tmp_path):
    ns = f"mon{os.getpid()}"
    with _monitor(tmp_path, ns) as session:
        restarts = 40  # more processes of one service than the ledger keeps one by one (32)
        t0 = time.time_ns()
        # BLOCK, not Zenoh's default DROP: the test counts every tracker heartbeat and needs the oversized one to
        # reach the monitor, and a router whose queue to a monitor busy under CI load fills may drop a DROP put
        block = zenoh.CongestionControl.BLOCK
        tracker = session.declare_publisher(keys.heartbeat(ns, "tracker"), congestion_control=block)
        for i in range(restarts):
            tracker.put(encode(Heartbeat(service="tracker", pid=1000 + i, stamp=t0 + i,
                                         counters={"frames": 1, "tracks_born": 2})))
            time.sleep(0.01)
        # one heartbeat past MAX_HEARTBEAT_BYTES: refused from its size, never read into the ledger
        bloat = {f"c{i:06d}": i for i in range(MAX_HEARTBEAT_BYTES // 8)}
        session.put(keys.heartbeat(ns, "bloat"), encode(Heartbeat(service="bloat", pid=7, stamp=t0, counters=bloat)),
                    congestion_control=block)
        # one far under the byte bound but with more counters than any service reports (MAX_HEARTBEAT_ENTRIES): the
        # ledger had kept 40,000 of them per process, 32 processes of each of 64 services, rewritten every second
        wide = {f"w{i:04x}": 1 for i in range(MAX_HEARTBEAT_ENTRIES + 1)}
        session.put(keys.heartbeat(ns, "wide"), encode(Heartbeat(service="wide", pid=8, stamp=t0, counters=wide)),
                    congestion_control=block)
        _flood_of_made_up_names(session, ns, t0)
        # a heartbeat on one key that names another service is refused, not summed as the one it names
        session.put(keys.heartbeat(ns, "spoof"), encode(Heartbeat(service="tracker", pid=99, stamp=t0 + 1000,
                                                                  counters={"frames": 10**15})),
                    congestion_control=block)

        def settled() -> dict | None:
            data = summary.load(tmp_path)
            if data is None:
                return None
            mon = data["services"].get("monitor", {}).get("counters", {})
            rejected = mon.get("rejected", 0)  # the oversized one, the wide one and the spoof
            done = data["frames"]["tracked"] == restarts and mon.get("heartbeats_dropped", 0) > 0 and rejected >= 3
            return data if done else None

        assert wait_until(settled, timeout=30, period=0.5), summary.load(tmp_path)
        data = settled()
        assert data is not None
        assert len(data["services"]) <= 64  # a stack has about ten
        assert "bloat" not in data["services"] and "wide" not in data["services"]
        assert data["tracks"]["born"] == 2 * restarts  # every process counted once, the retired ones folded
        assert data["services"]["tracker"]["processes"] == restarts
        assert len(data["ledger"]["tracker"]) <= 33
        assert len(json.dumps(data["dropped"])) < 4000
        assert "spoof" not in data["services"] and "99" not in data["ledger"]["tracker"]


def test_a_services_retired_record_keeps_a_bounded_set_of_counter_names() -> None:
    """Each process of a made-up service with 100 new counter names: the retired record had kept every name ever
    sent (496,800 after 5,000 heartbeats, 8 MB). Its names stay bounded; the counts of the rest are still summed."""
    led = summary.Ledger()
    for pid in range(1000):
        assert led.observe("made-up", pid, {f"n{pid}_{j}": 1 for j in range(100)}, stamp_ns=pid)
    retired = led.procs["made-up"][summary.RETIRED]["counters"]
    assert len(retired) <= summary.MAX_COUNTER_NAMES + 1
    assert sum(led.totals("made-up").values()) == 1000 * 100  # nothing lost from the sums


def test_a_new_process_given_the_old_ones_pid_adds_to_the_totals() -> None:
    """A service restarted with the pid its last process had (a container's service is pid 1 every time; a pid
    space that wrapped) starts its counters at 0 again under that pid: its first heartbeat had replaced the old
    process's record, every frame before the restart lost from the run's totals. Told from its uptime going back."""
    led = summary.Ledger()
    for i in range(1, 11):  # the first process: 10 frames over 10 s
        assert led.observe("tracker", 1, {"frames": i, "now.tracks": 5}, stamp_ns=i, extra={"uptime_s": float(i)})
    for i in range(1, 4):  # the second, with the same pid: 3 frames
        assert led.observe("tracker", 1, {"frames": i, "now.tracks": 2}, stamp_ns=100 + i,
                           extra={"uptime_s": 0.5 + i})
    assert led.totals("tracker") == {"frames": 13, "now.tracks": 2}
    assert led.processes("tracker") == 2
    # the same process, its heartbeats only later: nothing retired, nothing counted twice
    assert led.observe("tracker", 1, {"frames": 4, "now.tracks": 2}, stamp_ns=104, extra={"uptime_s": 4.5})
    assert led.totals("tracker") == {"frames": 14, "now.tracks": 2} and led.processes("tracker") == 2
    # a ledger read back from summary.json (a restarted monitor) tells it the same way
    back = summary.Ledger.from_json(json.loads(json.dumps(led.as_json())))
    assert back.observe("tracker", 1, {"frames": 1}, stamp_ns=200, extra={"uptime_s": 1.0})
    assert back.totals("tracker")["frames"] == 15 and back.processes("tracker") == 3


def test_the_ledger_is_bounded_in_bytes_whatever_the_counter_names() -> None:
    """Within every other bound (64 services, 32 processes each, 512 counters a heartbeat, 256 KiB), made-up
    heartbeats of 490-character counter names had made a 530 MB summary.json, rewritten every second. The ledger now
    refuses a new process, or a record's growth, past MAX_LEDGER_BYTES; what it already keeps goes on adding up."""
    led = summary.Ledger()
    for i in range(1, 4):  # a real tracker, heard before the flood
        assert led.observe("tracker", 10, {"frames": i}, stamp_ns=i, extra={"uptime_s": float(i)})
    names = {f"n{j:03d}" + "x" * 490: 1 for j in range(500)}
    refused = 0
    for s in range(64):
        for pid in range(32):
            refused += not led.observe(f"made-up{s}", 1000 + pid, names, stamp_ns=pid)
    size = sum(len(json.dumps(rec)) for slot in led.procs.values() for rec in slot.values())
    assert size < summary.MAX_LEDGER_BYTES + 300_000, size  # the last record taken, and the estimate's slack
    assert refused > 0
    # a kept process's heartbeats still count, and a record cannot grow past the bound
    assert led.observe("tracker", 10, {"frames": 4}, stamp_ns=4, extra={"uptime_s": 4.0})
    assert led.totals("tracker") == {"frames": 4}
    assert not led.observe("tracker", 10, {"frames": 5, **names}, stamp_ns=5, extra={"uptime_s": 5.0})
    # the size kept is the size a restarted monitor reads back
    assert summary.Ledger.from_json(json.loads(json.dumps(led.as_json()))).size == led.size


def test_a_real_stacks_ledger_is_far_below_the_byte_bound() -> None:
    """Ten services of 25 counters, each restarted 100 times: every heartbeat taken, the totals exact."""
    led = summary.Ledger()
    counters = {f"counter_{j}.frames_dropped": 3 for j in range(25)}
    for svc in range(10):
        for pid in range(100):
            assert led.observe(f"service{svc}", pid, counters, stamp_ns=pid, extra={"uptime_s": 1.0})
    assert all(led.totals(f"service{s}")[f"counter_{j}.frames_dropped"] == 300 for s in range(10) for j in range(25))
    assert led.size < summary.MAX_LEDGER_BYTES // 4


def test_a_second_monitor_on_one_run_dir_is_refused(tmp_path) -> None:
    """Two monitors on one run directory each ended frozen programs and held back crash loops, so one freeze was
    counted twice. The second is now refused in one line, exit 2, before it opens a session; the lock goes with the
    process that holds it, so a restarted monitor takes it again."""
    import fcntl

    from jitterguard.stack.monitor import MONITOR_LOCK

    def monitor() -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "jitterguard.cli", "stack-monitor", "--run-dir", str(tmp_path),
                               "--connect", f"tcp/127.0.0.1:{free_tcp_port()}"], capture_output=True, text=True,
                              timeout=60)

    with open(tmp_path / MONITOR_LOCK, "a") as held:  # a monitor that runs
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        res = monitor()
    assert res.returncode == 2 and res.stderr.strip().count("\n") == 0, res.stderr
    assert "another stack monitor keeps" in res.stderr and not (tmp_path / summary.SUMMARY_FILE).exists()


def test_made_up_services_are_evicted_to_keep_the_stacks_own() -> None:
    """A flood of made-up service names filled both bounds (64 services, MAX_LEDGER_BYTES), and every process of a
    real service started after it was refused: a restarted tracker's counts, and its restart, missing from the
    summary. A service of the stack (``own``) now evicts made-up ones, first heard first; a made-up one never
    evicts anything, and the stack's own are never evicted."""
    led = summary.Ledger()
    assert led.observe("tracker", 10, {"frames": 5}, stamp_ns=1, extra={"uptime_s": 5.0}, own=True)
    for s in range(summary.MAX_SERVICES - 1):
        assert led.observe(f"made-up{s}", 1000 + s, {"x_dropped": 1}, stamp_ns=s)
    assert not led.observe("made-up-late", 1, {"x_dropped": 1}, stamp_ns=1)  # bound reached: refused, as before
    # the classifier, first heard now, and a new tracker process: kept, the first-heard made-up names evicted
    assert led.observe("classifier", 20, {"frames": 7}, stamp_ns=2, extra={"uptime_s": 1.0}, own=True)
    assert led.observe("tracker", 11, {"frames": 3}, stamp_ns=3, extra={"uptime_s": 1.0}, own=True)
    assert "made-up0" not in led.procs and "made-up1" in led.procs and led.evicted == 1
    assert led.totals("tracker")["frames"] == 8 and led.processes("tracker") == 2
    assert len(led.procs) == summary.MAX_SERVICES

    # the byte bound: made-up services of long counter names fill it, then a tracker restarted takes its room
    led = summary.Ledger()
    assert led.observe("tracker", 10, {"frames": 5}, stamp_ns=1, extra={"uptime_s": 5.0}, own=True)
    names = {f"n{j:03d}" + "x" * 490: 1 for j in range(500)}
    for s in range(8):
        for pid in range(32):
            led.observe(f"made-up{s}", 1000 + pid, names, stamp_ns=pid)
    for s, width in enumerate((20_000, 2_000, 200)):  # then smaller records, until less than 200 bytes are left
        pid = 0
        while pid < 32 and led.observe(f"filler{s}", pid, {"y" * width: 1}, stamp_ns=pid):
            pid += 1
    assert summary.MAX_LEDGER_BYTES - led.size < 1_000
    assert not led.observe("made-up-late", 1, {"x_dropped": 1}, stamp_ns=1)
    assert led.observe("tracker", 11, {"frames": 3, **{f"c{j}": 1 for j in range(40)}}, stamp_ns=2,
                       extra={"uptime_s": 1.0}, own=True)
    assert led.totals("tracker")["frames"] == 8 and led.evicted == 1 and "made-up0" not in led.procs
    assert led.size <= summary.MAX_LEDGER_BYTES
    assert summary.Ledger.from_json(json.loads(json.dumps(led.as_json()))).size == led.size

    # the stack's own services are never evicted, whatever comes: a bound they fill alone still refuses
    led = summary.Ledger()
    for s in range(summary.MAX_SERVICES):
        assert led.observe(f"own{s}", s, {"frames": 1}, stamp_ns=s, own=True)
    assert not led.observe("own-late", 1, {"frames": 1}, stamp_ns=1, own=True)
    assert not led.observe("made-up", 1, {"frames": 1}, stamp_ns=1)
    assert led.evicted == 0 and all(f"own{s}" in led.procs for s in range(summary.MAX_SERVICES))


def test_a_monitor_keeps_a_restarted_stage_after_a_flood_of_made_up_names(tmp_path):
    """A real router and monitor of a stack whose spec (``stack.json``) runs a tracker: 200 made-up services fill the
    ledger, then the tracker's new process heartbeats. Its counts reach the summary (they had been refused as one
    service too many), and the monitor counts the made-up services it evicted."""
    from jitterguard.stack.status import SPEC_FILE

    ns = f"mon{os.getpid()}o"
    (tmp_path / SPEC_FILE).write_text(json.dumps({"ns": ns, "input": "detections", "run_dir": str(tmp_path)}))
    with _monitor(tmp_path, ns) as session:
        block = zenoh.CongestionControl.BLOCK
        t0 = time.time_ns()
        _flood_of_made_up_names(session, ns, t0)
        session.put(keys.heartbeat(ns, "tracker"), encode(Heartbeat(service="tracker", pid=4242, stamp=t0 + 500,
                                                                    counters={"frames": 17, "tracks_born": 3})),
                    congestion_control=block)

        def settled() -> dict | None:
            data = summary.load(tmp_path)
            return data if data is not None and data["frames"].get("tracked") == 17 else None

        assert wait_until(settled, timeout=30, period=0.5), summary.load(tmp_path)
        data = settled()
        assert data is not None and data["tracks"]["born"] == 3
        mon = data["services"]["monitor"]["counters"]
        assert mon.get("ledger_services_evicted", 0) >= 1 and mon.get("heartbeats_dropped", 0) > 0
        assert len(data["services"]) <= summary.MAX_SERVICES
