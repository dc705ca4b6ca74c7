"""The tracker's measurement scale: it learns, without labels, how far the detector's position variances are
off, and its filter then smooths the boxes as much as their real noise asks (docs/tracker.md)."""

from __future__ import annotations

import numpy as np

from jitterguard.services.tracker.arrays import DetectionFrame
from jitterguard.services.tracker.config import default_config
from jitterguard.services.tracker.core import TrackerCore
from jitterguard.services.tracker.kalman import STATE_DIM
from jitterguard.services.tracker.lifecycle import OBS_CHANNELS, TrackTable

T0 = 1_700_000_000_000_000_000
CAR = 1


def _parked_frames(seed: int, n_frames: int, true_sigma: float, reported_sigma: float, n_cars: int = 30):
    """Parked cars 10–40 m around a still sensor at 10 Hz whose boxes err by ``true_sigma`` per axis while the
    detector reports ``reported_sigma``."""
    rng = np.random.default_rng(seed)
    r, a = rng.uniform(10.0, 40.0, n_cars), rng.uniform(-np.pi, np.pi, n_cars)
    centre = np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
    for k in range(n_frames):
        xy = centre + rng.normal(0.0, true_sigma, centre.shape)
        var = np.full(n_cars, reported_sigma ** 2)
        yield DetectionFrame(seq=k, stamp_ns=T0 + k * 100_000_000, ego_x=0.0, ego_y=0.0, ego_yaw=0.0,
                             x=xy[:, 0], y=xy[:, 1], yaw=np.zeros(n_cars), label=np.full(n_cars, CAR),
                             length=np.full(n_cars, 4.5), width=np.full(n_cars, 1.9),
                             cov_xx=var, cov_xy=np.zeros(n_cars), cov_yy=var.copy(), has_cov=np.ones(n_cars, bool))


def _run(mode: str, seed: int = 3) -> tuple[TrackerCore, float]:
    """Mean speed the tracker reports for the parked cars over the last 5 s of 20."""
    core = TrackerCore(default_config().model_copy(update={"measurement_scale": mode}))
    speeds = []
    for k, f in enumerate(_parked_frames(seed, 200, true_sigma=0.3, reported_sigma=0.1)):
        res = core.step(f)
        if k >= 150:
            speeds.append(np.hypot(res.tracks.vel[:, 0], res.tracks.vel[:, 1]))
    return core, float(np.concatenate(speeds).mean())


def test_it_learns_how_far_the_reported_variances_are_off_and_the_velocities_calm_down() -> None:
    online, speed_online = _run("online")
    off, speed_off = _run("off")
    assert off.scale is None
    model = online.scale.online.refit()
    # σ reported 3× too small: variances 9× (along and across the line of sight, established vehicle tracks)
    assert np.all((model.scale[0, :, :2, 0] > 6.0) & (model.scale[0, :, :2, 0] < 12.0))
    # the filter now weighs the boxes by their real noise: parked cars' reported speeds fall by a third or more
    assert speed_online < 0.67 * speed_off
    # and a tracker restart keeps what it learnt about the detector
    online.reset()
    assert online.scale.model is model or np.allclose(online.scale.model.scale, model.scale)


def test_the_gate_and_update_use_the_scaled_variance_and_the_kept_detection_the_reported_one() -> None:
    core, _ = _run("online")
    k = core.scale.model.scale[0, 0, 1, 0]
    f = next(_parked_frames(7, 1, true_sigma=0.3, reported_sigma=0.1, n_cars=1))
    rng = float(np.hypot(f.x[0], f.y[0]))
    band = int(core.scale.model.bands(np.array([rng]))[0])
    ku, kv = core.scale.model.scale[0, :, band, 0]
    det = core._to_world(f)
    u = np.array([f.x[0], f.y[0]]) / rng
    v = np.array([-u[1], u[0]])
    R = det.R[0, :2, :2]
    assert np.isclose(u @ R @ u, ku * 0.01, rtol=1e-9) and np.isclose(v @ R @ v, kv * 0.01, rtol=1e-9)
    assert np.isclose(det.cov_xx[0], 0.01) and k > 1.0  # what is kept for learning is what the detector reported


def test_track_table_keeps_each_tracks_latest_detections_in_order_through_deletions() -> None:
    table = TrackTable(obs_window=4)
    from jitterguard.services.tracker.lifecycle import Confirmation, Seen

    seen = Seen(np.array([CAR, CAR], np.int8), np.ones(2), np.ones(2), np.zeros(2), np.ones((2, 3)),
                np.zeros(2, np.int8))
    table.append(np.zeros((2, STATE_DIM)), np.zeros((2, STATE_DIM, STATE_DIM)), 0, np.zeros(2, np.int8), seen, Confirmation.uniform(3))
    for i in range(6):  # row 0 gets 6 detections, row 1 gets 3
        rows = np.array([0, 1]) if i < 3 else np.array([0])
        table.record_observations(rows, np.full((rows.size, OBS_CHANNELS), float(i)) + rows[:, None] * 100)
    assert table.latest_observations(np.array([0]), 4)[0, :, 0].tolist() == [2.0, 3.0, 4.0, 5.0]
    assert table.latest_observations(np.array([1]), 3)[0, :, 0].tolist() == [100.0, 101.0, 102.0]
    assert table.obs_since.tolist() == [6, 3]
    table.keep(np.array([False, True]))
    assert table.latest_observations(np.array([0]), 3)[0, :, 0].tolist() == [100.0, 101.0, 102.0]
