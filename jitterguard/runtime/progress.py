"""Health means progress: whether a service turns the input it receives into output.

A live process with a liveliness token is not a working one: one poisonous message once made every later
frame of the tracker fail while supervisord said RUNNING and ``/readyz`` said ready. A service with an
input → output relation (tracker: ``detections`` → ``tracked``; classifier: ``tracked`` → ``objects``; detector:
``points`` → ``detections``) reports to a :class:`ProgressMonitor`:

- :meth:`~ProgressMonitor.input` when a message arrives that must lead to output;
- :meth:`~ProgressMonitor.output` when one is dealt with (published, or dropped on purpose: a duplicate);
- :meth:`~ProgressMonitor.failure` when handling one raised.

:meth:`~ProgressMonitor.assess` says ``ok``, ``failing`` (``failing_frames`` in a row failed) or ``stalled``
(input has been waiting ``stall_s`` with no output); the heartbeat carries it, the sidecar's ``/readyz`` and
``jitterguard status`` show it, and once a service has been unhealthy for the watchdog period the runtime exits
non-zero so that supervisord or systemd restart it (:meth:`jitterguard.runtime.Service.run_forever`).

Pure: every method takes the time from the caller (a monotonic clock in the service, numbers in tests).
No input at all is not a fault (a sensor may be off); only input that goes nowhere is.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

OK, FAILING, STALLED = "ok", "failing", "stalled"


@dataclass(frozen=True)
class ProgressPolicy:
    stall_s: float = 5.0
    """Input waiting this long with no output is a stall (a tracker frame takes ~10 ms)."""
    failing_frames: int = 5
    """This many failures in a row is failing."""


@dataclass(frozen=True)
class Health:
    state: str  # ok | failing | stalled
    reason: str = ""
    unhealthy_for_s: float = 0.0

    @property
    def ok(self) -> bool:
        return self.state == OK


class ProgressMonitor:
    """Thread-safe: inputs arrive on Zenoh callback threads, outputs and failures on the worker."""

    def __init__(self, policy: ProgressPolicy | None = None) -> None:
        self.policy = policy or ProgressPolicy()
        self._lock = threading.Lock()
        self._waiting_since: float | None = None  # first input since the last output
        self._failures = 0
        self._last_error = ""
        self._unhealthy_since: float | None = None

    def input(self, now: float) -> None:
        with self._lock:
            if self._waiting_since is None:
                self._waiting_since = now

    def output(self, now: float) -> None:
        with self._lock:
            self._waiting_since = None
            self._failures = 0

    def failure(self, now: float, error: str) -> None:
        """A message dealt with by raising: counted towards ``failing``; it is no input waiting either (one failed
        frame, then silence, had read as a stall and the watchdog restarted the service)."""
        with self._lock:
            self._failures += 1
            self._last_error = error
            self._waiting_since = None

    def assess(self, now: float) -> Health:
        """The health now; also starts or clears the unhealthy clock (call it periodically)."""
        p = self.policy
        with self._lock:
            if self._failures >= p.failing_frames:
                state, reason = FAILING, f"the last {self._failures} frames failed ({self._last_error})"
            elif self._waiting_since is not None and now - self._waiting_since >= p.stall_s:
                state, reason = STALLED, f"input has waited {now - self._waiting_since:.1f} s with no output"
            else:
                self._unhealthy_since = None
                return Health(OK)
            if self._unhealthy_since is None:
                self._unhealthy_since = now
            return Health(state, reason, now - self._unhealthy_since)
