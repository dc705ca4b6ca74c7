"""The idle collector hands freed heap memory back to the OS (glibc): RSS falls back after a burst; training's
``retain_heap`` keeps it instead."""

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


_LARGE_ARRAYS = """
import sys
from pathlib import Path
import numpy as np
if sys.argv[1] == "retain":
    from jitterguard.services.detector.cli import retain_heap
    retain_heap()
def rss_kb():
    return next(int(l.split()[1]) for l in Path("/proc/self/status").read_text().splitlines() if l.startswith("VmRSS:"))
before = rss_kb()
for _ in range(3):  # a frame's temporaries: allocated, written, freed
    a = np.ones(8_000_000)  # 64 MB
    del a
print(rss_kb() - before)
"""


@pytest.mark.parametrize("mode", ["default", "retain"])
def test_retained_heap_keeps_a_steps_large_temporaries_mapped(mode: str) -> None:
    """With glibc's defaults a 64 MB array is mmapped and unmapped each time (the next one faults in fresh
    pages); after the training commands' ``retain_heap`` the freed pages stay in the process for the next
    step's arrays. Each mode in its own process (the setting is process-wide)."""
    import subprocess
    import sys

    from jitterguard.runtime.gc_policy import _TRIM

    if _TRIM is None:
        pytest.skip("not glibc")
    grown = int(subprocess.run([sys.executable, "-c", _LARGE_ARRAYS, mode], capture_output=True, text=True,
                               check=True, timeout=120).stdout.strip())
    if mode == "retain":
        assert grown > 50_000, f"freed pages went back to the kernel ({grown} kB resident)"
    else:
        assert grown < 20_000, f"freed pages stayed resident ({grown} kB)"
