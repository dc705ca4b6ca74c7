"""One real run of the whole pipeline, shared by the integration tests of the bridges out of jitterguard.

In-process services on one loopback Zenoh mesh (peer mode, scouting off, a free port): the synthetic replay at
points level (ray-cast HDL-32E scans with ground truth), the lite detector, the tracker, the classifier, the Foxglove
bridge (WebSocket server on a free port *and* an MCAP recording) and the ROS 2 bag recorder. Beside them, as
independent observers: a plain Zenoh session keeping every ``objects``, ``detections`` and ``points`` message the
pipeline published (the reference), and a WebSocket client speaking the Foxglove protocol (``websockets``; it offers
both names of the protocol, ``foxglove.sdk.v1`` — what foxglove-sdk and foxglove_bridge 3 speak — and the
older ``foxglove.websocket.v1``, the same protocol) subscribed to the tracks channel.
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import zenoh

pytest.importorskip("foxglove")
pytest.importorskip("rosbags")

from jitterguard.runtime import build_config, free_tcp_port, loopback_options  # noqa: E402
from jitterguard.schemas import decode, keys  # noqa: E402
from jitterguard.schemas.models import DetectedObjects, PointCloud, TrackedObjects  # noqa: E402

NS = "fox_it"
SCENARIO = "synthetic:parking-street"
DURATION_S = 3.0
FOXGLOVE_SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]


@dataclass
class WsCapture:
    """What the WebSocket client saw: advertised channels and (arrival monotonic s, log time ns, payload) per
    message on the channel it subscribed to."""

    channels: dict[str, dict[str, Any]] = field(default_factory=dict)
    messages: list[tuple[float, int, bytes]] = field(default_factory=list)
    server_info: dict[str, Any] | None = None
    subprotocol: str | None = None
    error: str | None = None


@dataclass
class Run:
    mcap: Path
    bag: Path
    objects: dict[int, TrackedObjects]  # by header stamp
    detections: dict[int, DetectedObjects]
    points: dict[int, PointCloud]
    first_objects_at: float | None
    ws: WsCapture
    foxglove_counters: dict[str, int]
    recorder_counters: dict[str, int]
    tmp: Path


def _ws_client(port: int, topic: str, capture: WsCapture, stop: threading.Event, ready: threading.Event) -> None:
    from websockets.sync.client import connect

    try:
        with connect(f"ws://127.0.0.1:{port}", subprotocols=FOXGLOVE_SUBPROTOCOLS, open_timeout=10) as ws:
            capture.subprotocol = ws.subprotocol
            subscribed = False
            while not stop.is_set():
                try:
                    data = ws.recv(timeout=0.05)
                except TimeoutError:
                    continue
                now = time.monotonic()
                if isinstance(data, str):
                    msg = json.loads(data)
                    if msg.get("op") == "serverInfo":
                        capture.server_info = msg
                    elif msg.get("op") == "advertise":
                        for ch in msg["channels"]:
                            capture.channels[ch["topic"]] = ch
                        if not subscribed and topic in capture.channels:
                            ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                                {"id": 7, "channelId": capture.channels[topic]["id"]}]}))
                            subscribed = True
                            ready.set()
                elif data[0] == 0x01 and int.from_bytes(data[1:5], "little") == 7:  # message data, our subscription
                    capture.messages.append((now, int.from_bytes(data[5:13], "little"), bytes(data[13:])))
    except Exception as exc:  # noqa: BLE001 - reported by the test that reads the capture
        if not stop.is_set():  # a server closing at the end of the run, after the client was told to stop, is no error
            capture.error = f"{type(exc).__name__}: {exc}"
        ready.set()


@pytest.fixture(scope="package")
def pipeline_run(tmp_path_factory: pytest.TempPathFactory) -> Run:
    from jitterguard.services.classifier.service import ClassifierService
    from jitterguard.services.detector.inference import Detector
    from jitterguard.services.detector.service import DetectorService
    from jitterguard.services.foxglove.scene import TRACKS
    from jitterguard.services.foxglove.service import FoxgloveService, FoxgloveSink
    from jitterguard.services.recorder.rosbag import Rosbag2Sink
    from jitterguard.services.recorder.service import RecorderService
    from jitterguard.services.replay.service import ReplayService
    from jitterguard.services.replay.runner import ReplayPlan
    from jitterguard.services.replay.sources import SourceOptions, open_source
    from jitterguard.services.tracker.service import TrackerService

    tmp = tmp_path_factory.mktemp("pipeline_run")
    port = free_tcp_port()
    opts = lambda: loopback_options(NS, port)  # noqa: E731
    services: list[Any] = []
    ref: dict[str, dict[int, Any]] = {"objects": {}, "detections": {}, "points": {}}
    first: list[float] = []
    lock = threading.Lock()
    stop, ready = threading.Event(), threading.Event()
    capture = WsCapture()
    client = ws_thread = None
    try:
        services.append(TrackerService(loopback_options(NS, port, listen_self=True)))
        services.append(ClassifierService(opts()))
        services.append(DetectorService(opts(), Detector.load(None, "lite", threads=2)))
        sink = FoxgloveSink(port=0, mcap_path=tmp / "run.mcap")
        fox = FoxgloveService(opts(), sink)
        services.append(fox)
        rec = RecorderService(opts(), Rosbag2Sink(tmp / "bag"))
        services.append(rec)

        client = zenoh.open(build_config(opts()))

        def keep(kind: str, model: type) -> Any:
            def cb(s: zenoh.Sample) -> None:
                msg = decode(model, s.payload.to_bytes())
                with lock:
                    if kind == "objects" and not first:
                        first.append(time.monotonic())
                    ref[kind][msg.header.stamp] = msg
            return cb

        subs = [client.declare_subscriber(keys.objects(NS), keep("objects", TrackedObjects)),
                client.declare_subscriber(keys.detections(NS), keep("detections", DetectedObjects)),
                client.declare_subscriber(keys.points(NS), keep("points", PointCloud))]
        ws_thread = threading.Thread(target=_ws_client, args=(sink.port, TRACKS, capture, stop, ready), daemon=True)
        ws_thread.start()
        assert ready.wait(15), "the WebSocket client never got the tracks channel advertised"

        replay = ReplayService(opts(), "points")
        services.append(replay)
        assert replay.wait_for_subscribers(10)
        time.sleep(0.5)  # let every session's routes settle (the detector's slot takes the first scans)
        def paced(_frame: Any, seq: int) -> None:
            """Lock-step with the detector: the next scan goes out once this one's detections (same header seq) are
            back, or after 3 s, so a loaded machine sees the whole run instead of the detector's latest-scan slot
            skipping most of it. The scans keep their own stamps; only wall time stretches."""
            deadline = time.monotonic() + 3.0
            while time.monotonic() < deadline:
                with lock:
                    if any(d.header.seq >= seq for d in ref["detections"].values()):
                        return
                time.sleep(0.005)

        with open_source(SCENARIO, SourceOptions(duration_s=DURATION_S)) as src:
            replay.replay(src, ReplayPlan(rate=1.0), on_published=paced)
        # the last frames drain through detector, tracker, classifier and both bridges
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline:
            with lock:
                n_obj = len(ref["objects"])
            if n_obj and fox.counters.get("frames") >= n_obj and rec.counters.get("frames") >= n_obj:
                break
            time.sleep(0.1)
        time.sleep(0.5)
    finally:
        stop.set()
        if ws_thread is not None:  # the client leaves before the server closes under it
            ws_thread.join(timeout=5)
        for s in reversed(services):
            s.close()
        if client is not None:
            client.close()
    return Run(mcap=tmp / "run.mcap", bag=tmp / "bag", objects=ref["objects"], detections=ref["detections"],
               points=ref["points"], first_objects_at=first[0] if first else None, ws=capture,
               foxglove_counters=fox.counters.snapshot(), recorder_counters=rec.counters.snapshot(), tmp=tmp)
