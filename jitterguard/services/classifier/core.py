"""The motion classifier core: one sliding observation window per track, decided once per frame.

Pure: numpy arrays in, numpy arrays out, no I/O, no clock, no globals. The live service and the offline
evaluator both drive this class, so what is measured offline is what runs live.

Windows live in dense ``(capacity, window_size)`` ring buffers indexed by a row per track; track IDs map to
rows through a sorted ID array and ``np.searchsorted``, so the per-frame path has no per-track Python loop.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ...schemas.models import ClassifierConfig
from .statistics import CHANNELS, chi2_2_threshold, split_halves, window_statistics

F64 = NDArray[np.float64]
IDS = NDArray[np.bytes_]

UNDECIDED, STATIC, DYNAMIC = 0, 1, 2
STATE_NAMES = ("undecided", "static", "dynamic")
_NUM_LABELS = 8


@dataclass(frozen=True)
class Observations:
    """One frame of associated detections, world frame, one row per track (IDs unique within the frame).

    ``cxx, cxy, cyy`` are the detection's 2x2 position covariance already rotated into the world frame;
    ``speed`` is the tracker's speed estimate (used by the velocity-threshold baseline only).
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

    @staticmethod
    def from_lists(track_ids: list[str], labels, x, y, cxx, cxy, cyy, speed=None, stamp_ns: int = 0, seq: int = 0) -> "Observations":
        n = len(track_ids)
        f = lambda v: np.asarray(v, dtype=np.float64).reshape(n)  # noqa: E731
        return Observations(
            track_ids=np.asarray(track_ids, dtype="S32").reshape(n),
            labels=np.asarray(labels, dtype=np.int64).reshape(n),
            x=f(x), y=f(y), cxx=f(cxx), cxy=f(cxy), cyy=f(cyy),
            speed=f(np.zeros(n) if speed is None else speed),
            stamp_ns=stamp_ns, seq=seq,
        )

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

    def state_names(self) -> list[str]:
        return [STATE_NAMES[s] for s in self.state.tolist()]


@dataclass
class _Table:
    """Per-row storage; grows by doubling. ``win`` is (capacity, window, 5) over ``CHANNELS``."""

    window: int
    capacity: int
    win: F64 = field(init=False)
    head: NDArray[np.int64] = field(init=False)
    count: NDArray[np.int64] = field(init=False)
    label: NDArray[np.int64] = field(init=False)
    last: dict[str, np.ndarray] = field(init=False)

    _LAST = {
        "state": np.int8, "z_x": np.float64, "z_y": np.float64, "chi2": np.float64, "alpha": np.float64,
        "threshold": np.float64, "mean_x": np.float64, "mean_y": np.float64, "speed": np.float64,
        "stamp_ns": np.int64, "seq": np.int64,
    }

    def __post_init__(self) -> None:
        self.win = np.zeros((self.capacity, self.window, len(CHANNELS)))
        self.head = np.zeros(self.capacity, dtype=np.int64)
        self.count = np.zeros(self.capacity, dtype=np.int64)
        self.label = np.zeros(self.capacity, dtype=np.int64)
        self.last = {k: np.zeros(self.capacity, dtype=t) for k, t in self._LAST.items()}

    def grow(self, capacity: int) -> None:
        extra = capacity - self.capacity
        self.win = np.concatenate([self.win, np.zeros((extra, self.window, len(CHANNELS)))])
        self.head = np.concatenate([self.head, np.zeros(extra, dtype=np.int64)])
        self.count = np.concatenate([self.count, np.zeros(extra, dtype=np.int64)])
        self.label = np.concatenate([self.label, np.zeros(extra, dtype=np.int64)])
        self.last = {k: np.concatenate([v, np.zeros(extra, dtype=v.dtype)]) for k, v in self.last.items()}
        self.capacity = capacity

    def reset_rows(self, rows: NDArray[np.int64]) -> None:
        self.head[rows] = 0
        self.count[rows] = 0
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
        self.head = keep % window


class MotionClassifierCore:
    """Sliding windows per track ID and the static/dynamic decision of DESIGN.md "The motion classifier"."""

    def __init__(self, config: ClassifierConfig | None = None, capacity: int = 256) -> None:
        self._config = config or ClassifierConfig()
        self._table = _Table(window=self._config.window_size, capacity=max(8, capacity))
        self._ids: IDS = np.empty(0, dtype="S32")  # sorted
        self._id_rows: NDArray[np.int64] = np.empty(0, dtype=np.int64)
        self._free: list[int] = list(range(self._table.capacity - 1, -1, -1))
        self._alpha_table = self._make_alpha_table(self._config)

    # ------------------------------------------------------------------ configuration

    @property
    def config(self) -> ClassifierConfig:
        return self._config

    def configure(self, config: ClassifierConfig) -> None:
        """Apply a new config; a changed window length keeps each track's newest observations."""
        if config.window_size != self._table.window:
            self._table.rewindow(config.window_size)
        self._config = config
        self._alpha_table = self._make_alpha_table(config)

    @staticmethod
    def _make_alpha_table(config: ClassifierConfig) -> F64:
        return np.array([config.alpha_for(label) for label in range(_NUM_LABELS)], dtype=np.float64)

    # ------------------------------------------------------------------ ID -> row mapping

    def track_ids(self) -> list[str]:
        return [i.decode() for i in self._ids.tolist()]

    def _lookup(self, ids: IDS) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
        if self._ids.shape[0] == 0:
            return np.full(ids.shape[0], -1, dtype=np.int64), np.zeros(ids.shape[0], dtype=bool)
        pos = np.searchsorted(self._ids, ids)
        pos_c = np.minimum(pos, self._ids.shape[0] - 1)
        found = self._ids[pos_c] == ids
        return np.where(found, self._id_rows[pos_c], -1), found

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
        """Evict the windows of every track not in ``alive_ids`` (the tracker no longer reports it)."""
        keep = np.isin(self._ids, np.asarray(alive_ids, dtype="S32"))
        gone = self._id_rows[~keep]
        self._free.extend(gone.tolist())
        self._table.reset_rows(gone)
        self._ids, self._id_rows = self._ids[keep], self._id_rows[keep]
        return int(gone.shape[0])

    def reset(self) -> None:
        """Forget every track (e.g. the tracker restarted)."""
        self.retain(np.empty(0, dtype="S32"))

    # ------------------------------------------------------------------ the per-frame path

    def update(self, obs: Observations) -> Decisions:
        """Append one observation per track to its window and decide every observed track."""
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
        slot = t.head[rows]
        t.win[rows, slot] = np.stack([obs.x, obs.y, obs.cxx, obs.cxy, obs.cyy], axis=1)
        t.head[rows] = (slot + 1) % w
        t.count[rows] = np.minimum(t.count[rows] + 1, w)
        t.label[rows] = np.clip(obs.labels, 0, _NUM_LABELS - 1)
        return self._decide(rows, ids, obs.speed, obs.stamp_ns, obs.seq)

    def _decide(self, rows: NDArray[np.int64], ids: IDS, speed: F64, stamp_ns: int, seq: int) -> Decisions:
        cfg = self._config
        t = self._table
        count = t.count[rows]
        masks = split_halves(t.head[rows], count, t.window)
        stats = window_statistics(
            t.win[rows], masks, variance_floor=cfg.variance_floor, independent=cfg.effective_n == "independent"
        )
        alpha = self._alpha_table[t.label[rows]]
        decided = count >= cfg.min_window
        if cfg.mode == "z_test":
            threshold = alpha
            dynamic = np.maximum(stats.z_x, stats.z_y) > alpha
        elif cfg.mode == "chi2":
            threshold = chi2_2_threshold(alpha)
            dynamic = stats.chi2 > threshold
        else:  # velocity_threshold: Autoware's speed cut-off; decides from the first observation
            threshold = np.full(rows.shape[0], cfg.velocity_threshold)
            dynamic = speed > threshold
            decided = np.ones(rows.shape[0], dtype=bool)
        state = np.where(decided, np.where(dynamic, DYNAMIC, STATIC), UNDECIDED).astype(np.int8)

        last = t.last
        for name, value in (
            ("state", state), ("z_x", stats.z_x), ("z_y", stats.z_y), ("chi2", stats.chi2), ("alpha", alpha),
            ("threshold", threshold), ("mean_x", stats.mean_x), ("mean_y", stats.mean_y), ("speed", speed),
        ):
            last[name][rows] = value
        last["stamp_ns"][rows] = stamp_ns
        last["seq"][rows] = seq
        return Decisions(
            track_ids=ids, state=state, z_x=stats.z_x, z_y=stats.z_y, chi2=stats.chi2, alpha=alpha,
            threshold=np.asarray(threshold, dtype=np.float64), window_length=count,
            mean_x=stats.mean_x, mean_y=stats.mean_y, speed=speed,
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
            mean_y=pick("mean_y"), speed=pick("speed"),
        )

    def last_meta(self, ids: IDS) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
        """(label, last stamp ns, last seq) of known tracks, for state reports."""
        rows, found = self._lookup(np.asarray(ids, dtype="S32"))
        r = np.where(found, rows, 0)
        t = self._table
        return t.label[r], t.last["stamp_ns"][r], t.last["seq"][r]

