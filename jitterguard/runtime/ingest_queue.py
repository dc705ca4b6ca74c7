"""A bounded queue of received payloads that one worker drains in batches, and that counts what it drops.

Why not Zenoh's ``RingChannel``: it drops its oldest sample when full and says so to nobody (a 100,000-put flood
on ``tracks/*`` lost ~48 % of it, counted nowhere), and the project's rule is that every queue is bounded and its
drops are counted. Here a Zenoh callback copies each payload to ``bytes`` and appends it; when the queue is full
the oldest payload goes and the caller is told how many went, to count them.
"""

from __future__ import annotations

import threading
from collections import deque


class IngestQueue:
    """FIFO of ``(payload, key)``: :meth:`push` from Zenoh's callback (any thread), :meth:`take` from one worker.

    At most ``capacity`` payloads wait; a push into a full queue drops the oldest (the worker catches up on the
    newest). One lock keeps the drop count exact when the worker takes while a callback pushes.
    """

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be at least 1, not {capacity}")
        self.capacity = capacity
        self._items: deque[tuple[bytes, str]] = deque()
        self._lock = threading.Lock()

    def push(self, data: bytes, key: str) -> int:
        """Append one payload; returns how many of the oldest were dropped to make room (0 or 1)."""
        with self._lock:
            dropped = 0
            if len(self._items) >= self.capacity:
                self._items.popleft()
                dropped = 1
            self._items.append((data, key))
        return dropped

    def take(self, limit: int) -> list[tuple[bytes, str]]:
        """Up to ``limit`` of the oldest payloads, removed, in arrival order (empty when none wait)."""
        with self._lock:
            n = min(limit, len(self._items))
            return [self._items.popleft() for _ in range(n)]

    def __len__(self) -> int:
        return len(self._items)
