"""SIGINT/SIGTERM handlers that never block.

Python runs a signal handler in the main thread between two bytecodes, possibly while that thread holds a lock —
for instance inside ``Event.wait``, whose condition lock is not reentrant. A handler that calls ``Event.set`` on
that event then waits for a lock its own thread holds, for ever: a service that a supervisor asks to stop hangs
until the watchdog kills it (seen in CI: ``tracker`` after SIGTERM, main thread in ``Event.wait`` → handler →
``Event.set``). So the handler only hands the stop to a new thread, which takes whatever locks it needs once the
main thread has let go of them.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Callable, Iterator

STOP_SIGNALS: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGTERM)


def stop_on_signals(stop: Callable[[], object], signals: tuple[signal.Signals, ...] = STOP_SIGNALS) -> bool:
    """Call ``stop`` (off the main thread) on each of ``signals``. Handlers can only be installed from the main
    thread: elsewhere nothing is installed and False comes back."""
    if threading.current_thread() is not threading.main_thread():
        return False

    def handler(signum: int, _frame: object) -> None:
        threading.Thread(target=stop, name=f"stop-on-{signal.Signals(signum).name}", daemon=True).start()

    for sig in signals:
        signal.signal(sig, handler)
    return True


@contextlib.contextmanager
def sigterm_as_exit() -> Iterator[None]:
    """Within the block, SIGTERM raises ``SystemExit(143)`` in the main thread, so the command's ``finally`` and
    ``except`` clauses remove what it had half written, as they do for Ctrl-C (Python's default SIGTERM ends the
    process at once: `sim generate` had left its ``.NAME.PID.part`` file). For one-shot commands, not services: a
    service's stop goes through :func:`stop_on_signals`. Off the main thread it changes nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, _frame: object) -> None:
        raise SystemExit(128 + signum)

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)
