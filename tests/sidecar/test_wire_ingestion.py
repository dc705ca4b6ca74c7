"""What the sidecar does with hostile heartbeats on the bus: a real classifier, feeder and sidecar (uvicorn over
HTTP), and a second Zenoh session (loopback, multicast scouting off) that publishes what a broken or malicious
node would. The sidecar must keep counting per key, keep its state and keep telling the truth on ``/readyz`` and
``/metrics``."""

from __future__ import annotations

import re
import time
from collections.abc import Iterator

import httpx
import pytest
import zenoh

from jitterguard.runtime import build_config, loopback_options
from jitterguard.schemas import encode, keys
from jitterguard.schemas.models import Heartbeat
from jitterguard.services.sidecar.app import SidecarSettings, create_app
from jitterguard.schemas.wire import MAX_HEARTBEAT_BYTES, MAX_HEARTBEAT_ENTRIES
from jitterguard.services.sidecar.client import MAX_SERVICES

from .stack import Stack, Uvicorn, start_stack, wait_for

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def stack() -> Iterator[Stack]:
    """This module's own stack: its tests leave made-up services behind in the sidecar's view."""
    s = start_stack("sc-wire", window_ready=False)
    yield s
    s.close()


@pytest.fixture()
def bus(stack: Stack) -> Iterator[zenoh.Session]:
    with zenoh.open(build_config(loopback_options(stack.ns, stack.zport))) as s:
        # a fresh session's first put could go before it had heard of the sidecar's heartbeat subscriber, and be
        # lost (a test putting one heartbeat then waited for ever, 1 run in 3): wait until the route is known
        probe = s.declare_publisher(keys.heartbeat(stack.ns, "probe"))
        wait_for(lambda: probe.matching_status.matching, "the sidecar's heartbeat subscriber seen from the bus")
        probe.undeclare()
        yield s


def _beat(name: str, **kw) -> bytes:
    return encode(Heartbeat(service=name, pid=1, stamp=time.time_ns(), last_seq=3, **kw))


def _metric(text: str, name: str, labels: str) -> float | None:
    m = re.search(rf"^{re.escape(name)}{re.escape(labels)} (\S+)$", text, re.M)
    return float(m.group(1)) if m else None


def test_a_malformed_heartbeat_is_counted_in_metrics_by_key(stack: Stack, bus: zenoh.Session) -> None:
    """The sidecar refused malformed heartbeats and counted them in its own heartbeat only: /metrics'
    ``jitterguard_sidecar_rejected_messages`` had no series at all, however many came."""
    unknown_field = encode(Heartbeat(service="x", pid=1, stamp=1)).replace(b"schema_version", b"schema_versioN")
    for payload in (b"\xc1", b"", unknown_field):
        bus.put(keys.heartbeat(stack.ns, "garbage"), payload)
    with stack.http(auth=False) as c:
        def rejected() -> float | None:
            n = _metric(c.get("/metrics").text, "jitterguard_sidecar_rejected_messages_total", '{key="heartbeat/*"}')
            return n if n is not None and n >= 3 else None
        assert wait_for(rejected, "three rejected heartbeats in /metrics") == 3
        assert "garbage" not in c.get("/readyz").json()["services"]


def test_an_oversized_heartbeat_is_refused_unread(stack: Stack, bus: zenoh.Session) -> None:
    """A heartbeat's maps were unbounded: 64 service names' worth of 100 MB counter maps were decoded and kept.
    One over MAX_HEARTBEAT_BYTES is refused from its size (and counted); a normal one from the same name is taken."""
    token = bus.liveliness().declare_token(keys.alive(stack.ns, "bloated"))
    try:
        counters = {f"c{i:07d}": i for i in range(MAX_HEARTBEAT_BYTES // 10)}
        big = _beat("bloated", counters=counters)
        assert len(big) > MAX_HEARTBEAT_BYTES
        with stack.http(auth=False) as c:
            before = _metric(c.get("/metrics").text, "jitterguard_sidecar_rejected_messages_total",
                             '{key="heartbeat/*"}') or 0.0
            bus.put(keys.heartbeat(stack.ns, "bloated"), big)
            wait_for(lambda: (_metric(c.get("/metrics").text, "jitterguard_sidecar_rejected_messages_total",
                                      '{key="heartbeat/*"}') or 0.0) == before + 1, "the big heartbeat refused")
            assert "bloated" not in c.get("/readyz").json()["services"]
            bus.put(keys.heartbeat(stack.ns, "bloated"), _beat("bloated", counters={"frames": 1}))
            wait_for(lambda: "bloated" in c.get("/readyz").json()["services"], "a normal heartbeat taken")
    finally:
        token.undeclare()


def test_a_heartbeat_with_too_many_entries_is_refused_before_it_is_built(stack: Stack, bus: zenoh.Session) -> None:
    """Within MAX_HEARTBEAT_BYTES a heartbeat held 40,000 counters, each exported as a /metrics series (64 made-up
    names: millions of series per scrape). One map over MAX_HEARTBEAT_ENTRIES is refused, counted, and none of its
    entries reaches /metrics; a heartbeat at the bound is taken."""
    wide = {f"w{i:04x}": i for i in range(MAX_HEARTBEAT_ENTRIES + 1)}
    for field in ("counters", "gauges"):
        payload = _beat("wide", **{field: wide})
        assert len(payload) < MAX_HEARTBEAT_BYTES // 10  # refused for its entries, not its size
        with stack.http(auth=False) as c:
            before = _metric(c.get("/metrics").text, "jitterguard_sidecar_rejected_messages_total",
                             '{key="heartbeat/*"}') or 0.0
            bus.put(keys.heartbeat(stack.ns, "wide"), payload)
            wait_for(lambda: (_metric(c.get("/metrics").text, "jitterguard_sidecar_rejected_messages_total",
                                      '{key="heartbeat/*"}') or 0.0) == before + 1, f"the wide {field} refused")
            assert "wide" not in c.get("/readyz").json()["services"]
            assert 'service="wide"' not in c.get("/metrics").text
    at_bound = {f"w{i:04x}": i for i in range(MAX_HEARTBEAT_ENTRIES)}
    bus.put(keys.heartbeat(stack.ns, "wide"), _beat("wide", counters=at_bound))
    with stack.http(auth=False) as c:
        wait_for(lambda: "wide" in c.get("/readyz").json()["services"], "a heartbeat at the bound taken")


def test_a_flood_of_made_up_service_names_does_not_hide_a_frozen_stage(stack: Stack, bus: zenoh.Session) -> None:
    """A tracker frozen on the bus (token present, heartbeats stopped) makes /readyz 503. Heartbeats are kept for
    MAX_SERVICES names, and a flood of made-up names used to push out the oldest — the frozen tracker's — so /readyz
    went 200 while nothing moved. A name whose token is on the bus now keeps its slot; made-up names displace only
    each other (and the sidecar's memory stays bounded)."""
    token = bus.liveliness().declare_token(keys.alive(stack.ns, "tracker"))
    try:
        bus.put(keys.heartbeat(stack.ns, "tracker"), _beat("tracker"))
        with stack.http(auth=False) as c:
            def frozen() -> dict | None:
                r = c.get("/readyz")
                return r.json() if r.status_code == 503 and "tracker: no heartbeat" in r.json()["reason"] else None
            wait_for(frozen, "readyz to report the frozen tracker")
            n = 4 * MAX_SERVICES
            for i in range(n):
                bus.put(keys.heartbeat(stack.ns, f"madeup{i:04d}"), _beat(f"madeup{i:04d}"),
                        congestion_control=zenoh.CongestionControl.BLOCK)
            last = f"madeup{n - 1:04d}"
            body = wait_for(lambda: (lambda b: b if last in b["services"] else None)(c.get("/readyz").json()),
                            "the last made-up heartbeat taken")
            assert len(body["services"]) <= MAX_SERVICES
            assert "tracker" in body["services"] and "classifier" in body["services"]
            r = c.get("/readyz")
            assert r.status_code == 503 and "tracker: no heartbeat" in r.json()["reason"], r.text
            def thawed() -> bool:  # it beats again: ready again
                bus.put(keys.heartbeat(stack.ns, "tracker"), _beat("tracker"))
                return c.get("/readyz").status_code == 200
            wait_for(thawed, "readyz once the tracker beats again")
    finally:
        bus.put(keys.heartbeat(stack.ns, "tracker"), _beat("tracker"))
        token.undeclare()


def test_event_streams_are_bounded(stack: Stack) -> None:
    """Each ``/v1/events`` stream has its own bounded queue, but their number had no bound (reads need no token):
    1000 idle streams cost the sidecar 70 % of a core and made ``GET /v1/state`` take 0.7 s. Beyond
    ``max_event_streams`` a new one is a 503 with Retry-After; once one closes, there is room again."""
    app = create_app(SidecarSettings(zenoh=loopback_options(stack.ns, stack.zport), max_event_streams=2))
    server = Uvicorn(app)
    try:
        with httpx.Client(base_url=server.url, timeout=10.0) as c:
            wait_for(lambda: c.get("/readyz").status_code == 200, "the second sidecar ready")
            with c.stream("GET", "/v1/events") as one, c.stream("GET", "/v1/events") as two:
                readers = [r.iter_text() for r in (one, two)]  # kept: a dropped iterator closes its stream
                for r, text in zip((one, two), readers):
                    assert r.status_code == 200 and "event: hello" in next(text)
                third = c.get("/v1/events")
                assert third.status_code == 503 and third.headers["Retry-After"], third.text
                assert "event streams" in third.json()["detail"]
                metrics = c.get("/metrics").text
                assert _metric(metrics, "jitterguard_sidecar_sse_clients", "") == 2
            def admitted() -> bool:
                with c.stream("GET", "/v1/events") as again:
                    return again.status_code == 200 and "event: hello" in next(iter(again.iter_text()))
            wait_for(admitted, "room for a stream once the others closed")
    finally:
        server.close()


def test_a_burst_of_event_streams_past_the_bound_is_answered_503_never_busy_inside_a_200(stack: Stack) -> None:
    """Requests that passed the route's "full?" check together were admitted, then told ``busy`` inside a 200 (8 of
    a burst of 100 at the bound of 64). The route now reserves each stream's place before it answers: every stream
    past the bound is a 503 with Retry-After."""
    import asyncio

    app = create_app(SidecarSettings(zenoh=loopback_options(stack.ns, stack.zport), max_event_streams=4))
    server = Uvicorn(app)

    async def burst(n: int = 24) -> list[tuple[int, str]]:
        answered, everyone = [0], asyncio.Event()

        def tally() -> None:
            answered[0] += 1
            if answered[0] == n:
                everyone.set()

        async with httpx.AsyncClient(base_url=server.url, timeout=30.0,
                                     limits=httpx.Limits(max_connections=40)) as c:
            async def one() -> tuple[int, str]:
                async with c.stream("GET", "/v1/events") as r:
                    tally()
                    if r.status_code != 200:
                        return r.status_code, r.headers.get("Retry-After", "")
                    first = await anext(r.aiter_text())
                    # held open until every request of the burst has its answer: no place frees up meanwhile
                    await asyncio.wait_for(everyone.wait(), 30)
                    return 200, first
            return await asyncio.gather(*(one() for _ in range(n)))

    try:
        with httpx.Client(base_url=server.url, timeout=10.0) as c:
            wait_for(lambda: c.get("/readyz").status_code == 200, "the second sidecar ready")
        broker = app.state.sidecar.broker  # the streams open at once, as the broker counts them for /metrics
        peak, counted = [0], broker._on_count

        def count(n: int) -> None:
            peak[0] = max(peak[0], n)
            counted(n)

        broker._on_count = count
        got = asyncio.run(burst())
        ok = [text for code, text in got if code == 200]
        # every admitted stream begins with hello (none is told busy), every other request is a 503, and never are
        # more than the bound open at once (a stream that uvicorn ends early under load frees its place for another)
        assert len(ok) >= 4 and all(t.split("\n")[1] == "event: hello" for t in ok), got
        assert all(code == 503 and retry for code, retry in got if code != 200), got
        assert peak[0] == 4, peak
    finally:
        server.close()


def test_a_slow_event_client_gets_resync_where_its_events_were_lost(stack: Stack) -> None:
    """A client that reads ``/v1/events`` too slowly loses events (its queue is bounded, the drops are counted) and is
    told so with ``resync``: refetch ``/v1/state``. The ``resync`` had been sent before the up to 256 older events
    still waiting for that client, and the loss came after them unmarked: a client that refetched its state on
    ``resync`` then applied those stale changes over it. Now every gap in the stream is where a ``resync`` stands,
    and every event after one is newer than every event lost."""
    import json
    import threading

    broker = stack.server.server.config.app.state.sidecar.broker  # the sidecar's own broker: real events, real HTTP
    n_events, pad = 2000, "x" * 20_000  # 40 MB: more than the socket buffers and the stream's queue hold
    with httpx.Client(base_url=stack.url, timeout=10.0) as c, c.stream("GET", "/v1/events") as r:
        dropped_before = _metric(c.get("/metrics").text, "jitterguard_sidecar_sse_dropped_events_total", "") or 0.0
        lines = r.iter_lines()
        assert next(lines).startswith("id: ") and next(lines) == "event: hello"
        for n in range(n_events):  # while this client reads nothing
            broker.publish("probe", {"n": n, "pad": pad})
        threading.Timer(2.0, broker.publish, ("probe", {"n": n_events, "pad": ""})).start()  # once it reads again
        seen: list[int | str] = []
        event = None
        deadline = time.monotonic() + 60
        for line in lines:
            assert time.monotonic() < deadline, "the last event never came"
            if line.startswith("event: "):
                event = line[7:]
                if event == "resync":
                    seen.append("resync")
            elif line.startswith("data: ") and event == "probe":
                seen.append(json.loads(line[6:])["n"])
                if seen[-1] == n_events:
                    break
        dropped = _metric(c.get("/metrics").text, "jitterguard_sidecar_sse_dropped_events_total", "") - dropped_before
    numbers = [n for n in seen if n != "resync"]
    lost = n_events + 1 - len(numbers)
    assert "resync" in seen and lost > 0 and dropped >= lost and numbers == sorted(numbers)
    for i, item in enumerate(seen[1:], 1):
        before = next((n for n in reversed(seen[:i]) if n != "resync"), -1)
        if item == "resync":  # ... stands where events were lost
            after = next(n for n in seen[i:] if n != "resync")
            assert after > before + 1, f"resync between {before} and {after}, where nothing was lost"
        else:  # and no events were lost anywhere else
            assert item == before + 1 or seen[i - 1] == "resync", f"{before} to {item} lost without a resync"


def test_every_service_health_and_counters_are_in_metrics(stack: Stack, bus: zenoh.Session) -> None:
    """/metrics had the classifier's figures only: a stalled tracker or a frozen detector was visible to whoever
    asked /readyz, never to an alert rule. Each heard service now has up / healthy / heartbeat age / last seq and
    its counters (running counts as counters, now.* as gauges) and gauges, labelled by service."""
    token = bus.liveliness().declare_token(keys.alive(stack.ns, "tracker"))
    try:
        bus.put(keys.heartbeat(stack.ns, "tracker"),
                _beat("tracker", health="stalled", health_reason="input waited 5 s with no output",
                      counters={"frames": 41, "now.tracks": 7}, gauges={"period_s": 0.1}))
        with stack.http(auth=False) as c:
            def stalled() -> str | None:
                text = c.get("/metrics").text
                return text if _metric(text, "jitterguard_service_healthy", '{service="tracker"}') == 0.0 else None
            text = wait_for(stalled, "the stalled tracker in /metrics")
            assert _metric(text, "jitterguard_service_up", '{service="tracker"}') == 1.0
            assert _metric(text, "jitterguard_service_last_seq", '{service="tracker"}') == 3.0
            assert _metric(text, "jitterguard_service_counter_total", '{name="frames",service="tracker"}') == 41.0
            assert _metric(text, "jitterguard_service_current", '{name="now.tracks",service="tracker"}') == 7.0
            assert _metric(text, "jitterguard_service_counter_total", '{name="now.tracks",service="tracker"}') is None
            assert _metric(text, "jitterguard_service_gauge", '{name="period_s",service="tracker"}') == 0.1
            assert (_metric(text, "jitterguard_service_heartbeat_age_seconds", '{service="tracker"}') or 99.0) < 30.0
            # the classifier of the stack beats too, and is healthy
            assert _metric(text, "jitterguard_service_healthy", '{service="classifier"}') == 1.0
            bus.put(keys.heartbeat(stack.ns, "tracker"), _beat("tracker", counters={"frames": 42}))
            wait_for(lambda: _metric(c.get("/metrics").text, "jitterguard_service_healthy", '{service="tracker"}')
                     == 1.0, "the tracker healthy again")
        token.undeclare()
        token = None
        with stack.http(auth=False) as c:
            wait_for(lambda: _metric(c.get("/metrics").text, "jitterguard_service_up", '{service="tracker"}') == 0.0,
                     "the tracker's token gone")
    finally:
        if token is not None:
            token.undeclare()


def test_a_flood_of_liveliness_tokens_does_not_grow_the_sidecar(stack: Stack, bus: zenoh.Session) -> None:
    """Every liveliness token on the bus was kept by name, so a node declaring made-up tokens grew the sidecar's set
    (and each readiness check's copy of it) without bound. Past MAX_TOKENS names a new token is counted and not
    kept; the classifier's own token and the pipeline's are always kept, and readiness holds."""
    from jitterguard.services.sidecar.client import MAX_TOKENS, ClassifierClient

    client = ClassifierClient(loopback_options(stack.ns, stack.zport))
    tokens = []
    try:
        wait_for(client.is_alive, "the classifier's token seen")
        n = MAX_TOKENS + 100
        tokens = [bus.liveliness().declare_token(keys.alive(stack.ns, f"flood{i:04d}")) for i in range(n)]
        wait_for(lambda: client.counters.get("liveliness_tokens_ignored") >= 1, "tokens past the bound counted")
        tracker = bus.liveliness().declare_token(keys.alive(stack.ns, "tracker"))  # a stage comes after the flood
        tokens.append(tracker)
        wait_for(lambda: "tracker" in client._on_bus, "the tracker's token kept past the bound")
        assert len(client._on_bus) <= MAX_TOKENS + 1
        assert client.is_alive()
    finally:
        for t in tokens:
            t.undeclare()
        client.close()
