"""The test statistics of the motion classifier (paper §III-B), over every track of a frame at once.

Inputs are windows stored as dense ``(K, W)`` arrays with a boolean mask per half, so one call scores every
track of a frame at once: the paper's statistic as numpy expressions, the calibrated one by a compiled loop per
window (:mod:`.window_kernel`). Nothing here knows about tracks, IDs or messages.

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

from .calibration import SCALE_BOUNDS, NoiseModel
from .calibration import warm_up as calibration_warm_up
from .jump_kernel import jump_ratios
from .window_kernel import CLUSTER, INDEPENDENT, MEASURED, calibrated_windows

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


def two_sided_p(alpha: float | F64) -> F64:
    """P(|Z| > alpha) for a standard normal Z: the nominal false-alarm rate of one z-test axis."""
    a = np.asarray(alpha, dtype=np.float64)
    return np.vectorize(math.erfc, otypes=[np.float64])(a / math.sqrt(2.0))


def chi2_2_threshold(alpha: float | F64) -> F64:
    """The χ²₂ quantile with the same false-alarm rate as a two-sided z-test at ``alpha``.

    χ² with two degrees of freedom has survival function exp(-x/2), so the quantile is -2 ln p, with ln p taken
    in the log domain (ln 2 + ln Φ(−α)): p itself underflows past α ≈ 37.5, and clipped to 1e-300 it had held
    the threshold at 1381.6 for every α from there to the config's bound of 100 (α 50 fired at χ² 1400, a z of
    37; exactly, 2508).
    """
    from scipy.special import log_ndtr  # type: ignore[import-untyped]

    a = np.asarray(alpha, dtype=np.float64)
    return np.maximum(-2.0 * (math.log(2.0) + log_ndtr(-a)), 0.0)  # α ≤ 0: every window (0, as p = 1 gave)


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
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
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
    # Δμᵀ S⁻¹ Δμ with S divided by its trace first: the determinant of S itself underflows to 0 for variances below
    # ~1e-154 (a variance_floor the config accepts, reported variances of 0), and 0 / 0 had saturated the χ² of a
    # window that did not move to the largest float — "dynamic" in the chi2 mode
    s = a + c  # > 0: both eigenvalues are floored
    a, b, c = a / s, b / s, c / s
    num = c * dx * dx - 2.0 * b * dx * dy + a * dy * dy
    chi2 = np.where(num == 0.0, 0.0, num / ((a * c - b * b) * s))  # no displacement: no evidence of motion

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
                          min_speed: float = 0.0, view_slide: F64 | None = None,
                          contrast: F64 | None = None) -> WindowStats:
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
    ν degrees of freedom, reported as a z): λ from the residuals of the window about a constant-velocity fit
    against what the model expects of them, shrunk to 1 with the class's prior degrees of freedom
    (:meth:`NoiseModel.test_dof`). ``view_slide`` (per window, m; None or 0: none) then adds the view term:
    λ V + s² Δū Δūᵀ, Δū the half-mean contrast of the unit vectors from the sensor to the window's mean position
    — a box centre placed from the faces the sensor sees slides with the view as the sensor drives past a parked
    car, a displacement the reported covariances do not describe. It is geometry, not noise, so λ does not scale
    it (a mover on a curve, whose λ is large, would otherwise lose its displacement to it; docs/classifier.md
    'The view term'). Not the observed line of sight: a car passing a stopped sensor turns that by its own
    motion, and the allowance would hide the motion it is tested for.

    The arithmetic runs compiled, one loop per window (:func:`~.window_kernel.calibrated_windows`, where the
    track scale's closed form is written out). A statistic that overflows saturates (:func:`_saturate`), as in
    :func:`window_statistics`.

    ``contrast`` (optional, a (7, K) array) receives what the view term's learning weighs (:mod:`.view_slide`):
    the displacement d (x, y; before H0's speed shrinks it), its covariance before the view term (λ V: xx, xy, yy) and
    Δū (x, y).
    """
    k = len(groups)
    # the compiled loop does not check its indices: what numpy would refuse with an IndexError is refused here
    if windows.ndim != 3 or windows.shape[0] != k or windows.shape[2] < len(CHANNELS):
        raise ValueError(f"windows: expected ({k}, W, ≥{len(CHANNELS)}), got {windows.shape}")
    if masks.old.shape != windows.shape[:2] or masks.new.shape != windows.shape[:2] or masks.n_old.shape != (k,) \
            or masks.n_new.shape != (k,):
        raise ValueError(f"masks: expected ({k}, {windows.shape[1]}) and ({k},)")
    if k and (int(groups.min()) < 0 or int(groups.max()) >= model.scale.shape[0]):
        raise ValueError(f"groups: expected indices in [0, {model.scale.shape[0]})")
    if view_slide is not None and np.shape(view_slide) != (k,):
        raise ValueError(f"view_slide: expected ({k},), got {np.shape(view_slide)}")
    if model.scale.shape[2] != len(model.band_edges_m) + 1 or model.scale.shape[3] < 2:
        raise ValueError(f"model.scale: expected (G, 2, {len(model.band_edges_m) + 1}, 2), got {model.scale.shape}")
    if contrast is not None and contrast.shape != (7, k):
        raise ValueError(f"contrast: expected (7, {k}), got {contrast.shape}")
    out = np.zeros((6 if contrast is None else 13, k))
    dof = model.test_dof(np.arange(model.scale.shape[0])) if track_scale_prior else np.ones(model.scale.shape[0])
    view = np.zeros(k) if view_slide is None else np.ascontiguousarray(view_slide, dtype=np.float64)
    calibrated_windows(np.ascontiguousarray(windows, dtype=np.float64), np.ascontiguousarray(masks.old),
                       np.ascontiguousarray(masks.new), np.ascontiguousarray(masks.n_old, dtype=np.float64),
                       np.ascontiguousarray(masks.n_new, dtype=np.float64),
                       np.ascontiguousarray(groups, dtype=np.int64), np.ascontiguousarray(model.scale, dtype=np.float64),
                       np.asarray(model.band_edges_m, dtype=np.float64),
                       np.ascontiguousarray(model.correlation, dtype=np.float64),
                       np.ascontiguousarray(model.tau_s, dtype=np.float64), np.ascontiguousarray(dof, dtype=np.float64),
                       view, float(variance_floor), _MODES[effective_n], bool(track_scale_prior), float(min_speed),
                       float(SCALE_BOUNDS[0]), float(SCALE_BOUNDS[1]), out)
    if contrast is not None:
        contrast[:] = out[6:]
    z_x, z_y, chi2, mean_x, mean_y, nu = out[:6]
    if track_scale_prior:
        with np.errstate(invalid="ignore"):
            z = t_to_z(np.concatenate([z_x, z_y]), np.concatenate([nu, nu]))
            chi2 = t2_to_chi2(chi2, nu)
        z_x, z_y = z[:k], z[k:]
    return WindowStats(z_x=_saturate(z_x), z_y=_saturate(z_y), chi2=_saturate(chi2), mean_x=mean_x, mean_y=mean_y)


_MODES = {"cluster": CLUSTER, "independent": INDEPENDENT, "measured": MEASURED}


def warm_up() -> None:
    """Compile (or load from numba's cache) the calibrated statistic, the jump veto's shape test and the online
    calibration's pooling now, so a service pays it at start rather than on its first frames."""
    masks = split_halves(np.zeros(1, dtype=np.int64), np.array([4]), 4)
    win = np.zeros((1, 4, len(CHANNELS)))
    win[0, :, 2] = win[0, :, 4] = 0.01
    win[0, :, 5] = np.arange(4) * 0.1
    calibrated_statistics(win, masks, np.zeros(1, dtype=np.int64), NoiseModel.prior(), variance_floor=1e-4,
                          effective_n="measured", track_scale_prior=False)
    jump_ratio(win, np.array([4]), min_count=4)
    calibration_warm_up()


def jump_ratio(windows: F64, count: I64, *, min_count: int = 6) -> F64:
    """Per window, the residual sum of squares of its positions about the best single step (each side of one split
    its own mean, the split shared by both axes, at least two observations a side) over that about the best
    motion — the least-squares constant-velocity line, or a one-sided hinge (a stand that turns into steady motion at
    one observation's stamp, or steady motion that comes to a stand there, each axis its own offset and speed, the
    knot shared, two observations or more a side: an object that starts or stops inside the window): below 1 a jump
    explains the window better than any of them. The hinges are fitted only where the step beats the line
    (elsewhere the ratio is the step's over the line's, at least 1 either way), so a mover's ramp costs no more
    than the line and the step.

    Why: the half-mean contrast the z-test weighs is the same for a box the detector re-placed once (an occlusion
    change, a box slid along the car) and for an object that moved as far; the shape of the window tells them
    apart — a mover traces a ramp, a re-placed box a step. A car that starts (or stops) in the window traces a
    ramp on one side of a stand, which a step can fit better than one straight line; the hinges, with as many
    free values as the step, keep it a mover. ``windows`` is ``(K, W, ≥6)`` over :data:`CHANNELS` oldest first
    with each row's ``count`` newest observations in its last slots (``_Table.ordered``); rows with fewer than
    ``min_count`` observations (at least 4: two a side; the classifier asks 6 of a vehicle's window and a full
    window of other classes, whose short windows' shape says little), a line that fits exactly, one instant for
    every stamp, or non-finite input give inf (no evidence of a jump). Computed by :func:`~.jump_kernel.jump_ratios`, one compiled loop per window."""
    out = np.full(windows.shape[0], np.inf)
    jump_ratios(np.ascontiguousarray(windows, dtype=np.float64), np.ascontiguousarray(count, dtype=np.int64),
                max(int(min_count), 4), out)
    return out


def t_to_z(t: F64, dof: F64) -> F64:
    """The standard-normal score with the same two-sided p-value as |t| under Student's t with ``dof``.

    Where the tail probability falls below :data:`_TINY_P` (a z beyond 37) it is taken in the log domain
    (:func:`_t_log_tail`): as a probability it underflows, and the z had stuck at 37.04 (the clip) and then jumped
    to |t| itself (ν 1000, t 100: z 100 where it is 49) — wrong decisions for an α the config allows (up to 100),
    and a statistic that did not grow with the evidence."""
    from scipy.special import ndtri, ndtri_exp, stdtr  # type: ignore[import-untyped]

    t = np.abs(np.asarray(t, dtype=np.float64))
    dof = np.broadcast_to(np.asarray(dof, dtype=np.float64), t.shape)
    p_half = stdtr(dof, -t)  # one tail
    z = np.array(-ndtri(np.maximum(p_half, _TINY_P)), dtype=np.float64)
    far = ~(p_half > _TINY_P) & ~np.isnan(t) & ~np.isnan(dof)
    if far.any():
        z[far] = -ndtri_exp(np.minimum(_t_log_tail(t[far], dof[far]), math.log(_TINY_P)))
    return np.where(np.isnan(t), t, z)


_TINY_P = 1e-300
"""Below this one-sided tail probability :func:`t_to_z` works in the log domain (z ≈ 37.04 here)."""


def _t_log_tail(t: F64, dof: F64) -> F64:
    """ln P(T > t) for Student's t with ``dof`` degrees of freedom and t > 0, without forming the probability:
    P = ½ I_x(ν/2, ½), x = ν / (ν + t²), and I_x(a, b) = x^a (1 − x)^b ₂F₁(a + b, 1; a + 1; x) / (a B(a, b)) —
    a series whose terms shrink at least as fast as x^n, and x is small wherever the tail is (< e^(−690/a)).
    Infinite ``dof`` is the normal tail."""
    from scipy.special import betaln, hyp2f1, log_ndtr  # type: ignore[import-untyped]

    finite = np.isfinite(dof)
    nu = np.where(finite, dof, 1.0)
    a = nu / 2.0
    with np.errstate(over="ignore", divide="ignore"):
        r = t * t / nu
        log_x = np.where(np.isfinite(r), -np.log1p(r), np.log(nu) - 2.0 * np.log(t))  # ln ν/(ν + t²), t² may overflow
        x = np.exp(log_x)
        out = (a * log_x + 0.5 * np.log1p(-x) - np.log(a) - betaln(a, 0.5) + np.log(hyp2f1(a + 0.5, 1.0, a + 1.0, x))
               - math.log(2.0))
    return np.where(finite, out, log_ndtr(-t))


def t2_to_chi2(t2: F64, dof: F64) -> F64:
    """The χ²₂ value with the same upper-tail probability as T² = Δμᵀ (λ̂ V)⁻¹ Δμ, whose scale λ̂ (the window's own)
    has ``dof`` degrees of freedom — what :func:`t_to_z` is to each axis' t, for the ``chi2`` mode: compared with
    the χ²₂ quantile of α, it then fires at the rate the z's do rather than at the heavier tail of an estimated
    scale (at a cold start, about twice the nominal rate at α 2.58). T²/2 ~ F(2, ν), whose survival is
    (1 + T²/ν)^(−ν/2), so −2 ln p = ν ln(1 + T²/ν); T² itself as ν → ∞."""
    ok = np.isfinite(dof) & (dof > 0)
    return np.where(ok, dof * np.log1p(t2 / np.where(ok, dof, 1.0)), t2)


_MAX = float(np.finfo(np.float64).max)


def _saturate(stat: F64) -> F64:
    """A statistic that overflowed (positions ~1e300 apart square to inf; inf - inf is NaN) is beyond any
    threshold: the largest finite float, so the decision is "dynamic" and every message carrying it stays valid
    (the wire contract, and the classifier's own readers, reject non-finite numbers). A negative zero (−ndtri(½)
    of a window inside the H0 speed bound) becomes 0.0: it had gone on the wire as −0.0 and read "z=-0.00" in
    every viewer."""
    return np.clip(np.nan_to_num(stat, nan=_MAX, posinf=_MAX, neginf=0.0), 0.0, _MAX) + 0.0
