"""Ground-truth boxes through the detection-level noise model: ``--level detections`` for any source that has
boxes (the synthetic world, a nuScenes scene's annotations).

Why: the noise model (:mod:`jitterguard.sim.detection_model`) gives detections whose errors and predicted
variances are known, so the tracker and classifier can be watched live on real trajectories (nuScenes) exactly
as the offline evaluator runs them (``jitterguard eval --input gt-noise``). The model is seeded and starts
afresh on every pass, so pass k of a loop sees the same noise as pass 1, like a recording would.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from ..frames import DetectionFrame, EgoPose, Item, SourceError, SourceInfo
from ..truth import truth_message
from .base import Source


def noisy_detections(frame_at: Callable[[int], Any], num_frames: int, seed: int, start: int,
                     origin: str) -> Iterator[Item]:
    """One pass of ``DetectedObjects`` from ground-truth frames ``frame_at(0..num_frames-1)`` from ``start`` on,
    each with its labels for ``jg/{ns}/groundtruth`` (viewers only; nothing in the pipeline reads them).

    Every frame is drawn from the model, also those before ``start``, so a ``--start`` window sees the same noise
    as a full pass.
    """
    from ....sim.detection_model import DetectionModel, NoiseConfig  # the simulator is an optional area

    model = DetectionModel(NoiseConfig(), seed)
    for i in range(num_frames):
        gt = frame_at(i)
        det = model.detect(gt).detections
        if i < start:
            continue
        p = det.ego_pose
        pose = EgoPose(p.position.x, p.position.y, p.position.z, p.orientation.x, p.orientation.y, p.orientation.z,
                       p.orientation.w)
        yield DetectionFrame(int(gt.stamp_ns), pose, list(det.objects), f"{origin}#{i}", det.header.frame_id,
                             truth=truth_message(gt))


class NuScenesBoxes(Source):
    """A nuScenes scene's annotated boxes (every key frame) as noisy detections at the LIDAR_TOP pose."""

    def __init__(self, dataroot: Path, *, scene: str | None = None, seed: int = 0, version: str | None = None) -> None:
        from ....eval.groundtruth import NuScenesError, load_nuscenes_frames  # evaluation: an optional area

        try:
            self.scene_name, self.gt = load_nuscenes_frames(Path(dataroot), scene, version)
        except NuScenesError as exc:
            raise SourceError(str(exc)) from None
        self.seed = seed
        from ....sim.detection_model import NoiseConfig  # the simulator is an optional area

        n_boxes = sum(int(f.num_objects) for f in self.gt)
        hidden = sum(int(NoiseConfig().without_returns(f).sum()) for f in self.gt)  # the model noisy_detections runs
        self.info = SourceInfo(
            name=f"{dataroot} ({self.scene_name}, annotations)",
            kind="detections",
            num_frames=len(self.gt),
            notes=[f"nuScenes scene {self.scene_name}: {len(self.gt)} key frames, {n_boxes} boxes through the"
                   f" detection-level noise model (seed {seed}); the {hidden} without a LiDAR return are"
                   f" never detected"],
        )

    def frames(self, start: int = 0) -> Iterator[Item]:
        yield from noisy_detections(self.gt.__getitem__, len(self.gt), self.seed, start, f"nuscenes:{self.scene_name}")
