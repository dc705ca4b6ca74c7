"""Batched Kalman filters for every track at once: constant velocity (CV) and CTRV, one shared layout.

Why one layout: the per-frame path must handle hundreds of tracks in a few milliseconds, which rules out a
Python object per filter. Every track's state is a row of one ``(N, 5)`` array and its covariance a slice of
one ``(N, 5, 5)`` array; the two motion models only differ in prediction, so the measurement update is a
single batched expression over all associated tracks.

State layout (the first three entries are the measured ones, so ``H = [I3 | 0]`` for both models):

* CV   (model 0): ``[x, y, yaw, vx, vy]`` — world-frame velocity; heading is a random walk (shape only).
* CTRV (model 1): ``[x, y, yaw, v, w]``  — speed along the heading and yaw rate (Autoware's vehicle model).

The heading innovation is wrapped modulo pi, as Autoware does for vehicles: detectors often flip a box by
180 degrees, and a CTRV filter represents driving backwards with a negative speed, not a flipped heading.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]

CV = 0
CTRV = 1
STATE_DIM = 5
MEAS_DIM = 3
IX, IY, IYAW, I3, I4 = 0, 1, 2, 3, 4


def wrap_pi(a: F64) -> F64:
    """Wrap to [-pi, pi)."""
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def wrap_half_pi(a: F64) -> F64:
    """Wrap to [-pi/2, pi/2): a heading difference where a 180-degree flip counts as no difference."""
    return (a + 0.5 * np.pi) % np.pi - 0.5 * np.pi


def predict(
    x: F64,
    P: F64,
    dt: F64,
    model: NDArray[np.int8],
    q_acc: F64,
    q_acc_lat: F64,
    q_yaw: F64,
    q_yaw_rate_acc: F64,
) -> tuple[F64, F64]:
    """Propagate every track by its own ``dt`` (seconds, >= 0); returns new arrays (inputs are not changed).

    CV uses the discrete white-noise-acceleration model per axis; CTRV propagates along the heading with the
    midpoint heading ``yaw + w dt / 2`` (Autoware's CTRV), linearised for the covariance (an EKF), with
    longitudinal/lateral acceleration noise on position and random walks on speed and yaw rate. Both models
    are evaluated for every row and selected with ``np.where``: a handful of full-length vector operations
    is far cheaper than masked fancy indexing per model.
    """
    n = x.shape[0]
    ct = model == CTRV
    yaw, a3, a4 = x[:, IYAW], x[:, I3], x[:, I4]
    dt2 = dt * dt
    th = yaw + 0.5 * a4 * dt
    c, s = np.cos(th), np.sin(th)
    vc, vs = a3 * c, a3 * s

    xn = x.copy()
    xn[:, IX] += np.where(ct, vc, a3) * dt
    xn[:, IY] += np.where(ct, vs, a4) * dt
    xn[:, IYAW] = np.where(ct, wrap_pi(yaw + a4 * dt), yaw)

    F = np.zeros((n, STATE_DIM, STATE_DIM))
    F[:, IX, IX] = F[:, IY, IY] = F[:, IYAW, IYAW] = F[:, I3, I3] = F[:, I4, I4] = 1.0
    zero = np.zeros(n)
    F[:, IX, IYAW] = np.where(ct, -vs * dt, zero)
    F[:, IX, I3] = np.where(ct, c * dt, dt)
    F[:, IX, I4] = np.where(ct, -0.5 * vs * dt2, zero)
    F[:, IY, IYAW] = np.where(ct, vc * dt, zero)
    F[:, IY, I3] = np.where(ct, s * dt, zero)
    F[:, IY, I4] = np.where(ct, 0.5 * vc * dt2, dt)
    F[:, IYAW, I4] = np.where(ct, dt, zero)

    Q = np.zeros((n, STATE_DIM, STATE_DIM))
    qa2 = q_acc * q_acc
    # CV: white-noise acceleration per world axis
    cv_pp = 0.25 * dt2 * dt2 * qa2
    cv_pv = 0.5 * dt2 * dt * qa2
    cv_vv = dt2 * qa2
    # CTRV: acceleration along / across the heading on position, rotated into the world frame
    ql = 0.25 * dt2 * dt2 * qa2
    qt = 0.25 * dt2 * dt2 * q_acc_lat * q_acc_lat
    cy, sy = np.cos(yaw), np.sin(yaw)
    Q[:, IX, IX] = np.where(ct, cy * cy * ql + sy * sy * qt, cv_pp)
    Q[:, IY, IY] = np.where(ct, sy * sy * ql + cy * cy * qt, cv_pp)
    Q[:, IX, IY] = Q[:, IY, IX] = np.where(ct, cy * sy * (ql - qt), zero)
    Q[:, IX, I3] = Q[:, I3, IX] = np.where(ct, zero, cv_pv)
    Q[:, IY, I4] = Q[:, I4, IY] = np.where(ct, zero, cv_pv)
    Q[:, IYAW, IYAW] = q_yaw * q_yaw * dt
    Q[:, I3, I3] = cv_vv
    Q[:, I4, I4] = np.where(ct, q_yaw_rate_acc * q_yaw_rate_acc * dt2, cv_vv)

    Pn = F @ P @ F.transpose(0, 2, 1) + Q
    return xn, Pn  # prediction leaves speeds and yaw rates as they were: no clamp needed here


def clamp(x: F64, model: NDArray[np.int8], max_speed: F64, max_yaw_rate: F64) -> None:
    """Keep speeds and yaw rates physical (a filter fed a bad association must not report 200 km/h)."""
    ct = model == CTRV
    a3, a4 = x[:, I3], x[:, I4]
    sp = np.where(ct, np.abs(a3), np.hypot(a3, a4))
    scale = np.minimum(1.0, max_speed / np.maximum(sp, 1e-12))
    x[:, I3] = a3 * scale
    x[:, I4] = np.where(ct, np.clip(a4, -max_yaw_rate, max_yaw_rate), a4 * scale)


def _inv3_sym(S: F64) -> F64:
    """Inverse of a batch of symmetric positive-definite 3x3 matrices by cofactors (no LAPACK call per row)."""
    a, b, c = S[:, 0, 0], S[:, 0, 1], S[:, 0, 2]
    d, e, f = S[:, 1, 1], S[:, 1, 2], S[:, 2, 2]
    A = d * f - e * e
    B = c * e - b * f
    C = b * e - c * d
    D = a * f - c * c
    E = b * c - a * e
    G = a * d - b * b
    det = a * A + b * B + c * C
    inv = np.empty_like(S)
    inv[:, 0, 0], inv[:, 0, 1], inv[:, 0, 2] = A, B, C
    inv[:, 1, 0], inv[:, 1, 1], inv[:, 1, 2] = B, D, E
    inv[:, 2, 0], inv[:, 2, 1], inv[:, 2, 2] = C, E, G
    return inv / det[:, None, None]


def update(x: F64, P: F64, z: F64, R: F64) -> tuple[F64, F64]:
    """Batched measurement update with ``z = [x, y, yaw]`` and ``H = [I3 | 0]``; returns new arrays.

    ``R`` is ``(K, 3, 3)``; a heading that was not measured is given a huge variance (and any value), which
    leaves the heading untouched without a second code path. The heading innovation is wrapped modulo pi.
    ``P - K H P`` is symmetrised afterwards; with float64 and measurement noise floored that stays positive
    definite (the Joseph form costs two more batched 5x5 products per frame for no observable gain here).
    """
    innov = z - x[:, :MEAS_DIM]
    innov[:, IYAW] = wrap_half_pi(innov[:, IYAW])
    HP = P[:, :MEAS_DIM, :]  # H P, (K, 3, 5)
    S = HP[:, :, :MEAS_DIM] + R
    K = HP.transpose(0, 2, 1) @ _inv3_sym(S)  # P Hᵀ S⁻¹, (K, 5, 3)
    xn = x + (K @ innov[:, :, None])[:, :, 0]
    xn[:, IYAW] = wrap_pi(xn[:, IYAW])
    Pn = P - K @ HP
    Pn = 0.5 * (Pn + Pn.transpose(0, 2, 1))
    return xn, Pn


def world_velocity(x: F64, P: F64, model: NDArray[np.int8]) -> tuple[F64, F64, F64, F64]:
    """World-frame velocity (N, 2), its covariance (N, 2, 2), yaw rate (N,) and yaw-rate variance (N,).

    CTRV's (speed, heading) is mapped to (vx, vy) with the Jacobian of ``v (cos yaw, sin yaw)``, so the
    covariance reflects heading uncertainty too; a CV track has no yaw rate (zero, zero variance).
    """
    ct = model == CTRV
    yaw, a3, a4 = x[:, IYAW], x[:, I3], x[:, I4]
    c, s = np.cos(yaw), np.sin(yaw)
    vel = np.empty((x.shape[0], 2))
    vel[:, 0] = np.where(ct, a3 * c, a3)
    vel[:, 1] = np.where(ct, a3 * s, a4)
    # J = d(vx, vy)/d(yaw, v) = [[-v s, c], [v c, s]];  cov = J [[a, b], [b, d]] Jᵀ
    a, b, d = P[:, IYAW, IYAW], P[:, IYAW, I3], P[:, I3, I3]
    v = a3
    cov = np.empty((x.shape[0], 2, 2))
    cov[:, 0, 0] = np.where(ct, v * v * s * s * a - 2.0 * v * s * c * b + c * c * d, P[:, I3, I3])
    cov[:, 1, 1] = np.where(ct, v * v * c * c * a + 2.0 * v * c * s * b + s * s * d, P[:, I4, I4])
    cov[:, 0, 1] = cov[:, 1, 0] = np.where(ct, -v * v * s * c * a + v * (c * c - s * s) * b + c * s * d,
                                           P[:, I3, I4])
    zero = np.zeros(x.shape[0])
    return vel, cov, np.where(ct, a4, zero), np.where(ct, P[:, I4, I4], zero)


def set_static(x: F64, P: F64, rows: NDArray[np.intp], px: F64, py: F64) -> None:
    """Autoware's setStaticState, in place: zero velocity (and yaw rate), position set to ``(px, py)``.

    The velocity's correlations with the other states are cleared as well: they described how the old
    velocity explained the old position, and keeping them would let the next update pull the velocity back.
    The variances stay, so a track that really starts moving picks its speed up again at the usual rate.
    """
    if rows.size == 0:
        return
    x[rows, IX] = px
    x[rows, IY] = py
    x[rows, I3] = 0.0  # CV: vx, CTRV: speed
    x[rows, I4] = 0.0  # CV: vy, CTRV: yaw rate
    for k in (I3, I4):
        var = P[rows, k, k].copy()
        P[rows, k, :] = 0.0
        P[rows, :, k] = 0.0
        P[rows, k, k] = var
