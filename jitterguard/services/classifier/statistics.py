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

from .calibration import SCALE_BOUNDS, NoiseModel, line_of_sight

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
                          min_speed: float = 0.0, view_slide: F64 | None = None) -> WindowStats:
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

    With the track-scale prior the denominator is the window's own scale λ times that (a Student-t statistic with
    ν degrees of freedom, reported as a z: :func:`track_scale`). ``view_slide`` (per window, m; None or 0: none)
    then adds the view term: λ V + s² Δū Δūᵀ, Δū the half-mean contrast of the unit vectors from the sensor to the
    window's mean position (:func:`view_turn`) — a box centre placed from the faces the sensor sees slides with the
    view as the sensor drives past a parked car, a displacement the reported covariances do not describe. It is geometry, not noise, so λ does not scale it (a
    mover on a curve, whose λ is large, would otherwise lose its displacement to it; docs/classifier.md 'The view
    term').

    A statistic that overflows saturates (:func:`_saturate`), as in :func:`window_statistics`.
    """
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        st = _calibrated_statistics(windows, masks, groups, model, variance_floor=variance_floor,
                                    effective_n=effective_n, track_scale_prior=track_scale_prior, min_speed=min_speed,
                                    view_slide=view_slide)
    return WindowStats(z_x=_saturate(st.z_x), z_y=_saturate(st.z_y), chi2=_saturate(st.chi2),
                       mean_x=st.mean_x, mean_y=st.mean_y)


def _calibrated_statistics(windows: F64, masks: HalfMasks, groups: I64, model: NoiseModel, *,
                           variance_floor: float, effective_n: str, track_scale_prior: bool,
                           min_speed: float, view_slide: F64 | None = None) -> WindowStats:
    k_old, k_new = masks.n_old, masks.n_new
    valid = masks.old | masks.new
    pos_x, pos_y = windows[..., 0], windows[..., 1]
    t = windows[..., 5]
    # the line of sight u (sensor → object) and v (u turned +90°) per observation, component-wise
    ux, uy = pos_x - windows[..., 6], pos_y - windows[..., 7]
    rng = np.hypot(ux, uy)
    far = rng > 1e-6
    inv_r = np.divide(1.0, rng, out=np.zeros_like(rng), where=far)
    ux *= inv_r
    uy *= inv_r
    ux[~far] = 1.0  # an object on the sensor: any direction, x by convention (as calibration.line_of_sight)
    vx, vy = -uy, ux
    cxx0, cxy0, cyy0 = windows[..., 2], windows[..., 3], windows[..., 4]
    vu = ux * ux * cxx0 + 2.0 * ux * uy * cxy0 + uy * uy * cyy0  # uᵀΣu, vᵀΣv, uᵀΣv
    vv = uy * uy * cxx0 - 2.0 * ux * uy * cxy0 + ux * ux * cyy0
    cuv = ux * uy * (cyy0 - cxx0) + (ux * ux - uy * uy) * cxy0
    band = model.bands(rng)  # (K, W)
    g = groups[:, None]
    age = (windows[..., 8] < windows.shape[1]).astype(np.int64)  # young: among the track's first W
    ku = model.scale[g, 0, band, age]
    kv = model.scale[g, 1, band, age]
    auu, avv = ku * np.maximum(vu, 0.0), kv * np.maximum(vv, 0.0)
    auv = np.sqrt(ku * kv) * cuv

    w_old = masks.old / np.maximum(k_old, 1.0)[:, None]
    w_new = masks.new / np.maximum(k_new, 1.0)[:, None]
    w = w_new - w_old  # the half-mean contrast, 0 outside the window
    dx = (w * pos_x).sum(1)
    dy = (w * pos_y).sum(1)
    if min_speed > 0:  # H0 is |v| ≤ min_speed: shrink the displacement by what that speed explains
        gap = np.maximum((w * t).sum(1), 0.0)  # t̄_new − t̄_old
        d = np.hypot(dx, dy)
        keep = np.maximum(0.0, 1.0 - min_speed * gap / np.maximum(d, 1e-300))
        dx, dy = dx * keep, dy * keep
    # σ of the calibrated covariance along and across the line of sight (floored), and the Cholesky factor
    sig_u = np.sqrt(np.maximum(auu, variance_floor))
    sig_v = np.sqrt(np.maximum(avv, variance_floor))
    measured = effective_n == "measured"
    need_kernels = measured or track_scale_prior
    if need_kernels:
        m_axis = model.correlation[groups]  # (K, 2)
        # per axis k: Φ_k applied to the columns [w h_x, w h_y, U₁, U₂, V₁, V₂] (see track_scale), rows of X
        vm = valid.astype(np.float64)
        n = vm.sum(1)
        tc, stt, b1, b2 = _line_basis(t, vm, n)
        cols = np.empty((2, len(n), 6, windows.shape[1]))
        sig = (sig_u, sig_v)
        for k in range(2):
            np.divide(b1, sig[k], out=cols[k, :, 2])
            np.divide(b2, sig[k], out=cols[k, :, 3])
            np.multiply(b1, sig[k], out=cols[k, :, 4])
            np.multiply(b2, sig[k], out=cols[k, :, 5])
    if measured:
        # Var(w·e) with e_j = H_j (√(1−m)·white_j + √m·correlated_j) per Cholesky component k of the calibrated
        # covariance (component 0 along the line of sight, 1 the rest): Cov(e_i, e_j) = Σ_k R^k_ij h_ik h_jkᵀ,
        # R^k = (1 − m_k) I + m_k Φ^k. Positive semi-definite by construction, and Cov(e_j, e_j) = Σ'_j.
        l21 = auv / sig_u
        l22 = np.sqrt(np.maximum(sig_v * sig_v - l21 * l21, variance_floor * 1e-6))
        h = ((sig_u * ux + l21 * vx, sig_u * uy + l21 * vy), (l22 * vx, l22 * vy))  # world columns per component
        for k, (hx, hy) in enumerate(h):
            np.multiply(w, hx, out=cols[k, :, 0])
            np.multiply(w, hy, out=cols[k, :, 1])
    if need_kernels:
        cols[:, :, 0:2] *= measured  # zeros when only the track scale is wanted
        phi_cols, phi_sq = exponential_kernel_products(t, valid, model.tau_s[groups], cols)  # X Φ (Φ symmetric)
    if measured:
        a = np.zeros(len(w))
        b = np.zeros(len(w))
        c = np.zeros(len(w))
        for k in range(2):
            x, y, m = cols[k], phi_cols[k], m_axis[:, k]
            a += (1.0 - m) * _dot(x[:, 0], x[:, 0]) + m * _dot(x[:, 0], y[:, 0])
            b += (1.0 - m) * _dot(x[:, 0], x[:, 1]) + m * _dot(x[:, 0], y[:, 1])
            c += (1.0 - m) * _dot(x[:, 1], x[:, 1]) + m * _dot(x[:, 1], y[:, 1])
    else:
        cxx = auu * ux * ux + avv * vx * vx + 2 * auv * ux * vx
        cyy = auu * uy * uy + avv * vy * vy + 2 * auv * uy * vy
        cxy = auu * ux * uy + avv * vx * vy + auv * (ux * vy + vx * uy)
        cxx, cyy = _floor_min_eigen(cxx, cxy, cyy, variance_floor)
        if effective_n == "independent":
            n_old, n_new = np.maximum(k_old, 1.0), np.maximum(k_new, 1.0)
        else:
            n_old = n_new = np.ones_like(k_old)
        mean = lambda x, wt: (wt * x).sum(1)  # noqa: E731
        a = mean(cxx, w_old) / n_old + mean(cxx, w_new) / n_new
        b = mean(cxy, w_old) / n_old + mean(cxy, w_new) / n_new
        c = mean(cyy, w_old) / n_old + mean(cyy, w_new) / n_new
    n_all = np.maximum(k_old + k_new, 1.0)
    mean_x, mean_y = (valid * pos_x).sum(1) / n_all, (valid * pos_y).sum(1) / n_all  # the window mean
    lam = nu = None
    if track_scale_prior:  # the window's own scale of its noise: λ V
        lam, nu = track_scale(pos_x, pos_y, vm, n, (tc, stt, b1, b2), ((ux, uy), (vx, vy)), (sig_u, sig_v), cols,
                              phi_cols, phi_sq, m_axis, model.test_dof(groups))
        a, b, c = a * lam, b * lam, c * lam
    if view_slide is not None and view_slide.any():  # s² Δū Δūᵀ: the centre's slide with the view (geometry, not
        s2 = view_slide * view_slide  # noise: not scaled by the window's λ)
        dux, duy = view_turn(mean_x, mean_y, windows[..., 6:8], w)
        a, b, c = a + s2 * dux * dux, b + s2 * dux * duy, c + s2 * duy * duy
    a = np.maximum(a, 1e-300)
    c = np.maximum(c, 1e-300)
    det = np.maximum(a * c - b * b, 1e-300)
    z_x, z_y = np.abs(dx) / np.sqrt(a), np.abs(dy) / np.sqrt(c)
    chi2 = (c * dx * dx - 2.0 * b * dx * dy + a * dy * dy) / det
    if lam is not None:
        z = t_to_z(np.concatenate([z_x, z_y]), np.concatenate([nu, nu]))
        z_x, z_y = z[: len(lam)], z[len(lam):]
    return WindowStats(
        z_x=z_x,
        z_y=z_y,
        chi2=chi2,
        mean_x=mean_x,
        mean_y=mean_y,
    )


def view_turn(mean_x: F64, mean_y: F64, sensor: F64, w: F64) -> tuple[F64, F64]:
    """Δū of the view term: the contrast ``w`` of the unit vectors from the sensor (``sensor``, (K, W, 2)) to the
    window's mean position — how far the sensor's own motion turned its view of the object between the halves, as
    it would under H0 (the object stands where its window says). Not the observed line of sight: a car passing a
    stopped sensor turns that by its own motion, and the slide the term allows for would hide the motion it is
    tested for."""
    u, _, _ = line_of_sight(np.stack([mean_x, mean_y], axis=-1)[:, None, :], sensor)
    return (w * u[..., 0]).sum(1), (w * u[..., 1]).sum(1)


def t_to_z(t: F64, dof: F64) -> F64:
    """The standard-normal score with the same two-sided p-value as |t| under Student's t with ``dof``."""
    from scipy.special import ndtri, stdtr  # type: ignore[import-untyped]

    p_half = stdtr(dof, -np.abs(t))  # one tail
    return np.where(p_half > 0, -ndtri(np.maximum(p_half, 1e-300)), np.abs(t))


def _dot(a: F64, b: F64) -> F64:
    """Row-wise inner products of two (K, W) arrays (einsum: a third of the time of ``(a * b).sum(1)``)."""
    return np.einsum("kw,kw->k", a, b)


def _line_basis(t: F64, vm: F64, n: F64) -> tuple[F64, F64, F64, F64]:
    """(t_c, S_tt, b₁, b₂) of the least-squares line in time over each window's slots ``vm``: centred times,
    their sum of squares, and the orthonormal basis b₁ = 1/√n, b₂ = t_c/√S_tt of the fitted lines (zero
    outside the window). Times are taken relative to the window's first one, so an epoch stamp (1.7e9 s) does
    not cost the centring its precision."""
    t0 = np.where(vm > 0, t, np.inf).min(1)
    rel = np.where(vm > 0, t - np.where(np.isfinite(t0), t0, 0.0)[:, None], 0.0)
    tbar = _dot(vm, rel) / np.maximum(n, 1.0)
    tc = (rel - tbar[:, None]) * vm
    stt = _dot(tc, tc)
    b1 = vm / np.sqrt(np.maximum(n, 1.0))[:, None]
    b2 = tc / np.sqrt(np.where(stt > 0, stt, 1.0))[:, None]
    return tc, stt, b1, b2


def exponential_kernel_products(t: F64, valid: NDArray[np.bool_], tau: F64, rows: F64) -> tuple[F64, F64]:
    """Per line-of-sight axis a: ``rows`` (2, K, C, W) times each window's kernel Φ_ij = exp(−|t_i − t_j| / τ_a)
    (τ per window and axis in ``tau``, (K, 2); zero where slot i or j is outside the window), and Σ_ij Φ_ij² per
    window, (2, K). The correlation of the normalised errors is R = (1 − m) I + m Φ.

    Φ is the covariance of an Ornstein–Uhlenbeck process sampled at the window's stamps, so Φ x needs no W × W
    matrix: with the slots in time order, f_i = x_i + e^{−(t_i − t_{i−1})/τ} f_{i−1} sums the older
    observations, a backward pass the newer ones, and Φ x = f + b − x — W exponentials and 4 W multiply-adds
    per window instead of W² of each, whatever the windows' time patterns (a recording where every track misses
    different frames costs the same as a steady one). Σ Φ² = 1ᵀ Φ' 1 with Φ' the kernel at τ / 2. The slots
    may come in any order (a ring buffer); ties and repeated stamps are exact."""
    k_n, w = t.shape
    key = np.where(valid, t, -np.inf)  # outside the window first
    order = None
    if not (key[:, 1:] >= key[:, :-1]).all():  # the core's windows come oldest first: no sort, no permutation
        order = np.argsort(key, axis=1, kind="stable")
        t, valid = np.take_along_axis(t, order, axis=1), np.take_along_axis(valid, order, axis=1)
        rows = np.take_along_axis(rows, order[None, :, None, :], axis=3)
    step = valid[:, 1:] & valid[:, :-1]  # both ends in the window: a pass carries its sum over the step
    with np.errstate(invalid="ignore", over="ignore"):
        gap = np.where(step, t[:, 1:] - t[:, :-1], 0.0)
    decay = np.exp(-gap.T[:, None, :] / tau.T[None])  # (W − 1, 2, K): time-major like the passes
    decay *= step.T[:, None, :]
    vm = valid.T.astype(np.float64)  # (W, K)
    # (W, 2, C, K): each step of a pass works on one contiguous (2, C, K) slice, the decay broadcast over C
    x = rows.transpose(3, 0, 2, 1) * vm[:, None, None, :]
    acc = np.empty_like(x)  # the forward sums f, then b − x added slot by slot: Φ x = f + b − x
    acc[0] = x[0]
    for i in range(1, w):  # older observations, decayed to slot i
        np.multiply(acc[i - 1], decay[i - 1, :, None, :], out=acc[i])
        acc[i] += x[i]
    back = x[w - 1].copy()
    for i in range(w - 2, -1, -1):  # newer ones
        back *= decay[i, :, None, :]
        acc[i] += back
        back += x[i]
    # slots outside the window come first, hold x = 0 and a zero decay into the window: both passes leave them 0
    # Σ Φ² = 1ᵀ Φ' 1 with Φ' at τ / 2: s_i = Σ_{j<i} Φ'_ij by the same forward pass, Σ Φ² = n + 2 Σ_i s_i
    decay *= decay
    s = np.zeros((2, k_n))
    total = np.zeros((2, k_n))
    for i in range(1, w):
        s += vm[i - 1]
        s *= decay[i - 1]
        total += s  # 0 until the window starts
    phi_sq = vm.sum(0) + 2.0 * total
    out = acc.transpose(1, 3, 2, 0)
    if order is not None:
        back_order = np.argsort(order, axis=1)
        out = np.take_along_axis(out, back_order[None, :, None, :], axis=3)
    return np.ascontiguousarray(out), phi_sq


def track_scale(pos_x: F64, pos_y: F64, vm: F64, n: F64, basis: tuple[F64, F64, F64, F64],
                axes: tuple[tuple[F64, F64], tuple[F64, F64]], sig: tuple[F64, F64], cols: F64, phi_cols: F64,
                phi_sq: F64, m_axis: F64, prior_dof: F64) -> tuple[F64, F64]:
    """Per window: (λ, ν) — the track's own variance scale relative to its class calibration, from the
    residuals of its window about a constant-velocity fit, shrunk to 1 with ``prior_dof`` pseudo degrees of
    freedom (an inverse-gamma prior), and the degrees of freedom of the resulting Student-t statistic.

    Per line-of-sight axis a (unit vectors ``axes[a]`` per observation, calibrated σ ``sig[a]``, correlated
    share ``m_axis[:, a]``, Φ the kernel of :func:`exponential_kernel_products`): the residuals ε = M x about the
    least-squares line, M = P − B Bᵀ the projection (P the window's slots, B = [b₁ b₂] of :func:`_line_basis`),
    normalised r = ε·a / σ; S = Σ r², and under the model E[S] = tr Q, Var[S] ∝ ‖Q‖², with Q = G R Gᵀ,
    G = D⁻¹ M D = P − U Vᵀ, U = D⁻¹ B, V = D B, R = (1 − m) P + m Φ. Written out with A = R V, C = Vᵀ A,
    L = U C − A:  tr Q = n − 2 tr(Uᵀ A) + ⟨C, UᵀU⟩  and
    ‖Q‖² = ‖R‖² + 2[tr(UᵀRU C) − 2 tr(UᵀR²V)] + ⟨UᵀU, LᵀL⟩ − 2⟨UᵀA, LᵀU⟩ + ⟨AᵀA, UᵀU⟩ — Φ applied to four
    columns (rows 2–5 of ``cols``, Φ times them in ``phi_cols``) and 2 × 2 matrices per window instead of
    W × W products (the dense form is kept in ``tests/classifier/reference_statistics.py`` and checked against
    this one)."""
    tc, stt, b1, b2 = basis
    ok = (n >= 3) & (stt > 0)
    # residuals about the fitted line, world frame: ε = P x − B (Bᵀ x)
    ex = vm * pos_x - b1 * _dot(b1, pos_x)[:, None] - b2 * _dot(b2, pos_x)[:, None]
    ey = vm * pos_y - b1 * _dot(b1, pos_y)[:, None] - b2 * _dot(b2, pos_y)[:, None]
    bb = (_dot(b1, b1), _dot(b1, b2), _dot(b2, b2))  # BᵀB (the identity up to rounding and empty windows)
    S = np.zeros(len(n))
    T = np.zeros(len(n))
    T2 = np.zeros(len(n))
    for ai in range(2):
        ax, s, m = axes[ai], sig[ai], m_axis[:, ai]
        om = 1.0 - m
        r = (ex * ax[0] + ey * ax[1]) / s
        S += _dot(r, r)
        x, y = cols[ai], phi_cols[ai]  # rows 2, 3: U; 4, 5: V
        U1, U2, V1, V2 = x[:, 2], x[:, 3], x[:, 4], x[:, 5]
        PU1, PU2, PV1, PV2 = y[:, 2], y[:, 3], y[:, 4], y[:, 5]  # Φ U, Φ V
        # 2 × 2 matrices as row-major 4-tuples of (K,) arrays; UᵀV = BᵀB (σ cancels)
        uu = _sym(_dot(U1, U1), _dot(U1, U2), _dot(U2, U2))
        vv = _sym(_dot(V1, V1), _dot(V1, V2), _dot(V2, V2))
        uv = _sym(*bb)
        f_uv = (_dot(U1, PV1), _dot(U1, PV2), _dot(U2, PV1), _dot(U2, PV2))  # Uᵀ Φ V
        f_vv = _sym(_dot(V1, PV1), _dot(V1, PV2), _dot(V2, PV2))
        f_uu = _sym(_dot(U1, PU1), _dot(U1, PU2), _dot(U2, PU2))
        g_vv = _sym(_dot(PV1, PV1), _dot(PV1, PV2), _dot(PV2, PV2))  # Vᵀ Φ² V
        g_uv_tr = _dot(PU1, PV1) + _dot(PU2, PV2)  # tr(Uᵀ Φ² V)
        mix = lambda white, phi: tuple(om * p + m * q for p, q in zip(white, phi))  # noqa: E731 - Uᵀ R V etc.
        ua = mix(uv, f_uv)  # Uᵀ A
        c = mix(vv, f_vv)  # C = Vᵀ R V
        uru = mix(uu, f_uu)  # Uᵀ R U
        aa = tuple(om * om * p + 2.0 * m * om * q + m * m * r for p, q, r in zip(vv, f_vv, g_vv))  # Vᵀ R² V
        rr_tr = om * om * (uv[0] + uv[3]) + 2.0 * m * om * (f_uv[0] + f_uv[3]) + m * m * g_uv_tr  # tr(Uᵀ R² V)
        T += n - 2.0 * (ua[0] + ua[3]) + _inner(c, uu)
        # Lᵀ U = C UᵀU − Aᵀ U;  Lᵀ L = C UᵀU C − C UᵀA − AᵀU C + AᵀA
        cu = _mm(c, uu)
        cua = _mm(c, ua)
        lu = _sub(cu, _tr(ua))
        ll = _add(_sub(_sub(_mm(cu, c), cua), _tr(cua)), aa)
        x_sq = _inner(uu, ll) - 2.0 * _inner(ua, lu) + _inner(aa, uu)  # ‖U Lᵀ − A Uᵀ‖²
        rp2 = n + m * m * (phi_sq[ai] - n)  # ‖R‖² over the window: the diagonal is 1, the rest m Φ
        T2 += rp2 + 2.0 * (_inner(uru, c) - 2.0 * rr_tr) + x_sq
    nu_own = np.where(ok & (T2 > 0), T * T / np.where(T2 > 0, T2, 1.0), 0.0)
    ratio = np.where(ok & (T > 0), S / np.where(T > 0, T, 1.0), 1.0)
    lam = (prior_dof + nu_own * ratio) / (prior_dof + nu_own)
    # bounded like a class scale: a window whose residuals overflow (a jump to 1e300 from a broken upstream) or
    # dwarf its σ a thousandfold is not "a noisier track" whose test should shrink to nothing
    lam = np.clip(np.nan_to_num(lam, nan=1.0, posinf=SCALE_BOUNDS[1]), *SCALE_BOUNDS)
    return lam, prior_dof + nu_own


def _sym(p, q, r):  # noqa: ANN001, ANN202 - 2 × 2 helpers of track_scale on row-major 4-tuples of (K,) arrays
    return (p, q, q, r)


def _mm(a, b):  # noqa: ANN001, ANN202
    """2 × 2 product of row-major 4-tuples of (K,) arrays."""
    return (a[0] * b[0] + a[1] * b[2], a[0] * b[1] + a[1] * b[3], a[2] * b[0] + a[3] * b[2], a[2] * b[1] + a[3] * b[3])


def _tr(a):  # noqa: ANN001, ANN202
    return (a[0], a[2], a[1], a[3])


def _add(a, b):  # noqa: ANN001, ANN202
    return tuple(x + y for x, y in zip(a, b))


def _sub(a, b):  # noqa: ANN001, ANN202
    return tuple(x - y for x, y in zip(a, b))


def _inner(a, b):  # noqa: ANN001, ANN202
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3]


_MAX = float(np.finfo(np.float64).max)


def _saturate(stat: F64) -> F64:
    """A statistic that overflowed (positions ~1e300 apart square to inf; inf - inf is NaN) is beyond any
    threshold: the largest finite float, so the decision is "dynamic" and every message carrying it stays valid
    (the wire contract, and the classifier's own readers, reject non-finite numbers)."""
    return np.clip(np.nan_to_num(stat, nan=_MAX, posinf=_MAX, neginf=0.0), 0.0, _MAX)
