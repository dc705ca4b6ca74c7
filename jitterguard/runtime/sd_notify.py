"""systemd's notify protocol, just the watchdog ping: ``WATCHDOG=1`` datagrams to ``$NOTIFY_SOCKET``.

Why: a process that is stopped (SIGSTOP, a cgroup freezer) or hung where neither its own watchdog nor
faulthandler's timer runs stays "active (running)" for systemd, and ``Restart=always`` never fires: the stack
stands still for good. With ``WatchdogSec=`` in a unit, systemd ends a service that stops pinging; the services
ping from their heartbeat thread (:class:`~.service.Service`), the router from its main loop, so a ping proves
that the process still runs Python code. Under supervisord the stack's monitor does the same job
(:mod:`jitterguard.stack.monitor`).

No dependency (no ``systemd`` Python package): the protocol is one datagram on a unix socket. Without
``NOTIFY_SOCKET`` (supervisord, a terminal) every call does nothing.
"""

from __future__ import annotations

import os
import socket

ENV_SOCKET = "NOTIFY_SOCKET"


class Notifier:
    """Sends notify messages to the socket ``$NOTIFY_SOCKET`` names (a path, or ``@name`` for an abstract one)."""

    def __init__(self, address: str | None = None) -> None:
        address = os.environ.get(ENV_SOCKET) if address is None else address
        self._address: str | None = None
        self._sock: socket.socket | None = None
        if address and (address.startswith(("/", "@"))):
            self._address = "\0" + address[1:] if address.startswith("@") else address
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)

    @property
    def enabled(self) -> bool:
        return self._sock is not None

    def send(self, message: str) -> bool:
        """Send ``message`` (e.g. ``WATCHDOG=1``); False if there is no socket or it cannot be reached (systemd
        restarting, a test's socket gone) — never raises: a ping must not take the heartbeat down with it."""
        if self._sock is None or self._address is None:
            return False
        try:
            self._sock.sendto(message.encode(), self._address)
            return True
        except OSError:
            return False

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
