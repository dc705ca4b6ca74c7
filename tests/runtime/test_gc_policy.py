"""The idle collector hands freed heap memory back to the OS (glibc): RSS falls back after a burst."""

from __future__ import annotations

from pathlib import Path

import pytest

from jitterguard.runtime.gc_policy import IdleCollector, release_freed_memory


def _rss_kb() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError("no VmRSS")


def test_a_burst_freed_between_frames_goes_back_to_the_os() -> None:
    burst = [bytearray(100_000) for _ in range(2000)]  # 200 MB of frame-sized buffers
    for b in burst:
        b[0] = 1  # touched: resident
    keep = burst[::50]  # a few survivors pin the heap's top, as a live service's objects do
    del burst
    held = _rss_kb()
    if not release_freed_memory():
        pytest.skip("no malloc_trim here (not glibc)")
    assert held - _rss_kb() > 50_000, "freed pages stayed resident"
    assert len(keep) == 40


def test_the_idle_collector_trims_on_its_full_collections() -> None:
    c = IdleCollector(full_every=3)
    for _ in range(2):
        c.collect()
    burst = [bytearray(100_000) for _ in range(1000)]
    for b in burst:
        b[0] = 1
    keep = burst[::50]
    del burst
    held = _rss_kb()
    c.collect()  # the third: full, and a trim
    assert held - _rss_kb() > 25_000 or not release_freed_memory()
    assert len(keep) == 20
