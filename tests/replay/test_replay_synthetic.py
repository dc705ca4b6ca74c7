"""The synthetic world as a replay source (skipped while jitterguard.sim lacks the piece a test needs)."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from jitterguard.services.replay.frames import DetectionFrame, ScanFrame, SourceError
from replay.helpers import FakeClock
from jitterguard.services.replay.runner import ReplayPlan, run_replay
from jitterguard.services.replay.sources import SourceOptions, open_source


def _has(mod: str) -> bool:
    try:
        return importlib.util.find_spec(mod) is not None
    except ModuleNotFoundError:
        return False


needs_world = pytest.mark.skipif(
    not (_has("jitterguard.sim.world") and _has("jitterguard.sim.detection_model")), reason="jitterguard.sim not there yet"
)
needs_lidar = pytest.mark.skipif(not _has("jitterguard.sim.lidar"), reason="jitterguard.sim.lidar not there yet")


def _positions(frame: DetectionFrame) -> list[tuple[float, float]]:
    return [(o.kinematics.pose_with_covariance.pose.position.x, o.kinematics.pose_with_covariance.pose.position.y) for o in frame.objects]


@needs_world
def test_synthetic_detections_are_deterministic_per_seed_and_per_pass() -> None:
    opts = SourceOptions(level="detections", seed=4, duration_s=1.5)
    a = open_source("synthetic:parking-street", opts)
    first, second = list(a.frames()), list(a.frames())
    other = list(open_source("synthetic:parking-street", SourceOptions(level="detections", seed=5, duration_s=1.5)).frames())
    assert a.info.kind == "detections" and len(first) == a.info.num_frames == 15
    assert all(isinstance(f, DetectionFrame) for f in first)
    assert [_positions(f) for f in first] == [_positions(f) for f in second]  # a loop replays the same noise
    assert [_positions(f) for f in first] != [_positions(f) for f in other]
    stamps = [f.stamp_ns for f in first]
    assert all(b - a == 100_000_000 for a, b in zip(stamps, stamps[1:]))


@needs_world
def test_synthetic_detections_window_sees_the_same_frames_as_the_full_run() -> None:
    src = open_source("synthetic:intersection", SourceOptions(level="detections", seed=1, duration_s=1.0))
    full = list(src.frames())
    tail = list(src.frames(start=6))
    assert [_positions(f) for f in tail] == [_positions(f) for f in full[6:]]


@needs_world
def test_synthetic_detections_loop_through_the_runner_with_increasing_seq() -> None:
    src = open_source("synthetic:mixed", SourceOptions(level="detections", seed=0, duration_s=0.5))
    out: list[tuple[int, int]] = []
    run_replay(src, ReplayPlan(rate=None, loop=True, passes=2), lambda f, seq, t: out.append((seq, t)), clock=FakeClock())
    assert [s for s, _ in out] == list(range(10))
    assert all(b[1] > a[1] for a, b in zip(out, out[1:]))


@needs_world
def test_unknown_level_and_bad_duration_are_source_errors() -> None:
    with pytest.raises(SourceError, match="--level"):
        open_source("synthetic:mixed", SourceOptions(level="boxes"))
    with pytest.raises(SourceError, match="positive"):
        open_source("synthetic:mixed", SourceOptions(level="detections", duration_s=0))


@needs_world
@needs_lidar
def test_synthetic_scans_have_points_rings_and_the_sensor_pose() -> None:
    from jitterguard.sim.world import make_scenario

    src = open_source("synthetic:parking-street", SourceOptions(seed=2, duration_s=0.3))
    frames = list(src.frames())
    assert len(frames) == 3 and all(isinstance(f, ScanFrame) for f in frames)
    f = frames[1]
    assert f.fields == ("x", "y", "z", "intensity", "ring") and f.points.dtype == np.float32
    assert f.points.shape[0] > 1000 and np.isfinite(f.points).all()
    rings = f.points[:, 4]
    assert rings.min() >= 0 and rings.max() <= 31 and len(np.unique(rings)) > 16  # HDL-32E
    gt = make_scenario("parking-street", 2, duration_s=0.3).frame(1)
    assert (f.pose.x, f.pose.y, f.pose.yaw) == pytest.approx((gt.ego_x, gt.ego_y, gt.ego_yaw))
    # the sensor is mounted above flat ground: the lowest returns lie one mount height below it
    assert np.percentile(f.points[:, 2], 5) == pytest.approx(-f.pose.z, abs=0.15)


@needs_world
@needs_lidar
def test_synthetic_scans_repeat_exactly_across_passes_and_differ_across_seeds() -> None:
    src = open_source("synthetic:diagonal-lot", SourceOptions(seed=1, duration_s=0.2, lidar="vlp16"))
    a, b = list(src.frames()), list(src.frames(start=1))
    np.testing.assert_array_equal(a[1].points, b[0].points)
    assert a[0].points[:, 4].max() <= 15  # VLP-16
    c = list(open_source("synthetic:diagonal-lot", SourceOptions(seed=2, duration_s=0.2, lidar="vlp16")).frames())
    assert a[0].points.shape != c[0].points.shape or not np.array_equal(a[0].points, c[0].points)


@needs_world
@needs_lidar
def test_unknown_lidar_is_a_source_error_listing_the_sensors() -> None:
    with pytest.raises(SourceError, match="hdl32e"):
        open_source("synthetic:mixed", SourceOptions(lidar="hdl64"))


@needs_world
@pytest.mark.parametrize("duration_s, frames", [(0.96, 9), (0.3, 3), (0.1, 1)])
def test_the_probe_announces_the_frames_the_source_yields(duration_s: float, frames: int) -> None:
    """The probe counts whole frames as the world does (it rounded: 0.96 s at 10 Hz announced 10 of 9)."""
    from jitterguard.services.replay.sources import probe_source

    opts = SourceOptions(level="detections", duration_s=duration_s, rate_hz=10.0)
    src = open_source("synthetic:mixed", opts)
    assert probe_source("synthetic:mixed", opts).num_frames == src.info.num_frames == frames
    assert len(list(src.frames())) == frames


@needs_world
def test_a_scenario_shorter_than_one_frame_is_a_source_error() -> None:
    """0.07 s at 10 Hz holds no frame: the probe said 1 and the stack came up on a source that published nothing."""
    from jitterguard.services.replay.sources import probe_source

    opts = SourceOptions(level="detections", duration_s=0.07, rate_hz=10.0)
    with pytest.raises(SourceError, match="no whole frame"):
        probe_source("synthetic:mixed", opts)
    with pytest.raises(SourceError, match="no whole frame"):
        open_source("synthetic:mixed", opts)
