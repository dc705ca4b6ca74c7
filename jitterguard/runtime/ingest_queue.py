"""A bounded queue of received payloads that a worker drains, and that counts what it drops.

Every subscription whose worker runs apart from Zenoh's callback goes through one of these (``tracks/*`` in
batches, ``tracked`` and ``detections`` one frame at a time, a ROS 2 scan topic): a Zenoh callback copies each
payload to ``bytes`` and appends it with its arrival time; when the queue is full the oldest payload goes and the
caller is told how many went, to count them. Why not Zenoh's ``RingChannel``: it drops its oldest sample when full
and says so to nobody (a 100,000-put flood on ``tracks/*`` lost ~48 % of it, counted nowhere), and the project's
rule is that every queue is bounded — in payloads and in bytes — and its drops are counted.
"""

from __future__ import annotations

import threading
from collections import deque

Item = tuple[bytes, str, float]
"""``(payload, key, arrival time)``: the time is the caller's clock (``time.monotonic()`` in the services)."""


class IngestQueue:
    """FIFO of :data:`Item`: :meth:`push` from Zenoh's callback (any thread); :meth:`take` (a batch, never blocks) or
    :meth:`get` (one, blocks until one comes) from one worker.

    At most ``capacity`` payloads and ``max_bytes`` bytes of them wait; a push into a full queue drops the oldest
    until the new one fits (the worker catches up on the newest). Bytes as well as payloads: a count alone bounds
    memory only by the largest payload a subscriber lets in (16,384 × 8 MiB; the 64 frames of a tracker's inbox,
    512 MiB). A payload larger than ``max_bytes`` by itself still goes in, alone: the subscriber refuses those from
    their size before they get here. One lock keeps the drop count exact when the worker takes while a callback
    pushes; its condition wakes a worker blocked in :meth:`get`.
    """

    def __init__(self, capacity: int, max_bytes: int | None = None) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be at least 1, not {capacity}")
        if max_bytes is not None and max_bytes < 1:
            raise ValueError(f"max_bytes must be at least 1, not {max_bytes}")
        self.capacity = capacity
        self.max_bytes = max_bytes
        self._items: deque[Item] = deque()
        self._bytes = 0
        self._ready = threading.Condition(threading.Lock())

    def push(self, data: bytes, key: str, arrived: float = 0.0) -> int:
        """Append one payload; returns how many of the oldest were dropped to make room."""
        n = len(data)
        budget = self.max_bytes
        dropped = 0
        with self._ready:
            items = self._items
            while items and (len(items) >= self.capacity or (budget is not None and self._bytes + n > budget)):
                self._bytes -= len(items.popleft()[0])
                dropped += 1
            items.append((data, key, arrived))
            self._bytes += n
            if len(items) == 1:  # a worker waits in get() only while the queue is empty
                self._ready.notify()
        return dropped

    def take(self, limit: int) -> list[Item]:
        """Up to ``limit`` of the oldest payloads, removed, in arrival order (empty when none wait)."""
        with self._ready:
            items = [self._items.popleft() for _ in range(min(limit, len(self._items)))]
            self._bytes -= sum(len(item[0]) for item in items)
        return items

    def get(self, timeout: float) -> Item | None:
        """The oldest payload, removed; waits up to ``timeout`` seconds for one (``None`` if none came)."""
        with self._ready:
            if not self._items and not self._ready.wait_for(lambda: self._items, timeout):
                return None
            item = self._items.popleft()
            self._bytes -= len(item[0])
        return item

    @property
    def queued_bytes(self) -> int:
        """Bytes of the payloads waiting now."""
        return self._bytes

    def __len__(self) -> int:
        return len(self._items)
