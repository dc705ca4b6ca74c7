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
