"""Frame assembly: stragglers, timeouts, duplicates, upstream restarts."""

from __future__ import annotations

from jitterguard.schemas.models import DetectedObject, Header, TrackedObject, TrackedObjects, TrackObservation, TrackState
from jitterguard.services.classifier.assembly import FrameAssembler

IDS = [f"{i:032x}" for i in range(1, 4)]


class _Assembler(FrameAssembler):
    """The assembler fed with models, as the tests write frames (the service feeds it what it keeps)."""

    def add_observation(self, obs: TrackObservation) -> None:
        self.add_observation_item(obs.header.seq, obs.track.object_id, obs)

    def add_close(self, tracked: TrackedObjects, now: float) -> bool:
        return self.add_close_item(tracked.header.seq, tracked.observed_track_ids, tracked, now,
                                   stamp_ns=tracked.header.stamp)


def ob(seq: int, tid: str) -> TrackObservation:
    return TrackObservation(header=Header(stamp=seq, seq=seq), detection=DetectedObject(), track=TrackState(object_id=tid, x=0, y=0))


def close(seq: int, ids=IDS) -> TrackedObjects:
    return TrackedObjects(header=Header(stamp=seq, seq=seq), objects=[TrackedObject(object_id=i) for i in ids],
                          observed_track_ids=list(ids))


def test_frame_waits_for_stragglers_then_completes():
    fa = _Assembler(straggler_timeout_s=0.05)
    fa.add_observation(ob(0, IDS[0]))
    assert fa.add_close(close(0), now=0.0)
    assert fa.pop_ready(0.01) == []
    fa.add_observation(ob(0, IDS[1]))
    fa.add_observation(ob(0, IDS[2]))
    (frame,) = fa.pop_ready(0.02)
    assert frame.seq == 0 and frame.missing == 0 and len(frame.observations) == 3


def test_timeout_releases_frame_and_counts_missing_and_late():
    fa = _Assembler(straggler_timeout_s=0.05)
    fa.add_close(close(0), now=0.0)
    fa.add_observation(ob(0, IDS[0]))
    (frame,) = fa.pop_ready(0.06)
    assert frame.missing == 2 and fa.counts["missing_observations"] == 2
    fa.add_observation(ob(0, IDS[1]))
    assert fa.counts["late_observations"] == 1


def test_frames_released_in_order_and_duplicates_and_late_closes_dropped():
    fa = _Assembler(straggler_timeout_s=1.0)
    for s in (0, 1):
        for i in IDS:
            fa.add_observation(ob(s, i))
        fa.add_close(close(s), now=0.0)
    assert [f.seq for f in fa.pop_ready(0.0)] == [0, 1]
    assert not fa.add_close(close(1), now=0.0)
    assert not fa.add_close(close(0), now=0.0)
    assert fa.counts["duplicate_or_late_frames"] == 2


def test_upstream_restart_is_followed_once_confirmed():
    fa = _Assembler()
    fa.add_close(close(100, []), now=0.0)
    assert fa.pop_ready(0.0)[0].seq == 100
    assert not fa.add_close(close(0, []), now=0.1) and not fa.add_close(close(1, []), now=0.2)
    assert not fa.add_close(close(2, []), now=0.3)  # three frames, but only 0.2 s of them
    assert fa.add_close(close(3, []), now=0.4)  # 0.3 s: confirmed
    assert fa.counts["upstream_restarts"] == 1 and fa.counts["duplicate_or_late_frames"] == 3
    assert fa.pop_ready(0.4)[0].seq == 3


def test_observations_without_close_do_not_grow_forever():
    fa = _Assembler(max_pending_frames=4)
    for s in range(10):
        fa.add_observation(ob(s, IDS[0]))
    assert fa.counts["orphaned_observations"] == 6


def test_late_is_only_within_the_restart_gap():
    fa = _Assembler()
    fa.add_close(close(50, []), now=0.0)
    fa.pop_ready(0.0)
    assert fa.is_late(50) and fa.is_late(40)
    assert not fa.is_late(51)
    assert not fa.is_late(5)  # far below: an upstream restart, to be decoded


def test_no_giving_up_while_the_caller_is_still_behind():
    fa = _Assembler(straggler_timeout_s=0.05)
    fa.add_close(close(0), now=0.0)
    fa.add_observation(ob(0, IDS[0]))
    assert fa.pop_ready(10.0, give_up=False) == []  # long past the timeout, but stragglers may be queued
    fa.add_observation(ob(0, IDS[1]))
    fa.add_observation(ob(0, IDS[2]))
    (frame,) = fa.pop_ready(10.0, give_up=False)
    assert frame.missing == 0 and "missing_observations" not in fa.counts


def test_a_restarted_seq_with_time_going_on_keeps_the_windows_and_the_confirming_frames_observations():
    """A restarted LiDAR driver or detector under a tracker that keeps its tracks: the tracker copies the scans'
    seq, so `tracked` starts again at seq 0 while its stamps go on. Confirmed, it had reset the core (every window
    back to 1, every object undecided) and, with the old seq near the new, dropped the confirming frame's
    observations as late."""
    from jitterguard.schemas.models import Header
    from jitterguard.services.classifier.adapter import ClassifierAdapter
    from jitterguard.services.classifier.synthetic_tracks import FrameRecords, TrackScenario, generate

    frames = list(generate(TrackScenario(n_static=3, n_moving=1, n_starting=0, seed=1), 24))
    pipe = ClassifierAdapter()
    decided = []

    def send(f, seq: int, t: float) -> None:
        obs, tracked = FrameRecords.of(f).payloads(Header(stamp=f.stamp_ns, frame_id="map", seq=seq))
        pipe.observations([p for _, p in obs])
        pipe.close(tracked, received_at=t)
        for fr in pipe.ready(t + 1.0):
            out = pipe.finish(fr)
            pipe.settle(out)
            decided.append((out.seq, out.decisions.window_length.tolist(), out.missing))

    t = 0.0
    for i in range(15):
        send(frames[i], 10 + i, t)
        t += 0.1
    before = decided[-1][1]
    for k, i in enumerate(range(15, 24)):
        send(frames[i], k, t)  # seq 0, 1, … : within the old stream's restart gap, stamps going on
        t += 0.1
    assert pipe.assembler.counts["source_restarts"] == 1 and "upstream_restarts" not in pipe.assembler.counts
    first = decided[15]  # the frame that confirmed the restart
    assert first[2] == 0  # none of its observations dropped as late
    assert min(first[1]) > min(before)  # the windows went on growing (a reset had set them all to 1)


def test_observations_come_out_in_the_closes_order_whatever_order_they_arrived_in():
    """Zenoh delivers a frame's tracks/{id} in any order; handed on in that order, new tracks took their rows and
    full windows their turn in the calibration's learning differently from run to run (and from the offline
    evaluator, which hands them on in the tracker's order)."""
    ids = [f"{i:032x}" for i in range(1, 9)]
    fa = _Assembler(straggler_timeout_s=1.0)
    for i in reversed(ids[:5]):
        fa.add_observation(ob(0, i))
    fa.add_close(close(0, ids), now=0.0)
    for i in (ids[7], ids[5], ids[6]):
        fa.add_observation(ob(0, i))
    (frame,) = fa.pop_ready(0.0)
    assert [o.track.object_id for o in frame.observations] == ids



def test_a_flood_of_made_up_seqs_from_one_track_does_not_evict_the_frames_being_closed():
    """A publisher allowed one track's key (IDS[2]) puts an observation under each of 65 made-up future seqs per
    frame. The first-begun frame had been evicted — the real one — so every frame was decided without its
    observations and none counted missing. The frames next to the last close stay; the made-up far ones go."""
    fa = _Assembler(max_pending_frames=8, straggler_timeout_s=0.05)
    fa.add_close(close(0, []), now=0.0)
    fa.pop_ready(0.0)
    made_up = 1000
    for s in range(1, 11):
        fa.add_observation(ob(s, IDS[0]))  # the real frame's first observation
        for _ in range(65):
            made_up += 1
            fa.add_observation(ob(made_up, IDS[2]))
        fa.add_observation(ob(s, IDS[1]))  # the rest of the real frame's observations, then its close
        assert fa.add_close(close(s, IDS[:2]), now=float(s))
        (frame,) = fa.pop_ready(float(s))
        assert frame.seq == s and len(frame.observations) == 2 and frame.missing == 0, s
    assert fa.counts["orphaned_observations"] >= 10 * 65 - 8


def test_a_closed_frame_keeps_its_observations_whatever_else_is_opened():
    """A frame whose close has come waits for its stragglers; what it has must not be evicted meanwhile (it had
    been, and the frame was then decided with none of them and nothing counted missing)."""
    fa = _Assembler(max_pending_frames=2, straggler_timeout_s=1.0)
    fa.add_observation(ob(0, IDS[0]))
    fa.add_close(close(0), now=0.0)  # waits for IDS[1], IDS[2]
    for s in range(1, 6):
        fa.add_observation(ob(s, IDS[2]))
    (frame,) = fa.pop_ready(2.0)
    assert len(frame.observations) == 1 and frame.missing == 2


def test_when_every_open_frame_is_closed_the_evicted_ones_observations_count_missing():
    """A worker far behind holds more closed frames than the bound: one must go, and its observations are then
    counted missing when it is decided (they had been counted nowhere)."""
    fa = _Assembler(max_pending_frames=2, straggler_timeout_s=1.0)
    for s in (0, 1, 2):
        fa.add_close(close(s), now=0.0)
        fa.add_observation(ob(s, IDS[0]))  # the third frame's opens a third bucket: every one is closed
    frames = fa.pop_ready(2.0)
    assert [f.seq for f in frames] == [0, 1, 2]
    assert [len(f.observations) for f in frames] == [0, 1, 1]
    assert [f.missing for f in frames] == [3, 2, 2] and fa.counts["orphaned_observations"] == 1
