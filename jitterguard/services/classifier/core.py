"""The motion classifier core: one sliding observation window per track, decided once per frame.

Pure: numpy arrays in, numpy arrays out, no I/O, no clock, no globals. The live service and the offline
evaluator both drive this class, so what is measured offline is what runs live.

Windows live in dense ``(capacity, window_size)`` ring buffers indexed by a row per track; track IDs map to
rows through a sorted ID array and ``np.searchsorted``, so the per-frame path has no per-track Python loop.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace

import numpy as np
from numpy.typing import NDArray

from ...schemas.models import ClassifierConfig
from .calibration import GROUPS, MIN_BLOCK, NoiseModel, OnlineCalibration, block_moments, group_of_labels
from .statistics import (CHANNELS, WindowStats, calibrated_statistics, chi2_2_threshold, jump_ratio, split_halves,
                         window_statistics)

F64 = NDArray[np.float64]
IDS = NDArray[np.bytes_]

UNDECIDED, STATIC, DYNAMIC = 0, 1, 2
STATE_NAMES = ("undecided", "static", "dynamic")
_NUM_LABELS = 8
JUMP_VETO_MIN_VEHICLE = 6
"""Observations a vehicle's window needs before the jump veto looks at its shape (other classes: a full window).
A detector re-places a car's box most often as the car comes out of occlusion, when its track is young, and six
observations give a step and a hinge two a side; a walker's young window says too little about its shape (on the
tuning seeds the veto from six observations for every class missed 0.9–2.7 points more walkers; for vehicles
alone it cut static vehicles called moving in the lot with the detector by a fifth and missed no more walkers —
docs/classifier.md 'The jump veto')."""
_VEHICLE = GROUPS.index("vehicle")
RATE_WINDOW_FLOOR = 10
"""Fewest observations a slow stream's window is shortened to (the paper's window): at 2 Hz the default's two
seconds are four frames, too few to split into halves worth testing; ten is what the paper tested."""
RATE_FRAMES = 14
"""Latest frames the stream's rate is measured over: the Theil–Sen slope of their stamps against their seqs (the
median over every pair of frames of time per frame between them), which neither a dropped or late frame nor a
stamp's jitter moves. The median of successive intervals had: with ±20–30 ms of jitter on a 10 Hz driver, or
frames alternating 50 / 150 ms or delivered in pairs 2 ms apart, it swung the window between 10 and 20
observations frame to frame, and each shrink dropped every track's oldest observations."""
MAX_STRIDE = 100
"""Largest stride (a 1 kHz stream at the 10 Hz reference): bounds the ratio of a nonsense stamp pair."""
LEARN_BLOCKS_PER_FRAME = 32
"""Filled windows pooled into the online calibration per frame at most (more when a backlog builds: 1/W of it),
the rest kept for the next frames. Every track of a scene born in one frame — a stack start, a replay — fills its
window in the same later frame, and again every W frames after; pooling 1000 windows at once took 0.1–0.7 s
(~0.1 ms each), a stall every 2 s that the frames after it queued behind. Spread, a frame pools at most ~3 ms;
at a steady 1000 tracks (50 windows a frame at W = 20) the backlog stays under W × 50 rows."""


def stride_for_interval(config: ClassifierConfig, interval_s: float | None, current: int = 1) -> int:
    """Every how many frames a track's window takes an observation on a stream whose frames are ``interval_s``
    apart: 1 below 1.6 × ``window_reference_hz`` for a stream taking every frame (16 Hz at 10 Hz: the ratio must
    move 0.6 from the stride in force, below); on a faster stream the nearest whole ratio of
    its rate to the reference (20 Hz at 10 Hz: every second frame), so the window keeps the span it was
    chosen with (the default's 2 s) at the cost per second of the reference rate — successive detections of a
    fast sensor err alike, so the frames skipped add little. ``current`` (the stride in force) is kept while the
    ratio is within 0.6 of it — a rate at a rounding edge does not flip it — and while the rate is not known (a
    recording that started over is measured afresh: its first frame does not fall back to every frame)."""
    if config.window_reference_hz is None:
        return 1
    if interval_s is None or not interval_s > 0:
        return current
    frames = interval_s * config.window_reference_hz  # reference frames per frame (a denormal: 1/frames is inf)
    ratio = min(1.0 / frames, float(MAX_STRIDE)) if frames > 0 else float(MAX_STRIDE)
    if abs(ratio - current) < 0.6:
        return current
    return max(1, int(math.floor(ratio + 0.5)))


def window_for_interval(config: ClassifierConfig, interval_s: float | None) -> int:
    """The window a stream whose window observations are ``interval_s`` apart gets (the frame interval times
    the :func:`stride_for_interval`): ``window_size`` observations at ``window_reference_hz`` or faster; on a
    slower stream proportionally fewer — the same span in time — but at least min(:data:`RATE_WINDOW_FLOOR`,
    ``window_size``) and ``min_window``; ``window_size`` when the reference is off or the interval not yet
    known. The default window was chosen as 2 s at 10 Hz, and a fixed count would stretch that span on a slow
    stream (20 frames of nuScenes' 2 Hz key frames are 10 s)."""
    w = config.window_size
    if config.window_reference_hz is None or interval_s is None or not interval_s > 0:
        return w
    low = max(config.min_window, min(RATE_WINDOW_FLOOR, w))
    frames = interval_s * config.window_reference_hz  # reference frames per window observation
    span = w / frames if frames > 0 else math.inf  # observations of the reference span at this rate
    return int(min(w, max(low, round(span)))) if math.isfinite(span) else w


@dataclass(frozen=True)
class Observations:
    """One frame of associated detections, world frame, one row per track (IDs unique within the frame).

    ``cxx, cxy, cyy`` are the detection's 2x2 position covariance already rotated into the world frame;
    ``speed`` is the tracker's speed estimate (used by the velocity-threshold baseline only);
    ``sensor_x, sensor_y`` the sensor's world position at ``stamp_ns`` (the frame's ``ego_pose``: the origin
    of the line of sight along which the calibration splits its scales); ``published_ids``: the IDs of the
    frame's ``tracked`` objects (None: every observed track is published) — a tracker with ``observe_tentative``
    also observes tentative tracks, whose windows fill like any other, but only tracks that were ever published
    get a decision out and teach the calibration (a clutter return the tracker never confirms must not).
    """

    track_ids: IDS
    labels: NDArray[np.int64]
    x: F64
    y: F64
    cxx: F64
    cxy: F64
    cyy: F64
    speed: F64
    stamp_ns: int = 0
    seq: int = 0
    sensor_x: float = 0.0
    sensor_y: float = 0.0
    published_ids: IDS | None = None

    @staticmethod
    def from_lists(track_ids: list[str], labels, x, y, cxx, cxy, cyy, speed=None, stamp_ns: int = 0, seq: int = 0,
                   sensor_x: float = 0.0, sensor_y: float = 0.0,
                   published_ids: IDS | None = None) -> "Observations":
        n = len(track_ids)
        f = lambda v: np.asarray(v, dtype=np.float64).reshape(n)  # noqa: E731
        return Observations(
            track_ids=np.asarray(track_ids, dtype="S32").reshape(n),
            labels=np.asarray(labels, dtype=np.int64).reshape(n),
            x=f(x), y=f(y), cxx=f(cxx), cxy=f(cxy), cyy=f(cyy),
            speed=f(np.zeros(n) if speed is None else speed),
            stamp_ns=stamp_ns, seq=seq, sensor_x=float(sensor_x), sensor_y=float(sensor_y),
            published_ids=None if published_ids is None else np.asarray(published_ids, dtype="S32"),
        )

    def subset(self, mask: NDArray[np.bool_]) -> "Observations":
        """The rows where ``mask`` holds."""
        return replace(self, track_ids=self.track_ids[mask], labels=self.labels[mask], x=self.x[mask],
                       y=self.y[mask], cxx=self.cxx[mask], cxy=self.cxy[mask], cyy=self.cyy[mask],
                       speed=self.speed[mask])

    def __len__(self) -> int:
        return int(self.track_ids.shape[0])


@dataclass(frozen=True)
class Decisions:
    """The classifier's output for the tracks of one frame, aligned with the input order."""

    track_ids: IDS
    state: NDArray[np.int8]  # UNDECIDED / STATIC / DYNAMIC
    z_x: F64
    z_y: F64
    chi2: F64
    alpha: F64
    threshold: F64
    window_length: NDArray[np.int64]
    mean_x: F64
    mean_y: F64
    speed: F64
    published: NDArray[np.bool_]  # the track has been in ``tracked`` (a tentative one has not: no decision goes out)
    vetoed: NDArray[np.bool_]  # the test rejected H0 but the jump veto called the window static (not on the wire)

    def state_names(self) -> list[str]:
        return [STATE_NAMES[s] for s in self.state.tolist()]

    def subset(self, mask: NDArray[np.bool_]) -> "Decisions":
        """The rows where ``mask`` holds."""
        return Decisions(**{k: v[mask] for k, v in self.__dict__.items()})


@dataclass
class _Table:
    """Per-row storage; grows by doubling. ``win`` is (capacity, window, 5) over ``CHANNELS``."""

    window: int
    capacity: int
    win: F64 = field(init=False)
    head: NDArray[np.int64] = field(init=False)
    count: NDArray[np.int64] = field(init=False)
    label: NDArray[np.int64] = field(init=False)
    since: NDArray[np.int64] = field(init=False)  # observations not yet given to the calibration
    seen: NDArray[np.int64] = field(init=False)  # observations of the track so far
    published: NDArray[np.bool_] = field(init=False)  # the track has been in ``tracked`` (it may teach the calibration)
    fast_since: F64 = field(init=False)  # baseline: stamp [s] since which the speed is above threshold (NaN: not)
    reject_since: F64 = field(init=False)  # the test: stamp [s] since which it rejects H0 (NaN: it does not)
    last: dict[str, np.ndarray] = field(init=False)

    _LAST = {
        "state": np.int8, "z_x": np.float64, "z_y": np.float64, "chi2": np.float64, "alpha": np.float64,
        "threshold": np.float64, "mean_x": np.float64, "mean_y": np.float64, "speed": np.float64,
        "stamp_ns": np.int64, "seq": np.int64, "vetoed": np.bool_,
    }

    def __post_init__(self) -> None:
        self.win = np.zeros((self.capacity, self.window, len(CHANNELS)))
        self.head = np.zeros(self.capacity, dtype=np.int64)
        self.count = np.zeros(self.capacity, dtype=np.int64)
        self.label = np.zeros(self.capacity, dtype=np.int64)
        self.since = np.zeros(self.capacity, dtype=np.int64)
        self.seen = np.zeros(self.capacity, dtype=np.int64)
        self.published = np.zeros(self.capacity, dtype=bool)
        self.fast_since = np.full(self.capacity, np.nan)
        self.reject_since = np.full(self.capacity, np.nan)
        self.last = {k: np.zeros(self.capacity, dtype=t) for k, t in self._LAST.items()}

    def grow(self, capacity: int) -> None:
        extra = capacity - self.capacity
        self.win = np.concatenate([self.win, np.zeros((extra, self.window, len(CHANNELS)))])
        self.head = np.concatenate([self.head, np.zeros(extra, dtype=np.int64)])
        self.count = np.concatenate([self.count, np.zeros(extra, dtype=np.int64)])
        self.label = np.concatenate([self.label, np.zeros(extra, dtype=np.int64)])
        self.since = np.concatenate([self.since, np.zeros(extra, dtype=np.int64)])
        self.seen = np.concatenate([self.seen, np.zeros(extra, dtype=np.int64)])
        self.published = np.concatenate([self.published, np.zeros(extra, dtype=bool)])
        self.fast_since = np.concatenate([self.fast_since, np.full(extra, np.nan)])
        self.reject_since = np.concatenate([self.reject_since, np.full(extra, np.nan)])
        self.last = {k: np.concatenate([v, np.zeros(extra, dtype=v.dtype)]) for k, v in self.last.items()}
        self.capacity = capacity

    def reset_rows(self, rows: NDArray[np.int64]) -> None:
        self.head[rows] = 0
        self.count[rows] = 0
        self.since[rows] = 0
        self.seen[rows] = 0
        self.published[rows] = False
        self.fast_since[rows] = np.nan
        self.reject_since[rows] = np.nan
        for v in self.last.values():
            v[rows] = 0

    def rewindow(self, window: int) -> None:
        """Change the window length keeping each row's newest min(N, window) observations in order."""
        keep = np.minimum(self.count, window)
        k = np.arange(window)[None, :]  # k-th newest
        src = (self.head[:, None] - 1 - k) % self.window
        dst = keep[:, None] - 1 - k  # the newest goes to slot keep-1
        ok = k < keep[:, None]
        rows = np.broadcast_to(np.arange(self.capacity)[:, None], ok.shape)[ok]
        new = np.zeros((self.capacity, window, len(CHANNELS)))
        new[rows, dst[ok]] = self.win[rows, src[ok]]
        self.win = new
        self.window = window
        self.count = keep
        self.since = np.minimum(self.since, keep)
        self.head = keep % window

    def ordered(self, rows: NDArray[np.int64], n: int) -> F64:
        """The newest ``n`` observations of each row, oldest first: ``(len(rows), n, channels)``."""
        k = np.arange(n)[None, :]
        slots = (self.head[rows, None] - n + k) % self.window
        flat = (rows[:, None] * self.window + slots).ravel()  # one gather of whole observations (2–3× faster than
        c = self.win.shape[-1]  # indexing rows and slots as two axes)
        return self.win.reshape(-1, c).take(flat, axis=0).reshape(rows.shape[0], n, c)


def _running_since(since: F64, on: NDArray[np.bool_], now_s: float) -> F64:
    """The clock of a condition that must hold for a while (the baseline's sustain, the test's hold): where it
    holds, the stamp since which it has held without a break (``now_s`` where it starts); NaN where it does not.
    A clock that started after ``now_s`` (the stamps went back) starts again at ``now_s``: kept, it had held every
    rejection back until the stamps caught up with it — a car moving all along was called static (zero twist) for
    as long as time had gone back, even with no hold at all."""
    return np.where(on, np.where(np.isnan(since) | (since > now_s), now_s, since), np.nan)


MAX_VARIANCE = 1e100
"""Largest reported variance a window takes [m²]: the statistic's products of variances overflow beyond it (a
variance of 1e300 had saturated z and called the track dynamic). The wire's bound is far below (1e6)."""
MAX_CORRELATION = 1.0 + 1e-6
"""Largest |cxy| / sqrt(cxx·cyy) a window takes: the wire's bound (a covariance that is not positive
semi-definite has a negative variance along some axis; pooled, it had taught the calibration a scale of 25)."""


def _valid_observations(obs: "Observations") -> NDArray[np.bool_]:
    """Which rows of ``obs`` a window may take: a finite position and a positive semi-definite covariance whose
    variances are at most :data:`MAX_VARIANCE` — what the wire contract lets through. Another one (a broken
    upstream; a caller of the core need not be the wire) is left out of the window as if the track had not been
    observed this frame: taken, a NaN position had gone out as the static position of the window's mean for a
    whole window, and a NaN, negative or overflowing variance had made the statistic — and the decision —
    whatever its saturation said."""
    with np.errstate(invalid="ignore", over="ignore"):  # NaN compares False
        spread = np.sqrt(obs.cxx) * np.sqrt(obs.cyy)  # as the wire computes it
        return (np.isfinite(obs.x) & np.isfinite(obs.y) & (obs.cxx >= 0.0) & (obs.cxx <= MAX_VARIANCE)
                & (obs.cyy >= 0.0) & (obs.cyy <= MAX_VARIANCE) & (np.abs(obs.cxy) <= MAX_CORRELATION * spread))


class MotionClassifierCore:
    """Sliding windows per track ID and the static/dynamic decision of DESIGN.md "The motion classifier"."""

    def __init__(self, config: ClassifierConfig | None = None, capacity: int = 256,
                 calibration_model: NoiseModel | None = None, online: OnlineCalibration | None = None) -> None:
        """``calibration_model``: the scales for ``calibration: file`` (the adapter reads the file);
        ``online``: an online calibration to continue (e.g. from the previous recording of one drive)."""
        self._config = config or ClassifierConfig()
        self._table = _Table(window=window_for_interval(self._config, None), capacity=max(8, capacity))
        self._clock: tuple[int, int] | None = None  # (stamp ns, seq) of the last frame
        # (stamp ns, seq) of the latest frames with distinct stamps, for the rate (:attr:`frame_interval_s`)
        self._clocks: deque[tuple[int, int]] = deque(maxlen=RATE_FRAMES)
        self._stride = 1  # every how many frames a window takes an observation (:func:`stride_for_interval`)
        self._ids: IDS = np.empty(0, dtype="S32")  # sorted
        self._id_rows: NDArray[np.int64] = np.empty(0, dtype=np.int64)
        self._free: list[int] = list(range(self._table.capacity - 1, -1, -1))
        self._set_tables(self._config)
        self._online = online if online is not None else self.make_online(self._config)
        self._file_model = calibration_model
        self.check_config(self._config)
        self._state_cache: tuple[tuple, dict] | None = None
        self._pending: NDArray[np.int64] = np.empty(0, dtype=np.int64)  # rows whose filled windows wait for learn
        self._learn_due = False  # a frame has come since :meth:`learn` last pooled

    # ------------------------------------------------------------------ configuration

    @property
    def config(self) -> ClassifierConfig:
        return self._config

    def configure(self, config: ClassifierConfig, calibration_model: NoiseModel | None = None) -> None:
        """Apply a new config; a changed window length keeps each track's newest observations. The online
        calibration keeps what it learnt unless its range bands change; ``calibration_model`` replaces the
        scales used with ``calibration: file`` (the last one given stays otherwise)."""
        self.check_config(config, calibration_model)
        self.learn(everything=True)  # what filled under the old window length is learnt with it
        if calibration_model is not None:
            self._file_model = calibration_model
        old = self._config
        self._config = config
        self._set_tables(config)
        if config.mode != old.mode:  # a hold runs on one test's rejections: another test starts its clock afresh
            self._table.reject_since[:] = np.nan
        if (config.calibration_range_bands_m != old.calibration_range_bands_m
                or config.calibration_prior_blocks != old.calibration_prior_blocks):
            self._online = self.make_online(config)
        self._online.half_life_s = config.calibration_half_life_s
        self._follow_rate(exact=True)

    def check_config(self, config: ClassifierConfig, calibration_model: NoiseModel | None = None) -> None:
        """Raise ``ValueError`` if :meth:`configure` would refuse ``config`` (changes nothing)."""
        if config.calibration == "file" and calibration_model is None and self._file_model is None:
            raise ValueError("calibration 'file' needs the file's scales (load calibration_file first)")

    @staticmethod
    def make_online(config: ClassifierConfig) -> OnlineCalibration:
        """A fresh online calibration for ``config`` (its range bands, prior, half-life and window)."""
        return OnlineCalibration(tuple(config.calibration_range_bands_m), config.calibration_prior_blocks,
                                 config.calibration_half_life_s, config.window_size)

    def _set_tables(self, config: ClassifierConfig) -> None:
        """The per-class settings as arrays indexed by label, so a frame looks them up for all tracks at once."""
        def per_label(value_for: Callable[[int], float]) -> F64:
            return np.array([value_for(label) for label in range(_NUM_LABELS)], dtype=np.float64)

        self._alpha_table = per_label(config.alpha_for)
        self._speed_table = per_label(config.speed_threshold_for)
        self._sustain_table = per_label(config.sustain_for)
        self._hold_table = per_label(config.hold_for)
        self._view_table = per_label(config.view_slide_for)

    # ------------------------------------------------------------------ the window and the stream's rate

    @property
    def window(self) -> int:
        """Observations a window holds now: ``window_size``, or fewer for a slow stream
        (:func:`window_for_interval`)."""
        return self._table.window

    @property
    def stride(self) -> int:
        """Every how many frames a window takes an observation: 1, or more on a stream faster than the
        reference (:func:`stride_for_interval`)."""
        return self._stride

    @property
    def frame_interval_s(self) -> float | None:
        """The stream's time between frames: the Theil–Sen slope of the latest :data:`RATE_FRAMES` frames' stamps
        against their ``seq`` (frames with no observations skipped between two updates count); None before two
        frames with different stamps."""
        c = np.asarray(self._clocks, dtype=np.float64)
        if len(c) < 2:
            return None
        i, j = np.triu_indices(len(c), 1)
        return float(np.median((c[j, 0] - c[i, 0]) * 1e-9 / (c[j, 1] - c[i, 1])))

    def _observe_clock(self, stamp_ns: int, seq: int) -> None:
        last, self._clock = self._clock, (stamp_ns, seq)
        if last is None:
            self._clocks.append((stamp_ns, seq))
            return
        if stamp_ns == last[0]:
            return
        if stamp_ns < last[0] or seq <= last[1]:  # a recording that started over: its rate is measured afresh
            self._clocks.clear()
        self._clocks.append((stamp_ns, seq))

    def _follow_rate(self, exact: bool = False) -> float | None:
        """Set the stride and the window for the stream's measured rate; the window is resized for a change of
        two observations or more (a rate at a rounding edge does not flip it), of any size when ``exact`` (a new
        config). Returns the frame interval it used."""
        interval = self.frame_interval_s
        self._stride = stride_for_interval(self._config, interval, self._stride)
        target = window_for_interval(self._config, None if interval is None else interval * self._stride)
        if exact or abs(target - self._table.window) >= 2:
            self._resize(target)
        return interval

    def _takes(self, rows: NDArray[np.int64], stamp_s: float, interval: float | None) -> NDArray[np.bool_] | None:
        """Which of ``rows`` take this frame's observation into their windows (None: all — stride 1, or every
        row's turn): a track seen for the first time, or whose newest window observation is at least stride − ½
        frames of ``interval`` old (after a dropped frame the next one is taken: no hole, the phase moves; a
        stamp that went back restarts it)."""
        if self._stride == 1 or interval is None:
            return None
        t = self._table
        newest = t.win[rows, (t.head[rows] - 1) % t.window, 5]
        age = stamp_s - newest
        take = (t.count[rows] == 0) | (age < 0) | (age >= (self._stride - 0.5) * interval)
        return None if take.all() else take

    def _resize(self, window: int) -> None:
        """Give every window ``window`` slots (each keeps its newest observations); the online calibration's
        blocks follow."""
        if window == self._table.window:
            return
        self.learn()  # what filled under the old length is learnt with it
        self._table.rewindow(window)
        self._online.set_window(window)

    # ------------------------------------------------------------------ calibration

    @property
    def online_calibration(self) -> OnlineCalibration:
        """The online estimator (learning whenever ``calibration`` is ``online``)."""
        return self._online

    def noise_model(self) -> NoiseModel:
        """The scales and serial correlation the test uses now (the prior when calibration is off)."""
        mode = self._config.calibration
        if mode == "online":
            return self._online.current
        if mode == "file" and self._file_model is not None:
            return self._file_model
        return NoiseModel.prior(tuple(self._config.calibration_range_bands_m))

    def calibration_state(self) -> dict:
        """What the calibration uses now (a ``CalibrationState`` map): :meth:`NoiseModel.to_mapping` at this
        window size, the mode, and the online estimator's counters (blocks pooled, too fast to pool,
        down-weighted as outliers). Rebuilt only when the model or the config changed."""
        model = self.noise_model()
        key = (id(model), self._config.calibration, self._config.effective_n, self.window,
               self._online.counts["blocks"])
        if self._state_cache is None or self._state_cache[0] != key:
            # the evidence behind the scales in force: the online estimator's only while it supplies them (a file's
            # are the file's blocks, the prior's none; the idle estimator's had been shown beside a file's scales)
            evidence = (self._online.effective_blocks if self._config.calibration == "online"
                        else float(model.blocks.sum()) / 2)
            state = {"mode": self._config.calibration, "effective_n": self._config.effective_n,
                     **model.to_mapping(self.window), "counts": dict(self._online.counts),
                     "effective_blocks": round(evidence, 3),
                     "scale_dof": round(model.scale_dof, 3) if math.isfinite(model.scale_dof) else None}
            self._state_cache = (key, state)
        return self._state_cache[1]

    def learn(self, *, everything: bool = False) -> None:
        """Pool windows that filled into the online calibration — at most :data:`LEARN_BLOCKS_PER_FRAME` (or 1/W
        of the backlog) once per frame, oldest first; ``everything``: all of them now — and refit it when due.
        Kept off the decision: the service calls it (through the adapter's ``settle``) once ``objects`` is out,
        so a frame is decided with what the frames before it taught — a frame or a few later than the data
        allowed, which moves nothing a refit every ``refit_period_s`` would show, and keeps pooling and fitting
        (several ms at 200 tracks) out of the frame's latency. :meth:`update` calls it first if nobody did."""
        if self._config.calibration != "online":
            self._pending, self._learn_due = self._pending[:0], False
            return
        if self._learn_due or everything:
            self._learn_due = False
            rows = self._pending
            budget = rows.shape[0] if everything else max(LEARN_BLOCKS_PER_FRAME, -(-rows.shape[0] // self._table.window))
            rows, self._pending = rows[:budget], rows[budget:]
            t = self._table
            rows = rows[(t.count[rows] >= t.window) & (t.since[rows] >= t.window)]  # still full (not evicted)
            if rows.size:
                self._harvest(rows, np.full(rows.shape[0], t.window))
        self._online.model()  # refits when due

    def _harvest(self, rows: NDArray[np.int64], lengths: NDArray[np.int64]) -> None:
        """Give the newest ``lengths[i]`` observations of ``rows[i]`` to the online calibration as one block
        each (only rows with at least MIN_BLOCK observations spread in time); marks them used."""
        t = self._table
        t.since[rows] = 0
        ok = (lengths >= MIN_BLOCK) & t.published[rows]
        rows, lengths = rows[ok], lengths[ok]
        for n in np.unique(lengths).tolist():
            sel = rows[lengths == n]
            blk = t.ordered(sel, int(n))
            times = blk[..., 5]
            spread = times[:, -1] > times[:, 0]
            if not spread.any():
                continue
            blk = blk[spread]
            mom = block_moments(times[spread], blk[..., 0:2], blk[..., 2:5], blk[..., 6:8],
                                variance_floor=self._config.variance_floor)
            young = blk[:, 0, 8] < t.window  # the block starts among the track's first W observations
            self._online.add(group_of_labels(t.label[sel[spread]]), mom, young)

    # ------------------------------------------------------------------ ID -> row mapping

    def track_ids(self) -> list[str]:
        return [i.decode() for i in self._ids.tolist()]

    def _positions(self, ids: IDS) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
        """Where each of ``ids`` sits in the sorted ID array (a binary search each: no sort of strings), and
        whether it is there; call only with known IDs present (``self._ids`` not empty)."""
        pos = np.minimum(np.searchsorted(self._ids, ids), self._ids.shape[0] - 1)
        return pos, self._ids[pos] == ids

    def _lookup(self, ids: IDS) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
        if self._ids.shape[0] == 0:
            return np.full(ids.shape[0], -1, dtype=np.int64), np.zeros(ids.shape[0], dtype=bool)
        pos, found = self._positions(ids)
        return np.where(found, self._id_rows[pos], -1), found

    def _allocate(self, new_ids: IDS) -> NDArray[np.int64]:
        n = new_ids.shape[0]
        if n > len(self._free):
            old = self._table.capacity
            cap = old
            while cap - old + len(self._free) < n:
                cap *= 2
            self._table.grow(cap)
            self._free = list(range(cap - 1, old - 1, -1)) + self._free
        rows = np.array([self._free.pop() for _ in range(n)], dtype=np.int64) if n else np.empty(0, np.int64)
        self._table.reset_rows(rows)
        ids = np.concatenate([self._ids, new_ids])
        id_rows = np.concatenate([self._id_rows, rows])
        order = np.argsort(ids, kind="stable")
        self._ids, self._id_rows = ids[order], id_rows[order]
        return rows

    def retain(self, alive_ids: IDS) -> int:
        """Evict the windows of every track not in ``alive_ids`` (the tracker no longer reports it); what their
        windows hold that the calibration has not had is pooled first."""
        self.learn()
        keep = np.zeros(self._ids.shape[0], dtype=bool)
        if self._ids.shape[0]:
            pos, found = self._positions(np.asarray(alive_ids, dtype="S32"))
            keep[pos[found]] = True
        gone = self._id_rows[~keep]
        if gone.size:
            self._pending = self._pending[~np.isin(self._pending, gone)]  # pooled below, whole
        if gone.size and self._config.calibration == "online":
            self._harvest(gone, np.minimum(self._table.since[gone], self._table.count[gone]))
        self._free.extend(gone.tolist())
        self._table.reset_rows(gone)
        self._ids, self._id_rows = self._ids[keep], self._id_rows[keep]
        return int(gone.shape[0])

    def reset(self) -> None:
        """Forget every track (e.g. the tracker restarted). The calibration stays: it describes the detector,
        not the tracks."""
        self.retain(np.empty(0, dtype="S32"))

    # ------------------------------------------------------------------ the per-frame path

    def update(self, obs: Observations) -> Decisions:
        """Append one observation per track to its window and decide every observed track (with the
        calibration as :meth:`learn` left it)."""
        self.learn()  # a no-op when the adapter's settle has run since the last frame
        self._observe_clock(obs.stamp_ns, obs.seq)
        interval = self._follow_rate()
        ids = obs.track_ids
        rows, found = self._lookup(ids)
        if not found.all():
            new_ids = ids[~found]
            if np.unique(new_ids).shape[0] != new_ids.shape[0]:
                raise ValueError("track_ids must be unique within a frame")
            rows[~found] = self._allocate(new_ids)
        t = self._table
        if rows.shape[0] and np.bincount(rows, minlength=1).max() > 1:
            raise ValueError("track_ids must be unique within a frame")
        w = t.window
        stamp_s = obs.stamp_ns * 1e-9
        fresh = self._takes(rows, stamp_s, interval)
        valid = _valid_observations(obs)
        if not valid.all():
            fresh = valid if fresh is None else fresh & valid
        taken, o = (rows, obs) if fresh is None else (rows[fresh], obs.subset(fresh))
        slot = t.head[taken]
        n = taken.shape[0]
        t.win[taken, slot] = np.stack([o.x, o.y, o.cxx, o.cxy, o.cyy, np.full(n, stamp_s),
                                       np.full(n, obs.sensor_x), np.full(n, obs.sensor_y),
                                       t.seen[taken].astype(np.float64)], axis=1)
        t.head[taken] = (slot + 1) % w
        t.count[taken] = np.minimum(t.count[taken] + 1, w)
        t.since[taken] += 1
        t.seen[taken] += 1
        # a class the classifier does not know is UNKNOWN (as the calibration's groups read it): clipped, a label
        # past the last had been decided as a pedestrian's, with the most sensitive alpha
        t.label[rows] = np.where((obs.labels >= 0) & (obs.labels < _NUM_LABELS), obs.labels, 0)
        if obs.published_ids is None:
            t.published[rows] = True
        else:  # confirmation is final, so "was ever published" is "is published" for an observed track
            pub, found = self._lookup(obs.published_ids)
            t.published[pub[found]] = True
        if self._config.calibration == "online":
            self._online.advance(stamp_s)
            full = taken[(t.since[taken] >= w) & (t.count[taken] >= w)]
            if full.size:  # a row stays full until pooled: queue it once
                self._pending = np.concatenate([self._pending, full[~np.isin(full, self._pending)]])
            self._learn_due = self._pending.size > 0
        return self._decide(rows, ids, obs.speed, obs.stamp_ns, obs.seq, fresh)

    def _statistics(self, rows: NDArray[np.int64]) -> WindowStats:
        """The test statistic of the windows of ``rows`` as they stand."""
        cfg = self._config
        t = self._table
        count = t.count[rows]
        if cfg.calibration == "off" and cfg.effective_n != "measured" and cfg.min_speed_mps == 0:
            masks = split_halves(t.head[rows], count, t.window)
            stats = window_statistics(t.win[rows], masks, variance_floor=cfg.variance_floor,
                                      independent=cfg.effective_n == "independent")
        else:
            # oldest first (the newest in the last slot): the correlation kernel's passes run along the slots
            # in time order without a permutation
            masks = split_halves(np.zeros(rows.shape[0], dtype=np.int64), count, t.window)
            stats = calibrated_statistics(t.ordered(rows, t.window), masks, group_of_labels(t.label[rows]),
                                          self.noise_model(),
                                          variance_floor=cfg.variance_floor, effective_n=cfg.effective_n,
                                          track_scale_prior=cfg.calibration != "off", min_speed=cfg.min_speed_mps,
                                          view_slide=self._view_table[t.label[rows]])
        if (count < 2).any():  # one observation: no older half, nothing to compare (z is not defined)
            one = count < 2
            stats = replace(stats, z_x=np.where(one, 0.0, stats.z_x), z_y=np.where(one, 0.0, stats.z_y),
                            chi2=np.where(one, 0.0, stats.chi2))
        return stats

    def _decide(self, rows: NDArray[np.int64], ids: IDS, speed: F64, stamp_ns: int, seq: int,
                fresh: NDArray[np.bool_] | None = None) -> Decisions:
        """Decide every row; the statistic only for the ``fresh`` ones (None: all) — a window that took no
        observation this frame keeps its last statistic, while the hold and the baseline run on this frame's
        clock and speed."""
        cfg = self._config
        t = self._table
        count = t.count[rows]
        if fresh is None:
            stats = self._statistics(rows)
        else:
            new = self._statistics(rows[fresh])
            kept = {}
            for f in fields(WindowStats):  # each is also kept per row in ``last``
                col = t.last[f.name][rows].copy()
                col[fresh] = getattr(new, f.name)
                kept[f.name] = col
            stats = WindowStats(**kept)
        alpha = self._alpha_table[t.label[rows]]
        decided = count >= cfg.min_window
        # the baseline's state is kept whatever the mode, so switching to it is immediate
        threshold_v = self._speed_table[t.label[rows]]
        fast = speed > threshold_v
        now_s = stamp_ns * 1e-9
        t.fast_since[rows] = _running_since(t.fast_since[rows], fast, now_s)
        vetoed = np.zeros(rows.shape[0], dtype=bool)
        if cfg.mode in ("z_test", "chi2"):
            if cfg.mode == "z_test":
                threshold = alpha
                reject = np.maximum(stats.z_x, stats.z_y) > alpha
            else:
                threshold = chi2_2_threshold(alpha)
                reject = stats.chi2 > threshold
            if cfg.jump_veto:  # a window one jump explains better than steady motion is a re-placed box
                # only a window the test rejects can be vetoed: a vehicle's from JUMP_VETO_MIN_VEHICLE observations,
                # any other class's once full
                youngest = min(JUMP_VETO_MIN_VEHICLE, t.window)
                need = np.where(group_of_labels(t.label[rows]) == _VEHICLE, youngest, t.window)
                ask = np.flatnonzero(reject & (count >= need))
                if ask.size:
                    vetoed[ask] = jump_ratio(t.ordered(rows[ask], t.window), count[ask], min_count=youngest) < 1.0
                    reject &= ~vetoed
            # dynamic once the test has rejected H0 on every decision for the class's hold (none: at once); the
            # microsecond spares a hold of whole frames the rounding of stamps in seconds
            reject &= decided
            since = t.reject_since[rows] = _running_since(t.reject_since[rows], reject, now_s)
            dynamic = reject & (now_s - since >= self._hold_table[t.label[rows]] - 1e-6)
        else:  # velocity_threshold: Autoware's per-class speed cut-off, held for its sustain time
            threshold = threshold_v
            sustain = self._sustain_table[t.label[rows]]
            dynamic = fast & (now_s - t.fast_since[rows] >= sustain)
            decided = np.ones(rows.shape[0], dtype=bool)
        state = np.where(decided, np.where(dynamic, DYNAMIC, STATIC), UNDECIDED).astype(np.int8)

        last = t.last
        for name, value in (
            ("state", state), ("z_x", stats.z_x), ("z_y", stats.z_y), ("chi2", stats.chi2), ("alpha", alpha),
            ("threshold", threshold), ("mean_x", stats.mean_x), ("mean_y", stats.mean_y), ("speed", speed),
            ("vetoed", vetoed),
        ):
            last[name][rows] = value
        last["stamp_ns"][rows] = stamp_ns
        last["seq"][rows] = seq
        return Decisions(
            track_ids=ids, state=state, z_x=stats.z_x, z_y=stats.z_y, chi2=stats.chi2, alpha=alpha,
            threshold=np.asarray(threshold, dtype=np.float64), window_length=count,
            mean_x=stats.mean_x, mean_y=stats.mean_y, speed=speed, published=t.published[rows].copy(), vetoed=vetoed,
        )

    # ------------------------------------------------------------------ state queries

    def last_decisions(self, ids: IDS | None = None) -> Decisions:
        """The most recent decision of the given tracks (all known tracks if ``ids`` is None).

        Unknown IDs come back ``undecided`` with a zero-length window.
        """
        ids = self._ids if ids is None else np.asarray(ids, dtype="S32")
        rows, found = self._lookup(ids)
        r = np.where(found, rows, 0)
        last = self._table.last
        pick = lambda name: np.where(found, last[name][r], 0).astype(last[name].dtype)  # noqa: E731
        return Decisions(
            track_ids=ids, state=pick("state"), z_x=pick("z_x"), z_y=pick("z_y"), chi2=pick("chi2"),
            alpha=pick("alpha"), threshold=pick("threshold"),
            window_length=np.where(found, self._table.count[r], 0), mean_x=pick("mean_x"),
            mean_y=pick("mean_y"), speed=pick("speed"), published=found & self._table.published[r],
            vetoed=pick("vetoed"),
        )

    def last_meta(self, ids: IDS) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
        """(label, last stamp ns, last seq) of known tracks, for state reports."""
        rows, found = self._lookup(np.asarray(ids, dtype="S32"))
        r = np.where(found, rows, 0)
        t = self._table
        return t.label[r], t.last["stamp_ns"][r], t.last["seq"][r]



def calibration_gauges(state: dict) -> dict[str, float]:
    """A ``calibration_state`` as flat heartbeat gauges: ``calibration.{group}.{axis}.{scale|scale_young}.{band}``,
    ``calibration.{group}.{axis}.{correlation|correlation_time_s|variance_factor}``,
    ``calibration.{group}.track_dof``, ``calibration.effective_blocks`` and ``calibration.scale_dof`` (absent
    for scales taken as given)."""
    out: dict[str, float] = {"calibration.effective_blocks": float(state.get("effective_blocks", 0.0))}
    if state.get("scale_dof") is not None:
        out["calibration.scale_dof"] = float(state["scale_dof"])
    for g, entry in state.get("groups", {}).items():
        out[f"calibration.{g}.track_dof"] = float(entry["track_dof"])
        for axis in ("along", "across"):
            a = entry[axis]
            for key in ("scale", "scale_young"):
                for band, v in a[key].items():
                    out[f"calibration.{g}.{axis}.{key}.{band}"] = float(v)
            for key in ("correlation", "correlation_time_s", "variance_factor"):
                out[f"calibration.{g}.{axis}.{key}"] = float(a[key])
    return out
