"""The batched filters: CV and CTRV predict/update against closed forms and long-run convergence."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jitterguard.services.tracker import kalman
from jitterguard.services.tracker.kalman import CTRV, CV


def _noise(n: int, **kw: float) -> dict[str, np.ndarray]:
    base = dict(q_acc=1.0, q_acc_lat=0.5, q_yaw=0.1, q_yaw_rate_acc=0.3)
    base.update(kw)
    return {k: np.full(n, v) for k, v in base.items()}


def test_cv_predict_moves_by_velocity_and_grows_covariance_like_white_noise_acceleration() -> None:
    x = np.array([[1.0, 2.0, 0.3, 3.0, -1.0]])
    P = np.eye(5)[None] * 0.5
    dt = np.array([0.2])
    xn, Pn = kalman.predict(x, P, dt, np.array([CV], dtype=np.int8), **_noise(1, q_acc=2.0))
    np.testing.assert_allclose(xn[0], [1.6, 1.8, 0.3, 3.0, -1.0])
    F = np.eye(5)
    F[0, 3] = F[1, 4] = 0.2
    q = 4.0
    Q = np.zeros((5, 5))
    for p, v in ((0, 3), (1, 4)):
        Q[p, p] = 0.25 * 0.2**4 * q
        Q[p, v] = Q[v, p] = 0.5 * 0.2**3 * q
        Q[v, v] = 0.2**2 * q
    Q[2, 2] = 0.1**2 * 0.2
    np.testing.assert_allclose(Pn[0], F @ P[0] @ F.T + Q, atol=1e-12)


def test_ctrv_predict_follows_the_arc_midpoint_heading() -> None:
    x = np.array([[0.0, 0.0, 0.0, 10.0, 0.5]])
    xn, _ = kalman.predict(x, np.eye(5)[None], np.array([0.1]), np.array([CTRV], dtype=np.int8), **_noise(1))
    th = 0.5 * 0.5 * 0.1
    np.testing.assert_allclose(xn[0], [10 * math.cos(th) * 0.1, 10 * math.sin(th) * 0.1, 0.05, 10.0, 0.5])


def test_ctrv_jacobian_matches_finite_differences() -> None:
    """The EKF covariance is only right if F is the derivative of the motion model."""
    x0 = np.array([3.0, -2.0, 0.7, 8.0, 0.3])
    dt = np.array([0.1])
    m = np.array([CTRV], dtype=np.int8)
    zeros = _noise(1, q_acc=1e-12, q_acc_lat=1e-12, q_yaw=1e-12, q_yaw_rate_acc=1e-12)
    J = np.zeros((5, 5))
    eps = 1e-6
    for k in range(5):
        d = np.zeros(5)
        d[k] = eps
        a, _ = kalman.predict((x0 + d)[None], np.zeros((1, 5, 5)), dt, m, **zeros)
        b, _ = kalman.predict((x0 - d)[None], np.zeros((1, 5, 5)), dt, m, **zeros)
        J[:, k] = (a[0] - b[0]) / (2 * eps)
    P = np.diag([0.1, 0.2, 0.05, 1.0, 0.1])
    _, Pn = kalman.predict(x0[None], P[None], dt, m, **zeros)
    np.testing.assert_allclose(Pn[0], J @ P @ J.T, atol=1e-9)


@settings(max_examples=40, deadline=None, derandomize=True)
@given(st.lists(st.floats(0.01, 10.0), min_size=6, max_size=6), st.floats(-0.9, 0.9))
def test_update_matches_textbook_kalman_gain(diag: list[float], rho: float) -> None:
    rng = np.random.default_rng(0)
    A = rng.normal(size=(5, 5))
    P = A @ A.T + np.diag(diag[:5])
    R = np.diag([diag[5], diag[5] * 2, 0.01])
    R[0, 1] = R[1, 0] = rho * math.sqrt(R[0, 0] * R[1, 1])
    x = rng.normal(size=5)
    x[2] = 0.1
    z = x[:3] + rng.normal(size=3) * 0.1
    xn, Pn = kalman.update(x[None], P[None], z[None], R[None])
    H = np.hstack([np.eye(3), np.zeros((3, 2))])
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    np.testing.assert_allclose(xn[0], x + K @ (z - H @ x), rtol=1e-8, atol=1e-9)
    np.testing.assert_allclose(Pn[0], (np.eye(5) - K @ H) @ P, rtol=1e-7, atol=1e-9)
    assert np.all(np.linalg.eigvalsh(Pn[0]) > 0)


def test_heading_flip_is_not_an_innovation() -> None:
    """A detector box turned by 180 degrees must not swing the track's heading (innovation mod pi)."""
    x = np.array([[0.0, 0.0, 0.1, 5.0, 0.0]])
    P = np.eye(5)[None]
    xn, _ = kalman.update(x, P, np.array([[0.0, 0.0, 0.1 + math.pi]]), np.eye(3)[None] * 0.01)
    assert xn[0, 2] == pytest.approx(0.1, abs=1e-9)


def test_unmeasured_heading_leaves_heading_alone() -> None:
    x = np.array([[0.0, 0.0, 0.4, 1.0, 0.0]])
    R = np.diag([0.1, 0.1, 1e6])[None]
    xn, _ = kalman.update(x, np.eye(5)[None], np.array([[0.5, 0.0, -1.2]]), R)
    assert xn[0, 2] == pytest.approx(0.4, abs=1e-5)
    assert xn[0, 0] > 0.4  # the position still moved towards the measurement


@pytest.mark.parametrize("model", [CV, CTRV])
def test_filter_recovers_constant_velocity_from_noisy_positions(model: int) -> None:
    rng = np.random.default_rng(3)
    vx, vy = 6.0, 2.0
    heading = math.atan2(vy, vx)
    x = np.array([[0.0, 0.0, heading, 0.0, 0.0]])
    P = np.diag([0.1, 0.1, 0.01, 100.0, 100.0 if model == CV else 0.25])[None]
    m = np.array([model], dtype=np.int8)
    R = np.diag([0.04, 0.04, 0.0025])[None]
    for k in range(1, 80):
        x, P = kalman.predict(x, P, np.array([0.1]), m, **_noise(1))
        t = 0.1 * k
        z = np.array([[vx * t + rng.normal(0, 0.2), vy * t + rng.normal(0, 0.2), heading + rng.normal(0, 0.05)]])
        x, P = kalman.update(x, P, z, R)
    vel, cov, _, _ = kalman.world_velocity(x, P, m)
    assert vel[0] == pytest.approx([vx, vy], abs=0.4)
    # the reported velocity uncertainty is consistent with the error (within 4 sigma per axis)
    err = vel[0] - [vx, vy]
    assert abs(err[0]) < 4 * math.sqrt(cov[0, 0, 0]) + 0.05
    assert abs(err[1]) < 4 * math.sqrt(cov[0, 1, 1]) + 0.05


def test_ctrv_world_velocity_covariance_is_the_jacobian_transform() -> None:
    x = np.array([[0.0, 0.0, 0.6, 7.0, 0.1]])
    P = np.diag([0.1, 0.1, 0.02, 0.5, 0.05])[None].copy()
    P[0, 2, 3] = P[0, 3, 2] = 0.01
    vel, cov, w, wvar = kalman.world_velocity(x, P, np.array([CTRV], dtype=np.int8))
    c, s = math.cos(0.6), math.sin(0.6)
    J = np.array([[-7 * s, c], [7 * c, s]])
    np.testing.assert_allclose(vel[0], [7 * c, 7 * s])
    np.testing.assert_allclose(cov[0], J @ P[0][np.ix_([2, 3], [2, 3])] @ J.T, atol=1e-12)
    assert w[0] == pytest.approx(0.1) and wvar[0] == pytest.approx(0.05)


def test_clamp_limits_speed_and_yaw_rate() -> None:
    x = np.array([[0, 0, 0, 30.0, 40.0], [0, 0, 0, -90.0, 3.0]])
    kalman.clamp(x, np.array([CV, CTRV], dtype=np.int8), np.array([10.0, 20.0]), np.array([1.0, 1.0]))
    assert math.hypot(x[0, 3], x[0, 4]) == pytest.approx(10.0)
    assert x[0, 3] / x[0, 4] == pytest.approx(0.75)  # direction kept
    assert x[1, 3] == -20.0 and x[1, 4] == 1.0


def test_set_static_zeroes_velocity_moves_position_and_decorrelates() -> None:
    rng = np.random.default_rng(1)
    A = rng.normal(size=(2, 5, 5))
    P = A @ A.transpose(0, 2, 1) + np.eye(5)
    x = rng.normal(size=(2, 5))
    var_before = P[1, 3, 3]
    kalman.set_static(x, P, np.array([1]), np.array([4.0]), np.array([-2.0]))
    assert x[1, 0] == 4.0 and x[1, 1] == -2.0 and x[1, 3] == 0.0 and x[1, 4] == 0.0
    assert np.all(P[1, 3, [0, 1, 2, 4]] == 0.0) and np.all(P[1, [0, 1, 2, 4], 3] == 0.0)
    assert P[1, 3, 3] == var_before
    assert np.all(np.linalg.eigvalsh(P[1]) > 0)
    assert x[0, 3] != 0.0  # other rows untouched
