"""KeyedPublishers over real Zenoh sessions: per-track keys reach a wildcard subscriber, and a stream of
never-reused track IDs leaves nothing behind in a real router (``jitterguard router`` in its own process)."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path

import zenoh

from helpers import wait_until
from jitterguard.runtime import ZenohOptions, build_config, free_tcp_port, loopback_options
from jitterguard.runtime.keyed_publishers import KeyedPublishers


def test_puts_reach_the_subscriber_on_each_key(zenoh_port: int) -> None:
    got: list[tuple[str, bytes]] = []
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        with lock:
            got.append((str(sample.key_expr), sample.payload.to_bytes()))

    with zenoh.open(build_config(loopback_options("kp", zenoh_port, listen_self=True))) as sub_side, \
            zenoh.open(build_config(loopback_options("kp", zenoh_port))) as pub_side:
        sub = sub_side.declare_subscriber("kp/tracks/**", on_sample)
        pubs = KeyedPublishers(pub_side, lambda ident: f"kp/tracks/{ident}")
        ids = [f"{i:032x}" for i in range(5)]

        def burst(tag: bytes) -> None:
            for ident in ids:
                pubs.put(ident, tag + ident.encode())

        def tagged(tag: bytes) -> list[tuple[str, bytes]]:
            with lock:
                return sorted(g for g in got if g[1].startswith(tag))

        assert wait_until(lambda: (burst(b"warm-"), len(got) > 0)[1], timeout=10)  # discovery done
        burst(b"a-")
        assert wait_until(lambda: len(tagged(b"a-")) >= 5)
        assert tagged(b"a-") == sorted((f"kp/tracks/{i}", b"a-" + i.encode()) for i in ids)  # each key, once
        pubs.undeclare()
        sub.undeclare()


def _rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError("no VmRSS")


def test_router_memory_stays_flat_under_track_id_churn(tmp_path: Path) -> None:
    """20 000 distinct ``tracks/{id}`` keys through a client session and the router: a publisher declared per
    key (what this class used to do) left ~3 KB per key in the router, i.e. ~60 MB here, and ~1-1.5 KB per key in
    the publishing process (the tracker's RSS growth); now nothing."""
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    log = open(tmp_path / "router.log", "wb")
    router = subprocess.Popen([sys.executable, "-m", "jitterguard.cli", "router", "--listen", endpoint],
                              stdout=log, stderr=subprocess.STDOUT)
    log.close()
    received = [0]
    try:
        opts = ZenohOptions(ns="churn", connect=(endpoint,), mode="client", extra={"connect/timeout_ms": 30000})
        with zenoh.open(build_config(opts)) as sub_side, zenoh.open(build_config(opts)) as pub_side:
            sub = sub_side.declare_subscriber("jg/churn/tracks/*",
                                              lambda s: received.__setitem__(0, received[0] + 1))
            pubs = KeyedPublishers(pub_side, lambda ident: f"jg/churn/tracks/{ident}")
            payload = b"x" * 200

            def churn(start: int, n: int) -> None:
                for i in range(start, start + n):
                    pubs.put(f"{i:032x}", payload)

            assert wait_until(lambda: (churn(0, 10), received[0] > 0)[1], timeout=20)
            churn(100, 2000)  # warm the router's buffers and allocator
            assert wait_until(lambda: received[0] >= 2000, timeout=30)
            before, before_self = _rss_kb(router.pid), _rss_kb(os.getpid())
            churn(10_000, 20_000)
            assert wait_until(lambda: received[0] >= 22_000, timeout=60), received[0]
            growth_kb = _rss_kb(router.pid) - before
            growth_self_kb = _rss_kb(os.getpid()) - before_self  # the publishing process: the tracker's case
            sub.undeclare()
        assert growth_kb < 8_000, f"router RSS grew {growth_kb} KB over 20 000 distinct keys"
        assert growth_self_kb < 8_000, f"publisher RSS grew {growth_self_kb} KB over 20 000 distinct keys"
    finally:
        router.terminate()
        router.wait(timeout=15)
