"""A bird's-eye PNG of one frame of a recorded MCAP (``jitterguard foxglove --record``): the scan, ground truth,
detections with their 1σ/2σ ellipses, and tracks coloured by motion state with velocity arrows — what the layout's
3D panel shows, for documents and reports where Foxglove is not at hand.

It reads the MCAP as any consumer would: the ``mcap`` reader, and Google's protobuf runtime on the
FileDescriptorSets the file embeds (nothing from the writer's side), so it also checks the recording is
self-describing. Geometry goes through the recorded ``/tf`` (``map → ego → sensor``).
"""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ...files import save_figure
from .scene import DETECTIONS, GROUNDTRUTH, MOTION, POINTS, STATE_COLORS, TF, TRACKS

TOPICS = (TF, POINTS, DETECTIONS, TRACKS, GROUNDTRUTH, MOTION)


class RenderError(ValueError):
    """The file is not a jitterguard Foxglove recording, or has no such frame."""


@dataclass
class RecordedFrame:
    """Every channel's message of one frame (log time), decoded to plain dicts."""

    log_time: int
    messages: dict[str, Any] = field(default_factory=dict)


def _protobuf_class(name: str, data: bytes) -> Any:
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    pool = descriptor_pool.DescriptorPool()
    for fd in descriptor_pb2.FileDescriptorSet.FromString(data).file:
        pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))


def read_frames(path: str | Path) -> list[RecordedFrame]:
    """The recording's frames in time order (a frame: the messages sharing one log time). A recording whose writer
    was killed has no summary to seek by: it is read from the start as far as its records are whole."""
    from google.protobuf.json_format import MessageToDict
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    frames: dict[int, RecordedFrame] = {}
    classes: dict[int, Any] = {}

    def take(messages: Any) -> None:
        for schema, channel, msg in messages:
            if schema is None or channel.topic not in TOPICS:
                continue
            if schema.encoding == "jsonschema":
                body = json.loads(msg.data)
            elif schema.encoding != "protobuf":  # e.g. a ROS 2 bag's /tf (ros2msg): not the bridge's channel
                continue
            else:
                if schema.id not in classes:
                    classes[schema.id] = _protobuf_class(schema.name, schema.data)
                body = MessageToDict(classes[schema.id].FromString(msg.data), preserving_proto_field_name=True)
            frames.setdefault(msg.log_time, RecordedFrame(msg.log_time)).messages[channel.topic] = body

    from google.protobuf.message import DecodeError

    # struct.error: too short to hold a record; DecodeError: a schema or message the protobuf runtime cannot parse
    bad = (OSError, McapError, struct.error, ValueError, DecodeError)
    try:
        with open(path, "rb") as f:
            take(make_reader(f).iter_messages(topics=list(TOPICS), log_time_order=True))
    except bad as exc:
        frames.clear()
        try:  # no summary (the writer was killed): stream it, keeping what reads before the first broken record
            with open(path, "rb") as f:
                take(_streamed_messages(f))
        except bad:
            pass
        if not frames:
            raise RenderError(f"{path}: not a readable MCAP file ({type(exc).__name__}: {exc})") from None
    out = [frames[t] for t in sorted(frames) if TRACKS in frames[t].messages]
    if not out:
        raise RenderError(f"{path}: no {TRACKS} messages (a recording of no classified frame, or none of"
                          " jitterguard's: `foxglove --record`, `up --record-mcap`, `eval --mcap`)")
    return out


def _streamed_messages(f: Any) -> Iterator[tuple[Any, Any, Any]]:
    """(schema, channel, message) of every whole record of an MCAP stream, in file order (a summary not needed)."""
    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import StreamReader

    schemas: dict[int, Any] = {}
    channels: dict[int, Any] = {}
    for rec in StreamReader(f, skip_magic=False, emit_chunks=False).records:
        if isinstance(rec, Schema):
            schemas[rec.id] = rec
        elif isinstance(rec, Channel):
            channels[rec.id] = rec
        elif isinstance(rec, Message) and rec.channel_id in channels:
            ch = channels[rec.channel_id]
            yield schemas.get(ch.schema_id), ch, rec


# ---------------------------------------------------------------------------------------------------- geometry


def _quat(d: dict[str, Any] | None) -> np.ndarray:
    d = d or {}
    return np.array([d.get("x", 0.0), d.get("y", 0.0), d.get("z", 0.0), d.get("w", 0.0)], dtype=np.float64)


def _vec(d: dict[str, Any] | None) -> np.ndarray:
    d = d or {}
    return np.array([d.get("x", 0.0), d.get("y", 0.0), d.get("z", 0.0)], dtype=np.float64)


def _rot(q: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(q).as_matrix() if np.linalg.norm(q) > 0 else np.eye(3)


def sensor_to_world(tf_msg: dict[str, Any] | None) -> np.ndarray:
    """4×4 transform sensor → world from the frame's ``map → ego → sensor`` chain (identity without one)."""
    m = np.eye(4)
    for t in (tf_msg or {}).get("transforms", []):
        step = np.eye(4)
        step[:3, :3] = _rot(_quat(t.get("rotation")))
        step[:3, 3] = _vec(t.get("translation"))
        m = m @ step
    return m


def _apply(m: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    return xyz @ m[:3, :3].T + m[:3, 3]


def _pose_xy_yaw(pose: dict[str, Any], m: np.ndarray | None = None) -> tuple[float, float, float]:
    p, q = _vec(pose.get("position")), _quat(pose.get("orientation"))
    r = _rot(q)
    if m is not None:
        p, r = _apply(m, p[None])[0], m[:3, :3] @ r
    return float(p[0]), float(p[1]), math.atan2(r[1, 0], r[0, 0])


def _meta(entity: dict[str, Any]) -> dict[str, str]:
    return {kv["key"]: kv.get("value", "") for kv in entity.get("metadata", [])}


def scan_points_world(pc: dict[str, Any], m: np.ndarray) -> np.ndarray:
    """(N, 3) world points of a recorded ``foxglove.PointCloud`` (float32 fields, x, y, z first)."""
    import base64

    raw = pc.get("data", "")
    data = base64.b64decode(raw) if isinstance(raw, str) else bytes(raw)
    stride = int(pc["point_stride"])
    n = len(data) // stride
    cols = np.frombuffer(data[: n * stride], dtype="<f4").reshape(n, stride // 4)
    return _apply(m, cols[:, :3].astype(np.float64))


# ---------------------------------------------------------------------------------------------------- drawing


def render(frame: RecordedFrame, out: str | Path, *, span_m: float = 50.0, title: str | None = None) -> Path:
    """Draw ``frame`` bird's-eye around the ego into ``out`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Ellipse, FancyArrow, Polygon

    msgs = frame.messages
    m = sensor_to_world(msgs.get(TF))
    cx, cy = float(m[0, 3]), float(m[1, 3])
    fig, ax = plt.subplots(figsize=(9, 9), dpi=110)
    ax.set_facecolor("#111418")
    if POINTS in msgs:
        pts = scan_points_world(msgs[POINTS], m)
        near = (np.abs(pts[:, 0] - cx) < span_m) & (np.abs(pts[:, 1] - cy) < span_m)
        pts = pts[near]
        ax.scatter(pts[:, 0], pts[:, 1], s=0.3, c=np.clip(pts[:, 2] - m[2, 3], -2.5, 1.0), cmap="cividis",
                   alpha=0.6, linewidths=0, zorder=1)

    def box(x: float, y: float, yaw: float, length: float, width: float) -> np.ndarray:
        c, s = math.cos(yaw), math.sin(yaw)
        corners = np.array([[length, width], [length, -width], [-length, -width], [-length, width]]) / 2
        return corners @ np.array([[c, s], [-s, c]]) + (x, y)

    for e in msgs.get(GROUNDTRUTH, {}).get("entities", []):
        cube = e["cubes"][0]
        x, y, yaw = _pose_xy_yaw(cube["pose"])
        size = _vec(cube.get("size"))
        moving = _meta(e).get("moving") == "true"
        ax.add_patch(Polygon(box(x, y, yaw, size[0], size[1]), closed=True, fill=False, lw=0.8, ls="--",
                             ec="#33f25a" if moving else "#8c8c8c", zorder=2))
    for e in msgs.get(DETECTIONS, {}).get("entities", []):
        for disc in e.get("cylinders", []):  # the 1σ and 2σ ellipses, in the sensor frame
            x, y, yaw = _pose_xy_yaw(disc["pose"], m)
            size = _vec(disc.get("size"))
            ax.add_patch(Ellipse((x, y), size[0], size[1], angle=math.degrees(yaw), fill=False, lw=0.8,
                                 ec="#ffe633", zorder=4))
    for e in msgs.get(TRACKS, {}).get("entities", []):
        meta = _meta(e)
        cube = e["cubes"][0]
        x, y, yaw = _pose_xy_yaw(cube["pose"])
        rgba = STATE_COLORS.get(meta.get("state", "unknown"), STATE_COLORS["unknown"])
        size = _vec(cube.get("size"))
        ax.add_patch(Polygon(box(x, y, yaw, size[0], size[1]), closed=True, fc=rgba[:3] + (0.55,), ec=rgba[:3],
                             lw=1.0, zorder=3))
        vx, vy = float(meta.get("vx", 0.0)), float(meta.get("vy", 0.0))
        if math.hypot(vx, vy) > 0:
            ax.add_patch(FancyArrow(x, y, vx, vy, width=0.15, head_width=0.9, head_length=0.9,
                                    length_includes_head=True, color=rgba[:3], zorder=5))
    ax.plot([cx], [cy], marker="^", ms=10, color="white", zorder=6)
    ax.set_xlim(cx - span_m, cx + span_m)
    ax.set_ylim(cy - span_m, cy + span_m)
    ax.set_aspect("equal")
    ax.set_xlabel("map x (m)")
    ax.set_ylabel("map y (m)")
    stats = msgs.get(MOTION, {})
    counts = stats.get("counts", {})
    ax.set_title(title or (f"seq {stats.get('seq', '?')}: tracks static {counts.get('static', 0)}, dynamic "
                           f"{counts.get('dynamic', 0)}, undecided {counts.get('undecided', 0)}"))
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], marker="s", ls="", color=STATE_COLORS[s][:3], label=f"track: {s}")
               for s in ("static", "dynamic", "undecided")]
    handles += [Line2D([], [], color="#ffe633", label="detection 1σ / 2σ"),
                Line2D([], [], color="#33f25a", ls="--", label="ground truth: moving"),
                Line2D([], [], color="#8c8c8c", ls="--", label="ground truth: not moving")]
    ax.legend(handles=handles, loc="upper right", fontsize=8, framealpha=0.8)
    fig.tight_layout()
    out = Path(out)
    try:
        save_figure(fig, out)
    finally:
        plt.close(fig)
    return out


def pick_frame(frames: list[RecordedFrame], index: int | None) -> RecordedFrame:
    """Frame ``index`` (negative from the end); by default, among the frames with every channel, the one with the
    most tracks in motion and at rest."""
    if index is not None:
        if not -len(frames) <= index < len(frames):
            raise RenderError(f"--index {index}: the recording has {len(frames)} frames")
        return frames[index]

    def score(f: RecordedFrame) -> tuple[int, int, int]:
        c = f.messages.get(MOTION, {}).get("counts", {})
        return (len(f.messages), min(c.get("static", 0), 3 * c.get("dynamic", 0)),
                c.get("static", 0) + c.get("dynamic", 0))

    return max(frames, key=score)
