"""deploy/: the Zenoh multi-host configs parse and really do mutual TLS; the systemd units are consistent."""

from __future__ import annotations

import configparser
import json
import shutil
import subprocess
import threading
from pathlib import Path

import pytest
import zenoh

from jitterguard.runtime import ZenohOptions, free_tcp_port
from jitterguard.schemas import decode, encode, keys
from jitterguard.schemas.models import ClassifierConfig, ConfigReply
from jitterguard.services.classifier.config_writes import ConfigWritePolicy
from jitterguard.runtime.envvars import DEFAULT_WATCHDOG_S, HANG_GRACE_S
from jitterguard.services.classifier.service import ClassifierService

from helpers import wait_until

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
SERVICES = ("router", "classifier", "tracker", "detector", "replay", "sidecar", "ros2-in", "ros2-out")


@pytest.mark.parametrize("name", ["router-host.json5", "service-host.json5", "single-host.json5"])
def test_zenoh_configs_parse(name):
    zenoh.Config.from_file(str(DEPLOY / "zenoh" / name))


def test_systemd_units_are_consistent():
    target = configparser.ConfigParser(interpolation=None, strict=False)
    target.read(DEPLOY / "systemd" / "jitterguard.target")
    wants = target["Unit"]["Wants"].split()
    for svc in SERVICES:
        unit = DEPLOY / "systemd" / f"jitterguard-{svc}.service"
        cp = configparser.ConfigParser(interpolation=None, strict=False)
        cp.read(unit)
        exec_start = cp["Service"]["ExecStart"].split()
        assert exec_start[:2] == ["/opt/jitterguard/venv/bin/jitterguard", svc]
        assert cp["Service"]["Restart"] == "always"
        # a frozen process pings no more (jitterguard.runtime.sd_notify); after its own watchdog's last resort
        assert int(cp["Service"]["WatchdogSec"]) > DEFAULT_WATCHDOG_S + HANG_GRACE_S
        assert cp["Unit"]["PartOf"] == "jitterguard.target" and cp["Install"]["WantedBy"] == "jitterguard.target"
        if svc != "router":
            assert "jitterguard-router.service" in cp["Unit"]["After"]
        if svc.startswith("ros2-"):  # on a vehicle, enabled in the replay's place: not wanted by default
            assert f"jitterguard-{svc}.service" not in wants
        else:
            assert f"jitterguard-{svc}.service" in wants
        if svc == "classifier":  # its compiled statistic's cache must be somewhere the unit may write
            env = dict(line.split("=", 1) for line in (DEPLOY / "systemd" / "jitterguard.env").read_text().splitlines()
                       if line and not line.startswith("#"))
            writable = cp["Service"]["ReadWritePaths"].split()
            assert cp["Service"]["ProtectSystem"] == "strict"
            assert any(Path(env["NUMBA_CACHE_DIR"]).is_relative_to(w) for w in writable), (env, writable)


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True)


def _make_pki(d: Path, router_san: str = "DNS:localhost,IP:127.0.0.1") -> None:
    _openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca-key.pem", "-out", "ca.pem", "-days", "2",
             "-subj", "/CN=jitterguard-test-ca", cwd=d)
    for name, cn, san in (("router", "router", router_san),
                          ("host", "jitterguard-tracker", "DNS:jitterguard-tracker"),
                          ("ops", "jitterguard-ops", "DNS:jitterguard-ops"),
                          ("sensor", "jitterguard-sensor", "DNS:jitterguard-sensor"),
                          ("classifier", "jitterguard-classifier", "DNS:jitterguard-classifier")):
        _openssl("req", "-newkey", "rsa:2048", "-nodes", "-keyout", f"{name}-key.pem", "-out", f"{name}.csr",
                 "-subj", f"/CN={cn}", cwd=d)
        (d / f"{name}.ext").write_text(f"subjectAltName={san}\n")
        _openssl("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca-key.pem", "-CAcreateserial",
                 "-out", f"{name}.pem", "-days", "2", "-extfile", f"{name}.ext", cwd=d)


@pytest.mark.integration
@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl CLI to make a test PKI")
def test_mtls_router_and_service_hosts(tmp_path):
    """deploy/zenoh/*-host.json5 with a throwaway CA: a certified client gets data through, one without a
    certificate is refused by the router."""
    _make_pki(tmp_path)
    port = free_tcp_port()
    rcfg = zenoh.Config.from_file(str(DEPLOY / "zenoh" / "router-host.json5"))
    rcfg.insert_json5("listen/endpoints", json.dumps([f"tls/127.0.0.1:{port}"]))
    rcfg.insert_json5("access_control/enabled", "false")  # the ACL is an example; mTLS is what is tested here
    for key, val in (("root_ca_certificate", "ca.pem"), ("listen_certificate", "router.pem"),
                     ("listen_private_key", "router-key.pem")):
        rcfg.insert_json5(f"transport/link/tls/{key}", json.dumps(str(tmp_path / val)))

    def client(cert: bool) -> zenoh.Config:
        c = zenoh.Config.from_file(str(DEPLOY / "zenoh" / "service-host.json5"))
        c.insert_json5("connect/endpoints", json.dumps([f"tls/localhost:{port}"]))
        c.insert_json5("connect/timeout_ms", "3000")
        c.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(tmp_path / "ca.pem")))
        if cert:
            c.insert_json5("transport/link/tls/connect_certificate", json.dumps(str(tmp_path / "host.pem")))
            c.insert_json5("transport/link/tls/connect_private_key", json.dumps(str(tmp_path / "host-key.pem")))
        else:
            c.insert_json5("transport/link/tls/connect_certificate", "null")
            c.insert_json5("transport/link/tls/connect_private_key", "null")
        return c

    got: list[bytes] = []
    ev = threading.Event()
    with zenoh.open(rcfg):
        with zenoh.open(client(True)) as sub_s, zenoh.open(client(True)) as pub_s:
            sub = sub_s.declare_subscriber("jg/mtls/objects", lambda s: (got.append(s.payload.to_bytes()), ev.set()))
            assert wait_until(lambda: (pub_s.put("jg/mtls/objects", b"hello"), ev.wait(0.2))[1], timeout=20)
            sub.undeclare()
        assert got and got[0] == b"hello"
        with pytest.raises(Exception):
            zenoh.open(client(False)).close()


def _acl_router(pki: Path, port: int) -> zenoh.Config:
    """deploy/zenoh/router-host.json5 on ``tls/127.0.0.1:port`` with the test CA, ACL as shipped except that
    loopback is not trusted: everything here runs on loopback, which the example trusts as "local" (services on
    the router host), so that subject is taken out and the certificate subjects are what decides."""
    rcfg = zenoh.Config.from_file(str(DEPLOY / "zenoh" / "router-host.json5"))
    rcfg.insert_json5("listen/endpoints", json.dumps([f"tls/127.0.0.1:{port}"]))
    for key, val in (("root_ca_certificate", "ca.pem"), ("listen_certificate", "router.pem"),
                     ("listen_private_key", "router-key.pem")):
        rcfg.insert_json5(f"transport/link/tls/{key}", json.dumps(str(pki / val)))
    acl = json.loads(rcfg.get_json("access_control"))
    acl["subjects"] = [s for s in acl["subjects"] if s["id"] != "local"]
    for pol in acl["policies"]:
        pol["subjects"] = [s for s in pol["subjects"] if s != "local"]
    rcfg.insert_json5("access_control", json.dumps(acl))
    return rcfg


def _host_settings(pki: Path, port: int, who: str) -> dict[str, object]:
    """What a service host changes in deploy/zenoh/service-host.json5: the router's address, its certificate."""
    return {"connect/endpoints": [f"tls/localhost:{port}"],
            "transport/link/tls/root_ca_certificate": str(pki / "ca.pem"),
            "transport/link/tls/connect_certificate": str(pki / f"{who}.pem"),
            "transport/link/tls/connect_private_key": str(pki / f"{who}-key.pem")}


def _host(pki: Path, port: int, who: str) -> zenoh.Config:
    c = zenoh.Config.from_file(str(DEPLOY / "zenoh" / "service-host.json5"))
    for key, value in _host_settings(pki, port, who).items():
        c.insert_json5(key, json.dumps(value))
    return c


@pytest.mark.integration
@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl CLI to make a test PKI")
def test_access_control_example_limits_puts_by_certificate(tmp_path):
    """The router-host ACL: the tracker host (CN jitterguard-tracker) may publish ``tracked`` but not
    ``objects``; the ops host reads everything."""
    _make_pki(tmp_path)
    port = free_tcp_port()
    got: dict[str, int] = {}
    with zenoh.open(_acl_router(tmp_path, port)), zenoh.open(_host(tmp_path, port, "ops")) as ops, \
            zenoh.open(_host(tmp_path, port, "host")) as tracker:
        ops.declare_subscriber("jg/acl/**", lambda s: got.__setitem__(str(s.key_expr), got.get(str(s.key_expr), 0) + 1))
        assert wait_until(lambda: (tracker.put("jg/acl/tracked", b"x"), got.get("jg/acl/tracked", 0) > 0)[1],
                          timeout=20)
        for _ in range(20):
            tracker.put("jg/acl/objects", b"forged")
        tracker.put("jg/acl/tracked", b"fence")
        n = got["jg/acl/tracked"]
        assert wait_until(lambda: got["jg/acl/tracked"] > n, timeout=10)
    assert "jg/acl/objects" not in got


def _ok_replies(session: zenoh.Session, selector: str, payload: bytes | None = None) -> list[bytes]:
    return [r.ok.payload.to_bytes() for r in session.get(selector, payload=payload, timeout=2.0) if r.ok is not None]


@pytest.mark.integration
@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl CLI to make a test PKI")
def test_access_control_example_lets_only_the_ops_host_write_the_config(tmp_path):
    """A certified sensor host cannot change the classifier's config, neither on its key nor through a wildcard
    query (the classifier accepts writes without a token here, so the ACL alone is what stops them); it can
    still read the state. The ops host can write (the control)."""
    _make_pki(tmp_path)
    port = free_tcp_port()
    ns = "aclcfg"
    forged = encode(ClassifierConfig(alpha_default=99.0))
    with zenoh.open(_acl_router(tmp_path, port)):
        opts = ZenohOptions(ns=ns, config_file=str(DEPLOY / "zenoh" / "service-host.json5"),
                            extra=_host_settings(tmp_path, port, "classifier"))
        with ClassifierService(opts, config_writes=ConfigWritePolicy.open()) as classifier, \
                zenoh.open(_host(tmp_path, port, "sensor")) as sensor, zenoh.open(_host(tmp_path, port, "ops")) as ops:
            assert wait_until(lambda: bool(_ok_replies(ops, keys.classifier_config(ns))), timeout=30)
            assert _ok_replies(sensor, keys.classifier_state(ns))  # reads stay open to certified hosts
            for selector in (keys.classifier_config(ns), f"jg/{ns}/classifier/*", f"jg/{ns}/**", "jg/**", "**"):
                assert _ok_replies(sensor, selector, forged) == [], selector
            assert classifier.core.config == ClassifierConfig()
            assert classifier.counters.get("config_changes") == 0
            reply = decode(ConfigReply, _ok_replies(ops, keys.classifier_config(ns),
                                                    encode(ClassifierConfig(alpha_default=2.5)))[0])
            assert reply.ok and classifier.core.config.alpha_default == 2.5


@pytest.mark.integration
@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl CLI to make a test PKI")
def test_an_endpoint_that_turns_mtls_off_is_refused_off_loopback(tmp_path):
    """Zenoh lets an endpoint's own ``#enable_mtls=false`` win over router-host.json5's ``enable_mtls: true``: a
    client with no certificate then connects (shown on loopback with Zenoh alone). `jitterguard router --listen
    'tls/0.0.0.0:7447#enable_mtls=false'` had listened so, on every interface; it must refuse, exit 2."""
    import os
    import sys

    from jitterguard.runtime.router import router_config

    _make_pki(tmp_path)
    port = free_tcp_port()
    rcfg = zenoh.Config.from_file(str(DEPLOY / "zenoh" / "router-host.json5"))
    rcfg.insert_json5("listen/endpoints", json.dumps([f"tls/127.0.0.1:{port}#enable_mtls=false"]))
    rcfg.insert_json5("access_control/enabled", "false")
    for key, val in (("root_ca_certificate", "ca.pem"), ("listen_certificate", "router.pem"),
                     ("listen_private_key", "router-key.pem")):
        rcfg.insert_json5(f"transport/link/tls/{key}", json.dumps(str(tmp_path / val)))
    anon = zenoh.Config.from_file(str(DEPLOY / "zenoh" / "service-host.json5"))
    anon.insert_json5("connect/endpoints", json.dumps([f"tls/localhost:{port}"]))
    anon.insert_json5("connect/timeout_ms", "3000")
    anon.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(tmp_path / "ca.pem")))
    anon.insert_json5("transport/link/tls/connect_certificate", "null")
    anon.insert_json5("transport/link/tls/connect_private_key", "null")
    anon.insert_json5("transport/link/tls/enable_mtls", "false")
    with zenoh.open(rcfg):
        zenoh.open(anon).close()  # no certificate, and in

    cfg = tmp_path / "router-host.json5"
    cfg.write_text((DEPLOY / "zenoh" / "router-host.json5").read_text().replace("/etc/jitterguard/tls", str(tmp_path)))
    bad = f"tls/0.0.0.0:{free_tcp_port()}#enable_mtls=false"
    with pytest.raises(ValueError, match="needs mutual TLS"):
        router_config([bad], str(cfg))
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "router", "--zenoh-config", str(cfg), "--listen",
                          bad], capture_output=True, text=True, timeout=30,
                         env={k: v for k, v in os.environ.items() if k != "JG_ZENOH_CONFIG"})
    assert res.returncode == 2 and res.stderr.strip() == (
        f"jitterguard: error: refusing to listen on {bad}: a non-loopback listener needs mutual TLS "
        "(transport/link/tls/enable_mtls: true in the Zenoh config)"), res.stderr
    assert router_config([f"tls/0.0.0.0:{port}#enable_mtls=true"], str(cfg)) is not None  # said on the endpoint
