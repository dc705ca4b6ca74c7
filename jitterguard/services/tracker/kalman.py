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
    max_speed: F64,
    max_yaw_rate: F64,
) -> tuple[F64, F64]:
    """Propagate every track by its own ``dt`` (seconds, >= 0); returns new arrays (inputs are not changed).

    CV uses the discrete white-noise-acceleration model per axis; CTRV propagates along the heading with the
    midpoint heading ``yaw + w dt / 2`` (Autoware's CTRV), linearised for the covariance (an EKF), with
    longitudinal/lateral acceleration noise on position and random walks on speed and yaw rate.
    """
    n = x.shape[0]
    xn = x.copy()
    F = np.broadcast_to(np.eye(STATE_DIM), (n, STATE_DIM, STATE_DIM)).copy()
    Q = np.zeros((n, STATE_DIM, STATE_DIM))
    dt2 = dt * dt

    cv = model == CV
    if cv.any():
        d = dt[cv]
        d2 = d * d
        xn[cv, IX] += x[cv, I3] * d
        xn[cv, IY] += x[cv, I4] * d
        F[cv, IX, I3] = d
        F[cv, IY, I4] = d
        qa = q_acc[cv] ** 2
        q_pp = 0.25 * d2 * d2 * qa
        q_pv = 0.5 * d2 * d * qa
        q_vv = d2 * qa
        Q[cv, IX, IX] = q_pp
        Q[cv, IY, IY] = q_pp
        Q[cv, IX, I3] = Q[cv, I3, IX] = q_pv
        Q[cv, IY, I4] = Q[cv, I4, IY] = q_pv
        Q[cv, I3, I3] = q_vv
        Q[cv, I4, I4] = q_vv
        Q[cv, IYAW, IYAW] = q_yaw[cv] ** 2 * d

    ct = ~cv
    if ct.any():
        d = dt[ct]
        d2 = dt2[ct]
        yaw = x[ct, IYAW]
        v = x[ct, I3]
        w = x[ct, I4]
        th = yaw + 0.5 * w * d
        c, s = np.cos(th), np.sin(th)
        xn[ct, IX] += v * c * d
        xn[ct, IY] += v * s * d
        xn[ct, IYAW] = wrap_pi(yaw + w * d)
        F[ct, IX, IYAW] = -v * s * d
        F[ct, IX, I3] = c * d
        F[ct, IX, I4] = -0.5 * v * s * d2
        F[ct, IY, IYAW] = v * c * d
        F[ct, IY, I3] = s * d
        F[ct, IY, I4] = 0.5 * v * c * d2
        F[ct, IYAW, I4] = d
        # position noise from acceleration, along / across the heading, rotated into the world frame
        ql = (0.5 * q_acc[ct] * d2) ** 2
        qt = (0.5 * q_acc_lat[ct] * d2) ** 2
        cy, sy = np.cos(yaw), np.sin(yaw)
        Q[ct, IX, IX] = cy * cy * ql + sy * sy * qt
        Q[ct, IY, IY] = sy * sy * ql + cy * cy * qt
        Q[ct, IX, IY] = Q[ct, IY, IX] = cy * sy * (ql - qt)
        Q[ct, IYAW, IYAW] = q_yaw[ct] ** 2 * d
        Q[ct, I3, I3] = (q_acc[ct] * d) ** 2
        Q[ct, I4, I4] = (q_yaw_rate_acc[ct] * d) ** 2

    Pn = F @ P @ F.transpose(0, 2, 1) + Q
    clamp(xn, model, max_speed, max_yaw_rate)
    return xn, Pn


def clamp(x: F64, model: NDArray[np.int8], max_speed: F64, max_yaw_rate: F64) -> None:
    """Keep speeds and yaw rates physical (a filter fed a bad association must not report 200 km/h)."""
    cv = model == CV
    if cv.any():
        v = x[cv, I3:I4 + 1]
        sp = np.hypot(v[:, 0], v[:, 1])
        scale = np.minimum(1.0, max_speed[cv] / np.maximum(sp, 1e-12))
        x[cv, I3:I4 + 1] = v * scale[:, None]
    ct = ~cv
    if ct.any():
        x[ct, I3] = np.clip(x[ct, I3], -max_speed[ct], max_speed[ct])
        x[ct, I4] = np.clip(x[ct, I4], -max_yaw_rate[ct], max_yaw_rate[ct])


def update(x: F64, P: F64, z: F64, R: F64) -> tuple[F64, F64]:
    """Batched measurement update with ``z = [x, y, yaw]`` and ``H = [I3 | 0]``; returns new arrays.

    ``R`` is ``(K, 3, 3)``; a heading that was not measured is given a huge variance (and any value), which
    leaves the heading untouched without a second code path. The heading innovation is wrapped modulo pi.
    The covariance update uses the Joseph form so it stays symmetric positive definite over long runs.
    """
    innov = z - x[:, :MEAS_DIM]
    innov[:, IYAW] = wrap_half_pi(innov[:, IYAW])
    PHt = P[:, :, :MEAS_DIM]  # P Hᵀ, (K, 5, 3)
    S = P[:, :MEAS_DIM, :MEAS_DIM] + R
    K = np.linalg.solve(S, PHt.transpose(0, 2, 1)).transpose(0, 2, 1)  # P Hᵀ S⁻¹ (S symmetric)
    xn = x + np.einsum("kij,kj->ki", K, innov)
    xn[:, IYAW] = wrap_pi(xn[:, IYAW])
    IKH = np.broadcast_to(np.eye(STATE_DIM), P.shape).copy()
    IKH[:, :, :MEAS_DIM] -= K
    Pn = IKH @ P @ IKH.transpose(0, 2, 1) + K @ R @ K.transpose(0, 2, 1)
    Pn = 0.5 * (Pn + Pn.transpose(0, 2, 1))
    return xn, Pn


def world_velocity(x: F64, P: F64, model: NDArray[np.int8]) -> tuple[F64, F64, F64, F64]:
    """World-frame velocity (N, 2), its covariance (N, 2, 2), yaw rate (N,) and yaw-rate variance (N,).

    CTRV's (speed, heading) is mapped to (vx, vy) with the Jacobian of ``v (cos yaw, sin yaw)``, so the
    covariance reflects heading uncertainty too; a CV track has no yaw rate (zero, zero variance).
    """
    n = x.shape[0]
    vel = np.empty((n, 2))
    cov = np.empty((n, 2, 2))
    w = np.zeros(n)
    wvar = np.zeros(n)
    cv = model == CV
    if cv.any():
        vel[cv] = x[cv, I3:I4 + 1]
        cov[cv] = P[cv, I3:I4 + 1, I3:I4 + 1]
    ct = ~cv
    if ct.any():
        yaw = x[ct, IYAW]
        v = x[ct, I3]
        c, s = np.cos(yaw), np.sin(yaw)
        vel[ct, 0] = v * c
        vel[ct, 1] = v * s
        J = np.zeros((int(ct.sum()), 2, 2))  # d(vx, vy) / d(yaw, v)
        J[:, 0, 0] = -v * s
        J[:, 0, 1] = c
        J[:, 1, 0] = v * c
        J[:, 1, 1] = s
        sub = P[ct][:, [IYAW, I3]][:, :, [IYAW, I3]]
        cov[ct] = J @ sub @ J.transpose(0, 2, 1)
        w[ct] = x[ct, I4]
        wvar[ct] = P[ct, I4, I4]
    return vel, cov, w, wvar


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
