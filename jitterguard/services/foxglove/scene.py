"""One joined frame as Foxglove messages: pure functions, no server, no file, no clock.

Topics (one message per frame on each that applies; ``TOPICS`` names them):

- ``/tf`` (``foxglove.FrameTransforms``): ``map → ego → <sensor frame>`` (:mod:`..bridge.frames`: ``ego`` is the
  sensor pose on the ground plane, a gravity-aligned frame to follow in the 3D panel; composed, the two transforms
  are the sensor pose the wire carries).
- ``/jitterguard/points`` (``foxglove.PointCloud``, sensor frame): the scan's float32 columns as they came.
- ``/jitterguard/detections`` (``foxglove.SceneUpdate``, sensor frame): each detection's box and its 1σ and 2σ
  position ellipses (flat discs) from the detector's 2×2 x/y covariance (eigen-decomposed, so correlated errors tilt
  them).
- ``/jitterguard/tracks`` (``foxglove.SceneUpdate``, world frame): the classifier's ``objects`` as boxes coloured by
  motion state (static blue, dynamic orange, undecided grey, never decided white; a track not observed this frame
  shows its latest decision, its label naming the frame it is from), a velocity arrow for
  every object with a non-zero twist (static objects leave the classifier with zero twist: no arrow), a label
  ``class state`` and the statistic that decided (``z=… α=…``; ``χ²=… thr=…`` in χ² mode, ``v=… m/s thr=…`` for the
  speed threshold), and metadata (state, vx, vy, z_x, z_y, chi2, mode, statistic, threshold, alpha, is_stationary) on
  each entity.
- ``/jitterguard/groundtruth`` (``foxglove.SceneUpdate``, world frame): labelled boxes when the source has them
  (green moving, grey not moving; translucent, outlined by the panel), each with its attribute.
- ``/jitterguard/motion`` (JSON, :data:`MOTION_SCHEMA`): the classifier's per-track statistics of the frame, for the
  Plot panel (``z_by_track``: one dynamic series per track) and the Table panel (``tracks``).

Each SceneUpdate first deletes every entity of the previous one, so the panel shows exactly this frame.
"""

from __future__ import annotations

import math
from typing import Any

import foxglove.messages as fm
import numpy as np

from ...geometry import yaw_from_quaternion
from ...schemas.models import LABEL_NAMES, X_X, X_Y, Y_Y, DetectedObject, MotionState, Pose, Shape, TrackedObject
from ..bridge.frames import sensor_chain
from ..bridge.joiner import JoinedFrame

TF, POINTS, DETECTIONS, TRACKS, GROUNDTRUTH, MOTION = (
    "/tf", "/jitterguard/points", "/jitterguard/detections", "/jitterguard/tracks", "/jitterguard/groundtruth",
    "/jitterguard/motion")
TOPICS = (TF, POINTS, DETECTIONS, TRACKS, GROUNDTRUTH, MOTION)
EGO_FRAME = "ego"
ARROW_SECONDS = 1.0
"""A velocity arrow is as long as the distance covered in this many seconds."""
ELLIPSE_SIGMAS = (1.0, 2.0)

STATE_COLORS: dict[str, tuple[float, float, float, float]] = {
    "static": (0.20, 0.55, 1.00, 0.55),
    "dynamic": (1.00, 0.45, 0.10, 0.55),
    "undecided": (0.65, 0.65, 0.65, 0.45),
    "unknown": (1.00, 1.00, 1.00, 0.30),
}
DETECTION_COLOR = (1.0, 0.9, 0.2, 0.12)
ELLIPSE_COLORS = ((1.0, 0.9, 0.2, 0.55), (1.0, 0.9, 0.2, 0.25))
TRUTH_COLORS = {True: (0.2, 0.95, 0.35, 0.12), False: (0.55, 0.55, 0.55, 0.12)}

MOTION_SCHEMA: dict[str, Any] = {
    "title": "jitterguard.MotionStatistics",
    "description": "The motion classifier's per-track statistics of one frame (jitterguard).",
    "type": "object",
    "properties": {
        "timestamp": {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}},
        "seq": {"type": "integer"},
        "counts": {"type": "object", "properties": {s: {"type": "integer"} for s in STATE_COLORS}},
        "max_z": {"type": "number", "description": "largest max(z_x, z_y) over the frame's decided tracks"},
        "alpha_min": {"type": "number"},
        "alpha_max": {"type": "number"},
        "z_by_track": {"type": "array", "items": {"type": "object", "properties": {
            "label": {"type": "string"}, "value": {"type": "number"}}}},
        "tracks": {"type": "array", "items": {"type": "object", "properties": {
            "id": {"type": "string"}, "class": {"type": "string"}, "state": {"type": "string"},
            "z_x": {"type": "number"}, "z_y": {"type": "number"}, "z": {"type": "number"},
            "mode": {"type": "string", "description": "the test that decided: z_test, chi2 or velocity_threshold"},
            "chi2": {"type": "number"},
            "statistic": {"type": "number", "description": "what the mode compared with threshold: max(z_x, z_y),"
                          " chi2 or speed"},
            "alpha": {"type": "number"}, "threshold": {"type": "number"}, "window_length": {"type": "integer"},
            "speed": {"type": "number"}, "x": {"type": "number"}, "y": {"type": "number"},
            "decided_seq": {"type": "integer", "description": "seq of the frame the statistics are from"},
            "vx": {"type": "number"}, "vy": {"type": "number"}, "is_stationary": {"type": "boolean"}}}},
    },
}


# ----------------------------------------------------------------------------------------- small builders


def timestamp(stamp_ns: int) -> fm.Timestamp:
    return fm.Timestamp(sec=stamp_ns // 1_000_000_000, nsec=stamp_ns % 1_000_000_000)


def _color(rgba: tuple[float, float, float, float]) -> fm.Color:
    return fm.Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])


def _pose(x: float, y: float, z: float, yaw: float = 0.0) -> fm.Pose:
    return fm.Pose(position=fm.Vector3(x=x, y=y, z=z),
                   orientation=fm.Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)))


def _wire_pose(p: Pose) -> fm.Pose:
    q = p.orientation
    return fm.Pose(position=fm.Vector3(x=p.position.x, y=p.position.y, z=p.position.z),
                   orientation=fm.Quaternion(x=q.x, y=q.y, z=q.z, w=q.w))


def _shape_primitives(shape: Shape, pose: Pose, rgba: tuple[float, float, float, float]
                      ) -> tuple[list[fm.CubePrimitive], list[fm.LinePrimitive]]:
    """A box as a cube; a POLYGON (Autoware's UNKNOWN clusters: a footprint, length and width 0) as its footprint's
    outline at the bottom and the top of its height, in the object's frame — its cube had been drawn 0 × 0."""
    pts = shape.footprint
    if shape.type != Shape.POLYGON or len(pts) < 3:
        d = shape.dimensions
        return [fm.CubePrimitive(pose=_wire_pose(pose), size=fm.Vector3(x=d.x, y=d.y, z=d.z), color=_color(rgba))], []
    h = shape.dimensions.z
    loops = [fm.LinePrimitive(type=fm.LinePrimitiveLineType.LineLoop, pose=_wire_pose(pose), thickness=0.06,
                              scale_invariant=False, color=_color(rgba[:3] + (1.0,)),
                              points=[fm.Point3(x=q.x, y=q.y, z=z) for q in pts])
             for z in (-h / 2, h / 2)]
    return [], loops


def _kv(**items: Any) -> list[fm.KeyValuePair]:
    return [fm.KeyValuePair(key=k, value=v if isinstance(v, str) else f"{v:.6g}" if isinstance(v, float) else str(v))
            for k, v in items.items()]


def _class_name(classification: list[Any]) -> str:
    if not classification:
        return "unknown"
    return LABEL_NAMES.get(int(max(classification, key=lambda c: c.probability).label), "unknown")


def ellipse_axes(cov_xx: float, cov_xy: float, cov_yy: float) -> tuple[float, float, float]:
    """(σ along the major axis, σ along the minor axis, heading of the major axis in rad) of a 2-D Gaussian:
    eigen-decomposed, so correlated errors tilt the ellipse."""
    vals, vecs = np.linalg.eigh(np.array([[cov_xx, cov_xy], [cov_xy, cov_yy]], dtype=np.float64))
    major = vecs[:, 1]
    return (math.sqrt(max(float(vals[1]), 0.0)), math.sqrt(max(float(vals[0]), 0.0)),
            math.atan2(float(major[1]), float(major[0])))


def ellipse_xy(cov_xx: float, cov_xy: float, cov_yy: float, sigma: float, segments: int = 48) -> np.ndarray:
    """(segments, 2) points of the ``sigma``-σ contour centred at the origin (what an ellipse disc's rim covers)."""
    a, b, th = ellipse_axes(cov_xx, cov_xy, cov_yy)
    t = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    c, s = math.cos(th), math.sin(th)
    ex, ey = sigma * a * np.cos(t), sigma * b * np.sin(t)
    return np.column_stack([c * ex - s * ey, s * ex + c * ey])


# ----------------------------------------------------------------------------------------- per topic


def frame_transforms(frame: JoinedFrame) -> fm.FrameTransforms | None:
    """``map → ego → sensor`` at the frame's stamp (:func:`..bridge.frames.sensor_chain`; None without a pose:
    tracks-level input, or with data in the world frame)."""
    pose = frame.sensor_pose
    if pose is None:
        return None
    links = sensor_chain(pose, frame.world_frame, EGO_FRAME, frame.sensor_frame)
    if not links:
        return None
    ts = timestamp(frame.stamp_ns)
    return fm.FrameTransforms(transforms=[
        fm.FrameTransform(timestamp=ts, parent_frame_id=parent, child_frame_id=child,
                          translation=fm.Vector3(x=xyz[0], y=xyz[1], z=xyz[2]),
                          rotation=fm.Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))
        for parent, child, xyz, q in links])


def point_cloud(frame: JoinedFrame) -> fm.PointCloud | None:
    """The scan as sent (packed little-endian float32 rows), in the sensor frame."""
    pc = frame.points
    if pc is None:
        return None
    fields = [fm.PackedElementField(name=n, offset=4 * j, type=fm.PackedElementFieldNumericType.Float32)
              for j, n in enumerate(pc.fields)]
    return fm.PointCloud(timestamp=timestamp(frame.stamp_ns), frame_id=pc.header.frame_id or frame.sensor_frame,
                         pose=_pose(0.0, 0.0, 0.0), point_stride=4 * len(pc.fields), fields=fields, data=pc.data)


def _clear_all(stamp: fm.Timestamp) -> list[fm.SceneEntityDeletion]:
    return [fm.SceneEntityDeletion(timestamp=stamp, type=fm.SceneEntityDeletionType.All)]


def _detection_entity(i: int, d: DetectedObject, frame_id: str, stamp: fm.Timestamp) -> fm.SceneEntity:
    """The detection's box (a translucent cube; the panel outlines it) and its 1σ and 2σ position ellipses as flat
    discs (a cylinder ``2kσ_major × 2kσ_minor`` turned to the major axis): two primitives, not hundreds of points —
    a scan has a hundred detections and the bridge builds them ten times a second."""
    k = d.kinematics
    p = k.pose_with_covariance.pose
    dims = d.shape.dimensions
    cubes, lines = _shape_primitives(d.shape, p, DETECTION_COLOR)
    cylinders = []
    meta: dict[str, Any] = {"class": _class_name(d.classification), "score": float(d.existence_probability)}
    if k.has_position_covariance:
        c = k.pose_with_covariance.covariance
        a, b, heading = ellipse_axes(c[X_X], c[X_Y], c[Y_Y])
        meta.update(sigma_x=math.sqrt(c[X_X]), sigma_y=math.sqrt(c[Y_Y]), sigma_major=a, sigma_minor=b)
        at = _pose(p.position.x, p.position.y, p.position.z - dims.z / 2 + 0.05, heading)
        for sigma, rgba in zip(ELLIPSE_SIGMAS, ELLIPSE_COLORS, strict=True):
            cylinders.append(fm.CylinderPrimitive(pose=at, size=fm.Vector3(x=2 * sigma * a, y=2 * sigma * b, z=0.04),
                                                  bottom_scale=1.0, top_scale=1.0, color=_color(rgba)))
    return fm.SceneEntity(timestamp=stamp, frame_id=frame_id, id=f"det-{i}", cubes=cubes, lines=lines,
                          cylinders=cylinders, metadata=_kv(**meta))


def detections_scene(frame: JoinedFrame) -> fm.SceneUpdate | None:
    dets = frame.detections
    if dets is None:
        return None
    stamp = timestamp(frame.stamp_ns)
    frame_id = dets.header.frame_id or frame.sensor_frame
    return fm.SceneUpdate(deletions=_clear_all(stamp),
                          entities=[_detection_entity(i, d, frame_id, stamp) for i, d in enumerate(dets.objects)])


def motion_of(frame: JoinedFrame, obj: TrackedObject) -> tuple[Any, bool]:
    """(the MotionState behind ``obj``'s state, whether it is this frame's): a track not observed this frame (or a
    frame whose motion messages the classifier shed) shows its latest earlier decision."""
    m = frame.motion.get(obj.object_id)
    if m is not None:
        return m, True
    return frame.last_motion.get(obj.object_id), False


def track_state(frame: JoinedFrame, obj: TrackedObject) -> str:
    """The classifier's decision for ``obj`` as the published object states it: ``static`` when it is stationary;
    else this frame's decision, else the latest earlier one; ``unknown`` when there is none, or when the latest one
    seen was ``static`` although the object no longer is (a decision message was missed)."""
    if obj.kinematics.is_stationary:
        return "static"
    m, _ = motion_of(frame, obj)
    if m is None or m.state == "static":
        return "unknown"
    return m.state


def _track_entity(frame: JoinedFrame, obj: TrackedObject, stamp: fm.Timestamp) -> fm.SceneEntity:
    k = obj.kinematics
    p = k.pose_with_covariance.pose
    dims = obj.shape.dimensions
    v = k.twist_with_covariance.twist.linear
    state = track_state(frame, obj)
    m, current = motion_of(frame, obj)
    cls = _class_name(obj.classification)
    yaw = yaw_from_quaternion(p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w)
    top = p.position.z + max(dims.z, 0.5) / 2
    arrows = []
    speed = math.hypot(v.x, v.y)
    if speed > 0.0:
        head = min(0.6, 0.5 * speed * ARROW_SECONDS)
        arrows.append(fm.ArrowPrimitive(pose=_pose(p.position.x, p.position.y, top + 0.1, math.atan2(v.y, v.x)),
                                        shaft_length=max(speed * ARROW_SECONDS - head, 0.0), shaft_diameter=0.12,
                                        head_length=head, head_diameter=0.35, color=_color(STATE_COLORS[state][:3] + (1.0,))))
    if m is not None:
        text = f"{cls} {state} {_decided_text(m)}" + ("" if current else f" (seq {m.header.seq})")
    else:
        text = f"{cls} {state}"
    texts = [fm.TextPrimitive(pose=_pose(p.position.x, p.position.y, top + 0.6, yaw), billboard=True, font_size=14.0,
                              scale_invariant=True, color=_color((1.0, 1.0, 1.0, 1.0)), text=text)]
    cubes, lines = _shape_primitives(obj.shape, p, STATE_COLORS[state])
    meta: dict[str, Any] = {"class": cls, "state": state, "vx": float(v.x), "vy": float(v.y),
                            "is_stationary": str(k.is_stationary).lower()}
    if m is not None:
        meta.update(z_x=_unsigned_zero(m.z_x), z_y=_unsigned_zero(m.z_y), alpha=float(m.alpha), window_length=m.window_length,
                    decided_seq=m.header.seq, mode=m.mode, statistic=decided_statistic(m), chi2=_unsigned_zero(m.chi2),
                    threshold=float(m.threshold))
    return fm.SceneEntity(timestamp=stamp, frame_id=frame.world_frame, id=obj.object_id, cubes=cubes, lines=lines,
                          arrows=arrows, texts=texts, metadata=_kv(**meta))


def decided_statistic(m: MotionState) -> float:
    """The value the classifier compared with ``m.threshold`` in ``m.mode``: max(z_x, z_y) for the z-test, the χ²
    statistic for ``chi2``, the speed for ``velocity_threshold``. In χ² mode the label had shown max(z_x, z_y), a wire
    field the decision never used (a track called dynamic on χ² 12.5 read "z=3.00 α=1.96")."""
    if m.mode == "chi2":
        return _unsigned_zero(m.chi2)
    if m.mode == "velocity_threshold":
        return _unsigned_zero(m.speed)
    return _unsigned_zero(max(m.z_x, m.z_y))


def _decided_text(m: MotionState) -> str:
    """A label's statistic, as its mode decided: ``z=… α=…``, ``χ²=… thr=…`` (the χ²₂ quantile) or ``v=… m/s
    thr=…``."""
    if m.mode == "chi2":
        return f"χ²={decided_statistic(m):.2f} thr={m.threshold:.2f}"
    if m.mode == "velocity_threshold":
        return f"v={decided_statistic(m):.2f} m/s thr={m.threshold:.2f}"
    return f"z={decided_statistic(m):.2f} α={m.alpha:.2f}"


def _unsigned_zero(v: float) -> float:
    """``v`` with a negative zero made 0.0: the classifier's z of a window inside its H0 speed bound can come as -0.0,
    which every static car's label showed as "z=-0.00" (and the Table and Plot as -0)."""
    return float(v) + 0.0


def tracks_scene(frame: JoinedFrame) -> fm.SceneUpdate:
    stamp = timestamp(frame.stamp_ns)
    return fm.SceneUpdate(deletions=_clear_all(stamp),
                          entities=[_track_entity(frame, o, stamp) for o in frame.objects.objects])


def groundtruth_scene(frame: JoinedFrame) -> fm.SceneUpdate | None:
    gt = frame.groundtruth
    if gt is None:
        return None
    stamp = timestamp(frame.stamp_ns)
    ents = []
    for o in gt.objects:
        d = o.dimensions
        ents.append(fm.SceneEntity(
            timestamp=stamp, frame_id=gt.header.frame_id or frame.world_frame, id=f"gt-{o.instance_id}",
            cubes=[fm.CubePrimitive(pose=_wire_pose(o.pose), size=fm.Vector3(x=d.x, y=d.y, z=d.z),
                                    color=_color(TRUTH_COLORS[o.moving]))],
            metadata=_kv(instance=o.instance_id, label=LABEL_NAMES.get(o.label, "unknown"), moving=str(o.moving).lower(),
                         attribute=o.attribute, vx=float(o.velocity.x), vy=float(o.velocity.y))))
    return fm.SceneUpdate(deletions=_clear_all(stamp), entities=ents)


def motion_statistics(frame: JoinedFrame) -> dict[str, Any]:
    """The JSON message of :data:`MOTION_SCHEMA` for this frame (tracks in ``objects`` order)."""
    rows = []
    counts = dict.fromkeys(STATE_COLORS, 0)
    for obj in frame.objects.objects:
        state = track_state(frame, obj)
        counts[state] += 1
        m, _ = motion_of(frame, obj)
        p = obj.kinematics.pose_with_covariance.pose.position
        v = obj.kinematics.twist_with_covariance.twist.linear
        row: dict[str, Any] = {"id": obj.object_id, "class": _class_name(obj.classification), "state": state,
                               "x": p.x, "y": p.y, "vx": v.x, "vy": v.y, "is_stationary": obj.kinematics.is_stationary}
        if m is not None:
            row.update(z_x=_unsigned_zero(m.z_x), z_y=_unsigned_zero(m.z_y), z=_unsigned_zero(max(m.z_x, m.z_y)),
                       mode=m.mode, chi2=_unsigned_zero(m.chi2), statistic=decided_statistic(m),
                       alpha=m.alpha, threshold=m.threshold,
                       window_length=m.window_length, speed=m.speed, decided_seq=m.header.seq)
        rows.append(row)
    decided = [r for r in rows if "z" in r]
    alphas = [r["alpha"] for r in decided]
    return {
        "timestamp": {"sec": frame.stamp_ns // 1_000_000_000, "nsec": frame.stamp_ns % 1_000_000_000},
        "seq": frame.seq,
        "counts": counts,
        "max_z": max((r["z"] for r in decided), default=0.0),
        "alpha_min": min(alphas, default=0.0),
        "alpha_max": max(alphas, default=0.0),
        "z_by_track": [{"label": f"{r['class']} {r['id'][-6:]}", "value": r["z"]} for r in decided],  # the
        # ID's end: the evaluator's IDs are counters, zero-padded in front (its start is "000000" for every track)
        "tracks": rows,
    }


def frame_messages(frame: JoinedFrame) -> dict[str, Any]:
    """Every message of this frame by topic (topics without data this frame are left out)."""
    out: dict[str, Any] = {
        TF: frame_transforms(frame),
        POINTS: point_cloud(frame),
        DETECTIONS: detections_scene(frame),
        TRACKS: tracks_scene(frame),
        GROUNDTRUTH: groundtruth_scene(frame),
        MOTION: motion_statistics(frame),
    }
    return {k: v for k, v in out.items() if v is not None}
