"""The tracker service over real in-process Zenoh sessions (peer mode, loopback, multicast off, free ports)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

import pytest
import zenoh

from jitterguard.geometry import quaternion_from_yaw
from jitterguard.runtime import build_config, free_tcp_port, loopback_options
from jitterguard.schemas import decode, encode, keys
from jitterguard.schemas.models import (
    DetectedObjects,
    Header,
    MotionState,
    Pose,
    Quaternion,
    TrackedObjects,
    TrackObservation,
)
from jitterguard.services.tracker.config import default_config
from jitterguard.services.tracker.service import TrackerService
from helpers import to_message
from jitterguard.bench.tracker_sequences import make_sequence

pytestmark = pytest.mark.integration


def wait_for(pred, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.01)
    return pred()


@dataclass
class Harness:
    """A tracker service plus a plain client session that plays detector and consumer."""

    ns: str
    service: TrackerService
    client: zenoh.Session
    samples: list[tuple[str, bytes]] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)
    next_seq: int = 0
    stamp0: int = 1_700_000_000_000_000_000

    def on_sample(self, s: zenoh.Sample) -> None:
        with self.lock:
            self.samples.append((str(s.key_expr), s.payload.to_bytes()))

    def tracked(self) -> list[TrackedObjects]:
        with self.lock:
            return [decode(TrackedObjects, b) for k, b in self.samples if k == keys.tracked(self.ns)]

    def put(self, payload: bytes) -> None:
        self.client.put(keys.detections(self.ns), payload, congestion_control=zenoh.CongestionControl.BLOCK)

    def send(self, msg: DetectedObjects) -> None:
        self.put(encode(msg))

    def empty_frame(self, seq: int, stamp: int) -> DetectedObjects:
        return DetectedObjects(header=Header(stamp=stamp, frame_id="lidar", seq=seq))

    def sync(self) -> None:
        """Send empty frames until the tracker answers one: the routes both ways are up."""
        def answered() -> bool:
            self.send(self.empty_frame(self.next_seq, self.stamp0 + self.next_seq))
            self.next_seq += 1
            return wait_for(lambda: len(self.tracked()) > 0, timeout=0.3)
        assert wait_for(answered, timeout=15.0), "tracker never answered"

    def wait_seq(self, seq: int, timeout: float = 10.0) -> TrackedObjects:
        assert wait_for(lambda: any(t.header.seq == seq for t in self.tracked()), timeout), f"no tracked seq {seq}"
        return next(t for t in self.tracked() if t.header.seq == seq)


@pytest.fixture
def harness_factory() -> Iterator:
    made: list[Harness] = []

    def make(ns: str, **kw) -> Harness:
        port = free_tcp_port()
        svc = TrackerService(loopback_options(ns, port, listen_self=True), **kw)
        client = zenoh.open(build_config(loopback_options(ns, port)))
        h = Harness(ns=ns, service=svc, client=client)
        client.declare_subscriber(f"jg/{ns}/**", h.on_sample)
        made.append(h)
        h.sync()
        return h

    yield make
    for h in made:
        h.client.close()
        h.service.close()


def _shifted(msg: DetectedObjects, seq: int, stamp: int) -> DetectedObjects:
    return msg.model_copy(update={"header": Header(stamp=stamp, frame_id="lidar", seq=seq)})


def test_each_frame_publishes_its_observations_then_the_closing_tracked(harness_factory) -> None:
    h = harness_factory("trk_frames")
    seq = make_sequence(8, n_frames=25)
    base = h.next_seq + 10
    for k, sf in enumerate(seq.frames):
        h.send(_shifted(to_message(sf), base + k, h.stamp0 + 10**9 + k * 100_000_000))
    last = h.wait_seq(base + len(seq.frames) - 1)
    assert len(last.objects) >= 10

    with h.lock:
        samples = list(h.samples)
    # walk the stream in arrival order: every tracks/{id} of a frame precedes that frame's tracked
    pending: dict[int, set[str]] = {}
    checked = 0
    for key, data in samples:
        if key.startswith(f"jg/{h.ns}/tracks/"):
            obs = decode(TrackObservation, data)
            tid = keys.last_chunk(key)
            assert obs.track.object_id == tid and obs.header.frame_id == "map"
            pending.setdefault(obs.header.seq, set()).add(tid)
        elif key == keys.tracked(h.ns):
            t = decode(TrackedObjects, data)
            assert pending.pop(t.header.seq, set()) == set(t.observed_track_ids)
            assert set(t.observed_track_ids) <= {o.object_id for o in t.objects}
            checked += len(t.observed_track_ids)
    assert not pending and checked > 100
    assert h.service.counters.get("frames") >= len(seq.frames)
    assert h.service.counters.get("tracks_born") > 0


def test_malformed_payloads_are_rejected_and_counted_and_tracking_goes_on(harness_factory) -> None:
    h = harness_factory("trk_reject")
    before = h.service.counters.get("rejected")
    h.put(b"\x00\x01garbage")
    h.put(encode(TrackedObjects(header=Header(stamp=h.stamp0 + 4, seq=h.next_seq + 1))))  # valid msgpack, wrong schema
    h.put(encode(h.empty_frame(h.next_seq + 1, h.stamp0 + 5))[:-3])  # truncated
    h.put(b"\x81\xa2\xca\xca\x01")  # a map key that is not UTF-8
    assert wait_for(lambda: h.service.counters.get("rejected") >= before + 4)
    assert h.service.counters.get("rejected.detections") >= 4
    seq = h.next_seq + 2
    h.send(h.empty_frame(seq, h.stamp0 + 10**9))
    h.wait_seq(seq)
    assert h.service.counters.get("handler_errors") == 0


def test_duplicate_and_out_of_order_frames_are_dropped_and_counted(harness_factory) -> None:
    h = harness_factory("trk_order")
    s = h.next_seq + 5
    h.send(h.empty_frame(s, h.stamp0 + 10**9))
    h.wait_seq(s)
    h.send(h.empty_frame(s, h.stamp0 + 10**9))  # duplicate
    h.send(h.empty_frame(s - 2, h.stamp0 + 10**9 - 1))  # older
    h.send(h.empty_frame(s + 1, h.stamp0 + 10**9 + 10**8))
    h.wait_seq(s + 1)
    assert h.service.counters.get("dropped_duplicate") == 1
    assert h.service.counters.get("dropped_out_of_order") == 1
    assert [t.header.seq for t in h.tracked()].count(s) == 1
    assert all(t.header.seq != s - 2 for t in h.tracked())


def test_static_hints_zero_the_velocity_of_the_hinted_track(harness_factory) -> None:
    h = harness_factory("trk_hints", static_hints=True, config=default_config(confirm_hits=2))
    q = quaternion_from_yaw(0.0)
    first = h.next_seq + 1
    seq = make_sequence(2, n_frames=12, miss_rate=0.0, fp_rate=0.0, ego_speed=0.0, ego_yaw_rate=0.0,
                        objects=None)
    for k, sf in enumerate(seq.frames):
        msg = to_message(sf)
        msg = msg.model_copy(update={"ego_pose": Pose(orientation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))})
        h.send(_shifted(msg, first + k, h.stamp0 + 10**9 + k * 100_000_000))
    t = h.wait_seq(first + len(seq.frames) - 1)
    moving = max(t.objects, key=lambda o: abs(o.kinematics.twist_with_covariance.twist.linear.x))
    tid = moving.object_id
    assert abs(moving.kinematics.twist_with_covariance.twist.linear.x) > 1.0
    pos = moving.kinematics.pose_with_covariance.pose.position
    hint = MotionState(header=Header(stamp=1, seq=t.header.seq), track_id=tid, state="static", mode="z_test",
                       threshold=1.96, alpha=1.96, window_length=10, mean_x=pos.x, mean_y=pos.y)
    h.client.put(keys.motion(h.ns, tid), encode(hint))
    h.client.put(keys.motion(h.ns, "e" * 32), encode(hint.model_copy(update={"track_id": "e" * 32})))
    assert wait_for(lambda: h.service.counters.get("static_hints_received") == 2)
    nxt = first + len(seq.frames)
    h.send(h.empty_frame(nxt, h.stamp0 + 10**9 + len(seq.frames) * 100_000_000))  # the object is unseen: coast
    after = next(o for o in h.wait_seq(nxt).objects if o.object_id == tid)
    tw = after.kinematics.twist_with_covariance.twist.linear
    assert abs(tw.x) < 1e-6 and abs(tw.y) < 1e-6
    p = after.kinematics.pose_with_covariance.pose.position
    assert (p.x, p.y) == pytest.approx((pos.x, pos.y), abs=1e-6)  # zero velocity: the prediction stays put
    assert h.service.counters.get("static_hints_applied") == 1
    assert h.service.counters.get("static_hints_unknown") == 1
    # a hint whose mean lies beyond the limits is refused and counted; the track keeps where it is
    far = hint.model_copy(update={"mean_x": 1e300})
    h.client.put(keys.motion(h.ns, tid), encode(far))
    assert wait_for(lambda: h.service.counters.get("rejected.motion/*") == 1)
    assert h.service.counters.get("over_limit.motion/*") == 1 and h.service.counters.get("static_hints_received") == 2
    h.send(h.empty_frame(nxt + 1, h.stamp0 + 10**9 + (len(seq.frames) + 1) * 100_000_000))
    kept = next(o for o in h.wait_seq(nxt + 1).objects if o.object_id == tid)
    p = kept.kinematics.pose_with_covariance.pose.position
    assert (p.x, p.y) == pytest.approx((pos.x, pos.y), abs=1e-6)
    # a hint 500 m off, and one about this track on another track's key: neither moves it
    h.client.put(keys.motion(h.ns, tid), encode(hint.model_copy(update={"mean_x": pos.x + 500.0})))
    h.client.put(keys.motion(h.ns, "e" * 32), encode(hint.model_copy(update={"mean_x": pos.x + 3.0})))
    assert wait_for(lambda: h.service.counters.get("rejected.motion/*") == 2)
    h.send(h.empty_frame(nxt + 2, h.stamp0 + 10**9 + (len(seq.frames) + 2) * 100_000_000))
    kept = next(o for o in h.wait_seq(nxt + 2).objects if o.object_id == tid)
    p = kept.kinematics.pose_with_covariance.pose.position
    assert (p.x, p.y) == pytest.approx((pos.x, pos.y), abs=1e-6)
    assert h.service.counters.get("static_hints_implausible") == 1
    # a newer dynamic decision cancels an older static one that has not been applied yet (a tracker behind by a
    # frame had applied the stale static hint); here the dynamic one arrives first, the older static one after
    newer = t.header.seq + 20
    h.client.put(keys.motion(h.ns, tid), encode(hint.model_copy(update={
        "state": "dynamic", "header": Header(stamp=2, seq=newer), "mean_x": pos.x + 0.5})))
    h.client.put(keys.motion(h.ns, tid), encode(hint.model_copy(update={
        "header": Header(stamp=1, seq=newer - 1), "mean_x": pos.x + 0.5})))
    assert wait_for(lambda: h.service.counters.get("static_hints_received") == 4)  # the 500 m one above was the 3rd
    h.send(h.empty_frame(nxt + 3, h.stamp0 + 10**9 + (len(seq.frames) + 3) * 100_000_000))
    kept = next(o for o in h.wait_seq(nxt + 3).objects if o.object_id == tid)
    p = kept.kinematics.pose_with_covariance.pose.position
    assert (p.x, p.y) == pytest.approx((pos.x, pos.y), abs=1e-6)  # not moved to the stale static mean
    assert h.service.counters.get("static_hints_applied") == 1


def test_the_measurement_scale_it_learns_is_in_the_heartbeat(harness_factory) -> None:
    """With ``measurement_scale: online`` the heartbeat carries what the tracker has learnt of the detector's
    variances (and the shipped default, off, carries none)."""
    from jitterguard.schemas.models import Heartbeat

    h = harness_factory("trk_scale", config=default_config().model_copy(update={"measurement_scale": "online"}))
    off = harness_factory("trk_scale_off")
    assert off.service.gauges() == {}
    seq = make_sequence(9, n_frames=40)
    base = h.next_seq + 10
    for k, sf in enumerate(seq.frames):
        h.send(_shifted(to_message(sf), base + k, h.stamp0 + 10**9 + k * 100_000_000))
    h.wait_seq(base + len(seq.frames) - 1)
    gauges = h.service.gauges()
    assert gauges["measurement_scale.effective_blocks"] > 0  # 40 frames: tracks' detections turned over
    assert gauges["measurement_scale.vehicle.along.0-20"] > 0

    def beat() -> Heartbeat | None:
        with h.lock:
            for key, data in reversed(h.samples):
                if key == keys.heartbeat(h.ns, "tracker"):
                    hb = decode(Heartbeat, data)
                    if hb.gauges.get("measurement_scale.effective_blocks", 0) > 0:
                        return hb
        return None

    assert wait_for(lambda: beat() is not None, 5.0)


def test_detections_below_the_confirmation_existence_are_counted_and_a_zero_existence_detector_is_warned_of(
        harness_factory, caplog) -> None:
    """A detector that leaves ``existence_probability`` at 0 never gets a track published (confirmation needs a
    running existence of ``confirm_min_existence``), and nothing had said why: the tracker's decisions stay as they
    are, but its heartbeat counts the detections below that gate and its log says once what a zero means."""
    import logging

    h = harness_factory("trk_existence")
    seq = make_sequence(8, n_frames=12)
    base = h.next_seq + 10
    sent = 0
    with caplog.at_level(logging.WARNING):
        for k, sf in enumerate(seq.frames):
            msg = to_message(sf)
            msg = msg.model_copy(update={"objects": [o.model_copy(update={"existence_probability": 0.0})
                                                     for o in msg.objects]})
            sent += len(msg.objects)
            h.send(_shifted(msg, base + k, h.stamp0 + 10**9 + k * 100_000_000))
        last = h.wait_seq(base + len(seq.frames) - 1)
    assert last.objects == []  # unchanged decisions: no track confirms on existence 0
    assert h.service.counters.get("detections_below_min_existence") == sent > 0
    warned = [r for r in caplog.records if "existence_probability" in r.getMessage()]
    assert len(warned) == 1, [r.getMessage() for r in warned]  # once a run, not once a frame
    assert "confirm_min_existence" in warned[0].getMessage()
