"""What every replay source yields: scans, detection sets, or a per-frame read error.

Sources are pure readers: they turn a recording into a lazy stream of these values and know nothing about
Zenoh, pacing or sequence numbers. A frame that cannot be read is *yielded* as a :class:`FrameError` rather
than raised, so one corrupt file does not end the iteration and the publisher can choose to skip it (and
count it) or stop — a generator that raises cannot be resumed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Union

import numpy as np
from numpy.typing import NDArray

from ...geometry import (
    quaternion_from_rotation,
    quaternion_from_yaw,
    quaternion_multiply,
    rotation_from_quaternion,
    yaw_from_quaternion,
)
from ...schemas.codec import LimitExceeded
from ...schemas.models import DetectedObject, GroundTruthObjects, Point, Pose, Quaternion
from ...schemas.wire import check_pose

MAX_SCAN_BYTES = 64 << 20
"""The largest ``points`` payload the replay publishes, and the largest raw ``.bin`` it reads: the detector's default
``max_scan_bytes`` (the bridges' and ``ros2-in``'s too), beyond which every consumer refuses a scan unread. Kept equal
to it by a test rather than imported: the detector's configuration is not the replay's to load."""

DEFAULT_PERIOD_NS = 100_000_000
"""10 Hz: the stamp spacing used for recordings that carry no time (KITTI without times.txt, loose PCDs)."""


class SourceError(Exception):
    """A recording that cannot be opened at all (missing path, wrong layout). The message names the path."""


@dataclass(frozen=True)
class EgoPose:
    """The sensor's pose in the world frame: position and a unit quaternion (x, y, z, w)."""

    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    qx: float = 0.0
    qy: float = 0.0
    qz: float = 0.0
    qw: float = 1.0

    @classmethod
    def from_yaw(cls, x: float, y: float, yaw: float, z: float = 0.0) -> "EgoPose":
        qx, qy, qz, qw = quaternion_from_yaw(yaw)
        return cls(x, y, z, qx, qy, qz, qw)

    @classmethod
    def from_matrix(cls, m: NDArray[np.float64]) -> "EgoPose":
        """From a 4x4 (or 3x4) homogeneous transform; the rotation is re-orthonormalised first."""
        m = np.asarray(m, dtype=np.float64)
        qx, qy, qz, qw = quaternion_from_rotation(m[:3, :3])
        return cls(float(m[0, 3]), float(m[1, 3]), float(m[2, 3]), qx, qy, qz, qw)

    @property
    def yaw(self) -> float:
        return yaw_from_quaternion(self.qx, self.qy, self.qz, self.qw)

    def to_schema(self) -> Pose:
        n = math.sqrt(self.qx**2 + self.qy**2 + self.qz**2 + self.qw**2) or 1.0
        return Pose(
            position=Point(x=self.x, y=self.y, z=self.z),
            orientation=Quaternion(x=self.qx / n, y=self.qy / n, z=self.qz / n, w=self.qw / n),
        )

    def matrix(self) -> NDArray[np.float64]:
        """The 4x4 homogeneous transform sensor -> world."""
        m = np.eye(4)
        m[:3, :3] = rotation_from_quaternion(self.qx, self.qy, self.qz, self.qw)
        m[:3, 3] = (self.x, self.y, self.z)
        return m


IDENTITY = EgoPose()


@dataclass(frozen=True)
class ScanFrame:
    """One LiDAR scan in the sensor frame. ``points`` is (P, F) float32 whose columns are ``fields``."""

    stamp_ns: int
    pose: EgoPose
    points: NDArray[np.float32]
    fields: tuple[str, ...]
    origin: str
    """Where it came from (file name, ``bag:topic#index``): named in every message about this frame."""
    frame_id: str = "lidar"
    truth: GroundTruthObjects | None = field(default=None, repr=False, compare=False)
    """The frame's labels when the source has them (its header is filled in when published)."""

    def __post_init__(self) -> None:
        if self.points.ndim != 2 or self.points.shape[1] != len(self.fields):
            raise ValueError(f"{self.origin}: points {self.points.shape} do not match fields {self.fields}")
        if self.fields[:3] != ("x", "y", "z"):
            raise ValueError(f"{self.origin}: the first three fields must be x, y, z, got {self.fields}")


@dataclass(frozen=True)
class DetectionFrame:
    """One frame of detection-level input: objects in the sensor frame (``frame_id``) plus the ego pose."""

    stamp_ns: int
    pose: EgoPose
    objects: list[DetectedObject]
    origin: str
    frame_id: str = "lidar"
    truth: GroundTruthObjects | None = field(default=None, repr=False, compare=False)


NO_POSE_YET = "no pose yet"
"""How a scan recorded before localization's first pose is refused: the replay skips it, and ``up``'s pre-start check
reads past such scans rather than refusing the recording (see ``probe_source``)."""


@dataclass(frozen=True)
class FrameError:
    """A frame that could not be read; ``origin`` names the file (and record), ``reason`` says why."""

    origin: str
    reason: str
    invalid: bool = False
    """The message itself breaks the contract (a cloud without z, a box with an impossible probability): the sender's
    fault, which ``ros2-in`` counts ``invalid``, apart from a scan it could not pose (``unposed``)."""

    def __str__(self) -> str:
        return f"{self.origin}: {self.reason}"


Frame = Union[ScanFrame, DetectionFrame]
Item = Union[ScanFrame, DetectionFrame, FrameError]


def pose_refusal(frame: Frame) -> FrameError | None:
    """``frame`` as an unreadable frame when its ego pose is one that cannot go out or that no reader takes (not
    finite; beyond ``max_abs_coordinate_m`` or no unit quaternion: :func:`~jitterguard.schemas.wire.check_pose`, the
    detector's and the tracker's rule), else None. Such a pose comes from the recording (a NaN odometry or TF
    sample, a PCD's VIEWPOINT): one had ended the whole replay with a multi-line validation error and exit 1, the
    frames after it never published; one beyond the limits went out for every consumer to refuse, uncounted.
    The replay loop and :func:`~.sources.probe_source` (``jitterguard up``'s check) apply this one rule: the probe
    had taken a frame that read but whose pose the replay then refused, and ``up`` started a stack whose replay
    crash-looped on "no frame could be read"."""
    p = frame.pose
    if not all(math.isfinite(v) for v in (p.x, p.y, p.z, p.qx, p.qy, p.qz, p.qw)):
        return FrameError(frame.origin, "ego pose is not finite")
    try:
        check_pose(type(frame).__name__, "ego_pose", p.to_schema())
    except LimitExceeded as exc:
        return FrameError(frame.origin, f"{exc.field}: {exc.reason}")
    return None


def mib(n: int) -> str:
    """A byte count as people read it in a refusal: ``64 MiB``, ``80.5 MiB``."""
    return f"{n / (1 << 20):.4g} MiB"


SHELL_BOUND = 1024
"""More than a ``points`` message holds besides its points and names (keys, header, pose: about 300 bytes)."""


def _msgpack_bin_header(n: int) -> int:
    return 2 if n < 1 << 8 else 3 if n < 1 << 16 else 5


def scan_refusal(frame: Frame, max_bytes: int = MAX_SCAN_BYTES) -> FrameError | None:
    """``frame`` as an unreadable frame when its ``points`` payload would be larger than ``max_bytes``, else None.
    Such a scan (a dense sensor's bag or PCD) had gone out without a word for the detector to refuse every one of them
    unread (``rejected.points``). The size is the payload's own, computed without copying the points: the message
    around no data, plus the points' bytes (the header's seq and stamp as the recording gives them, a few bytes from
    what the replay writes). The replay loop and ``up``'s pre-start check (:func:`~.sources.probe_source`) apply it, as
    they apply :func:`pose_refusal`."""
    if not isinstance(frame, ScanFrame):
        return None
    data = frame.points.shape[0] * frame.points.shape[1] * 4
    names = sum(len(f.encode()) + 5 for f in frame.fields) + len(frame.frame_id.encode())
    if data + names + SHELL_BOUND <= max_bytes:  # the common case, far below: no message built
        return None
    from ...schemas import PointCloud, encode
    from ...schemas.models import Header

    empty = PointCloud.model_construct(header=Header(stamp=frame.stamp_ns, frame_id=frame.frame_id, seq=0),
                                       ego_pose=frame.pose.to_schema(), fields=list(frame.fields),
                                       num_points=int(frame.points.shape[0]), data=b"")
    size = len(encode(empty)) - _msgpack_bin_header(0) + _msgpack_bin_header(data) + data
    if size <= max_bytes:
        return None
    return FrameError(frame.origin, f"scan of {size} bytes ({mib(size)}, {frame.points.shape[0]} points) is over the"
                                    f" {mib(max_bytes)} the detector takes (its max_scan_bytes): not published")


@dataclass
class SourceInfo:
    """What a source tells the publisher up front: its kind, a display name and (if known) its length."""

    name: str
    kind: str  # "points" or "detections"
    num_frames: int | None = None
    notes: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    """What will likely make the result wrong though the source replays (a moving sensor without poses)."""
    period_ns: int | None = None
    """The spacing of its frames when the source sets it (``--hz``: synthetic sources, scans without time): what a
    pass of one frame (one scan, ``--limit 1``) is paced by when looping, as its spacing cannot be measured."""


# ----------------------------------------------------------------------------------------- point helpers


def finite_rows(points: NDArray[np.float32]) -> tuple[NDArray[np.float32], int]:
    """Drop rows whose x, y or z is not finite (organised clouds mark missing returns with NaN).

    Returns the kept rows and how many were dropped. Other columns may legitimately hold anything finite;
    a non-finite intensity is zeroed rather than dropping a valid point.
    """
    if points.dtype == np.float32 and points.flags.c_contiguous and np.isfinite(points).all():
        return points, 0  # the common case, ~30x cheaper than the per-row test below (a row reduction)
    xyz_ok = np.isfinite(points[:, :3]).all(axis=1)
    dropped = int(points.shape[0] - np.count_nonzero(xyz_ok))
    if dropped:
        points = points[xyz_ok]
    if points.shape[1] > 3:
        rest = points[:, 3:]
        bad = ~np.isfinite(rest)
        if bad.any():
            points = points.copy()
            points[:, 3:][bad] = 0.0
    return np.ascontiguousarray(points, dtype=np.float32), dropped


def compose(parent: EgoPose, child: EgoPose) -> EgoPose:
    """``parent ∘ child``: the pose of a frame given in ``parent``'s frame, expressed in the world."""
    r = rotation_from_quaternion(parent.qx, parent.qy, parent.qz, parent.qw)
    t = r @ np.array([child.x, child.y, child.z]) + np.array([parent.x, parent.y, parent.z])
    q = quaternion_multiply((parent.qx, parent.qy, parent.qz, parent.qw), (child.qx, child.qy, child.qz, child.qw))
    return EgoPose(float(t[0]), float(t[1]), float(t[2]), *q)
