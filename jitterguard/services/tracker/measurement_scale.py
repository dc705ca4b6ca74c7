"""The tracker's measurement noise, learnt from its own tracks: how far the detector's reported position
variances are off (docs/tracker.md, "The measurement scale").

Why: the Kalman filter's gain and the association gate take each detection's position covariance as the
truth. A detector that reports σ 2× too small (the shipped one on real scans before its score-binned
recalibration; the honest noise model copies that) makes the filter follow every wobble of the boxes, and the velocities it publishes — what the speed
threshold, and a planner, read — wobble with them. The classifier already learns that error from its windows
without labels (:mod:`jitterguard.services.classifier.calibration`); the tracker learns it the same way, with
the same estimator, from the detections each track received: blocks of ``window`` consecutive detections of
one track, their residuals about a constant-velocity line along and across the line of sight from the sensor,
robustly pooled per class group, axis and range band, slow blocks only, with forgetting. The scale of
*established* tracks then multiplies every detection's reported covariance along and across the line of sight
before the gate and the update (at association time nobody knows yet which track, young or old, a detection
belongs to). Each kept detection carries its reported covariance, so what is learnt is always reported →
true, whatever scale was applied.

Pure: numpy in, numpy out; time is the data's stamps.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ...geometry import scale_beam_covariance
from ..classifier.calibration import (
    AXES,
    GROUPS,
    MIN_BLOCK,
    NoiseModel,
    OnlineCalibration,
    band_names,
    block_moments,
    group_of_labels,
)
from .lifecycle import TrackTable

F64 = NDArray[np.float64]


class MeasurementScale:
    """The online estimate and what it does to a frame's detections (see the module docstring)."""

    def __init__(self, window: int = 10, band_edges_m: tuple[float, ...] = (20.0, 40.0),
                 prior_blocks: float = 20.0, half_life_s: float = 600.0) -> None:
        self.window = window
        self.online = OnlineCalibration(band_edges_m, prior_blocks, half_life_s, window)

    @property
    def model(self) -> NoiseModel:
        return self.online.current

    def gauges(self) -> dict[str, float]:
        """Flat heartbeat gauges of the scales applied (established tracks),
        ``measurement_scale.{group}.{axis}.{band}``, and the evidence behind them,
        ``measurement_scale.effective_blocks``."""
        model = self.model
        out = {"measurement_scale.effective_blocks": round(self.online.effective_blocks, 3)}
        for gi, g in enumerate(GROUPS):
            for ai, axis in enumerate(AXES):
                for bi, band in enumerate(band_names(model.band_edges_m)):
                    out[f"measurement_scale.{g}.{axis}.{band}"] = float(model.scale[gi, ai, bi, 0])
        return out

    def rescale(self, x: F64, y: F64, cxx: F64, cxy: F64, cyy: F64, labels: NDArray[np.integer]
                ) -> tuple[F64, F64, F64]:
        """Sensor-frame covariances of detections at sensor-frame (x, y), scaled along the line of sight by the
        established scale k_u of their class group and range band and across it by k_v
        (:func:`~jitterguard.geometry.scale_beam_covariance`)."""
        model = self.model
        g = group_of_labels(labels)
        band = model.bands(np.hypot(x, y))
        return scale_beam_covariance(x, y, cxx, cxy, cyy, model.scale[g, 0, band, 0], model.scale[g, 1, band, 0])

    def learn(self, tracks: TrackTable, stamp_s: float) -> None:
        """Pool every track whose kept detections have turned over since it was last pooled; refit when due."""
        self.online.advance(stamp_s)
        full = np.flatnonzero(tracks.obs_since >= self.window)
        self._pool(tracks, full, self.window)
        self.online.model()

    def evict(self, tracks: TrackTable, gone: NDArray[np.intp]) -> None:
        """Pool what tracks about to be deleted have not given yet (blocks of at least MIN_BLOCK)."""
        n = np.minimum(tracks.obs_since[gone], self.window)  # never more than it has: since ≤ seen
        for k in np.unique(n[n >= MIN_BLOCK]).tolist():
            self._pool(tracks, gone[n == k], int(k))

    def _pool(self, tracks: TrackTable, rows: NDArray[np.intp], n: int) -> None:
        if rows.size == 0:
            return
        blk = tracks.latest_observations(rows, n)
        t = blk[..., 5]
        ok = (t[:, -1] > t[:, 0]) & (blk[..., 2] > 0).all(axis=1) & (blk[..., 4] > 0).all(axis=1)
        tracks.obs_since[rows] = 0
        if not ok.any():
            return
        blk = blk[ok]
        mom = block_moments(t[ok], blk[..., 0:2], blk[..., 2:5], blk[..., 6:8])
        young = (tracks.obs_seen[rows[ok]] - n) < self.window  # the block starts among the track's first
        self.online.add(group_of_labels(tracks.label[rows[ok]]), mom, young)
