"""A small seeded generator of detection-level sequences for the tracker's tests and metrics.

Not the project's simulator (that lives in ``jitterguard/sim``): just enough of a world to exercise a tracker
with realistic detection noise. A moving, turning ego carries a sensor; objects drive straight and through
turns, park, walk, cross each other's paths and walk side by side. Each scan yields detections in the SENSOR
frame with noise that grows with range (more across the beam than along it), a reported covariance that
matches the noise up to a mis-calibration factor, 5-10 % random misses, occlusion gaps, a few false
positives, occasional 180-degree heading flips and class flicker. Every draw comes from one seeded generator.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..geometry import world_to_sensor_xy
from ..services.tracker.arrays import DetectionFrame

CAR, TRUCK, PED, BICYCLE = 1, 2, 7, 6
DIMS = {CAR: (4.5, 1.9, 1.6), TRUCK: (8.0, 2.5, 3.0), PED: (0.6, 0.6, 1.7), BICYCLE: (1.8, 0.6, 1.6)}


@dataclass
class Obj:
    """A ground-truth object: its trajectory is sampled at every frame by :meth:`state`."""

    gid: int
    label: int
    x0: float
    y0: float
    yaw0: float
    speed: float = 0.0
    # (t_start, t_end, yaw_rate): the object turns at yaw_rate between t_start and t_end
    turns: list[tuple[float, float, float]] = field(default_factory=list)
    t_on: float = 0.0  # exists from
    t_off: float = 1e9  # until
    t_move: float = 0.0  # starts moving at this time (a parked car pulling out)
    occlusions: list[tuple[float, float]] = field(default_factory=list)

    def state(self, t: float, dt: float) -> tuple[float, float, float]:
        """(x, y, yaw) at time ``t``, integrated in ``dt`` steps from t=0 (deterministic)."""
        return self._cache(dt)[int(round(t / dt))]

    def _cache(self, dt: float) -> list[tuple[float, float, float]]:
        if getattr(self, "_traj", None) is None:
            traj = []
            x, y, yaw = self.x0, self.y0, self.yaw0
            for k in range(4000):
                t = k * dt
                traj.append((x, y, yaw))
                v = self.speed if t >= self.t_move else 0.0
                w = sum(r for (a, b, r) in self.turns if a <= t < b) if v > 0 else 0.0
                th = yaw + 0.5 * w * dt
                x += v * math.cos(th) * dt
                y += v * math.sin(th) * dt
                yaw += w * dt
            self._traj = traj
        return self._traj

    def occluded(self, t: float) -> bool:
        return any(a <= t < b for a, b in self.occlusions)


@dataclass
class SimFrame:
    """One scan: the detections (core arrays and wire message) and the ground truth in the world frame."""

    t: float
    seq: int
    stamp_ns: int
    ego: tuple[float, float, float]
    detections: DetectionFrame
    det_gid: np.ndarray  # ground-truth id per detection, -1 for a false positive
    gt_ids: np.ndarray
    gt_xy: np.ndarray  # (K, 2) world
    gt_moving: np.ndarray  # (K,) bool


@dataclass
class Sequence:
    frames: list[SimFrame]
    objects: list[Obj]
    dt: float


def default_world(rng: np.random.Generator, duration: float) -> list[Obj]:
    """The standard scene: moving cars (straight + turns), a truck, parked cars, crossings, pedestrians."""
    objs: list[Obj] = []
    gid = 0

    def add(**kw: object) -> Obj:
        nonlocal gid
        o = Obj(gid=gid, **kw)  # type: ignore[arg-type]
        objs.append(o)
        gid += 1
        return o

    # Layout (world frame, the ego starts at the origin driving +x): a road with an eastbound lane at
    # y=-1.8 and a westbound one at y=+1.8, parking rows at y=+-5.5, sidewalks beyond them, a plaza at
    # y=12..20 and two more roads at y=-20 and y=-26. Nothing drives through anything else.
    for i in range(6):  # parked cars, parallel and diagonal
        side = 1 if i % 2 == 0 else -1
        add(label=CAR, x0=8.0 + 8.0 * i + rng.uniform(-0.5, 0.5), y0=side * (5.5 + rng.uniform(-0.2, 0.2)),
            yaw0=0.0 if i % 3 else side * 0.5)
    # lane traffic: a car following another 12 m behind, two oncoming ones; occlusion gaps on two of them
    add(label=CAR, x0=-10.0, y0=-1.8, yaw0=0.0, speed=8.0, occlusions=[(6.0, 6.6)])
    add(label=CAR, x0=-22.0, y0=-1.8, yaw0=0.0, speed=8.0)
    add(label=CAR, x0=70.0, y0=1.8, yaw0=math.pi, speed=7.0, occlusions=[(2.0, 2.5)])
    add(label=CAR, x0=84.0, y0=1.8, yaw0=math.pi, speed=7.5)
    # a car that drives through a left and a right curve on the road at y=-20, a truck on the one at y=-26
    add(label=CAR, x0=0.0, y0=-20.0, yaw0=0.0, speed=rng.uniform(7.0, 9.0),
        turns=[(3.0, 5.0, 0.25), (5.0, 9.0, -0.25), (9.0, 11.0, 0.25)])
    add(label=TRUCK, x0=90.0, y0=-26.0, yaw0=math.pi, speed=5.0)
    add(label=BICYCLE, x0=0.0, y0=-14.0, yaw0=0.0, speed=4.5, turns=[(5.0, 6.0, 0.3), (6.0, 7.0, -0.3)])
    # a parked car that pulls out into the westbound lane halfway through
    add(label=CAR, x0=58.0, y0=5.3, yaw0=math.pi, speed=4.0, t_move=duration / 2,
        turns=[(duration / 2, duration / 2 + 2.0, 0.45), (duration / 2 + 2.0, duration / 2 + 4.0, -0.45)])
    # pedestrians: two walking side by side 0.9 m apart (merged in a coarse detector's eyes), two whose
    # paths cross on the plaza a second apart, two standing
    add(label=PED, x0=10.0, y0=8.0, yaw0=0.0, speed=1.3)
    add(label=PED, x0=10.0, y0=8.9, yaw0=0.0, speed=1.3)
    add(label=PED, x0=20.0, y0=12.0, yaw0=math.pi / 4, speed=1.3, occlusions=[(4.0, 4.5)])
    add(label=PED, x0=21.3, y0=20.0, yaw0=-math.pi / 4, speed=1.3)
    add(label=PED, x0=40.0, y0=8.5, yaw0=1.0, speed=0.0)
    add(label=PED, x0=15.0, y0=-7.5, yaw0=0.0, speed=0.0)
    # an object that appears late and one that leaves early (births and deaths inside the sequence)
    add(label=CAR, x0=62.0, y0=-5.5, yaw0=0.0, t_on=duration * 0.3)
    add(label=CAR, x0=5.0, y0=12.0, yaw0=0.0, t_off=duration * 0.6)
    return objs


def make_sequence(
    seed: int,
    n_frames: int = 150,
    dt: float = 0.1,
    objects: list[Obj] | None = None,
    ego_speed: float = 3.0,
    ego_yaw_rate: float = 0.02,
    miss_rate: float = 0.07,
    fp_rate: float = 0.8,
    sensor_range: float = 60.0,
    noise_base: float = 0.05,
    noise_per_m: float = 0.004,
    var_miscalibration: float = 0.3,
    flip_rate: float = 0.02,
    class_flicker: float = 0.03,
    seq0: int = 0,
    t0_ns: int = 1_700_000_000_000_000_000,
) -> Sequence:
    """Generate ``n_frames`` scans; everything random comes from ``seed``."""
    rng = np.random.default_rng(seed)
    duration = n_frames * dt
    objs = objects if objects is not None else default_world(rng, duration)
    frames: list[SimFrame] = []
    ex, ey, eyaw = 0.0, 0.0, 0.0
    for k in range(n_frames):
        t = k * dt
        rows = []
        gt_ids, gt_xy, gt_moving = [], [], []
        for o in objs:
            if not (o.t_on <= t < o.t_off):
                continue
            x, y, yaw = o.state(t, dt)
            rng_m = math.hypot(x - ex, y - ey)
            if rng_m > sensor_range:
                continue
            gt_ids.append(o.gid)
            gt_xy.append((x, y))
            gt_moving.append(o.speed > 0 and t >= o.t_move)
            if o.occluded(t) or rng.random() < miss_rate:
                continue
            rows.append(_detect(rng, o, x, y, yaw, ex, ey, eyaw, noise_base, noise_per_m, var_miscalibration,
                                flip_rate, class_flicker))
        n_fp = rng.poisson(fp_rate)
        for _ in range(n_fp):
            r = rng.uniform(5.0, sensor_range)
            b = rng.uniform(-math.pi, math.pi)
            lbl = CAR if rng.random() < 0.5 else PED
            L, W, H = DIMS[lbl]
            sx, sy = r * math.cos(b), r * math.sin(b)
            sig = noise_base + noise_per_m * r
            rows.append(dict(gid=-1, x=sx, y=sy, z=0.8, yaw=rng.uniform(-math.pi, math.pi), label=lbl, L=L, W=W,
                             H=H, cxx=sig * sig, cxy=0.0, cyy=sig * sig, vyaw=0.04, prob=0.4))
        order = rng.permutation(len(rows))
        rows = [rows[i] for i in order]

        def col(name: str, rows: list[dict] = rows) -> np.ndarray:
            return np.array([r[name] for r in rows], dtype=np.float64)

        det = DetectionFrame(
            seq=seq0 + k,
            stamp_ns=t0_ns + int(round(t * 1e9)),
            ego_x=ex, ego_y=ey, ego_yaw=eyaw,
            x=col("x"), y=col("y"), z=col("z"), yaw=col("yaw"),
            label=np.array([r["label"] for r in rows], dtype=np.int8),
            length=col("L"), width=col("W"), height=col("H"),
            cov_xx=col("cxx"), cov_xy=col("cxy"), cov_yy=col("cyy"), var_yaw=col("vyaw"),
            has_cov=np.ones(len(rows), dtype=bool), label_prob=col("prob"),
        )
        frames.append(SimFrame(
            t=t, seq=seq0 + k, stamp_ns=det.stamp_ns, ego=(ex, ey, eyaw), detections=det,
            det_gid=np.array([r["gid"] for r in rows], dtype=np.int64),
            gt_ids=np.array(gt_ids, dtype=np.int64), gt_xy=np.array(gt_xy).reshape(-1, 2),
            gt_moving=np.array(gt_moving, dtype=bool),
        ))
        # the ego drives on, turning gently
        th = eyaw + 0.5 * ego_yaw_rate * dt
        ex += ego_speed * math.cos(th) * dt
        ey += ego_speed * math.sin(th) * dt
        eyaw += ego_yaw_rate * dt
    return Sequence(frames=frames, objects=objs, dt=dt)


def _detect(rng: np.random.Generator, o: Obj, x: float, y: float, yaw: float, ex: float, ey: float, eyaw: float,
            noise_base: float, noise_per_m: float, miscal: float, flip_rate: float, flicker: float) -> dict:
    """One noisy detection of ``o`` in the sensor frame, with the covariance a detector would report."""
    sx, sy = world_to_sensor_xy(x, y, ex, ey, eyaw)
    sx, sy = float(sx), float(sy)
    r = math.hypot(sx, sy)
    bearing = math.atan2(sy, sx)
    sig_r = noise_base + noise_per_m * r  # along the beam
    sig_t = noise_base + 1.5 * noise_per_m * r  # across the beam
    nr, nt = rng.normal(0.0, sig_r), rng.normal(0.0, sig_t)
    cb, sb = math.cos(bearing), math.sin(bearing)
    dx, dy = cb * nr - sb * nt, sb * nr + cb * nt
    # the reported covariance: the true one, mis-scaled by a log-normal factor (detectors are not calibrated)
    f = math.exp(rng.normal(0.0, miscal))
    vr, vt = f * sig_r * sig_r, f * sig_t * sig_t
    cxx = cb * cb * vr + sb * sb * vt
    cyy = sb * sb * vr + cb * cb * vt
    cxy = cb * sb * (vr - vt)
    syaw = 0.05 if o.label in (CAR, TRUCK) else 0.3
    dyaw = rng.normal(0.0, syaw) + (math.pi if rng.random() < flip_rate else 0.0)
    label = o.label
    if label == CAR and rng.random() < flicker:
        label = TRUCK
    L, W, H = DIMS[o.label]
    dims_noise = rng.normal(0.0, 0.05, 3)
    return dict(gid=o.gid, x=sx + dx, y=sy + dy, z=H / 2, yaw=yaw - eyaw + dyaw, label=label,
                L=max(0.3, L * (1 + dims_noise[0])), W=max(0.3, W * (1 + dims_noise[1])), H=H * (1 + dims_noise[2]),
                cxx=cxx, cxy=cxy, cyy=cyy, vyaw=syaw * syaw, prob=float(rng.uniform(0.6, 0.95)))
