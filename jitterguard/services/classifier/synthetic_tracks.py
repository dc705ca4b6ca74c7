"""A built-in track-level scenario: what the tracker would publish for parked, moving and starting cars.

It feeds the classifier with no tracker and no detector in the loop (the main job's classifier-only mode,
integration tests, the service benchmark). Detections are drawn in the *sensor* frame from exactly the
covariance they report — along-beam and across-beam variances differ — and then moved into the world frame
with the ego pose, covariance rotated (R Σ Rᵀ), as the tracker does. Ground truth (``moving``) comes along.
"""

from __future__ import annotations

import math
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np

from ...geometry import quaternion_from_yaw, rotate_cov2, sensor_to_world_xy, world_to_sensor_xy
from ...schemas.wire import (
    DETECTED,
    TRACK_STATE,
    TRACKED,
    TrackedColumns,
    records_of,
    write_track_observations,
    write_tracked_objects,
)
from ...schemas.models import (X_X, X_Y, Y_X, Y_Y, YAW_YAW, DetectedObject, DetectedObjectKinematics, Header,
    Label, ObjectClassification, Point, Pose, PoseWithCovariance, Quaternion, Shape, TrackedObject,
    TrackedObjectKinematics, TrackedObjects, TrackObservation, TrackState, Twist, TwistWithCovariance,
    Vector3)


@dataclass(frozen=True)
class TrackFrame:
    """One frame of tracker output plus the ground truth behind it."""

    seq: int
    stamp_ns: int
    observations: list[TrackObservation]
    tracked: TrackedObjects
    moving: dict[str, bool]


@dataclass(frozen=True)
class TrackScenario:
    """Objects on straight lines; ``start_frame`` > 0 makes a parked object start moving then; ``replaced_frame``
    ≥ 0 makes the detector re-place the first parked object's box ``replaced_m`` along its heading from that frame
    on (an occlusion change: the object stays parked, its detections jump once)."""

    n_static: int = 6
    n_moving: int = 4
    n_starting: int = 1
    rate_hz: float = 10.0
    speed_mps: float = 5.0
    sigma_long: float = 0.15  # along the beam, metres (1-sigma, what the detector reports)
    sigma_lat: float = 0.08  # across the beam
    start_frame: int = 30
    ego_speed_mps: float = 3.0
    ego_yaw_rate: float = 0.05
    seed: int = 0
    replaced_frame: int = -1
    replaced_m: float = 0.8


def _cov36(cxx: float, cxy: float, cyy: float, cyaw: float = 0.01) -> tuple[float, ...]:
    c = [0.0] * 36
    c[X_X], c[X_Y], c[Y_X], c[Y_Y], c[14], c[YAW_YAW] = cxx, cxy, cxy, cyy, 0.01, cyaw
    return tuple(c)


def _classification(label: int) -> list[ObjectClassification]:
    return [ObjectClassification(label=label, probability=0.9)]


def generate(sc: TrackScenario, num_frames: int) -> Iterator[TrackFrame]:
    """Yield ``num_frames`` frames of the scenario; deterministic given ``sc.seed``."""
    rng = np.random.default_rng(sc.seed)
    n = sc.n_static + sc.n_moving + sc.n_starting
    ids = [uuid.UUID(int=int(rng.integers(0, 2**63)) << 64 | i).hex for i in range(n)]
    # Parked cars along both kerbs, movers on the road, starters parked until start_frame.
    x0 = rng.uniform(-40.0, 40.0, n)
    y0 = np.where(np.arange(n) % 2 == 0, 6.0, -6.0) + rng.normal(0, 0.3, n)
    heading = np.where(y0 > 0, 0.0, math.pi)
    speed = np.zeros(n)
    speed[sc.n_static:sc.n_static + sc.n_moving] = sc.speed_mps
    start = np.full(n, -1)
    start[sc.n_static + sc.n_moving:] = sc.start_frame
    labels = np.full(n, int(Label.CAR))
    dt = 1.0 / sc.rate_hz
    pos = np.stack([x0, y0], axis=1)
    ego = np.zeros(3)  # x, y, yaw
    for f in range(num_frames):
        stamp = int(1_700_000_000e9 + f * dt * 1e9)
        moving_now = (speed > 0) | ((start >= 0) & (f >= start))
        v = np.where(moving_now, np.where(speed > 0, speed, sc.speed_mps), 0.0)
        vel = np.stack([v * np.cos(heading), v * np.sin(heading)], axis=1)
        if f:
            pos = pos + vel * dt
            ego[2] += sc.ego_yaw_rate * dt
            ego[0] += sc.ego_speed_mps * dt * math.cos(ego[2])
            ego[1] += sc.ego_speed_mps * dt * math.sin(ego[2])
        # Draw each detection in the sensor frame along/across its beam, with the variance it reports.
        sx, sy = world_to_sensor_xy(pos[:, 0], pos[:, 1], ego[0], ego[1], ego[2])
        bearing = np.arctan2(sy, sx)
        c_s_xx, c_s_xy, c_s_yy = rotate_cov2(sc.sigma_long**2, 0.0, sc.sigma_lat**2, bearing)
        e_long = rng.normal(0.0, sc.sigma_long, n)
        e_lat = rng.normal(0.0, sc.sigma_lat, n)
        dx = e_long * np.cos(bearing) - e_lat * np.sin(bearing)
        dy = e_long * np.sin(bearing) + e_lat * np.cos(bearing)
        wx, wy = sensor_to_world_xy(sx + dx, sy + dy, ego[0], ego[1], ego[2])
        if 0 <= sc.replaced_frame <= f and sc.n_static:  # no draw: the other objects' frames stay as they were
            wx[0] += sc.replaced_m * math.cos(heading[0])
            wy[0] += sc.replaced_m * math.sin(heading[0])
        cxx, cxy, cyy = rotate_cov2(c_s_xx, c_s_xy, c_s_yy, ego[2])  # sensor -> world
        header = Header(stamp=stamp, frame_id="map", seq=f)
        observations, tracked = [], []
        for i in range(n):
            q = Quaternion(**dict(zip("xyzw", quaternion_from_yaw(float(heading[i])))))
            shape = Shape(dimensions=Vector3(x=4.5, y=1.9, z=1.6))
            det = DetectedObject(
                existence_probability=0.9,
                classification=_classification(int(labels[i])),
                kinematics=DetectedObjectKinematics(
                    pose_with_covariance=PoseWithCovariance(
                        pose=Pose(position=Point(x=float(wx[i]), y=float(wy[i]), z=0.8), orientation=q),
                        covariance=_cov36(float(cxx[i]), float(cxy[i]), float(cyy[i])),
                    ),
                    has_position_covariance=True,
                ),
                shape=shape,
            )
            trk = TrackedObject(
                object_id=ids[i],
                existence_probability=0.9,
                classification=_classification(int(labels[i])),
                kinematics=TrackedObjectKinematics(
                    pose_with_covariance=PoseWithCovariance(
                        pose=Pose(position=Point(x=float(wx[i]), y=float(wy[i]), z=0.8), orientation=q),
                        covariance=_cov36(float(cxx[i]), float(cxy[i]), float(cyy[i])),
                    ),
                    twist_with_covariance=TwistWithCovariance(
                        twist=Twist(linear=Vector3(x=float(vel[i, 0]) + float(rng.normal(0, 0.3)),
                                                   y=float(vel[i, 1]) + float(rng.normal(0, 0.3)))),
                        covariance=_cov36(0.25, 0.0, 0.25),
                    ),
                ),
                shape=shape,
            )
            tracked.append(trk)
            tw = trk.kinematics.twist_with_covariance.twist.linear
            state = TrackState(object_id=ids[i], label=int(labels[i]), existence_probability=0.9,
                               x=float(wx[i]), y=float(wy[i]), yaw=float(heading[i]), vx=tw.x, vy=tw.y,
                               hits=f + 1, age_s=f * dt)
            observations.append(TrackObservation(header=header, detection=det, track=state))
        ego_pose = Pose(position=Point(x=float(ego[0]), y=float(ego[1])),
                        orientation=Quaternion(**dict(zip("xyzw", quaternion_from_yaw(float(ego[2]))))))
        yield TrackFrame(
            seq=f,
            stamp_ns=stamp,
            observations=observations,
            tracked=TrackedObjects(header=header, ego_pose=ego_pose, objects=tracked,
                                   observed_track_ids=[o.object_id for o in tracked]),
            moving={ids[i]: bool(moving_now[i]) for i in range(n)},
        )


@dataclass(frozen=True)
class FrameRecords:
    """A :class:`TrackFrame` as the tracker writes it (records), ready to be put under any header."""

    track_ids: list[str]
    detections: np.ndarray
    states: np.ndarray
    tracked: TrackedColumns

    @staticmethod
    def of(frame: TrackFrame) -> FrameRecords:
        t = frame.tracked
        return FrameRecords([o.track.object_id for o in frame.observations],
                            records_of(DETECTED, [o.detection for o in frame.observations]),
                            records_of(TRACK_STATE, [o.track for o in frame.observations]),
                            TrackedColumns(t.header, t.ego_pose, records_of(TRACKED, t.objects), t.observed_track_ids))

    def payloads(self, header: Header | None = None) -> tuple[list[tuple[str, bytes]], bytes]:
        """``(track_id, tracks/{id} payload)`` per observation and the closing ``tracked`` payload."""
        h = header or self.tracked.header
        obs = write_track_observations(h, self.detections, self.states)
        return list(zip(self.track_ids, obs)), write_tracked_objects(replace(self.tracked, header=h))
