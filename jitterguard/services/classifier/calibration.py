"""Variance self-calibration: how far the detector's reported positional variances are off, learnt from the
tracks themselves, without labels (docs/calibration.md has the derivation).

Why: the z-test of paper §III-B assumes the detector's variances are right. Real detectors mis-state them
(the paper: along the line of sight over-, across it under-estimated; the shipped detector on real scans
reports σ about 2× too small) and successive errors of one object are serially correlated, so neither the
per-cluster nor the per-observation count gives the variance of a half-window mean. Both are measurable:

* Within a block of one track's consecutive observations, the residuals about a constant-velocity
  (straight line in time) fit are detection noise whether the object stands still or moves steadily. They
  are projected on the line of sight from the sensor (``along``) and across it (``across``) and divided by
  the reported σ on that axis: ε_j = r_j / σ_j.
* Model: ε has variance k (the scale the reported variances are off by) and correlation
  R(Δt) = (1 − m)·[Δt = 0] + m·exp(−|Δt|/τ) (white noise plus a correlated "jitter" part). With M the
  projection that removes the fitted line and D = diag(σ), the normalised residuals ε̃ = G ε, G = D⁻¹ M D,
  have E[ε̃ ε̃ᵀ] = k G R Gᵀ = k[(1 − m) G Gᵀ + m G Φ_τ Gᵀ], known per block up to (k, m, τ)
  (:func:`block_moments`). Pooled over blocks, the entries of Σ ε̃ ε̃ᵀ are fitted by non-negative least
  squares for each τ on a grid (:func:`fit_shape`): detrending bias is accounted for exactly.
* Each observation is counted once: a track contributes a block when its window has turned over
  (``window_size`` new observations) and a shorter one when it is evicted.
* Pooling is robust and bounded: a block whose sum of squares is more than :data:`HUBER_C` times what the current
  model predicts (a manoeuvre, an ID switch, a ghost) is down-weighted to count like :data:`HUBER_C` normal
  blocks (a Huber weight); scales are clipped to :data:`SCALE_BOUNDS`; sums decay with a half-life in data
  time (``forgetting``).
* Priors are hierarchical pseudo-blocks: all classes per axis shrink to k = 1, m = :data:`PRIOR_CORRELATION`,
  τ = :data:`PRIOR_TAU_S`; a class group to the all-classes fit; a (group, axis, range band) cell's scale to
  its group's. A handful of tracks cannot swing a cell, while a scale error shared by every class (what
  ``jitterguard eval --variance-scale`` injects) is learnt from all tracks at once.

The result is a :class:`NoiseModel`: a variance scale per (class group, axis, range band) and (m, τ) per
(class group, axis). :func:`jitterguard.services.classifier.statistics.calibrated_statistics` turns it into
the z-test's denominator. Pure: numpy in, numpy out; no clock (time is the data's stamps), no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...schemas.models import LABEL_NAMES
from .block_kernel import pool_blocks

F64 = NDArray[np.float64]

GROUPS: tuple[str, ...] = ("vehicle", "pedestrian", "cycle", "unknown")
"""Calibration class groups (objects of similar size and detectability share their errors)."""
LABEL_GROUP = np.array([3, 0, 0, 0, 0, 2, 2, 1], dtype=np.int64)
"""Group index per Autoware label: UNKNOWN, CAR, TRUCK, BUS, TRAILER, MOTORCYCLE, BICYCLE, PEDESTRIAN."""
AXES: tuple[str, ...] = ("along", "across")
"""Line-of-sight axes: sensor → object, and perpendicular to it (in the ground plane)."""
AGES: tuple[str, ...] = ("established", "young")
"""Track age classes: ``young`` observations are a track's first ``window_size`` ones. An object that just
appeared is measured worse (partly visible, entering the field of view) than the detector's variance says: with
the detector in the loop the error of static vehicles is 2–3× larger over a track's first observations than
later (docs/calibration.md), so these get scales of their own."""

TAU_GRID_S = np.geomspace(0.05, 3.0, 12)
"""Correlation times the fit chooses from. Longer ones cannot be told from motion inside a window."""
SCALE_BOUNDS = (1e-2, 1e2)
"""A variance scale is clipped to this range (σ off by at most 10× either way)."""
PRIOR_CORRELATION = 0.5
"""Prior correlated fraction m: successive detections are correlated (paper §III-B, condition iii)."""
PRIOR_TAU_S = float(TAU_GRID_S[6])
"""Prior correlation time [s] (0.47 s, on the grid so that the prior is exactly representable)."""
MAX_BLOCK_SPEED = 1.0
"""Blocks whose fitted line is faster than this [m/s] are not pooled: the test's null is an object standing
still, and the residuals of faster objects mix in manoeuvres (turns, braking) that look like correlated noise
(measured with the detector in the loop, synthetic seeds 0–3: vehicle along-sight scale 2.1 from all blocks,
0.36 from these; docs/calibration.md). For an object moving steadily the fitted speed is independent of the
residuals, so the selection does not bias them."""
PRIOR_TRACK_DOF = 10.0
"""ν₀ before the data says otherwise (a track's scale within about ±45 % of its class's, 1σ)."""
TRACK_DOF_BOUNDS = (2.0, 1000.0)
"""ν₀ is kept in this range (2: as heterogeneous as a χ²₂ draw; 1000: every track like its class)."""
MIN_HETEROGENEITY_BLOCKS = 30.0
"""Blocks a group needs before its own ν₀ is estimated (else all groups', else the prior)."""
TOP_PRIOR_BLOCKS = 2.0
"""Pseudo-blocks of the all-classes level's prior (k = 1): weak, since detectors are often off by a factor."""
HUBER_C = 5.0
"""A block with more than this many times the predicted lag-0 sum is down-weighted (Huber)."""
MIN_BLOCK = 5
"""Fewest observations in a block (3 residual degrees of freedom after the line fit)."""
PRIOR_SCALE_DOF = 2.0
"""How well the test trusts k = 1 before any block: ν = 2, Var(log k) ≈ 2/ν = 1, a reported variance right to
within a factor e at 1σ. Real detectors are off by that much: the shipped one's variances were 4× too small on
real scans before their score-binned recalibration (docs/calibration.md), and a recalibration fitted on one
domain is off on the next. A cold start therefore tests with heavy tails and calls less dynamic until
the first blocks arrive (within MIN_BLOCK frames of the first tracks)."""
BLOCK_DOF = 8.0
"""Degrees of freedom one block of evidence gives a scale (a full 10-observation window less its line fit; a
block of the default 20-observation window holds more, so the count is conservative: the window was chosen
and validated with it as it is)."""
REFIT_PERIOD_S = 0.5
"""Data time between two fits of the online model."""
CANONICAL_DT_S = 0.1
"""Frame spacing of the pseudo-blocks before any block was seen (the prior does not depend on it much)."""


def group_of_labels(labels: NDArray[np.integer]) -> NDArray[np.int64]:
    """Calibration group index of Autoware labels (out-of-range labels count as unknown)."""
    lab = np.asarray(labels, dtype=np.int64)
    return np.where((lab >= 0) & (lab < len(LABEL_GROUP)), LABEL_GROUP[np.clip(lab, 0, len(LABEL_GROUP) - 1)],
                    GROUPS.index("unknown"))


def vehicle_class_names() -> list[str]:
    """The lowercase class names of the ``vehicle`` group (car, truck, bus, trailer): the classes whose boxes
    slide with the view (docs/classifier.md 'The view term')."""
    return [LABEL_NAMES[label] for label in range(len(LABEL_GROUP)) if LABEL_GROUP[label] == GROUPS.index("vehicle")]


def band_names(edges_m: Sequence[float]) -> list[str]:
    """``["0-20", "20-40", "40-inf"]`` for edges (20, 40): each edge with 6 significant digits, or as many more as
    the names need to differ (edges 20, 20.000001 and 20.000002 m had named two bands "20-20": one band's scale
    lost from /v1/state, the heartbeat and the calibration file, and a duplicate sample in /metrics)."""
    lo = [0.0, *edges_m]
    hi = [*edges_m, math.inf]
    for digits in (6, 9, 12, 17):
        names = [f"{a:.{digits}g}-{'inf' if math.isinf(b) else f'{b:.{digits}g}'}" for a, b in zip(lo, hi)]
        if len(set(names)) == len(names):
            break
    return names


# ---------------------------------------------------------------------------------------------- the model


@dataclass(frozen=True)
class NoiseModel:
    """What the z-test needs to know about the detector's errors.

    ``scale[g, a, b, y]``: true variance / reported variance for class group g, line-of-sight axis a, range band
    b (bands split at ``band_edges_m``) and track age y (:data:`AGES`); ``correlation[g, a]`` and ``tau_s[g, a]``:
    the correlated fraction m and correlation time τ of the normalised error; ``blocks[g, a, b, y]``: the
    evidence behind each scale (effective number of blocks after forgetting; 0 for a prior or a scale nobody
    measured).
    """

    band_edges_m: tuple[float, ...]
    scale: F64
    correlation: F64
    tau_s: F64
    blocks: F64
    frame_interval_s: float = CANONICAL_DT_S
    """Typical time between two observations of a track (reported, and used by :meth:`variance_factor`)."""
    track_dof: F64 | None = None
    """(G,) ν₀: how far one track's noise may stray from its class's (the prior degrees of freedom of a track's
    own scale, :func:`~.window_kernel.calibrated_windows`); None: :data:`PRIOR_TRACK_DOF` for every group."""
    scale_dof: float = math.inf
    """Degrees of freedom of the scales themselves: how well the calibration knows them. ∞ for scales taken as
    given (a calibration file); the online fit sets :data:`PRIOR_SCALE_DOF` plus :data:`BLOCK_DOF` per block
    of evidence behind the all-classes level, so that a cold start, which has nothing but the prior k = 1,
    tests with heavier tails (:meth:`test_dof`) until the data has spoken."""

    def __post_init__(self) -> None:
        if self.track_dof is None:
            object.__setattr__(self, "track_dof", np.full(len(GROUPS), PRIOR_TRACK_DOF))

    @staticmethod
    def prior(band_edges_m: Sequence[float] = (20.0, 40.0)) -> "NoiseModel":
        """Reported variances taken as they are (k = 1) with the prior correlation model."""
        g, b, y = len(GROUPS), len(band_edges_m) + 1, len(AGES)
        return NoiseModel(tuple(float(e) for e in band_edges_m), np.ones((g, 2, b, y)),
                          np.full((g, 2), PRIOR_CORRELATION), np.full((g, 2), PRIOR_TAU_S), np.zeros((g, 2, b, y)))

    def test_dof(self, groups: NDArray[np.int64]) -> F64:
        """Prior degrees of freedom of a track's own scale in the test (per window of class group ``groups``):
        the spread of tracks about their class (ν₀) and the class scale's own uncertainty add up in the log
        domain (Var log χ²_ν/ν ≈ 2/ν), so 1/ν = 1/ν₀ + 1/``scale_dof``."""
        assert self.track_dof is not None
        return 1.0 / (1.0 / self.track_dof[groups] + 1.0 / self.scale_dof)

    def variance_factor(self, window: int) -> F64:
        """(G, 2): Var(μ̄₂ − μ̄₁) of a full, evenly spaced window under the serial correlation, divided by its
        value for independent observations (1: no correlation; window/2: each half moves as one, the
        paper's ``cluster`` assumption)."""
        t = np.arange(window) * self.frame_interval_s
        h = window // 2
        w = np.r_[np.full(h, -1.0 / h), np.full(window - h, 1.0 / (window - h))]
        phi = np.exp(-np.abs(t[:, None] - t[None, :])[None, None] / self.tau_s[..., None, None])
        R = (1 - self.correlation)[..., None, None] * np.eye(window) + self.correlation[..., None, None] * phi
        return np.einsum("i,gaij,j->ga", w, R, w) / float(w @ w)

    def bands(self, range_m: F64) -> NDArray[np.int64]:
        """Range-band index of ranges in metres."""
        return np.searchsorted(np.asarray(self.band_edges_m, dtype=np.float64), range_m, side="right")

    def to_mapping(self, window: int = 10) -> dict[str, Any]:
        """Plain nested dict (the calibration file's ``groups`` and what ``/v1/state`` shows); ``window`` sets
        the window of the reported ``variance_factor``."""
        names = band_names(self.band_edges_m)
        factor = self.variance_factor(window)
        out: dict[str, Any] = {}
        assert self.track_dof is not None
        for gi, g in enumerate(GROUPS):
            out[g] = {"track_dof": round(float(self.track_dof[gi]), 4)}
            for ai, a in enumerate(AXES):
                out[g][a] = {
                    **{_key("scale", y): {n: round(float(self.scale[gi, ai, bi, yi]), 6) for bi, n in enumerate(names)}
                       for yi, y in enumerate(AGES)},
                    **{_key("blocks", y): {n: round(float(self.blocks[gi, ai, bi, yi]), 3)
                                           for bi, n in enumerate(names)} for yi, y in enumerate(AGES)},
                    "correlation": round(float(self.correlation[gi, ai]), 6),
                    "correlation_time_s": round(float(self.tau_s[gi, ai]), 6),
                    "variance_factor": round(float(factor[gi, ai]), 6),
                }
        return {"range_bands_m": list(self.band_edges_m), "frame_interval_s": round(self.frame_interval_s, 6),
                "window": window, "groups": out}

    @staticmethod
    def from_mapping(data: Mapping[str, Any]) -> "NoiseModel":
        """Inverse of :meth:`to_mapping`; raises ValueError naming the first bad entry. Groups or axes left out
        keep the prior; every value must be finite and in range."""
        if not isinstance(data, Mapping):
            raise ValueError("calibration: expected a mapping")
        _known_keys(data, TOP_KEYS, "")  # a misspelt key had left its scales at the prior of 1, silently
        edges = data.get("range_bands_m", [20.0, 40.0])
        # the classifier config's own bounds (at most 8 edges of at most 1000 m); `true` is no distance (it had
        # read as a 1 m band)
        if (not isinstance(edges, list) or len(edges) > 8
                or not all(isinstance(e, (int, float)) and not isinstance(e, bool) and math.isfinite(e)
                           and 0 < e <= 1000 for e in edges) or list(edges) != sorted(set(edges))):
            raise ValueError("range_bands_m: expected at most 8 increasing distances in (0, 1000] m")
        model = NoiseModel.prior(edges)
        scale, corr, tau, blocks = model.scale.copy(), model.correlation.copy(), model.tau_s.copy(), model.blocks.copy()
        track_dof = np.full(len(GROUPS), PRIOR_TRACK_DOF)
        names = band_names(model.band_edges_m)
        groups = data.get("groups", {})
        if not isinstance(groups, Mapping):
            raise ValueError("groups: expected a mapping")
        for g, axes in groups.items():
            if g not in GROUPS:
                raise ValueError(f"groups.{g}: unknown group; expected some of {list(GROUPS)}")
            if not isinstance(axes, Mapping):
                raise ValueError(f"groups.{g}: expected a mapping of axes")
            gi = GROUPS.index(g)
            for a, entry in axes.items():
                where = f"groups.{g}.{a}"
                if a == "track_dof":
                    track_dof[gi] = _checked(entry, f"groups.{g}.track_dof", TRACK_DOF_BOUNDS[0], TRACK_DOF_BOUNDS[1])
                    continue
                if a not in AXES or not isinstance(entry, Mapping):
                    raise ValueError(f"{where}: expected one of {list(AXES)} with a mapping")
                _known_keys(entry, AXIS_KEYS, f"{where}.")
                ai = AXES.index(a)
                for yi, y in enumerate(AGES):
                    key = _key("scale", y)
                    sc = entry.get(key, {})
                    if not isinstance(sc, Mapping) or set(sc) - set(names):
                        raise ValueError(f"{where}.{key}: expected a mapping over bands {names}")
                    for bn, v in sc.items():
                        scale[gi, ai, names.index(bn), yi] = _checked(v, f"{where}.{key}.{bn}", *SCALE_BOUNDS)
                    bkey = _key("blocks", y)
                    bl = entry.get(bkey, {})  # a key left empty (`blocks:`, a file cut short) is no mapping
                    if not isinstance(bl, Mapping):
                        raise ValueError(f"{where}.{bkey}: expected a mapping over bands {names}")
                    if set(bl) - set(names):  # a misspelt band had been skipped unsaid (under scale: refused)
                        raise ValueError(f"{where}.{bkey}: expected a mapping over bands {names}")
                    for bn, v in bl.items():
                        blocks[gi, ai, names.index(bn), yi] = _checked(v, f"{where}.{bkey}.{bn}", 0.0, 1e12)
                if "variance_factor" in entry:  # derived on reading, but a number in the file all the same
                    _checked(entry["variance_factor"], f"{where}.variance_factor", 1e-6, 1e6)
                if "correlation" in entry:
                    corr[gi, ai] = _checked(entry["correlation"], f"{where}.correlation", 0.0, 1.0)
                if "correlation_time_s" in entry:
                    tau[gi, ai] = _checked(entry["correlation_time_s"], f"{where}.correlation_time_s", 1e-3, 1e3)
        dt = _checked(data.get("frame_interval_s", CANONICAL_DT_S), "frame_interval_s", 1e-4, 1e3)
        if "window" in data and (isinstance(data["window"], bool) or not isinstance(data["window"], int)
                                 or not 2 <= data["window"] <= 10_000):  # the window the factors were written for
            raise ValueError(f"window: expected a whole number of observations in [2, 10000], got {data['window']!r}")
        return NoiseModel(model.band_edges_m, scale, corr, tau, blocks, dt, track_dof)


def _key(name: str, age: str) -> str:
    """Mapping key of a per-age entry: ``scale`` (established tracks) and ``scale_young``."""
    return name if age == AGES[0] else f"{name}_{age}"


TOP_KEYS = frozenset({"format", "range_bands_m", "frame_interval_s", "window", "groups", "source", "counts"})
"""What a calibration file's top level may hold (what :meth:`NoiseModel.to_mapping` and the file writer write)."""
AXIS_KEYS = frozenset({_key(n, y) for n in ("scale", "blocks") for y in AGES}
                      | {"correlation", "correlation_time_s", "variance_factor"})
"""What one group's axis may hold (``variance_factor`` is written for people and derived on reading)."""


def _known_keys(data: Mapping[str, Any], allowed: frozenset[str], where: str) -> None:
    unknown = sorted(str(k) for k in data if k not in allowed)
    if unknown:
        raise ValueError(f"{where}{unknown[0]}: unknown key; expected some of {sorted(allowed)}")


def _checked(v: Any, where: str, lo: float, hi: float) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not lo <= v <= hi:
        raise ValueError(f"{where}: expected a number in [{lo:g}, {hi:g}], got {v!r}")
    return float(v)


# ---------------------------------------------------------------------------------------------- one block


@dataclass(frozen=True)
class BlockMoments:
    """Per block: what its moments are made of — the stamps, the reported σ and the normalised residuals on each
    line-of-sight axis. The matrices of the module docstring, the observed ε̃ ε̃ᵀ = r rᵀ and its expectations per
    unit model G Gᵀ and G Φ_τ Gᵀ (G = D⁻¹ M D, D = diag σ), are formed from these by the compiled pooling
    (:func:`~.block_kernel.pool_blocks`) straight into the cells' sums, never stored per block; the dense
    matrices are properties (tests, pseudo-blocks)."""

    t: F64  # (N, n) stamps [s]
    sig: F64  # (N, 2, n) reported σ along / across the line of sight (after the variance floor)
    r: F64  # (N, 2, n) normalised residuals about the block's constant-velocity line
    range_m: F64  # (N,) mean distance from the sensor
    interval_s: F64  # (N,) mean time between two observations
    speed: F64  # (N,) speed of the fitted line

    def __len__(self) -> int:
        return int(self.r.shape[0])

    @property
    def size(self) -> int:
        return int(self.r.shape[-1])

    @property
    def Y(self) -> F64:  # noqa: N802 - the module's notation
        """(N, 2, n, n) observed ε̃ ε̃ᵀ."""
        return self.r[..., :, None] * self.r[..., None, :]

    @property
    def Ew(self) -> F64:  # noqa: N802
        """(N, 2, n, n) expectation for white noise of unit variance: G Gᵀ."""
        return self._dense()[0]

    @property
    def Et(self) -> F64:  # noqa: N802
        """(N, 2, T, n, n) expectation for unit-variance exp(−|Δt|/τ) noise, τ = TAU_GRID_S[t]: G Φ Gᵀ."""
        return self._dense()[1]

    def _dense(self) -> tuple[F64, F64]:
        """(G Gᵀ, G Φ Gᵀ) per block: each block pooled alone, with weight 1, into a cell of its own."""
        N, n, T = len(self), self.size, len(TAU_GRID_S)
        Ew, Et = np.zeros((N, 2, 1, 1, n * n)), np.zeros((N, 2, 1, 1, n * n, T))
        cell, zeros, ones = np.arange(N, dtype=np.int64), np.zeros(N, np.int64), np.ones((N, 2))
        pool_blocks(self.t, self.sig, self.r, np.ones(N, dtype=np.bool_), cell, zeros, zeros, ones, ones * 0.5,
                    np.zeros((N, 2), np.int64), np.zeros((N, 2)), TAU_GRID_S, math.inf, np.zeros_like(Ew), Ew, Et,
                    np.zeros((N, 2, 1, 1)), n, np.empty((N, 2)), np.empty((N, 2)))
        return Ew[:, :, 0, 0].reshape(N, 2, n, n), np.moveaxis(Et[:, :, 0, 0].reshape(N, 2, n, n, T), -1, 2)

    def subset(self, keep: NDArray[np.int64]) -> "BlockMoments":
        """The blocks ``keep`` (indices)."""
        return BlockMoments(*(getattr(self, f.name)[keep] for f in fields(self)))

    def finite(self) -> NDArray[np.bool_]:
        """Blocks whose moments are finite numbers: stamps, residuals and σ finite, and bounded so that their
        products are (σ enters the expectations as σ_i / σ_j, a residual of 1e200 squares to inf)."""
        ok = np.isfinite(self.range_m) & np.isfinite(self.speed)
        if self.size:  # NaN compares False: not finite
            ok &= (np.abs(self.t).max(axis=1) < 1e150) & (np.abs(self.r).max(axis=(1, 2)) < 1e150)
            ok &= (self.sig.max(axis=(1, 2)) < 1e50) & (self.sig.min(axis=(1, 2)) > 0)
        return ok


def line_of_sight(pos: F64, sensor: F64) -> tuple[F64, F64, F64]:
    """Unit vectors u (sensor → object), v (u turned +90°) and the range, for positions ``(..., 2)``."""
    d = pos - sensor
    rng = np.hypot(d[..., 0], d[..., 1])
    ok = rng > 1e-6
    safe = np.where(ok, rng, 1.0)
    ux = np.where(ok, d[..., 0] / safe, 1.0)
    uy = np.where(ok, d[..., 1] / safe, 0.0)
    return np.stack([ux, uy], axis=-1), np.stack([-uy, ux], axis=-1), rng


def project_covariance(u: F64, v: F64, cov: F64) -> tuple[F64, F64, F64]:
    """(uᵀΣu, vᵀΣv, uᵀΣv) of covariances ``cov[..., (xx, xy, yy)]``."""
    cxx, cxy, cyy = cov[..., 0], cov[..., 1], cov[..., 2]
    uu = u[..., 0] ** 2 * cxx + 2 * u[..., 0] * u[..., 1] * cxy + u[..., 1] ** 2 * cyy
    vv = v[..., 0] ** 2 * cxx + 2 * v[..., 0] * v[..., 1] * cxy + v[..., 1] ** 2 * cyy
    uv = u[..., 0] * v[..., 0] * cxx + (u[..., 0] * v[..., 1] + u[..., 1] * v[..., 0]) * cxy + u[..., 1] * v[..., 1] * cyy
    return uu, vv, uv


def block_moments(t: F64, pos: F64, cov: F64, sensor: F64, *, variance_floor: float = 1e-4) -> BlockMoments:
    """The normalised constant-velocity residuals of N blocks of n observations each, with what
    :meth:`OnlineCalibration.add` needs to pool their moments (:class:`BlockMoments`).

    ``t`` (N, n) seconds (spread: a block whose times are all equal has no line to fit — the caller drops
    it), ``pos`` (N, n, 2) world positions, ``cov`` (N, n, 3) reported world covariances (xx, xy, yy),
    ``sensor`` (N, n, 2) the sensor's position at each observation. The line-of-sight axes are taken per
    observation, to the fitted line's position at that time (not the observed one); the residuals are those of the
    world-frame line fit projected on them."""
    with np.errstate(over="ignore", invalid="ignore"):  # non-finite blocks are dropped by the pooling
        t = np.ascontiguousarray(t, dtype=np.float64)
        n = t.shape[1]
        tc = t - t.mean(axis=1, keepdims=True)
        stt = np.maximum((tc * tc).sum(axis=1), 1e-12)
        vel = (tc[:, :, None] * pos).sum(axis=1) / stt[:, None]
        E = pos - pos.mean(axis=1, keepdims=True) - tc[:, :, None] * vel[:, None, :]  # residuals about the line
        # the axes point at the fitted line, not at each observation: at the sensor the observed direction turns
        # with the error itself and would put all of it along the line of sight
        u, v, rng = line_of_sight(pos - E, sensor)
        var_u, var_v, _ = project_covariance(u, v, cov)
        sig = np.sqrt(np.maximum(np.stack([var_u, var_v], axis=1), variance_floor))  # (N, 2, n)
        r = np.stack([(E * u).sum(-1), (E * v).sum(-1)], axis=1) / sig  # (N, 2, n)
        return BlockMoments(t, sig, r, rng.mean(axis=1), (t[:, -1] - t[:, 0]) / max(n - 1, 1),
                            np.hypot(vel[:, 0], vel[:, 1]))


@lru_cache(maxsize=16)
def canonical_moments(n: int, dt_s: float = CANONICAL_DT_S) -> tuple[F64, F64]:
    """(Ew, Et) of one evenly spaced block of ``n`` observations with equal variances (for pseudo-blocks);
    cached, so the arrays are shared: do not modify them."""
    t = np.arange(n, dtype=np.float64)[None] * dt_s
    pos = np.zeros((1, n, 2))
    pos[..., 0] = 10.0
    cov = np.tile(np.array([1.0, 0.0, 1.0]), (1, n, 1))
    m = block_moments(t, pos, cov, np.zeros((1, n, 2)))
    return m.Ew[0, 0], m.Et[0, 0]


def warm_up() -> None:
    """Compile (or load from numba's cache) the compiled pooling now — a service that learns (the classifier, the
    tracker's measurement scale) calls it at start, so its first pooled window does not pay the compilation."""
    t = np.arange(MIN_BLOCK, dtype=np.float64)[None] * 0.1
    pos = np.full((1, MIN_BLOCK, 2), 10.0)
    cov = np.tile(np.array([0.01, 0.0, 0.01]), (1, MIN_BLOCK, 1))
    OnlineCalibration(window=MIN_BLOCK).add(np.zeros(1, dtype=np.int64), block_moments(t, pos, cov, pos * 0.0))


# ---------------------------------------------------------------------------------------------- the fit


def _nnls2(s: F64, a: F64, b: F64) -> tuple[F64, F64, F64]:
    """min ‖s − α a − β b‖² over α, β ≥ 0 along the last axis (broadcast); returns (α, β, residual²)."""
    aa, bb, ab = (a * a).sum(-1), (b * b).sum(-1), (a * b).sum(-1)
    as_, bs, ss = (a * s).sum(-1), (b * s).sum(-1), (s * s).sum(-1)

    def sse(al: F64, be: F64) -> F64:
        return ss - 2 * (al * as_ + be * bs) + al * al * aa + 2 * al * be * ab + be * be * bb

    det = aa * bb - ab * ab
    ok = det > 1e-12 * np.maximum(aa * bb, 1e-300)
    safe = np.where(ok, det, 1.0)
    al2 = np.where(ok, (bb * as_ - ab * bs) / safe, -1.0)
    be2 = np.where(ok, (aa * bs - ab * as_) / safe, -1.0)
    cands = [
        (al2, be2, (al2 >= 0) & (be2 >= 0)),
        (np.maximum(as_ / np.maximum(aa, 1e-300), 0.0), np.zeros_like(aa), np.ones_like(ok)),
        (np.zeros_like(aa), np.maximum(bs / np.maximum(bb, 1e-300), 0.0), np.ones_like(ok)),
    ]
    best_al, best_be, best = np.zeros_like(aa), np.zeros_like(aa), np.full_like(aa, np.inf)
    for al, be, feasible in cands:
        e = np.where(feasible, sse(al, be), np.inf)
        take = e < best
        best_al, best_be, best = np.where(take, al, best_al), np.where(take, be, best_be), np.where(take, e, best)
    return best_al, best_be, best


def fit_shape(S: F64, A: F64, B: F64) -> tuple[F64, F64, F64]:
    """(k, m, τ) per leading index from pooled sums S (…, L), A (…, L), B (…, L, T): the τ on the grid whose
    non-negative least-squares fit of S ≈ k[(1 − m)A + m B(τ)] leaves the least residual."""
    al, be, err = _nnls2(S[..., None, :], A[..., None, :], np.moveaxis(B, -1, -2))  # (…, T)
    t = np.argmin(err, axis=-1)
    pick = lambda x: np.take_along_axis(x, t[..., None], axis=-1)[..., 0]  # noqa: E731
    al, be = pick(al), pick(be)
    k = al + be
    m = np.where(k > 0, be / np.where(k > 0, k, 1.0), PRIOR_CORRELATION)
    return np.clip(k, *SCALE_BOUNDS), m, TAU_GRID_S[t]


def _tau_interpolation(tau_s: F64) -> tuple[NDArray[np.int64], F64]:
    """Grid index i and weight w of τ between TAU_GRID_S[i] and [i + 1], linear in log τ."""
    lt = np.log(TAU_GRID_S)
    x = np.clip(np.log(np.asarray(tau_s, dtype=np.float64)), lt[0], lt[-1])
    i = np.clip(np.searchsorted(lt, x) - 1, 0, len(lt) - 2)
    return i, (x - lt[i]) / (lt[i + 1] - lt[i])


def at_tau(B: F64, tau_s: F64) -> F64:
    """B (…, L, T), given on the grid of correlation times, at τ = ``tau_s`` (its leading axes broadcast against
    B's): interpolated between the two grid points around it, linearly in log τ."""
    i, w = _tau_interpolation(tau_s)
    pick = lambda j: np.take_along_axis(B, j[..., None, None], axis=-1)[..., 0]  # noqa: E731
    return (1 - w)[..., None] * pick(i) + w[..., None] * pick(i + 1)


def expected_moments(A: F64, B: F64, k: F64, m: F64, tau_s: F64) -> F64:
    """k[(1 − m) A + m B(τ)] with τ interpolated on the grid in log τ (broadcast over leading axes)."""
    return np.asarray(k)[..., None] * ((1 - np.asarray(m))[..., None] * A + np.asarray(m)[..., None] * at_tau(B, tau_s))


@lru_cache(maxsize=1)
def _track_dof_grid() -> tuple[F64, F64]:
    """The ν₀ a fit can choose (400 points over :data:`TRACK_DOF_BOUNDS`) and ψ'(ν₀/2) on them, which decreases in
    ν₀ (computed once: a fit looks it up five times). Cached, so the arrays are shared: do not modify them."""
    from scipy.special import polygamma  # type: ignore[import-untyped]

    grid = np.geomspace(*TRACK_DOF_BOUNDS, 400)
    return grid, polygamma(1, grid / 2)


# ---------------------------------------------------------------------------------------------- online


@dataclass
class OnlineCalibration:
    """Pooled block statistics per (group, axis, range band) with forgetting, and the :class:`NoiseModel` they
    give. ``prior_blocks``: pseudo-blocks at each level of the hierarchy; ``half_life_s``: data time after
    which a block counts half; ``window``: the longest block expected (longer ones grow the sums)."""

    band_edges_m: tuple[float, ...] = (20.0, 40.0)
    prior_blocks: float = 20.0
    half_life_s: float = 600.0
    window: int = 10
    refit_period_s: float = REFIT_PERIOD_S
    _fitted_at_s: float | None = field(default=None, init=False, repr=False)
    _Y: F64 = field(init=False, repr=False)  # (G, 2, B, Y, n²)
    _Ew: F64 = field(init=False, repr=False)  # (G, 2, B, Y, n²)
    _Et: F64 = field(init=False, repr=False)  # (G, 2, B, Y, n², T)
    _n: F64 = field(init=False, repr=False)  # (G, 2, B, Y) effective blocks
    _interval: F64 = field(init=False, repr=False)  # (2,) Σ w·interval, Σ w
    _het: F64 = field(init=False, repr=False)  # (G, 4) Σ w·y, Σ w·y², Σ w·ψ'(ν_b/2), Σ w  (track heterogeneity)
    _stamp_s: float | None = field(default=None, init=False, repr=False)
    _model: NoiseModel = field(init=False, repr=False)
    _dirty: bool = field(default=False, init=False, repr=False)
    counts: dict[str, int] = field(default_factory=dict, init=False)

    def __post_init__(self) -> None:
        self.band_edges_m = tuple(float(e) for e in self.band_edges_m)
        g, b, y, nn, T = len(GROUPS), len(self.band_edges_m) + 1, len(AGES), self.window ** 2, len(TAU_GRID_S)
        self._Y = np.zeros((g, 2, b, y, nn))
        self._Ew = np.zeros((g, 2, b, y, nn))
        self._Et = np.zeros((g, 2, b, y, nn, T))
        self._n = np.zeros((g, 2, b, y))
        self._interval = np.zeros(2)
        self._het = np.zeros((g, 4))
        self._model = replace(NoiseModel.prior(self.band_edges_m), scale_dof=PRIOR_SCALE_DOF)  # and how little it knows
        self.counts = {"blocks": 0, "blocks_fast": 0, "blocks_downweighted": 0, "blocks_invalid": 0}

    @property
    def effective_blocks(self) -> float:
        """Blocks behind the current model after forgetting (each block counts once, both axes together)."""
        return float(self._n.sum() / 2)

    def advance(self, stamp_s: float) -> None:
        """Forget with the data's clock: every sum decays by 2^(−Δt / half_life) since the last stamp. A stamp
        behind the last one (a recording that started over) restarts the clock without forgetting."""
        if self._stamp_s is None or stamp_s < self._stamp_s:
            self._stamp_s = stamp_s
            self._fitted_at_s = None
            return
        if stamp_s > self._stamp_s and self.half_life_s > 0:
            f = 0.5 ** ((stamp_s - self._stamp_s) / self.half_life_s)
            for arr in (self._Y, self._Ew, self._Et, self._n, self._interval, self._het):
                arr *= f
            self._dirty = True
        self._stamp_s = stamp_s

    def _grow(self, n: int) -> None:
        """Embed the sums in n × n (a longer window): leading entries keep their meaning."""
        k = self.window
        lead = self._n.shape
        T = len(TAU_GRID_S)

        def pad(a: F64, tail: tuple[int, ...]) -> F64:
            a = a.reshape(*lead, k, k, *tail)
            widths = [(0, 0)] * len(lead) + [(0, n - k), (0, n - k)] + [(0, 0)] * len(tail)
            return np.pad(a, widths).reshape(*lead, n * n, *tail)

        self._Y, self._Ew, self._Et = pad(self._Y, ()), pad(self._Ew, ()), pad(self._Et, (T,))
        self.window = n

    def set_window(self, n: int) -> None:
        """Blocks will be ``n`` observations long (the classifier sized its window to the stream's rate): an
        estimator that has pooled nothing starts over at that size, so its prior's pseudo-blocks are blocks of
        ``n``; one that has pooled blocks keeps them (grown if ``n`` is longer; shorter blocks pool into the
        larger sums as they are)."""
        if self._n.sum() == 0 and self._het[:, 3].sum() == 0 and n != self.window:
            counts = self.counts
            self.window = n
            self.__post_init__()
            self.counts = counts
        elif n > self.window:
            self._grow(n)

    def add(self, groups: NDArray[np.int64], mom: BlockMoments, young: NDArray[np.bool_] | None = None) -> None:
        """Pool N blocks (``groups`` their class-group index, ``young`` whether each is a track's first) with
        Huber weights against the current model. Blocks faster than :data:`MAX_BLOCK_SPEED` are counted, not
        pooled."""
        finite = mom.finite()
        if not finite.all():  # positions far beyond any sensor (a broken upstream): nothing to learn from them
            self.counts["blocks_invalid"] += int((~finite).sum())
            keep = np.flatnonzero(finite)
            mom = mom.subset(keep)
            groups = np.asarray(groups)[keep]
            young = None if young is None else np.asarray(young)[keep]
        if len(mom) == 0:
            return
        if mom.size > self.window:
            self._grow(mom.size)
        model = self.model()
        band = model.bands(mom.range_m).astype(np.int64)
        g = np.asarray(groups, dtype=np.int64)
        age = np.zeros(len(g), np.int64) if young is None else np.asarray(young, dtype=np.int64)
        k = np.ascontiguousarray(model.scale[g, :, band, age])  # (N, 2)
        tau_i, tau_w = _tau_interpolation(model.tau_s[g])  # (N, 2): the group's τ between two grid points
        slow = mom.speed <= MAX_BLOCK_SPEED
        w, het = np.empty((len(g), 2)), np.empty((len(g), 2))
        pool_blocks(mom.t, mom.sig, mom.r, slow, g, band, age, k, np.ascontiguousarray(model.correlation[g]),
                    tau_i.astype(np.int64), tau_w, TAU_GRID_S, HUBER_C, self._Y, self._Ew, self._Et, self._n,
                    self.window, w, het)
        self._interval += (float(mom.interval_s[slow].sum()), float(slow.sum()))
        self._add_heterogeneity(g[slow], het[slow], (mom.r[slow] ** 2).sum((1, 2)), w[slow])
        self.counts["blocks"] += int(slow.sum())
        self.counts["blocks_fast"] += int((~slow).sum())
        self.counts["blocks_downweighted"] += int(((w < 1.0) & slow[:, None]).any(axis=1).sum())
        self._dirty = True

    def _add_heterogeneity(self, g: NDArray[np.int64], het: F64, S0: F64, w: F64) -> None:
        """Pool, per group, the spread of the blocks' own scales around the model's: y_b = log(q_b) minus the
        mean of log(χ²_ν/ν), q_b = S_b / E[S_b] (both axes together), ν_b the block's Satterthwaite degrees
        of freedom (tr Q)² / ‖Q‖²_F from ``het`` = (tr Q, ‖Q‖²_F), Q the model's covariance of the block's
        residuals (:func:`~.block_kernel.pool_blocks`); ``S0`` = the block's Σ r². Var(y) − mean ψ'(ν_b/2)
        estimates Var(log λ) of the tracks' own scales (the rest is the χ² spread of a block) — an
        empirical-Bayes estimate of the per-track prior ν₀."""
        trace, trace2 = het[:, 0], het[:, 1]
        ok = (trace > 0) & (trace2 > 0) & (S0 > 0)
        if not ok.any():
            return
        from scipy.special import digamma, polygamma  # type: ignore[import-untyped]

        nu = trace[ok] ** 2 / trace2[ok]
        y = np.log(S0[ok] / trace[ok]) - (digamma(nu / 2) - np.log(nu / 2))
        wt = w[ok].min(axis=1)  # a down-weighted block counts less here too
        tri = polygamma(1, nu / 2)
        for col, val in enumerate((wt * y, wt * y * y, wt * tri, wt)):
            self._het[:, col] += np.bincount(g[ok], weights=val, minlength=len(GROUPS))

    def _track_dof(self) -> F64:
        """ν₀ per group from the pooled heterogeneity (group, else all groups, else the prior), bounded."""
        grid, trigamma = _track_dof_grid()

        def solve(h: F64) -> float:
            if h[3] < MIN_HETEROGENEITY_BLOCKS:
                return math.nan
            mean = h[0] / h[3]
            var_log_lambda = h[1] / h[3] - mean * mean - h[2] / h[3]
            if var_log_lambda <= 0:
                return TRACK_DOF_BOUNDS[1]
            return float(grid[np.argmin(np.abs(trigamma - var_log_lambda))])

        overall = solve(self._het.sum(axis=0))
        fallback = PRIOR_TRACK_DOF if math.isnan(overall) else overall
        return np.array([fallback if math.isnan(v := solve(h)) else v for h in self._het])

    @property
    def current(self) -> NoiseModel:
        """The model as last fitted (no fitting here: what a decision uses)."""
        return self._model

    _STATE = ("_Y", "_Ew", "_Et", "_n", "_interval", "_het")

    def state(self) -> dict[str, np.ndarray]:
        """What the estimator has pooled, as plain arrays (copies): enough for :meth:`restore` to go on from
        here in another process. The grids it is pooled on (groups, ages, correlation times, range bands,
        window) travel with it, so a restore can tell a state it cannot use."""
        out = {name.lstrip("_"): getattr(self, name).copy() for name in self._STATE}
        out.update(band_edges_m=np.asarray(self.band_edges_m, np.float64), window=np.asarray(self.window),
                   groups=np.asarray(GROUPS), ages=np.asarray(AGES), tau_grid_s=TAU_GRID_S.copy(),
                   counts_keys=np.asarray(list(self.counts)), counts=np.asarray(list(self.counts.values())))
        return out

    def restore(self, state: Mapping[str, np.ndarray], *, max_blocks: float | None = None) -> float:
        """Go on from a :meth:`state` (of another process, e.g. before a restart): its pooled sums replace
        this estimator's and the model is refitted. ``max_blocks`` caps the evidence taken over: sums whose
        effective blocks exceed it are scaled down to it, so that what a restart inherits is a prior that the
        new data overrides within about that many blocks (a detector swapped between the two runs is not
        trusted for long). Returns the effective blocks restored. Raises ``ValueError`` (naming the mismatch)
        for a state pooled on other grids or range bands, or with arrays of the wrong shape or non-finite."""
        def grid(name: str) -> np.ndarray:
            if name not in state:
                raise ValueError(f"missing {name!r}")
            return np.asarray(state[name])

        if tuple(grid("groups").tolist()) != GROUPS or tuple(grid("ages").tolist()) != AGES:
            raise ValueError("pooled for other class groups or ages")
        if not np.array_equal(grid("tau_grid_s"), TAU_GRID_S):
            raise ValueError("pooled on another grid of correlation times")
        edges = tuple(float(e) for e in grid("band_edges_m").tolist())
        if edges != self.band_edges_m:
            raise ValueError(f"pooled for range bands {list(edges)} m, the config has {list(self.band_edges_m)}")
        window = int(grid("window"))
        if not 1 <= window <= 1000:
            raise ValueError(f"window {window} out of range")
        g, b, y, T = len(GROUPS), len(edges) + 1, len(AGES), len(TAU_GRID_S)
        shapes = {"Y": (g, 2, b, y, window ** 2), "Ew": (g, 2, b, y, window ** 2), "Et": (g, 2, b, y, window ** 2, T),
                  "n": (g, 2, b, y), "interval": (2,), "het": (g, 4)}
        arrays = {}
        for name, shape in shapes.items():
            a = np.asarray(grid(name), dtype=np.float64)
            if a.shape != shape or not np.isfinite(a).all():
                raise ValueError(f"{name!r} has shape {a.shape} (expected {shape}) or non-finite values")
            arrays[name] = a.copy()
        if (arrays["n"] < 0).any():
            raise ValueError("negative block counts")
        blocks = float(arrays["n"].sum() / 2)
        if max_blocks is not None and blocks > max_blocks:
            f = max_blocks / blocks
            for name in arrays:
                arrays[name] *= f
            blocks = max_blocks
        here = self.window
        self.window = window
        for name, a in arrays.items():
            setattr(self, "_" + name, a)
        if here > window:
            self._grow(here)
        keys, values = grid("counts_keys").tolist(), grid("counts").tolist()
        self.counts = {**{k: 0 for k in self.counts}, **{str(k): int(v) for k, v in zip(keys, values)}}
        self._stamp_s = None  # the next stamp restarts the data clock (no forgetting across the gap)
        self.refit()
        return blocks

    def model(self) -> NoiseModel:
        """The current :class:`NoiseModel`: refitted when blocks arrived or sums decayed, at most once per
        ``refit_period_s`` of data time (a fit costs about a millisecond; the scales move slowly)."""
        due = (self._fitted_at_s is None or self._stamp_s is None
               or self._stamp_s - self._fitted_at_s >= self.refit_period_s)
        if self._dirty and due:
            self._model = self._fit()
            self._dirty = False
            self._fitted_at_s = self._stamp_s
        return self._model

    def refit(self) -> NoiseModel:
        """Fit now, whatever the period (for a final snapshot, e.g. ``jitterguard calibrate``)."""
        self._model = self._fit()
        self._dirty = False
        self._fitted_at_s = self._stamp_s
        return self._model

    def _pseudo(self, Y: F64, Ew: F64, Et: F64, n: F64, k: F64, m: F64, tau: F64,
                blocks: float | None = None) -> tuple[F64, F64, F64]:
        """Sums plus ``blocks`` (default ``prior_blocks``) pseudo-blocks of the level's average block, drawn
        from (k, m, τ)."""
        cw, ct = canonical_moments(self.window)
        cw, ct = cw.reshape(-1), np.swapaxes(ct.reshape(len(TAU_GRID_S), -1), 0, 1)
        have = n[..., None] > 1e-9
        safe_n = np.where(n > 1e-9, n, 1.0)[..., None]
        Wbar = np.where(have, Ew / safe_n, cw)
        Tbar = np.where(have[..., None], Et / safe_n[..., None], ct)
        n0 = self.prior_blocks if blocks is None else blocks
        return (Y + n0 * expected_moments(Wbar, Tbar, k, m, tau), Ew + n0 * Wbar, Et + n0 * Tbar)

    def _fit(self) -> NoiseModel:
        if self.window < MIN_BLOCK:  # no block is ever pooled, and a prior of 2–4-observation blocks fits nothing:
            # its pseudo-blocks are rank-deficient after the line fit (k came out 0.57–1.57, not the prior's 1)
            return replace(NoiseModel.prior(self.band_edges_m), scale_dof=PRIOR_SCALE_DOF)
        Y, Ew, Et, n = self._Y, self._Ew, self._Et, self._n
        Y1, Ew1, Et1, n1 = Y.sum((2, 3)), Ew.sum((2, 3)), Et.sum((2, 3)), n.sum((2, 3))  # per group and axis
        # level 0: all groups, bands and ages, per axis; a weak prior at k = 1 and the prior shape (detectors are
        # often off by a factor: the data should win quickly here)
        ones = np.ones(2)
        k0, m0, t0 = fit_shape(*self._pseudo(Y1.sum(0), Ew1.sum(0), Et1.sum(0), n1.sum(0), ones,
                                             ones * PRIOR_CORRELATION, ones * PRIOR_TAU_S, TOP_PRIOR_BLOCKS))
        # level 1: per group and axis, shrunk to level 0
        g = len(GROUPS)
        k1, m1, t1 = fit_shape(*self._pseudo(Y1, Ew1, Et1, n1, np.broadcast_to(k0, (g, 2)),
                                             np.broadcast_to(m0, (g, 2)), np.broadcast_to(t0, (g, 2))))
        if self.prior_blocks <= 0:  # no prior and no block: nothing to fit, the level above stands (the fit of
            # nothing had come out k = 0, clipped to the lower bound: σ taken 10× too large where nobody measured)
            none1 = n1 <= 0
            k1, m1, t1 = (np.where(none1, np.broadcast_to(a, (g, 2)), b) for a, b in ((k0, k1), (m0, m1), (t0, t1)))
        # level 2: the scale per band and age, with the group's shape, shrunk to the group's scale — what
        # _pseudo and expected_moments do at levels 0 and 1, written out for one τ per group: everything here is
        # linear in the correlated sums, so they are taken at the group's τ first (at_tau) and the rest works on
        # one n² slice per cell rather than the whole grid
        lead = (slice(None), slice(None), None, None)  # (G, 2) → (G, 2, B, Y)
        tau = t1[lead]
        cw, ct = canonical_moments(self.window)
        cw, ct = cw.reshape(-1), np.swapaxes(ct.reshape(len(TAU_GRID_S), -1), 0, 1)  # (n²,), (n², T)
        ct_tau = at_tau(np.broadcast_to(ct, (*tau.shape, *ct.shape)), tau)  # (G, 2, 1, 1, n²)
        Et_tau = at_tau(Et, tau)  # (G, 2, B, Y, n²)
        have = n[..., None] > 1e-9
        safe_n = np.where(have, n[..., None], 1.0)
        Wbar, Tbar = np.where(have, Ew / safe_n, cw), np.where(have, Et_tau / safe_n, ct_tau)
        kb, mb, n0 = k1[(*lead, None)], m1[(*lead, None)], self.prior_blocks
        Yp = Y + n0 * kb * ((1 - mb) * Wbar + mb * Tbar)
        E = (1 - mb) * (Ew + n0 * Wbar) + mb * (Et_tau + n0 * Tbar)  # per unit scale
        k2 = np.clip((Yp * E).sum(-1) / np.maximum((E * E).sum(-1), 1e-300), *SCALE_BOUNDS)
        if n0 <= 0:  # as above: a cell without blocks or prior takes its group's scale
            k2 = np.where(n <= 0, np.broadcast_to(k1[lead], k2.shape), k2)
        dt = self._interval[0] / self._interval[1] if self._interval[1] > 0 else CANONICAL_DT_S
        scale_dof = PRIOR_SCALE_DOF + BLOCK_DOF * float(n.sum((0, 2, 3)).min())  # all classes, the poorer axis
        return NoiseModel(self.band_edges_m, k2, m1, t1, n.copy(), float(dt), self._track_dof(), scale_dof)

    def snapshot(self, window: int | None = None) -> dict[str, Any]:
        """The current model as :meth:`NoiseModel.to_mapping` plus the block counters."""
        return {**self._model.to_mapping(window or self.window), "counts": dict(self.counts)}
