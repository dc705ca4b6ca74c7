"""The ``jitterguard record`` process: a bridge (:mod:`..bridge.service`) writing a ROS 2 bag (:mod:`.rosbag`)."""

from __future__ import annotations

from ...runtime import ZenohOptions
from ..bridge.joiner import DEFAULT_MOTION_WAIT_S
from ..bridge.service import BridgeService, FrameSink


class RecorderService(BridgeService):
    name = "record"

    def __init__(self, opts: ZenohOptions, sink: FrameSink, *, points: bool = True,
                 motion_wait_s: float = DEFAULT_MOTION_WAIT_S) -> None:
        super().__init__(opts, sink, points=points, motion_wait_s=motion_wait_s)
