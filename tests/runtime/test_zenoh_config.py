"""The Zenoh configuration a service opens its session with: listeners held to the bind policy whatever the mode,
and multicast scouting off for a client unless its config file turns it on."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from jitterguard.runtime.zenoh_config import ZenohOptions, build_config


def _file(tmp_path: Path, text: str) -> str:
    path = tmp_path / "zenoh.json5"
    path.write_text(text)
    return str(path)


def test_a_client_file_that_listens_off_loopback_is_refused(tmp_path: Path) -> None:
    """Zenoh 1.x clients do listen on listen/endpoints: a client file naming tcp/0.0.0.0 had opened a plain
    listener on every interface, unchecked — the bind policy looked at no endpoint of a client."""
    bad = _file(tmp_path, '{mode: "client", connect: {endpoints: ["tcp/127.0.0.1:7447"]},'
                          ' listen: {endpoints: ["tcp/0.0.0.0:17999"]}}')
    with pytest.raises(ValueError, match="refusing to listen on tcp/0.0.0.0:17999"):
        build_config(ZenohOptions(config_file=bad))
    with pytest.raises(ValueError, match="refusing to listen"):  # the flag too, on top of a client file
        build_config(ZenohOptions(config_file=_file(tmp_path, '{mode: "client"}'), listen=("tcp/0.0.0.0:17998",)))
    ok = _file(tmp_path, '{mode: "client", listen: {endpoints: ["tcp/127.0.0.1:17997"]}}')
    assert build_config(ZenohOptions(config_file=ok)) is not None  # loopback is fine


def test_multicast_scouting_is_off_for_a_client_unless_its_file_turns_it_on(tmp_path: Path) -> None:
    silent = build_config(ZenohOptions(config_file=_file(tmp_path, '{mode: "client"}')))
    assert json.loads(silent.get_json("scouting/multicast/enabled")) is False  # had been Zenoh's default: on
    on = build_config(ZenohOptions(config_file=_file(tmp_path, '{mode: "client", scouting: {multicast:'
                                                               ' {enabled: true}}}'),
                                   connect=("tcp/127.0.0.1:7447",)))
    assert json.loads(on.get_json("scouting/multicast/enabled")) is True  # the file says so: --connect kept it
    assert json.loads(build_config(ZenohOptions(connect=("tcp/127.0.0.1:7447",)))
                      .get_json("scouting/multicast/enabled")) is False


def test_a_router_whose_tls_files_are_missing_says_so_in_one_line_and_exits_2(tmp_path: Path) -> None:
    """A missing TLS key had been retried every 0.25 s for ever, as if a router were not up yet (and SIGTERM then
    ended it with a traceback): no wait cures it."""
    import os
    import subprocess
    import sys

    from jitterguard.runtime import free_tcp_port

    missing = tmp_path / "no-such-dir"
    cfg = tmp_path / "router.json5"
    cfg.write_text(json.dumps({"mode": "router", "transport": {"link": {"tls": {
        "root_ca_certificate": str(missing / "ca.pem"), "listen_certificate": str(missing / "router.pem"),
        "listen_private_key": str(missing / "router-key.pem"), "enable_mtls": True}}}}))
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "router", "--zenoh-config", str(cfg), "--listen",
                          f"tls/127.0.0.1:{free_tcp_port()}"], capture_output=True, text=True, timeout=60,
                         env={k: v for k, v in os.environ.items() if k != "JG_ZENOH_CONFIG"})
    assert res.returncode == 2, res.stderr
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "cannot open the Zenoh session" in lines[0] and "No such file" in lines[0], res.stderr
    assert ".rs:" not in lines[0] and "retrying" not in res.stderr


def _client_tls_file(tmp_path: Path, tls_dir: Path, endpoint: str = "tls/127.0.0.1:1") -> str:
    """A client config like deploy/zenoh/service-host.json5 once was (``connect/timeout_ms: -1``: Zenoh retries
    the connect for ever inside the open) naming ``tls_dir``'s files."""
    return _file(tmp_path, json.dumps({
        "mode": "client", "connect": {"endpoints": [endpoint], "timeout_ms": -1},
        "transport": {"link": {"tls": {"root_ca_certificate": str(tls_dir / "ca.pem"),
                                        "connect_certificate": str(tls_dir / "host.pem"),
                                        "connect_private_key": str(tls_dir / "host-key.pem"),
                                        "enable_mtls": True}}}}))


def test_a_client_whose_tls_files_are_missing_is_refused_before_the_open_naming_the_setting(tmp_path: Path) -> None:
    """A client's open never reports a missing TLS file: with connect/timeout_ms -1 (the service hosts' template)
    it retried the TLS link for ever without a word, so a service with a missing key waited silently."""
    import time

    from jitterguard.runtime.zenoh_config import UnusableConfig, open_session, tls_file_refusal

    tls = tmp_path / "tls"
    tls.mkdir()
    cfg = build_config(ZenohOptions(config_file=_client_tls_file(tmp_path, tls)))
    t0 = time.monotonic()
    with pytest.raises(UnusableConfig, match=r"transport/link/tls/root_ca_certificate .*ca\.pem: No such file"):
        open_session(cfg, timeout_s=30)
    assert time.monotonic() - t0 < 5  # refused, not retried until the timeout
    for name in ("ca.pem", "host.pem"):
        (tls / name).write_text("-----BEGIN CERTIFICATE-----\n")
    assert tls_file_refusal(cfg) == f"transport/link/tls/connect_private_key {tls / 'host-key.pem'}: " \
                                    "No such file or directory"  # the first unusable one, by its setting
    (tls / "host-key.pem").mkdir()
    assert tls_file_refusal(cfg).endswith("Is a directory")  # type: ignore[union-attr]
    (tls / "host-key.pem").rmdir()
    (tls / "host-key.pem").write_text("key")
    assert tls_file_refusal(cfg) is None  # all there: zenoh judges their contents
    plain = build_config(ZenohOptions(config_file=_client_tls_file(tmp_path, tmp_path / "nowhere", "tcp/127.0.0.1:1")))
    assert tls_file_refusal(plain) is None  # no tls/ or quic/ endpoint: the files are never read


def test_a_service_given_missing_tls_files_exits_2_with_one_line(tmp_path: Path) -> None:
    """The sidecar opens its session inside uvicorn's startup: a refusal there was a traceback and exit 3."""
    import os
    import subprocess
    import sys

    cfg = _client_tls_file(tmp_path, tmp_path / "nowhere")
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "sidecar", "--port", "0"], capture_output=True,
                         text=True, timeout=60, env={**os.environ, "JG_ZENOH_CONFIG": cfg})
    assert res.returncode == 2, res.stderr
    assert res.stderr.strip() == (f"jitterguard: error: cannot open the Zenoh session: transport/link/tls/"
                                  f"root_ca_certificate {tmp_path / 'nowhere' / 'ca.pem'}: No such file or directory")


def test_a_service_on_the_service_host_template_says_it_waits_for_the_router(tmp_path: Path) -> None:
    """deploy/zenoh/service-host.json5 had set connect/timeout_ms -1: Zenoh then retried inside the open without a
    word, so a service host whose router was down (or refused its certificate) logged nothing at all."""
    import os
    import subprocess
    import sys

    from jitterguard.runtime import free_tcp_port

    root = Path(__file__).resolve().parents[2]
    for name in ("ca.pem", "host.pem", "host-key.pem"):
        (tmp_path / name).write_text("not checked before the connect\n")
    endpoint = f"tls/127.0.0.1:{free_tcp_port()}"  # no router there
    text = (root / "deploy" / "zenoh" / "service-host.json5").read_text()
    cfg = tmp_path / "service-host.json5"
    cfg.write_text(text.replace("/etc/jitterguard/tls", str(tmp_path))
                   .replace("tls/router.jitterguard.internal:7447", endpoint))
    proc = subprocess.Popen([sys.executable, "-m", "jitterguard.cli", "tracker", "--zenoh-config", str(cfg)],
                            stderr=subprocess.PIPE, text=True, env={**os.environ, "JG_ZENOH_CONFIG": ""})
    try:
        import select

        ready, _, _ = select.select([proc.stderr], [], [], 30)  # the first warning comes at the first failure
        line = proc.stderr.readline() if ready else "(nothing in 30 s)"  # type: ignore[union-attr]
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    assert "cannot open the Zenoh session (Unable to connect" in line and endpoint in line, line
    assert ".rs:" not in line  # zenoh's Rust source location is dropped


def test_a_config_file_zenoh_cannot_parse_is_refused_in_one_line_naming_where(tmp_path: Path) -> None:
    """Zenoh's parser says where with a six-line caret display ending in a Rust source path; that had been the
    service's "one line" refusal."""
    with pytest.raises(ValueError) as err:
        build_config(ZenohOptions(config_file=_file(tmp_path, '{"a": [1, 2')))
    said = str(err.value)
    assert "\n" not in said and ".rs:" not in said, said
    assert said.startswith("zenoh config ") and "line 1, column 11: expected" in said, said


@pytest.mark.parametrize("text", ["[1, 2]", "// a comment\n/* and another */ [\"peer\"]", "\"router\""])
def test_a_config_file_that_is_no_object_is_refused_as_such(tmp_path: Path, text: str) -> None:
    """A list at the top level had been read as the config's id: "expected An hex string of 1-16 bytes"."""
    with pytest.raises(ValueError, match=r"expected an object \{…\} at the top level"):
        build_config(ZenohOptions(config_file=_file(tmp_path, text)))
    build_config(ZenohOptions(config_file=_file(tmp_path, "// fine\n{mode: 'client'}")))  # JSON5 with a comment


def test_a_router_file_that_names_no_listener_listens_on_loopback(tmp_path: Path) -> None:
    """A router config file without ``listen`` (``{}``, or one with only ``connect``): Zenoh fills in its own
    default, ``tcp/[::]:7447``, which had been taken as the file's choice and refused as off loopback. The router's
    default, ``tcp/127.0.0.1:7447``, holds as ``--help`` says; a file that names a listener keeps it."""
    from jitterguard.runtime.router import router_config

    for text in ("{}", '{mode: "router", connect: {endpoints: ["tcp/127.0.0.1:7000"]}}'):
        cfg = router_config([], _file(tmp_path, text))
        assert json.loads(cfg.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"], text
    named = _file(tmp_path, '{listen: {endpoints: ["tcp/127.0.0.1:17996"]}}')
    assert json.loads(router_config([], named).get_json("listen/endpoints")) == ["tcp/127.0.0.1:17996"]


def test_a_chosen_free_port_is_one_the_kernel_never_hands_out_by_itself():
    """A port from the kernel's ephemeral range can be taken between the check and its use by any session's
    ``listen :0`` or outgoing connect: CI (7 Dec) saw a test's own client session hold the port its service was to
    listen on, and the service wait for it for 300 s. Chosen ports lie outside that range, and bind."""
    import socket

    from jitterguard.runtime import free_tcp_port

    low, high = (int(v) for v in Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split())
    ports = [free_tcp_port() for _ in range(50)] + [free_tcp_port("::1") for _ in range(5)]
    assert all(not low <= p <= high for p in ports), (low, high, ports)
    assert len(set(ports)) > 10  # drawn, not one fixed port
    with socket.socket() as s:
        s.bind(("127.0.0.1", ports[0]))


def test_a_session_that_only_listens_says_it_waits_for_its_port_not_for_a_router():
    """A peer whose listen port is held (by a process still ending) waits for the port; the log had said it waited
    for "the router at [] is up"."""
    import logging
    import socket
    import threading

    from jitterguard.runtime import free_tcp_port, loopback_options, open_session

    port = free_tcp_port()
    records: list[str] = []

    class Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            records.append(record.getMessage())

    log = logging.getLogger("test.listen_wait")
    log.addHandler(Keep())
    with socket.socket() as held:
        held.bind(("127.0.0.1", port))
        held.listen()
        with pytest.raises(Exception, match="Address already in use"):
            open_session(build_config(loopback_options("t", port, listen_self=True)), timeout_s=0.3, log=log,
                         stop=threading.Event())
    assert records and f"retrying until it can listen on tcp/127.0.0.1:{port}" in records[0], records
