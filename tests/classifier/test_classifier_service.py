"""The classifier service over real in-process Zenoh (peer mode, loopback, multicast off)."""

from __future__ import annotations

import logging
import math
import threading
import time
from contextlib import contextmanager

import msgpack
import numpy as np
import pytest

from jitterguard.runtime import loopback_options
from jitterguard.schemas import decode, encode, keys
from jitterguard.schemas.models import (
    ClassifierConfig,
    ClassifierStateSnapshot,
    ConfigReply,
    MotionState,
    TrackedObjects,
)
from jitterguard.schemas.wire import Limits
from jitterguard.services.classifier.config_writes import ConfigWritePolicy
from jitterguard.services.classifier.service import ClassifierService
from jitterguard.services.classifier.synthetic_tracks import TrackScenario, generate

from helpers import wait_until

pytestmark = pytest.mark.integration
NS = "test"


@pytest.fixture
def service(zenoh_port):
    svc = ClassifierService(loopback_options(NS, zenoh_port, listen_self=True), straggler_timeout_s=0.5,
                            config_writes=ConfigWritePolicy.open())
    yield svc
    svc.close()


def _collect(session):
    got = {"objects": [], "motion": {}}
    session.declare_subscriber(keys.objects(NS), lambda s: got["objects"].append(decode(TrackedObjects, s.payload.to_bytes())))
    session.declare_subscriber(
        keys.motion_all(NS),
        lambda s: got["motion"].__setitem__(keys.last_chunk(str(s.key_expr)), decode(MotionState, s.payload.to_bytes())),
    )
    return got


def _send(session, frame):
    for o in frame.observations:
        session.put(keys.track(NS, o.track.object_id), encode(o))
    session.put(keys.tracked(NS), encode(frame.tracked))


def _send_paced(session, frames, got):
    """Send frame by frame, each after the previous one's objects came back: on a loaded machine a burst
    can outrun the straggler timeout, which is tested on its own (test_frames.py)."""
    for f in frames:
        n = len(got["objects"])
        _send(session, f)
        assert wait_until(lambda: len(got["objects"]) == n + 1, timeout=30)


def _wait_connected(session):
    assert wait_until(lambda: any(True for _ in session.liveliness().get(keys.alive(NS, "classifier"), timeout=0.5)), 10)


def _query(session, key, payload=None):
    replies = list(session.get(key, payload=payload, timeout=5.0))
    assert len(replies) == 1
    return replies[0]


def test_static_and_moving_objects_get_the_right_states(service, client_session):
    got = _collect(client_session)
    _wait_connected(client_session)
    frames = list(generate(TrackScenario(n_static=5, n_moving=4, n_starting=0, seed=1), 15))
    _send_paced(client_session, frames, got)
    truth = frames[-1].moving
    assert wait_until(lambda: len(got["motion"]) == len(truth) and all(m.header.seq == 14 for m in got["motion"].values()))
    for tid, m in got["motion"].items():
        assert m.state == ("dynamic" if truth[tid] else "static"), (tid, m)
        assert m.window_length == min(len(frames), ClassifierConfig().window_size)
    last = got["objects"][-1]
    assert last.header.seq == 14 and last.observed_track_ids == []
    for obj in last.objects:
        kin = obj.kinematics
        if truth[obj.object_id]:
            assert not kin.is_stationary
            assert abs(kin.twist_with_covariance.twist.linear.x) > 1.0  # passes through untouched
        else:
            assert kin.is_stationary
            assert kin.twist_with_covariance.twist.linear.x == 0.0
            assert kin.pose_with_covariance.pose.position.x == pytest.approx(got["motion"][obj.object_id].mean_x)
    assert service.counters.get("rejected") == 0


def test_car_that_starts_moving_flips_within_the_window(service, client_session):
    got = _collect(client_session)
    _wait_connected(client_session)
    sc = TrackScenario(n_static=0, n_moving=0, n_starting=1, start_frame=12, seed=4)
    frames = list(generate(sc, 24))
    history = []
    for f in frames:
        _send(client_session, f)
        assert wait_until(lambda: got["motion"] and next(iter(got["motion"].values())).header.seq == f.seq)
        history.append(next(iter(got["motion"].values())).state)
    assert history[11] == "static"
    first_dynamic = history.index("dynamic")
    assert 12 <= first_dynamic <= 12 + 10


def test_a_parked_box_replaced_once_stays_static_and_the_veto_is_counted(service, client_session):
    """The detector re-places a parked car's box 0.8 m once (about 5σ of its jitter along the beam): the test alone
    would call the windows that hold the jump moving; the jump veto keeps the car static, the mover stays dynamic,
    and ``objects.vetoed`` (on /metrics and in the run summary) tells the operator how often the veto overruled
    the test."""
    got = _collect(client_session)
    _wait_connected(client_session)
    sc = TrackScenario(n_static=1, n_moving=1, n_starting=0, replaced_frame=15, seed=2)
    frames = list(generate(sc, 34))
    parked = next(t for t, moving in frames[0].moving.items() if not moving)
    states: dict[str, list[str]] = {t: [] for t in frames[0].moving}
    for f in frames:
        _send(client_session, f)
        assert wait_until(lambda: len(got["motion"]) == 2
                          and all(m.header.seq == f.seq for m in got["motion"].values()), timeout=30)
        for t, m in got["motion"].items():
            states[t].append(m.state)
    mover = next(t for t in states if t != parked)
    assert all(s == "static" for s in states[parked][19:])  # every full window holds the jump
    assert all(s == "dynamic" for s in states[mover][19:])
    vetoed = service.counters.get("objects.vetoed")  # the test rejected there: the veto, not the test, kept it
    assert 1 <= vetoed <= 34 - 15  # static (tests/classifier/test_classifier_jump_veto.py: dynamic without it)


@pytest.mark.parametrize(("rate_hz", "frames", "length", "size", "logged"), [
    (2.0, 14, 10, 10, "window now 10 observations (was 20 observations): frames 0.5 s apart"),
    (20.0, 30, 15, 20, "window now 20 observations of every 2nd frame (was 20 observations): frames 0.05 s apart"),
])
def test_a_stream_gets_windows_of_the_reference_span(service, client_session, caplog, rate_hz, frames, length, size,
                                                     logged):
    """Through the live service, windows keep the default's 2 s at 10 Hz: key frames at 2 Hz hold 10 observations
    (floored at the paper's 10), not 20 (10 s); at 20 Hz every second frame is taken (30 frames leave 15 of 20),
    while every frame still gets its decision — in ``motion/{id}``, the state and the calibration — and the log
    says when the window changed and why."""
    caplog.set_level(logging.INFO, logger="jitterguard.classifier")
    got = _collect(client_session)
    _wait_connected(client_session)
    sent = list(generate(TrackScenario(n_static=3, n_moving=2, n_starting=0, rate_hz=rate_hz, seed=4), frames))
    _send_paced(client_session, sent, got)
    last = frames - 1
    assert wait_until(lambda: len(got["motion"]) == 5 and all(m.header.seq == last for m in got["motion"].values()))
    assert {m.window_length for m in got["motion"].values()} == {length}
    snap = decode(ClassifierStateSnapshot, _query(client_session, keys.classifier_state(NS)).ok.payload.to_bytes())
    assert {(t.window_length, t.window_size) for t in snap.tracks} == {(length, size)}
    assert snap.calibration is not None and snap.calibration.window == size
    assert any(logged in r.getMessage() for r in caplog.records)


def test_alpha_change_through_queryable_flips_a_borderline_object(service, client_session):
    got = _collect(client_session)
    _wait_connected(client_session)
    frames = list(generate(TrackScenario(n_static=0, n_moving=1, n_starting=0, speed_mps=1.0, seed=2), 30))
    _send_paced(client_session, frames[:10], got)
    assert wait_until(lambda: next(iter(got["motion"].values())).header.seq == 9)
    m = next(iter(got["motion"].values()))
    z = max(m.z_x, m.z_y)
    assert m.state == "dynamic" and z > 1.96, m
    reply = _query(client_session, keys.classifier_config(NS),
                   encode(ClassifierConfig(alpha_default=z + 5.0, alpha_per_class={})))
    in_force = decode(ConfigReply, reply.ok.payload.to_bytes())
    assert in_force.ok and in_force.config.alpha_default == pytest.approx(z + 5.0)
    _send(client_session, frames[10])
    assert wait_until(lambda: len(got["objects"]) == 11)
    assert wait_until(lambda: next(iter(got["motion"].values())).header.seq == 10)
    m2 = next(iter(got["motion"].values()))
    assert m2.header.seq == 10 and m2.alpha == pytest.approx(z + 5.0)
    assert m2.state == "static"
    assert got["objects"][-1].objects[0].kinematics.is_stationary
    # a plain get reports what is in force; the state queryable shows the track
    plain = decode(ConfigReply, _query(client_session, keys.classifier_config(NS)).ok.payload.to_bytes())
    assert plain.config.alpha_default == pytest.approx(z + 5.0)
    snap = decode(ClassifierStateSnapshot, _query(client_session, keys.classifier_state(NS)).ok.payload.to_bytes())
    assert [t.state for t in snap.tracks] == ["static"]
    assert snap.tracks[0].window_length == min(11, ClassifierConfig().window_size)  # frames 0-10


def test_invalid_config_write_is_refused_and_nothing_changes(service, client_session):
    _wait_connected(client_session)
    bad = msgpack.packb({**ClassifierConfig().model_dump(), "window_size": 1})
    reply = _query(client_session, keys.classifier_config(NS), bad)
    assert reply.err is not None
    err = decode(ConfigReply, reply.err.payload.to_bytes())
    assert not err.ok and "window_size" in err.error
    assert service.core.config == ClassifierConfig()


def test_a_conditional_write_applies_only_while_the_config_it_read_is_in_force(service, client_session):
    """``classifier/config?if_match=ETAG``: a read-modify-write that another writer overtook is refused (conflict,
    nothing applied) instead of overwriting that writer's change unseen. Every reply carries the etag of the config
    it holds, so the loser can redo its change at once."""
    from jitterguard.schemas.models import config_etag

    _wait_connected(client_session)
    key = keys.classifier_config(NS)
    first = decode(ConfigReply, _query(client_session, key).ok.payload.to_bytes())
    assert first.etag == config_etag(ClassifierConfig()) and not first.conflict
    # writer A read `first`; writer B (unconditional) changes another field meanwhile
    b = decode(ConfigReply, _query(client_session, key, encode(first.config.model_copy(
        update={"min_window": 4}))).ok.payload.to_bytes())
    assert b.etag != first.etag and b.etag == config_etag(service.core.config)
    # A's put, conditional on what it read, would drop B's min_window: refused
    a_cfg = first.config.model_copy(update={"alpha_default": 3.3})
    reply = _query(client_session, f"{key}?{keys.IF_MATCH}={first.etag}", encode(a_cfg))
    assert reply.err is not None
    err = decode(ConfigReply, reply.err.payload.to_bytes())
    assert err.conflict and not err.ok and err.error.startswith("conflict") and err.etag == b.etag
    assert service.core.config.min_window == 4 and service.core.config.alpha_default == ClassifierConfig().alpha_default
    assert service.counters.get("config_writes_conflicted") == 1
    # redone on the config in force, with its etag: applied, both changes kept
    redo = err.config.model_copy(update={"alpha_default": 3.3})
    ok = decode(ConfigReply, _query(client_session, f"{key}?{keys.IF_MATCH}={err.etag}", encode(redo))
                .ok.payload.to_bytes())
    assert ok.ok and ok.config.min_window == 4 and ok.config.alpha_default == 3.3
    assert ok.etag == config_etag(service.core.config)
    # an if_match that is no etag is refused naming the parameter, nothing applied
    bad = _query(client_session, f"{key}?{keys.IF_MATCH}=latest", encode(ClassifierConfig()))
    assert bad.err is not None
    assert decode(ConfigReply, bad.err.payload.to_bytes()).error.startswith("if_match: must be 16 lowercase hex")
    assert service.core.config.alpha_default == 3.3 and service.counters.get("config_changes") == 2


def test_a_write_the_busy_worker_did_not_take_in_time_is_withdrawn(service, client_session):
    """The worker is busy for 3 s (a long frame, a stall): the write times out after 2 s and its writer is told
    "not applied" — it had then been applied (and stored) a second later all the same."""

    _wait_connected(client_session)
    busy = threading.Thread(target=service.run_on_worker, args=(lambda: time.sleep(3.0), 5.0))
    busy.start()
    time.sleep(0.2)
    reply = _query(client_session, keys.classifier_config(NS),
                   encode(ClassifierConfig().model_copy(update={"alpha_default": 3.3})))
    assert reply.err is not None
    err = decode(ConfigReply, reply.err.payload.to_bytes())
    assert "not applied" in err.error and "did not take it" in err.error
    busy.join()
    time.sleep(0.5)  # the worker is free again: the withdrawn write must stay withdrawn
    assert service.core.config.alpha_default == ClassifierConfig().alpha_default
    assert service.counters.get("config_changes") == 0
    assert service.counters.get("config_writes_unapplied") == 1  # counted (it had been in no counter)


def test_a_write_behind_a_full_worker_queue_is_told_not_applied(service, client_session):
    """64 writes and calls wait behind a stuck worker: a further write's put found the queue full and raised in the
    query handler — its writer got no reply at all (the sidecar then said "did not confirm")."""
    from concurrent.futures import Future

    _wait_connected(client_session)
    busy = threading.Thread(target=service.run_on_worker, args=(lambda: time.sleep(3.0), 5.0))
    busy.start()
    time.sleep(0.2)
    while not service._queue.full():
        service._queue.put_nowait(("call", (lambda: None, Future()), None))
    reply = _query(client_session, keys.classifier_config(NS),
                   encode(ClassifierConfig().model_copy(update={"alpha_default": 3.3})))
    assert reply.err is not None
    err = decode(ConfigReply, reply.err.payload.to_bytes())
    assert not err.ok and "not applied" in err.error and "queue stayed full" in err.error
    assert service.counters.get("config_writes_unapplied") == 1
    busy.join()
    time.sleep(0.5)
    assert service.core.config.alpha_default == ClassifierConfig().alpha_default


def test_malformed_payloads_on_every_key_are_counted_and_service_keeps_running(service, client_session):
    got = _collect(client_session)
    _wait_connected(client_session)
    frames = list(generate(TrackScenario(n_static=2, n_moving=1, n_starting=0, seed=3), 4))
    tid = frames[0].observations[0].track.object_id
    junk = [b"", b"\x00\xff", msgpack.packb({"schema_version": 1}), encode(frames[0].tracked)[:-7],
            b"\x81\xa2\xca\xca\x01"]  # the last: a map key that is not UTF-8
    for j in junk:
        client_session.put(keys.track(NS, tid), j)
        client_session.put(keys.tracked(NS), j)
    for f in frames:
        _send(client_session, f)
    assert wait_until(lambda: len(got["objects"]) == 4)
    assert wait_until(lambda: service.counters.get("rejected") == 2 * len(junk))
    assert service.counters.get("rejected.tracks/*") == len(junk)
    assert service.counters.get("rejected.tracked") == len(junk)


def test_restarted_tracker_leaves_no_stale_windows(service, client_session):
    got = _collect(client_session)
    _wait_connected(client_session)
    first = list(generate(TrackScenario(n_static=3, n_moving=0, n_starting=0, seed=5), 30))
    _send_paced(client_session, first, got)
    second = list(generate(TrackScenario(n_static=2, n_moving=0, n_starting=0, seed=6), 10))  # seq restarts at 0
    for f in second:  # at 10 Hz: the restart is followed once a run of its frames has lasted confirm_s
        _send(client_session, f)
        time.sleep(0.1)
    assert wait_until(lambda: got["objects"] and got["objects"][-1].header.seq == 9, timeout=30)
    assert service.counters.get("frames.upstream_restarts") == 1
    new_ids = {o.track.object_id for o in second[0].observations}
    assert set(service.run_on_worker(service.core.track_ids)) == new_ids


def test_calibration_is_in_the_state_and_the_heartbeat_and_a_file_can_be_put_in_force(
        service, client_session, tmp_path):
    """The calibration the frames were decided with shows in the state queryable and as heartbeat gauges; a
    config write naming a calibration file loads it (the scales then in force are the file's); a bad file is
    refused with the entry named and nothing changes."""
    from jitterguard.schemas.models import Heartbeat
    from jitterguard.services.classifier.calibration import NoiseModel
    from jitterguard.services.classifier.calibration_file import write_calibration

    beats = []
    client_session.declare_subscriber(keys.heartbeat(NS, "classifier"),
                                      lambda s: beats.append(decode(Heartbeat, s.payload.to_bytes())))
    got = _collect(client_session)
    _wait_connected(client_session)
    frames = list(generate(TrackScenario(n_static=3, n_moving=1, n_starting=0, seed=9), 6))
    _send_paced(client_session, frames[:4], got)
    snap = decode(ClassifierStateSnapshot, _query(client_session, keys.classifier_state(NS)).ok.payload.to_bytes())
    assert snap.calibration is not None and snap.calibration.mode == "online"
    assert set(snap.calibration.groups) == {"vehicle", "pedestrian", "cycle", "unknown"}
    assert wait_until(lambda: beats and "calibration.vehicle.along.scale.0-20" in beats[-1].gauges, timeout=10)
    model = NoiseModel.prior()
    model = NoiseModel(model.band_edges_m, model.scale * 7.0, model.correlation, model.tau_s, model.blocks)
    good = tmp_path / "cal.yaml"
    write_calibration(good, model, window=10)
    cfg = ClassifierConfig(calibration="file", calibration_file=str(good))
    reply = _query(client_session, keys.classifier_config(NS), encode(cfg))
    assert decode(ConfigReply, reply.ok.payload.to_bytes()).config.calibration == "file"
    _send_paced(client_session, frames[4:], got)
    snap = decode(ClassifierStateSnapshot, _query(client_session, keys.classifier_state(NS)).ok.payload.to_bytes())
    assert snap.calibration.mode == "file" and snap.calibration.groups["vehicle"].along.scale["0-20"] == 7.0
    bad = tmp_path / "bad.yaml"
    bad.write_text("format: jitterguard-calibration/1\ngroups: {vehicle: {along: {scale: {0-20: -3}}}}\n")
    reply = _query(client_session, keys.classifier_config(NS),
                   encode(ClassifierConfig(calibration="file", calibration_file=str(bad))))
    err = decode(ConfigReply, reply.err.payload.to_bytes())
    assert not err.ok and "calibration_file" in err.error and "groups.vehicle.along.scale.0-20" in err.error
    assert service.core.config.calibration_file == str(good)
    # the refusal is counted in the total as well as under its key, as every other rejection is
    assert service.counters.get("rejected.classifier/config") == 1 and service.counters.get("rejected") == 1


def test_state_map_validates_as_the_snapshot_model(service, client_session):
    got = _collect(client_session)
    _wait_connected(client_session)
    _send_paced(client_session, list(generate(TrackScenario(n_static=2, n_moving=2, n_starting=0, seed=8), 6)), got)
    assert wait_until(lambda: len(got["motion"]) == 4 and all(m.header.seq == 5 for m in got["motion"].values()))
    snap = ClassifierStateSnapshot.model_validate(service.state_map())  # validates the map the queryable sends
    assert snap.header.seq == 5 and len(snap.tracks) == 4
    by_id = {t.track_id: t for t in snap.tracks}
    for m in got["motion"].values():
        t = by_id[m.track_id]
        assert t.state == m.state and t.z_x == pytest.approx(m.z_x) and t.window_length == m.window_length
        if t.state == "static":
            assert (t.x, t.y) == (pytest.approx(m.mean_x), pytest.approx(m.mean_y))


# ------------------------------------------------------------ the adapter (no Zenoh): same answers as the models

def _reference_objects(frames, config=None):
    """What the classifier must publish, computed the slow way and independently: pydantic models, the core, the
    decisions applied to the models by hand (static: window mean, zero twist, is_stationary)."""
    from jitterguard.services.classifier.adapter import observations_from_rows
    from jitterguard.services.classifier.core import STATIC, MotionClassifierCore

    core = MotionClassifierCore(config or ClassifierConfig())
    out = []
    for f in frames:
        tracked = decode(TrackedObjects, encode(f.tracked))
        rows = []
        for o in (decode(type(o), encode(o)) for o in f.observations):
            pwc = o.detection.kinematics.pose_with_covariance
            rows.append((o.track.object_id, o.track.label, pwc.pose.position.x, pwc.pose.position.y,
                         pwc.covariance[0], pwc.covariance[1], pwc.covariance[7], math.hypot(o.track.vx, o.track.vy)))
        ego = tracked.ego_pose.position  # the origin of the line of sight (calibration axes, the view term)
        core.update(observations_from_rows(rows, tracked.header.seq, tracked.header.stamp, (ego.x, ego.y)))
        ids = np.asarray([o.object_id for o in tracked.objects], dtype="S32")
        dec = core.last_decisions(ids)
        core.retain(ids)
        for obj, state, mx, my in zip(tracked.objects, dec.state.tolist(), dec.mean_x.tolist(), dec.mean_y.tolist()):
            kin = obj.kinematics
            kin.is_stationary = state == STATIC
            if state == STATIC:
                kin.pose_with_covariance.pose.position.x, kin.pose_with_covariance.pose.position.y = mx, my
                tw = kin.twist_with_covariance.twist
                for v in (tw.linear, tw.angular):
                    v.x = v.y = v.z = 0.0
            obj.classification = [max(obj.classification, key=lambda c: c.probability)]  # the record shape
        tracked.observed_track_ids = []
        out.append(msgpack.unpackb(encode(tracked)))
    return out


@pytest.mark.parametrize("shape", ["records", "other"])
def test_adapter_publishes_exactly_what_the_model_path_computes(shape):
    """``tracked`` of the usual shape is decided as a view of its records; any other valid shape (here: two
    classifications per object, written by the model) is normalised into the same records and said so; both
    publish what the models compute."""
    from jitterguard.schemas.models import ObjectClassification
    from jitterguard.services.classifier.adapter import ClassifierAdapter
    from jitterguard.services.classifier.synthetic_tracks import FrameRecords

    frames = list(generate(TrackScenario(n_static=6, n_moving=5, n_starting=1, seed=11), 14))
    if shape == "other":
        for f in frames:
            for o in f.tracked.objects:
                o.classification = [*o.classification, ObjectClassification(label=0, probability=0.01)]
    pipe = ClassifierAdapter()
    got = []
    for i, f in enumerate(frames):
        observations, _ = FrameRecords.of(f).payloads()
        pipe.observations([p for _, p in reversed(observations)])  # arrival order within a frame does not matter
        cols = pipe.close(encode(f.tracked), received_at=float(i))
        assert cols is not None and cols.normalised == (shape == "other")
        (frame,) = pipe.ready(float(i))
        out = pipe.finish(frame)
        got.append(msgpack.unpackb(out.payload))
        motion = [decode(MotionState, p) for _, p in pipe.motion_payloads(out)]  # valid MotionStates
        assert {m.track_id for m in motion} == {o.track.object_id for o in f.observations}
        assert got[-1]["ego_pose"] == f.tracked.ego_pose.model_dump()  # passed through unchanged
        pipe.settle(out)
    assert got == _reference_objects(frames)
    assert any(o["kinematics"]["is_stationary"] for o in got[-1]["objects"])


def test_adapter_rejects_bad_payloads_and_counts_stragglers():
    from jitterguard.schemas import DecodeError
    from jitterguard.services.classifier.adapter import ClassifierAdapter

    f0, f1 = generate(TrackScenario(n_static=2, n_moving=1, n_starting=0, seed=3), 2)
    pipe = ClassifierAdapter()
    bad = msgpack.unpackb(encode(f0.observations[0]))
    bad["detection"]["kinematics"]["pose_with_covariance"]["covariance"][7] = -1.0
    (err,) = pipe.observations([msgpack.packb(bad)]).errors
    assert err[0] == 0 and "covariance.7" in str(err[1])
    with pytest.raises(DecodeError, match="TrackedObjects"):
        pipe.close(encode(f0.tracked)[:-3], received_at=0.0)
    pipe.observations([encode(o) for o in f0.observations])
    pipe.close(encode(f0.tracked), received_at=0.0)
    pipe.finish(pipe.ready(0.0)[0])
    pipe.observations([encode(f0.observations[0])])  # frame 0 is decided: a straggler now
    assert pipe.assembler.counts["late_observations"] == 1


@contextmanager
def _held_worker(service, hold_s: float = 30.0):
    """The classifier's worker busy (a call on it that waits) until the block ends: what arrives queues up."""
    entered, release = threading.Event(), threading.Event()

    def hold() -> None:
        entered.set()
        release.wait(hold_s)

    blocked = threading.Thread(target=service.run_on_worker, args=(hold,), kwargs={"timeout": hold_s + 5})
    blocked.start()
    try:
        assert entered.wait(10)
        yield
    finally:
        release.set()
        blocked.join()


def test_a_frame_already_behind_sheds_its_motion_messages_but_not_its_objects(service, client_session):
    got = _collect(client_session)
    _wait_connected(client_session)
    frames = list(generate(TrackScenario(n_static=2, n_moving=1, n_starting=0, seed=9), 3))
    _send_paced(client_session, frames[:1], got)
    with _held_worker(service):  # the worker is busy: the next two frames queue up behind it
        for f in frames[1:]:
            _send(client_session, f)
        assert wait_until(lambda: len(service._closes) == 2)
    assert wait_until(lambda: len(got["objects"]) == 3)
    assert [o.header.seq for o in got["objects"]] == [0, 1, 2]
    assert service.counters.get("motion_frames_shed") == 1  # frame 1: frame 2 was already waiting
    assert wait_until(lambda: all(m.header.seq == 2 for m in got["motion"].values()))


def test_closes_behind_a_held_worker_are_bounded_in_bytes_and_the_oldest_counted(service, client_session):
    """``tracked`` had waited in a queue bounded by count alone: 64 closes of up to ``max_payload_bytes`` (8 MiB)
    each, 512 MiB. It holds 64 MiB at most now; beyond that the oldest go, counted ``dropped_queue.tracked``, and
    the classifier goes on deciding frames once its worker is free."""
    import zenoh

    got = _collect(client_session)
    _wait_connected(client_session)
    frames = list(generate(TrackScenario(n_static=2, n_moving=1, n_starting=0, seed=9), 2))
    _send_paced(client_session, frames[:1], got)
    h = frames[0].tracked.header  # a repeat of the decided frame's header: dropped unread once the worker is back
    big = msgpack.packb({"schema_version": 1, "header": {"stamp": h.stamp, "frame_id": h.frame_id, "seq": h.seq},
                         "pad": b"\0" * (7 << 20)})  # under the 8 MiB limit: queued, not refused
    with _held_worker(service):
        for _ in range(12):  # 84 MiB
            client_session.put(keys.tracked(NS), big, congestion_control=zenoh.CongestionControl.BLOCK)
        assert wait_until(lambda: service.counters.get("dropped_queue.tracked") == 3, timeout=30), \
            service.counters.snapshot()
        assert len(service._closes) == 9 and service._closes.queued_bytes <= 64 << 20
    assert wait_until(lambda: len(service._closes) == 0, timeout=10)
    _send_paced(client_session, frames[1:], got)  # its state kept: the next frame is decided
    assert [o.header.seq for o in got["objects"]] == [0, 1]


def test_the_subscription_routes_observations_and_closes_and_nothing_else() -> None:
    from jitterguard.services.classifier.service import route_by_key

    route = route_by_key(keys.tracks_all(NS)[:-1], keys.tracked(NS))
    assert route(keys.track(NS, "a1b2")) == 0 and route(keys.tracked(NS)) == 1
    for other in (f"jg/{NS}/tracks/a/b", f"jg/{NS}/tracks/", f"jg/{NS}/tracks", f"jg/{NS}/trackers/x",
                  f"jg/{NS}/trackedX", "jg/other/tracked"):
        assert route(other) is None, other


def test_a_frames_observations_are_queued_before_its_close_in_a_burst(zenoh_port, client_session, monkeypatch):
    """Observations and closes come through one subscription, one callback thread: every observation of a frame is
    queued before the frame's close, as the tracker put them. With a subscription each (two threads) a close had
    been able to overtake its observations and the frame to wait for them as stragglers, or go without them."""
    import zenoh

    from jitterguard.runtime.ingest_queue import IngestQueue

    BLOCK = zenoh.CongestionControl.BLOCK
    order: list[tuple[str, int]] = []  # (key, header seq) of every payload queued, in the order queued
    push = IngestQueue.push

    def recording_push(self, data, key, arrived=0.0):
        order.append((key, msgpack.unpackb(data)["header"]["seq"]))
        return push(self, data, key, arrived)

    monkeypatch.setattr(IngestQueue, "push", recording_push)
    svc = ClassifierService(loopback_options(NS, zenoh_port, listen_self=True), straggler_timeout_s=0.5,
                            config_writes=ConfigWritePolicy.open())
    try:
        got = _collect(client_session)
        _wait_connected(client_session)
        frames = list(generate(TrackScenario(n_static=30, n_moving=10, n_starting=0, seed=11), 16))

        def routed() -> bool:  # the first frame again until it comes back: the subscription has reached the client
            _send(client_session, frames[0])
            return wait_until(lambda: len(got["objects"]) == 1, timeout=1.0)

        assert wait_until(routed, timeout=20)
        for f in frames[1:]:  # a burst: no pacing, nothing dropped on the way (BLOCK)
            for o in f.observations:
                client_session.put(keys.track(NS, o.track.object_id), encode(o), congestion_control=BLOCK)
            client_session.put(keys.tracked(NS), encode(f.tracked), congestion_control=BLOCK)
        assert wait_until(lambda: len(got["objects"]) == len(frames), timeout=30), (
            [o.header.seq for o in got["objects"]], {k: v for k, v in svc.counters.snapshot().items()
                                                     if not k.startswith("frame_latency")}, len(order))
        for f in frames[1:]:
            seq = f.tracked.header.seq
            (close_at,) = [i for i, (k, q) in enumerate(order) if k == keys.tracked(NS) and q == seq]
            queued = [(k, q) for k, q in order if q == seq and k != keys.tracked(NS)]
            assert order[close_at - len(queued):close_at] == queued  # every one of them before the close
            assert {k for k, _ in queued} == {keys.track(NS, o.track.object_id) for o in f.observations}
        counts = svc.pipeline.assembler.counts
        assert counts.get("late_observations", 0) == 0 and counts.get("missing_observations", 0) == 0, counts
    finally:
        svc.close()


def _frames_with_a_track_at_1e300():
    frames = list(generate(TrackScenario(n_static=2, n_moving=0, n_starting=0, seed=5), 12))
    tid = frames[0].observations[0].track.object_id
    for f in frames[6:]:
        for o in f.observations:
            if o.track.object_id == tid:
                o.detection.kinematics.pose_with_covariance.pose.position.x = 1e300
    return frames, tid


def test_a_track_at_1e300_is_refused_by_the_read_limits(service, client_session):
    """x = 1e300 from a broken upstream is beyond ``limits.max_abs_coordinate_m``: each such observation is
    refused at the read and counted (``rejected``, ``over_limit``), the frames still close and every output
    stays valid."""
    got = _collect(client_session)
    _wait_connected(client_session)
    frames, tid = _frames_with_a_track_at_1e300()
    _send_paced(client_session, frames, got)
    assert got["objects"][-1].header.seq == 11  # decoded, so valid
    assert service.counters.get("rejected") == 6
    assert service.counters.get("over_limit.tracks/*") == 6
    snap = decode(ClassifierStateSnapshot, _query(client_session, keys.classifier_state(NS)).ok.payload.to_bytes())
    entry = next(t for t in snap.tracks if t.track_id == tid)
    assert np.isfinite([entry.chi2, entry.z_x, entry.z_y, entry.x]).all() and abs(entry.x) < 1e3


def test_a_track_at_1e300_keeps_every_output_valid(zenoh_port, client_session):
    """With the coordinate limit opened up, x = 1e300 reaches the statistics. It used to make chi2 infinite, and
    the state feed (classifier/state, read by the sidecar) was rejected by its own reader until the track aged
    out. Every output stays valid: the state, the track's MotionState and ``objects``."""
    svc = ClassifierService(loopback_options(NS, zenoh_port, listen_self=True), straggler_timeout_s=0.5,
                            limits=Limits(max_abs_coordinate_m=1e308), config_writes=ConfigWritePolicy.open())
    try:
        got = _collect(client_session)
        _wait_connected(client_session)
        frames, tid = _frames_with_a_track_at_1e300()
        _send_paced(client_session, frames, got)
        assert wait_until(lambda: tid in got["motion"] and got["motion"][tid].header.seq == 11)
        m = got["motion"][tid]
        # z beyond every α the config takes (≤ 100); it is the Student-t tail's normal score, not |t| itself (which
        # the conversion had fallen back to once the tail probability underflowed)
        assert m.state == "dynamic" and np.isfinite([m.chi2, m.z_x, m.z_y]).all() and m.z_x > 100
        snap = decode(ClassifierStateSnapshot,
                      _query(client_session, keys.classifier_state(NS)).ok.payload.to_bytes())
        entry = next(t for t in snap.tracks if t.track_id == tid)
        assert entry.state == "dynamic" and entry.chi2 > 1e6
        assert got["objects"][-1].header.seq == 11  # decoded, so valid
        assert svc.counters.get("rejected") == 0
    finally:
        svc.close()


def test_heartbeats_go_out_while_the_statistic_warms_up(zenoh_port, client_session, monkeypatch) -> None:
    """The heartbeat starts with the session, before the compiled statistic has warmed up (seconds on a first run):
    it read gauges set only after the warm-up, and every heartbeat of that time failed (AttributeError)."""

    from jitterguard.schemas.models import Heartbeat
    from jitterguard.services.classifier import service as service_module

    release, warming = threading.Event(), threading.Event()

    def slow_warm_up() -> None:
        warming.set()
        assert release.wait(30)

    monkeypatch.setattr(service_module, "warm_up", slow_warm_up)
    beats: list[Heartbeat] = []
    client_session.declare_subscriber(keys.heartbeat(NS, "classifier"),
                                      lambda s: beats.append(decode(Heartbeat, s.payload.to_bytes())))
    built: list[ClassifierService] = []
    maker = threading.Thread(target=lambda: built.append(ClassifierService(
        loopback_options(NS, zenoh_port, listen_self=True))), daemon=True)
    maker.start()
    try:
        assert warming.wait(30)
        assert wait_until(lambda: len(beats) >= 2, timeout=10)  # a heartbeat a second, during the warm-up
    finally:
        release.set()
        maker.join(30)
        for svc in built:
            svc.close()


def test_frames_whose_observations_never_come_are_failing_not_ok(service, client_session):
    """`tracked` arrives, every `tracks/{id}` is left out (an ACL or a router that does not pass tracks/**): the
    objects go out undecided frame after frame. Health had said ok; now the frames count as failures."""
    got = _collect(client_session)
    _wait_connected(client_session)
    for f in generate(TrackScenario(n_static=3, n_moving=1, n_starting=0, seed=2), 8):
        n = len(got["objects"])
        client_session.put(keys.tracked(NS), encode(f.tracked))  # the close alone
        assert wait_until(lambda: len(got["objects"]) == n + 1, timeout=30)
    health = service.progress.assess(time.monotonic())
    assert health.state == "failing" and "no tracks/* observation" in health.reason


def test_an_observation_on_another_tracks_key_is_refused_and_the_window_keeps_the_real_one(service, client_session):
    """A copy of parked car A's observation moved 3 m and put on track B's key (a publisher the ACL allows only
    tracks/B) had been taken as A's: counted a duplicate, it replaced A's real observation and A was called
    dynamic. Now the key's ID must be the payload's, and a frame's first observation of a track stands."""
    import msgpack as mp

    got = _collect(client_session)
    _wait_connected(client_session)
    frames = list(generate(TrackScenario(n_static=2, n_moving=0, n_starting=0, seed=5), 20))
    a, b = sorted(frames[0].moving)
    for f in frames:
        n = len(got["objects"])
        for o in f.observations:
            client_session.put(keys.track(NS, o.track.object_id), encode(o))
        obs = next(o for o in f.observations if o.track.object_id == a)
        forged = mp.unpackb(encode(obs))
        forged["detection"]["kinematics"]["pose_with_covariance"]["pose"]["position"]["x"] += 3.0 * (f.tracked.header.seq % 2)
        client_session.put(keys.track(NS, b), mp.packb(forged))  # A's ID, B's key
        client_session.put(keys.track(NS, a), mp.packb(forged))  # a second one of A in the frame: dropped
        client_session.put(keys.tracked(NS), encode(f.tracked))
        assert wait_until(lambda: len(got["objects"]) == n + 1, timeout=30)
    assert wait_until(lambda: service.counters.get("rejected") == len(frames))
    assert service.counters.get("rejected.tracks/*") == len(frames)
    # observations and closes reach the worker through two callback threads, so a close may overtake the second A
    # put before it: read after its frame was decided, that one is dropped as late instead (counted as such)
    counts = service.assembler.counts
    assert wait_until(lambda: counts.get("duplicate_observations", 0) + counts.get("late_observations", 0)
                      == len(frames)), counts
    assert counts.get("missing_observations", 0) == 0
    assert got["motion"][a].state == "static" and got["motion"][b].state == "static", got["motion"]
