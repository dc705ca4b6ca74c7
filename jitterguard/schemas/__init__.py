"""The wire contract: models, the general codec, the hot messages' read/write functions, key builders. No I/O."""

from . import keys
from .codec import DecodeError, decode, decode_with_raw, encode
from .models import *  # noqa: F401,F403  (the models are the contract; re-export them all)
from .models import SCHEMA_VERSION, ClassifierConfig, DetectedObjects, GroundTruthObjects, Label, MotionState, PointCloud
from .models import TrackedObjects, TrackObservation
from .wire import (
    DetectedColumns,
    LimitExceeded,
    Limits,
    ObservationColumns,
    TrackedColumns,
    peek_header,
    read_detected_objects,
    read_track_observations,
    read_tracked_objects,
    write_detected_objects,
    write_motion_states,
    write_track_observations,
    write_tracked_objects,
)

__all__ = [
    "keys", "encode", "decode", "decode_with_raw", "DecodeError", "LimitExceeded", "Limits", "peek_header",
    "DetectedColumns", "TrackedColumns", "ObservationColumns",
    "read_detected_objects", "write_detected_objects", "read_track_observations", "write_track_observations",
    "read_tracked_objects", "write_tracked_objects", "write_motion_states",
    "SCHEMA_VERSION", "Label", "ClassifierConfig", "DetectedObjects", "GroundTruthObjects", "MotionState", "PointCloud",
    "TrackedObjects",
    "TrackObservation",
]
