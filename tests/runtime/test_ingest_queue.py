"""The bounded ingest queue behind ``Service.subscribe_queue``: what it drops when full, and that the count of
drops stays exact while Zenoh's callbacks push and the worker takes at the same time."""

from __future__ import annotations

import threading

import pytest

from jitterguard.runtime.ingest_queue import IngestQueue


def test_a_full_queue_drops_its_oldest_and_says_how_many() -> None:
    q = IngestQueue(3)
    assert [q.push(bytes([i]), f"k/{i}") for i in range(5)] == [0, 0, 0, 1, 1]
    assert q.take(2) == [(b"\x02", "k/2", 0.0), (b"\x03", "k/3", 0.0)]
    assert q.take(10) == [(b"\x04", "k/4", 0.0)]
    assert q.take(10) == [] and len(q) == 0


def test_a_queue_bounded_in_bytes_drops_as_many_of_the_oldest_as_a_large_payload_needs() -> None:
    """A count alone bounds memory only by the largest payload let in (16,384 of up to 8 MiB): the bytes waiting
    are bounded too, and a payload that needs the room of several small ones drops them all, counted."""
    q = IngestQueue(100, max_bytes=25)
    assert [q.push(b"x" * 10, str(i)) for i in range(2)] == [0, 0]
    assert q.queued_bytes == 20
    assert q.push(b"y" * 5, "2") == 0 and q.queued_bytes == 25
    assert q.push(b"z" * 24, "3") == 3  # every one before it goes
    assert [k for _, k, _ in q.take(10)] == ["3"] and q.queued_bytes == 0
    assert q.push(b"w" * 40, "4") == 0  # larger than the whole budget: alone, as the caller refuses those first
    assert q.push(b"v", "5") == 1 and q.queued_bytes == 1


def test_drops_are_counted_exactly_while_producers_push_and_a_worker_takes() -> None:
    """Two callback threads and one worker at once: every push is either taken or counted dropped, none twice
    (a check of the length before the append, without the lock, can count a drop the worker's take made room
    for), and each producer's payloads come out in the order pushed."""
    q, per_producer = IngestQueue(50, max_bytes=4 * 40), 40_000
    dropped = [0, 0]
    taken: list[tuple[bytes, str, float]] = []
    done = threading.Event()

    def produce(n: int) -> None:
        for i in range(per_producer):
            dropped[n] += q.push(i.to_bytes(4, "big"), str(n))

    def consume() -> None:
        while not done.is_set() or len(q):
            taken.extend(q.take(7))

    producers = [threading.Thread(target=produce, args=(n,)) for n in range(2)]
    worker = threading.Thread(target=consume)
    worker.start()
    for t in producers:
        t.start()
    for t in producers:
        t.join()
    done.set()
    worker.join()
    assert len(taken) + sum(dropped) == 2 * per_producer and q.queued_bytes == 0
    for n in ("0", "1"):
        seq = [int.from_bytes(d, "big") for d, k, _ in taken if k == n]
        assert seq == sorted(seq) and len(set(seq)) == len(seq)


def test_get_hands_over_the_oldest_with_its_arrival_time_and_waits_only_while_empty() -> None:
    q = IngestQueue(2, max_bytes=8)
    assert q.get(0.01) is None  # nothing came: None once the timeout has passed
    q.push(b"abcd", "k/a", 1.5)
    q.push(b"efgh", "k/b", 2.5)
    assert q.push(b"ij", "k/c", 3.5) == 1  # eight bytes at most: the oldest went
    assert q.get(0) == (b"efgh", "k/b", 2.5) and q.queued_bytes == 2
    assert q.get(0) == (b"ij", "k/c", 3.5) and q.queued_bytes == 0 and len(q) == 0


def test_a_worker_blocked_in_get_wakes_when_a_payload_comes() -> None:
    """The tracker's worker sleeps in get() between frames: a push from another thread must wake it at once, not
    at its timeout (a frame would otherwise wait up to the idle period)."""
    q = IngestQueue(4)
    got: list[object] = []
    waiting = threading.Event()

    def worker() -> None:
        waiting.set()
        got.append(q.get(30.0))

    t = threading.Thread(target=worker, daemon=True)
    t.start()
    assert waiting.wait(5)
    q.push(b"frame", "k", 7.0)
    t.join(10)  # a worker left waiting for its 30 s timeout fails here
    assert not t.is_alive() and got == [(b"frame", "k", 7.0)]


@pytest.mark.parametrize("capacity, max_bytes", [(0, None), (1, 0)])
def test_a_queue_refuses_a_bound_that_holds_nothing(capacity: int, max_bytes: int | None) -> None:
    with pytest.raises(ValueError):
        IngestQueue(capacity, max_bytes)
