"""The bag's ``metadata.yaml`` as ROS 2 Humble's rosbag2 (0.15, which writes and knows metadata version 5) reads it.

Restated from rosbag2's ``rosbag2_storage/yaml.hpp`` decoder, whose reads are gated by the file's version: it reads
``version``, ``storage_identifier``, ``duration``, ``starting_time``, ``message_count``, ``relative_file_paths``, each
topic's ``name``, ``type``, ``serialization_format`` and (version >= 4) ``offered_qos_profiles`` *as a string*, the
compression fields (>= 3) and ``files`` (>= 5); Humble knows nothing newer and reads no other key, so
``custom_data``, ``ros_distro`` and ``type_description_hash`` are not read. Its player takes an empty
``offered_qos_profiles`` as its default QoS and parses a non-empty one as a YAML list. Version 9 writes the QoS as a
YAML list instead of a string, which Humble's ``as<std::string>()`` refuses ("bad conversion", the known Jazzy →
Humble failure): the check refuses such a bag (rosbags writes one with ``version=9``), and the recorder's passes.
Not run against ROS 2 (none here)."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

pytest.importorskip("rosbags")

from jitterguard.schemas.models import Header, PointCloud, Pose, TrackedObjects  # noqa: E402
from jitterguard.services.bridge.joiner import JoinedFrame  # noqa: E402
from jitterguard.services.recorder.rosbag import Rosbag2Sink  # noqa: E402

STAMP = 1_700_000_000_000_000_000


def _humble_reads(meta: dict) -> list[str]:
    """What Humble's decoder would refuse in ``metadata.yaml`` (empty: it reads the file)."""
    problems = []
    info = meta.get("rosbag2_bagfile_information")
    if not isinstance(info, dict):
        return ["no rosbag2_bagfile_information"]
    version = info.get("version")
    if not isinstance(version, int):
        return ["version is not an integer"]
    for key, kind in (("storage_identifier", str), ("message_count", int), ("relative_file_paths", list)):
        if not isinstance(info.get(key), kind):
            problems.append(f"{key} is not a {kind.__name__}")
    for key, field in (("duration", "nanoseconds"), ("starting_time", "nanoseconds_since_epoch")):
        if not isinstance((info.get(key) or {}).get(field), int):
            problems.append(f"{key}.{field} is not an integer")
    for t in info.get("topics_with_message_count") or []:
        tm = t.get("topic_metadata") or {}
        for key in ("name", "type", "serialization_format") + (("offered_qos_profiles",) if version >= 4 else ()):
            if not isinstance(tm.get(key), str):
                problems.append(f"topic {tm.get('name')}: {key} is not a string")
        qos = tm.get("offered_qos_profiles")
        if isinstance(qos, str) and qos and not isinstance(yaml.safe_load(qos), list):
            problems.append(f"topic {tm.get('name')}: offered_qos_profiles is no YAML list")
        if not isinstance(t.get("message_count"), int):
            problems.append(f"topic {tm.get('name')}: message_count is not an integer")
    if version >= 3 and not all(isinstance(info.get(k), str) for k in ("compression_format", "compression_mode")):
        problems.append("compression fields are not strings")
    if version >= 5 and not isinstance(info.get("files"), list):
        problems.append("files is not a list")
    return problems


def _frame() -> JoinedFrame:
    pts = np.array([[1.0, 2.0, 0.5, 7.0]], dtype="<f4")
    points = PointCloud(header=Header(stamp=STAMP, seq=1, frame_id="lidar"), ego_pose=Pose(), num_points=1,
                        data=pts.tobytes())
    return JoinedFrame(seq=1, stamp_ns=STAMP, objects=TrackedObjects(header=Header(stamp=STAMP, seq=1, frame_id="map")),
                       points=points)


def test_the_recorders_metadata_is_what_humbles_rosbag2_reads(tmp_path) -> None:
    sink = Rosbag2Sink(tmp_path / "bag")
    sink.write(_frame())
    sink.close()
    meta = yaml.safe_load((tmp_path / "bag" / "metadata.yaml").read_text())
    assert _humble_reads(meta) == []
    assert meta["rosbag2_bagfile_information"]["version"] == 8


def test_the_check_refuses_what_humble_refuses(tmp_path) -> None:
    """A version-9 bag (QoS as a YAML list) fails the check: it can fail, and would if the writer's version moved."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
    from rosbags.rosbag2 import StoragePlugin, Writer

    from jitterguard.ros2.types import TF_MESSAGE, typestore

    forever = QosTime(9223372036, 854775807)
    qos = Qos(QosHistory.KEEP_LAST, 100, QosReliability.RELIABLE, QosDurability.VOLATILE, forever, forever,
              QosLiveliness.AUTOMATIC, forever, False)
    store = typestore()
    with Writer(tmp_path / "bag", version=9, storage_plugin=StoragePlugin.MCAP) as w:
        w.add_connection("/tf", TF_MESSAGE, typestore=store, offered_qos_profiles=[qos])
    problems = _humble_reads(yaml.safe_load((tmp_path / "bag" / "metadata.yaml").read_text()))
    assert problems == ["topic /tf: offered_qos_profiles is not a string"]
