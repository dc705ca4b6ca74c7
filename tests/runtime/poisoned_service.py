"""A service whose handler goes wrong on purpose, run as its own process by ``test_watchdog.py``.

``python poisoned_service.py MODE NS PORT``: listens on ``tcp/127.0.0.1:PORT`` (peer) and takes messages on
``jg/NS/input`` through the runtime's inbox. MODE ``fail``: every message raises (a poisonous message
wedging a worker); ``stall``: the first message blocks the worker (input keeps arriving, no output);
``hang``: the first message runs a regular expression that never finishes while holding the GIL, so the
heartbeat thread cannot run either. Everything else is the real runtime: progress monitor, heartbeat,
watchdog, faulthandler.
"""

from __future__ import annotations

import re
import sys
import time

from jitterguard.runtime import Service, loopback_options
from jitterguard.runtime.progress import ProgressPolicy


class Poisoned(Service):
    name = "poisoned"

    def __init__(self, mode: str, ns: str, port: int) -> None:
        super().__init__(loopback_options(ns, port, listen_self=True))
        self.mode = mode
        self.monitor_progress(ProgressPolicy(stall_s=1.0, failing_frames=3))
        self.inbox = self.subscribe_queue(f"jg/{ns}/input", 64, progress=True)
        self.spawn(self._worker, "worker")

    def _worker(self) -> None:
        while not self.stop_event.is_set():
            if self.inbox.get(0.1) is None:
                continue
            try:
                self.handle()
            except Exception as exc:
                self.progress.failure(time.monotonic(), f"{type(exc).__name__}: {exc}")
            else:
                self.progress.output(time.monotonic())

    def handle(self) -> None:
        if self.mode == "fail":
            raise MemoryError("Unable to allocate 74.5 GiB")
        if self.mode == "stall":
            self.stop_event.wait(3600)
        if self.mode == "hang":
            re.match(r"(a+)+$", "a" * 64 + "b")  # catastrophic backtracking, GIL held throughout


if __name__ == "__main__":
    Poisoned(sys.argv[1], sys.argv[2], int(sys.argv[3])).run_forever()
