"""Multi-host in network namespaces: the router on one "host", classifier and feeder on another, joined by a
veth link, talking mutual TLS with deploy/zenoh/router-host.json5 and service-host.json5 (paths patched to a
throwaway CA). Needs root and ``ip netns``; skipped otherwise."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from helpers import wait_until
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
        from jitterguard.runtime import open_session
        got = threading.Event(); n = [0]
        def cb(s):
            n[0] += 1
            if n[0] >= 5: got.set()
        cfg = zenoh.Config.from_file({str(obs_cfg)!r})
        with open_session(cfg, timeout_s=60) as s:  # retried until the router is up, as every service does
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


PROBE = textwrap.dedent("""
    import json, socket, sys
    host, ports = sys.argv[1], json.loads(sys.argv[2])
    reached = []
    for port in ports:
        try:
            socket.create_connection((host, port), timeout=2).close()
            reached.append(port)
        except OSError:
            pass
    print(json.dumps(reached))
""")


def _listeners(netns: str, proto: str) -> list[tuple[str, int, int | None]]:
    """(local address, port, pid) of every listening TCP socket / bound UDP socket in ``netns``."""
    out = subprocess.run(["ip", "netns", "exec", netns, "ss", "-Hnp", f"-l{proto}"], capture_output=True,
                         text=True, check=True).stdout
    rows = []
    for line in out.splitlines():
        parts = line.split()
        local = parts[3]
        addr, _, port = local.rpartition(":")
        m = re.search(r"pid=(\d+)", line)
        rows.append((addr.strip("[]"), int(port), int(m.group(1)) if m else None))
    return rows


def test_only_the_router_listens_and_nothing_is_reachable_from_another_namespace(two_hosts, tmp_path):
    """The whole stack (`jitterguard up`: router, replay, tracker, classifier, sidecar) runs in one namespace;
    from another one, joined by a veth link, no port of it can be reached. Every listening socket belongs to
    the router or the sidecar and is bound to loopback (before issue 18 every service listened on
    ``tcp/[::]:0`` and a client in the other namespace could set the classifier's alpha). A plain listener on
    all interfaces shows that the probe does reach what is exposed."""
    r, s = two_hosts
    run_dir = tmp_path / "run"
    py = [sys.executable, "-m", "jitterguard.cli"]
    env = {k: v for k, v in os.environ.items() if k != "JG_API_TOKEN"}

    def in_r(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
        return subprocess.run(["ip", "netns", "exec", r, *args], capture_output=True, text=True, timeout=timeout,
                              env=env)

    up = in_r(*py, "up", "-d", "--ns", "exposed", "--input", "detections", "--run-dir", str(run_dir))
    assert up.returncode == 0, up.stdout + up.stderr
    exposed = subprocess.Popen(["ip", "netns", "exec", r, sys.executable, "-c",
                                "import socket,time; s=socket.socket(); s.bind(('0.0.0.0', 9999)); s.listen(); "
                                "time.sleep(600)"])
    try:
        def all_alive() -> dict | None:
            res = in_r(*py, "status", "--run-dir", str(run_dir), "--json", "--listen-s", "1.2")
            rows = {row["name"]: row for row in json.loads(res.stdout)["services"]} if res.stdout else {}
            ok = rows and all(row["alive"] is not False for row in rows.values()) and \
                (rows.get("classifier", {}).get("last_seq") or -1) >= 0
            return rows if ok else None

        assert wait_until(lambda: all_alive() is not None, timeout=120, period=1.0), \
            (run_dir / "logs" / "classifier.log").read_text()[-2000:]
        rows = all_alive()
        assert rows is not None and {"router", "replay", "tracker", "classifier", "sidecar"} <= set(rows)
        pids = {name: row["pid"] for name, row in rows.items()}
        tcp = [t for t in _listeners(r, "t") if t[1] != 9999]
        udp = [u for u in _listeners(r, "u") if u[2] in pids.values()]
        owners = {name for name, pid in pids.items() if any(t[2] == pid for t in tcp)}
        assert owners <= {"router", "sidecar"} and "router" in owners, (owners, tcp)
        assert all(addr in ("127.0.0.1", "::1") for addr, _, _ in tcp), tcp
        assert udp == [], udp  # no scouting socket either
        ports = sorted({port for _, port, _ in tcp} | {9999})
        probe = subprocess.run(["ip", "netns", "exec", s, sys.executable, "-c", PROBE, R_IP, json.dumps(ports)],
                               capture_output=True, text=True, timeout=120)
        assert json.loads(probe.stdout) == [9999], probe.stdout + probe.stderr
    finally:
        exposed.kill()
        in_r(*py, "down", "--run-dir", str(run_dir))
        wait_until(lambda: not (run_dir / "supervisord.pid").exists(), timeout=30)
