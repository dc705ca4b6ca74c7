"""A real stack for the sidecar tests: classifier + deterministic track feed + the sidecar under uvicorn.

Everything is real and on loopback: the classifier is a :class:`ClassifierService` with its own Zenoh peer
session listening on a free port (multicast scouting off), the feeder and the sidecar connect to it, and the
sidecar runs in a real ``uvicorn.Server`` on a free loopback port, driven over HTTP with httpx.

The scenario is built so that the tests' expectations follow from the statistics, not from luck:

- parked cars (tiny seeded jitter): z ≈ 0.1 ± 0.1 → static at any alpha ≥ 0.5;
- movers on a 15 m circle at 6 m/s: z > 10 → dynamic;
- one noise-free *creeper* (a car at 0.4 m/s on a 4 m circle): with window 10 at 20 Hz — every second frame, the
  classifier keeping the window's 1 s span of 10 Hz — cluster mode and a reported σ = 0.1 m, its halves' means
  differ by 0.2 m, so max(z_x, z_y) ∈ [1.0, 1.42] — static at the default alpha 1.96, dynamic at alpha 0.5. That
  is the borderline track an alpha change flips.

These z values are the paper's statistic, so the stack's classifier runs with ``PAPER_STATISTIC`` (variances
as reported, clusters, H0 v = 0, α 1.96 for every class, window 10); the calibrated default has its own tests.
"""

from __future__ import annotations

import math
import socket
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import httpx
import numpy as np
import pytest
import uvicorn
import zenoh

from jitterguard.runtime import free_tcp_port, loopback_options
from jitterguard.runtime.zenoh_config import build_config
from jitterguard.schemas import encode, keys
from jitterguard.schemas.models import (
    ClassifierConfig,
    X_X,
    Y_Y,
    DetectedObject,
    DetectedObjectKinematics,
    Header,
    ObjectClassification,
    Point,
    Pose,
    PoseWithCovariance,
    Quaternion,
    Shape,
    TrackedObject,
    TrackedObjectKinematics,
    TrackedObjects,
    TrackObservation,
    TrackState,
    Twist,
    TwistWithCovariance,
    Vector3,
)
from jitterguard.services.classifier.config import PRESETS
from jitterguard.services.classifier.config_writes import ConfigWritePolicy
from jitterguard.services.classifier.service import ClassifierService
from jitterguard.services.sidecar.app import SidecarSettings, create_app

RATE_HZ = 20.0
SIGMA_REPORTED = 0.1  # m, what every detection says its 1-sigma position error is
STAMP0 = 1_700_000_000_000_000_000


def _tid(i: int) -> str:
    return uuid.UUID(int=(0xA5A5 << 112) | i).hex


@dataclass(frozen=True)
class Track:
    """A scripted object: ``pos(seq) -> (x, y, yaw, vx, vy)``."""

    track_id: str
    label: int
    kind: str  # parked | mover | creeper
    pos: Callable[[int], tuple[float, float, float, float, float]]
    jitter: float = 0.0
    length: float = 4.5
    width: float = 1.9


def _circle(cx: float, cy: float, r: float, speed: float, phase: float) -> Callable[[int], tuple]:
    w = speed / r

    def pos(seq: int) -> tuple[float, float, float, float, float]:
        a = phase + w * seq / RATE_HZ
        x, y = cx + r * math.cos(a), cy + r * math.sin(a)
        yaw = math.remainder(a + math.pi / 2, 2 * math.pi)  # wrapped: past 4π the wire refuses a track's yaw
        return x, y, yaw, speed * math.cos(yaw), speed * math.sin(yaw)

    return pos


def _parked(x: float, y: float, yaw: float) -> Callable[[int], tuple]:
    return lambda seq: (x, y, yaw, 0.0, 0.0)


def scenario() -> list[Track]:
    """The fixed cast: 6 parked (4 cars, a truck, a pedestrian), 3 movers, 1 creeper; all inside
    the world window (-40, -25)..(40, 25)."""
    # Parked objects stay clear of the movers' circle (radius 15 around the origin) so no two boxes overlap.
    parked = [(-30.0, 19.0, 0.0, 1), (-18.0, 19.0, 0.0, 1), (-6.0, 19.0, 0.0, 1), (8.0, -19.0, math.pi, 1),
              (22.0, -19.0, math.pi, 2), (30.0, 14.0, 0.0, 7)]
    tracks = [Track(_tid(i), label, "parked", _parked(x, y, yaw), jitter=0.02,
                    length=10.0 if label == 2 else (0.8 if label == 7 else 4.5),
                    width=2.5 if label == 2 else (0.8 if label == 7 else 1.9))
              for i, (x, y, yaw, label) in enumerate(parked)]
    movers = [(0.0, 0.0, 15.0, 6.0, 0.0, 1), (0.0, 0.0, 15.0, 6.0, 2.1, 1), (0.0, 0.0, 15.0, 6.0, 4.2, 6)]
    for j, (cx, cy, r, v, ph, label) in enumerate(movers):
        tracks.append(Track(_tid(100 + j), label, "mover", _circle(cx, cy, r, v, ph), jitter=0.02,
                            length=1.8 if label == 6 else 4.5, width=0.7 if label == 6 else 1.9))
    tracks.append(Track(_tid(200), 1, "creeper", _circle(-28.0, -14.0, 4.0, 0.4, 0.0)))
    return tracks


def _cov(var: float) -> tuple[float, ...]:
    c = [0.0] * 36
    c[X_X] = c[Y_Y] = var
    c[14] = c[35] = 0.01
    return tuple(c)


def build_frame(tracks: list[Track], seq: int, rng: np.random.Generator) -> tuple[list[bytes], list[str], bytes]:
    """One frame on the wire: encoded observations (with their keys) and the closing ``tracked``."""
    header = Header(stamp=STAMP0 + int(seq * 1e9 / RATE_HZ), frame_id="map", seq=seq)
    obs, obs_keys, objects = [], [], []
    var = SIGMA_REPORTED**2
    for t in tracks:
        x, y, yaw, vx, vy = t.pos(seq)
        if t.jitter:
            x += float(rng.normal(0.0, t.jitter))
            y += float(rng.normal(0.0, t.jitter))
        q = Quaternion(z=math.sin(yaw / 2), w=math.cos(yaw / 2))
        cls = [ObjectClassification(label=t.label, probability=0.9)]
        shape = Shape(dimensions=Vector3(x=t.length, y=t.width, z=1.6))
        pose = PoseWithCovariance(pose=Pose(position=Point(x=x, y=y, z=0.8), orientation=q), covariance=_cov(var))
        det = DetectedObject(classification=cls, shape=shape,
                             kinematics=DetectedObjectKinematics(pose_with_covariance=pose, has_position_covariance=True))
        state = TrackState(object_id=t.track_id, label=t.label, x=x, y=y, yaw=yaw, vx=vx, vy=vy, hits=seq + 1,
                           age_s=seq / RATE_HZ)
        obs.append(encode(TrackObservation(header=header, detection=det, track=state)))
        obs_keys.append(t.track_id)
        objects.append(TrackedObject(
            object_id=t.track_id, classification=cls, shape=shape,
            kinematics=TrackedObjectKinematics(pose_with_covariance=pose, twist_with_covariance=TwistWithCovariance(
                twist=Twist(linear=Vector3(x=vx, y=vy)), covariance=_cov(0.25)))))
    tracked = TrackedObjects(header=header, objects=objects, observed_track_ids=[t.track_id for t in tracks])
    return obs, obs_keys, encode(tracked)


class Feeder:
    """Publishes the scenario like the tracker would, at ``RATE_HZ``, on its own thread and session."""

    def __init__(self, ns: str, zport: int, tracks: list[Track], seed: int = 7) -> None:
        self.ns = ns
        self.tracks = tracks
        self.rng = np.random.default_rng(seed)
        self.session = zenoh.open(build_config(loopback_options(ns, zport)))
        self.seq = 0
        self._stop = threading.Event()
        self._paused = threading.Event()
        self._thread = threading.Thread(target=self._run, name="test-feeder", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        period = 1.0 / RATE_HZ
        while not self._stop.wait(period):
            if self._paused.is_set():
                continue
            self.publish_frame()

    def publish_frame(self) -> None:
        obs, ids, tracked = build_frame(self.tracks, self.seq, self.rng)
        for tid, payload in zip(ids, obs):
            self.session.put(keys.track(self.ns, tid), payload, congestion_control=zenoh.CongestionControl.BLOCK)
        self.session.put(keys.tracked(self.ns), tracked, congestion_control=zenoh.CongestionControl.BLOCK)
        self.seq += 1

    def pause(self) -> None:
        self._paused.set()

    def resume(self) -> None:
        self._paused.clear()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.session.close()


class Uvicorn:
    """A real uvicorn server for ``app`` on a free loopback port, in a thread."""

    def __init__(self, app: Any) -> None:
        self.port = free_tcp_port()
        self.server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=self.port, log_level="warning",
                                                    timeout_graceful_shutdown=1, lifespan="on"))
        self.thread = threading.Thread(target=self.server.run, name="test-uvicorn", daemon=True)
        self.thread.start()
        wait_for(lambda: self.server.started or not self.thread.is_alive(), "uvicorn to start")
        assert self.server.started, "uvicorn did not start"
        self.url = f"http://127.0.0.1:{self.port}"

    def close(self) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=10)


def wait_for(cond: Callable[[], Any], what: str, timeout: float = 20.0, period: float = 0.05) -> Any:
    """Poll ``cond`` until it returns something truthy (and return it); fail the test after ``timeout``.

    A bounded wait for an event, not a timing assertion: the deadline is generous and only stops a hang.
    """
    deadline = time.monotonic() + timeout
    while True:
        value = cond()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(period)


@dataclass
class Stack:
    ns: str
    zport: int
    classifier: ClassifierService
    feeder: Feeder
    server: Uvicorn
    token: str | None
    tracks: list[Track] = field(default_factory=scenario)
    closed: bool = False

    @property
    def url(self) -> str:
        return self.server.url

    def http(self, auth: bool = True) -> httpx.Client:
        headers = {"Authorization": f"Bearer {self.token}"} if (auth and self.token) else {}
        return httpx.Client(base_url=self.url, headers=headers, timeout=10.0)

    def raw(self, request: bytes) -> str:
        """One request as raw bytes on a fresh connection, for what an HTTP client will not send (headers given
        twice, a body shorter than announced); the whole reply, read until the server closes the connection."""
        with socket.create_connection(("127.0.0.1", self.server.port), timeout=10) as sock:
            sock.sendall(request)
            reply = b""
            while chunk := sock.recv(4096):
                reply += chunk
            return reply.decode(errors="replace")

    def track(self, kind: str) -> Track:
        return next(t for t in self.tracks if t.kind == kind)

    def wait_state(self, cond: Callable[[dict], Any], what: str, timeout: float = 20.0) -> dict:
        """Poll ``GET /v1/state`` until ``cond(body)`` holds; returns that body."""
        with self.http() as c:
            def probe() -> dict | None:
                r = c.get("/v1/state")
                if r.status_code != 200:
                    return None
                body = r.json()
                return body if cond(body) else None
            return wait_for(probe, what, timeout)

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self.server.close()
        self.feeder.close()
        self.classifier.close()


PAPER_STATISTIC: dict[str, Any] = dict(PRESETS["paper"])
"""The config fields the scenario's expected z values are computed for (the shipped ``paper`` preset: variances
as reported, clusters, H0 v = 0, α 1.96, a window of 10; the rest stays default)."""


def start_stack(ns: str, token: str | None = None, *, window_ready: bool = True) -> Stack:
    """Classifier listening on a free port; feeder and sidecar connect to it; wait until state flows."""
    zport = free_tcp_port()
    writes = ConfigWritePolicy(token=token) if token else ConfigWritePolicy.open()
    classifier = ClassifierService(loopback_options(ns, zport, listen_self=True),
                                   ClassifierConfig(**PAPER_STATISTIC), config_writes=writes)
    tracks = scenario()
    feeder = Feeder(ns, zport, tracks)
    app = create_app(SidecarSettings(zenoh=loopback_options(ns, zport), api_token=token))
    server = Uvicorn(app)
    stack = Stack(ns, zport, classifier, feeder, server, token, tracks)
    with stack.http() as c:
        wait_for(lambda: c.get("/readyz").status_code == 200, "the sidecar to see the classifier ready")
    if window_ready:  # every track present and past its first full window
        stack.wait_state(lambda b: b["counts"]["total"] == len(tracks) and
                         all(t["window_length"] == t["window_size"] for t in b["tracks"]), "a full window")
    return stack
