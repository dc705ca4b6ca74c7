"""A stop signal that arrives while the main thread holds the stop event's lock must still stop the process.

CPython runs a signal handler in the main thread between bytecodes, so it can run while that thread is inside
``Event.wait`` holding the event's (non-reentrant) condition lock; a handler that calls ``Event.set`` itself then
waits for ever (a tracker hung on SIGTERM in CI that way). The child process below forces that moment: it takes
the event's lock, signals itself, and only then lets go.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
import threading

from jitterguard.runtime.signals import stop_on_signals

CHILD = textwrap.dedent("""
    import os, signal, sys, threading, time
    from jitterguard.runtime.signals import stop_on_signals
    ev = threading.Event()
    if sys.argv[1] == "helper":
        assert stop_on_signals(ev.set)
    else:  # what the services did before
        signal.signal(signal.SIGTERM, lambda *_: ev.set())
    with ev._cond:  # the main thread holds the lock, as inside Event.wait
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.05)  # the handler runs here, lock held
    print("set" if ev.wait(5.0) else "not set", flush=True)
""")


def _child(mode: str) -> subprocess.CompletedProcess[str] | None:
    try:
        return subprocess.run([sys.executable, "-c", CHILD, mode], capture_output=True, text=True, timeout=10)
    except subprocess.TimeoutExpired:
        return None


def test_the_stop_handler_returns_at_once_and_the_event_is_set_once_the_lock_is_free() -> None:
    res = _child("helper")
    assert res is not None, "the child hung in its signal handler"
    assert res.returncode == 0 and res.stdout.strip() == "set", res.stderr


def test_the_child_reproduces_the_hang_of_a_handler_that_sets_the_event_itself() -> None:
    """The control: the same moment with the old handler deadlocks, so the test above is not vacuous."""
    assert _child("naive") is None


def test_off_the_main_thread_nothing_is_installed() -> None:
    got: list[bool] = []
    t = threading.Thread(target=lambda: got.append(stop_on_signals(lambda: None)))
    t.start()
    t.join()
    assert got == [False]
