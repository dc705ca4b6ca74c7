"""Detection-level model: ground truth straight to ``DetectedObjects``, with the errors a real detector makes.

Why: the tracker and the motion classifier can be tested and studied without a trained network, with noise
that is *known*. The model draws, per detection, a position error in the sensor frame

    e = e_white + R(yaw_obj) o

* ``e_white`` ~ N(0, R(φ) diag(σ_long², σ_lat²) R(φ)ᵀ), φ the beam azimuth to the object; σ grows linearly with
  range and is multiplied by ``1 + occlusion_factor · (1 − visibility)``. Independent across frames.
* ``o`` is a per-object box offset along the object's own length/width axes that jumps when the object's
  visibility changes (the box "slides" as the visible part changes; paper Fig. 4) and decays back with time
  constant ``jitter_tau_s``: o_t = ρ o_{t−1} + w_t, ρ = exp(−Δt/τ), w_t ~ N(0, diag(q_l, q_w)),
  q_l = (jitter_m · |Δvisibility|)², q_w = (jitter_lateral_ratio)² q_l. Temporally correlated by design.

**Reported vs. drawn.** The covariance written to ``covariance[X_X, X_Y, Y_X, Y_Y]`` (sensor frame) is the exact
marginal covariance of ``e`` given the visibility history: Σ_white + R P Rᵀ with P_t = ρ² P_{t−1} + Q_t (the
jitter part only when ``report_jitter_variance``). With both miscalibration factors at 1.0 the detector is
therefore calibrated: (e ᵀ Σ⁻¹ e) ~ χ²(2), and for a parked object at constant visibility (no jitter) a
two-frame z-test |x₁ − x₂| / sqrt(σ₁² + σ₂²) exceeds 1.96 about 5 % of the time. Miscalibration is applied only
to what is *reported*: the covariance is rotated into the beam frame, its along-beam (longitudinal) variance
scaled by ``variance_scale_longitudinal``, its across-beam (lateral) variance by ``variance_scale_lateral``
(covariance by the geometric mean), and rotated back. The paper's detector under-estimated lateral and
over-estimated longitudinal variance: ``NoiseConfig.paper_like()``.

Misses, false positives (uniform over a disc, ``gt_index`` −1) and a heading flip are outside the Gaussian
model and do not enter the reported variance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..geometry import quaternion_from_yaw
from ..schemas.models import (
    X_X, X_Y, Y_X, Y_Y, YAW_YAW, Z_Z,
    DetectedObject, DetectedObjectKinematics, DetectedObjects, Header, Label, ObjectClassification, Point, Pose,
    PoseWithCovariance, Quaternion, Shape, Twist, TwistWithCovariance, Vector3,
)
from .catalog import CLASSES
from .world import SENSOR_HEIGHT_M, GroundTruthFrame

F64 = NDArray[np.float64]

FRAME_ID = "lidar"


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
    report_jitter_variance: bool = True
    """Whether the reported covariance includes the jitter offset's variance (a detector aware of it)."""
    p_miss: float = 0.0
    p_miss_per_m: float = 0.0
    p_miss_occluded: float = 0.0
    """Extra miss probability at visibility 0 (linear in 1 − visibility)."""
    min_visibility: float = 0.02
    """Objects less visible than this are never detected."""
    max_range_m: float = 100.0
    min_points: int = 1
    """With ``use_point_counts``: objects with fewer LiDAR points inside are never detected."""
    use_point_counts: bool = False
    false_positives_per_frame: float = 0.0
    """Mean of a Poisson number of false positives per frame."""
    fp_range_m: float = 50.0
    p_heading_flip: float = 0.0
    """Probability that a detection's heading is off by π (vehicles' front/back confusion)."""
    variance_scale_longitudinal: float = 1.0
    """Reported along-beam variance = drawn variance × this (1.0: calibrated)."""
    variance_scale_lateral: float = 1.0
    """Reported across-beam variance = drawn variance × this (1.0: calibrated)."""

    @staticmethod
    def clean() -> "NoiseConfig":
        """Small calibrated noise, no misses, no false positives, no jitter: for tests of downstream logic."""
        return NoiseConfig(sigma_long_0=0.03, sigma_lat_0=0.03, sigma_long_per_m=0.001, sigma_lat_per_m=0.001,
                           occlusion_factor=0.5, sigma_yaw_0=0.01, velocity_sigma=0.1, min_visibility=0.0)

    @staticmethod
    def jittery() -> "NoiseConfig":
        """A realistic detector that still reports calibrated variances: range/occlusion-dependent noise,
        box jitter on occlusion changes, misses and false positives."""
        return NoiseConfig(sigma_long_0=0.08, sigma_lat_0=0.06, sigma_long_per_m=0.004, sigma_lat_per_m=0.005,
                           occlusion_factor=3.0, jitter_m=0.8, jitter_lateral_ratio=0.3, jitter_tau_s=1.5,
                           p_miss=0.03, p_miss_per_m=0.001, p_miss_occluded=0.35, min_visibility=0.05,
                           false_positives_per_frame=1.0, p_heading_flip=0.01)

    @staticmethod
    def paper_like() -> "NoiseConfig":
        """``jittery`` with the miscalibration the paper observed: lateral variance under-, longitudinal
        over-estimated."""
        return replace(NoiseConfig.jittery(), variance_scale_longitudinal=2.0, variance_scale_lateral=0.5)


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


def beam_covariance(x: ArrayLike, y: ArrayLike, var_long: ArrayLike, var_lat: ArrayLike) -> tuple[F64, F64, F64]:
    """Sensor-frame (cxx, cxy, cyy) of variances given along the beam to (x, y) and across it."""
    var_long = np.asarray(var_long, dtype=np.float64)
    var_lat = np.asarray(var_lat, dtype=np.float64)
    phi = np.arctan2(y, x)
    c, s = np.cos(phi), np.sin(phi)
    return c * c * var_long + s * s * var_lat, c * s * (var_long - var_lat), s * s * var_long + c * c * var_lat


def miscalibrate(x: F64, y: F64, cxx: F64, cxy: F64, cyy: F64, k_long: float, k_lat: float
                 ) -> tuple[F64, F64, F64]:
    """Scale a sensor-frame covariance's along-beam variance by ``k_long`` and across-beam by ``k_lat``."""
    phi = np.arctan2(y, x)
    c, s = np.cos(phi), np.sin(phi)
    # into the beam frame: Σ_b = Rᵀ Σ R
    bll = c * c * cxx + 2 * c * s * cxy + s * s * cyy
    btt = s * s * cxx - 2 * c * s * cxy + c * c * cyy
    blt = -c * s * cxx + (c * c - s * s) * cxy + c * s * cyy
    bll, btt, blt = bll * k_long, btt * k_lat, blt * math.sqrt(k_long * k_lat)
    return (c * c * bll - 2 * c * s * blt + s * s * btt,
            c * s * (bll - btt) + (c * c - s * s) * blt,
            s * s * bll + 2 * c * s * blt + c * c * btt)


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
        for i in range(n):
            iid = int(frame.instance_ids[i])
            st = self._jitter.get(iid)
            if st is None:
                st = _JitterState(np.zeros(2), np.zeros(2), float(vis[i]), frame.stamp_ns)
            dt = max(frame.stamp_ns - st.stamp_ns, 0) * 1e-9
            rho = math.exp(-dt / cfg.jitter_tau_s) if cfg.jitter_tau_s > 0 else 0.0
            q_l = (cfg.jitter_m * abs(float(vis[i]) - st.visibility)) ** 2
            q = np.array([q_l, q_l * cfg.jitter_lateral_ratio**2])
            offset = rho * st.offset + (np.sqrt(q) * rng.standard_normal(2) if q_l > 0 else 0.0)
            var = rho * rho * st.var + q
            self._jitter[iid] = _JitterState(offset, var, float(vis[i]), frame.stamp_ns)
            jit_off[i], jit_var[i] = offset, var

        # --- misses
        p_miss = cfg.p_miss + cfg.p_miss_per_m * rng_m + cfg.p_miss_occluded * (1.0 - vis)
        u = rng.random(n)
        detected = (u >= p_miss) & (vis >= cfg.min_visibility) & (rng_m <= cfg.max_range_m)
        if cfg.use_point_counts:
            detected &= frame.num_points >= cfg.min_points
        idx = np.flatnonzero(detected)

        # --- white noise along / across the beam
        occ = 1.0 + cfg.occlusion_factor * (1.0 - vis[idx])
        sl = (cfg.sigma_long_0 + cfg.sigma_long_per_m * rng_m[idx]) * occ
        st_ = (cfg.sigma_lat_0 + cfg.sigma_lat_per_m * rng_m[idx]) * occ
        phi = np.arctan2(sy[idx], sx[idx])
        nl, nt = rng.standard_normal(len(idx)) * sl, rng.standard_normal(len(idx)) * st_
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
        rxx, rxy, ryy = miscalibrate(sx[idx], sy[idx], cxx, cxy, cyy, cfg.variance_scale_longitudinal,
                                     cfg.variance_scale_lateral)
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
