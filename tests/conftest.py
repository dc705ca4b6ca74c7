"""Shared fixtures: real Zenoh sessions on loopback (peer mode, multicast scouting off, free ports)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import zenoh

from jitterguard.runtime import build_config, free_tcp_port, loopback_options


@pytest.fixture
def zenoh_port() -> int:
    return free_tcp_port()


@pytest.fixture
def client_session(zenoh_port: int) -> Iterator[zenoh.Session]:
    """A plain Zenoh session connected to the test's listening endpoint (tests act as tracker/consumer)."""
    s = zenoh.open(build_config(loopback_options("test", zenoh_port)))
    yield s
    s.close()
