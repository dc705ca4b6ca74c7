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

from .calibration import SCALE_BOUNDS, NoiseModel, line_of_sight, project_covariance

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


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


CHANNELS = ("x", "y", "cxx", "cxy", "cyy", "t", "sx", "sy", "ordinal")
"""Order of the last axis of a window array: position, the 2x2 world-frame covariance, the observation's time
[s], the sensor's world position at that time (the origin of the line of sight) and the observation's ordinal
in its track (0 for the first: young observations get scales of their own)."""


def window_statistics(windows: F64, masks: HalfMasks, *, variance_floor: float, independent: bool) -> WindowStats:
    """z_x, z_y (eq. 1 with eq. 2) and the 2-D χ² statistic for every window in the batch.

    ``windows`` is ``(K, W, ≥5)`` over :data:`CHANNELS` (only the first five are read). Each half's means of the
    five channels come out of one weighted contraction, so the cost is two passes over the batch whatever the
    statistic. The reported variances are taken as they are (``calibration: off``). A statistic that overflows
    saturates (:func:`_saturate`).
    """
    with np.errstate(over="ignore", invalid="ignore"):
        return _window_statistics(windows[..., :5], masks, variance_floor=variance_floor, independent=independent)


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


def calibrated_statistics(windows: F64, masks: HalfMasks, groups: I64, model: NoiseModel, *,
                          variance_floor: float, effective_n: str, track_scale_prior: bool = True,
                          min_speed: float = 0.0) -> WindowStats:
    """z_x, z_y and χ² with the reported covariances corrected by ``model`` (docs/calibration.md).

    Per observation j: the line of sight u_j from the sensor, v_j across it; the reported covariance Σ_j is
    rescaled along u and v by the scales of the track's class group (``groups``, per window) and of the range
    band of the observation: Σ'_j = D Σ_j D in the (u, v) frame, D = diag(√k_u, √k_v), and its smaller
    eigenvalue floored at ``variance_floor``. The denominator is then

    * ``cluster``:      mean_old Σ' + mean_new Σ'                         (n₁ = n₂ = 1, the paper's)
    * ``independent``:  mean_old Σ' / n₁ + mean_new Σ' / n₂               (independent observations)
    * ``measured``:     Var(μ̄₂ − μ̄₁) = Σ_ij w_i w_j Cov(e_i, e_j) under the model's serial correlation,
      w the half-mean contrast (−1/n₁ on the older half, +1/n₂ on the newer): with h_j0, h_j1 the columns of
      the Cholesky factor of Σ'_j in the (u, v) frame (h_j0 along the line of sight),
      Cov(e_i, e_j) = Σ_k [(1 − m_k)·[i = j] + m_k exp(−|t_i − t_j| / τ_k)] h_ik h_jkᵀ, which is positive
      semi-definite by construction and gives Cov(e_j, e_j) = Σ'_j.

    A statistic that overflows saturates (:func:`_saturate`), as in :func:`window_statistics`.
    """
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        st = _calibrated_statistics(windows, masks, groups, model, variance_floor=variance_floor,
                                    effective_n=effective_n, track_scale_prior=track_scale_prior, min_speed=min_speed)
    return WindowStats(z_x=_saturate(st.z_x), z_y=_saturate(st.z_y), chi2=_saturate(st.chi2),
                       mean_x=st.mean_x, mean_y=st.mean_y)


def _calibrated_statistics(windows: F64, masks: HalfMasks, groups: I64, model: NoiseModel, *,
                           variance_floor: float, effective_n: str, track_scale_prior: bool,
                           min_speed: float) -> WindowStats:
    k_old, k_new = masks.n_old, masks.n_new
    valid = masks.old | masks.new
    pos = windows[..., 0:2]
    cov = windows[..., 2:5]
    t = windows[..., 5]
    sensor = windows[..., 6:8]
    u, v, rng = line_of_sight(pos, sensor)
    vu, vv, cuv = project_covariance(u, v, cov)
    band = model.bands(rng)  # (K, W)
    g = groups[:, None]
    age = (windows[..., 8] < windows.shape[1]).astype(np.int64)  # young: among the track's first W
    ku = model.scale[g, 0, band, age]
    kv = model.scale[g, 1, band, age]
    auu, avv = ku * np.maximum(vu, 0.0), kv * np.maximum(vv, 0.0)
    auv = np.sqrt(ku * kv) * cuv
    ux, uy, vx, vy = u[..., 0], u[..., 1], v[..., 0], v[..., 1]
    cxx = auu * ux * ux + avv * vx * vx + 2 * auv * ux * vx
    cyy = auu * uy * uy + avv * vy * vy + 2 * auv * uy * vy
    cxy = auu * ux * uy + avv * vx * vy + auv * (ux * vy + vx * uy)
    cxx, cyy = _floor_min_eigen(cxx, cxy, cyy, variance_floor)

    w_old = masks.old / np.maximum(k_old, 1.0)[:, None]
    w_new = masks.new / np.maximum(k_new, 1.0)[:, None]
    dx = ((w_new - w_old) * pos[..., 0]).sum(1)
    dy = ((w_new - w_old) * pos[..., 1]).sum(1)
    if min_speed > 0:  # H0 is |v| ≤ min_speed: shrink the displacement by what that speed explains
        gap = np.maximum(((w_new - w_old) * t).sum(1), 0.0)  # t̄_new − t̄_old
        d = np.hypot(dx, dy)
        keep = np.maximum(0.0, 1.0 - min_speed * gap / np.maximum(d, 1e-300))
        dx, dy = dx * keep, dy * keep
    if effective_n == "measured":
        # Var(w·e) with e_j = H_j (√(1−m)·white_j + √m·correlated_j) per Cholesky component k of the calibrated
        # covariance (component 0 along the line of sight, 1 the rest): Cov(e_i, e_j) = Σ_k K^k_ij h_ik h_jkᵀ,
        # K^k = (1 − m_k) I + m_k Φ^k. Positive semi-definite by construction, and Cov(e_j, e_j) = Σ'_j.
        w = np.where(valid, w_new - w_old, 0.0)  # (K, W)
        luu = np.maximum(auu, variance_floor)
        lvv = np.maximum(avv, variance_floor)
        l11 = np.sqrt(luu)
        l21 = auv / l11
        l22 = np.sqrt(np.maximum(lvv - l21 * l21, variance_floor * 1e-6))
        h = ((l11 * ux + l21 * vx, l11 * uy + l21 * vy), (l22 * vx, l22 * vy))  # world columns per component
        a = np.zeros(len(w))
        b = np.zeros(len(w))
        c = np.zeros(len(w))
        corr = correlation_matrices(t, groups, model)
        for k, (hx, hy) in enumerate(h):
            K = corr[k]  # (K, W, W)
            px, py = w * hx, w * hy
            Kx, Ky = (K @ px[..., None])[..., 0], (K @ py[..., None])[..., 0]
            a = a + (px * Kx).sum(1)
            b = b + (px * Ky).sum(1)
            c = c + (py * Ky).sum(1)
    else:
        corr = None
        if effective_n == "independent":
            n_old, n_new = np.maximum(k_old, 1.0), np.maximum(k_new, 1.0)
        else:
            n_old = n_new = np.ones_like(k_old)
        mean = lambda x, wt: (wt * x).sum(1)  # noqa: E731
        a = mean(cxx, w_old) / n_old + mean(cxx, w_new) / n_new
        b = mean(cxy, w_old) / n_old + mean(cxy, w_new) / n_new
        c = mean(cyy, w_old) / n_old + mean(cyy, w_new) / n_new
    a = np.maximum(a, 1e-300)
    c = np.maximum(c, 1e-300)
    det = np.maximum(a * c - b * b, 1e-300)
    n_all = np.maximum(k_old + k_new, 1.0)
    z_x, z_y = np.abs(dx) / np.sqrt(a), np.abs(dy) / np.sqrt(c)
    chi2 = (c * dx * dx - 2.0 * b * dx * dy + a * dy * dy) / det
    if track_scale_prior:
        assert model.track_dof is not None
        lam, nu = track_scale(windows, valid, groups, model, ku, kv, vu, vv, u, v, model.track_dof[groups],
                              variance_floor, corr)
        z_x = t_to_z(z_x / np.sqrt(lam), nu)
        z_y = t_to_z(z_y / np.sqrt(lam), nu)
        chi2 = chi2 / lam
    return WindowStats(
        z_x=z_x,
        z_y=z_y,
        chi2=chi2,
        mean_x=((masks.old | masks.new) * pos[..., 0]).sum(1) / n_all,
        mean_y=((masks.old | masks.new) * pos[..., 1]).sum(1) / n_all,
    )


def t_to_z(t: F64, dof: F64) -> F64:
    """The standard-normal score with the same two-sided p-value as |t| under Student's t with ``dof``."""
    from scipy.special import ndtri, stdtr  # type: ignore[import-untyped]

    p_half = stdtr(dof, -np.abs(t))  # one tail
    return np.where(p_half > 0, -ndtri(np.maximum(p_half, 1e-300)), np.abs(t))


def correlation_matrices(t: F64, groups: I64, model: NoiseModel) -> tuple[F64, F64]:
    """Per line-of-sight axis, the (K, W, W) correlation of each window's errors under ``model``:
    (1 − m) I + m exp(−|t_i − t_j| / τ) with the (m, τ) of the window's class group.

    Computed once per distinct (time pattern, class group): in a steady stream most windows hold the same
    frame spacing, and the exponentials are most of the cost."""
    rel = t - t[:, :1]
    key = np.concatenate([rel, groups[:, None].astype(np.float64)], axis=1)
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    inv = inv.reshape(-1)
    tu, gu = rel[first], groups[first]
    dt = np.abs(tu[:, :, None] - tu[:, None, :])
    eye = np.eye(t.shape[1])[None]
    out = []
    for ai in range(2):
        m = model.correlation[gu, ai][:, None, None]
        tau = model.tau_s[gu, ai][:, None, None]
        out.append(((1.0 - m) * eye + m * np.exp(-dt / tau))[inv])
    return out[0], out[1]


def track_scale(windows: F64, valid: NDArray[np.bool_], groups: I64, model: NoiseModel, ku: F64, kv: F64,
                vu: F64, vv: F64, u: F64, v: F64, prior_dof: F64, variance_floor: float,
                corr: tuple[F64, F64] | None = None) -> tuple[F64, F64]:
    """Per window: (λ, ν) — the track's own variance scale relative to its class calibration, from the
    residuals of its window about a constant-velocity fit, shrunk to 1 with ``prior_dof`` pseudo degrees of
    freedom (an inverse-gamma prior), and the degrees of freedom of the resulting Student-t statistic.
    ``corr``: :func:`correlation_matrices` of these windows when the caller has them already."""
    t = windows[..., 5]
    pos = windows[..., 0:2]
    vm = valid.astype(np.float64)
    n = vm.sum(1)
    tbar = (vm * t).sum(1) / np.maximum(n, 1.0)
    tc = (t - tbar[:, None]) * vm
    stt = (tc * tc).sum(1)
    ok = (n >= 3) & (stt > 0)
    Wn = t.shape[1]
    M = (vm[:, :, None] * np.eye(Wn)[None] - vm[:, :, None] * vm[:, None, :] / np.maximum(n, 1.0)[:, None, None]
         - tc[:, :, None] * tc[:, None, :] / np.where(stt > 0, stt, 1.0)[:, None, None])
    E = M @ pos
    if corr is None:
        corr = correlation_matrices(t, groups, model)
    S = np.zeros(len(n))
    T = np.zeros(len(n))
    T2 = np.zeros(len(n))
    for ai, (kk, var, ax) in enumerate(((ku, vu, u), (kv, vv, v))):
        sig = np.sqrt(np.maximum(kk * np.maximum(var, 0.0), variance_floor))  # calibrated σ
        r = (E * ax).sum(-1) / sig * vm
        G = M * sig[:, None, :] / sig[:, :, None]
        Q = G @ corr[ai] @ np.swapaxes(G, -1, -2)
        S += (r * r).sum(1)
        T += np.einsum("kii->k", Q)
        T2 += (Q * Q).sum((1, 2))
    nu_own = np.where(ok & (T2 > 0), T * T / np.where(T2 > 0, T2, 1.0), 0.0)
    ratio = np.where(ok & (T > 0), S / np.where(T > 0, T, 1.0), 1.0)
    lam = (prior_dof + nu_own * ratio) / (prior_dof + nu_own)
    # bounded like a class scale: a window whose residuals overflow (a jump to 1e300 from a broken upstream) or
    # dwarf its σ a thousandfold is not "a noisier track" whose test should shrink to nothing
    lam = np.clip(np.nan_to_num(lam, nan=1.0, posinf=SCALE_BOUNDS[1]), *SCALE_BOUNDS)
    return lam, prior_dof + nu_own


_MAX = float(np.finfo(np.float64).max)


def _saturate(stat: F64) -> F64:
    """A statistic that overflowed (positions ~1e300 apart square to inf; inf - inf is NaN) is beyond any
    threshold: the largest finite float, so the decision is "dynamic" and every message carrying it stays valid
    (the wire contract, and the classifier's own readers, reject non-finite numbers)."""
    return np.clip(np.nan_to_num(stat, nan=_MAX, posinf=_MAX, neginf=0.0), 0.0, _MAX)
