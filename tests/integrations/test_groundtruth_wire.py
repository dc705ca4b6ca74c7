"""Ground truth on the wire: the replay publishes a labelled source's boxes on ``jg/{ns}/groundtruth`` with the seq
and stamp of the frame they label; the model rejects malformed payloads like every other."""

from __future__ import annotations

import math
import threading

import pytest
import zenoh

from jitterguard.runtime import build_config, free_tcp_port, loopback_options
from jitterguard.schemas import DecodeError, decode, encode, keys
from jitterguard.schemas.models import GroundTruthObjects, PointCloud
from jitterguard.services.replay.service import ReplayService
from jitterguard.services.replay.runner import ReplayPlan
from jitterguard.services.replay.sources import SourceOptions, open_source

from helpers import NUSC, collector, wait_until



@pytest.mark.integration
def test_the_replay_publishes_each_frames_labels_under_its_seq_and_stamp() -> None:
    ns, port = "gt_wire", free_tcp_port()
    client = zenoh.open(build_config(loopback_options(ns, port, listen_self=True)))
    got: dict[str, list] = {"gt": [], "points": []}
    lock = threading.Lock()

    subs = [client.declare_subscriber(keys.groundtruth(ns), collector(got, lock, "gt", GroundTruthObjects)),
            client.declare_subscriber(keys.points(ns), collector(got, lock, "points", PointCloud))]
    svc = ReplayService(loopback_options(ns, port), "points")
    try:
        assert svc.wait_for_subscribers(10)
        with open_source("synthetic:parking-street", SourceOptions(duration_s=0.5)) as src:
            stats = svc.replay(src, ReplayPlan(rate=None, stamps="wall"))
        assert wait_until(lambda: len(got["points"]) == stats.published == 5 and len(got["gt"]) == 5, 10)
    finally:
        svc.close()
        for s in subs:
            s.undeclare()
        client.close()
    assert svc.counters.get("groundtruth_published") == 5
    for gt, pc in zip(sorted(got["gt"], key=lambda m: m.header.seq), sorted(got["points"], key=lambda m: m.header.seq)):
        assert (gt.header.seq, gt.header.stamp) == (pc.header.seq, pc.header.stamp)  # re-stamped like the scan
        assert gt.header.frame_id == "map" and len(gt.objects) > 10
        parked = [o for o in gt.objects if o.attribute == "vehicle.parked"]
        assert parked and not any(o.moving for o in parked)
        assert all(math.hypot(o.velocity.x, o.velocity.y) > 0.3 for o in gt.objects if o.attribute == "vehicle.moving")


@pytest.mark.skipif(not NUSC.is_dir(), reason="../shared/data/nuscenes-scene-0523 absent")
def test_a_nuscenes_scene_carries_its_annotations_on_every_key_frame() -> None:
    with open_source(str(NUSC)) as src:
        frames = list(src.frames())
    assert all(f.truth is not None for f in frames)
    n = [len(f.truth.objects) for f in frames]
    assert min(n) > 5
    attrs = {o.attribute for f in frames for o in f.truth.objects}
    assert "vehicle.parked" in attrs


@pytest.mark.parametrize("bad", [
    {"objects": [{"instance_id": "1", "label": 9, "moving": False}]},
    {"objects": [{"instance_id": "", "label": 1, "moving": False}]},
    {"objects": [{"instance_id": "x" * 65, "label": 1, "moving": False}]},
    {"objects": [{"instance_id": "1", "label": 1}]},  # motion truth is required
    {"objects": [{"instance_id": "1", "label": 1, "moving": True, "velocity": {"x": float("nan")}}]},
])
def test_malformed_ground_truth_is_rejected_naming_the_field(bad) -> None:
    import msgpack

    payload = msgpack.packb({"schema_version": 1, "header": {"stamp": 1, "frame_id": "map", "seq": 0}, **bad})
    with pytest.raises(DecodeError, match="objects"):
        decode(GroundTruthObjects, payload)
    ok = GroundTruthObjects.model_validate({"header": {"stamp": 1}, "objects": [
        {"instance_id": "1", "label": 1, "moving": True}]})
    assert decode(GroundTruthObjects, encode(ok)) == ok
