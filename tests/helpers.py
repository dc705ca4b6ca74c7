"""Small helpers shared by tests (importable as ``helpers``: pytest puts tests/ on sys.path)."""

from __future__ import annotations

import time
from collections.abc import Callable


def wait_until(pred: Callable[[], bool], timeout: float = 10.0, period: float = 0.02) -> bool:
    """Poll ``pred`` until it holds or ``timeout`` passes (no fixed sleeps in tests)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(period)
    return pred()


def collector(store: dict, lock, kind: str, model):
    """A Zenoh subscriber callback that decodes each sample as ``model`` (the wire's own validation) into
    ``store[kind]`` under ``lock``: the tests' independent observer of what a service published."""
    from jitterguard.schemas import decode

    def cb(sample) -> None:
        msg = decode(model, sample.payload.to_bytes())
        with lock:
            store[kind].append(msg)

    return cb

