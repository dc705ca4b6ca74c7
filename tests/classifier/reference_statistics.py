"""The calibrated statistic as first written (issue 15): dense W × W projection and correlation matrices per
window, batched matrix products. Kept as the straightforward reference that the vectorised closed forms in
``jitterguard/services/classifier/statistics.py`` are checked against (``test_classifier_statistics_reference``).
Not used by the service."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from jitterguard.services.classifier.calibration import SCALE_BOUNDS, NoiseModel, line_of_sight, project_covariance
from jitterguard.services.classifier.statistics import HalfMasks, WindowStats, _floor_min_eigen, _saturate

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


def reference_calibrated_statistics(windows: F64, masks: HalfMasks, groups: I64, model: NoiseModel, *,
                                    variance_floor: float, effective_n: str, track_scale_prior: bool = True,
                                    min_speed: float = 0.0, view_slide: F64 | None = None,
                                    contrast: F64 | None = None) -> WindowStats:
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        st = _calibrated_statistics(windows, masks, groups, model, variance_floor=variance_floor,
                                    effective_n=effective_n, track_scale_prior=track_scale_prior, min_speed=min_speed,
                                    view_slide=view_slide, contrast=contrast)
    return WindowStats(z_x=_saturate(st.z_x), z_y=_saturate(st.z_y), chi2=_saturate(st.chi2),
                       mean_x=st.mean_x, mean_y=st.mean_y)


def _calibrated_statistics(windows: F64, masks: HalfMasks, groups: I64, model: NoiseModel, *,
                           variance_floor: float, effective_n: str, track_scale_prior: bool,
                           min_speed: float, view_slide: F64 | None, contrast: F64 | None = None) -> WindowStats:
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
    luu, lvv = _floor_min_eigen(auu, auv, avv, variance_floor)  # the calibrated (u, v) covariance, floored
    ux, uy, vx, vy = u[..., 0], u[..., 1], v[..., 0], v[..., 1]
    cxx = auu * ux * ux + avv * vx * vx + 2 * auv * ux * vx
    cyy = auu * uy * uy + avv * vy * vy + 2 * auv * uy * vy
    cxy = auu * ux * uy + avv * vx * vy + auv * (ux * vy + vx * uy)
    cxx, cyy = _floor_min_eigen(cxx, cxy, cyy, variance_floor)

    w_old = masks.old / np.maximum(k_old, 1.0)[:, None]
    w_new = masks.new / np.maximum(k_new, 1.0)[:, None]
    half_empty = (k_old == 0) | (k_new == 0)  # one observation: no contrast, nothing to test
    dx = np.where(half_empty, 0.0, ((w_new - w_old) * pos[..., 0]).sum(1))
    dy = np.where(half_empty, 0.0, ((w_new - w_old) * pos[..., 1]).sum(1))
    raw = (dx, dy)
    if min_speed > 0:  # H0 is |v| ≤ min_speed: shrink the displacement by what that speed explains
        t0 = np.where(valid, t, np.inf).min(1)  # times relative to the window's first: an epoch keeps its precision
        t_rel = np.where(valid, t - np.where(np.isfinite(t0), t0, 0.0)[:, None], 0.0)
        gap = np.maximum(((w_new - w_old) * t_rel).sum(1), 0.0)  # t̄_new − t̄_old
        d = np.hypot(dx, dy)
        keep = np.maximum(0.0, 1.0 - min_speed * gap / np.maximum(d, 1e-300))
        dx, dy = dx * keep, dy * keep
    if effective_n == "measured":
        # Var(w·e) with e_j = H_j (√(1−m)·white_j + √m·correlated_j) per Cholesky component k of the calibrated
        # covariance (component 0 along the line of sight, 1 the rest): Cov(e_i, e_j) = Σ_k K^k_ij h_ik h_jkᵀ,
        # K^k = (1 − m_k) I + m_k Φ^k. Positive semi-definite by construction, and Cov(e_j, e_j) = Σ'_j.
        w = np.where(valid, w_new - w_old, 0.0)  # (K, W)
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
    lam = nu = None
    if track_scale_prior:  # the window's own noise scale multiplies the noise's covariance, not the view term
        assert model.track_dof is not None
        lam, nu = track_scale(windows, valid, groups, model, np.sqrt(luu), np.sqrt(lvv), u, v,
                              model.track_dof[groups], corr)
        a, b, c = a * lam, b * lam, c * lam
    centre = (valid[..., None] * pos).sum(1) / np.maximum(valid.sum(1), 1)[:, None]  # (K, 2): the window mean
    u_h0, _, _ = line_of_sight(np.broadcast_to(centre[:, None, :], pos.shape), sensor)
    du = ((w_new - w_old)[..., None] * u_h0).sum(1)  # (K, 2): the view's contrast under H0
    if contrast is not None:
        contrast[:] = np.stack([raw[0], raw[1], a, b, c, du[:, 0], du[:, 1]])
    if view_slide is not None:  # the view term: s² times the outer product of the view's contrast under H0
        view = view_slide[:, None, None] ** 2 * du[:, :, None] * du[:, None, :]
        a, b, c = a + view[:, 0, 0], b + view[:, 0, 1], c + view[:, 1, 1]
    a = np.maximum(a, 1e-300)
    c = np.maximum(c, 1e-300)
    det = np.maximum(a * c - b * b, 1e-300)
    n_all = np.maximum(k_old + k_new, 1.0)
    z_x, z_y = np.abs(dx) / np.sqrt(a), np.abs(dy) / np.sqrt(c)
    chi2 = (c * dx * dx - 2.0 * b * dx * dy + a * dy * dy) / det
    if lam is not None:  # Student-t with the window's degrees of freedom, reported as a z; T² as a χ²₂
        z_x = t_to_z(z_x, nu)
        z_y = t_to_z(z_y, nu)
        chi2 = nu * np.log(1.0 + chi2 / nu)  # −2 ln of F(2, ν)'s survival at T²/2
    return WindowStats(
        z_x=z_x,
        z_y=z_y,
        chi2=chi2,
        mean_x=((masks.old | masks.new) * pos[..., 0]).sum(1) / n_all,
        mean_y=((masks.old | masks.new) * pos[..., 1]).sum(1) / n_all,
    )


def t_to_z(t: F64, dof: F64) -> F64:
    """The standard-normal score with the same two-sided p-value as |t| under Student's t with ``dof``: from the
    tail probability where it is a float, else from its logarithm integrated numerically (:func:`t_log_tail`) and
    the normal tail inverted by root finding — neither the series nor the inverse the production code uses."""
    from scipy.special import ndtri, stdtr  # type: ignore[import-untyped]

    t = np.abs(np.asarray(t, dtype=np.float64))
    dof = np.broadcast_to(np.asarray(dof, dtype=np.float64), t.shape)
    p_half = stdtr(dof, -t)  # one tail
    z = np.array(-ndtri(np.maximum(p_half, 1e-300)), dtype=np.float64)
    for i in zip(*np.nonzero(~(p_half > 1e-300) & np.isfinite(t) & np.isfinite(dof))):
        z[i] = normal_score_of_log_tail(t_log_tail(float(t[i]), float(dof[i])))
    return np.where(np.isinf(t), np.inf, np.where(np.isnan(t), t, z))


def t_log_tail(t: float, dof: float) -> float:
    """ln P(T > t) for Student's t (t > 0) by quadrature in the log domain: ln f(t) + ln t + ln ∫₀^∞ f(t(1 + v)) /
    f(t) dv, f the density, so no probability below the float range is ever formed."""
    import math

    from scipy.integrate import quad  # type: ignore[import-untyped]
    from scipy.special import gammaln  # type: ignore[import-untyped]

    e = (dof + 1.0) / 2.0
    log_q = 2.0 * math.log(t) + math.log1p(dof / (t * t)) - math.log(dof)  # ln(1 + t²/ν), t² may overflow
    log_f = gammaln(e) - gammaln(dof / 2.0) - 0.5 * math.log(dof * math.pi) - e * log_q
    share = 1.0 / (1.0 + dof / (t * t))  # t² / (ν + t²)
    ratio = lambda v: math.exp(-e * math.log1p(v * (2.0 + v) * share))  # noqa: E731
    edge = 50.0 / (e * share)  # the ratio is e^(−2 e v share) near 0: its mass lies below this
    area = quad(ratio, 0.0, edge, epsabs=0.0, epsrel=1e-12, limit=200)[0] + quad(ratio, edge, math.inf,
                                                                                 epsabs=0.0, epsrel=1e-12)[0]
    return float(log_f + math.log(t) + math.log(area))


def normal_score_of_log_tail(log_p: float) -> float:
    """The z with ln P(Z > z) = ``log_p`` (standard normal), by bisection on ln Φ(−z)."""
    import math

    from scipy.optimize import brentq  # type: ignore[import-untyped]
    from scipy.special import log_ndtr  # type: ignore[import-untyped]

    return float(brentq(lambda z: log_ndtr(-z) - log_p, 0.0, math.sqrt(-2.0 * log_p) + 10.0, xtol=1e-13, rtol=1e-14))


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


def track_scale(windows: F64, valid: NDArray[np.bool_], groups: I64, model: NoiseModel, sig_u: F64, sig_v: F64,
                u: F64, v: F64, prior_dof: F64, corr: tuple[F64, F64] | None = None) -> tuple[F64, F64]:
    """Per window: (λ, ν) — the track's own variance scale relative to its class calibration, from the
    residuals of its window about a constant-velocity fit, shrunk to 1 with ``prior_dof`` pseudo degrees of
    freedom (an inverse-gamma prior), and the degrees of freedom of the resulting Student-t statistic.
    ``corr``: :func:`correlation_matrices` of these windows when the caller has them already."""
    t = windows[..., 5]
    t = t - np.where(valid, t, np.inf).min(1, keepdims=True)  # relative: epoch stamps would cost precision
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
    for ai, (sig, ax) in enumerate(((sig_u, u), (sig_v, v))):  # calibrated σ along and across the line of sight
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


def reference_block_moments(t: F64, pos: F64, cov: F64, sensor: F64, variance_floor: float = 1e-4) -> tuple[
        F64, F64, F64]:
    """(Y, Ew, Et) of blocks as first written: the dense projection M about each block's line in time,
    G = D⁻¹ M D per axis, Φ_τ = exp(−|Δt|/τ) entry by entry and the batched products G Gᵀ and G Φ Gᵀ — the
    reference for the factored :class:`~jitterguard.services.classifier.calibration.BlockMoments`."""
    from jitterguard.services.classifier.calibration import TAU_GRID_S

    n = t.shape[1]
    tc = t - t.mean(axis=1, keepdims=True)
    stt = np.maximum((tc * tc).sum(axis=1), 1e-12)
    M = np.eye(n)[None] - 1.0 / n - tc[:, :, None] * tc[:, None, :] / stt[:, None, None]
    E = M @ pos
    u, v, _ = line_of_sight(pos - E, sensor)  # to the fitted line
    var_u, var_v, _ = project_covariance(u, v, cov)
    sig = np.sqrt(np.maximum(np.stack([var_u, var_v], axis=1), variance_floor))
    r = np.stack([(E * u).sum(-1), (E * v).sum(-1)], axis=1) / sig
    G = M[:, None] * sig[:, :, None, :] / sig[:, :, :, None]
    phi = np.exp(-np.abs(t[:, None, :, None] - t[:, None, None, :]) / TAU_GRID_S[None, :, None, None])
    Ew = G @ np.swapaxes(G, -1, -2)
    Et = (G[:, :, None] @ phi[:, None]) @ np.swapaxes(G, -1, -2)[:, :, None]
    return r[:, :, :, None] * r[:, :, None, :], Ew, Et
