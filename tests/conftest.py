"""Shared fixtures: real Zenoh sessions on loopback (peer mode, multicast scouting off, free ports)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import zenoh
from hypothesis import settings

from jitterguard.runtime import build_config, free_tcp_port, loopback_options

# Property tests draw their examples from a fixed seed and keep no example database: every run, here and in CI,
# tests the same inputs (a randomly drawn failure would make CI red by chance).
settings.register_profile("seeded", derandomize=True, database=None)
settings.load_profile("seeded")


@pytest.fixture(scope="session", autouse=True)
def compiled_statistic() -> None:
    """Compile (or load from numba's cache) the classifier's calibrated statistic once, in this process, before
    any test: the services the tests start then load it from the cache instead of each compiling it (seconds)
    inside a test's own timeouts — after a change to the statistic's source the setup's compilation is stale."""
    from jitterguard.services.classifier.statistics import warm_up

    warm_up()


@pytest.fixture
def zenoh_port() -> int:
    return free_tcp_port()


@pytest.fixture
def client_session(zenoh_port: int) -> Iterator[zenoh.Session]:
    """A plain Zenoh session connected to the test's listening endpoint (tests act as tracker/consumer)."""
    s = zenoh.open(build_config(loopback_options("test", zenoh_port)))
    yield s
    s.close()
