"""``jitterguard feed-tracks``: publish the built-in track-level scenario the way the tracker would.

Per frame: one ``tracks/{id}`` per observed track, then ``tracked`` closing the frame (its
``observed_track_ids`` tell the classifier which stragglers to wait for).
"""

from __future__ import annotations

import time

from ...runtime import Service, ZenohOptions
from ...schemas import keys
from .synthetic_tracks import TrackFrame, TrackScenario, generate


def publish_track_frame(service: Service, frame: TrackFrame, ns: str) -> None:
    """Put one frame on the wire in the tracker's order (observations, then the closing message)."""
    for obs in frame.observations:
        service.put(keys.track(ns, obs.track.object_id), obs)
    service.put(keys.tracked(ns), frame.tracked)


class TrackFeeder(Service):
    name = "feed-tracks"

    def __init__(self, opts: ZenohOptions, *, frames: int = 200, rate_hz: float = 10.0, loop: bool = False,
                 seed: int = 0, scenario: TrackScenario | None = None) -> None:
        super().__init__(opts)
        self.frames, self.rate_hz, self.loop, self.seed = frames, rate_hz, loop, seed
        self.scenario = scenario or TrackScenario(seed=seed, rate_hz=rate_hz)
        self.spawn(self._run, "feed")

    def _run(self) -> None:
        period = 1.0 / self.rate_hz
        seq = 0
        loop_no = 0
        next_t = time.monotonic()
        while not self.stop_event.is_set():
            sc = TrackScenario(**{**self.scenario.__dict__, "seed": self.seed + loop_no})
            for frame in generate(sc, self.frames):
                if self.stop_event.is_set():
                    return
                frame = _renumber(frame, seq)
                publish_track_frame(self, frame, self.ns)
                self.last_seq = seq
                seq += 1
                next_t += period
                self.stop_event.wait(max(0.0, next_t - time.monotonic()))
            loop_no += 1
            if not self.loop:
                self.log.info("scenario done (%d frames)", seq)
                self.stop()
                return


def _renumber(frame: TrackFrame, seq: int) -> TrackFrame:
    """Give a looped frame a fresh, monotonically increasing seq (the classifier drops repeats)."""
    if frame.seq == seq:
        return frame
    header = frame.tracked.header.model_copy(update={"seq": seq})
    obs = [o.model_copy(update={"header": header}) for o in frame.observations]
    tracked = frame.tracked.model_copy(update={"header": header})
    return TrackFrame(seq=seq, stamp_ns=frame.stamp_ns, observations=obs, tracked=tracked, moving=frame.moving)
