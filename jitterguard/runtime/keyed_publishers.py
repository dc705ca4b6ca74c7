"""Puts on per-track keys (``tracks/{id}``, ``motion/{id}``) without one declared publisher per key.

Why not a declared publisher per track: in eclipse-zenoh 1.x a publisher declared and then undeclared leaves
about 3 KB behind in the router and about 1.5 KB in the publishing process, per distinct key, for good
(eclipse-zenoh/zenoh#1518; measured here with a Python router and 30 000 distinct keys). Track IDs are never
reused, and a detector produces tens of new tracks per frame on real scans, so that was hundreds of MB a day
in the router and the tracker. A plain ``session.put`` leaves nothing behind (router RSS flat over 60 000
distinct keys) and, in client mode through the router, costs the same as a declared publisher within this
machine's noise (``tests/runtime/test_runtime_keyed_publishers.py`` holds the memory test; the cost is in the pipeline bench).
"""

from __future__ import annotations

from collections.abc import Callable

import zenoh


class KeyedPublishers:
    """``put(ident, payload)`` on ``key_of(ident)`` with BLOCK congestion control (a lost observation would
    silently shorten a classifier window) at one priority. Holds no Zenoh entity: nothing to release per ID."""

    def __init__(self, session: zenoh.Session, key_of: Callable[[str], str], *,
                 priority: zenoh.Priority = zenoh.Priority.DATA) -> None:
        self._session, self._key_of, self._priority = session, key_of, priority

    def put(self, ident: str, payload: bytes) -> None:
        self._session.put(self._key_of(ident), payload, congestion_control=zenoh.CongestionControl.BLOCK,
                          priority=self._priority)

    def undeclare(self) -> None:
        """Nothing is declared (kept so that :meth:`~jitterguard.runtime.Service.close` treats it like its
        other entities)."""
