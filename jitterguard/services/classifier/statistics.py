"""The test statistics of the motion classifier (paper §III-B), vectorised over tracks.

Inputs are windows stored as dense ``(K, W)`` arrays with a boolean mask per half, so one call scores every
track of a frame at once. Nothing here knows about tracks, IDs or messages.

Per axis (eq. 1, 2):  z = |μ̄₁ − μ̄₂| / sqrt(σ̂₁²/n₁ + σ̂₂²/n₂), with σ̂ᵢ² the mean predicted variance of half i,
floored at ``variance_floor``. ``cluster`` sets n₁ = n₂ = 1 (the paper's final method: serially correlated
detections are one sample each); ``independent`` uses the real counts (the authors' C++ code).

The optional ``chi2`` statistic is the frame-invariant 2-D version: Δμᵀ (Σ̂₁/n₁ + Σ̂₂/n₂)⁻¹ Δμ, compared with
the χ²₂ quantile that has the same false-alarm probability as a two-sided z-test at ``alpha``. Unlike
max(z_x, z_y) it does not change when the world frame is rotated, and its false-alarm rate is exactly the
nominal one when the predicted covariances are right (max over two axes roughly doubles it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


def two_sided_p(alpha: float | F64) -> F64:
    """P(|Z| > alpha) for a standard normal Z: the nominal false-alarm rate of one z-test axis."""
    a = np.asarray(alpha, dtype=np.float64)
    return np.vectorize(math.erfc, otypes=[np.float64])(a / math.sqrt(2.0))


def chi2_2_threshold(alpha: float | F64) -> F64:
    """The χ²₂ quantile with the same false-alarm rate as a two-sided z-test at ``alpha``.

    χ² with two degrees of freedom has survival function exp(-x/2), so the quantile is -2 ln p.
    """
    p = np.clip(two_sided_p(alpha), 1e-300, 1.0)
    return -2.0 * np.log(p)


@dataclass(frozen=True)
class HalfMasks:
    """Which window slots belong to the older and the newer half, per track."""

    old: NDArray[np.bool_]  # (K, W)
    new: NDArray[np.bool_]  # (K, W)
    n_old: F64  # (K,) floor(N/2)
    n_new: F64  # (K,) ceil(N/2)


def split_halves(head: NDArray[np.int64], count: NDArray[np.int64], window: int) -> HalfMasks:
    """Masks for a ring buffer whose next write slot is ``head`` and which holds ``count`` observations.

    The age rank of slot s is (head − 1 − s) mod W (0 = newest). The newer half is the ceil(N/2) youngest,
    the older half the floor(N/2) before them.
    """
    slots = np.arange(window, dtype=np.int64)
    rank = (head[:, None] - 1 - slots[None, :]) % window
    n_new = (count + 1) // 2
    valid = rank < count[:, None]
    new = rank < n_new[:, None]
    return HalfMasks(old=valid & ~new, new=new, n_old=(count // 2).astype(np.float64), n_new=n_new.astype(np.float64))


@dataclass(frozen=True)
class WindowStats:
    """Statistics of a batch of windows; every array is (K,)."""

    z_x: F64
    z_y: F64
    chi2: F64
    mean_x: F64  # mean over the whole window (the static output position)
    mean_y: F64


def _floor_min_eigen(a: F64, b: F64, c: F64, floor: float) -> tuple[F64, F64]:
    """Raise the smaller eigenvalue of [[a, b], [b, c]] to ``floor`` by adding a multiple of I."""
    lam_min = 0.5 * (a + c) - np.sqrt(0.25 * (a - c) ** 2 + b * b)
    shift = np.maximum(0.0, floor - lam_min)
    return a + shift, c + shift


CHANNELS = ("x", "y", "cxx", "cxy", "cyy")
"""Order of the last axis of a window array: position and the 2x2 world-frame covariance."""


def window_statistics(windows: F64, masks: HalfMasks, *, variance_floor: float, independent: bool) -> WindowStats:
    """z_x, z_y (eq. 1 with eq. 2) and the 2-D χ² statistic for every window in the batch.

    ``windows`` is ``(K, W, 5)`` over :data:`CHANNELS`. Each half's means of all five channels come out of
    one weighted contraction, so the cost is two passes over the batch whatever the statistic. A statistic
    that overflows saturates (:func:`_saturate`).
    """
    with np.errstate(over="ignore", invalid="ignore"):
        return _window_statistics(windows, masks, variance_floor=variance_floor, independent=independent)


def _window_statistics(windows: F64, masks: HalfMasks, *, variance_floor: float, independent: bool) -> WindowStats:
    n_old, n_new = masks.n_old, masks.n_new
    w_old = masks.old / np.maximum(n_old, 1.0)[:, None]
    w_new = masks.new / np.maximum(n_new, 1.0)[:, None]
    m_old = np.einsum("kwc,kw->ck", windows, w_old)
    m_new = np.einsum("kwc,kw->ck", windows, w_new)
    dx, dy = m_new[0] - m_old[0], m_new[1] - m_old[1]
    vxx_old, vxy_old, vyy_old = m_old[2], m_old[3], m_old[4]
    vxx_new, vxy_new, vyy_new = m_new[2], m_new[3], m_new[4]

    if independent:
        k_old, k_new = np.maximum(n_old, 1.0), np.maximum(n_new, 1.0)
    else:
        k_old = k_new = np.ones_like(n_old)

    sx = np.maximum(vxx_old, variance_floor) / k_old + np.maximum(vxx_new, variance_floor) / k_new
    sy = np.maximum(vyy_old, variance_floor) / k_old + np.maximum(vyy_new, variance_floor) / k_new
    z_x = np.abs(dx) / np.sqrt(sx)
    z_y = np.abs(dy) / np.sqrt(sy)

    a_old, c_old = _floor_min_eigen(vxx_old, vxy_old, vyy_old, variance_floor)
    a_new, c_new = _floor_min_eigen(vxx_new, vxy_new, vyy_new, variance_floor)
    a = a_old / k_old + a_new / k_new
    b = vxy_old / k_old + vxy_new / k_new
    c = c_old / k_old + c_new / k_new
    det = a * c - b * b
    chi2 = (c * dx * dx - 2.0 * b * dx * dy + a * dy * dy) / det

    n_all = np.maximum(n_old + n_new, 1.0)
    return WindowStats(
        z_x=_saturate(z_x),
        z_y=_saturate(z_y),
        chi2=_saturate(chi2),
        # weights before sums: n * mean overflows for positions near the float limit, the weighted mean does not
        mean_x=m_old[0] * (n_old / n_all) + m_new[0] * (n_new / n_all),
        mean_y=m_old[1] * (n_old / n_all) + m_new[1] * (n_new / n_all),
    )


_MAX = float(np.finfo(np.float64).max)


def _saturate(stat: F64) -> F64:
    """A statistic that overflowed (positions ~1e300 apart square to inf; inf - inf is NaN) is beyond any
    threshold: the largest finite float, so the decision is "dynamic" and every message carrying it stays valid
    (the wire contract, and the classifier's own readers, reject non-finite numbers)."""
    return np.clip(np.nan_to_num(stat, nan=_MAX, posinf=_MAX, neginf=0.0), 0.0, _MAX)
