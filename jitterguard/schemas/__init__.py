"""The wire contract: models, the msgpack codec and key-expression builders. No I/O."""

from . import keys
from .codec import DecodeError, decode, decode_map, decode_with_raw, encode, peek_header_seq, unpack_map, validate_map
from .models import *  # noqa: F401,F403  (the models are the contract; re-export them all)
from .models import (
    AUTHORS_ALPHA,
    LABEL_BY_NAME,
    LABEL_NAMES,
    PRESETS,
    SCHEMA_VERSION,
    ClassifierConfig,
    DetectedObjects,
    GroundTruthObjects,
    Label,
    MotionState,
    PointCloud,
    TrackedObjects,
    TrackObservation,
)

__all__ = [
    "keys",
    "encode",
    "decode",
    "decode_with_raw",
    "decode_map",
    "unpack_map",
    "validate_map",
    "peek_header_seq",
    "DecodeError",
    "SCHEMA_VERSION",
    "Label",
    "LABEL_NAMES",
    "LABEL_BY_NAME",
    "AUTHORS_ALPHA",
    "PRESETS",
    "ClassifierConfig",
    "DetectedObjects",
    "GroundTruthObjects",
    "MotionState",
    "PointCloud",
    "TrackedObjects",
    "TrackObservation",
]
