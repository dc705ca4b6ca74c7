"""How wrong a detector's reported positional variances are, per line-of-sight axis: the numbers behind the
honest presets of :mod:`jitterguard.sim.detection_model`.

The detector reports a variance per sensor axis; the motion classifier's calibration works along and across
the line of sight from the sensor, because that is where real detectors err differently (the paper's §IV-A:
longitudinal over-, lateral under-estimated). So each matched detection's error r (detection − ground truth,
sensor frame) and its reported covariance are projected on u (sensor → object) and v (u turned by 90°), and
per axis a the normalised error ε = r_a / σ_a is summarised in the log domain, where a reported σ that is off
by a factor b and scattered by a log-normal factor exp(η), η ~ N(0, s²), separates cleanly:

    log ε² = log z² − 2 log b − 2η,   z ~ N(0, 1):   E[log z²] = ψ(½) + log 2 = −1.2704,  Var[log z²] = π²/2

so ``bias`` b = exp((−1.2704 − mean log ε²) / 2) (the factor the reported σ is too small by) and ``scatter``
s = sqrt(max(0, var log ε² − π²/2) / 4). The classical figures are there too: the variance ratio mean ε²
(1 when calibrated), the ±1σ coverage (0.683). ``lag_correlation`` is the autocorrelation of ε of one object
in consecutive frames (static objects only, so a ground-truth velocity error cannot pose as correlation):
the serially correlated error ("jitter") that no per-frame variance can express.

Pure numpy over :class:`MatchedErrors`; the script ``scripts/measure_detector_noise.py`` runs the detector.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]

LOG_CHI2_1_MEAN = -1.2703628454614782
"""E[log z²] for z ~ N(0, 1): ψ(½) + log 2."""
LOG_CHI2_1_VAR = math.pi ** 2 / 2
"""Var[log z²] for z ~ N(0, 1)."""
AXES = ("along", "across")


@dataclass(frozen=True)
class MatchedErrors:
    """One row per detection matched to a ground-truth object (sensor frame)."""

    instance: NDArray[np.int64]  # ground-truth instance (one object over time)
    frame: NDArray[np.int64]  # frame index (consecutive frames differ by 1)
    static: NDArray[np.bool_]  # ground truth says the object does not move
    gx: F64  # ground-truth centre, sensor frame
    gy: F64
    rx: F64  # detection − ground truth
    ry: F64
    cxx: F64  # reported covariance of the detection, sensor frame
    cxy: F64
    cyy: F64


def line_of_sight(gx: F64, gy: F64, rx: F64, ry: F64, cxx: F64, cxy: F64, cyy: F64
                  ) -> tuple[F64, F64, F64, F64]:
    """(r_along, r_across, σ²_along, σ²_across): errors and reported variances on the line-of-sight axes."""
    rng = np.maximum(np.hypot(gx, gy), 1e-6)
    ux, uy = gx / rng, gy / rng
    r_u, r_v = ux * rx + uy * ry, -uy * rx + ux * ry
    v_u = ux * ux * cxx + 2 * ux * uy * cxy + uy * uy * cyy
    v_v = uy * uy * cxx - 2 * ux * uy * cxy + ux * ux * cyy
    return r_u, r_v, v_u, v_v


def lag_correlations(eps: F64, instance: NDArray[np.int64], frame: NDArray[np.int64], max_lag: int) -> list[float | None]:
    """Pearson correlation of ε(object, frame) with ε(object, frame + h), h = 1 … max_lag (None: no pairs)."""
    key = {(int(i), int(f)): float(e) for i, f, e in zip(instance.tolist(), frame.tolist(), eps.tolist())}
    out: list[float | None] = []
    for h in range(1, max_lag + 1):
        a, b = [], []
        for (i, f), e in key.items():
            o = key.get((i, f + h))
            if o is not None:
                a.append(e)
                b.append(o)
        out.append(float(np.corrcoef(a, b)[0, 1]) if len(a) > 2 else None)
    return out


def axis_summary(r: F64, var: F64) -> dict[str, float | int]:
    """Bias, scatter, variance ratio and coverage of one axis (see the module docstring)."""
    eps2 = r * r / np.maximum(var, 1e-12)
    le = np.log(np.maximum(eps2, 1e-300))
    mean_le, var_le = float(np.mean(le)), float(np.var(le))
    return {
        "n": int(len(r)),
        "variance_ratio": float(np.mean(eps2)),
        "variance_ratio_median": float(np.median(eps2) / 0.45493642311957283),  # median of χ²₁
        "coverage_1sigma": float(np.mean(eps2 <= 1.0)),
        "coverage_2sigma": float(np.mean(eps2 <= 4.0)),
        "bias_sigma_factor": math.exp((LOG_CHI2_1_MEAN - mean_le) / 2.0),
        "scatter_log_sigma": math.sqrt(max(0.0, var_le - LOG_CHI2_1_VAR) / 4.0),
    }


def summarize(m: MatchedErrors, max_lag: int = 3) -> dict[str, object]:
    """Per line-of-sight axis: :func:`axis_summary` over all matches and the lag correlations of static objects."""
    r_u, r_v, v_u, v_v = line_of_sight(m.gx, m.gy, m.rx, m.ry, m.cxx, m.cxy, m.cyy)
    out: dict[str, object] = {"num_matched": int(len(m.rx)), "num_static": int(m.static.sum())}
    for name, r, v in (("along", r_u, v_u), ("across", r_v, v_v)):
        s = axis_summary(r, v) if len(r) else {}
        st = m.static
        eps = r[st] / np.sqrt(np.maximum(v[st], 1e-12))
        s["lag_correlation_static"] = lag_correlations(eps, m.instance[st], m.frame[st], max_lag)
        out[name] = s
    return out
