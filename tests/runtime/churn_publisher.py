"""The publishing side of ``test_runtime_keyed_publishers.py``'s churn test, in its own process.

``python churn_publisher.py ENDPOINT NS``: opens a client session to the router at ENDPOINT and puts on
``jg/NS/tracks/{id}`` through ``KeyedPublishers``, as the tracker does. Why a process of its own: the test measures
how much this process's resident memory grows over 20 000 never-reused keys, and in the pytest process that
figure also carried the subscriber's samples and pytest's own allocations (it read 8.7 MB once, on a pass that
left nothing per key). Commands, one per line on stdin, each answered by one line on stdout:
``churn START N`` puts one 200-byte payload on each of N keys from START and answers ``ok``; ``rss`` answers
the process's VmRSS in KB; ``quit`` closes the session and exits.
"""

from __future__ import annotations

import sys
from pathlib import Path

import zenoh

from jitterguard.runtime import ZenohOptions, build_config
from jitterguard.runtime.keyed_publishers import KeyedPublishers


def rss_kb() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise RuntimeError("no VmRSS in /proc/self/status")


def main(endpoint: str, ns: str) -> None:
    opts = ZenohOptions(ns=ns, connect=(endpoint,), mode="client", extra={"connect/timeout_ms": 30000})
    payload = b"x" * 200
    with zenoh.open(build_config(opts)) as session:
        pubs = KeyedPublishers(session, lambda ident: f"jg/{ns}/tracks/{ident}")
        for line in sys.stdin:
            words = line.split()
            if words[:1] == ["churn"]:
                start, n = int(words[1]), int(words[2])
                for i in range(start, start + n):
                    pubs.put(f"{i:032x}", payload)
                answer = "ok"
            elif words[:1] == ["rss"]:
                answer = str(rss_kb())
            elif words[:1] == ["quit"]:
                pubs.undeclare()
                return
            else:
                answer = f"error: unknown command {line.strip()!r}"
            print(answer, flush=True)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
