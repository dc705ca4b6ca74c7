"""A service whose constructor fails after its session opened exits: Zenoh runs Python callbacks on threads the
interpreter waits for at exit, and such a service (``ros2-in`` given a topic Zenoh refused as a key) had printed
its traceback and then never exited — under supervisord, a program RUNNING that does nothing."""

from __future__ import annotations

import subprocess
import sys

import pytest

from jitterguard.runtime import free_tcp_port

pytestmark = pytest.mark.integration

FAILS_AFTER_OPEN = """
import sys
from jitterguard.runtime import Service, loopback_options

class Half(Service):
    name = "half"

    def __init__(self, port: int) -> None:
        super().__init__(loopback_options("fail{pid}", port, listen_self=True))
        self._declared.append(self.session.declare_subscriber("jg/x/in", lambda s: None))  # a Python callback
        self.session.declare_subscriber("jg/a//b", lambda s: None)  # a key Zenoh refuses

class Child(Half):  # a subclass of a subclass: what it opened is closed once
    name = "child"

Child(int(sys.argv[1]))
"""


def test_a_service_whose_constructor_fails_after_opening_its_session_exits() -> None:
    script = FAILS_AFTER_OPEN.replace("{pid}", str(free_tcp_port()))
    res = subprocess.run([sys.executable, "-c", script, str(free_tcp_port())], capture_output=True, text=True,
                         timeout=30)
    assert res.returncode == 1 and "Invalid Key Expr" in res.stderr, res.stderr[-2000:]
