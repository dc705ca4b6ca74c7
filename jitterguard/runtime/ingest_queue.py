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

    At most ``capacity`` payloads and ``max_bytes`` bytes of them wait; a push into a full queue drops the oldest
    until the new one fits (the worker catches up on the newest). Bytes as well as payloads: a count alone bounds
    memory only by the largest payload a subscriber lets in (16,384 × 8 MiB). A payload larger than ``max_bytes``
    by itself still goes in, alone: the subscriber refuses those from their size before they get here. One lock
    keeps the drop count exact when the worker takes while a callback pushes.
    """

    def __init__(self, capacity: int, max_bytes: int | None = None) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be at least 1, not {capacity}")
        self.capacity = capacity
        self.max_bytes = max_bytes
        self._items: deque[tuple[bytes, str]] = deque()
        self._bytes = 0
        self._lock = threading.Lock()

    def push(self, data: bytes, key: str) -> int:
        """Append one payload; returns how many of the oldest were dropped to make room."""
        n = len(data)
        budget = self.max_bytes
        dropped = 0
        with self._lock:
            while self._items and (len(self._items) >= self.capacity
                                   or (budget is not None and self._bytes + n > budget)):
                self._bytes -= len(self._items.popleft()[0])
                dropped += 1
            self._items.append((data, key))
            self._bytes += n
        return dropped

    def take(self, limit: int) -> list[tuple[bytes, str]]:
        """Up to ``limit`` of the oldest payloads, removed, in arrival order (empty when none wait)."""
        with self._lock:
            items = [self._items.popleft() for _ in range(min(limit, len(self._items)))]
            self._bytes -= sum(len(data) for data, _ in items)
        return items

    @property
    def queued_bytes(self) -> int:
        """Bytes of the payloads waiting now."""
        return self._bytes

    def __len__(self) -> int:
        return len(self._items)
