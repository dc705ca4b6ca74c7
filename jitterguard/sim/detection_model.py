"""Detection-level model: ground truth straight to ``DetectedObjects``, with the errors a real detector makes.

Why: the tracker and the motion classifier can be tested and studied without a trained network, with noise
that is *known*. The model draws, per detection, a position error in the sensor frame

    e = e_white + e_corr + R(yaw_obj) o

* ``e_white`` ~ N(0, R(φ) diag(σ_long², σ_lat²) R(φ)ᵀ), φ the beam azimuth to the object; σ grows linearly with
  range and is multiplied by ``1 + occlusion_factor · (1 − visibility)``. Independent across frames.
* ``e_corr``: a stationary error of each object along and across the beam, an AR(1) in time with correlation
  time ``correlated_tau_s`` whose share of the per-frame variance is ``correlated_fraction`` (σ_c² =
  m/(1 − m)·σ_white²). Real detectors err alike on consecutive scans of one object (the shipped detector on
  nuScenes scene-0523: lag correlation 0.33, 0.21, 0.12 at 0.5, 1.0, 1.5 s; docs/calibration.md).
* ``o`` is a per-object box offset along the object's own length/width axes that jumps when the object's
  visibility changes (the box "slides" as the visible part changes; paper Fig. 4) and decays back with time
  constant ``jitter_tau_s``: o_t = ρ o_{t−1} + w_t, ρ = exp(−Δt/τ), w_t ~ N(0, diag(q_l, q_w)),
  q_l = (jitter_m · |Δvisibility|)², q_w = (jitter_lateral_ratio)² q_l. Temporally correlated by design.

**Reported vs. drawn.** A real detector's variance is a prediction, not the truth. The reported covariance
(``covariance[X_X, X_Y, Y_X, Y_Y]``, sensor frame) starts from the marginal covariance of ``e_white + e_corr``
(plus, only with ``report_jitter_variance``, the jitter's: Σ_white + R P Rᵀ with P_t = ρ² P_{t−1} + Q_t), is
rotated into the beam frame, its along-beam variance multiplied by ``variance_scale_longitudinal``·exp(2η_l)
and its across-beam variance by ``variance_scale_lateral``·exp(2η_t) (covariance by the geometric mean),
η ~ N(0, ``variance_scatter``²) drawn per detection and axis, and rotated back. So the reporter has a
per-axis bias, a scatter, and never sees the box jitter: the honest presets (:meth:`NoiseConfig.jittery`,
``clean``, ``paper_like``, and the dataclass defaults) take the bias and scatter the shipped detector shows
on real scans (σ about 2× too small: ±1σ coverage 0.39 along, 0.43 across the beam on nuScenes
scene-0523). :meth:`NoiseConfig.oracle` is the only preset that reports exactly what it draws:
(e ᵀ Σ⁻¹ e) ~ χ²(2), and for a parked object at constant visibility a two-frame z-test
|x₁ − x₂| / sqrt(σ₁² + σ₂²) exceeds 1.96 about 5 % of the time. Never put a headline figure behind it.

Misses, false positives (uniform over a disc, ``gt_index`` −1) and a heading flip are outside the Gaussian
model and do not enter the reported variance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..geometry import quaternion_from_yaw, scale_beam_covariance
from ..schemas.models import (
    X_X, X_Y, Y_X, Y_Y, YAW_YAW, Z_Z,
    DetectedObject, DetectedObjectKinematics, DetectedObjects, Header, Label, ObjectClassification, Point, Pose,
    PoseWithCovariance, Quaternion, Shape, Twist, TwistWithCovariance, Vector3,
)
from .catalog import CLASSES
from .world import SENSOR_HEIGHT_M, GroundTruthFrame

F64 = NDArray[np.float64]

FRAME_ID = "lidar"

# The shipped detector's positional error on nuScenes scene-0523 (real scans), measured per line-of-sight axis
# with scripts/measure_detector_noise.py (docs/calibration.md, "The honest noise model"):
REAL_SCAN_BIAS_ALONG = 0.50
"""Reported σ / true σ along the beam (bias factor in the log domain; ±1σ coverage 0.39)."""
REAL_SCAN_BIAS_ACROSS = 0.58
"""Reported σ / true σ across the beam (±1σ coverage 0.43)."""
REAL_SCAN_SCATTER = 0.3
"""Scatter of log σ about its bias: 0.0–0.22 on the real scene (447 matches), 0.39–0.42 on synthetic scans."""
REAL_SCAN_CORRELATED_FRACTION = 0.4
"""Share of serially correlated error: lag correlation of the normalised error of static objects 0.33 at 0.5 s."""
REAL_SCAN_TAU_S = 1.0
"""Correlation time: the lag correlation falls 0.33 → 0.21 → 0.12 over 0.5 → 1.5 s."""


@dataclass
class NoiseConfig:
    """Every knob of the detection-level model. Distances in metres, angles in radians, times in seconds."""

    sigma_long_0: float = 0.05
    """Along-beam (longitudinal) position std at 0 m range."""
    sigma_lat_0: float = 0.04
    """Across-beam (lateral) position std at 0 m range."""
    sigma_long_per_m: float = 0.002
    """Growth of the along-beam std per metre of range."""
    sigma_lat_per_m: float = 0.003
    """Growth of the across-beam std per metre of range (lateral grows faster: angular resolution)."""
    occlusion_factor: float = 1.5
    """Stds are multiplied by 1 + occlusion_factor · (1 − visibility)."""
    sigma_z: float = 0.05
    sigma_yaw_0: float = 0.02
    sigma_yaw_per_m: float = 0.0005
    size_sigma_rel: float = 0.03
    """Relative std of each box dimension."""
    velocity_sigma: float = 0.25
    """Std of each velocity component (m/s), reported in the twist covariance."""
    jitter_m: float = 0.0
    """Box shift std (along the object's length) per unit change of visibility between frames."""
    jitter_lateral_ratio: float = 0.3
    jitter_tau_s: float = 1.5
    report_jitter_variance: bool = False
    """Whether the reported covariance includes the jitter offset's variance (a detector aware of it: only
    the ``oracle`` preset)."""
    correlated_fraction: float = 0.0
    """Share m of the per-frame (white + correlated) error variance that is serially correlated, in [0, 1)."""
    correlated_tau_s: float = 1.0
    """Correlation time of the serially correlated error."""
    p_miss: float = 0.0
    p_miss_per_m: float = 0.0
    p_miss_occluded: float = 0.0
    """Extra miss probability at visibility 0 (linear in 1 − visibility)."""
    min_visibility: float = 0.02
    """Objects less visible than this are never detected."""
    max_range_m: float = 100.0
    min_points: int = 1
    """With ``use_point_counts``: objects with fewer LiDAR points inside are never detected."""
    use_point_counts: bool = True
    """Apply ``min_points`` where the frame counts the returns (``GroundTruthFrame.points_counted``: a cast scan,
    nuScenes annotations): a LiDAR detector cannot see an object that returned nothing — nuScenes' own evaluation
    drops such boxes — while annotators interpolate boxes through the frames the object is hidden in."""
    false_positives_per_frame: float = 0.0
    """Mean of a Poisson number of false positives per frame."""
    fp_range_m: float = 50.0
    p_heading_flip: float = 0.0
    """Probability that a detection's heading is off by π (vehicles' front/back confusion)."""
    variance_scale_longitudinal: float = REAL_SCAN_BIAS_ALONG ** 2
    """Reported along-beam variance = drawn variance × this (1.0: calibrated; default: the shipped detector
    on real scans)."""
    variance_scale_lateral: float = REAL_SCAN_BIAS_ACROSS ** 2
    """Reported across-beam variance = drawn variance × this (1.0: calibrated)."""
    variance_scatter: float = REAL_SCAN_SCATTER
    """Std of the log of the reported σ about its biased value, per detection and axis (0: none)."""

    def without_returns(self, frame: GroundTruthFrame) -> NDArray[np.bool_]:
        """Boxes of ``frame`` this model never detects for want of LiDAR returns: fewer than ``min_points`` where
        the frame counts them (``use_point_counts``); none where it does not."""
        if not (self.use_point_counts and frame.points_counted):
            return np.zeros(frame.num_objects, dtype=bool)
        return frame.num_points < self.min_points

    @staticmethod
    def clean() -> "NoiseConfig":
        """Small noise, no misses, no false positives, no jitter: for tests of downstream logic. Reported like
        a real detector (biased and scattered σ)."""
        return NoiseConfig(sigma_long_0=0.03, sigma_lat_0=0.03, sigma_long_per_m=0.001, sigma_lat_per_m=0.001,
                           occlusion_factor=0.5, sigma_yaw_0=0.01, velocity_sigma=0.1, min_visibility=0.0)

    @staticmethod
    def jittery() -> "NoiseConfig":
        """A realistic detector: range/occlusion-dependent noise, a serially correlated error, box jitter on
        occlusion changes it does not report, misses and false positives; σ reported as the shipped
        detector reports it on real scans."""
        return NoiseConfig(sigma_long_0=0.08, sigma_lat_0=0.06, sigma_long_per_m=0.004, sigma_lat_per_m=0.005,
                           occlusion_factor=3.0, jitter_m=0.8, jitter_lateral_ratio=0.3, jitter_tau_s=1.5,
                           p_miss=0.03, p_miss_per_m=0.001, p_miss_occluded=0.35, min_visibility=0.05,
                           false_positives_per_frame=1.0, p_heading_flip=0.01,
                           correlated_fraction=REAL_SCAN_CORRELATED_FRACTION, correlated_tau_s=REAL_SCAN_TAU_S)

    @staticmethod
    def paper_like() -> "NoiseConfig":
        """``jittery`` with, on top, the miscalibration pattern the paper observed: lateral variance under-,
        longitudinal over-estimated (×2 and ×½)."""
        j = NoiseConfig.jittery()
        return replace(j, variance_scale_longitudinal=2.0 * j.variance_scale_longitudinal,
                       variance_scale_lateral=0.5 * j.variance_scale_lateral)

    @staticmethod
    def oracle() -> "NoiseConfig":
        """The ``jittery`` world with a reporter that knows its exact error covariance, box jitter included (no
        real detector does: for tests and ablations, never a headline figure)."""
        return replace(NoiseConfig.jittery(), report_jitter_variance=True, variance_scale_longitudinal=1.0,
                       variance_scale_lateral=1.0, variance_scatter=0.0, correlated_fraction=0.0)


@dataclass
class DetectionFrame:
    """One frame's detections and, per detection, the row of its ground-truth object (−1: false positive)."""

    detections: DetectedObjects
    gt_index: NDArray[np.int64]
    errors_xy: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    """Drawn sensor-frame position error per detection (NaN for false positives), for calibration studies."""


@dataclass
class _JitterState:
    offset: F64  # (2,) along length, along width (object frame)
    var: F64  # (2,) marginal variance of offset
    visibility: float
    stamp_ns: int
    corr: F64  # (2,) unit-variance AR(1) state of the serially correlated error, along / across the beam


def beam_covariance(x: ArrayLike, y: ArrayLike, var_long: ArrayLike, var_lat: ArrayLike) -> tuple[F64, F64, F64]:
    """Sensor-frame (cxx, cxy, cyy) of variances given along the beam to (x, y) and across it."""
    var_long = np.asarray(var_long, dtype=np.float64)
    var_lat = np.asarray(var_lat, dtype=np.float64)
    phi = np.arctan2(y, x)
    c, s = np.cos(phi), np.sin(phi)
    return c * c * var_long + s * s * var_lat, c * s * (var_long - var_lat), s * s * var_long + c * c * var_lat


class DetectionModel:
    """Turns :class:`GroundTruthFrame` s into detections. Stateful (per-object jitter offsets): feed the frames of
    one scenario in order. Deterministic given ``seed`` and the sequence of frames."""

    def __init__(self, config: NoiseConfig, seed: int) -> None:
        self.config = config
        self._rng = np.random.default_rng(seed)
        self._jitter: dict[int, _JitterState] = {}

    def detect(self, frame: GroundTruthFrame) -> DetectionFrame:
        cfg = self.config
        rng = self._rng
        n = frame.num_objects
        c, s = math.cos(frame.ego_yaw), math.sin(frame.ego_yaw)
        dx = frame.centers[:, 0] - frame.ego_x
        dy = frame.centers[:, 1] - frame.ego_y
        sx, sy = c * dx + s * dy, -s * dx + c * dy
        rng_m = np.hypot(sx, sy)
        vis = np.clip(frame.visibility, 0.0, 1.0)
        yaw_rel = frame.yaws - frame.ego_yaw

        # --- jitter state: advance every listed object, detected or not
        jit_off = np.zeros((n, 2))
        jit_var = np.zeros((n, 2))
        corr = np.zeros((n, 2))
        for i in range(n):
            iid = int(frame.instance_ids[i])
            st = self._jitter.get(iid)
            if st is None:
                first = rng.standard_normal(2) if cfg.correlated_fraction > 0 else np.zeros(2)
                st = _JitterState(np.zeros(2), np.zeros(2), float(vis[i]), frame.stamp_ns, first)
            dt = max(frame.stamp_ns - st.stamp_ns, 0) * 1e-9
            rho = math.exp(-dt / cfg.jitter_tau_s) if cfg.jitter_tau_s > 0 else 0.0
            q_l = (cfg.jitter_m * abs(float(vis[i]) - st.visibility)) ** 2
            q = np.array([q_l, q_l * cfg.jitter_lateral_ratio**2])
            offset = rho * st.offset + (np.sqrt(q) * rng.standard_normal(2) if q_l > 0 else 0.0)
            var = rho * rho * st.var + q
            cstate = st.corr
            if cfg.correlated_fraction > 0 and dt > 0:
                rc = math.exp(-dt / cfg.correlated_tau_s) if cfg.correlated_tau_s > 0 else 0.0
                cstate = rc * cstate + math.sqrt(1.0 - rc * rc) * rng.standard_normal(2)
            self._jitter[iid] = _JitterState(offset, var, float(vis[i]), frame.stamp_ns, cstate)
            jit_off[i], jit_var[i], corr[i] = offset, var, cstate

        # --- misses
        p_miss = cfg.p_miss + cfg.p_miss_per_m * rng_m + cfg.p_miss_occluded * (1.0 - vis)
        u = rng.random(n)
        detected = ((u >= p_miss) & (vis >= cfg.min_visibility) & (rng_m <= cfg.max_range_m)
                    & ~cfg.without_returns(frame))
        idx = np.flatnonzero(detected)

        # --- white noise along / across the beam
        occ = 1.0 + cfg.occlusion_factor * (1.0 - vis[idx])
        sl = (cfg.sigma_long_0 + cfg.sigma_long_per_m * rng_m[idx]) * occ
        st_ = (cfg.sigma_lat_0 + cfg.sigma_lat_per_m * rng_m[idx]) * occ
        phi = np.arctan2(sy[idx], sx[idx])
        nl, nt = rng.standard_normal(len(idx)) * sl, rng.standard_normal(len(idx)) * st_
        m = min(max(cfg.correlated_fraction, 0.0), 0.99)
        if m > 0:  # the serially correlated part, σ_c² = m/(1 − m) σ_white² on each beam axis
            gain = math.sqrt(m / (1.0 - m))
            nl = nl + gain * sl * corr[idx, 0]
            nt = nt + gain * st_ * corr[idx, 1]
            sl, st_ = sl / math.sqrt(1.0 - m), st_ / math.sqrt(1.0 - m)  # per-frame σ of white + correlated
        ex = np.cos(phi) * nl - np.sin(phi) * nt
        ey = np.sin(phi) * nl + np.cos(phi) * nt
        cxx, cxy, cyy = beam_covariance(sx[idx], sy[idx], sl**2, st_**2)
        # jitter offset in the object frame -> sensor frame
        cy_, sy_ = np.cos(yaw_rel[idx]), np.sin(yaw_rel[idx])
        o = jit_off[idx]
        ex = ex + cy_ * o[:, 0] - sy_ * o[:, 1]
        ey = ey + sy_ * o[:, 0] + cy_ * o[:, 1]
        if cfg.report_jitter_variance:
            pl, pw = jit_var[idx, 0], jit_var[idx, 1]
            cxx = cxx + cy_ * cy_ * pl + sy_ * sy_ * pw
            cyy = cyy + sy_ * sy_ * pl + cy_ * cy_ * pw
            cxy = cxy + cy_ * sy_ * (pl - pw)
        if cfg.variance_scatter > 0:
            eta = rng.standard_normal((len(idx), 2)) * cfg.variance_scatter
            k_long = cfg.variance_scale_longitudinal * np.exp(2.0 * eta[:, 0])
            k_lat = cfg.variance_scale_lateral * np.exp(2.0 * eta[:, 1])
        else:
            k_long, k_lat = np.full(len(idx), cfg.variance_scale_longitudinal), np.full(len(idx), cfg.variance_scale_lateral)
        rxx, rxy, ryy = scale_beam_covariance(sx[idx], sy[idx], cxx, cxy, cyy, k_long, k_lat)
        sig_yaw = (cfg.sigma_yaw_0 + cfg.sigma_yaw_per_m * rng_m[idx]) * occ
        yaw_det = yaw_rel[idx] + rng.standard_normal(len(idx)) * sig_yaw
        flip = rng.random(len(idx)) < cfg.p_heading_flip
        yaw_det = np.where(flip, yaw_det + math.pi, yaw_det)
        z_det = frame.centers[idx, 2] - SENSOR_HEIGHT_M + rng.standard_normal(len(idx)) * cfg.sigma_z
        sizes = frame.sizes[idx] * np.clip(1.0 + cfg.size_sigma_rel * rng.standard_normal((len(idx), 3)), 0.5, 1.5)
        v = frame.velocities[idx]
        vx = c * v[:, 0] + s * v[:, 1] + rng.standard_normal(len(idx)) * cfg.velocity_sigma
        vy = -s * v[:, 0] + c * v[:, 1] + rng.standard_normal(len(idx)) * cfg.velocity_sigma
        score = np.clip(0.5 + 0.45 * vis[idx] - 0.003 * rng_m[idx] + 0.05 * rng.standard_normal(len(idx)),
                        0.05, 1.0)

        objects: list[DetectedObject] = []
        for j, i in enumerate(idx.tolist()):
            objects.append(_make_object(
                int(frame.labels[i]), float(score[j]), sx[i] + ex[j], sy[i] + ey[j], float(z_det[j]),
                float(yaw_det[j]), sizes[j], float(rxx[j]), float(rxy[j]), float(ryy[j]), float(sig_yaw[j] ** 2),
                cfg.sigma_z**2, float(vx[j]), float(vy[j]), cfg.velocity_sigma**2))
        gt_index = list(idx.tolist())
        errors = [(float(a), float(b)) for a, b in zip(ex, ey)]

        # --- false positives
        for _ in range(int(rng.poisson(cfg.false_positives_per_frame))) if cfg.false_positives_per_frame > 0 else ():
            r = cfg.fp_range_m * math.sqrt(rng.uniform((4.0 / cfg.fp_range_m) ** 2, 1.0))
            a = rng.uniform(-math.pi, math.pi)
            key = str(rng.choice(["car", "pedestrian", "bicycle", "car"]))
            label = int(CLASSES[key].label) if rng.random() > 0.2 else int(Label.UNKNOWN)
            size = CLASSES[key].sample_size(rng)
            fx, fy = r * math.cos(a), r * math.sin(a)
            vl = (cfg.sigma_long_0 + cfg.sigma_long_per_m * r) ** 2 * 4
            vt = (cfg.sigma_lat_0 + cfg.sigma_lat_per_m * r) ** 2 * 4
            bxx, bxy, byy = beam_covariance(fx, fy, vl, vt)
            objects.append(_make_object(
                label, float(rng.uniform(0.1, 0.45)), fx, fy, size[2] / 2 - SENSOR_HEIGHT_M,
                float(rng.uniform(-math.pi, math.pi)), size, float(bxx), float(bxy), float(byy), 0.3, 0.04,
                0.0, 0.0, cfg.velocity_sigma**2))
            gt_index.append(-1)
            errors.append((math.nan, math.nan))

        order = rng.permutation(len(objects))
        qx, qy, qz, qw = quaternion_from_yaw(frame.ego_yaw)
        msg = DetectedObjects(
            header=Header(stamp=frame.stamp_ns, frame_id=FRAME_ID, seq=frame.seq),
            ego_pose=Pose(position=Point(x=frame.ego_x, y=frame.ego_y, z=SENSOR_HEIGHT_M),
                          orientation=Quaternion(x=qx, y=qy, z=qz, w=qw)),
            objects=[objects[k] for k in order],
        )
        return DetectionFrame(msg, np.asarray(gt_index, dtype=np.int64)[order].reshape(-1),
                              np.asarray(errors, dtype=np.float64).reshape(-1, 2)[order])


def _make_object(label: int, score: float, x: float, y: float, z: float, yaw: float, size: F64, cxx: float,
                 cxy: float, cyy: float, var_yaw: float, var_z: float, vx: float, vy: float, var_v: float
                 ) -> DetectedObject:
    cov = [0.0] * 36
    cov[X_X], cov[X_Y], cov[Y_X], cov[Y_Y], cov[Z_Z], cov[YAW_YAW] = cxx, cxy, cxy, cyy, var_z, var_yaw
    tcov = [0.0] * 36
    tcov[X_X] = tcov[Y_Y] = var_v
    qx, qy, qz, qw = quaternion_from_yaw(yaw)
    return DetectedObject(
        existence_probability=score,
        classification=[ObjectClassification(label=label, probability=score)],
        kinematics=DetectedObjectKinematics(
            pose_with_covariance=PoseWithCovariance(
                pose=Pose(position=Point(x=x, y=y, z=z), orientation=Quaternion(x=qx, y=qy, z=qz, w=qw)),
                covariance=cov),
            has_position_covariance=True,
            twist_with_covariance=TwistWithCovariance(twist=Twist(linear=Vector3(x=vx, y=vy)), covariance=tcov),
            has_twist=True,
            has_twist_covariance=True,
        ),
        shape=Shape(type=Shape.BOUNDING_BOX, dimensions=Vector3(x=float(size[0]), y=float(size[1]),
                                                                z=float(size[2]))),
    )
