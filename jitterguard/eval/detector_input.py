"""``--input detector``: the CenterPoint detector in the evaluation loop, scan by scan as the live stack runs it.

Why through the wire messages: what is scored offline must be what the live detector publishes. Each scan is
built as the replay publishes it (:func:`~jitterguard.services.replay.adapter.point_cloud_message` of the
replay's own ``ScanFrame``: x, y, z, intensity, ring and the sensor's world pose), goes through the detector
service's steps (:func:`detect_scan`: ``scan_points`` → ``publishable_detections`` (``Detector.detect`` and the filter of what is published)) and is
converted with the service's :func:`~jitterguard.services.detector.adapter.detections_payload` into the
sensor-frame ``DetectedObjects`` the tracker receives. The tracker and classifier cores then run exactly as
for the noise model (:func:`.pipeline.track_and_classify`).

Next to every scan travels its ground truth twice: the world-frame :class:`GroundTruthFrame` that labels
tracks with motion, and the sensor-frame :class:`~jitterguard.services.detector.config.Sample` that scores the
detector's raw ``Detections3D`` (nuScenes AP, positional calibration) — the same data the detector's own
evaluation reads (``data.sample_from_scan``, ``data.nuscenes_samples``).

Scan sources are adapters (ray-casting, reading a dataroot); :func:`run_detector_pipeline` and
:func:`detection_metrics` are pure given their inputs. Deterministic: the ray-cast is seeded by (seed, frame)
and the network is a fixed function (for a fixed torch thread count).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..schemas.models import ClassifierConfig, PointCloud
from ..services.detector.config import CLASS_NAMES, Detections3D, Sample
from ..services.detector.adapter import detections_payload, publishable_detections, scan_points, scan_pose
from ..services.detector.inference import crop_box
from ..services.detector.sweeps import SweepStacker
from ..services.detector.data import sample_from_scan
from ..services.replay.frames import EgoPose, ScanFrame, finite_rows
from ..services.replay.adapter import point_cloud_message
from ..services.replay.sources.synthetic import SCAN_FIELDS
from ..services.tracker.config import TrackerConfig
from ..sim.lidar import cast_frame
from ..sim.sensors import LidarSpec, hdl32e
from ..sim.world import GroundTruthFrame, Scenario
from .groundtruth import NuScenesError
from .pipeline import MATCH_DISTANCE_M, Records, track_and_classify


@dataclass(frozen=True)
class LabelledScan:
    """One scan as the replay publishes it, with its ground truth in both frames the evaluation needs (``None``
    for a sweep between labelled key frames: it feeds the tracker and the classifier and is not scored)."""

    gt: GroundTruthFrame | None
    """World frame: labels the tracks (motion attributes, instance IDs)."""
    scan: PointCloud
    """The ``points`` message (sensor frame, the sensor's world pose as ``ego_pose``)."""
    sample: Sample | None
    """Sensor-frame boxes of the detector's classes, with LiDAR point counts: scores the detections."""


@dataclass(frozen=True)
class DetectorFrame:
    """One scan after the detector: what the tracker receives, and the raw arrays the detection metrics read."""

    gt: GroundTruthFrame | None
    detections: bytes  # the ``DetectedObjects`` payload, as the detector service puts it
    predictions: Detections3D
    sample: Sample | None


def synthetic_scans(scenario: Scenario, seed: int, sensor: LidarSpec | None = None) -> Iterator[LabelledScan]:
    """Every frame of ``scenario`` ray-cast with ``sensor`` (HDL-32E, nuScenes' LIDAR_TOP, by default).

    The ``points`` message is built as ``jitterguard replay synthetic:NAME --seed SEED`` builds it (cast seed
    = scenario seed, five columns with the ring, non-finite rows dropped, pose at the mount height; the tests
    hold the two together); header seq and stamp are the frame's. One ray-cast per frame serves the scan and
    the ground truth's point counts.
    """
    spec = sensor or hdl32e()
    for gt in scenario:
        res, frame = cast_frame(gt, spec, seed)
        pts = np.empty((res.points.shape[0], len(SCAN_FIELDS)), dtype=np.float32)
        pts[:, :4] = res.points
        pts[:, 4] = res.ring
        pts, _ = finite_rows(pts)
        pose = EgoPose.from_yaw(float(gt.ego_x), float(gt.ego_y), float(gt.ego_yaw), z=float(spec.mount_height_m))
        sf = ScanFrame(int(gt.stamp_ns), pose, pts, SCAN_FIELDS, f"synthetic:{scenario.name}#{gt.seq}", "lidar")
        yield LabelledScan(frame, point_cloud_message(sf, int(gt.seq), int(gt.stamp_ns)),
                           sample_from_scan(frame, res, spec.mount_height_m,
                                            f"synthetic/{scenario.name}/{seed}/{gt.seq}"))


def nuscenes_scans(dataroot: Path, scene: str | None, gt_frames: Sequence[GroundTruthFrame], *,
                   sweeps: bool = False, version: str | None = None) -> list[LabelledScan]:
    """The LIDAR_TOP key frames of one nuScenes scene, aligned with ``gt_frames`` (from
    :func:`.groundtruth.load_nuscenes_frames`, same scene); with ``sweeps`` every LiDAR sweep from the first
    key frame to the last, as ``jitterguard replay DATAROOT --sweeps`` publishes them, the sweeps between key
    frames unlabelled (nuScenes labels key frames only).

    Scans come from the replay's :class:`NuScenesSource` (what ``jitterguard replay DATAROOT`` publishes),
    sensor-frame ground truth from the detector's loader (:func:`~.data_nuscenes.nuscenes_samples`). All
    three walk the scene's sample chain; stamps are checked to agree, so a misalignment fails loudly instead
    of scoring one frame's detections against another's boxes. Raises :class:`NuScenesError` (one line).
    """
    # only for --nuscenes: the nuScenes readers (and the devkit they may use) are an optional extra
    from ..services.detector.data_nuscenes import nuscenes_samples
    from ..services.replay.frames import FrameError, SourceError
    from ..services.replay.sources.nuscenes import NuScenesSource

    try:
        src = NuScenesSource(Path(dataroot), scene=scene, sweeps=sweeps, version=version)
        samples = nuscenes_samples(dataroot, src.version, scene_names=[src.scene_name])
        items = list(src.frames())
    except SourceError as exc:
        raise NuScenesError(" ".join(str(exc).split())) from None
    bad = [it for it in items if isinstance(it, FrameError)]
    if bad:
        raise NuScenesError(f"{len(bad)} LIDAR_TOP scan(s) unreadable, first: {bad[0]}")
    if not len(samples) == len(gt_frames) or not (sweeps or len(items) == len(gt_frames)):
        raise NuScenesError(f"{dataroot}: {len(items)} scans, {len(samples)} labelled samples and "
                            f"{len(gt_frames)} ground-truth frames do not line up")
    labelled = {int(gt.stamp_ns): (gt, sample) for gt, sample in zip(gt_frames, samples)}
    out = []
    for seq, sf in enumerate(items):
        assert isinstance(sf, ScanFrame)
        gt, sample = labelled.get(int(sf.stamp_ns), (None, None))
        if gt is None and not sweeps:
            raise NuScenesError(f"{dataroot}: scan stamp {sf.stamp_ns} is no ground-truth frame's")
        # the stream's own count, as the replay numbers what it publishes (a key frame's seq counts key frames)
        out.append(LabelledScan(gt, point_cloud_message(sf, seq if sweeps else int(gt.seq), int(sf.stamp_ns)),
                                sample))
    found = sum(ls.gt is not None for ls in out)
    if found != len(gt_frames):
        raise NuScenesError(f"{dataroot}: {len(gt_frames) - found} of {len(gt_frames)} key frames missing from "
                            "the scans' stamps")
    return out


def detect_scan(detect: Callable[[np.ndarray], Detections3D], scan: PointCloud, *,
                uncertainty: bool = True, stacker: SweepStacker | None = None,
                self_crop: Sequence[float] | None = None) -> Detections3D:
    """The detector service's per-scan steps without Zenoh (``DetectorService._on_scan`` and ``process``): the
    network's columns picked by name, non-finite points dropped, the scan — its ego's body (``self_crop``, the
    detector's box) cropped in its own frame — held by ``stacker`` and stacked with the earlier sweeps it holds (a
    model trained on stacked sweeps; :mod:`~jitterguard.services.detector.sweeps`), an empty scan gives no
    detections (the network is not run on nothing), and detections holding a non-finite number or lying beyond
    the wire's limits are dropped before publishing."""
    points, _ = scan_points(scan)
    if stacker is not None:
        rotation, translation = scan_pose(scan)
        stacker.add(scan.header.stamp, rotation, translation, crop_box(points, self_crop))
        if len(points):
            points = stacker.stack(scan.header.stamp, rotation, translation, points)
    return publishable_detections(detect, points, uncertainty=uncertainty)[0]


def detector_frames(scans: Iterable[LabelledScan], detect: Callable[[np.ndarray], Detections3D], *,
                    class_names: Sequence[str] = CLASS_NAMES, uncertainty: bool = True,
                    has_twist: bool = True, sweeps: int = 1,
                    self_crop: Sequence[float] | None = None) -> Iterator[DetectorFrame]:
    """Run ``detect`` (e.g. ``Detector.detect``) on every scan and convert as the live service does:
    the scan's header and ego pose carried over, sensor-frame boxes and variances, written as the
    ``DetectedObjects`` payload the service puts on the wire. ``sweeps`` > 1 (a model's
    :attr:`~jitterguard.services.detector.inference.Detector.sweeps`) stacks each scan with the earlier ones of
    the stream, as the live service does."""
    stacker = SweepStacker(sweeps) if sweeps > 1 else None
    for ls in scans:
        det = detect_scan(detect, ls.scan, uncertainty=uncertainty, stacker=stacker, self_crop=self_crop)
        payload = detections_payload(det, ls.scan.header, ls.scan.ego_pose, class_names, has_twist=has_twist)
        yield DetectorFrame(ls.gt, payload, det, ls.sample)


def run_detector_pipeline(frames: Iterable[DetectorFrame], classifier: ClassifierConfig | None = None,
                          tracker: TrackerConfig | None = None, match_distance_m: float = MATCH_DISTANCE_M,
                          **kwargs: Any) -> tuple[Records, list[Detections3D], list[Sample]]:
    """Tracker and classifier cores over the detector's frames; also returns every scan's raw detections and
    its sensor-frame ground truth, index-aligned, for :func:`detection_metrics`. ``kwargs`` go to
    :func:`~.pipeline.track_and_classify` (calibration to continue, variance scale, calibration file)."""
    preds: list[Detections3D] = []
    samples: list[Sample] = []

    def pairs() -> Iterator[tuple[GroundTruthFrame | None, bytes]]:
        for f in frames:
            if f.sample is not None:  # an unlabelled sweep is tracked and classified, not scored
                preds.append(f.predictions)
                samples.append(f.sample)
            yield f.gt, f.detections

    rec = track_and_classify(pairs(), classifier, tracker, match_distance_m, **kwargs)
    return rec, preds, samples


def detection_metrics(predictions: Sequence[Detections3D], samples: Sequence[Sample],
                      class_names: Sequence[str] = CLASS_NAMES) -> tuple[dict[str, Any], dict[str, Any]]:
    """(metrics.json's ``detection`` block, the full :func:`~.evaluate.evaluation_report` with PR curves for
    the figures).

    ``map`` is nuScenes' mAP over classes that have ground truth (null if none has); ``ece_pos`` the
    positional ECE in metres (paper Table I; null for a model without variance heads or with no true
    positive); per class ``ap`` (mean over the 0.5/1/2/4 m thresholds, null without ground truth) with the
    per-threshold APs and the TP/FP/FN counts at 2 m.
    """
    from ..services.detector.evaluate import evaluation_report

    rep = evaluation_report(predictions, samples, include_curves=True)
    cal = rep["calibration"]
    block: dict[str, Any] = {
        "map": rep["detection"]["mAP"],
        "ece_pos": cal["ece"] if cal else None,
        "ece_x": cal["axes"]["x"]["ece"] if cal else None,
        "ece_y": cal["axes"]["y"]["ece"] if cal else None,
        "nll_pos": cal["nll"] if cal else None,
        "coverage_1sigma": cal["coverage_1sigma"] if cal else None,
        "coverage_2sigma": cal["coverage_2sigma"] if cal else None,
        "num_matched": cal["num_matched"] if cal else None,
        "num_samples": rep["num_samples"],
    }
    for name in class_names:
        c = rep["detection"]["classes"][name]
        block[name] = {"ap": c["mean_ap"], "ap_by_threshold_m": c["ap"], "num_gt": c["num_gt"],
                       "num_pred": c["num_pred"], "tp": c["tp"], "fp": c["fp"], "fn": c["fn"]}
    return block, rep
