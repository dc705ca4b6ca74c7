"""``jitterguard feed-tracks``: publish the built-in track-level scenario the way the tracker would.

Per frame: one ``tracks/{id}`` per observed track, then ``tracked`` closing the frame (its
``observed_track_ids`` tell the classifier which stragglers to wait for).
"""

from __future__ import annotations

import time
from dataclasses import replace

from ...runtime import Service, ZenohOptions
from ...schemas import keys
from ...schemas.models import Header
from .synthetic_tracks import FrameRecords, TrackFrame, TrackScenario, generate


def publish_track_frame(service: Service, frame: TrackFrame, ns: str, header: Header | None = None) -> None:
    """Put one frame on the wire as the tracker writes it, in its order (observations, then the closing message),
    under ``header`` if given (a renumbered frame)."""
    observations, tracked = FrameRecords.of(frame).payloads(header)
    for tid, payload in observations:
        service.put(keys.track(ns, tid), payload)
    service.put(keys.tracked(ns), tracked)


class TrackFeeder(Service):
    name = "feed-tracks"

    def __init__(self, opts: ZenohOptions, *, frames: int = 200, rate_hz: float = 10.0, loop: bool = False,
                 seed: int = 0, scenario: TrackScenario | None = None) -> None:
        super().__init__(opts)
        self.frames, self.rate_hz, self.loop, self.seed = frames, rate_hz, loop, seed
        self.scenario = scenario or TrackScenario(seed=seed, rate_hz=rate_hz)
        self.spawn(self._run, "feed")

    def _run(self) -> None:
        """Frames at ``rate_hz``; a loop starts the scenario over with new track IDs, seq and stamp going on (the
        classifier takes a stream whose seq or stamp goes back for a restarted tracker)."""
        period = 1.0 / self.rate_hz
        seq = 0
        loop_no = 0
        stamp0 = time.time_ns()
        next_t = time.monotonic()
        while not self.stop_event.is_set():
            sc = replace(self.scenario, seed=self.seed + loop_no)
            for frame in generate(sc, self.frames):
                if self.stop_event.is_set():
                    return
                header = Header(stamp=stamp0 + round(seq * period * 1e9), frame_id="map", seq=seq)
                publish_track_frame(self, frame, self.ns, header)
                self.counters.inc("frames")  # what the stack's summary calls replayed ("published" counts every put)
                self.last_seq = seq
                seq += 1
                next_t += period
                self.stop_event.wait(max(0.0, next_t - time.monotonic()))
            loop_no += 1
            if not self.loop:
                self.log.info("scenario done (%d frames)", seq)
                self.stop()
                return
