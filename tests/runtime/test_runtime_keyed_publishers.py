"""KeyedPublishers over real Zenoh sessions on loopback: per-track keys reach a wildcard subscriber, and the
publishers of tracks that are gone are undeclared."""

from __future__ import annotations

import threading

import zenoh

from helpers import wait_until
from jitterguard.runtime import build_config, loopback_options
from jitterguard.runtime.keyed_publishers import KeyedPublishers


def test_puts_reach_the_subscriber_and_retain_drops_publishers_of_gone_ids(zenoh_port: int) -> None:
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
        assert len(pubs) == 5
        assert pubs.retain(ids[:2]) == 3 and len(pubs) == 2  # three tracks are gone
        pubs.put(ids[4], b"back")  # a returning ID gets a fresh publisher
        assert wait_until(lambda: len(tagged(b"back")) == 1)
        assert tagged(b"back") == [(f"kp/tracks/{ids[4]}", b"back")]
        assert len(pubs) == 3
        pubs.undeclare()
        assert len(pubs) == 0
        sub.undeclare()
