"""The track table (struct of arrays) and the lifecycle rules: birth, confirmation, deletion.

Why a struct of arrays: the filters, the gates and the lifecycle rules all run as array expressions over every
track; a list of track objects would force a Python loop per frame per track. Rows are in birth order, and
deleting tracks compacts every array with one boolean mask.

Lifecycle (Autoware-like): a detection nobody claims starts a *tentative* track; it becomes *confirmed* after
``confirm_hits`` associated detections (per class, as Autoware's ``confident_count_threshold``) once its running
existence probability (the smoothed detection scores) has also reached ``confirm_min_existence``. Only confirmed
tracks are published, and confirmation is final, so an ID that reached the output stays there until the track is
deleted instead of blinking in and out. A tentative track that misses for longer than ``tentative_max_gap_s`` is
deleted (that is what filters one-off false positives; a low-scored clutter return that recurs stays tentative),
a confirmed one after ``max_coast_s`` without a detection (Autoware's tracker lifetime: the detector's misses
are bridged by prediction) or once its position uncertainty has grown past ``max_position_stddev``. IDs are
fresh 16-byte UUIDs (``uuid4``): they never repeat, not even across restarts, because nothing is derived from a
counter.
"""

from __future__ import annotations

import uuid
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .config import NUM_LABELS
from .kalman import STATE_DIM

F64 = NDArray[np.float64]

LABEL_DECAY = 0.8
"""How fast a track's class vote forgets: a detector that flickers car/truck for a frame does not flip it."""


@dataclass(frozen=True)
class Confirmation:
    """When a tentative track becomes confirmed: ``hits[label]`` detections and ``min_existence`` reached."""

    hits: NDArray[np.int64]
    """Per Autoware label (8 entries): associated detections needed."""
    min_existence: float = 0.0

    @classmethod
    def uniform(cls, hits: int, min_existence: float = 0.0) -> "Confirmation":
        return cls(np.full(NUM_LABELS, hits, dtype=np.int64), min_existence)

    def reached(self, hits: NDArray[np.int64], label: NDArray[np.int8], existence: F64) -> NDArray[np.bool_]:
        return (hits >= self.hits[label.astype(np.intp)]) & (existence >= self.min_existence)


def new_track_id() -> str:
    """A fresh 32-hex-digit track ID (a random 16-byte UUID)."""
    return uuid.uuid4().hex


@dataclass(frozen=True)
class Seen:
    """What detections tell their tracks besides the position the filter takes: class and its probability,
    existence, height, size and orientation, one row per detection (in the order of the rows they update)."""

    label: NDArray[np.int8]
    label_prob: F64
    existence: F64
    z: F64
    dims: F64  # (k, 3): length, width, height
    orientation: NDArray[np.int8]


OBS_CHANNELS = 8
"""Per kept detection: world x, y; its reported world covariance xx, xy, yy; stamp [s]; the sensor's x, y."""


class TrackTable:
    """Every track's state and bookkeeping, one row per track. ``obs_window``: how many of each track's latest
    detections are kept (``obs``, a ring; ``obs_seen`` counts them all, ``obs_since`` those not yet learnt
    from) for the measurement scale (:mod:`.measurement_scale`); 0 keeps none."""

    def __init__(self, obs_window: int = 0) -> None:
        self.obs_window = obs_window
        self.obs = np.zeros((0, obs_window, OBS_CHANNELS))
        self.obs_seen = np.zeros(0, dtype=np.int64)
        self.obs_since = np.zeros(0, dtype=np.int64)
        self.ids: list[str] = []
        self.x = np.zeros((0, STATE_DIM))
        self.P = np.zeros((0, STATE_DIM, STATE_DIM))
        self.t_ns = np.zeros(0, dtype=np.int64)  # time the state refers to
        self.model = np.zeros(0, dtype=np.int8)
        self.votes = np.zeros((0, NUM_LABELS))  # decayed class votes; the label is their argmax
        self.label = np.zeros(0, dtype=np.int8)
        self.existence = np.zeros(0)
        self.z = np.zeros(0)
        self.dims = np.zeros((0, 3))
        self.orientation = np.zeros(0, dtype=np.int8)
        self.hits = np.zeros(0, dtype=np.int64)
        self.confirmed = np.zeros(0, dtype=bool)
        self.born_ns = np.zeros(0, dtype=np.int64)
        self.last_update_ns = np.zeros(0, dtype=np.int64)

    def __len__(self) -> int:
        return len(self.ids)

    def append(
        self,
        x: F64,
        P: F64,
        stamp_ns: int,
        model: NDArray[np.int8],
        seen: Seen,
        confirm: Confirmation,
        id_factory: Callable[[], str] = new_track_id,
    ) -> list[str]:
        """Add ``len(x)`` new tracks born from one detection each; returns their fresh IDs."""
        k = x.shape[0]
        if k == 0:
            return []
        ids = [id_factory() for _ in range(k)]
        votes = np.zeros((k, NUM_LABELS))
        votes[np.arange(k), seen.label.astype(np.intp)] = seen.label_prob
        self.ids.extend(ids)
        self.x = np.concatenate([self.x, x])
        self.P = np.concatenate([self.P, P])
        self.t_ns = np.concatenate([self.t_ns, np.full(k, stamp_ns, dtype=np.int64)])
        self.model = np.concatenate([self.model, model.astype(np.int8)])
        self.votes = np.concatenate([self.votes, votes])
        self.label = np.concatenate([self.label, seen.label.astype(np.int8)])
        self.existence = np.concatenate([self.existence, seen.existence])
        self.z = np.concatenate([self.z, seen.z])
        self.dims = np.concatenate([self.dims, seen.dims])
        self.orientation = np.concatenate([self.orientation, seen.orientation.astype(np.int8)])
        self.hits = np.concatenate([self.hits, np.ones(k, dtype=np.int64)])
        self.confirmed = np.concatenate([self.confirmed, confirm.reached(np.ones(k, dtype=np.int64), seen.label, seen.existence)])
        self.born_ns = np.concatenate([self.born_ns, np.full(k, stamp_ns, dtype=np.int64)])
        self.last_update_ns = np.concatenate([self.last_update_ns, np.full(k, stamp_ns, dtype=np.int64)])
        self.obs = np.concatenate([self.obs, np.zeros((k, self.obs_window, OBS_CHANNELS))])
        self.obs_seen = np.concatenate([self.obs_seen, np.zeros(k, dtype=np.int64)])
        self.obs_since = np.concatenate([self.obs_since, np.zeros(k, dtype=np.int64)])
        return ids

    def record_observations(self, rows: NDArray[np.intp], values: F64) -> None:
        """Keep one detection per row (``values``: (k, :data:`OBS_CHANNELS`)) in its ring."""
        if self.obs_window == 0 or rows.size == 0:
            return
        self.obs[rows, self.obs_seen[rows] % self.obs_window] = values
        self.obs_seen[rows] += 1
        self.obs_since[rows] += 1

    def latest_observations(self, rows: NDArray[np.intp], n: int) -> F64:
        """(k, n, :data:`OBS_CHANNELS`): each row's newest ``n`` kept detections, oldest first (n ≤ what it
        has and ≤ ``obs_window``)."""
        slots = (self.obs_seen[rows, None] - n + np.arange(n)[None, :]) % self.obs_window
        return self.obs[rows[:, None], slots]

    def record_hits(
        self,
        rows: NDArray[np.intp],
        stamp_ns: int,
        seen: Seen,
        confirm: Confirmation,
        smoothing: float,
    ) -> int:
        """Bookkeeping for tracks that received a detection: hit count, class vote, shape, confirmation. Returns
        how many of them became confirmed with it."""
        if rows.size == 0:
            return 0
        self.hits[rows] += 1
        self.last_update_ns[rows] = stamp_ns
        self.votes[rows] *= LABEL_DECAY
        self.votes[rows, seen.label.astype(np.intp)] += seen.label_prob
        self.label[rows] = np.argmax(self.votes[rows], axis=1).astype(np.int8)
        a = smoothing
        self.existence[rows] = (1.0 - a) * self.existence[rows] + a * seen.existence
        self.z[rows] = (1.0 - a) * self.z[rows] + a * seen.z
        self.dims[rows] = (1.0 - a) * self.dims[rows] + a * seen.dims
        self.orientation[rows] = seen.orientation
        was = self.confirmed[rows]
        now = was | confirm.reached(self.hits[rows], self.label[rows], self.existence[rows])
        self.confirmed[rows] = now
        return int(np.count_nonzero(now & ~was))

    def expired(self, stamp_ns: int, tentative_max_gap_s: float, max_coast_s: float,
                max_position_stddev: float) -> NDArray[np.bool_]:
        """Which rows the lifecycle rules delete at ``stamp_ns``; also any whose state or covariance is no longer
        finite (nothing brings such a filter back, and a NaN position poisons every gate it enters)."""
        gap = (stamp_ns - self.last_update_ns) * 1e-9
        too_old = np.where(self.confirmed, gap > max_coast_s, gap > tentative_max_gap_s)
        pos_var = np.maximum(self.P[:, 0, 0], self.P[:, 1, 1])
        broken = ~(np.isfinite(self.x).all(axis=1) & np.isfinite(self.P).all(axis=(1, 2)))
        return too_old | (pos_var > max_position_stddev * max_position_stddev) | broken

    def keep(self, mask: NDArray[np.bool_]) -> list[str]:
        """Drop the rows where ``mask`` is false; returns the IDs dropped."""
        if mask.all():
            return []
        dropped = [i for i, k in zip(self.ids, mask) if not k]
        self.ids = [i for i, k in zip(self.ids, mask) if k]
        for name in ("x", "P", "t_ns", "model", "votes", "label", "existence", "z", "dims", "orientation",
                     "hits", "confirmed", "born_ns", "last_update_ns", "obs", "obs_seen", "obs_since"):
            setattr(self, name, getattr(self, name)[mask])
        return dropped

    def row_of(self) -> dict[str, int]:
        """ID -> row, for the few lookups by ID (static hints)."""
        return {tid: i for i, tid in enumerate(self.ids)}
