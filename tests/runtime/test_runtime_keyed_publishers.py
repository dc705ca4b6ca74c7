"""KeyedPublishers over real Zenoh sessions: per-track keys reach a wildcard subscriber, and a stream of
never-reused track IDs leaves nothing behind in a real router (``jitterguard router`` in its own process)."""

from __future__ import annotations

import subprocess
import sys
import threading
from pathlib import Path

import zenoh

from helpers import wait_until
from jitterguard.runtime import ZenohOptions, build_config, free_tcp_port, loopback_options
from jitterguard.runtime.keyed_publishers import KeyedPublishers

PUBLISHER = Path(__file__).with_name("churn_publisher.py")


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
    the publishing process (the tracker's RSS growth); now nothing. Router and publisher each run in a process of
    their own (``churn_publisher.py``), so each RSS figure is theirs alone."""
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    log = open(tmp_path / "router.log", "wb")
    router = subprocess.Popen([sys.executable, "-m", "jitterguard.cli", "router", "--listen", endpoint],
                              stdout=log, stderr=subprocess.STDOUT)
    log.close()
    publisher = subprocess.Popen([sys.executable, str(PUBLISHER), endpoint, "churn"], text=True,
                                 stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    received = [0]

    def ask(command: str) -> str:
        assert publisher.stdin is not None and publisher.stdout is not None
        publisher.stdin.write(command + "\n")
        publisher.stdin.flush()
        answer = publisher.stdout.readline().strip()
        assert answer and not answer.startswith("error"), (command, answer)
        return answer

    try:
        opts = ZenohOptions(ns="churn", connect=(endpoint,), mode="client", extra={"connect/timeout_ms": 30000})
        with zenoh.open(build_config(opts)) as sub_side:
            sub = sub_side.declare_subscriber("jg/churn/tracks/*",
                                              lambda s: received.__setitem__(0, received[0] + 1))
            assert wait_until(lambda: (ask("churn 0 10"), received[0] > 0)[1], timeout=20)
            ask("churn 100 2000")  # warm the router's buffers and both allocators
            assert wait_until(lambda: received[0] >= 2000, timeout=30)
            before, before_pub = _rss_kb(router.pid), int(ask("rss"))
            ask("churn 10000 20000")
            assert wait_until(lambda: received[0] >= 22_000, timeout=60), received[0]
            growth_kb = _rss_kb(router.pid) - before
            growth_pub_kb = int(ask("rss")) - before_pub  # the publishing process: the tracker's case
            sub.undeclare()
        assert growth_kb < 8_000, f"router RSS grew {growth_kb} KB over 20 000 distinct keys"
        assert growth_pub_kb < 8_000, f"publisher RSS grew {growth_pub_kb} KB over 20 000 distinct keys"
        assert publisher.stdin is not None
        publisher.stdin.write("quit\n")
        publisher.stdin.close()
        assert publisher.wait(timeout=15) == 0
    finally:
        if publisher.poll() is None:
            publisher.kill()
            publisher.wait(timeout=15)
        router.terminate()
        router.wait(timeout=15)
