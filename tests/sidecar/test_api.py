"""The sidecar over real HTTP against a real classifier over real Zenoh (see ``stack.py``)."""

from __future__ import annotations

import json
import os
import re
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import httpx
import msgpack
import pytest
import zenoh

from jitterguard.runtime import build_config, loopback_options
from jitterguard.runtime.config_auth import NONCE_BYTES, write_attachment
from jitterguard.schemas import encode, keys
from jitterguard.schemas.models import ClassifierConfig, ConfigReply, Heartbeat, config_etag
from jitterguard.services.classifier.config import PRESETS

AUTHORS_ALPHA = PRESETS["authors"]["alpha_per_class"]
from jitterguard.services.sidecar.app import SidecarSettings, create_app
from jitterguard.services.sidecar.client import ClassifierClient, ClassifierRejected
from jitterguard.services.sidecar.core import StateView, TrackView

from .stack import PAPER_STATISTIC, Stack, Uvicorn, start_stack, wait_for

pytestmark = pytest.mark.integration

DEFAULTS = ClassifierConfig(**PAPER_STATISTIC).model_dump(mode="json", exclude={"schema_version"})
"""The config every test starts from: the defaults with the paper's statistic (what the scenario is built for)."""


def _state_of(body: dict, track_id: str) -> str | None:
    return next((t["state"] for t in body["tracks"] if t["id"] == track_id), None)


@pytest.fixture(autouse=True)
def _reset_config(stack: Stack):
    """Every test starts from DEFAULTS (and leaves it so), already seen in the served state."""
    with stack.http() as c:
        assert c.put("/v1/config", json=PAPER_STATISTIC).status_code == 200
    stack.wait_state(lambda b: b["mode"] == "z_test" and all(t["alpha"] == 1.96 for t in b["tracks"]),
                     "the default config in the served state")
    yield
    with stack.http() as c:
        c.put("/v1/config", json=PAPER_STATISTIC)


def test_health_and_readiness(stack: Stack) -> None:
    with stack.http(auth=False) as c:
        assert c.get("/healthz").json() == {"status": "ok"}
        for path in ("/healthz", "/readyz"):  # probes that ask with HEAD (HAProxy's default) get the status alone
            head = c.head(path)
            assert head.status_code == 200 and head.content == b"", (path, head.status_code)
        # every other GET route answers HEAD with the GET's headers (had been 405): a cache asks /v1/config's ETag
        for path in ("/v1/config", "/v1/state", "/metrics", "/", f"/v1/state/{stack.tracks[0].track_id}"):
            get, head = c.get(path), c.head(path)
            assert head.status_code == get.status_code == 200 and head.content == b"", (path, head.status_code)
            assert head.headers["content-type"] == get.headers["content-type"], path
        assert c.head("/v1/config").headers["etag"] == c.get("/v1/config").headers["etag"]
        assert c.head("/v1/state?state=nonsense").status_code == 422  # the GET's checks hold
        r = c.get("/readyz")
        assert r.status_code == 200
        body = r.json()
        assert body["ready"] is True and body["liveliness"] is True and body["reason"] == "ok"
        assert body["heartbeat_age_s"] is not None and body["last_seq"] >= 0
        assert body["services"]["classifier"]["health"] == "ok"


def test_readiness_reports_a_service_of_the_pipeline_that_makes_no_progress(stack: Stack) -> None:
    """A tracker whose frames keep failing (its heartbeat says so) makes the sidecar not ready, with the reason;
    once its heartbeat says ok again, the sidecar is ready again."""
    def beat(health: str, reason: str) -> bytes:
        return encode(Heartbeat(service="tracker", pid=1, stamp=time.time_ns(), last_seq=41, health=health,
                                health_reason=reason))

    with zenoh.open(build_config(loopback_options(stack.ns, stack.zport))) as s, stack.http(auth=False) as c:
        def readyz_after(payload: bytes, status: int) -> dict | None:
            s.put(keys.heartbeat(stack.ns, "tracker"), payload)
            r = c.get("/readyz")
            return r.json() if r.status_code == status else None

        body = wait_for(lambda: readyz_after(beat("failing", "the last 7 frames failed (MemoryError)"), 503),
                        "readyz to report the failing tracker")
        assert body["ready"] is False and body["liveliness"] is True
        assert "tracker failing: the last 7 frames failed (MemoryError)" in body["reason"]
        assert body["services"]["tracker"] == {**body["services"]["tracker"], "health": "failing", "last_seq": 41}
        body = wait_for(lambda: readyz_after(beat("ok", ""), 200), "readyz once the tracker recovers")
        assert body["reason"] == "ok" and body["services"]["tracker"]["health"] == "ok"


def test_classifier_up_is_the_classifier_not_another_stages_fault(stack: Stack) -> None:
    """``jitterguard_classifier_up`` says whether the classifier itself is on the bus with a recent heartbeat. It
    had followed the pipeline's readiness: a failing (or frozen) tracker set it to 0 beside a classifier that was up
    and healthy, so an alert on it blamed the wrong process. The tracker's fault is told by ``/readyz`` and by
    ``jitterguard_service_healthy{service="tracker"}``."""
    beat = encode(Heartbeat(service="tracker", pid=1, stamp=time.time_ns(), last_seq=41, health="failing",
                            health_reason="the last 7 frames failed (MemoryError)"))
    with zenoh.open(build_config(loopback_options(stack.ns, stack.zport))) as s, stack.http(auth=False) as c:
        def failing_tracker_scraped() -> str | None:
            s.put(keys.heartbeat(stack.ns, "tracker"), beat)
            if c.get("/readyz").status_code != 503:
                return None
            text = c.get("/metrics").text
            return text if _metric(text, "jitterguard_service_healthy", '{service="tracker"}') == 0.0 else None

        text = wait_for(failing_tracker_scraped, "readyz and /metrics to report the failing tracker")
        assert _metric(text, "jitterguard_service_healthy", '{service="classifier"}') == 1.0
        assert _metric(text, "jitterguard_classifier_up") == 1.0
        s.put(keys.heartbeat(stack.ns, "tracker"), encode(Heartbeat(service="tracker", pid=1, stamp=time.time_ns(),
                                                                    last_seq=42, health="ok")))
        wait_for(lambda: c.get("/readyz").status_code == 200, "readyz once the tracker says ok again")


def test_a_service_outside_the_pipeline_that_fails_is_a_warning_not_a_readiness_fault(stack: Stack) -> None:
    """The monitor on a full disk (its summary cannot be written) or a failing Foxglove bridge do not make the
    classifier's objects wrong: /readyz stays 200 and names them under ``warnings`` (a monitor that could not write
    had made the classifier "not ready")."""
    beat = encode(Heartbeat(service="monitor", pid=2, stamp=time.time_ns(), last_seq=-1, health="failing",
                            health_reason="cannot write /run/x/summary.json: No space left on device"))
    with zenoh.open(build_config(loopback_options(stack.ns, stack.zport))) as s, stack.http(auth=False) as c:
        def warned() -> dict | None:
            s.put(keys.heartbeat(stack.ns, "monitor"), beat)
            r = c.get("/readyz")
            body = r.json()
            return body if r.status_code == 200 and any(w.startswith("monitor") for w in body["warnings"]) else None

        body = wait_for(warned, "readyz to warn of the failing monitor")
        assert body["ready"] is True and body["reason"] == "ok"
        assert "monitor failing: cannot write /run/x/summary.json: No space left on device" in body["warnings"]


def test_readyz_names_a_service_that_refuses_messages_while_frames_flow(stack: Stack) -> None:
    """A recorder whose ``rejected.<key>`` counter rises (a publisher on the bus sends it messages that break the
    contract) stays ``ok`` and the pipeline ready: ``GET /readyz`` names it under ``warnings`` with what it refused
    in the last 10 s — it had done so only while the classifier's frames stood still."""
    refused = iter(range(0, 10**6, 7))
    with zenoh.open(build_config(loopback_options(stack.ns, stack.zport))) as s, stack.http(auth=False) as c:
        def warned() -> dict | None:
            s.put(keys.heartbeat(stack.ns, "record"), encode(Heartbeat(
                service="record", pid=6, stamp=time.time_ns(), health="ok",
                counters={"rejected.motion/*": next(refused), "written": 10})))
            r = c.get("/readyz")
            body = r.json()
            return body if r.status_code == 200 and any(w.startswith("record refused") for w in body["warnings"]) \
                else None

        body = wait_for(warned, "readyz to warn of the recorder's refusals")
        (warning,) = [w for w in body["warnings"] if w.startswith("record refused")]
        assert "(rejected.motion/* +" in warning and "jitterguard logs record" in warning, warning
        assert body["ready"] is True and body["services"]["record"]["health"] == "ok"


def test_readiness_reports_a_service_frozen_on_the_bus_or_a_stage_that_left_it() -> None:
    """A service whose liveliness token is present but whose heartbeats stopped (a SIGSTOPped process: the
    watchdog inside it cannot run) made no difference to /readyz, which stayed 200 while nothing moved. Once its
    Zenoh lease expires the token goes: a pipeline stage that left the bus stays a problem until it is back
    (/readyz had turned 200 again ~10 s into the freeze); a replay that leaves (the end of its recording) is not."""
    def beat(name: str) -> bytes:
        return encode(Heartbeat(service=name, pid=1, stamp=time.time_ns(), last_seq=7, health="ok"))

    stack = start_stack("sc-left", window_ready=False)  # its own: a stage that left stays left for the stack
    try:
        with zenoh.open(build_config(loopback_options(stack.ns, stack.zport))) as s, stack.http(auth=False) as c:
            def not_ready(why: str) -> dict | None:
                r = c.get("/readyz")
                return r.json() if r.status_code == 503 and why in r.json()["reason"] else None

            replay = s.liveliness().declare_token(keys.alive(stack.ns, "replay"))
            s.put(keys.heartbeat(stack.ns, "replay"), beat("replay"))
            token = s.liveliness().declare_token(keys.alive(stack.ns, "detector"))
            s.put(keys.heartbeat(stack.ns, "detector"), beat("detector"))
            body = wait_for(lambda: not_ready("detector"), "readyz to report the silent detector", timeout=20)
            assert "detector: no heartbeat for" in body["reason"] and "frozen" in body["reason"]
            # its entry says so too: it had read "ok" (its last heartbeat's word) beside a reason blaming it
            assert body["services"]["detector"]["health"] == "silent", body["services"]
            assert "frozen" in body["services"]["detector"]["reason"]
            assert body["services"]["classifier"]["health"] == "ok"
            replay.undeclare()
            token.undeclare()
            body = wait_for(lambda: not_ready("left the bus"), "readyz to report the detector gone", timeout=20)
            assert "detector: left the bus" in body["reason"] and "replay" not in body["reason"]
            assert body["services"]["detector"]["health"] == "silent"
            assert "left the bus" in body["services"]["detector"]["reason"]
            time.sleep(1.0)
            assert c.get("/readyz").status_code == 503  # it stays a problem: no frame reaches the classifier
            token = s.liveliness().declare_token(keys.alive(stack.ns, "detector"))  # restarted
            s.put(keys.heartbeat(stack.ns, "detector"), beat("detector"))
            body = wait_for(lambda: (r := c.get("/readyz")).status_code == 200 and r.json(),
                            "readyz once the detector is back")
            assert body["services"]["detector"]["health"] == "ok"

            # a service outside the pipeline that leaves (a monitor frozen past its lease looks the same) stays
            # a warning: it had dropped out of `warnings` once its token expired, ~10 s into the freeze
            monitor = s.liveliness().declare_token(keys.alive(stack.ns, "monitor"))
            s.put(keys.heartbeat(stack.ns, "monitor"), beat("monitor"))
            wait_for(lambda: "monitor" in c.get("/readyz").json()["services"], "the monitor's heartbeat")
            monitor.undeclare()

            def warned() -> dict | None:
                s.put(keys.heartbeat(stack.ns, "detector"), beat("detector"))  # keep the pipeline ready
                r = c.get("/readyz")
                body = r.json()
                return body if any(w.startswith("monitor: left the bus") for w in body["warnings"]) else None

            body = wait_for(warned, "readyz to warn of the monitor gone", timeout=20)
            assert body["ready"] is True and body["services"]["monitor"]["health"] == "silent", body
            token.undeclare()
    finally:
        stack.close()


def test_frames_that_enter_and_never_come_out_are_a_readiness_fault() -> None:
    """Readiness had held a stage that left the bus against the pipeline only if the sidecar had seen it leave: a
    sidecar restarted after the tracker had stopped for good answered 200 "ok", the tracker unlisted, while the
    replay published and no object came out (its one warning said "no input"). Frames entering — a source's
    heartbeat seq moving — while the classifier processes none for the pipeline's stall limit is now a readiness
    fault, whoever is missing; the classifier's frames moving, or no source feeding, is none. A service's refusals
    are warned of whether frames flow or stand."""
    stack = start_stack("sc-stuck", window_ready=False)
    client = ClassifierClient(loopback_options(stack.ns, stack.zport), pipeline_stall_s=3.0)  # a fresh sidecar
    try:
        with zenoh.open(build_config(loopback_options(stack.ns, stack.zport))) as s:
            replay = s.liveliness().declare_token(keys.alive(stack.ns, "replay"))
            seq = iter(range(10**6))

            def replay_beats_until(cond: Callable[[dict], bool]) -> dict | None:
                s.put(keys.heartbeat(stack.ns, "replay"), encode(Heartbeat(
                    service="replay", pid=3, stamp=time.time_ns(), last_seq=next(seq), health="ok")))
                body = client.readiness()
                return body if cond(body) else None

            # the replay publishes and the classifier's frames move: ready, past the stall limit
            t0 = time.monotonic()
            body = wait_for(lambda: replay_beats_until(lambda b: time.monotonic() - t0 > 5.0), "5 s of frames")
            assert body["ready"] is True and body["reason"] == "ok", body
            # while frames flow, a service that refuses part of what it is sent is named too (it had shown only in
            # its counters); the state poll's readiness checks leave that reckoning out
            rogue = iter(range(0, 10**6, 3))

            def foxglove_refuses() -> dict | None:
                replay_beats_until(lambda b: True)
                s.put(keys.heartbeat(stack.ns, "foxglove"), encode(Heartbeat(
                    service="foxglove", pid=5, stamp=time.time_ns(), health="ok",
                    counters={"rejected.motion/x": next(rogue)})))
                body = client.readiness(refusals=True)
                return body if any(w.startswith("foxglove refused") for w in body["warnings"]) else None

            body = wait_for(foxglove_refuses, "readyz to warn of refusals while frames flow", timeout=20)
            assert body["ready"] is True and not any("processed no frame" in w for w in body["warnings"]), body
            assert "(rejected.motion/x +" in next(w for w in body["warnings"] if w.startswith("foxglove refused"))
            assert not any("refused" in w for w in client.readiness()["warnings"])
            # nothing reaches the classifier any more (its tracker gone, which this sidecar never heard of)
            stack.feeder.pause()
            body = wait_for(lambda: replay_beats_until(lambda b: not b["ready"]), "readyz to report frames stuck",
                            timeout=30)
            assert "frames enter the pipeline (replay at seq" in body["reason"], body["reason"]
            assert "a stage between them is missing, stuck or cut off" in body["reason"]
            assert "tracker" not in body["services"] and body["services"]["classifier"]["health"] == "ok"
            # the source stops too: no input is no fault, and the warning says so again
            replay.undeclare()
            wait_for(lambda: (b := client.readiness())["ready"] and any(
                w.startswith("no input: the classifier has processed no frame") for w in b["warnings"]),
                "ready, with a warning of no input, once nothing enters", timeout=30)
            # a ROS 2 bridge fed only scans that break their contract publishes nothing and stays ok (a restart
            # cannot mend them): the warning names it and what it refused, not just "no input"
            bridge = s.liveliness().declare_token(keys.alive(stack.ns, "ros2-in"))
            refused = iter(range(0, 10**6, 20))

            def bridge_refuses() -> dict | None:
                s.put(keys.heartbeat(stack.ns, "ros2-in"), encode(Heartbeat(
                    service="ros2-in", pid=4, stamp=time.time_ns(), health="ok",
                    counters={"invalid": next(refused), "published": 0})))
                body = client.readiness(refusals=True)
                return body if any(w.startswith("ros2-in refused") for w in body["warnings"]) else None

            body = wait_for(bridge_refuses, "readyz to warn of the bridge's refusals", timeout=20)
            (warning,) = [w for w in body["warnings"] if w.startswith("ros2-in refused")]
            assert "messages in the last 10 s (invalid +" in warning and body["ready"] is True, body
            bridge.undeclare()
            # frames come out again
            stack.feeder.resume()
            wait_for(lambda: not any("processed no frame" in w for w in client.readiness()["warnings"]),
                     "no warning of standing frames once the classifier's frames move")
    finally:
        client.close()
        stack.close()


def test_query_parameters_a_route_does_not_take_or_gives_twice_are_a_422_naming_them(stack: Stack) -> None:
    """``/v1/state?sate=dynamic`` (a typo) had returned every track, and ``?state=static&state=dynamic`` the last
    value's tracks, both 200."""
    with stack.http(auth=False) as c:
        for path, params, loc, kind in (("/v1/state", [("sate", "dynamic")], "sate", "extra_forbidden"),
                                        ("/v1/state", [("state", "static"), ("state", "dynamic")], "state",
                                         "duplicate_query"),
                                        ("/v1/config", [("window_size", "12")], "window_size", "extra_forbidden"),
                                        (f"/v1/state/{stack.tracks[0].track_id}", [("x", "1")], "x",
                                         "extra_forbidden"),
                                        # the health routes, /metrics and the page too (they had answered 200)
                                        *((p, [("x", "1")], "x", "extra_forbidden")
                                          for p in ("/healthz", "/readyz", "/metrics", "/", "/openapi.json"))):
            r = c.get(path, params=params)
            assert r.status_code == 422, (path, params, r.text)
            assert [(d["loc"], d["type"]) for d in r.json()["detail"]] == [(["query", loc], kind)], r.text
        assert c.get("/v1/state", params={"state": "dynamic", "class": "car"}).status_code == 200
        assert c.get("/", params={"view": "-40,-40,40,40", "refresh": "100", "track": "ab" * 16}).status_code == 200


def test_a_path_with_a_trailing_slash_is_no_route_and_an_encoded_write_is_refused(stack: Stack) -> None:
    """``/v1/state/`` had been a 307 to ``/v1/state`` — a write too (``POST /v1/config/preset/paper/``), which a
    client following it re-sends elsewhere; and a body sent with ``Content-Encoding: gzip`` had been read as plain
    JSON and applied. Now a 404, and a 415 that applies nothing."""
    with stack.http() as c:
        before = c.get("/v1/config").json()
        for method, path in (("GET", "/v1/state/"), ("GET", "/v1/config/"), ("POST", "/v1/config/preset/paper/")):
            r = c.request(method, path)
            assert r.status_code == 404 and "location" not in r.headers, (method, path, r.status_code)
        r = c.patch("/v1/config", content=b'{"alpha_default": 0.5}',
                    headers={"Content-Type": "application/json", "Content-Encoding": "gzip"})
        assert r.status_code == 415 and "Content-Encoding" in r.json()["detail"], r.text
        r = c.patch("/v1/config", content=b'{"alpha_default": 0.5}',
                    headers={"Content-Type": "application/json", "Content-Encoding": "identity"})
        assert r.status_code == 200
        assert c.put("/v1/config", json=before).status_code == 200


def test_a_preset_takes_no_body_and_applies_nothing_when_one_is_sent(stack: Stack) -> None:
    """A preset POST had applied its preset whatever body came with it, malformed JSON included."""
    with stack.http() as c:
        before = c.get("/v1/config").json()
        for content, status in ((b"garbage{", 422), (b'{"x": 1}', 422), (b"[]", 422), (b"\xff", 400)):
            r = c.post("/v1/config/preset/authors", content=content, headers={"Content-Type": "application/json"})
            assert r.status_code == status, (content, r.text)
            assert c.get("/v1/config").json() == before, content
        r = c.post("/v1/config/preset/authors", content=b"{}", headers={"Content-Type": "application/json"})
        assert r.status_code == 200 and r.json()["alpha_per_class"] == AUTHORS_ALPHA
        c.put("/v1/config", json=before)


def test_state_appears_with_every_track(stack: Stack) -> None:
    with stack.http(auth=False) as c:
        r = c.get("/v1/state")
    assert r.status_code == 200 and r.headers["content-type"] == "application/json"
    body = r.json()
    view = StateView.model_validate(body)
    assert view.counts.total == len(stack.tracks) == len(view.tracks)
    by_id = {t.id: t for t in view.tracks}
    assert set(by_id) == {t.track_id for t in stack.tracks}
    for t in stack.tracks:
        v = by_id[t.track_id]
        expected = {"parked": "static", "mover": "dynamic", "creeper": "static"}[t.kind]
        assert v.state == expected, (t.kind, v)
        assert v.window_fill == 1.0 and v.alpha == 1.96 and v.threshold == 1.96
    creeper = by_id[stack.track("creeper").track_id]
    assert 0.9 <= creeper.z <= 1.5, creeper  # the borderline: between 0.5 and 1.96 by construction
    assert by_id[stack.tracks[5].track_id].class_ == "pedestrian"
    assert int(r.headers["x-classifier-seq"]) == body["seq"]


def test_state_filters(stack: Stack) -> None:
    with stack.http(auth=False) as c:
        dyn = c.get("/v1/state", params={"state": "dynamic"}).json()
        peds = c.get("/v1/state", params={"class": "pedestrian"}).json()
        assert c.get("/v1/state", params={"state": "moving"}).status_code == 422
        whole = c.get("/v1/state").json()
    assert dyn["tracks"] and all(t["state"] == "dynamic" for t in dyn["tracks"])
    assert [t["class"] for t in peds["tracks"]] == ["pedestrian"]
    assert set(dyn) == set(peds) == set(whole)  # a filter narrows the tracks, not the rest of the state
    assert dyn["calibration"] == whole["calibration"]


def test_a_method_a_path_does_not_serve_is_a_405_naming_those_it_does(stack: Stack) -> None:
    """``Allow`` lists every method of the path (FastAPI has one route per method, in included routers)."""
    with stack.http(auth=False) as c:
        for method, path, allow in (("DELETE", "/v1/config", "GET, HEAD, PATCH, PUT"),
                                    ("GET", "/v1/config/preset/paper", "POST"),
                                    ("POST", "/healthz", "GET, HEAD"),
                                    ("HEAD", "/v1/events", "GET"),  # a HEAD would hold a stream's place
                                    ("DELETE", f"/v1/state/{stack.tracks[0].track_id}", "GET, HEAD")):
            r = c.request(method, path)
            assert r.status_code == 405 and r.headers["allow"] == allow, (method, path, r.headers.get("allow"))


def test_one_track_and_404(stack: Stack) -> None:
    tid = stack.track("mover").track_id
    with stack.http(auth=False) as c:
        r = c.get(f"/v1/state/{tid}")
        assert r.status_code == 200
        t = TrackView.model_validate(r.json())
        assert t.id == tid and t.state == "dynamic" and t.speed > 5.0
        assert c.get(f"/v1/state/{tid.upper()}").json()["id"] == tid
        r = c.get(f"/v1/state/{'0' * 32}")
        assert r.status_code == 404 and "0" * 32 in r.json()["detail"]
        assert c.get("/v1/state/not-a-track").status_code == 422


def test_get_config_is_what_the_classifier_has(stack: Stack) -> None:
    with stack.http(auth=False) as c:
        assert c.get("/v1/config").json() == DEFAULTS
    assert stack.classifier.core.config == ClassifierConfig(**PAPER_STATISTIC)


def test_alpha_change_flips_the_borderline_track(stack: Stack) -> None:
    creeper = stack.track("creeper").track_id
    parked = stack.track("parked").track_id
    stack.wait_state(lambda b: _state_of(b, creeper) == "static", "creeper static at alpha 1.96")
    with stack.http() as c:
        r = c.patch("/v1/config", json={"alpha_default": 0.5})
        assert r.status_code == 200 and r.json() == {**DEFAULTS, "alpha_default": 0.5}
        # Applied before the reply: the classifier's own config already says so, and so does a fresh GET.
        assert stack.classifier.core.config.alpha_default == 0.5
        assert c.get("/v1/config").json()["alpha_default"] == 0.5
    body = stack.wait_state(lambda b: _state_of(b, creeper) == "dynamic", "creeper dynamic at alpha 0.5")
    assert _state_of(body, parked) == "static"  # real jitter stays below even the low threshold
    assert next(t for t in body["tracks"] if t["id"] == creeper)["alpha"] == 0.5
    with stack.http() as c:  # null resets to the default: the creeper goes back to static
        assert c.patch("/v1/config", json={"alpha_default": None}).json()["alpha_default"] == 1.96
    stack.wait_state(lambda b: _state_of(b, creeper) == "static", "creeper static again")


def test_per_class_alpha_flips_only_that_class(stack: Stack) -> None:
    creeper = stack.track("creeper").track_id
    with stack.http() as c:
        r = c.patch("/v1/config", json={"alpha_per_class": {"car": 0.5, "pedestrian": 1.0}})
        assert r.json()["alpha_per_class"] == {"car": 0.5, "pedestrian": 1.0}
    body = stack.wait_state(lambda b: _state_of(b, creeper) == "dynamic", "creeper dynamic at car alpha 0.5")
    bicycle = next(t for t in body["tracks"] if t["class"] == "bicycle")
    assert bicycle["alpha"] == 1.96  # no override for bicycles
    with stack.http() as c:
        r = c.patch("/v1/config", json={"alpha_per_class": {"car": None}})
        assert r.json()["alpha_per_class"] == {"pedestrian": 1.0}


def test_preset_and_put(stack: Stack) -> None:
    with stack.http() as c:
        assert c.patch("/v1/config", json={"window_size": 12, "min_window": 3}).status_code == 200
        r = c.post("/v1/config/preset/authors")
        assert r.status_code == 200
        cfg = r.json()
        assert cfg["alpha_per_class"] == AUTHORS_ALPHA and cfg["window_size"] == 12 and cfg["min_window"] == 3
        assert stack.classifier.core.config.alpha_per_class == AUTHORS_ALPHA
        assert c.get("/v1/config/presets").json()["authors"]["alpha_per_class"] == AUTHORS_ALPHA
        assert c.post("/v1/config/preset/bogus").status_code == 422
        full = {**DEFAULTS, "mode": "chi2", "effective_n": "independent", "variance_floor": 0.01,
                "velocity_threshold": 2.0}
        r = c.put("/v1/config", json=full)
        assert r.status_code == 200 and r.json() == full
        assert stack.classifier.core.config.mode == "chi2"
        body = stack.wait_state(lambda b: b["mode"] == "chi2", "chi2 mode in the state")
        assert all(t["statistic"] == t["chi2"] for t in body["tracks"])


def test_a_write_with_if_match_applies_only_to_the_version_it_names(stack: Stack) -> None:
    """GET /v1/config gives the version in force as its ETag; a write with If-Match applies only while that version
    is in force (412 naming the one that is, nothing applied), so two operators cannot undo each other unseen."""
    with stack.http() as c:
        got = c.get("/v1/config")
        tag = got.headers["etag"]
        assert re.fullmatch(r'"[0-9a-f]{16}"', tag)
        r = c.patch("/v1/config", json={"alpha_default": 2.2}, headers={"If-Match": tag})
        assert r.status_code == 200 and r.json()["alpha_default"] == 2.2
        new_tag = r.headers["etag"]
        assert new_tag != tag and c.get("/v1/config").headers["etag"] == new_tag
        for method, path, body in (("PATCH", "/v1/config", {"min_window": 3}),
                                   ("PUT", "/v1/config", {**DEFAULTS, "min_window": 3}),
                                   ("POST", "/v1/config/preset/authors", None)):
            stale = c.request(method, path, json=body, headers={"If-Match": tag})  # the version before the PATCH
            assert stale.status_code == 412, (method, stale.text)
            assert stale.headers["etag"] == new_tag and "nothing applied" in stale.json()["detail"]
        assert stack.classifier.core.config.min_window == ClassifierConfig(**PAPER_STATISTIC).min_window
        assert stack.classifier.core.config.alpha_per_class == ClassifierConfig(**PAPER_STATISTIC).alpha_per_class
        r = c.put("/v1/config", json={**DEFAULTS, "min_window": 3}, headers={"If-Match": new_tag.strip('"')})
        assert r.status_code == 200 and r.json()["min_window"] == 3  # a bare tag is taken too
        assert c.post("/v1/config/preset/authors", headers={"If-Match": "*"}).status_code == 200
        for bad in ('W/' + r.headers["etag"], f'{r.headers["etag"]}, "0123456789abcdef"', '"latest"'):
            refused = c.patch("/v1/config", json={"alpha_default": 1.0}, headers={"If-Match": bad})
            assert refused.status_code == 422 and refused.json()["detail"][0]["loc"] == ["header", "If-Match"]
        assert stack.classifier.core.config.alpha_default != 1.0


def test_a_patch_redoes_its_change_when_a_zenoh_writer_got_in_between(stack: Stack) -> None:
    """A PATCH is a read-modify-write: a write over Zenoh that lands between its read and its put had been
    overwritten without a word. The put is now conditional on what was read, so the PATCH is redone on the config
    the Zenoh writer left, and both changes stay. The Zenoh write is made from inside the change itself, so it
    lands in that window every time."""
    from jitterguard.services.sidecar.core import merge_patch

    zenoh_writer = zenoh.open(build_config(loopback_options(stack.ns, stack.zport)))
    client = ClassifierClient(loopback_options(stack.ns, stack.zport), api_token=stack.token)
    calls = []

    def change(current: ClassifierConfig) -> ClassifierConfig:
        calls.append(current.min_window)
        if len(calls) == 1:  # another writer changes min_window after this read
            key, payload = keys.classifier_config(stack.ns), encode(current.model_copy(update={"min_window": 3}))
            signed = write_attachment(stack.token, key, None, payload, time.time_ns(), os.urandom(NONCE_BYTES)) \
                if stack.token else None
            replies = list(zenoh_writer.get(key, timeout=5.0, payload=payload, attachment=signed))
            assert replies and replies[0].ok is not None
        return merge_patch(current, {"alpha_default": 2.2})

    try:
        wait_for(client.is_alive, "the classifier's liveliness token")
        reply = client.update_config(change)
    finally:
        client.close()
        zenoh_writer.close()
    assert len(calls) == 2 and calls[1] == 3  # redone once, on the config the other writer left
    assert reply.config.min_window == 3 and reply.config.alpha_default == 2.2
    assert stack.classifier.core.config == reply.config


def test_a_rogue_replier_learns_no_token_is_not_believed_and_cannot_replay_a_write(stack: Stack) -> None:
    """Any node may declare a queryable on ``jg/**`` and so receives every config write. The sidecar had sent its
    JG_API_TOKEN itself as the write's attachment, and took the first reply for the classifier's. Now a write is
    signed (the token never travels), the classifier signs its replies, the sidecar takes only a signed reply, and
    the classifier refuses a captured write sent again or altered."""
    fake = ClassifierConfig(alpha_default=9.9)
    forged = encode(ConfigReply(ok=True, config=fake, etag=config_etag(fake), error=None, conflict=False))
    seen: list[tuple[str, str, bytes | None, bytes | None]] = []

    def answer(query: zenoh.Query) -> None:
        with query:
            seen.append((str(query.key_expr), str(query.parameters),
                         query.payload.to_bytes() if query.payload is not None else None,
                         query.attachment.to_bytes() if query.attachment is not None else None))
            query.reply(query.key_expr, forged)

    rogue = zenoh.open(build_config(loopback_options(stack.ns, stack.zport)))
    rogue_q = rogue.declare_queryable("jg/**", answer, complete=True)
    key = keys.classifier_config(stack.ns)
    try:
        with stack.http() as c:
            assert c.get("/v1/config").json() == DEFAULTS  # the forged config (alpha 9.9) was not taken
            r = c.patch("/v1/config", json={"alpha_default": 0.3})
            assert r.status_code == 200 and r.json()["alpha_default"] == 0.3, r.text
            writes = [w for w in seen if w[0] == key and w[2]]
            assert writes, "the rogue queryable received no write: the test shows nothing"
            assert all(stack.token.encode() not in (a or b"") for *_, a in seen)  # type: ignore[union-attr]
            assert c.patch("/v1/config", json={"alpha_default": 0.4}).status_code == 200
            _, params, payload, attachment = writes[-1]  # the write of 0.3, captured
            selector = f"{key}?{params}" if params else key
            again = list(rogue.get(selector, payload=payload, attachment=attachment, timeout=5.0))
            errs = [x.err.payload.to_bytes() for x in again if x.err is not None]
            assert any(b"replay" in e for e in errs), errs
            altered = encode(ClassifierConfig(**{**PAPER_STATISTIC, "alpha_default": 0.5}))
            assert len(altered) == len(payload)  # type: ignore[arg-type]
            again = list(rogue.get(key, payload=altered, attachment=attachment, timeout=5.0))
            errs = [x.err.payload.to_bytes() for x in again if x.err is not None]
            assert any(b"signature does not match" in e for e in errs), errs
            assert stack.classifier.core.config.alpha_default == 0.4  # neither the replay nor the alteration landed
    finally:
        rogue_q.undeclare()
        rogue.close()
        with stack.http() as c:
            assert c.put("/v1/config", json=DEFAULTS).status_code == 200


@contextmanager
def _rogue_classifier(stack: Stack, ns: str, key: str, answer: Callable[[zenoh.Query], None],
                      api_token: str | None = None) -> Iterator[ClassifierClient]:
    """A node alone in namespace ``ns`` that announces itself as the classifier (its liveliness token) and answers
    queries on ``key`` with ``answer`` (a complete queryable where ``key`` is a wildcard), and a sidecar's client
    of that namespace that has seen the token; all closed after."""
    rogue = zenoh.open(build_config(loopback_options(ns, stack.zport)))
    alive = rogue.liveliness().declare_token(keys.alive(ns, "classifier"))
    rogue_q = rogue.declare_queryable(key, answer, complete="*" in key)
    client = ClassifierClient(loopback_options(ns, stack.zport), api_token=api_token)
    try:
        wait_for(client.is_alive, "the rogue's liveliness token")
        yield client
    finally:
        client.close()
        rogue_q.undeclare()
        alive.undeclare()
        rogue.close()


def test_a_rogue_alone_on_the_bus_is_not_taken_for_the_classifier(stack: Stack) -> None:
    """In a namespace where only a rogue announces itself as the classifier and answers every query, a client
    holding the token believes none of its replies (each counted), and the rogue learns no token."""
    ns = "sc-rogue"
    fake = ClassifierConfig(alpha_default=9.9)
    forged = encode(ConfigReply(ok=True, config=fake, etag=config_etag(fake), error=None, conflict=False))
    attachments: list[bytes | None] = []

    def answer(query: zenoh.Query) -> None:
        with query:
            attachments.append(query.attachment.to_bytes() if query.attachment is not None else None)
            query.reply(query.key_expr, forged)

    with _rogue_classifier(stack, ns, "jg/**", answer, api_token=stack.token) as client:
        with pytest.raises(ClassifierRejected, match="or another node answers on this key"):
            client.get_config()
        with pytest.raises(ClassifierRejected, match="or another node answers on this key"):
            client.put_config(ClassifierConfig(**{**PAPER_STATISTIC, "alpha_default": 0.5}))
        assert client.poll_once() is None  # its state is no state
        assert client.counters.snapshot()["rejected.classifier/config"] == 2
        assert client.counters.snapshot()["rejected.classifier/state"] >= 1  # (its own poll may have asked too)
    assert len(attachments) >= 3 and all(stack.token.encode() not in (a or b"") for a in attachments)  # type: ignore[union-attr]


def test_a_config_reply_is_read_only_within_its_bound(stack: Stack) -> None:
    """Without a token the first reply is taken, whoever sent it; it is now refused unread past a few hundred KB
    (a config reply is a few hundred bytes) rather than decoded whole."""
    ns = "sc-bigreply"
    huge = msgpack.packb({"ok": True, "error": "x" * (1 << 20)})

    def answer(query: zenoh.Query) -> None:
        with query:
            query.reply(query.key_expr, huge)

    with _rogue_classifier(stack, ns, keys.classifier_config(ns), answer) as client:
        with pytest.raises(ClassifierRejected, match=r"invalid: ConfigReply: 1048592 bytes exceed 262144"):
            client.get_config()
        assert client.counters.snapshot()["rejected.classifier/config"] == 1


def test_a_state_reply_is_read_only_within_its_bound(stack: Stack) -> None:
    """Without a token the sidecar takes the first state reply, whoever sent it, and had decoded it whole, 20 times
    a second: a list longer than any frame holds is now refused before it is built (counted
    ``rejected.classifier/state``), and no state is served from it."""
    ns = "sc-bigstate"
    huge = msgpack.packb({"schema_version": 1, "tracks": [0] * ((1 << 18) + 1)})

    def answer(query: zenoh.Query) -> None:
        with query:
            query.reply(query.key_expr, huge)

    with _rogue_classifier(stack, ns, keys.classifier_state(ns), answer) as client:
        assert client.poll_once() is None
        assert client.counters.snapshot()["rejected.classifier/state"] >= 1


def test_a_sidecar_with_another_token_believes_no_reply_and_applies_nothing(stack: Stack) -> None:
    client = ClassifierClient(loopback_options(stack.ns, stack.zport), api_token="not-the-token")
    try:
        wait_for(client.is_alive, "the classifier's liveliness token")
        with pytest.raises(ClassifierRejected, match="JG_API_TOKEN differs from the sidecar's"):
            client.get_config()
        with pytest.raises(ClassifierRejected, match="signature does not match"):
            client.put_config(ClassifierConfig(**{**PAPER_STATISTIC, "alpha_default": 0.5}))
    finally:
        client.close()
    assert stack.classifier.core.config == ClassifierConfig(**PAPER_STATISTIC)


def test_a_sidecar_with_another_token_answers_state_reads_502_naming_the_token(stack: Stack) -> None:
    """docs/http-api.md: a sidecar whose token differs from the classifier's answers 502 to reads as well as writes.
    ``GET /v1/state`` had answered 503 "no state from the classifier yet" for ever, while every poll was refused as
    unsigned: the operator was sent to wait for a classifier that was there all along."""
    server = Uvicorn(create_app(SidecarSettings(zenoh=loopback_options(stack.ns, stack.zport),
                                                api_token="not-the-token")))
    try:
        with httpx.Client(base_url=server.url, timeout=10.0) as c:
            r = wait_for(lambda: (lambda r: r if r.status_code != 503 else None)(c.get("/v1/state")),
                         "the sidecar's first state poll to be refused")
            assert r.status_code == 502 and "JG_API_TOKEN differs from the sidecar's" in r.json()["detail"], r.text
            track = c.get(f"/v1/state/{stack.track('parked').track_id}")
            assert track.status_code == 502 and "JG_API_TOKEN" in track.json()["detail"], track.text
            # not ready (once the classifier's first heartbeat is in): it answers, but to no token of this sidecar's
            ready = wait_for(lambda: (lambda r: r if "no heartbeat yet" not in r.text else None)(c.get("/readyz")),
                             "the classifier's first heartbeat at the sidecar")
            assert ready.status_code == 503 and "state cannot be read" in ready.json()["reason"], ready.text
            assert "JG_API_TOKEN differs from the sidecar's" in ready.json()["reason"]
    finally:
        server.close()
    with stack.http() as c:  # the stack's own sidecar, with the classifier's token, serves the state
        assert c.get("/v1/state").status_code == 200


def test_a_classifier_that_goes_silent_on_the_bus_has_its_counts_left_out_of_metrics(stack: Stack) -> None:
    """A classifier stopped (SIGSTOP) keeps its liveliness token for seconds, until the router drops it; it sends no
    heartbeat. ``/metrics`` said ``jitterguard_classifier_up 0`` beside its last frame and track counts, exported
    as current. Its heartbeats are cut off here at its publisher (a stopped process cannot be had in this one); the
    counts leave ``/metrics`` with ``up``, and come back with its heartbeats."""
    publisher = stack.classifier._hb_pub

    class Silent:
        def put(self, _payload: bytes) -> None:
            pass

        def undeclare(self) -> None:
            publisher.undeclare()

    with stack.http(auth=False) as c:
        assert "jitterguard_classifier_frames_total " in c.get("/metrics").text
        stack.classifier._hb_pub = Silent()
        try:
            scraped = wait_for(lambda: (lambda t: t if "jitterguard_classifier_up 0.0" in t else None)(
                c.get("/metrics").text), "the classifier's heartbeat to go stale")
            assert "jitterguard_classifier_frames_total " not in scraped
            assert "jitterguard_classifier_tracks " not in scraped and "jitterguard_classifier_last_seq " not in scraped
        finally:
            stack.classifier._hb_pub = publisher
        wait_for(lambda: "jitterguard_classifier_frames_total " in c.get("/metrics").text,
                 "the counts back with the heartbeats")


def test_a_sidecar_whose_polls_come_to_be_refused_stops_serving_the_state_it_read_before() -> None:
    """A classifier restarted with another ``JG_API_TOKEN`` refuses every later poll of a sidecar that had read its
    state: ``GET /v1/state`` had gone on answering 200 with that old state, only ``X-State-Age-Ms`` growing. It now
    answers 502 naming the token, as a sidecar that never read a state does, and 200 again once polls are answered;
    ``/metrics`` likewise leaves out the track gauges it can no longer read (they had stayed at their last values)
    while ``jitterguard_classifier_up`` stays 1: the classifier itself is there. (The sidecar's key is swapped here
    instead of the classifier's: the classifier sees the same mismatch.)"""
    stack = start_stack("sc-rotated", token="first-token", window_ready=False)
    try:
        client = stack.server.server.config.app.state.sidecar.client
        with stack.http() as c:
            assert c.get("/v1/state").status_code == 200
            assert "jitterguard_classifier_tracks " in c.get("/metrics").text
            client._api_token = "rotated-token"
            r = wait_for(lambda: (lambda r: r if r.status_code != 200 else None)(c.get("/v1/state")),
                         "the refused polls to end the old state's service")
            assert r.status_code == 502 and "JG_API_TOKEN differs from the sidecar's" in r.json()["detail"], r.text
            assert c.get(f"/v1/state/{stack.track('parked').track_id}").status_code == 502
            scraped = c.get("/metrics").text
            assert "jitterguard_classifier_up 1.0" in scraped
            assert "jitterguard_classifier_tracks " not in scraped and "jitterguard_classifier_tracks_by_state" not in scraped
            client._api_token = "first-token"
            wait_for(lambda: c.get("/v1/state").status_code == 200, "the state served again once polls are answered")
            assert "jitterguard_classifier_tracks " in c.get("/metrics").text
    finally:
        stack.close()


@pytest.mark.parametrize(("method", "path"), [
    ("PATCH", "/v1/config"), ("PUT", "/v1/config"), ("POST", "/v1/config/preset/authors")])
@pytest.mark.parametrize("auth", [None, "Bearer wrong-token", "Basic czNjcmV0LXRva2Vu", "Bearer s3cret-token-and-more"])
def test_writes_need_the_token(stack: Stack, method: str, path: str, auth: str | None) -> None:
    headers = {"Authorization": auth} if auth is not None else {}
    body = None if method == "POST" else {"alpha_default": 0.3}
    with stack.http(auth=False) as c:
        r = c.request(method, path, json=body, headers=headers)
        assert r.status_code == 401, r.text
        assert r.headers["www-authenticate"] == "Bearer"
        assert "token" in r.json()["detail"]
        assert c.get("/v1/config").json() == DEFAULTS  # nothing applied
        assert c.get("/v1/state").status_code == 200  # reads stay open


def test_a_write_without_the_token_is_refused_before_its_body_is_read(stack: Stack) -> None:
    """60 KB announced, none of it sent, a wrong token: the 401 comes from the headers alone. The guard had read (and
    FastAPI parsed) every write's body, up to 64 KB, before the route refused it; here it had waited for the body."""
    port = int(stack.url.rsplit(":", 1)[1])
    reply = stack.raw(f"PATCH /v1/config HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Type: application/json\r\n"
                      f"Authorization: Bearer wrong\r\nContent-Length: 60000\r\n\r\n".encode())
    assert reply.startswith("HTTP/1.1 401"), reply
    assert "www-authenticate: Bearer" in reply.lower().replace("bearer", "Bearer"), reply
    with stack.http(auth=False) as c:
        assert 'jitterguard_sidecar_refused_requests_total{status="401"}' in c.get("/metrics").text


@pytest.mark.parametrize(("method", "body", "field"), [
    ("PATCH", {"alpha_default": -1}, "alpha_default"),
    ("PATCH", {"alpha_default": "NaN"}, "alpha_default"),
    ("PATCH", {"window_size": 1}, "window_size"),
    ("PATCH", {"min_window": 50}, "min_window"),
    ("PATCH", {"mode": "t_test"}, "mode"),
    ("PATCH", {"alpha_per_class": {"spaceship": 2.0}}, "alpha_per_class"),
    ("PATCH", {"alpha_per_class": {"car": 0}}, "alpha_per_class"),
    ("PATCH", {"effective_n": 3}, "effective_n"),
    ("PATCH", {"velocity_threshold": 1e9}, "velocity_threshold"),
    ("PATCH", {"bogus": 1}, "bogus"),
    ("PATCH", {"window_size": 65}, "window_size"),  # W × W state per window: bounded
    ("PATCH", {"velocity_threshold_per_class": {"spaceship": 1.0}}, "velocity_threshold_per_class"),
    ("PATCH", {"calibration": "file"}, "calibration_file"),  # none given
    # a file only the classifier can look for (on its host): its refusal comes back as a 422 on the field
    ("PATCH", {"calibration": "file", "calibration_file": "/nonexistent/calibration.yaml"}, "calibration_file"),
    # a path no file system can hold (schemathesis found it: a NUL byte, a lone surrogate): the same 422
    ("PATCH", {"calibration": "file", "calibration_file": "cal\u0000\udbf1.yaml"}, "calibration_file"),
    # a key that is no Unicode text: named by its escape (pydantic had named only "body")
    ("PATCH", {"\ud800": 1}, "\\ud800"),
    ("PUT", {"alpha_default": 2.0, "\udbff": 1}, "\\udbff"),
    ("PATCH", {"alpha_per_class": {"\ud800": 2.0}}, "alpha_per_class"),
    ("PUT", {"window_size": 4, "min_window": 5}, "min_window"),
    ("PUT", {"variance_floor": 0}, "variance_floor"),
])
def test_invalid_values_get_422_naming_the_field(stack: Stack, method: str, body: dict, field: str) -> None:
    with stack.http() as c:
        # ASCII-escaped JSON, as a client that sends a lone surrogate must write it
        r = c.request(method, "/v1/config", content=json.dumps(body), headers={"Content-Type": "application/json"})
        assert r.status_code == 422, r.text
        locs = [e["loc"] for e in r.json()["detail"]]
        assert any(loc[:2] == ["body", field] for loc in locs), locs
        assert c.get("/v1/config").json() == DEFAULTS  # nothing applied


def test_malformed_json_is_422(stack: Stack) -> None:
    with stack.http() as c:
        r = c.patch("/v1/config", content=b"{not json", headers={"Content-Type": "application/json"})
        assert r.status_code == 422
        r = c.patch("/v1/config", content=b'{"alpha_default": NaN}', headers={"Content-Type": "application/json"})
        assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "alpha_default"]
        r = c.patch("/v1/config", content=b'{"alpha_default": 0.7}',
                    headers={"Content-Type": "application/merge-patch+json"})
        assert r.status_code == 200 and r.json()["alpha_default"] == 0.7


@pytest.mark.parametrize(("body", "loc"), [
    (b'{"window_size": ' + b"9" * 5000 + b"}", ["body", "window_size"]),  # Python reads no int of > 4300 digits
    (b'{"alpha_default": -' + b"9" * 400 + b"}", ["body", "alpha_default"]),  # beyond any float
    (b'{"alpha_per_class": {"car": ' + b"1" * 5000 + b"}}", ["body", "alpha_per_class", "car"]),
    (b'{"calibration_range_bands_m": [20, ' + b"4" * 5000 + b"]}", ["body", "calibration_range_bands_m", 1]),
    (b'{"window_size": 12, "window_size": 40}', ["body", "window_size"]),  # which one counts is anyone's guess
    (b'{"alpha_per_class": {"car": 1.0, "car": 50.0}}', ["body", "alpha_per_class", "car"]),
], ids=["int-5000-digits", "int-beyond-float", "int-in-map", "int-in-list", "repeated-key", "repeated-key-in-map"])
def test_numbers_and_keys_json_leaves_ambiguous_get_422_naming_the_field(stack: Stack, body: bytes,
                                                                          loc: list) -> None:
    """A 5000-digit integer in a config field was a 400 "There was an error parsing the body" naming nothing
    (Python's JSON parser raises past 4300 digits); a key given twice was silently the last one. Both are a 422
    naming the field now, for PUT and PATCH, and nothing is applied."""
    with stack.http() as c:
        for method in ("PATCH", "PUT"):
            r = c.request(method, "/v1/config", content=body, headers={"Content-Type": "application/json"})
            assert r.status_code == 422, (method, r.status_code, r.text)
            assert [e["loc"] for e in r.json()["detail"]] == [loc], r.text
        assert c.get("/v1/config").json() == DEFAULTS  # nothing applied
        big = c.patch("/v1/config", content=b'{"calibration_half_life_s": 1' + b"0" * 6 + b"}",
                      headers={"Content-Type": "application/json"})
        assert big.status_code == 200 and big.json()["calibration_half_life_s"] == 1e6  # long enough is still read


def test_bodies_that_are_no_readable_json_text_get_a_400_saying_why(stack: Stack) -> None:
    """Text that is not UTF-8 and JSON nested past what the parser recurses into were a 400 "There was an error
    parsing the body"; the 400 now says which (the body is under the 64 KB cap either way)."""
    with stack.http() as c:
        r = c.patch("/v1/config", content=b'{"calibration_file": "\xe9t\xe9"}',
                    headers={"Content-Type": "application/json"})
        assert r.status_code == 400 and "not UTF-8" in r.json()["detail"], r.text
        for codec in ("utf-16", "utf-32"):  # Python's parser guesses these; RFC 8259 asks for UTF-8 between systems
            r = c.patch("/v1/config", content='{"alpha_default": 2.5}'.encode(codec),
                        headers={"Content-Type": "application/json"})
            assert r.status_code == 400 and "not UTF-8" in r.json()["detail"], (codec, r.text)
        r = c.patch("/v1/config", content=b"[" * 30000 + b"]" * 30000, headers={"Content-Type": "application/json"})
        assert r.status_code == 400 and "nested too deeply" in r.json()["detail"], r.text
        assert c.get("/v1/config").json() == DEFAULTS


def _metric(text: str, name: str, labels: str = "") -> float:
    m = re.search(rf"^{re.escape(name)}{re.escape(labels)} (\S+)$", text, re.M)
    assert m, f"{name}{labels} not in /metrics"
    return float(m.group(1))


def test_a_config_the_classifier_model_refuses_counts_invalid_by_put_as_by_patch(stack: Stack) -> None:
    """``jitterguard_sidecar_config_writes_total{result="invalid"}`` counts a config refused as merged: a PATCH's
    was counted, the same config PUT was not (it was validated before the write was counted)."""
    def invalid(c: httpx.Client) -> float:
        text = c.get("/metrics").text
        return _metric(text, "jitterguard_sidecar_config_writes_total", '{result="invalid"}') \
            if 'result="invalid"' in text else 0.0

    with stack.http() as c:
        before = invalid(c)
        for method in ("PATCH", "PUT"):
            r = c.request(method, "/v1/config", json={**PAPER_STATISTIC, "window_size": 4, "min_window": 5})
            assert r.status_code == 422 and r.json()["detail"][0]["loc"][0] == "body", (method, r.text)
        assert invalid(c) == before + 2
        assert c.get("/v1/config").json() == DEFAULTS  # nothing applied


def test_metrics(stack: Stack) -> None:
    def same_frame() -> tuple[str, dict] | None:  # /metrics and /v1/state from one snapshot
        with stack.http(auth=False) as c:
            state = c.get("/v1/state").json()
            text = c.get("/metrics").text
        return (text, state) if _metric(text, "jitterguard_classifier_last_seq") == state["seq"] else None
    text, state = wait_for(same_frame, "metrics and state of the same frame")
    assert _metric(text, "jitterguard_classifier_up") == 1.0
    assert _metric(text, "jitterguard_classifier_frames_total") > 10
    assert _metric(text, "jitterguard_classifier_tracks") == len(stack.tracks)
    for cls, st in (("car", "static"), ("car", "dynamic"), ("pedestrian", "static"), ("bus", "dynamic")):
        n = sum(1 for t in state["tracks"] if t["class"] == cls and t["state"] == st)
        assert _metric(text, "jitterguard_classifier_tracks_by_state", f'{{class="{cls}",state="{st}"}}') == n
    assert _metric(text, "jitterguard_classifier_alpha", '{class="car"}') == 1.96
    assert _metric(text, "jitterguard_sidecar_state_poll_seconds_count") > 0
    # the last frame's counts go down as well as up: gauges, not counters (rate() would read resets)
    statics = sum(1 for t in state["tracks"] if t["state"] == "static")
    assert _metric(text, "jitterguard_classifier_current", '{name="now.static"}') == statics
    assert "# TYPE jitterguard_classifier_current gauge" in text
    assert 'jitterguard_classifier_counter_total{name="now.' not in text
    assert _metric(text, "jitterguard_classifier_counter_total", '{name="objects.static"}') >= statics
    before = _metric(text, "jitterguard_classifier_rejected_messages_total")
    # A malformed payload on the tracker's key: the classifier drops and counts it; /metrics shows it.
    stack.feeder.session.put(keys.track(stack.ns, "f" * 32), b"\x93not-msgpack-of-a-TrackObservation")

    def rejected() -> float | None:
        with stack.http(auth=False) as c:
            v = _metric(c.get("/metrics").text, "jitterguard_classifier_rejected_messages_total")
        return v if v > before else None
    assert wait_for(rejected, "the reject to show in /metrics") >= before + 1


def test_frame_latency_histogram_when_the_classifier_exports_it(stack: Stack) -> None:
    """The histogram appears as soon as the classifier's counters carry frame_latency_ms.* (see core)."""
    with stack.http(auth=False) as c:
        text = c.get("/metrics").text
    exported = any(k.startswith("frame_latency_ms.") for k in stack.classifier.counters.snapshot())
    has_hist = "jitterguard_classifier_frame_latency_seconds_bucket" in text
    assert has_hist == exported
    if has_hist:
        assert _metric(text, "jitterguard_classifier_frame_latency_seconds_count") > 0


def test_events_stream_state_and_config_changes(stack: Stack) -> None:
    creeper = stack.track("creeper").track_id
    stack.wait_state(lambda b: _state_of(b, creeper) == "static", "creeper static")
    seen: dict[str, list[dict]] = {}
    with httpx.Client(base_url=stack.url, timeout=20.0) as c, c.stream("GET", "/v1/events") as r:
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/event-stream")
        lines = r.iter_lines()
        event = None
        patched = False
        for line in lines:
            if line.startswith("event: "):
                event = line[7:]
            elif line.startswith("data: "):
                seen.setdefault(event or "", []).append(json.loads(line[6:]))
                if event == "hello" and not patched:
                    assert seen["hello"][0]["ready"] is True
                    with stack.http() as w:
                        assert w.patch("/v1/config", json={"alpha_default": 0.5}).status_code == 200
                    patched = True
                flips = [ch for d in seen.get("changes", []) for ch in d["changes"] if ch["id"] == creeper]
                if flips and "config" in seen:
                    break
    assert seen["config"][0]["alpha_default"] == 0.5
    assert flips[0]["from"] == "static" and flips[0]["to"] == "dynamic" and flips[0]["threshold"] == 0.5
    assert flips[0]["statistic"] > 0.5


def test_openapi_documents_every_endpoint(stack: Stack) -> None:
    with stack.http(auth=False) as c:
        spec = c.get("/openapi.json").json()
    paths = spec["paths"]
    for path, methods in {"/healthz": {"get"}, "/readyz": {"get"}, "/v1/state": {"get"},
                          "/v1/state/{track_id}": {"get"}, "/v1/config": {"get", "put", "patch"},
                          "/v1/config/preset/{name}": {"post"}, "/metrics": {"get"}, "/v1/events": {"get"},
                          "/": {"get"}}.items():
        assert methods <= set(paths[path]), path
    assert "401" in paths["/v1/config"]["patch"]["responses"] and "503" in paths["/v1/config"]["put"]["responses"]
    assert paths["/v1/config"]["patch"]["security"]  # the bearer scheme is declared for writes
    assert "security" not in paths["/v1/state"]["get"]


def test_page_is_self_contained(stack: Stack) -> None:
    with stack.http(auth=False) as c:
        r = c.get("/")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    assert "default-src 'self'" in r.headers["content-security-policy"]
    assert not re.search(r"""(src|href)=["']?(https?:)?//""", r.text)  # nothing from the internet
    assert "<canvas" in r.text
    with stack.http(auth=False) as c:  # no CDN-backed doc viewers either
        assert c.get("/docs").status_code == 404 and c.get("/redoc").status_code == 404


def test_cors_is_off_by_default(stack: Stack) -> None:
    with stack.http(auth=False) as c:
        r = c.options("/v1/config", headers={"Origin": "https://evil.example",
                                             "Access-Control-Request-Method": "PATCH"})
        assert "access-control-allow-origin" not in r.headers
        r = c.get("/v1/state", headers={"Origin": "https://evil.example"})
        assert "access-control-allow-origin" not in r.headers


def test_cors_only_for_configured_origins() -> None:
    """``--cors-origin`` turns CORS on for exactly those origins (no classifier needed for a preflight)."""
    from jitterguard.runtime import free_tcp_port, loopback_options
    from jitterguard.services.sidecar.app import SidecarSettings, create_app

    from .stack import Uvicorn

    app = create_app(SidecarSettings(zenoh=loopback_options("sc-cors", free_tcp_port(), listen_self=True),
                                     cors_origins=("https://ops.example",)))
    server = Uvicorn(app)
    try:
        with httpx.Client(base_url=server.url, timeout=10) as c:
            pre = {"Access-Control-Request-Method": "PATCH", "Access-Control-Request-Headers": "authorization"}
            r = c.options("/v1/config", headers={"Origin": "https://ops.example", **pre})
            assert r.status_code == 200 and r.headers["access-control-allow-origin"] == "https://ops.example"
            r = c.options("/v1/config", headers={"Origin": "https://evil.example", **pre})
            assert r.headers.get("access-control-allow-origin") != "https://evil.example"
            r = c.get("/readyz")  # no classifier in this namespace: not ready, and says why
            assert r.status_code == 503 and "liveliness" in r.json()["reason"]
    finally:
        server.close()


def test_state_and_metrics_show_the_variance_calibration(stack: Stack) -> None:
    """The calibration the classifier decides with: in /v1/state (validated by the view model), as gauges in
    /metrics, and live after a config write switches it on."""
    with stack.http() as c:
        assert c.patch("/v1/config", json={"calibration": "online", "effective_n": "measured"}).status_code == 200
    body = stack.wait_state(lambda b: (b.get("calibration") or {}).get("mode") == "online", "calibration online")
    view = StateView.model_validate(body)
    assert view.calibration is not None and view.calibration.effective_n == "measured"
    vehicle = view.calibration.groups["vehicle"]
    # m may be learned as 0 (a noiseless creeper's along-track residuals are not serially correlated)
    assert set(vehicle.along.scale) == {"0-20", "20-40", "40-inf"} and 0 <= vehicle.along.correlation <= 1
    assert vehicle.along.correlation_time_s > 0
    # how well the scales are known: at least the cold start's 2 degrees of freedom, more with every block
    assert view.calibration.scale_dof is not None and view.calibration.scale_dof >= 2.0
    with stack.http(auth=False) as c:
        text = c.get("/metrics").text
    scale = _metric(text, "jitterguard_classifier_variance_scale",
                    '{age="established",axis="along",band="0-20",group="vehicle"}')
    assert scale is not None and scale > 0
    assert _metric(text, "jitterguard_classifier_variance_factor", '{axis="across",group="pedestrian"}') > 0
    assert _metric(text, "jitterguard_classifier_calibration_scale_dof", "") >= 2.0
