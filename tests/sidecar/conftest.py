"""Fixtures for the sidecar tests; the stack itself lives in ``stack.py``."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from .stack import Stack, start_stack

API_TOKEN = "s3cret-token"


@pytest.fixture(scope="module")
def stack() -> Iterator[Stack]:
    """Classifier + feeder + sidecar (token required for writes), shared by one test module."""
    s = start_stack("sc-api", token=API_TOKEN)
    yield s
    s.close()
