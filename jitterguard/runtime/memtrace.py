"""Where a service's memory grows: ``JG_TRACEMALLOC_S=SECONDS`` makes every service log, every SECONDS, the
Python allocation sites that grew most since the first snapshot (:mod:`tracemalloc`), beside its RSS;
``JG_TRACEMALLOC_S=classifier=60,tracker=30`` picks services (the others run untraced, at full speed).

For diagnosis only (tracing allocations slows a service several times). Growth that RSS shows and these lines
do not is outside the Python heap (Zenoh's Rust side, numpy buffers freed to a fragmented heap, ...).
"""

from __future__ import annotations

import logging
import os
import threading
import tracemalloc
from pathlib import Path

ENV = "JG_TRACEMALLOC_S"
TOP = 12


def rss_kb() -> int | None:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        pass
    return None


def period_for(service: str, raw: str) -> float | None:
    """The tracing period ``raw`` (the variable's value) gives ``service``; raises ``ValueError``."""
    raw = raw.strip()
    if not raw:
        return None
    if "=" not in raw:
        return float(raw)
    periods = dict(item.split("=", 1) for item in raw.split(","))
    return float(periods[service]) if service in periods else None


def start_from_env(service: str, stop: threading.Event, log: logging.Logger) -> threading.Thread | None:
    """Start the tracing thread if ``JG_TRACEMALLOC_S`` names this service (a bad value is logged, ignored)."""
    try:
        period = period_for(service, os.environ.get(ENV, ""))
    except ValueError:
        log.error("%s=%r: expected SECONDS or SERVICE=SECONDS[,...]; no allocation tracing", ENV,
                  os.environ.get(ENV))
        return None
    if period is None:
        return None
    tracemalloc.start(16)

    def run() -> None:
        base = None
        base_rss = None
        while not stop.wait(period):
            snap = tracemalloc.take_snapshot().filter_traces(
                (tracemalloc.Filter(False, tracemalloc.__file__), tracemalloc.Filter(False, "<frozen importlib._bootstrap>")))
            if base is None:  # the first period is warm-up: growth counts from here
                base, base_rss = snap, rss_kb()
                continue
            traced, _ = tracemalloc.get_traced_memory()
            now_rss = rss_kb()
            log.warning("memtrace: RSS %+d KB since the baseline, traced Python heap %d KB; top growth:",
                        (now_rss or 0) - (base_rss or 0), traced // 1024)
            for stat in snap.compare_to(base, "traceback")[:TOP]:
                where = " <- ".join(f"{f.filename}:{f.lineno}" for f in list(stat.traceback)[::-1][:3])
                log.warning("memtrace: %+8.1f KB %+7d blocks  %s", stat.size_diff / 1024, stat.count_diff, where)

    t = threading.Thread(target=run, name="memtrace", daemon=True)
    t.start()
    return t
