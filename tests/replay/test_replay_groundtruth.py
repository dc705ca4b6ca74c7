"""`--level detections` on a nuScenes dataroot: the scene's annotated boxes through the detection-level noise
model, frame for frame what the offline evaluator (`eval --nuscenes --input gt-noise`) feeds its tracker."""

from __future__ import annotations

import pytest

from jitterguard.eval.groundtruth import load_nuscenes_frames
from jitterguard.schemas import encode
from jitterguard.services.replay.frames import DetectionFrame, SourceError
from jitterguard.services.replay.sources import SourceOptions, open_source, probe_source
from jitterguard.sim.detection_model import DetectionModel, NoiseConfig
from jitterguard.sim.export import export_scenario
from jitterguard.sim.world import make_scenario


@pytest.fixture(scope="module")
def dataroot(tmp_path_factory):
    root = tmp_path_factory.mktemp("nusc") / "root"
    export_scenario(make_scenario("parking-street", 3, duration_s=2.0, rate_hz=2.0), str(root), seed=3)
    return root


def test_nuscenes_boxes_replay_as_the_evaluator_sees_them(dataroot):
    src = open_source(str(dataroot), SourceOptions(level="detections", seed=5))
    assert src.info.kind == "detections"
    items = list(src.frames())
    _, gt = load_nuscenes_frames(dataroot)
    assert len(items) == len(gt) >= 3 and all(isinstance(i, DetectionFrame) for i in items)
    model = DetectionModel(NoiseConfig(), 5)
    for item, frame in zip(items, gt):
        want = model.detect(frame).detections
        assert item.stamp_ns == frame.stamp_ns
        assert [encode(o) for o in item.objects] == [encode(o) for o in want.objects]
    assert sum(len(i.objects) for i in items) > 0
    hidden = sum(int((f.num_points < 1).sum()) for f in gt)
    assert all(f.points_counted for f in gt) and f"the {hidden} without a LiDAR return are never detected" in src.info.notes[0]
    # a second pass draws the same noise (a loop replays the recording, not a new one); --start skips frames
    assert [len(i.objects) for i in src.frames()] == [len(i.objects) for i in items]
    assert [i.stamp_ns for i in src.frames(2)] == [i.stamp_ns for i in items[2:]]


def test_level_detections_needs_boxes(dataroot, tmp_path):
    assert probe_source(str(dataroot), SourceOptions(level="detections")).kind == "detections"
    (tmp_path / "scans").mkdir()
    (tmp_path / "scans" / "000000.bin").write_bytes(b"\0" * 16)
    with pytest.raises(SourceError, match="needs ground-truth boxes"):
        open_source(str(tmp_path / "scans"), SourceOptions(level="detections"))
    with pytest.raises(SourceError, match="--sweeps"):
        open_source(str(dataroot), SourceOptions(level="detections", sweeps=True))


def test_a_nuscenes_scene_takes_a_seed_only_for_its_noise_model(dataroot):
    """The seed draws the detection model's noise about the boxes; the scans themselves have none to draw, nor a
    scenario's --duration or --hz (its stamps are recorded): each had been taken and ignored."""
    assert open_source(str(dataroot), SourceOptions(level="detections", seed=2)).info.kind == "detections"
    for opts, flag in ((SourceOptions(seed=2), "--seed"), (SourceOptions(level="detections", duration_s=3.0), "--duration"),
                       (SourceOptions(rate_hz=20.0), "--hz")):
        with pytest.raises(SourceError, match=f"{flag} does not apply to a nuScenes source"):
            open_source(str(dataroot), opts)
