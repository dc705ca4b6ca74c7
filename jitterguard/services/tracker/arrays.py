"""The tracker core's inputs and outputs: plain numpy arrays, one row per object (no models, no I/O).

The Zenoh adapter converts wire columns to these and back (``adapter.py``); the offline evaluator and the
benchmark build them directly, so the core is measured and tested without any serialisation in the way.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


@dataclass
class DetectionFrame:
    """One scan's detections in the SENSOR frame, with the sensor's pose in the world (planar: x, y, z, yaw).

    ``cov_*`` are the detector's own position (co)variances in the sensor frame and ``var_yaw`` its heading
    variance; they are meaningful only where ``has_cov`` is true. ``orientation`` is Autoware's
    orientation_availability (0 unavailable, 1 sign unknown, 2 available).
    """

    seq: int
    stamp_ns: int
    ego_x: float
    ego_y: float
    ego_yaw: float
    x: F64
    y: F64
    yaw: F64
    label: NDArray[np.int8]
    ego_z: float = 0.0
    frame_id: str = "lidar"
    z: F64 | None = None
    length: F64 | None = None
    width: F64 | None = None
    height: F64 | None = None
    cov_xx: F64 | None = None
    cov_xy: F64 | None = None
    cov_yy: F64 | None = None
    var_yaw: F64 | None = None
    has_cov: NDArray[np.bool_] | None = None
    label_prob: F64 | None = None
    existence: F64 | None = None
    orientation: NDArray[np.int8] | None = None
    area: F64 | None = None  # footprint area for the area gate; length * width when not given
    vx: F64 | None = None  # the detector's velocity (world motion in the sensor's axes), where ``has_twist``
    vy: F64 | None = None
    has_twist: NDArray[np.bool_] | None = None

    def __post_init__(self) -> None:
        """Fill the optional columns so the core never branches on ``None`` (and check lengths once)."""
        m = int(np.asarray(self.x).shape[0])
        self.x = np.asarray(self.x, dtype=np.float64)
        self.y = np.asarray(self.y, dtype=np.float64)
        self.yaw = np.asarray(self.yaw, dtype=np.float64)
        self.label = np.asarray(self.label, dtype=np.int8)

        def fill(v: object, default: float, dtype: type = np.float64) -> np.ndarray:
            if v is None:
                return np.full(m, default, dtype=dtype)
            return np.asarray(v, dtype=dtype)

        self.z = fill(self.z, 0.0)
        self.length = fill(self.length, 4.5)
        self.width = fill(self.width, 1.9)
        self.height = fill(self.height, 1.6)
        self.cov_xx = fill(self.cov_xx, 0.0)
        self.cov_xy = fill(self.cov_xy, 0.0)
        self.cov_yy = fill(self.cov_yy, 0.0)
        self.var_yaw = fill(self.var_yaw, 0.0)
        self.has_cov = fill(self.has_cov, False, np.bool_)
        self.label_prob = fill(self.label_prob, 1.0)
        self.existence = fill(self.existence, 1.0)
        self.orientation = fill(self.orientation, 2, np.int8)
        self.area = self.length * self.width if self.area is None else np.asarray(self.area, dtype=np.float64)
        self.vx = fill(self.vx, 0.0)
        self.vy = fill(self.vy, 0.0)
        self.has_twist = fill(self.has_twist, False, np.bool_)
        for name in ("y", "yaw", "label", "z", "length", "width", "height", "cov_xx", "cov_xy", "cov_yy",
                     "var_yaw", "has_cov", "label_prob", "existence", "orientation", "area", "vx", "vy", "has_twist"):
            if getattr(self, name).shape != (m,):
                raise ValueError(f"DetectionFrame.{name} has shape {getattr(self, name).shape}, expected ({m},)")

    def __len__(self) -> int:
        return int(self.x.shape[0])

    def own_covariance(self) -> NDArray[np.bool_]:
        """Which detections report a position covariance of their own (``has_cov`` and a positive variance on an
        axis): the filter measures the others with its class's, and hands that on to the classifier."""
        assert self.has_cov is not None and self.cov_xx is not None and self.cov_yy is not None
        return self.has_cov & ((self.cov_xx > 0.0) | (self.cov_yy > 0.0))


@dataclass
class WorldDetections:
    """A frame's detections in the WORLD frame: the detector's covariance rotated (R Σ Rᵀ) and the
    measurement covariance ``R`` (``(M, 3, 3)`` over x, y, yaw) the filter actually used."""

    x: F64
    y: F64
    z: F64
    yaw: F64
    cov_xx: F64
    cov_xy: F64
    cov_yy: F64
    R: F64
    vx: F64  # the detector's velocity in the world frame (0 where the frame has no twist)
    vy: F64


@dataclass
class TrackSnapshot:
    """The confirmed tracks after a frame's update, one row each, in the world frame."""

    ids: list[str]
    label: NDArray[np.int8]
    label_prob: F64
    existence: F64
    x: F64
    y: F64
    z: F64
    yaw: F64
    pose_cov: F64  # (T, 3, 3) over x, y, yaw
    vel: F64  # (T, 2) world-frame vx, vy
    vel_cov: F64  # (T, 2, 2)
    yaw_rate: F64
    yaw_rate_var: F64
    dims: F64  # (T, 3) length, width, height
    orientation: NDArray[np.int8]
    hits: NDArray[np.int64]
    last_update_ns: NDArray[np.int64]
    born_ns: NDArray[np.int64]

    def __len__(self) -> int:
        return len(self.ids)

    @staticmethod
    def empty() -> "TrackSnapshot":
        z = np.zeros(0)
        return TrackSnapshot(ids=[], label=np.zeros(0, np.int8), label_prob=z, existence=z, x=z, y=z, z=z, yaw=z,
                             pose_cov=np.zeros((0, 3, 3)), vel=np.zeros((0, 2)), vel_cov=np.zeros((0, 2, 2)),
                             yaw_rate=z, yaw_rate_var=z, dims=np.zeros((0, 3)), orientation=np.zeros(0, np.int8),
                             hits=np.zeros(0, np.int64), last_update_ns=np.zeros(0, np.int64),
                             born_ns=np.zeros(0, np.int64))


@dataclass
class FrameResult:
    """What one frame did: the world-frame detections, the confirmed tracks, and which detection each
    confirmed track received this frame (``obs_track[k]`` indexes ``tracks``, ``obs_det[k]`` the detections)."""

    seq: int
    stamp_ns: int
    detections: WorldDetections
    tracks: TrackSnapshot
    obs_track: NDArray[np.intp]
    obs_det: NDArray[np.intp]
    born: list[str] = field(default_factory=list)
    deleted: list[str] = field(default_factory=list)
    confirmed: int = 0
    """Tracks that became confirmed this frame (born ones included where one detection confirms them): of
    ``born``'s tentative tracks, most from clutter, these are the ones that reached the output."""
    confirmed_deleted: int = 0
    """Of ``deleted``, the confirmed tracks (the rest were tentative)."""
    reset: bool = False
    """The source went back in time (a recording started over): every earlier track was dropped first."""
    source_restarted: bool = False
    """The source's seq began again while time went on (a restarted driver): tracks carried on."""
    jumped: bool = False
    """The source jumped ahead (a long gap, confirmed by the frames after it): tracks carried on and aged by it."""
    withheld: int = 0
    """Confirmed tracks left out of ``tracks`` because more than ``limits.max_objects`` were confirmed: coasting
    ones, the longest unseen first (downstream readers refuse a longer list; every observed track is kept)."""
    tentative: TrackSnapshot = field(default_factory=TrackSnapshot.empty)
    """The tentative tracks observed this frame (``observe_tentative``): on ``tracks/{id}``, never in ``tracked``."""
    tentative_det: NDArray[np.intp] = field(default_factory=lambda: np.zeros(0, dtype=np.intp))
    """The detection each of ``tentative`` received."""

    @property
    def observed_ids(self) -> list[str]:
        """Every track with a ``tracks/{id}`` this frame: the confirmed ones observed, then the tentative ones."""
        return [self.tracks.ids[i] for i in self.obs_track] + self.tentative.ids
