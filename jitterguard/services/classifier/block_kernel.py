"""Pooling the calibration's blocks as one compiled loop per block (numba): the online calibration's learning.

Why compiled: a block of n observations contributes its residuals' outer product r rᵀ and their expectations
under unit white noise, G Gᵀ, and under unit exponentially correlated noise, G Φ_τ Gᵀ for the 12 correlation times
of the grid — 2 axes × 13 matrices of n × n per block (docs/calibration.md). As numpy expressions those were
n × 4 factors per block and τ, materialised for every block, then multiplied side by side per cell: 6–8 ms per
frame for the ~50 windows of 20 that turn over among 1000 tracks, most of the classifier core's time with online
calibration. One loop per block forms each entry once, from the block's two basis vectors and Φ_τ (built by
products of the decays between successive stamps), and adds it, Huber-weighted, straight into its cell's sums;
the Huber weight and the two traces the track-heterogeneity estimate needs are taken in the same pass
(docs/performance.md, "The calibration's learning compiled").

The math is :class:`~.calibration.OnlineCalibration`'s (its module docstring); the tests hold it to the dense
G = D⁻¹ M D products of ``tests/classifier/reference_statistics.py``. Compiled and cached as
:mod:`~.window_kernel`'s loop is (its ``_compiled``).
"""

from __future__ import annotations

import math

import numpy as np

from .window_kernel import _compiled


@_compiled()
def _correlation_grid(t, tau_grid, phi):  # noqa: ANN001, ANN202
    """``phi[τ, i, j]`` = exp(−|t_i − t_j| / τ) for the block's stamps ``t``. Stamps in time order (the usual
    case) take n − 1 exponentials per τ and products along each row (Φ_ij = Φ_i,j−1 · exp(−(t_j − t_j−1) / τ),
    the Ornstein–Uhlenbeck covariance); out of order, every entry is its own exponential."""
    n = t.shape[0]
    ordered = True
    for i in range(1, n):
        if t[i] < t[i - 1]:
            ordered = False
    decay = np.empty(n)
    for k in range(tau_grid.shape[0]):
        tau = tau_grid[k]
        if ordered:
            for j in range(1, n):
                decay[j] = math.exp(-(t[j] - t[j - 1]) / tau)
        for i in range(n):
            phi[k, i, i] = 1.0
            for j in range(i + 1, n):
                e = phi[k, i, j - 1] * decay[j] if ordered else math.exp(-abs(t[i] - t[j]) / tau)
                phi[k, i, j] = e
                phi[k, j, i] = e


@_compiled()
def pool_blocks(t, sig, r, slow, cell_g, cell_b, cell_y, k, m, tau_i, tau_w, tau_grid, huber_c,  # noqa: ANN001, ANN201
                Y, Ew, Et, n_sum, width, w_out, het_out):
    """Add blocks to their cells' sums, in place, and say with what weight.

    Per block b (``t`` (N, n) stamps, ``sig`` (N, 2, n) reported σ along/across the line of sight, ``r`` (N, 2, n)
    normalised residuals about the block's line) and axis a, with B = [1/√n, t_c/√S_tt] the basis of the fitted
    lines, U = D⁻¹ B, V = D B (D = diag σ) and A_τ = Φ_τ V:

    * G Gᵀ = I − U Vᵀ − (V − U VᵀV) Uᵀ,  G Φ_τ Gᵀ = Φ_τ − U A_τᵀ − (A_τ − U VᵀA_τ) Uᵀ;
    * the Huber weight w = min(1, ``huber_c`` / (tr r rᵀ / pred)), pred = k[(1 − m) tr G Gᵀ + m tr G Φ_τ Gᵀ] with
      τ between grid points ``tau_i`` and ``tau_i`` + 1 (weight ``tau_w``, linear in log τ) — the model's
      prediction for the block (``k``, ``m``, ``tau_*`` (N, 2) from the block's cell and group);
    * ``Y``/``Ew``/``Et`` [g, a, band, age, i·``width`` + j(, τ)] += w × (r rᵀ, G Gᵀ, G Φ_τ Gᵀ)_ij for i, j < n (the
      sums hold ``width`` × ``width`` matrices flattened; a shorter block fills their leading rows and columns),
      ``n_sum`` += w, the cell (``cell_g``, ``cell_b``, ``cell_y``) per block;
    * ``het_out[b]`` = (tr Q, ‖Q‖²_F) summed over both axes, Q = k[(1 − m) G Gᵀ + m G Φ_τ Gᵀ] at the group's τ:
      the block's Satterthwaite degrees of freedom for the track-heterogeneity estimate.

    Blocks not ``slow`` (faster than the calibration pools) get weight 0 and no work. ``w_out`` (N, 2)."""
    N, n = t.shape
    T = tau_grid.shape[0]
    phi = np.empty((T, n, n))
    A = np.empty((T, n, 2))
    vta = np.empty((T, 4))
    trt = np.empty(T)
    etq = np.empty(T)
    U = np.empty((n, 2))
    V = np.empty((n, 2))
    P = np.empty((n, 2))  # V − U VᵀV
    Pt = np.empty((T, n, 2))  # A_τ − U VᵀA_τ
    b0 = 1.0 / math.sqrt(n)
    for b in range(N):
        w_out[b, 0] = 0.0
        w_out[b, 1] = 0.0
        het_out[b, 0] = 0.0
        het_out[b, 1] = 0.0
        if not slow[b]:
            continue
        mean = 0.0
        for i in range(n):
            mean += t[b, i]
        mean /= n
        stt = 0.0
        for i in range(n):
            stt += (t[b, i] - mean) ** 2
        rs = 1.0 / math.sqrt(max(stt, 1e-12))
        _correlation_grid(t[b], tau_grid, phi)
        g, band, age = cell_g[b], cell_b[b], cell_y[b]
        for a in range(2):
            vtv0 = vtv1 = vtv2 = vtv3 = 0.0  # VᵀV row-major
            for i in range(n):
                s = sig[b, a, i]
                c0, c1 = b0, (t[b, i] - mean) * rs
                U[i, 0], U[i, 1] = c0 / s, c1 / s
                V[i, 0], V[i, 1] = c0 * s, c1 * s
                vtv0 += V[i, 0] * V[i, 0]
                vtv1 += V[i, 0] * V[i, 1]
                vtv3 += V[i, 1] * V[i, 1]
            vtv2 = vtv1
            trw = float(n)
            for i in range(n):
                P[i, 0] = V[i, 0] - (U[i, 0] * vtv0 + U[i, 1] * vtv2)
                P[i, 1] = V[i, 1] - (U[i, 0] * vtv1 + U[i, 1] * vtv3)
                trw -= U[i, 0] * V[i, 0] + U[i, 1] * V[i, 1] + P[i, 0] * U[i, 0] + P[i, 1] * U[i, 1]
            for q in range(T):
                x0 = x1 = x2 = x3 = 0.0
                for i in range(n):
                    a0 = a1 = 0.0
                    for j in range(n):
                        a0 += phi[q, i, j] * V[j, 0]
                        a1 += phi[q, i, j] * V[j, 1]
                    A[q, i, 0], A[q, i, 1] = a0, a1
                    x0 += V[i, 0] * a0
                    x1 += V[i, 0] * a1
                    x2 += V[i, 1] * a0
                    x3 += V[i, 1] * a1
                vta[q, 0], vta[q, 1], vta[q, 2], vta[q, 3] = x0, x1, x2, x3
                tr = float(n)
                for i in range(n):
                    Pt[q, i, 0] = A[q, i, 0] - (U[i, 0] * x0 + U[i, 1] * x2)
                    Pt[q, i, 1] = A[q, i, 1] - (U[i, 0] * x1 + U[i, 1] * x3)
                    tr -= (U[i, 0] * A[q, i, 0] + U[i, 1] * A[q, i, 1]
                           + Pt[q, i, 0] * U[i, 0] + Pt[q, i, 1] * U[i, 1])
                trt[q] = tr
            ss = 0.0
            for i in range(n):
                ss += r[b, a, i] * r[b, a, i]
            kk, mm, ti, tw = k[b, a], m[b, a], tau_i[b, a], tau_w[b, a]
            pred = kk * ((1.0 - mm) * trw + mm * ((1.0 - tw) * trt[ti] + tw * trt[ti + 1]))
            w = min(1.0, huber_c / max(ss / max(pred, 1e-300), 1e-300))
            w_out[b, a] = w
            n_sum[g, a, band, age] += w
            qtr = 0.0
            q2 = 0.0
            for i in range(n):
                for j in range(i, n):
                    ew = (1.0 if i == j else 0.0) - (U[i, 0] * V[j, 0] + U[i, 1] * V[j, 1]) \
                        - (P[i, 0] * U[j, 0] + P[i, 1] * U[j, 1])
                    for q in range(T):
                        etq[q] = phi[q, i, j] - (U[i, 0] * A[q, j, 0] + U[i, 1] * A[q, j, 1]) \
                            - (Pt[q, i, 0] * U[j, 0] + Pt[q, i, 1] * U[j, 1])
                    qq = kk * ((1.0 - mm) * ew + mm * ((1.0 - tw) * etq[ti] + tw * etq[ti + 1]))
                    yy = r[b, a, i] * r[b, a, j]
                    Y[g, a, band, age, i * width + j] += w * yy
                    Ew[g, a, band, age, i * width + j] += w * ew
                    for q in range(T):
                        Et[g, a, band, age, i * width + j, q] += w * etq[q]
                    if i == j:
                        qtr += qq
                        q2 += qq * qq
                    else:
                        Y[g, a, band, age, j * width + i] += w * yy
                        Ew[g, a, band, age, j * width + i] += w * ew
                        for q in range(T):
                            Et[g, a, band, age, j * width + i, q] += w * etq[q]
                        q2 += 2.0 * qq * qq
            het_out[b, 0] += qtr
            het_out[b, 1] += q2
