"""The tracker core: one call per detection frame, numpy in, numpy out, no I/O and no globals.

Per frame (all steps batched over every track / detection):

1. drop a duplicate, a late frame or a jump, and follow a discontinuity only once successive frames confirm it
   (:mod:`jitterguard.stream_order`: time going back resets the tracks; a restarted seq or a long gap keeps them);
2. move the detections from the sensor frame into the world frame with the scan's ego pose, rotating their
   covariances with them (R Σ Rᵀ) and choosing each one's measurement covariance (the detector's or the
   class default's);
3. predict every track to the frame's stamp (CV or CTRV Kalman filters);
4. gate and score every (track, detection) pair as Autoware does, then assign optimally;
5. update the associated tracks, start tentative tracks from the unclaimed detections, confirm, delete;
6. report the confirmed tracks and which detection each of them received, and (``observe_tentative``) the
   tentative tracks observed in the frame with theirs: their detections go out on ``tracks/{id}`` so that the
   classifier's window of a track starts with its first detection, as the tracker's own velocity does.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from ...geometry import cov2_largest_variance, rotate_cov2, sensor_to_world_xy
from ...schemas.wire import Limits
from ...stream_order import StreamGuard, Verdict
from . import kalman
from .association import assign, gate, gate_newborn, near_pairs, overlapping
from .config import NUM_LABELS, ConfigTables, TrackerConfig, default_config
from .arrays import DetectionFrame, FrameResult, TrackSnapshot, WorldDetections
from .kalman import CTRV, STATE_DIM, wrap_pi
from .lifecycle import Confirmation, Seen, TrackTable, new_track_id
from .measurement_scale import MeasurementScale

F64 = NDArray[np.float64]

UNMEASURED_YAW_VAR = 1e6
"""Heading variance given to a detection without a usable heading: the update then leaves the heading alone."""
MIN_MEASURED_YAW_VAR = 1e-6
"""Floor on a detector's heading variance (rad², a σ of 1 mrad, finer than any detector's heading): a variance of
1e-20 is valid on the wire, but the update's ``P − K H P`` then rounded a track's heading variance below zero, and
the classifier's reader refused every ``tracked`` frame that carried it (9 of 60 frames lost, counted only there)."""


MIN_LABEL_PROB = 1e-3
"""Floor on a detection's class probability (as the adapter reads it): a zero vote left a new track's votes all zero,
and their argmax, UNKNOWN, then replaced the detected class."""


def _screened(f: DetectionFrame, limits: Limits) -> tuple[DetectionFrame, NDArray[np.bool_]]:
    """The frame with what a broken detector or pose source can put in it made harmless, and which of its
    detections the tracker may use at all (association and births).

    Unusable: a non-finite ego pose, centre, height, size or area, a world position (z too: the sensor's plus the
    detection's, each within the wire's bound, had made every ``tracked`` frame one its readers refuse) beyond
    ``max_abs_coordinate_m`` or a length, width or height beyond ``max_dimension_m`` (what every reader of
    ``tracked`` refuses; a box 1e30 m wide also made every pair of tracks a candidate overlap) or below 0 (a box
    all of whose sides were negative had a positive area: it was tracked and published so), or an exact
    repeat of an earlier detection of the frame (same centre and class). Taken, such a detection had started a
    NaN track, and NaN in the sweep of :func:`~.association.near_pairs` left every other detection of the frame
    without its track (each object got a new tentative one every frame); a NaN height or size stayed in its
    track's running estimate for good; more than ``max_candidates`` copies of one box kept that many confirmed
    tracks of one object, and a thousand new IDs a frame. Repaired, the detection still counts: a class the
    tracker does not know (label outside 0–7) is UNKNOWN (it had raised IndexError, and −1 had read as a
    pedestrian); a non-finite heading is unavailable (orientation 0); a position covariance with a non-finite
    entry, a negative variance or an x-y block whose larger eigenvalue exceeds ``max_variance`` (turned into the
    world it would leave the wire's bounds: :func:`~.adapter.world_detections`) is not used (the class default is,
    as for a detection without one), nor a non-finite or negative heading variance; a non-finite twist, or one
    faster than ``max_abs_speed_mps`` on the ground (1000 m/s on each sensor axis is 1414 m/s on one world axis),
    is no twist; a non-finite existence counts as 0
    and a class probability below :data:`MIN_LABEL_PROB` (or non-finite) as that floor. On well-formed input
    this changes nothing.
    """
    lbl = f.label.astype(np.int64)
    label = np.where((lbl >= 0) & (lbl < NUM_LABELS), lbl, 0).astype(np.int8)
    yaw_ok = np.isfinite(f.yaw)
    max_abs_coordinate_m, max_dimension_m = limits.max_abs_coordinate_m, limits.max_dimension_m
    with np.errstate(invalid="ignore", over="ignore"):  # non-finite rows are refused by the finiteness terms
        cov_ok = (np.isfinite(f.cov_xx) & np.isfinite(f.cov_xy) & np.isfinite(f.cov_yy)
                  & (f.cov_xx >= 0.0) & (f.cov_yy >= 0.0)
                  & (cov2_largest_variance(f.cov_xx, f.cov_xy, f.cov_yy) <= limits.max_variance))
        twist_ok = np.isfinite(f.vx) & np.isfinite(f.vy) & (np.hypot(f.vx, f.vy) <= limits.max_abs_speed_mps)
    yaw_var_ok = np.isfinite(f.var_yaw) & (f.var_yaw >= 0.0)
    prob = np.where(np.isfinite(f.label_prob), f.label_prob, 0.0)
    existence = np.where(np.isfinite(f.existence), f.existence, 0.0)
    clean = (label == f.label).all() and yaw_ok.all() and cov_ok.all() and twist_ok.all() and yaw_var_ok.all() \
        and (prob >= MIN_LABEL_PROB).all() and (prob <= 1.0).all() and (existence >= 0.0).all() \
        and (existence <= 1.0).all()
    if not clean:
        f = replace(
            f, label=label, yaw=np.where(yaw_ok, f.yaw, 0.0),
            orientation=np.where(yaw_ok, f.orientation, 0).astype(np.int8),
            cov_xx=np.where(cov_ok, f.cov_xx, 0.0), cov_xy=np.where(cov_ok, f.cov_xy, 0.0),
            cov_yy=np.where(cov_ok, f.cov_yy, 0.0), has_cov=f.has_cov & cov_ok,
            var_yaw=np.where(yaw_var_ok, f.var_yaw, 0.0), vx=np.where(twist_ok, f.vx, 0.0),
            vy=np.where(twist_ok, f.vy, 0.0), has_twist=f.has_twist & twist_ok,
            label_prob=np.clip(prob, MIN_LABEL_PROB, 1.0), existence=np.clip(existence, 0.0, 1.0),
        )
    pose_ok = all(np.isfinite(v) for v in (f.ego_x, f.ego_y, f.ego_z, f.ego_yaw))
    usable = (np.isfinite(f.x) & np.isfinite(f.y) & np.isfinite(f.z) & np.isfinite(f.area)
              & (f.length >= 0.0) & (f.length <= max_dimension_m) & (f.width >= 0.0) & (f.width <= max_dimension_m)
              & (f.height >= 0.0) & (f.height <= max_dimension_m))  # NaN compares False
    if not pose_ok:  # nothing can be placed in the world (and math.cos(inf) raises): the tracks coast
        usable[:] = False
        f = replace(f, ego_x=0.0, ego_y=0.0, ego_z=0.0, ego_yaw=0.0)
    elif usable.any():
        with np.errstate(invalid="ignore", over="ignore"):
            wx, wy = sensor_to_world_xy(f.x, f.y, f.ego_x, f.ego_y, f.ego_yaw)
            wz = f.z + f.ego_z  # the wire bounds each z, not their sum
        usable &= ((np.abs(wx) <= max_abs_coordinate_m) & (np.abs(wy) <= max_abs_coordinate_m)
                   & (np.abs(wz) <= max_abs_coordinate_m))
    idx = np.flatnonzero(usable)
    if idx.size > 1:  # exact repeats: the first of each (x, y, label) stays (idx breaks ties: the sort is stable)
        order = idx[np.lexsort((idx, f.label[idx], f.y[idx], f.x[idx]))]
        a, b = order[:-1], order[1:]
        same = (f.x[b] == f.x[a]) & (f.y[b] == f.y[a]) & (f.label[b] == f.label[a])
        usable[b[same]] = False
    return f, usable


def _seen(f: DetectionFrame, det: WorldDetections, idx: NDArray[np.intp]) -> Seen:
    """What the detections ``idx`` tell their tracks besides the filtered position."""
    return Seen(f.label[idx], f.label_prob[idx], f.existence[idx], det.z[idx],
                np.stack([f.length[idx], f.width[idx], f.height[idx]], axis=1), f.orientation[idx])


class FrameRejected(Exception):
    """A frame the tracker will not process; ``reason`` is ``duplicate``, ``out_of_order`` or ``jump``."""

    def __init__(self, reason: str, seq: int, last_seq: int) -> None:
        self.reason = reason
        super().__init__(f"{reason} frame: seq {seq} after seq {last_seq}")


class TrackerCore:
    """Multi-object tracker state and its per-frame update (see the module docstring)."""

    def __init__(self, config: TrackerConfig | None = None,
                 id_factory: Callable[[], str] = new_track_id) -> None:
        self.config = config or default_config()
        self.tables: ConfigTables = self.config.tables()
        self.confirmation = Confirmation(self.tables.confirm_hits, self.config.confirm_min_existence)
        self.id_factory = id_factory
        online = self.config.measurement_scale == "online" and self.config.measurement_covariance == "detector"
        self.scale = MeasurementScale(self.config.measurement_scale_window) if online else None
        self._obs_window = self.scale.window if self.scale is not None else 0
        self.tracks = TrackTable(self._obs_window)
        self.guard = StreamGuard(self.config.stream)
        self._period_s: float | None = None  # the stream's last frame interval (between the two frames before)

    # ----------------------------------------------------------------------------------------------- API

    def reset(self) -> list[str]:
        """Forget every track (a source restart); returns the IDs dropped."""
        dropped = list(self.tracks.ids)
        self.tracks = TrackTable(self._obs_window)  # the measurement scale stays: it describes the detector
        self.guard.reset()
        self._period_s = None
        return dropped

    @property
    def last_seq(self) -> int | None:
        return self.guard.last_seq

    def check_order(self, seq: int, stamp_ns: int, now_s: float | None = None) -> Verdict:
        """Judge a frame by its header (before it is read, if the caller likes); raise :class:`FrameRejected` for
        one that is dropped. ``now_s``: the receiver's clock, for confirming a discontinuity (None: frames only)."""
        verdict = self.guard.admit(seq, stamp_ns, now_s)
        if not verdict.accepted:
            last = self.guard.last_seq
            raise FrameRejected(verdict.value, seq, last if last is not None else -1)
        return verdict

    def step(self, frame: DetectionFrame, verdict: Verdict | None = None) -> FrameResult:
        """Process one detection frame; raises :class:`FrameRejected` (state untouched) for a dropped one.
        ``verdict``: what :meth:`check_order` already said of this frame's header."""
        if verdict is None:
            verdict = self.check_order(frame.seq, frame.stamp_ns)
        confirmed_deleted = int(np.count_nonzero(self.tracks.confirmed)) if verdict is Verdict.REWOUND else 0
        deleted: list[str] = self.reset() if verdict is Verdict.REWOUND else []
        last = self.guard.last_stamp_ns
        period_s = (frame.stamp_ns - last) * 1e-9 if last is not None and verdict is Verdict.NEXT else None
        self.guard.accept(frame.seq, frame.stamp_ns)

        cfg, tb, tr = self.config, self.tables, self.tracks
        stamp = frame.stamp_ns
        frame, usable = _screened(frame, cfg.limits)
        with np.errstate(invalid="ignore", over="ignore"):  # unusable rows may hold inf; none of them is read
            det = self._to_world(frame)
        m = len(frame)
        use = None if usable.all() else np.flatnonzero(usable)  # the detections association and births may take

        # ---- predict every track to this frame's stamp
        n = len(tr)
        if n:
            dt = np.maximum((stamp - tr.t_ns) * 1e-9, 0.0)
            lbl = tr.label.astype(np.intp)
            tr.x, tr.P = kalman.predict(
                tr.x, tr.P, dt, tr.model, tb.q_acc[lbl], tb.q_acc_lat[lbl], tb.q_yaw[lbl],
                tb.q_yaw_rate_acc[lbl],
            )
            tr.t_ns[:] = stamp

        # ---- associate
        det_pos = np.stack([det.x, det.y], axis=1)
        det_pos_cov = det.R[:, :2, :2]
        yaw_valid = frame.orientation > 0
        sel = slice(None) if use is None else use
        cand = gate(
            tr.x[:, :2], tr.label, tr.x[:, 2], tr.P[:, :2, :2],
            det_pos[sel], frame.label[sel], frame.area[sel], det.yaw[sel], yaw_valid[sel], det_pos_cov[sel],
            tb, cfg.mahalanobis_gate, cfg.mahalanobis_covariance == "innovation", cfg.score_threshold,
            cfg.gate_min_variance, cfg.max_candidates,
        )
        if use is not None:
            cand = replace(cand, cols=use[cand.cols])
        stale = self._stale(stamp, self._period_s)  # the interval before this frame: a pause is this one's
        self._period_s = period_s
        if stale.any():
            cand = cand.subset(~stale[cand.rows])
        rows, cols = assign(n, m, cand)
        rows, cols = self._second_detections(frame, det, stamp, rows, cols, stale, usable)
        claimed = cols.copy()  # a detection whose track is deleted below must not start a twin of it

        # ---- update the associated tracks
        confirmed = 0  # tracks that reach the output with this frame
        if rows.size:
            z = np.stack([det.x[cols], det.y[cols], det.yaw[cols]], axis=1)
            xr, Pr = kalman.update(tr.x[rows], tr.P[rows], z, det.R[cols])
            lbl = tr.label[rows].astype(np.intp)
            kalman.clamp(xr, tr.model[rows], tb.max_speed[lbl], tb.max_yaw_rate[lbl])
            tr.x[rows] = xr
            tr.P[rows] = Pr
            confirmed = tr.record_hits(rows, stamp, _seen(frame, det, cols), self.confirmation, cfg.shape_smoothing)
            self._keep_observations(frame, det, rows, cols)

        # ---- delete what the lifecycle rules expire (before births: a newborn never expires at once)
        if n:
            keep = ~tr.expired(stamp, cfg.tentative_max_gap_s, cfg.max_coast_s, cfg.max_position_stddev)
            # a filter gone non-finite (deleted above) must not enter the sweep: NaN there hid every overlap
            sane = np.isfinite(tr.x[:, :3]).all(axis=1) & np.isfinite(tr.dims[:, :2]).all(axis=1)
            o = slice(None) if sane.all() else np.flatnonzero(sane)
            keep[o] &= ~overlapping(tr.x[o, :2], tr.label[o], tr.dims[o, 1], tr.hits[o], tb.can_assign,
                                    cfg.overlap_factor, cfg.max_candidates, yaw=tr.x[o, 2], length=tr.dims[o, 0],
                                    min_iou=cfg.overlap_min_iou, min_iou_unknown=cfg.overlap_min_iou_unknown,
                                    confirmed=tr.confirmed[o])
            keep_rows = np.flatnonzero(keep)
            if keep_rows.size < n:
                if self.scale is not None:  # what the deleted tracks have not given yet, before their rows go
                    self.scale.evict(tr, np.flatnonzero(~keep))
                remap = np.full(n, -1, dtype=np.intp)
                remap[keep_rows] = np.arange(keep_rows.size)
                confirmed_deleted += int(np.count_nonzero(tr.confirmed & ~keep))
                deleted += tr.keep(keep)
                new_rows = remap[rows]
                alive = new_rows >= 0
                rows, cols = new_rows[alive], cols[alive]

        # ---- births from the detections nobody claimed (a newborn's detection is its first observation)
        free = usable.copy()
        free[claimed] = False
        new = np.flatnonzero(free)
        born: list[str] = []
        if new.size:
            start = len(tr)
            born = self._birth(frame, det, new)
            confirmed += int(np.count_nonzero(tr.confirmed[start:]))
            self._keep_observations(frame, det, np.arange(start, start + new.size), new)
            rows = np.concatenate([rows, np.arange(start, start + new.size)])
            cols = np.concatenate([cols, new])
        if self.scale is not None:
            self.scale.learn(tr, stamp * 1e-9)  # what this frame taught serves the next one

        snapshot, obs_track, obs_det, withheld, tentative, tentative_det = self._snapshot(rows, cols)
        return FrameResult(
            seq=frame.seq,
            stamp_ns=stamp,
            detections=det,
            tracks=snapshot,
            obs_track=obs_track,
            obs_det=obs_det,
            born=born,
            deleted=deleted,
            confirmed=confirmed,
            confirmed_deleted=confirmed_deleted,
            reset=verdict is Verdict.REWOUND,
            source_restarted=verdict is Verdict.RESTARTED,
            jumped=verdict is Verdict.JUMPED,
            withheld=withheld,
            tentative=tentative,
            tentative_det=tentative_det,
        )

    def apply_static_hints(self, track_ids: Sequence[str], mean_x: Sequence[float],
                           mean_y: Sequence[float]) -> tuple[int, int]:
        """Autoware's setStaticState for each known ID: zero velocity, position = the classifier's mean.

        Returns how many were applied and how many were refused as implausible: a mean farther from the track
        than the tracker would associate a detection of its class (``max_dist_matrix``) is not the window of
        this track — one message must not move a confirmed track across the map. Hints for tracks already
        deleted are neither.
        """
        where = self.tracks.row_of()
        known = [(where[t], x, y) for t, x, y in zip(track_ids, mean_x, mean_y) if t in where]
        if not known:
            return 0, 0
        rows = np.array([p[0] for p in known], dtype=np.intp)
        hx, hy = np.array([p[1] for p in known]), np.array([p[2] for p in known])
        lbl = self.tracks.label[rows].astype(np.intp)
        near = np.hypot(hx - self.tracks.x[rows, 0], hy - self.tracks.x[rows, 1]) <= self.tables.max_dist[lbl, lbl]
        if near.any():
            kalman.set_static(self.tracks.x, self.tracks.P, rows[near], hx[near], hy[near])
        return int(near.sum()), int((~near).sum())

    # ------------------------------------------------------------------------------------------ helpers

    def _to_world(self, f: DetectionFrame) -> WorldDetections:
        """Sensor frame -> world frame, with each detection's measurement covariance over (x, y, yaw)."""
        cfg, tb = self.config, self.tables
        x, y = sensor_to_world_xy(f.x, f.y, f.ego_x, f.ego_y, f.ego_yaw)
        yaw = wrap_pi(f.yaw + f.ego_yaw)
        cxx, cxy, cyy = rotate_cov2(f.cov_xx, f.cov_xy, f.cov_yy, f.ego_yaw)

        m = len(f)
        lbl = f.label.astype(np.intp)
        R = np.zeros((m, 3, 3))
        # class defaults: along / across the measured heading (isotropic where there is no heading)
        rl, rt = tb.r_long[lbl] ** 2, tb.r_lat[lbl] ** 2
        no_yaw = f.orientation == 0
        iso = np.maximum(rl, rt)
        rl = np.where(no_yaw, iso, rl)
        rt = np.where(no_yaw, iso, rt)
        ch, sh = np.cos(yaw), np.sin(yaw)
        R[:, 0, 0] = ch * ch * rl + sh * sh * rt
        R[:, 1, 1] = sh * sh * rl + ch * ch * rt
        R[:, 0, 1] = R[:, 1, 0] = ch * sh * (rl - rt)
        yaw_var = tb.r_yaw[lbl] ** 2
        if cfg.measurement_covariance == "detector":
            use = f.own_covariance()
            if use.any():
                floor = cfg.min_position_variance
                rxx, rxy, ryy = cxx, cxy, cyy
                if self.scale is not None:  # what the detector's variances are off by, as learnt so far
                    rxx, rxy, ryy = rotate_cov2(*self.scale.rescale(f.x, f.y, f.cov_xx, f.cov_xy, f.cov_yy, f.label),
                                                f.ego_yaw)
                # at most the variance past which a track is deleted: a detection reporting more (the wire allows
                # 1e6 m²) had started a track that the next frame deleted, having taken its detection — the object
                # was never tracked, and got a new ID every other frame
                cap = max(cfg.max_position_stddev ** 2, floor)
                R[use, 0, 0] = np.clip(rxx[use], floor, cap)
                R[use, 1, 1] = np.clip(ryy[use], floor, cap)
                lim = 0.999 * np.sqrt(R[use, 0, 0] * R[use, 1, 1])  # keep it positive definite
                R[use, 0, 1] = R[use, 1, 0] = np.clip(rxy[use], -lim, lim)
                yaw_var = np.where(use & (f.var_yaw > 0.0),
                                   np.clip(f.var_yaw, MIN_MEASURED_YAW_VAR, UNMEASURED_YAW_VAR), yaw_var)
        R[:, 2, 2] = np.where(no_yaw, UNMEASURED_YAW_VAR, yaw_var)
        c, s = np.cos(f.ego_yaw), np.sin(f.ego_yaw)
        return WorldDetections(x=x, y=y, z=f.z + f.ego_z, yaw=yaw, cov_xx=cxx, cov_xy=cxy, cov_yy=cyy, R=R,
                               vx=c * f.vx - s * f.vy, vy=s * f.vx + c * f.vy)

    def _keep_observations(self, f: DetectionFrame, det: WorldDetections, rows: NDArray[np.intp],
                           cols: NDArray[np.intp]) -> None:
        """Keep each track's detection with its reported covariance (world frame) for the measurement scale;
        one without a covariance of its own breaks the track's run (nothing to learn the detector's from)."""
        if self.scale is None or rows.size == 0:
            return
        own = f.has_cov[cols] & (f.cov_xx[cols] > 0.0) & (f.cov_yy[cols] > 0.0)
        self.tracks.obs_since[rows[~own]] = 0
        self.tracks.obs_seen[rows[~own]] = 0
        rows, cols = rows[own], cols[own]
        k = rows.size
        values = np.stack([det.x[cols], det.y[cols], det.cov_xx[cols], det.cov_xy[cols], det.cov_yy[cols],
                           np.full(k, f.stamp_ns * 1e-9), np.full(k, f.ego_x), np.full(k, f.ego_y)], axis=1)
        self.tracks.record_observations(rows, values)

    def _stale(self, stamp: int, period_s: float | None) -> NDArray[np.bool_]:
        """Tracks already past their lifetime (``tentative_max_gap_s`` / ``max_coast_s`` unseen) by more than the
        stream's frame interval: ones a frame would have deleted had the stream not paused. They take no detection
        — after a 3 s pause of the stream a coasting car's ID had gone to whatever stood near its prediction, with
        its velocity — and are deleted with the frame's expiry. Within one interval the rule is the frame's
        expiry alone (at 2 Hz every tentative track is 0.5 s unseen when its next detection comes)."""
        tr, cfg = self.tracks, self.config
        if not len(tr) or period_s is None:
            return np.zeros(len(tr), dtype=bool)
        return tr.expired(stamp - int(period_s * 1e9), cfg.tentative_max_gap_s, cfg.max_coast_s, np.inf)

    def _second_detections(self, f: DetectionFrame, det: WorldDetections, stamp: int, rows: NDArray[np.intp],
                           cols: NDArray[np.intp], stale: NDArray[np.bool_], usable: NDArray[np.bool_]
                           ) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
        """``rows``/``cols`` with each track born on the previous detection (one hit, no velocity yet) that the
        main gate left without one paired, where it can, with a detection no track took, within the reach of its
        class's top speed (:func:`~.association.gate_newborn`): a fast object's second detection."""
        tr = self.tracks
        taken = np.zeros(len(tr), dtype=bool)
        taken[rows] = True
        newborn = np.flatnonzero((tr.hits == 1) & ~taken & ~stale)
        if newborn.size == 0:
            return rows, cols
        free_mask = usable.copy()
        free_mask[cols] = False
        free = np.flatnonzero(free_mask & f.has_twist)  # few: what no track took (the rest of the frame is skipped)
        if free.size == 0:
            return rows, cols
        dpos = np.stack([det.x, det.y], axis=1)
        # neither a detection nor a newborn within the main gate of an older track: that is the older track's
        # object seen off its prediction (a jumpy box, a twin), not a fast newcomer
        older = np.flatnonzero(tr.hits > 1)
        if older.size:
            reach = float(self.tables.max_dist.max())
            _, near = near_pairs(tr.x[older, :2], dpos[free], reach)
            free = np.delete(free, np.unique(near))
            nb_i, _ = near_pairs(tr.x[newborn, :2], tr.x[older, :2], reach)
            newborn = np.delete(newborn, np.unique(nb_i))
            if newborn.size == 0 or free.size == 0:
                return rows, cols
        since_birth = np.maximum((stamp - tr.born_ns) * 1e-9, 0.0)
        cand = gate_newborn(tr.x[:, :2], tr.label, tr.x[:, 2], (tr.model == CTRV) & (tr.orientation > 0), newborn,
                            since_birth, dpos, np.stack([det.vx, det.vy], axis=1), f.label, f.area, free,
                            self.tables, self.config.max_candidates)
        r2, c2 = assign(len(tr), len(f), cand)
        if r2.size == 0:
            return rows, cols
        self._start_from_pair(r2, dpos[c2], since_birth[r2])
        return np.concatenate([rows, r2]), np.concatenate([cols, c2])

    def _start_from_pair(self, rows: NDArray[np.intp], second: F64, dt: F64) -> None:
        """Give newborns paired with a far second detection the velocity the two detections imply, before their
        update: predicted to that velocity, they stand where the second detection is.

        Why: a newborn is predicted at zero velocity, and one update from there takes about two thirds of the
        displacement as velocity (the prior's zero mean weighs in). A car first seen near its class's top speed
        (39–45 m/s at 10 Hz) was then predicted short by more than the main gate's 2 m at its third detection,
        started over, and was never tracked. These pairs passed :func:`~.association.gate_newborn` (the
        displacement lies along the box and agrees with the detector's own twist), so the displacement is the
        object's motion; the main gate's pairs, which jitter alone can explain, keep the filter's start."""
        tr = self.tracks
        ok = dt > 0.0
        rows, second, dt = rows[ok], second[ok], dt[ok]
        if rows.size == 0:
            return
        birth = tr.x[rows, :2]  # predicted at zero velocity: where each was born
        v = (second - birth) / dt[:, None]
        ctrv = tr.model[rows] == CTRV
        c, s = np.cos(tr.x[rows, 2]), np.sin(tr.x[rows, 2])
        speed = v[:, 0] * c + v[:, 1] * s  # CTRV: signed speed along the heading (negative: driving backwards)
        tr.x[rows, 3] = np.where(ctrv, speed, v[:, 0])
        tr.x[rows, 4] = np.where(ctrv, tr.x[rows, 4], v[:, 1])
        step = np.where(ctrv[:, None], speed[:, None] * np.stack([c, s], axis=1), v) * dt[:, None]
        tr.x[rows, :2] = birth + step

    def _birth(self, f: DetectionFrame, det: WorldDetections, idx: NDArray[np.intp]) -> list[str]:
        """Start a tentative track from each detection in ``idx`` (zero velocity, the class's spread)."""
        tb = self.tables
        k = idx.size
        lbl = f.label[idx].astype(np.intp)
        x0 = np.zeros((k, STATE_DIM))
        x0[:, 0] = det.x[idx]
        x0[:, 1] = det.y[idx]
        x0[:, 2] = det.yaw[idx]
        P0 = np.zeros((k, STATE_DIM, STATE_DIM))
        P0[:, :3, :3] = det.R[idx]
        P0[:, 2, 2] = np.minimum(P0[:, 2, 2], (0.5 * np.pi) ** 2)
        model = tb.model[lbl]
        pv = tb.p0_vel[lbl] ** 2
        P0[:, 3, 3] = pv
        P0[:, 4, 4] = np.where(model == CTRV, tb.p0_yaw_rate[lbl] ** 2, pv)
        return self.tracks.append(x0, P0, f.stamp_ns, model, _seen(f, det, idx), self.confirmation,
                                  self.id_factory)

    def _snapshot(self, rows: NDArray[np.intp], cols: NDArray[np.intp]
                  ) -> tuple[TrackSnapshot, NDArray[np.intp], NDArray[np.intp], int, TrackSnapshot, NDArray[np.intp]]:
        """Copy out the confirmed tracks — at most ``limits.max_objects``, so that no reader downstream refuses
        the frame (the classifier reads ``tracked`` under the same limit): beyond it the coasting tracks unseen
        the longest are withheld — and map this frame's (track row, detection) pairs onto them; with
        ``observe_tentative`` also the tentative tracks observed this frame and their detections."""
        tr = self.tracks
        conf = np.flatnonzero(tr.confirmed)
        withheld = conf.size - self.config.limits.max_objects
        if withheld > 0:
            seen_now = np.zeros(len(tr), dtype=bool)
            seen_now[rows] = True
            # observed first (never more than the detections, which the same limit bounds), then the most
            # recently updated; stable, so equal stamps keep their order
            rank = np.lexsort((-tr.last_update_ns[conf], ~seen_now[conf]))
            conf = np.sort(conf[rank[: self.config.limits.max_objects]])
        pos_in_conf = np.full(len(tr), -1, dtype=np.intp)
        pos_in_conf[conf] = np.arange(conf.size)
        obs = pos_in_conf[rows]
        ok = obs >= 0
        order = np.argsort(obs[ok], kind="stable")
        obs_track = obs[ok][order]
        obs_det = cols[ok][order]
        tent = ~tr.confirmed[rows] if self.config.observe_tentative else np.zeros(rows.size, dtype=bool)
        t_order = np.argsort(rows[tent], kind="stable")  # birth order, as the confirmed ones
        return (self._copy_out(conf), obs_track, obs_det, max(withheld, 0),
                self._copy_out(rows[tent][t_order]), cols[tent][t_order])

    def _copy_out(self, idx: NDArray[np.intp]) -> TrackSnapshot:
        """The tracks of rows ``idx`` as a :class:`TrackSnapshot` (copies, world frame)."""
        tr = self.tracks
        x = tr.x[idx]
        P = tr.P[idx]
        vel, vel_cov, w, wvar = kalman.world_velocity(x, P, tr.model[idx])
        lbl = tr.label[idx]
        votes = tr.votes[idx]
        total = np.maximum(votes.sum(axis=1), 1e-12)
        return TrackSnapshot(
            ids=[tr.ids[i] for i in idx],
            label=lbl.copy(),
            label_prob=np.clip(votes[np.arange(idx.size), lbl.astype(np.intp)] / total, 0.0, 1.0),
            existence=np.clip(tr.existence[idx], 0.0, 1.0),
            x=x[:, 0].copy(),
            y=x[:, 1].copy(),
            z=tr.z[idx].copy(),
            yaw=x[:, 2].copy(),
            pose_cov=P[:, :3, :3].copy(),
            vel=vel,
            vel_cov=vel_cov,
            yaw_rate=w,
            yaw_rate_var=wvar,
            dims=tr.dims[idx].copy(),
            orientation=tr.orientation[idx].copy(),
            hits=tr.hits[idx].copy(),
            last_update_ns=tr.last_update_ns[idx].copy(),
            born_ns=tr.born_ns[idx].copy(),
        )
