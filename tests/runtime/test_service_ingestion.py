"""What the classifier, the tracker, the detector and a bridge do with hostile input on the keys they subscribe to:
real in-process services on real Zenoh (peer mode, loopback, multicast scouting off, free ports) and a second
session that publishes what a broken or malicious node would. The work and memory one message or a flood may cause
stay bounded (what is refused is counted per key), and the service goes on with its real input afterwards."""

from __future__ import annotations

import logging
import random
import time

import msgpack
import pytest
import zenoh

from helpers import wait_until
from jitterguard.runtime import loopback_options
from jitterguard.schemas import decode, encode, keys
from jitterguard.schemas.models import (
    ClassifierConfig,
    ConfigReply,
    DetectedObject,
    DetectedObjects,
    Header,
    MotionState,
    ObjectClassification,
    TrackObservation,
    TrackState,
)
from jitterguard.schemas.wire import MAX_CONFIG_BYTES, Limits
from jitterguard.services.bridge.service import BridgeService
from jitterguard.services.classifier.config_writes import ConfigWritePolicy
from jitterguard.services.classifier.service import ClassifierService
from jitterguard.services.classifier.synthetic_tracks import TrackScenario, generate
from jitterguard.services.detector.inference import Detector
from jitterguard.services.detector.service import DetectorService
from jitterguard.services.tracker.config import default_config
from jitterguard.services.tracker.service import MOTION_MAX_BYTES, TrackerService

pytestmark = pytest.mark.integration
NS = "ingest"
BLOCK = zenoh.CongestionControl.BLOCK


def _ids(n: int, seed: int) -> list[str]:
    rng = random.Random(seed)
    return ["%032x" % rng.getrandbits(128) for _ in range(n)]


def test_made_up_track_ids_under_a_far_seq_do_not_grow_the_classifier(zenoh_port, client_session) -> None:
    """Observations wait per frame until the frame's ``tracked`` closes it; frames were bounded in number (64) but
    not in size, so ``tracks/{id}`` observations with ever new IDs under a seq no close comes for grew the
    classifier's memory without end (~0.5 kB each: 60 000 of them took 20 MB on a live stack). A frame now keeps at
    most ``limits.max_objects`` observations; the rest are counted ``frames.excess_observations``, and the
    classifier decides its real frames as before."""
    svc = ClassifierService(loopback_options(NS, zenoh_port, listen_self=True), straggler_timeout_s=0.5,
                            limits=Limits(max_objects=20), config_writes=ConfigWritePolicy.open())
    try:
        objects: list[bytes] = []
        client_session.declare_subscriber(keys.objects(NS), lambda s: objects.append(s.payload.to_bytes()))
        assert wait_until(lambda: any(True for _ in client_session.liveliness().get(
            keys.alive(NS, "classifier"), timeout=0.5)), 10)
        det = DetectedObject(classification=[ObjectClassification()])
        far = 10**12
        for tid in _ids(100, seed=3):
            obs = TrackObservation(header=Header(stamp=far, seq=far), detection=det,
                                   track=TrackState(object_id=tid, x=1.0, y=2.0))
            client_session.put(keys.track(NS, tid), encode(obs), congestion_control=BLOCK)
        assert wait_until(lambda: svc.counters.get("frames.excess_observations") == 80, timeout=20), \
            svc.counters.snapshot()
        assert svc.counters.get("rejected") == 0  # valid payloads: bounded, not refused
        for frame in generate(TrackScenario(n_static=3, n_moving=2, n_starting=0, seed=1), 3):
            n = len(objects)
            for o in frame.observations:
                client_session.put(keys.track(NS, o.track.object_id), encode(o), congestion_control=BLOCK)
            client_session.put(keys.tracked(NS), encode(frame.tracked), congestion_control=BLOCK)
            assert wait_until(lambda: len(objects) == n + 1, timeout=30)
        assert svc.counters.get("frames.missing_observations") == 0
    finally:
        svc.close()


def _hint(tid: str, seq: int = 1, frame_id: str = "map") -> bytes:
    return encode(MotionState(header=Header(stamp=1, seq=seq, frame_id=frame_id), track_id=tid, state="static",
                              mode="z_test", threshold=1.96, alpha=1.96, window_length=10))


def test_static_hints_for_made_up_tracks_stay_bounded_and_oversized_ones_are_refused(zenoh_port,
                                                                                     client_session) -> None:
    """With ``--static-hints`` the tracker keeps each track's newest ``motion/{id}`` decision until its next frame;
    with no frame coming, made-up track IDs grew that map for ever. It now holds at most twice ``max_objects``
    tracks (the rest counted ``static_hints_dropped``), and a ``motion/{id}`` payload over MOTION_MAX_BYTES is
    refused unread (a frame id of 70 kB had been decoded and kept). The next frame takes what was kept."""
    svc = TrackerService(loopback_options(NS, zenoh_port, listen_self=True), static_hints=True,
                         config=default_config(limits=Limits(max_objects=10)))
    try:
        tracked: list[bytes] = []
        client_session.declare_subscriber(keys.tracked(NS), lambda s: tracked.append(s.payload.to_bytes()))
        stamp0 = 1_700_000_000_000_000_000

        def frame(seq: int) -> bytes:
            return encode(DetectedObjects(header=Header(stamp=stamp0 + seq * 100_000_000, frame_id="lidar", seq=seq)))

        def answered() -> bool:  # the routes both ways are up
            client_session.put(keys.detections(NS), frame(len(tracked)), congestion_control=BLOCK)
            return wait_until(lambda: len(tracked) > 0, timeout=0.3)
        assert wait_until(answered, timeout=15)
        ids = _ids(50, seed=5)
        for tid in ids:
            client_session.put(keys.motion(NS, tid), _hint(tid), congestion_control=BLOCK)
        big = _hint(ids[0], seq=2, frame_id="x" * (MOTION_MAX_BYTES + 1))
        client_session.put(keys.motion(NS, ids[0]), big, congestion_control=BLOCK)
        assert wait_until(lambda: svc.counters.get("static_hints_received") == 50 and svc.counters.get(
            "static_hints_dropped") == 30 and svc.counters.get("rejected.motion/*") == 1, timeout=20), \
            svc.counters.snapshot()
        assert svc.counters.get("static_hints_dropped") == 30
        assert svc.counters.get("over_limit.motion/*") == 1
        n = len(tracked)
        client_session.put(keys.detections(NS), frame(n + 5), congestion_control=BLOCK)
        assert wait_until(lambda: len(tracked) > n, timeout=20)
        assert svc.counters.get("static_hints_unknown") == 20  # the kept ones, taken by the frame (no such tracks)
        for tid in ids[:5]:  # room again after the frame
            client_session.put(keys.motion(NS, tid), _hint(tid, seq=3), congestion_control=BLOCK)
        assert wait_until(lambda: svc.counters.get("static_hints_received") == 55, timeout=20)
        assert svc.counters.get("static_hints_dropped") == 30
    finally:
        svc.close()


class _Sink:
    def __init__(self) -> None:
        self.frames: list = []

    def write(self, frame) -> None:
        self.frames.append(frame)

    def close(self) -> None:
        pass


def test_a_bridge_refuses_lists_and_maps_no_message_has_before_building_them(zenoh_port, client_session) -> None:
    """A bridge (Foxglove, recorders) reads every message with its pydantic model, and nothing bounded that reading
    but the payload's size: a 1 MB ``detections`` of a million empty objects took minutes of its callback thread
    and gigabytes. Lists beyond the wire limits and maps beyond any model's fields are refused from their headers
    now (counted ``over_limit.<key>``); the same key's real messages still go through."""
    sink = _Sink()
    svc = BridgeService(loopback_options(NS, zenoh_port, listen_self=True), sink, points=False)
    try:
        header = {"stamp": 1_700_000_000_000_000_000, "frame_id": "lidar", "seq": 1}
        many_objects = msgpack.packb({"schema_version": 1, "header": header, "objects": [{}] * 5000})
        wide_object = msgpack.packb({"schema_version": 1, "header": header,
                                     "objects": [{f"k{i}": 0 for i in range(5000)}]})

        def settled() -> bool:  # the routes are up once a valid message comes through
            client_session.put(keys.detections(NS), encode(DetectedObjects(header=Header(**header))),
                               congestion_control=BLOCK)
            return wait_until(lambda: svc.counters.get("received") > 0, timeout=0.3)
        assert wait_until(settled, timeout=15)
        for payload in (many_objects, wide_object):
            client_session.put(keys.detections(NS), payload, congestion_control=BLOCK)
        assert wait_until(lambda: svc.counters.get("over_limit.detections") == 2, timeout=20), svc.counters.snapshot()
        assert svc.counters.get("rejected.detections") == 2
    finally:
        svc.close()


def _padded(header: dict, pad: int) -> bytes:
    """A payload with ``header`` and a ``pad`` bytes long field: beyond any limit, whatever the header says."""
    return msgpack.packb({"schema_version": 1, "header": header, "pad": b"\0" * pad})


def test_the_tracker_refuses_a_payload_over_its_limit_before_queueing_it(zenoh_port, client_session) -> None:
    """``detections`` payloads were copied into the tracker's inbox (64 of them, of any size Zenoh carries: up to
    1 GiB) and only the worker looked at their size — after their header: an oversized one that claimed the last
    frame's header was dropped as a duplicate, never counted as over the limit. It is refused from its size on
    arrival now (``over_limit.detections``), before it is copied or queued."""
    svc = TrackerService(loopback_options(NS, zenoh_port, listen_self=True),
                         config=default_config(limits=Limits(max_payload_bytes=64 * 1024)))
    try:
        tracked: list[bytes] = []
        client_session.declare_subscriber(keys.tracked(NS), lambda s: tracked.append(s.payload.to_bytes()))
        header = {"stamp": 1_700_000_000_000_000_000, "frame_id": "lidar", "seq": 0}

        def answered() -> bool:  # the routes both ways are up
            header["seq"] += 1
            header["stamp"] += 100_000_000
            client_session.put(keys.detections(NS), encode(DetectedObjects(header=Header(**header))),
                               congestion_control=BLOCK)
            return wait_until(lambda: len(tracked) > 0, timeout=0.3)
        assert wait_until(answered, timeout=15)
        assert wait_until(lambda: svc.last_seq == header["seq"], timeout=10)
        client_session.put(keys.detections(NS), _padded(header, 200_000), congestion_control=BLOCK)
        assert wait_until(lambda: svc.counters.get("over_limit.detections") == 1, timeout=20), svc.counters.snapshot()
        assert svc.counters.get("dropped_duplicate") == 0 and svc.counters.get("rejected.detections") == 1
    finally:
        svc.close()


def test_the_classifier_refuses_a_close_over_its_limit_before_queueing_it(zenoh_port, client_session) -> None:
    """The same for the classifier's ``tracked``: its queue of closes held 64 payloads of any size, judged by their
    header before their size (an oversized repeat of the last frame's header was counted a duplicate frame)."""
    svc = ClassifierService(loopback_options(NS, zenoh_port, listen_self=True), straggler_timeout_s=0.5,
                            limits=Limits(max_payload_bytes=64 * 1024), config_writes=ConfigWritePolicy.open())
    try:
        objects: list[bytes] = []
        client_session.declare_subscriber(keys.objects(NS), lambda s: objects.append(s.payload.to_bytes()))
        assert wait_until(lambda: any(True for _ in client_session.liveliness().get(
            keys.alive(NS, "classifier"), timeout=0.5)), 10)
        (frame,) = generate(TrackScenario(n_static=2, n_moving=1, n_starting=0, seed=2), 1)
        for o in frame.observations:
            client_session.put(keys.track(NS, o.track.object_id), encode(o), congestion_control=BLOCK)
        client_session.put(keys.tracked(NS), encode(frame.tracked), congestion_control=BLOCK)
        assert wait_until(lambda: len(objects) == 1, timeout=30)
        h = frame.tracked.header
        client_session.put(keys.tracked(NS), _padded({"stamp": h.stamp, "frame_id": h.frame_id, "seq": h.seq},
                                                     200_000), congestion_control=BLOCK)
        assert wait_until(lambda: svc.counters.get("over_limit.tracked") == 1, timeout=20), svc.counters.snapshot()
        assert svc.counters.get("frames.duplicate_or_late_frames") == 0
    finally:
        svc.close()


def _observation(tid: str, seq: int) -> bytes:
    det = DetectedObject(classification=[ObjectClassification()])
    return encode(TrackObservation(header=Header(stamp=seq, seq=seq), detection=det,
                                   track=TrackState(object_id=tid, x=1.0, y=2.0)))


def test_a_flood_beyond_the_classifiers_observation_queue_is_counted_dropped(zenoh_port, client_session,
                                                                             monkeypatch) -> None:
    """Observations wait for the classifier's worker in a bounded queue. It had been a Zenoh ring channel, which
    drops its oldest sample when full and tells nobody: ~48 % of a 100,000-put flood was lost, counted nowhere.
    With the worker held, every put beyond the queue's capacity is now counted ``dropped_queue.tracks/*``, in the
    counters the heartbeat and ``classifier/state`` carry; once released the worker reads what the queue kept, and
    sent = read + dropped. A payload over ``max_payload_bytes`` is refused from its size in the callback: counted
    while the worker is still held, never queued."""
    import threading

    from jitterguard.services.classifier import service as classifier_service

    capacity, sent = 64, 300
    monkeypatch.setattr(classifier_service, "OBS_QUEUE", capacity)
    svc = ClassifierService(loopback_options(NS, zenoh_port, listen_self=True), straggler_timeout_s=0.5,
                            limits=Limits(max_payload_bytes=64 * 1024), config_writes=ConfigWritePolicy.open())
    held, release = threading.Event(), threading.Event()

    def hold() -> None:
        held.set()
        release.wait(60)

    worker_call = threading.Thread(target=svc.run_on_worker, args=(hold, 60.0))
    try:
        assert wait_until(lambda: any(True for _ in client_session.liveliness().get(
            keys.alive(NS, "classifier"), timeout=0.5)), 10)
        worker_call.start()
        assert held.wait(10)
        ids = _ids(sent, seed=11)
        for i, tid in enumerate(ids):  # far seqs no close comes for: read and kept per frame, never decided
            client_session.put(keys.track(NS, tid), _observation(tid, 10**12 + i % 3), congestion_control=BLOCK)
        client_session.put(keys.track(NS, ids[0]), _padded({"stamp": 1, "frame_id": "map", "seq": 10**12}, 100_000),
                           congestion_control=BLOCK)
        counter = "dropped_queue.tracks/*"
        assert wait_until(lambda: svc.counters.get(counter) == sent - capacity
                          and svc.counters.get("over_limit.tracks/*") == 1, timeout=20), svc.counters.snapshot()
        assert svc.counters.get("received") == 1  # the oversized one, refused unqueued; the worker read none yet
        release.set()
        worker_call.join(10)
        assert wait_until(lambda: svc.counters.get("received") == 1 + capacity, timeout=20), svc.counters.snapshot()
        time.sleep(0.5)  # nothing more comes
        assert svc.counters.get("received") == 1 + capacity
        assert svc.counters.get(counter) == sent - capacity
        assert svc.counters.get("rejected") == 1
        state = msgpack.unpackb(next(iter(client_session.get(keys.classifier_state(NS), timeout=5.0))).ok
                                .payload.to_bytes())
        assert state["counters"][counter] == sent - capacity
        assert svc.heartbeat().counters[counter] == sent - capacity
    finally:
        release.set()
        svc.close()


def test_the_detector_refuses_a_scan_whose_lists_no_scan_has_before_building_them(zenoh_port,
                                                                                 client_session) -> None:
    """A ``points`` payload was bounded only by ``max_scan_bytes`` (64 MB): a 2 MB scan whose ``fields`` held two
    million one-byte items cost the detector's callback 7 s and 1.9 GB (pydantic builds the list, then one error per
    item). A list beyond ``max_list_items`` or a map beyond any model's fields is refused from its header now,
    counted ``over_limit.points``."""
    svc = DetectorService(loopback_options(NS, zenoh_port, listen_self=True), Detector.load(None, "lite", threads=1))
    try:
        pub = client_session.declare_publisher(keys.points(NS), congestion_control=BLOCK)
        assert wait_until(lambda: pub.matching_status.matching, 15)
        header = {"stamp": 1_700_000_000_000_000_000, "frame_id": "lidar", "seq": 1}
        long_list = {"schema_version": 1, "header": header, "fields": [0] * 100_000, "num_points": 0, "data": b""}
        wide_map = {"schema_version": 1, "header": header, "ego_pose": {f"k{i}": 0 for i in range(100_000)},
                    "num_points": 0, "data": b""}
        for payload in (long_list, wide_map):
            pub.put(msgpack.packb(payload))
        assert wait_until(lambda: svc.counters.get("rejected.points") == 2, timeout=20), svc.counters.snapshot()
        assert svc.counters.get("over_limit.points") == 2
    finally:
        svc.close()


def test_a_config_write_is_bounded_before_it_is_built(zenoh_port, client_session) -> None:
    """A config write over Zenoh (with the token, or under ``--open-config-writes``) was decoded whole: one 8 MB
    per-class map was built and validated key by key on the query's thread. A write over MAX_CONFIG_BYTES, or with
    a map or list longer than any config has, is refused from its size or its header now; nothing is applied and
    the refusal is counted per key."""
    svc = ClassifierService(loopback_options(NS, zenoh_port, listen_self=True), config_writes=ConfigWritePolicy.open())
    try:
        assert wait_until(lambda: any(True for _ in client_session.liveliness().get(
            keys.alive(NS, "classifier"), timeout=0.5)), 10)
        before = svc.core.config
        wide = {"schema_version": 1, "alpha_per_class": {f"k{i}": 1.0 for i in range(100)}}
        big = {"schema_version": 1, "calibration_file": "x" * (MAX_CONFIG_BYTES + 1)}
        for payload, why in ((wide, "map holds more than"), (big, "bytes exceed")):
            (reply,) = list(client_session.get(keys.classifier_config(NS), payload=msgpack.packb(payload), timeout=5))
            assert reply.err is not None
            answer = decode(ConfigReply, reply.err.payload.to_bytes())
            assert not answer.ok and why in answer.error, answer.error
        assert svc.core.config == before and svc.counters.get("rejected.classifier/config") == 2
        assert svc.counters.get("over_limit.classifier/config") == 2  # had been counted `rejected` alone
        (ok,) = list(client_session.get(keys.classifier_config(NS), timeout=5,
                                        payload=encode(ClassifierConfig(alpha_default=2.5))))
        assert ok.ok is not None and svc.core.config.alpha_default == 2.5  # a real write still goes through
    finally:
        svc.close()


def test_a_classifier_still_warming_up_says_so_in_its_heartbeat(zenoh_port, client_session, monkeypatch) -> None:
    """Its token and heartbeat go out when its session opens, but it subscribes only once its compiled statistic has
    warmed up (seconds on a first start): /readyz had called the pipeline ready while every frame reaching it was
    lost. Until it subscribes its health is ``stalled``, ``starting: …``; then ``ok``."""
    import threading
    import time

    from jitterguard.schemas.models import Heartbeat
    from jitterguard.services.classifier import service as classifier_service

    monkeypatch.setattr(classifier_service, "warm_up", lambda: time.sleep(2.5))  # a first start's compile
    beats: list[Heartbeat] = []
    client_session.declare_subscriber(keys.heartbeat(NS, "classifier"),
                                       lambda s: beats.append(decode(Heartbeat, s.payload.to_bytes())))
    made: list[ClassifierService] = []
    builder = threading.Thread(target=lambda: made.append(ClassifierService(
        loopback_options(NS, zenoh_port, listen_self=True), config_writes=ConfigWritePolicy.open())))
    builder.start()
    try:
        assert wait_until(lambda: len(beats) >= 1, timeout=20)
        first = beats[0]
        assert first.health == "stalled" and first.health_reason.startswith("starting: warming up"), first
        builder.join(timeout=60)
        n = len(beats)
        assert wait_until(lambda: len(beats) > n, timeout=20)
        assert beats[-1].health == "ok", beats[-1]
    finally:
        builder.join(timeout=60)
        for svc in made:
            svc.close()


def test_per_key_counters_name_jitterguard_keys_without_their_namespace_and_other_keys_whole() -> None:
    """A ROS 2 topic's key (ros2-in) had been cut like a jg/{ns}/ key: an oversized scan counted under
    ``rejected.top/pointcloud``, an undecodable one under another name."""
    from jitterguard.runtime.service import counter_key

    assert counter_key("jg/default/tracked") == "tracked"
    assert counter_key("jg/run7/tracks/*") == "tracks/*"
    assert counter_key("sensing/lidar/top/pointcloud") == "sensing/lidar/top/pointcloud"
    assert counter_key("tf") == "tf"


def test_wire_text_in_a_rejection_cannot_forge_log_lines(zenoh_port, client_session, caplog) -> None:
    """Zenoh keys may hold a newline or an escape sequence, and a payload's unknown field name is named in its
    error: both went into the warning verbatim, so a put on ``tracks/x\\n<date> ERROR ...`` wrote a forged ERROR
    line into the classifier's log (what supervisord keeps and log shippers alert on). The line now shows them
    escaped, and the rejections are counted as before."""
    forged = "2099-01-01 00:00:00,000 ERROR jitterguard.classifier: FORGED"
    svc = ClassifierService(loopback_options(NS, zenoh_port, listen_self=True), config_writes=ConfigWritePolicy.open())
    try:
        assert wait_until(lambda: any(True for _ in client_session.liveliness().get(
            keys.alive(NS, "classifier"), timeout=0.5)), 10)
        with caplog.at_level(logging.WARNING, logger="jitterguard.classifier"):
            client_session.put(f"jg/{NS}/tracks/x\n{forged}\x1b[2K", b"\x00", congestion_control=BLOCK)
            assert wait_until(lambda: svc.counters.get("rejected.tracks/*") == 1, 10)
            junk = msgpack.packb({"schema_version": 1, f"x\n{forged}": 1})
            reply = next(iter(client_session.get(keys.classifier_config(NS), payload=junk, timeout=5.0)))
            assert reply.err is not None
            assert wait_until(lambda: svc.counters.get("rejected.classifier/config") == 1, 10)
        lines = [r.getMessage() for r in caplog.records if "rejected payload" in r.getMessage()]
        assert len(lines) == 2, lines
        assert all(line.isprintable() and "\\n2099-01-01" in line for line in lines), lines
        assert "\\x1b[2K" in lines[0]
    finally:
        svc.close()


def test_a_zenoh_delete_is_counted_as_one_and_not_as_a_corrupt_payload(zenoh_port, client_session, caplog) -> None:
    """``session.delete`` on an input key (a storage's or an admin tool's) had been counted ``rejected`` and logged
    "not valid msgpack", as if a writer were broken; it is counted ``deletes.<key>`` — on a plain subscription (the
    bridge's) and on a queued one (the tracker's) — and the next frame still goes through."""
    tracker = TrackerService(loopback_options(NS, zenoh_port, listen_self=True))
    sink = _Sink()
    bridge = BridgeService(loopback_options(NS, zenoh_port), sink, points=False)
    try:
        tracked: list[bytes] = []
        client_session.declare_subscriber(keys.tracked(NS), lambda s: tracked.append(s.payload.to_bytes()))
        header = {"stamp": 1_700_000_000_000_000_000, "frame_id": "lidar", "seq": 0}

        def frame() -> bool:
            header["seq"] += 1
            header["stamp"] += 100_000_000
            before = len(tracked)
            client_session.put(keys.detections(NS), encode(DetectedObjects(header=Header(**header))),
                               congestion_control=BLOCK)
            return wait_until(lambda: len(tracked) > before and bridge.counters.get("received") > 1, timeout=0.5)
        assert wait_until(frame, timeout=15)
        with caplog.at_level(logging.WARNING):
            client_session.delete(keys.detections(NS))
            assert wait_until(lambda: tracker.counters.get("deletes.detections") == 1
                              and bridge.counters.get("deletes.detections") == 1, timeout=10), \
                (tracker.counters.snapshot(), bridge.counters.snapshot())
        assert tracker.counters.get("rejected") == 0 and bridge.counters.get("rejected") == 0
        assert "msgpack" not in caplog.text
        assert frame()  # the next frame goes through
    finally:
        bridge.close()
        tracker.close()
