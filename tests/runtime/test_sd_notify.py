"""systemd's watchdog ping (``WATCHDOG=1`` on ``$NOTIFY_SOCKET``), from real processes to a real unix socket.

The units set ``WatchdogSec=``: a service that stops pinging is ended and restarted by systemd. That is the only
cure for a process stopped (SIGSTOP, a cgroup freezer) or hung where its own watchdog cannot run, which systemd
had shown "active (running)" for ever. Here a service waiting for its router pings (waiting is not hanging), goes
on pinging from its heartbeat once connected, stops pinging while it is stopped with SIGSTOP, and the router
pings from its main loop.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from jitterguard.runtime import free_tcp_port
from jitterguard.runtime.sd_notify import Notifier

from helpers import stop_process

pytestmark = pytest.mark.integration


class NotifySocket:
    """The systemd side: a datagram socket that collects what arrives."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))

    def wait_for(self, message: bytes, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.sock.settimeout(max(0.05, deadline - time.monotonic()))
            try:
                if self.sock.recv(4096) == message:
                    return True
            except TimeoutError:
                return False
        return False

    def drain(self) -> None:
        self.sock.setblocking(False)
        try:
            while True:
                self.sock.recv(4096)
        except BlockingIOError:
            pass

    def close(self) -> None:
        self.sock.close()


def _start(args: list[str], notify: Path, tmp_path: Path) -> subprocess.Popen:
    env = {**os.environ, "NOTIFY_SOCKET": str(notify), "JG_WATCHDOG_S": "0"}
    return subprocess.Popen([sys.executable, "-m", "jitterguard.cli", *args], env=env, cwd=tmp_path,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def test_a_service_pings_while_it_waits_for_the_router_and_from_its_heartbeat(tmp_path):
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    svc_sock, router_sock = NotifySocket(tmp_path / "svc.sock"), NotifySocket(tmp_path / "router.sock")
    (tmp_path / "run").mkdir()
    service = _start(["stack-monitor", "--run-dir", str(tmp_path / "run"), "--connect", endpoint],
                     svc_sock.path, tmp_path)
    router = None
    try:
        assert svc_sock.wait_for(b"WATCHDOG=1", timeout=60), "no ping while it waited for the router"
        router = _start(["router", "--listen", endpoint], router_sock.path, tmp_path)
        assert router_sock.wait_for(b"WATCHDOG=1", timeout=60), "the router does not ping"
        # connected: its heartbeat pings (the summary it writes says the session is up)
        assert svc_sock.wait_for(b"WATCHDOG=1", timeout=60)
        deadline = time.monotonic() + 60
        while not (tmp_path / "run" / "summary.json").exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert (tmp_path / "run" / "summary.json").exists()
        assert svc_sock.wait_for(b"WATCHDOG=1", timeout=30)
        # stopped: no ping at all (what systemd's WatchdogSec= acts on)
        os.kill(service.pid, signal.SIGSTOP)
        time.sleep(0.2)  # a ping already on its way may still arrive
        svc_sock.drain()
        assert not svc_sock.wait_for(b"WATCHDOG=1", timeout=3.0)
        os.kill(service.pid, signal.SIGCONT)
        assert svc_sock.wait_for(b"WATCHDOG=1", timeout=30)
    finally:
        stop_process(service, timeout=60)
        if router is not None:
            stop_process(router, timeout=60)
        svc_sock.close()
        router_sock.close()


def test_without_notify_socket_nothing_is_sent_and_a_gone_socket_is_no_error(tmp_path):
    assert not Notifier("").enabled and Notifier("").send("WATCHDOG=1") is False
    n = Notifier(str(tmp_path / "nobody-listens.sock"))
    assert n.enabled and n.send("WATCHDOG=1") is False  # systemd restarting: the heartbeat goes on
    n.close()
