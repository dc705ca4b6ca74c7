"""Multi-host in network namespaces: the router on one "host", classifier and feeder on another, joined by a
veth link, talking mutual TLS with deploy/zenoh/router-host.json5 and service-host.json5 (paths patched to a
throwaway CA). Needs root and ``ip netns``; skipped otherwise."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from test_stack_deploy import DEPLOY, _make_pki

pytestmark = pytest.mark.integration

R_IP, S_IP = "10.77.0.1", "10.77.0.2"


def _netns_ok() -> bool:
    if os.geteuid() != 0 or shutil.which("ip") is None or shutil.which("openssl") is None:
        return False
    probe = f"jgprobe{os.getpid()}"
    ok = subprocess.run(["ip", "netns", "add", probe], capture_output=True).returncode == 0
    if ok:
        subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    return ok


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True)


@pytest.fixture
def two_hosts():
    if not _netns_ok():
        pytest.skip("needs root and `ip netns`")
    tag = f"{os.getpid() % 100000}"
    r, s = f"jgr{tag}", f"jgs{tag}"
    _ip("netns", "add", r)
    _ip("netns", "add", s)
    try:
        _ip("link", "add", f"vr{tag}", "type", "veth", "peer", "name", f"vs{tag}")
        _ip("link", "set", f"vr{tag}", "netns", r)
        _ip("link", "set", f"vs{tag}", "netns", s)
        for ns, dev, addr in ((r, f"vr{tag}", R_IP), (s, f"vs{tag}", S_IP)):
            _ip("-n", ns, "addr", "add", f"{addr}/24", "dev", dev)
            _ip("-n", ns, "link", "set", dev, "up")
            _ip("-n", ns, "link", "set", "lo", "up")
        yield r, s
    finally:
        subprocess.run(["ip", "netns", "del", r], capture_output=True)
        subprocess.run(["ip", "netns", "del", s], capture_output=True)


def _patch(src: Path, dst: Path, pki: Path, cert: str) -> Path:
    text = src.read_text()
    text = text.replace("/etc/jitterguard/tls/ca.pem", str(pki / "ca.pem"))
    text = text.replace("/etc/jitterguard/tls/router.pem", str(pki / "router.pem"))
    text = text.replace("/etc/jitterguard/tls/router-key.pem", str(pki / "router-key.pem"))
    text = text.replace("/etc/jitterguard/tls/host.pem", str(pki / f"{cert}.pem"))
    text = text.replace("/etc/jitterguard/tls/host-key.pem", str(pki / f"{cert}-key.pem"))
    text = text.replace("router.jitterguard.internal", R_IP)
    # the ACL example is tested on its own (test_stack_deploy); here every host may publish
    text = text.replace('enabled: true,\n    default_permission: "deny"', 'enabled: false,\n    default_permission: "deny"')
    dst.write_text(text)
    return dst


def test_router_host_and_service_host_over_mtls(two_hosts, tmp_path):
    r, s = two_hosts
    _make_pki(tmp_path, router_san=f"IP:{R_IP},DNS:localhost")
    router_cfg = _patch(DEPLOY / "zenoh" / "router-host.json5", tmp_path / "router.json5", tmp_path, "host")
    svc_cfg = _patch(DEPLOY / "zenoh" / "service-host.json5", tmp_path / "service.json5", tmp_path, "host")
    obs_cfg = _patch(DEPLOY / "zenoh" / "service-host.json5", tmp_path / "observer.json5", tmp_path, "ops")
    assert f"tls/{R_IP}:7447" in svc_cfg.read_text()
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "JG_NS": "mh"}
    py = [sys.executable, "-m", "jitterguard.cli"]
    procs = []

    def spawn(ns: str, name: str, *args: str, extra_env: dict | None = None) -> subprocess.Popen:
        out = open(tmp_path / f"{name}.log", "wb")
        p = subprocess.Popen(["ip", "netns", "exec", ns, *args], stdout=out, stderr=subprocess.STDOUT,
                             env={**env, **(extra_env or {})}, cwd=tmp_path)
        out.close()
        procs.append(p)
        return p

    observer = textwrap.dedent(f"""
        import sys, threading, zenoh
        got = threading.Event(); n = [0]
        def cb(s):
            n[0] += 1
            if n[0] >= 5: got.set()
        cfg = zenoh.Config.from_file({str(obs_cfg)!r})
        with zenoh.open(cfg) as s:
            s.declare_subscriber("jg/mh/objects", cb)
            ok = got.wait(60)
        print("objects received:", n[0]); sys.exit(0 if ok else 1)
    """)
    try:
        spawn(r, "router", *py, "router", "--zenoh-config", str(router_cfg), "--listen", f"tls/{R_IP}:7447")
        spawn(s, "classifier", *py, "classifier", extra_env={"JG_ZENOH_CONFIG": str(svc_cfg)})
        spawn(s, "feeder", *py, "feed-tracks", "--loop", extra_env={"JG_ZENOH_CONFIG": str(svc_cfg)})
        # the observer sits on the router host, connecting over the veth like any other client
        res = subprocess.run(["ip", "netns", "exec", r, sys.executable, "-c", observer], capture_output=True,
                             text=True, timeout=120, env=env)
        logs = "\n".join(f"--- {n}\n" + (tmp_path / f"{n}.log").read_text()[-1500:]
                         for n in ("router", "classifier", "feeder"))
        assert res.returncode == 0, res.stdout + res.stderr + logs
        assert all(p.poll() is None for p in procs), logs
    finally:
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in procs:
            try:
                p.wait(timeout=15)
            except subprocess.TimeoutExpired:
                p.kill()
