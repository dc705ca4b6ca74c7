"""`jitterguard up` under a real supervisord: the stack starts, objects flow, status and down work."""

from __future__ import annotations

import subprocess
import sys

import pytest
import zenoh

from jitterguard.runtime import ZenohOptions, build_config, free_tcp_port, open_session
from jitterguard.schemas import decode, keys
from jitterguard.schemas.models import TrackedObjects
from jitterguard.stack.supervisor import StackSpec, programs, render_config

from helpers import wait_until

pytestmark = pytest.mark.integration


def jg(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "jitterguard.cli", *args], capture_output=True, text=True, timeout=timeout)


def test_rendered_config_starts_router_first_and_restarts_everything(tmp_path):
    spec = StackSpec(ns="x", router_port=1234, input="tracks")
    progs = programs(spec)
    prio = {p.name: p.priority for p in progs}
    # the router before every service; the monitor (bookkeeping) first of all, so it is also stopped last, and its
    # watch (no Zenoh: it needs no router) before and after it
    assert all(prio["router"] < v for k, v in prio.items() if k not in ("router", "monitor", "monitor-watch"))
    assert prio["monitor-watch"] < prio["monitor"] < prio["router"]
    conf = render_config(spec, tmp_path, progs, nodaemon=True)
    for p in progs:
        kind = "eventlistener" if p.events else "program"  # the monitor-watch: its stdout is supervisord's protocol
        section = conf.split(f"[{kind}:{p.name}]")[1].split("\n[")[0]
        for line in ("autorestart=true", "startretries=10", "stopasgroup=true", "killasgroup=true"):
            assert line in section
        assert f"{p.name}.log" in section and f"{'stderr' if p.events else 'stdout'}_logfile_backups=3" in section
    assert "--connect tcp/127.0.0.1:1234" in conf


def test_up_detached_runs_the_stack_until_down(tmp_path):
    run_dir = tmp_path / "run"
    router, http = free_tcp_port(), free_tcp_port()
    ns = "stacktest"
    res = jg("up", "-d", "--ns", ns, "--input", "tracks", "--router-port", str(router), "--port", str(http),
             "--run-dir", str(run_dir))
    assert res.returncode == 0, res.stderr
    try:
        got: list[TrackedObjects] = []
        cfg = build_config(ZenohOptions(ns=ns, connect=(f"tcp/127.0.0.1:{router}",), listen=()))
        with open_session(cfg, timeout_s=60) as s:
            s.declare_subscriber(keys.objects(ns), lambda x: got.append(decode(TrackedObjects, x.payload.to_bytes())))
            assert wait_until(lambda: len(got) >= 5, timeout=60), (run_dir / "logs" / "classifier.log").read_text()
        assert any(o.kinematics.is_stationary for o in got[-1].objects)
        # replay publishes at once but supervisord calls it RUNNING only after its startsecs: poll, do not race it
        def all_running() -> bool:
            out = jg("status", "--run-dir", str(run_dir)).stdout
            return all(any(line.startswith(name) and "RUNNING" in line for line in out.splitlines())
                       for name in ("router", "classifier", "replay"))
        assert wait_until(all_running, timeout=30), jg("status", "--run-dir", str(run_dir)).stdout
        logs = jg("logs", "classifier", "--run-dir", str(run_dir))
        assert "classifier up" in logs.stdout
    finally:
        down = jg("down", "--run-dir", str(run_dir))
    assert down.returncode == 0
    assert wait_until(lambda: not (run_dir / "supervisord.pid").exists(), timeout=30)
