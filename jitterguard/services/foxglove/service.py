"""``jitterguard foxglove``: the joined frames (:mod:`..bridge`) as Foxglove messages (:mod:`.scene`), served live
over the Foxglove WebSocket protocol and/or written to MCAP, both by the ``foxglove-sdk`` package.

One :class:`foxglove.Context` binds the channels to both sinks, so the live view and the recording carry the very
same messages. ``/tf``, the tracks and the motion statistics exist from the start (every frame has them, and a
viewer can subscribe before the first frame); the other channels are created with their first message (a
detection-level run has no points channel; a source without labels no ground-truth channel). Every message is logged at the frame's stamp.

The server binds loopback only: the Foxglove protocol has no authentication, so viewing from another machine goes
through an SSH tunnel (``ssh -L 8765:127.0.0.1:8765 vehicle``). It advertises no client-publish capability:
viewers can subscribe, not write.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import foxglove
from foxglove import channels as fch

from ...runtime import ZenohOptions
from ..bridge.joiner import DEFAULT_MOTION_WAIT_S, JoinedFrame
from ..bridge.service import BridgeService
from .scene import DETECTIONS, GROUNDTRUTH, MOTION, MOTION_SCHEMA, POINTS, TF, TRACKS, frame_messages

log = logging.getLogger("jitterguard.foxglove")
DEFAULT_PORT = 8765

EAGER_TOPICS = (TF, TRACKS, MOTION)
_CHANNEL_TYPES: dict[str, Any] = {
    TF: fch.FrameTransformsChannel,
    POINTS: fch.PointCloudChannel,
    DETECTIONS: fch.SceneUpdateChannel,
    TRACKS: fch.SceneUpdateChannel,
    GROUNDTRUTH: fch.SceneUpdateChannel,
}


class SinkStartError(Exception):
    """The sink could not start its ``part`` (``"server"`` or ``"recording"``); nothing of it is left open or
    written: the server is started first, so a port in use neither leaves an empty MCAP nor overwrites one."""

    def __init__(self, part: str, message: str) -> None:
        super().__init__(message)
        self.part = part


class FoxgloveSink:
    """Writes joined frames to a Foxglove WebSocket server (``port`` not None) and/or an MCAP file."""

    def __init__(self, *, host: str = "127.0.0.1", port: int | None = DEFAULT_PORT, mcap_path: str | Path | None = None,
                 overwrite: bool = False) -> None:
        if port is None and mcap_path is None:
            raise ValueError("nothing to do: no server port and no MCAP path")
        self.context = foxglove.Context()
        self._channels: dict[str, Any] = {}
        self.server: Any = None
        self.mcap: Any = None
        self.mcap_path = Path(mcap_path) if mcap_path is not None else None
        self._logged = False  # a message went to the MCAP: else its channels are written on close (_channels_only)
        if port is not None:  # first: a port in use had left a new, empty MCAP behind, or overwritten an old one
            try:
                self.server = foxglove.start_server(name="jitterguard", host=host, port=port, context=self.context)
            except Exception as exc:  # noqa: BLE001 - the SDK raises its own error types
                raise SinkStartError("server", f"cannot serve on {host}:{port}: {exc}") from exc
        if self.mcap_path is not None:
            try:
                self.mcap = foxglove.open_mcap(str(self.mcap_path), allow_overwrite=overwrite, context=self.context)
            except Exception as exc:  # noqa: BLE001
                if self.server is not None:
                    self.server.stop()
                raise SinkStartError("recording", f"cannot record to {self.mcap_path}: {exc}") from exc
        for topic in EAGER_TOPICS:  # every frame has these: a viewer can subscribe before the first frame
            self._channel(topic)

    @property
    def port(self) -> int | None:
        return None if self.server is None else int(self.server.port)

    def _channel(self, topic: str) -> Any:
        ch = self._channels.get(topic)
        if ch is None:
            if topic == MOTION:
                ch = foxglove.Channel(topic, schema=MOTION_SCHEMA, context=self.context)
            else:
                ch = _CHANNEL_TYPES[topic](topic, context=self.context)
            self._channels[topic] = ch
        return ch

    def write(self, frame: JoinedFrame) -> None:
        for topic, msg in frame_messages(frame).items():
            self._channel(topic).log(msg, log_time=frame.stamp_ns)
            self._logged = True

    def _close_mcap(self) -> None:
        if self.mcap is not None:
            self.mcap.close()
            self.mcap = None
            if not self._logged and self.mcap_path is not None:
                self._channels_only(self.mcap_path)

    def _channels_only(self, path: Path) -> None:
        """Rewrite the MCAP at ``path`` as the channels created so far with their schemas and no message. The SDK
        writes a channel with its first message, so a recording without a frame (``eval --mcap`` of a run too short to
        decide anything, a stack stopped before its first frame) had held no channel and no schema: Foxglove opened an
        empty file, the layout's panels bound to nothing. Written with the ``mcap`` package the SDK's extra brings."""
        from mcap.writer import Writer

        with path.open("wb") as f:
            w = Writer(f)
            w.start(profile="", library="jitterguard")
            for topic, ch in self._channels.items():
                schema = ch.schema()
                sid = w.register_schema(schema.name, schema.encoding, bytes(schema.data)) if schema is not None else 0
                w.register_channel(topic, ch.message_encoding, sid, dict(ch.metadata() or {}))
            w.finish()

    def close(self) -> None:
        self._close_mcap()
        if self.server is not None:
            self.server.stop()
            self.server = None


class FoxgloveService(BridgeService):
    """The ``jitterguard foxglove`` process."""

    name = "foxglove"

    def __init__(self, opts: ZenohOptions, sink: FoxgloveSink, *, points: bool = True,
                 motion_wait_s: float = DEFAULT_MOTION_WAIT_S) -> None:
        super().__init__(opts, sink, points=points, motion_wait_s=motion_wait_s)
