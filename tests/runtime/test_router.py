"""`jitterguard router` on a config Zenoh refuses: one line and exit 2, not a wait for ever; and a router waiting
for its port stops cleanly on SIGTERM."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import zenoh

from jitterguard.runtime import free_tcp_port

ENV = {k: v for k, v in os.environ.items() if k not in ("JG_ZENOH_CONFIG", "JG_API_TOKEN")}


def _router(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "jitterguard.cli", "router", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=ENV)


def _finish(proc: subprocess.Popen, timeout: float = 30) -> tuple[int | None, str]:
    """Exit status (None: still running after ``timeout`` s, then killed) and stderr."""
    try:
        _, err = proc.communicate(timeout=timeout)
        return proc.returncode, err
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
        return None, err


def _assert_one_line_exit_2(proc: subprocess.Popen, *words: str) -> None:
    rc, err = _finish(proc)
    lines = [line for line in err.splitlines() if line.strip()]
    assert rc == 2, err
    assert len(lines) == 1 and "cannot open the Zenoh session" in lines[0], err
    assert all(w in lines[0] for w in words) and "retrying" not in err and "Traceback" not in err, err


def test_a_router_whose_access_control_zenoh_rejects_says_so_and_exits_2(tmp_path: Path) -> None:
    """A policy naming a rule that is not there (a typo in router-host.json5) had been retried every 0.25 s for
    ever, logged as "retrying until the router at [] is up"; SIGTERM then ended it in a traceback."""
    cfg = tmp_path / "router.json5"
    cfg.write_text(json.dumps({"mode": "router", "access_control": {
        "enabled": True, "default_permission": "deny",
        "rules": [{"id": "read-all", "permission": "allow", "flows": ["ingress"], "messages": ["put"],
                   "key_exprs": ["jg/**"]}],
        "subjects": [{"id": "local", "interfaces": ["lo"]}],
        "policies": [{"rules": ["read-al"], "subjects": ["local"]}]}}))
    _assert_one_line_exit_2(_router("--zenoh-config", str(cfg), "--listen", f"tcp/127.0.0.1:{free_tcp_port()}"),
                            "Access control", "read-al")


def test_a_router_whose_certificate_is_not_pem_refuses_to_start(tmp_path: Path) -> None:
    """docs/deployment.md: a TLS file that is there but wrong makes the router refuse to start. It had waited for
    ever instead."""
    for name in ("ca.pem", "router.pem", "router-key.pem"):
        (tmp_path / name).write_text("not a certificate\n")
    cfg = tmp_path / "router.json5"
    cfg.write_text(json.dumps({"mode": "router", "transport": {"link": {"tls": {
        "root_ca_certificate": str(tmp_path / "ca.pem"), "listen_certificate": str(tmp_path / "router.pem"),
        "listen_private_key": str(tmp_path / "router-key.pem"), "enable_mtls": True}}}}))
    _assert_one_line_exit_2(_router("--zenoh-config", str(cfg), "--listen", f"tls/127.0.0.1:{free_tcp_port()}"),
                            "TLS listener")


def test_a_router_waits_for_a_busy_port_and_stops_cleanly_on_sigterm() -> None:
    """A port still held is the one thing worth waiting for (the router being replaced): it says so, and SIGTERM
    while it waits is a clean stop (it had been a traceback)."""
    port = free_tcp_port()
    held = zenoh.Config()
    held.insert_json5("mode", json.dumps("router"))
    held.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    held.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(held):
        proc = _router("--listen", f"tcp/127.0.0.1:{port}")
        err = ""
        deadline = time.monotonic() + 30
        assert proc.stderr is not None
        while time.monotonic() < deadline and "retrying" not in err:
            err += proc.stderr.readline()
        assert "Address already in use" in err and f"retrying until it can listen on tcp/127.0.0.1:{port}" in err, err
        assert "the router at" not in err
        proc.send_signal(signal.SIGTERM)
        rc, rest = _finish(proc)
    assert rc == 0 and "Traceback" not in rest, err + rest
