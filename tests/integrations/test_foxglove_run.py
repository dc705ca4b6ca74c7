"""A real run recorded with the Foxglove bridge (``--record run.mcap``) and watched live over the Foxglove WebSocket
protocol: the MCAP read back with the ``mcap`` reader and Google's protobuf runtime; the live stream with a
``websockets`` client. The reference is what the pipeline itself published on Zenoh."""

from __future__ import annotations

import json
import math
from collections import Counter, defaultdict
from typing import Any

import numpy as np
import pytest
from google.protobuf.json_format import MessageToDict
from mcap.reader import make_reader

from jitterguard.services.foxglove.scene import DETECTIONS, GROUNDTRUTH, MOTION, POINTS, TF, TRACKS

from .decoding import protobuf_class, ws_schema_class

pytestmark = [pytest.mark.integration, pytest.mark.slow]

EXPECTED_SCHEMAS = {
    TF: ("foxglove.FrameTransforms", "protobuf"),
    POINTS: ("foxglove.PointCloud", "protobuf"),
    DETECTIONS: ("foxglove.SceneUpdate", "protobuf"),
    TRACKS: ("foxglove.SceneUpdate", "protobuf"),
    GROUNDTRUTH: ("foxglove.SceneUpdate", "protobuf"),
    MOTION: ("jitterguard.MotionStatistics", "jsonschema"),
}


def _read_mcap(path) -> tuple[dict[str, tuple[str, str]], dict[str, list[tuple[int, Any]]]]:
    """(topic → (schema name, schema encoding), topic → [(log time, decoded message as a dict)])."""
    schemas: dict[str, tuple[str, str]] = {}
    msgs: dict[str, list[tuple[int, Any]]] = defaultdict(list)
    classes: dict[int, Any] = {}
    with open(path, "rb") as f:
        reader = make_reader(f)
        for schema, channel, message in reader.iter_messages(log_time_order=True):
            schemas[channel.topic] = (schema.name, schema.encoding)
            if schema.encoding == "jsonschema":
                msgs[channel.topic].append((message.log_time, json.loads(message.data)))
                continue
            if schema.id not in classes:
                classes[schema.id] = protobuf_class(schema.name, schema.data)
            msgs[channel.topic].append((message.log_time, MessageToDict(classes[schema.id].FromString(message.data),
                                                                        preserving_proto_field_name=True)))
    return schemas, msgs


def _meta(entity: dict[str, Any]) -> dict[str, str]:
    return {kv["key"]: kv.get("value", "") for kv in entity.get("metadata", [])}


@pytest.fixture(scope="module")
def mcap_contents(pipeline_run):
    return _read_mcap(pipeline_run.mcap)


def test_every_channel_is_present_with_its_foxglove_schema(pipeline_run, mcap_contents) -> None:
    schemas, msgs = mcap_contents
    assert schemas == EXPECTED_SCHEMAS
    assert pipeline_run.foxglove_counters["frames"] >= 8  # a run, not a frame or two
    assert pipeline_run.foxglove_counters.get("sink_errors", 0) == 0


def test_one_message_per_frame_on_every_channel(pipeline_run, mcap_contents) -> None:
    _, msgs = mcap_contents
    frames = pipeline_run.foxglove_counters["frames"]
    for topic in EXPECTED_SCHEMAS:
        times = [t for t, _ in msgs[topic]]
        assert len(times) == frames, (topic, len(times), frames)
        assert max(Counter(times).values()) == 1, topic  # never two messages of one frame
    stamps = {topic: sorted(t for t, _ in msgs[topic]) for topic in EXPECTED_SCHEMAS}
    assert all(s == stamps[TRACKS] for s in stamps.values())  # the same frames on every channel
    assert set(stamps[TRACKS]) <= set(pipeline_run.objects)  # each one a frame the classifier published


def test_box_count_is_the_frames_track_count_and_static_boxes_stand_still(pipeline_run, mcap_contents) -> None:
    _, msgs = mcap_contents
    n_static = n_moving = n_decided = n_entities = 0
    for stamp, update in msgs[TRACKS]:
        objects = pipeline_run.objects[stamp].objects
        entities = update.get("entities", [])
        assert len(entities) == len(objects)
        assert update["deletions"][0]["type"] == "ALL"  # each update replaces the previous frame's
        by_id = {o.object_id: o for o in objects}
        for e in entities:
            obj = by_id[e["id"]]
            meta = _meta(e)
            assert len(e["cubes"]) == 1
            size = e["cubes"][0]["size"]
            assert size["x"] == pytest.approx(obj.shape.dimensions.x)
            if meta["state"] == "static":
                n_static += 1
                assert obj.kinematics.is_stationary or meta.get("decided_seq")
                assert float(meta["vx"]) == 0.0 and float(meta["vy"]) == 0.0
                assert "arrows" not in e  # zero velocity: no arrow
            v = obj.kinematics.twist_with_covariance.twist.linear
            if math.hypot(v.x, v.y) > 0:
                n_moving += 1
                (arrow,) = e["arrows"]
                assert arrow.get("shaft_length", 0.0) + arrow["head_length"] == pytest.approx(math.hypot(v.x, v.y), rel=1e-5)
            if obj.kinematics.is_stationary:
                assert meta["state"] == "static"
            decided = "decided_seq" in meta
            assert ("z=" in e["texts"][0]["text"]) == decided  # the statistic shows exactly when a decision is known
            n_decided += decided
            n_entities += 1
    assert n_static > 10 and n_moving > 0  # parked cars decided static, and some tracks move
    # motion/{id} joins its frame: a track decided first in a frame whose motion messages the classifier shed (the
    # next frame already waiting) or that came after --motion-wait shows no statistic yet (a loaded machine: one)
    assert n_decided >= 0.75 * n_entities, (n_decided, n_entities)


def test_points_detections_and_ground_truth_match_what_was_published(pipeline_run, mcap_contents) -> None:
    _, msgs = mcap_contents
    for stamp, pc in msgs[POINTS]:
        ref = pipeline_run.points[stamp]
        assert pc["frame_id"] == ref.header.frame_id
        assert [f["name"] for f in pc["fields"]] == ref.fields
        assert pc["point_stride"] == 4 * len(ref.fields)
    for stamp, upd in msgs[DETECTIONS]:
        dets = pipeline_run.detections[stamp].objects
        ents = upd.get("entities", [])
        assert len(ents) == len(dets)
        for e, d in zip(ents, dets):
            (cube,) = e["cubes"]
            assert cube["size"]["x"] == pytest.approx(d.shape.dimensions.x)
            discs = e.get("cylinders", [])
            assert len(discs) == (2 if d.kinematics.has_position_covariance else 0)  # 1σ and 2σ
            if discs:  # the 2σ disc is twice the 1σ one; its axes are the covariance's (the eigenvalues' roots)
                c = d.kinematics.pose_with_covariance.covariance
                lam = np.linalg.eigvalsh([[c[0], c[1]], [c[6], c[7]]])
                assert discs[0]["size"]["x"] == pytest.approx(2 * math.sqrt(lam[1]), rel=1e-5)
                assert discs[1]["size"]["y"] == pytest.approx(4 * math.sqrt(lam[0]), rel=1e-5)
    truths = [len(u.get("entities", [])) for _, u in msgs[GROUNDTRUTH]]
    assert min(truths) > 10  # the parking street's labelled cars
    states = [r["state"] for _, m in msgs[MOTION] for r in m["tracks"]]
    assert "static" in states and "dynamic" in states


def test_frames_chain_map_ego_sensor_to_the_published_pose(pipeline_run, mcap_contents) -> None:
    from scipy.spatial.transform import Rotation

    _, msgs = mcap_contents
    for stamp, tfs in msgs[TF]:
        a, b = tfs["transforms"]
        assert (a["parent_frame_id"], a["child_frame_id"], b["parent_frame_id"], b["child_frame_id"]) == (
            "map", "ego", "ego", "lidar")
        q = lambda t: [t["rotation"].get(k, 0.0) for k in "xyzw"]  # noqa: E731
        v = lambda t: [t["translation"].get(k, 0.0) for k in "xyz"]  # noqa: E731
        r = Rotation.from_quat(q(a)) * Rotation.from_quat(q(b))
        pos = Rotation.from_quat(q(a)).apply(v(b)) + v(a)
        ego = pipeline_run.points[stamp].ego_pose
        assert pos == pytest.approx([ego.position.x, ego.position.y, ego.position.z], abs=1e-9)
        o = ego.orientation
        assert (r * Rotation.from_quat([o.x, o.y, o.z, o.w]).inv()).magnitude() < 1e-9


def test_a_live_foxglove_client_gets_a_scene_update_within_2_s_of_the_first_frame(pipeline_run) -> None:
    ws = pipeline_run.ws
    assert ws.error is None, ws.error
    assert ws.subprotocol == "foxglove.sdk.v1"  # the Foxglove WebSocket protocol under its current name
    assert ws.server_info is not None and ws.server_info["name"] == "jitterguard"
    assert "clientPublish" not in ws.server_info.get("capabilities", [])  # viewers cannot write
    channel = ws.channels[TRACKS]
    assert channel["schemaName"] == "foxglove.SceneUpdate"
    assert ws.messages, "no SceneUpdate reached the client"
    assert pipeline_run.first_objects_at is not None
    assert ws.messages[0][0] - pipeline_run.first_objects_at <= 2.0
    cls = ws_schema_class(channel)
    decoded = [(t, MessageToDict(cls.FromString(p))) for _, t, p in ws.messages]
    for stamp, upd in decoded:  # what went over the wire is the frame's tracks
        assert len(upd.get("entities", [])) == len(pipeline_run.objects[stamp].objects)
    assert len(decoded) >= pipeline_run.foxglove_counters["frames"] - 1
