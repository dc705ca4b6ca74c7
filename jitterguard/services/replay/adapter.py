"""The replay's seam between its frames and the wire: a scan becomes a ``PointCloud``, a detection frame a
``DetectedObjects``, under the header seq and stamp the runner gives it. Pure."""

from __future__ import annotations

from ...schemas import DetectedObjects, GroundTruthObjects, PointCloud
from ...schemas.models import Header
from .frames import DetectionFrame, Frame, ScanFrame


def point_cloud_message(frame: ScanFrame, seq: int, stamp_ns: int) -> PointCloud:
    """The ``points`` payload of one scan under the given header seq and stamp."""
    pts = frame.points
    return PointCloud(
        header=Header(stamp=stamp_ns, frame_id=frame.frame_id, seq=seq),
        ego_pose=frame.pose.to_schema(),
        fields=list(frame.fields),
        num_points=int(pts.shape[0]),
        data=pts.astype("<f4", copy=False).tobytes(),
    )


def detections_message(frame: DetectionFrame, seq: int, stamp_ns: int) -> DetectedObjects:
    """The ``detections`` payload of one detection frame under the given header seq and stamp."""
    return DetectedObjects(
        header=Header(stamp=stamp_ns, frame_id=frame.frame_id, seq=seq),
        ego_pose=frame.pose.to_schema(),
        objects=frame.objects,
    )


def truth_for(frame: Frame, seq: int, stamp_ns: int) -> GroundTruthObjects | None:
    """The frame's labels under the seq and stamp its ``points`` / ``detections`` go out with, if it has any."""
    if frame.truth is None:
        return None
    return frame.truth.model_copy(update={"header": Header(stamp=stamp_ns, frame_id=frame.truth.header.frame_id, seq=seq)})


def message_for(frame: Frame, seq: int, stamp_ns: int) -> PointCloud | DetectedObjects:
    if isinstance(frame, ScanFrame):
        return point_cloud_message(frame, seq, stamp_ns)
    return detections_message(frame, seq, stamp_ns)
