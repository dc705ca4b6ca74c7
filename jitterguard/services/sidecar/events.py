"""Server-sent events: fan change events out from the client's threads to every open ``/v1/events`` stream.

Events are produced on plain threads (the state poll, request handlers) and consumed by async generators on
the server's event loop. Each stream gets a bounded queue fed with ``call_soon_threadsafe``; a client that
reads too slowly loses events rather than growing memory, and is told so with a ``resync`` event (refetch
``/v1/state``) — the producer never blocks on a consumer. The ``resync`` stands where the events were lost: the
events still waiting for that client are dropped with the one that did not fit, so every event after a ``resync``
is newer than every event lost (the ``resync`` had come first and the up to 256 older events that had waited behind
it after, which a client that had refetched its state then applied over it).
"""

from __future__ import annotations

import asyncio
import itertools
import json
import threading
import weakref
from collections.abc import AsyncIterator, Callable
from typing import Any

QUEUE_SIZE = 256
MAX_STREAMS = 64
"""Open ``/v1/events`` streams at most (more get a 503). Each has its own queue and gets every event: 1000 idle
streams had cost the sidecar 70 % of a core and made ``GET /v1/state`` take 0.7 s (reads need no token, so anyone
who reaches the port could open them)."""
KEEPALIVE_S = 15.0
_CLOSE = b""  # sentinel: the server is shutting down
_RESYNC = b"resync"  # sentinel: events were dropped here (never an event frame: those begin with "id: ")


def format_event(event_id: int, kind: str, data: dict[str, Any]) -> bytes:
    """One SSE frame: ``id``, ``event`` and a single-line JSON ``data`` field."""
    payload = json.dumps(data, separators=(",", ":"), allow_nan=False)
    return f"id: {event_id}\nevent: {kind}\ndata: {payload}\n\n".encode()


class _Stream:
    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self.queue: asyncio.Queue[bytes] = asyncio.Queue(QUEUE_SIZE)

    def offer(self, frame: bytes, on_drop: Callable[[int], None]) -> None:
        """Runs on the event loop. A full queue: the client fell behind, and what waits for it is of no use once it
        has to refetch its state; it is dropped (counted), and ``resync`` and ``frame`` take its place."""
        try:
            self.queue.put_nowait(frame)
            return
        except asyncio.QueueFull:
            pass
        dropped = 0
        while not self.queue.empty():
            old = self.queue.get_nowait()
            if old is _CLOSE:  # the server is stopping: the stream ends, nothing to resync
                self.queue.put_nowait(_CLOSE)
                return
            dropped += old is not _RESYNC
        on_drop(dropped)
        self.queue.put_nowait(_RESYNC)
        self.queue.put_nowait(frame)


class EventBroker:
    """Thread-safe publish; one bounded queue per subscriber; a close that ends every stream. ``on_drop(n)``: ``n``
    events were dropped for a slow client."""

    def __init__(self, on_drop: Callable[[int], None] = lambda n: None,
                 on_count: Callable[[int], None] = lambda n: None, max_streams: int = MAX_STREAMS) -> None:
        self._max_streams = max_streams
        self._lock = threading.Lock()
        self._streams: set[_Stream] = set()
        self._ids = itertools.count(1)
        self._on_drop = on_drop
        self._on_count = on_count
        self._held: set[object] = set()  # places taken by streams whose body has not begun
        self._closed = False

    def publish(self, kind: str, data: dict[str, Any]) -> None:
        """Send an event to every stream (callable from any thread)."""
        frame = format_event(next(self._ids), kind, data)
        self._deliver(frame)

    def _deliver(self, frame: bytes) -> None:
        with self._lock:
            streams = list(self._streams)
        for s in streams:
            try:
                s.loop.call_soon_threadsafe(s.offer, frame, self._on_drop)
            except RuntimeError:  # that loop is closed: the stream is gone
                self._remove(s)

    def _remove(self, s: _Stream) -> None:
        with self._lock:
            self._streams.discard(s)
            n = len(self._streams)
        self._on_count(n)

    def close(self) -> None:
        """End every open stream (server shutdown) and refuse new ones."""
        self._closed = True
        self._deliver(_CLOSE)

    def open(self, hello: dict[str, Any], is_disconnected: Callable[[], Any]) -> AsyncIterator[bytes] | None:
        """The body of one ``/v1/events`` response — ``hello`` first, then events until disconnect/close — in a
        place taken now, or None when ``max_streams`` are open or about to be. The route asks before it answers, so
        a refusal is a 503 with ``Retry-After``: requests that had passed a bare "full?" check together were
        admitted, then told ``busy`` inside a 200 (8 of a burst of 100). The place is the body's until it ends, or
        until the body is dropped unstarted (the client left first): then it is freed with it."""
        with self._lock:
            if len(self._streams) + len(self._held) >= self._max_streams:
                return None
            place = object()
            self._held.add(place)
        body = self._stream(place, hello, is_disconnected)
        weakref.finalize(body, self._release, place).atexit = False  # nothing to free at exit
        return body

    def _release(self, place: object) -> None:
        with self._lock:
            self._held.discard(place)

    async def _stream(self, place: object, hello: dict[str, Any],
                      is_disconnected: Callable[[], Any]) -> AsyncIterator[bytes]:
        s = _Stream(asyncio.get_running_loop())
        with self._lock:  # the place taken in open() becomes this stream's
            self._held.discard(place)
            self._streams.add(s)
            n = len(self._streams)
        self._on_count(n)
        try:
            yield format_event(next(self._ids), "hello", hello)
            while not self._closed:
                try:
                    frame = await asyncio.wait_for(s.queue.get(), KEEPALIVE_S)
                except asyncio.TimeoutError:
                    if await is_disconnected():
                        return
                    yield b": keepalive\n\n"
                    continue
                if frame is _CLOSE or frame == _CLOSE:
                    return
                if frame is _RESYNC:
                    yield format_event(next(self._ids), "resync",
                                       {"reason": "events were dropped for this slow client; refetch /v1/state"})
                    continue
                yield frame
        finally:
            self._remove(s)
