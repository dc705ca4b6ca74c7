"""The calibrated statistic as one compiled loop per window (numba): the hot part of the classifier core.

Why compiled: the statistic works on each window's 10–40 observations — calibrated variances along and across the
line of sight, the serial-correlation kernel applied by two recursions, the window's own noise scale from 2 × 2
algebra — and as numpy array expressions over (windows × slots) it spent its time in temporaries, transposes and
a hundred small reductions (11–21 ms for 1000 windows of 20). One loop per window holds everything in a few
scratch arrays and does the same arithmetic in 2–3 ms (docs/performance.md, "The calibrated statistic compiled").
The math is :func:`~.statistics.calibrated_statistics`'s; ``tests/classifier/reference_statistics.py`` computes it
again with dense W × W matrices and the tests hold the two together.

Compiled on first use and cached next to this file (``cache=True``; numba falls back to a per-user cache where the
package directory is read-only, and ``NUMBA_CACHE_DIR`` names one), so only the first process after an install pays
the compilation (seconds); :func:`~.statistics.warm_up` lets a service pay it before its first frame. Where no
cache can be written at all each process compiles once (:data:`CACHED` False) rather than failing. ``error_model="numpy"``: a division by
zero gives inf or NaN as numpy does — the statistic saturates such values (``statistics._saturate``) rather than
raising.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numba
import numpy as np

CLUSTER, INDEPENDENT, MEASURED = 0, 1, 2
"""``mode`` of :func:`calibrated_windows`: the ``effective_n`` of the configuration."""

CACHED = True
"""Whether the compiled code is cached on disk (False: no writable cache location, each process compiles)."""


def _compiled(**options: object) -> Callable[[Callable[..., Any]], Any]:
    """``numba.njit`` with IEEE division and the on-disk cache — or, where numba finds no writable place for a
    cache (a read-only install whose user has no writable home, as under systemd's ``ProtectSystem=strict`` and
    ``ProtectHome=true`` without ``NUMBA_CACHE_DIR``), without it: the process then compiles on its first call
    instead of failing at import (numba raises ``RuntimeError`` there when asked to cache)."""

    def wrap(fn: Callable[..., Any]) -> Any:
        global CACHED
        try:
            return numba.njit(cache=True, error_model="numpy", **options)(fn)
        except RuntimeError:
            CACHED = False
            return numba.njit(error_model="numpy", **options)(fn)

    return wrap


@_compiled(inline="always")
def _mm(a0, a1, a2, a3, b0, b1, b2, b3):  # noqa: ANN001, ANN202
    """2 × 2 product of row-major 4-tuples."""
    return (a0 * b0 + a1 * b2, a0 * b1 + a1 * b3, a2 * b0 + a3 * b2, a2 * b1 + a3 * b3)


@_compiled(inline="always")
def _unit(dx, dy):  # noqa: ANN001, ANN202
    """The unit vector along (dx, dy) and its length; on the sensor (length ≤ 1 µm) any direction, x by
    convention (as :func:`~.calibration.line_of_sight`)."""
    length = math.hypot(dx, dy)
    if length > 1e-6:
        return dx / length, dy / length, length
    return 1.0, 0.0, length


@_compiled()
def ou_kernel_apply(x, decay, n, out):  # noqa: ANN001, ANN201
    """``out[:n]`` = Φ x for slots in time order, Φ_ij = exp(−|t_i − t_j| / τ), ``decay[i]`` = exp(−(t_i − t_{i−1})
    / τ) (``decay[0]`` unused). Φ is the covariance of an Ornstein–Uhlenbeck process sampled at the stamps, so
    Φ x needs no W × W matrix: f_i = x_i + decay_i f_{i−1} sums the older observations, a backward pass the newer
    ones, and Φ x = f + b − x. Ties and repeated stamps (decay 1) are exact."""
    f = 0.0
    for i in range(n):
        f = x[i] + decay[i] * f if i > 0 else x[i]
        out[i] = f
    b = 0.0
    for i in range(n - 1, -1, -1):
        if i < n - 1:
            b *= decay[i + 1]
        out[i] += b
        b += x[i]


@_compiled()
def calibrated_windows(windows, old, new, n_old_a, n_new_a, groups, scale, edges, corr, tau, dof, view,  # noqa: ANN001, ANN201, C901, PLR0912, PLR0913, PLR0915
                       floor, mode, prior, min_speed, lam_lo, lam_hi, out):
    """Per window k of ``windows`` (K, W, channels of ``statistics.CHANNELS``; slots in any order, ``old``/``new``
    the half masks, ``n_old_a``/``n_new_a`` their counts): ``out[0..5, k]`` = z_x, z_y, χ² (t statistics when
    ``prior``), the window mean x, y, and the degrees of freedom ν of the t statistic.

    Each observation's reported covariance is rescaled along (u) and across (v) the line of sight by
    ``scale[group, axis, range band, young]`` (bands split at ``edges``; young: ordinal < W) and floored
    (``floor``). The denominator is that of ``mode``: ``CLUSTER`` mean_old Σ' + mean_new Σ'; ``INDEPENDENT`` each
    divided by its half's count; ``MEASURED`` Var(w·e), w the half-mean contrast, under the serial-correlation
    model R^a = (1 − m_a) I + m_a Φ^a per Cholesky component a of Σ' (m = ``corr``, τ = ``tau`` per group and
    axis). With ``prior`` it is multiplied by the window's own scale λ — the residuals about the least-squares
    line, normalised along and across the line of sight: S = Σ r², E[S] = tr Q and Var[S] ∝ ‖Q‖² with Q = G R Gᵀ,
    G = P − U Vᵀ, U = D⁻¹ B, V = D B (B the line's orthonormal basis, D the σ per observation); written out with
    A = R V, C = Vᵀ A, L = U C − A: tr Q = n − 2 tr(Uᵀ A) + ⟨C, UᵀU⟩ and ‖Q‖² = ‖R‖² + 2[tr(UᵀRU C) −
    2 tr(UᵀR²V)] + ⟨UᵀU, LᵀL⟩ − 2⟨UᵀA, LᵀU⟩ + ⟨AᵀA, UᵀU⟩; ν_own = (tr Q)² / ‖Q‖², λ = (ν₀ + ν_own S / tr Q) /
    (ν₀ + ν_own) bounded to [``lam_lo``, ``lam_hi``], ν₀ = ``dof[group]``. Then the view term s² Δū Δūᵀ
    (s = ``view[k]``, Δū the contrast of the unit vectors from the sensor to the window mean), unscaled by λ.
    H0 |v| ≤ ``min_speed`` shrinks the displacement by what that speed explains over the halves' time gap.
    An ``out`` of 13 rows also receives, in rows 6–12, the displacement before that shrinking (x, y), the
    contrast's covariance before the view term (xx, xy, yy) and Δū (x, y): ``statistics.calibrated_statistics``'s
    ``contrast``."""
    k_n, w_n = windows.shape[0], windows.shape[1]
    n_edges = edges.shape[0]
    key = np.empty(w_n)
    order = np.arange(w_n)
    px = np.empty(w_n)
    py = np.empty(w_n)
    tt = np.empty(w_n)
    wv = np.empty(w_n)
    ux = np.empty(w_n)
    uy = np.empty(w_n)
    sen_x = np.empty(w_n)
    sen_y = np.empty(w_n)
    sig = np.empty((2, w_n))
    auu = np.empty(w_n)
    avv = np.empty(w_n)
    auv = np.empty(w_n)
    b2 = np.empty(w_n)
    dec = np.empty((2, w_n))
    cols = np.zeros((2, 6, w_n))  # per axis: w h (two world columns), U₁, U₂, V₁, V₂
    pcols = np.empty((2, 6, w_n))  # Φ times each
    ex = np.empty(w_n)
    ey = np.empty(w_n)
    for k in range(k_n):
        g = groups[k]
        n_old, n_new = n_old_a[k], n_new_a[k]
        w_old, w_new = 1.0 / max(n_old, 1.0), 1.0 / max(n_new, 1.0)
        # the window's observations in time order (a ring buffer's slots need not be)
        ascending = True
        for j in range(w_n):
            key[j] = windows[k, j, 5] if (old[k, j] or new[k, j]) else -np.inf
            if j > 0 and key[j] < key[j - 1]:
                ascending = False
        if ascending:
            for j in range(w_n):
                order[j] = j
        else:
            order[:] = np.argsort(key, kind="mergesort")
        n = 0
        for jj in range(w_n):
            j = order[jj]
            if not (old[k, j] or new[k, j]):
                continue
            px[n] = windows[k, j, 0]
            py[n] = windows[k, j, 1]
            tt[n] = windows[k, j, 5]
            wv[n] = (w_new if new[k, j] else 0.0) - (w_old if old[k, j] else 0.0)
            sen_x[n] = windows[k, j, 6]
            sen_y[n] = windows[k, j, 7]
            lx, ly = px[n] - sen_x[n], py[n] - sen_y[n]
            u0, u1, rng = _unit(lx, ly)
            ux[n] = u0
            uy[n] = u1
            cxx, cxy, cyy = windows[k, j, 2], windows[k, j, 3], windows[k, j, 4]
            var_u = u0 * u0 * cxx + 2.0 * u0 * u1 * cxy + u1 * u1 * cyy  # uᵀΣu, vᵀΣv, uᵀΣv
            var_v = u1 * u1 * cxx - 2.0 * u0 * u1 * cxy + u0 * u0 * cyy
            cov_uv = u0 * u1 * (cyy - cxx) + (u0 * u0 - u1 * u1) * cxy
            band = 0
            while band < n_edges and edges[band] <= rng:
                band += 1
            young = 1 if windows[k, j, 8] < w_n else 0
            ku, kv = scale[g, 0, band, young], scale[g, 1, band, young]
            auu[n] = ku * max(var_u, 0.0)
            avv[n] = kv * max(var_v, 0.0)
            auv[n] = math.sqrt(ku * kv) * cov_uv
            # the smaller eigenvalue raised to the floor (not each axis: an oblique, thin ellipse would keep a
            # near-zero variance across its long axis, and the test would fire by the ellipse's bearing)
            low = 0.5 * (auu[n] + avv[n]) - math.sqrt(0.25 * (auu[n] - avv[n]) ** 2 + auv[n] * auv[n])
            lift = max(0.0, floor - low)
            sig[0, n] = math.sqrt(auu[n] + lift)
            sig[1, n] = math.sqrt(avv[n] + lift)
            n += 1
        nf = float(n)
        dx = dy = sum_x = sum_y = 0.0
        for i in range(n):
            dx += wv[i] * px[i]
            dy += wv[i] * py[i]
            sum_x += px[i]
            sum_y += py[i]
        if n_old == 0 or n_new == 0:  # one observation: no contrast, nothing to test
            dx = dy = 0.0
        n_all = max(n_old + n_new, 1.0)
        mean_x, mean_y = sum_x / n_all, sum_y / n_all
        raw_dx, raw_dy = dx, dy
        t0 = tt[0] if n > 0 else 0.0  # times relative to the window's first: an epoch stamp keeps its precision
        if min_speed > 0:  # H0 is |v| ≤ min_speed: shrink the displacement by what that speed explains
            gap = 0.0
            for i in range(n):
                gap += wv[i] * (tt[i] - t0)
            d = math.hypot(dx, dy)
            keep = max(0.0, 1.0 - min_speed * max(gap, 0.0) / max(d, 1e-300))
            dx *= keep
            dy *= keep
        stt = 0.0
        b1 = 1.0 / math.sqrt(max(nf, 1.0))  # the fitted lines' orthonormal basis: b₁ constant, b₂ the centred time
        if mode == MEASURED or prior:
            t_bar = 0.0
            for i in range(n):
                t_bar += tt[i] - t0
            t_bar /= max(nf, 1.0)
            for i in range(n):
                b2[i] = tt[i] - t0 - t_bar
                stt += b2[i] * b2[i]
            root = math.sqrt(stt if stt > 0 else 1.0)
            for i in range(n):
                b2[i] /= root
            for a in range(2):
                for i in range(n):
                    dec[a, i] = math.exp(-(tt[i] - tt[i - 1]) / tau[g, a]) if i > 0 else 0.0
                    s = sig[a, i]
                    cols[a, 2, i] = b1 / s
                    cols[a, 3, i] = b2[i] / s
                    cols[a, 4, i] = b1 * s
                    cols[a, 5, i] = b2[i] * s
            if mode == MEASURED:  # w times the Cholesky columns of Σ' (component 0 along the line of sight)
                for i in range(n):
                    su = sig[0, i]
                    l21 = auv[i] / su
                    l22 = math.sqrt(max(sig[1, i] * sig[1, i] - l21 * l21, floor * 1e-6))
                    vx, vy = -uy[i], ux[i]
                    cols[0, 0, i] = wv[i] * (su * ux[i] + l21 * vx)
                    cols[0, 1, i] = wv[i] * (su * uy[i] + l21 * vy)
                    cols[1, 0, i] = wv[i] * (l22 * vx)
                    cols[1, 1, i] = wv[i] * (l22 * vy)
            for a in range(2):
                for c in range(0 if mode == MEASURED else 2, 6):
                    ou_kernel_apply(cols[a, c], dec[a], n, pcols[a, c])
        va = vb = vc = 0.0  # the contrast's covariance [[va, vb], [vb, vc]]
        if mode == MEASURED:
            for a in range(2):
                m = corr[g, a]
                s00 = s01 = s11 = p00 = p01 = p11 = 0.0
                for i in range(n):
                    x0, x1 = cols[a, 0, i], cols[a, 1, i]
                    s00 += x0 * x0
                    s01 += x0 * x1
                    s11 += x1 * x1
                    p00 += x0 * pcols[a, 0, i]
                    p01 += x0 * pcols[a, 1, i]
                    p11 += x1 * pcols[a, 1, i]
                va += (1.0 - m) * s00 + m * p00
                vb += (1.0 - m) * s01 + m * p01
                vc += (1.0 - m) * s11 + m * p11
        else:
            k_old = max(n_old, 1.0) if mode == INDEPENDENT else 1.0
            k_new = max(n_new, 1.0) if mode == INDEPENDENT else 1.0
            for i in range(n):
                u0, u1 = ux[i], uy[i]
                vx, vy = -u1, u0
                cxx = auu[i] * u0 * u0 + avv[i] * vx * vx + 2.0 * auv[i] * u0 * vx
                cyy = auu[i] * u1 * u1 + avv[i] * vy * vy + 2.0 * auv[i] * u1 * vy
                cxy = auu[i] * u0 * u1 + avv[i] * vx * vy + auv[i] * (u0 * vy + vx * u1)
                low = 0.5 * (cxx + cyy) - math.sqrt(0.25 * (cxx - cyy) ** 2 + cxy * cxy)
                shift = max(0.0, floor - low)  # the smaller eigenvalue raised to the floor
                weight = w_old / k_old if wv[i] < 0 else w_new / k_new
                va += weight * (cxx + shift)
                vb += weight * cxy
                vc += weight * (cyy + shift)
        if prior:  # the window's own scale of its noise: λ V, a t statistic with ν degrees of freedom
            s1x = s2x = s1y = s2y = bb0 = bb1 = bb3 = 0.0
            for i in range(n):
                s1x += b1 * px[i]
                s2x += b2[i] * px[i]
                s1y += b1 * py[i]
                s2y += b2[i] * py[i]
                bb0 += b1 * b1
                bb1 += b1 * b2[i]
                bb3 += b2[i] * b2[i]
            for i in range(n):  # residuals about the fitted line: ε = x − B (Bᵀ x)
                ex[i] = px[i] - b1 * s1x - b2[i] * s2x
                ey[i] = py[i] - b1 * s1y - b2[i] * s2y
            big_s = big_t = big_t2 = 0.0
            for a in range(2):
                m = corr[g, a]
                om = 1.0 - m
                uu0 = uu1 = uu3 = vv0 = vv1 = vv3 = 0.0
                fuv0 = fuv1 = fuv2 = fuv3 = fvv0 = fvv1 = fvv3 = fuu0 = fuu1 = fuu3 = 0.0
                gvv0 = gvv1 = gvv3 = g_uv_tr = 0.0
                phi_sq = nf  # Σ_ij Φ_ij²: n + 2 Σ_i s_i, s_i = Σ_{j<i} Φ_ij² by the forward pass at τ / 2
                s_i = 0.0
                for i in range(n):
                    if a == 0:
                        r = (ex[i] * ux[i] + ey[i] * uy[i]) / sig[0, i]
                    else:
                        r = (ey[i] * ux[i] - ex[i] * uy[i]) / sig[1, i]
                    big_s += r * r
                    u_1, u_2, v_1, v_2 = cols[a, 2, i], cols[a, 3, i], cols[a, 4, i], cols[a, 5, i]
                    pu1, pu2, pv1, pv2 = pcols[a, 2, i], pcols[a, 3, i], pcols[a, 4, i], pcols[a, 5, i]
                    uu0 += u_1 * u_1
                    uu1 += u_1 * u_2
                    uu3 += u_2 * u_2
                    vv0 += v_1 * v_1
                    vv1 += v_1 * v_2
                    vv3 += v_2 * v_2
                    fuv0 += u_1 * pv1  # Uᵀ Φ V
                    fuv1 += u_1 * pv2
                    fuv2 += u_2 * pv1
                    fuv3 += u_2 * pv2
                    fvv0 += v_1 * pv1  # Vᵀ Φ V
                    fvv1 += v_1 * pv2
                    fvv3 += v_2 * pv2
                    fuu0 += u_1 * pu1  # Uᵀ Φ U
                    fuu1 += u_1 * pu2
                    fuu3 += u_2 * pu2
                    gvv0 += pv1 * pv1  # Vᵀ Φ² V
                    gvv1 += pv1 * pv2
                    gvv3 += pv2 * pv2
                    g_uv_tr += pu1 * pv1 + pu2 * pv2  # tr(Uᵀ Φ² V)
                    if i > 0:
                        s_i = (s_i + 1.0) * dec[a, i] * dec[a, i]
                        phi_sq += 2.0 * s_i
                # 2 × 2 matrices as row-major 4-tuples; UᵀV = BᵀB (σ cancels)
                uu = (uu0, uu1, uu1, uu3)
                uv = (bb0, bb1, bb1, bb3)
                ua = (om * uv[0] + m * fuv0, om * uv[1] + m * fuv1, om * uv[2] + m * fuv2, om * uv[3] + m * fuv3)
                cc = (om * vv0 + m * fvv0, om * vv1 + m * fvv1, om * vv1 + m * fvv1, om * vv3 + m * fvv3)
                uru = (om * uu0 + m * fuu0, om * uu1 + m * fuu1, om * uu1 + m * fuu1, om * uu3 + m * fuu3)
                aa0 = om * om * vv0 + 2.0 * m * om * fvv0 + m * m * gvv0  # Vᵀ R² V
                aa1 = om * om * vv1 + 2.0 * m * om * fvv1 + m * m * gvv1
                aa3 = om * om * vv3 + 2.0 * m * om * fvv3 + m * m * gvv3
                aa = (aa0, aa1, aa1, aa3)
                rr_tr = om * om * (uv[0] + uv[3]) + 2.0 * m * om * (fuv0 + fuv3) + m * m * g_uv_tr  # tr(Uᵀ R² V)
                big_t += nf - 2.0 * (ua[0] + ua[3]) + (cc[0] * uu[0] + cc[1] * uu[1] + cc[2] * uu[2] + cc[3] * uu[3])
                # Lᵀ U = C UᵀU − Aᵀ U;  Lᵀ L = C UᵀU C − C UᵀA − AᵀU C + AᵀA
                cu = _mm(cc[0], cc[1], cc[2], cc[3], uu[0], uu[1], uu[2], uu[3])
                cua = _mm(cc[0], cc[1], cc[2], cc[3], ua[0], ua[1], ua[2], ua[3])
                lu = (cu[0] - ua[0], cu[1] - ua[2], cu[2] - ua[1], cu[3] - ua[3])
                cuc = _mm(cu[0], cu[1], cu[2], cu[3], cc[0], cc[1], cc[2], cc[3])
                ll = (cuc[0] - cua[0] - cua[0] + aa[0], cuc[1] - cua[1] - cua[2] + aa[1],
                      cuc[2] - cua[2] - cua[1] + aa[2], cuc[3] - cua[3] - cua[3] + aa[3])
                x_sq = ((uu[0] * ll[0] + uu[1] * ll[1] + uu[2] * ll[2] + uu[3] * ll[3])
                        - 2.0 * (ua[0] * lu[0] + ua[1] * lu[1] + ua[2] * lu[2] + ua[3] * lu[3])
                        + (aa[0] * uu[0] + aa[1] * uu[1] + aa[2] * uu[2] + aa[3] * uu[3]))  # ‖U Lᵀ − A Uᵀ‖²
                rp2 = nf + m * m * (phi_sq - nf)  # ‖R‖² over the window: the diagonal is 1, the rest m Φ
                big_t2 += (rp2 + 2.0 * ((uru[0] * cc[0] + uru[1] * cc[1] + uru[2] * cc[2] + uru[3] * cc[3])
                                        - 2.0 * rr_tr) + x_sq)
            ok = n >= 3 and stt > 0
            nu_own = big_t * big_t / big_t2 if (ok and big_t2 > 0) else 0.0
            ratio = big_s / big_t if (ok and big_t > 0) else 1.0
            lam = (dof[g] + nu_own * ratio) / (dof[g] + nu_own)
            # bounded like a class scale: a window whose residuals overflow (a jump to 1e300 from a broken upstream)
            # or dwarf its σ a thousandfold is not "a noisier track" whose test should shrink to nothing
            if math.isnan(lam):
                lam = 1.0
            lam = min(max(lam, lam_lo), lam_hi)
            va *= lam
            vb *= lam
            vc *= lam
            out[5, k] = dof[g] + nu_own
        slide = view[k]
        du0 = du1 = 0.0
        if slide != 0.0 or out.shape[0] > 6:  # Δū: the contrast of the unit vectors to the window mean
            for i in range(n):
                e0, e1, _ = _unit(mean_x - sen_x[i], mean_y - sen_y[i])
                du0 += wv[i] * e0
                du1 += wv[i] * e1
        if out.shape[0] > 6:  # what the view term's learning weighs: the contrast (before H0's speed), its covariance before the term, Δū
            out[6, k] = raw_dx
            out[7, k] = raw_dy
            out[8, k] = va
            out[9, k] = vb
            out[10, k] = vc
            out[11, k] = du0
            out[12, k] = du1
        if slide != 0.0:  # s² Δū Δūᵀ: the centre's slide with the view (geometry, not noise: not scaled by λ)
            s2 = slide * slide
            va += s2 * du0 * du0
            vb += s2 * du0 * du1
            vc += s2 * du1 * du1
        va = max(va, 1e-300)
        vc = max(vc, 1e-300)
        det = max(va * vc - vb * vb, 1e-300)
        out[0, k] = abs(dx) / math.sqrt(va)
        out[1, k] = abs(dy) / math.sqrt(vc)
        out[2, k] = (vc * dx * dx - 2.0 * vb * dx * dy + va * dy * dy) / det
        out[3, k] = mean_x
        out[4, k] = mean_y
