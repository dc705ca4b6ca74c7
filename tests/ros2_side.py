"""A vehicle's ROS 2 side as zenoh-bridge-ros2dds shows it to Zenoh — each topic's key (the topic without its leading
'/') carrying the message's CDR bytes — or as ROS 2 nodes on rmw_zenoh put it (:func:`rmw_key`, each sample with
rmw_zenoh's attachment), played by a Zenoh session. CDR is encoded and decoded by mcap-ros2-support, an implementation
independent of the rosbags typestore jitterguard's ROS 2 services use; keys and attachments are spelt out here, not
taken from jitterguard's own naming."""

from __future__ import annotations

import itertools
import time
from pathlib import Path
from typing import Any

import zenoh
import zenoh.ext

from jitterguard.schemas.models import PointCloud, Pose
from jitterguard.services.replay.sources.ros_types import typestore


def codec(msgtype: str, *, encode: bool) -> Any:
    """mcap-ros2-support's encoder (dict → CDR bytes) or decoder (CDR bytes → message) of ``msgtype``."""
    from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic

    text, _ = typestore().generate_msgdef(msgtype, ros_version=2)
    return (serialize_dynamic if encode else generate_dynamic)(msgtype, text)[msgtype]


def rmw_key(topic: str, msgtype: str, domain: int = 0) -> str:
    """The key a ROS 2 node on rmw_zenoh (Jazzy and later) publishes ``topic`` on: domain, topic, DDS type name,
    REP 2011 type hash."""
    package, _, name = msgtype.split("/")
    return f"{domain}/{topic.strip('/')}/{package}::msg::dds_::{name}_/{typestore().hash_rihs01(msgtype)}"


def rmw_attachment(seq: int) -> bytes:
    """rmw_zenoh's attachment, written by zenoh-ext's serializer: sequence number, source timestamp, a 16-byte GID."""
    return zenoh.ext.z_serialize((zenoh.ext.Int64(seq), zenoh.ext.Int64(time.time_ns()), bytes(16))).to_bytes()


GRAPH_ENTITIES = {"NN": "node", "MP": "publisher", "MS": "subscription", "SS": "service", "SC": "client"}
QOS_DEFAULTS = {"reliability": 1, "durability": 2, "history": 1, "depth": 42}  # rmw_zenoh's qos.cpp


def read_graph_token(key: str) -> dict[str, Any]:
    """A liveliness token read as rmw_zenoh's graph cache reads it (``Entity::make(keyexpr)`` in
    ``liveliness_utils.cpp``): at least 9 chunks, none empty, ``@ros2_lv`` first; a publisher's or subscription's 13,
    its QoS six ``:``-separated fields whose empty values are rmw_zenoh's defaults; names with ``%`` for ``/``.
    AssertionError where rmw_zenoh would log "invalid liveliness token" and leave the entity out of the graph."""
    parts = str(key).split("/")
    assert len(parts) >= 9 and all(parts) and parts[0] == "@ros2_lv", key
    assert parts[5] in GRAPH_ENTITIES, key
    out: dict[str, Any] = {"domain": int(parts[1]), "zid": parts[2], "nid": parts[3], "id": parts[4],
                           "entity": GRAPH_ENTITIES[parts[5]], "enclave": parts[6].replace("%", "/"),
                           "namespace": parts[7].replace("%", "/"), "node": parts[8].replace("%", "/")}
    if parts[5] == "NN":
        return out
    assert len(parts) == 13, key
    qos = parts[12].split(":")
    assert len(qos) >= 6, key
    history, deadline, lifespan, liveliness = (q.split(",") for q in qos[2:6])
    assert len(history) >= 2 and len(deadline) >= 2 and len(lifespan) >= 2 and len(liveliness) >= 3, key
    for value in (*qos[:2], *history, *deadline, *lifespan, *liveliness):
        assert value == "" or value.isdigit(), key
    given = {"reliability": qos[0], "durability": qos[1], "history": history[0], "depth": history[1]}
    return out | {"topic": parts[9].replace("%", "/"), "type": parts[10].replace("%", "/"), "type_hash": parts[11],
                  "qos": {k: int(v) if v else QOS_DEFAULTS[k] for k, v in given.items()}}


def graph(session: zenoh.Session, domain: int) -> list[dict[str, Any]]:
    """The ROS graph's entities of ``domain`` that answer a liveliness query now (what ``ros2 node list`` and
    ``ros2 topic list`` are built from), each read by :func:`read_graph_token`, with its key as ``token``."""
    return [read_graph_token(r.ok.key_expr) | {"token": str(r.ok.key_expr)}
            for r in session.liveliness().get(f"@ros2_lv/{domain}/**", timeout=5.0) if r.ok is not None]


def sdk_messages(root: Path, msgtypes: tuple[str, ...]) -> Path:
    """A message folder as zenoh-ros2-sdk reads one (``pkg/msg/Name.msg``) holding ``msgtypes`` and every type they
    use: ROS 2's standard definitions as rosbags spells them, Autoware's from the ``.msg`` files jitterguard ships
    (the SDK would otherwise clone them from GitHub). The SDK parses them and computes the type hashes itself."""
    from jitterguard.ros2.types import shipped_definitions

    store = typestore()
    files: dict[str, str] = {}
    for msgtype in msgtypes:
        text, _ = store.generate_msgdef(msgtype, ros_version=2)
        main, *deps = text.split("=" * 80 + "\n")
        files[msgtype] = main
        for dep in deps:
            head, body = dep.split("\n", 1)
            package, name = head.removeprefix("MSG: ").strip().split("/")
            files[f"{package}/msg/{name}"] = body
    files |= shipped_definitions()
    for msgtype, text in files.items():
        path = root / f"{msgtype}.msg"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return root


def stamp(ns: int) -> dict:
    return {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}


def transform(parent: str, child: str, t: int, p: Pose) -> dict:
    return {"header": {"stamp": stamp(t), "frame_id": parent}, "child_frame_id": child,
            "transform": {"translation": {"x": p.position.x, "y": p.position.y, "z": p.position.z},
                          "rotation": {"x": p.orientation.x, "y": p.orientation.y, "z": p.orientation.z,
                                       "w": p.orientation.w}}}


class RosSide:
    """Puts a LiDAR's scans with ``/tf`` (map → base_link, the scan's pose) and ``/tf_static`` (base_link → lidar,
    level) on their topics' keys: a bridge's, or with ``rmw`` those of nodes on rmw_zenoh (domain 0)."""

    def __init__(self, session: zenoh.Session, points_topic: str, *, rmw: bool = False) -> None:
        self.session = session
        self.rmw = rmw
        self.keys = {t: rmw_key(t, m) if rmw else t.strip("/") for t, m in (
            (points_topic, "sensor_msgs/msg/PointCloud2"), ("/tf", "tf2_msgs/msg/TFMessage"),
            ("/tf_static", "tf2_msgs/msg/TFMessage"))}
        self.points_key = self.keys[points_topic]
        self.seq = itertools.count(1)
        self.tf = codec("tf2_msgs/msg/TFMessage", encode=True)
        self.cloud = codec("sensor_msgs/msg/PointCloud2", encode=True)
        self.static = bytes(self.tf({"transforms": [transform("base_link", "lidar", 0, Pose())]}))

    def _put(self, key: str, payload: bytes) -> None:
        self.session.put(key, payload, attachment=rmw_attachment(next(self.seq)) if self.rmw else None)

    def send(self, pc: PointCloud, t: int) -> None:
        """One wire scan (sensor frame, its world pose) as the ROS 2 side would have it, stamped ``t``."""
        self._put(self.keys["/tf_static"], self.static)
        self._put(self.keys["/tf"], bytes(self.tf({"transforms": [transform("map", "base_link", t, pc.ego_pose)]})))
        fields = [{"name": n, "offset": 4 * i, "datatype": 7, "count": 1} for i, n in enumerate(pc.fields)]
        self._put(self.points_key, bytes(self.cloud({
            "header": {"stamp": stamp(t), "frame_id": "lidar"}, "height": 1, "width": pc.num_points, "fields": fields,
            "is_bigendian": False, "point_step": 4 * len(fields), "row_step": 4 * len(fields) * pc.num_points,
            "data": pc.data, "is_dense": True})))
