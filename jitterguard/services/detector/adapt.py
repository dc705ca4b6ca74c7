"""Adapting synthetic-trained weights to a real sensor without labels (``jitterguard adapt``).

A user points the detector at their own unlabelled recordings; three label-free steps fit it to them:

1. **Normalisation statistics** (AdaBN): every BatchNorm layer's running mean and variance are recomputed on
   the real scans (cumulative average over all of them, the network in train mode, no gradients). Real scans
   differ from synthetic ones in density, height and intensity statistics, and a BatchNorm fitted to the
   synthetic statistics shifts every feature the head reads.
2. **Self-training** on pseudo-labels: the adapted model's confident detections on the real scans become
   boxes of pseudo-labelled samples (:attr:`~.config.Sample.pseudo`), trained together with labelled synthetic
   scans for a few epochs, for ``rounds`` rounds (pseudo-labels redrawn with the improved model each round).
   Pseudo-labels train the heatmap only — where objects are and where they are not — never the regression and
   variance heads (trained on a model's own boxes the variances would collapse); the synthetic scans keep
   those honest. The BatchNorm statistics are recomputed on the real scans after every round. Optionally
   (``--propagate``, :func:`propagate_static`) the pseudo-labels of static objects are carried to the scans of
   the same posed recording where the model missed them.
3. **Recalibration.** By default (``adapt --recalibration synthetic``) the CLI refits the adapted network's
   variance scales per score bin on labelled synthetic scans after these steps
   (:func:`~.train_cli.fit_synthetic_recalibration`), which holds on real scans. Optionally
   (``--recalibration tracked``, :attr:`AdaptConfig.recalibrate`), from tracked residuals: where the recordings carry
   ego poses, confident detections are associated over time in the world frame; the residuals of each track
   about a constant-position (or constant-velocity) fit, rotated back into the sensor axes and divided by the
   predicted σ, give per-axis variance scales. This measures the frame-to-frame scatter the classifier's
   z-test relies on; an error that stays the same over a whole track (a box consistently too far back) is not
   seen, so coverage against labels stays below nominal (docs/detector.md: 0.49 against the synthetic
   refit's 0.65 on scene-0523).

Nothing here reads a label: recordings are opened with the replay's readers (nuScenes: scenes, samples,
sample_data, poses and calibration only — never ``sample_annotation``). The scans used are named in the
adapted weights' metadata. The data: :class:`UnlabelledScan` (points in the sensor frame, the sensor's world
pose, where it came from).
"""

from __future__ import annotations

import hashlib
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray
from torch import nn

from .augment import points_in_boxes
from .config import CLASS_NAMES, SELF_CROP_M, Detections3D, Sample
from .flips import check_symmetric, merge_mirrored, mirrored_views
from .ground import GroundPlane, boxes_to_scan_frame, boxes_to_trained_frame, scan_ground, to_trained_frame
from .inference import crop_box
from .network import CenterPointNet

log = logging.getLogger(__name__)

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]

DEFAULT_PSEUDO_THRESHOLDS: tuple[float, ...] = (0.5, 0.5, 0.5, 0.4, 0.4)
"""Minimum score of a pseudo-label per class (car, truck, bus, bicycle, pedestrian)."""


@dataclass(frozen=True)
class UnlabelledScan:
    """One real scan: ``points`` (P, 4) x, y, z, intensity (0–255) in the sensor frame, the sensor's ``pose`` in
    the world (4×4, identity when the recording has none), the recording it came from and its file."""

    points: F32
    pose: F64
    source: str
    name: str
    has_pose: bool


def read_unlabelled(specs: Sequence[str], *, max_scans: int | None = None,
                    progress: Callable[[int], None] | None = None) -> list[UnlabelledScan]:
    """Every scan of each recording in ``specs`` (any SOURCE the replay reads: a nuScenes dataroot — every scene
    —, a folder of KITTI ``.bin`` scans or one file, PCD, bags), points picked and intensities scaled as the
    detector service does (:func:`~.adapter.points_from_fields`: KITTI-style reflectance in 0…1 becomes 0…255).
    Raises :class:`~..replay.frames.SourceError` naming the recording. ``progress`` is called with 1 per scan read
    (a real recording's scans take minutes to read: a caller's progress bar)."""
    # the replay's readers (and through them rosbags, PCD) load only when scans are read, not when the CLI starts
    from ..replay.frames import IDENTITY, ScanFrame, SourceError
    from ..replay.sources import SourceOptions, open_source
    from ..replay.sources.nuscenes import _load_table, consistent_tables, find_version, is_nuscenes_root
    from .adapter import points_from_fields

    out: list[UnlabelledScan] = []
    for spec in specs:
        path = Path(spec)
        # the absolute path names the recording in the metadata, so eval-detector can tell adapted-on scans
        name = str(path.resolve()) if path.exists() else spec
        scenes: list[str | None] = [None]
        if path.exists() and is_nuscenes_root(path):
            folder = path / find_version(path, None)
            with consistent_tables(folder):
                scenes = [s["name"] for s in _load_table(folder, "scene")]
        for scene in scenes:
            src = open_source(spec, SourceOptions(scene=scene))
            n_before = len(out)
            for item in src.frames():
                if not isinstance(item, ScanFrame):
                    raise SourceError(f"{spec}: {item}")
                pts, _ = points_from_fields(np.asarray(item.points), item.fields)
                out.append(UnlabelledScan(pts, item.pose.matrix(), name if scene is None else f"{name}#{scene}",
                                          Path(item.origin).name, item.pose != IDENTITY))
                if progress is not None:
                    progress(1)
                if max_scans is not None and len(out) >= max_scans:
                    return out
            if len(out) == n_before:
                raise SourceError(f"{spec}: no scans read")
    return out


def describe(scans: Sequence[UnlabelledScan]) -> list[dict[str, Any]]:
    """What the weights' metadata records about the scans used: per recording its count and a digest of the
    file names (the names themselves when few)."""
    groups: dict[str, list[str]] = {}
    for s in scans:
        groups.setdefault(s.source, []).append(s.name)
    out = []
    for src, names in groups.items():
        rec: dict[str, Any] = {"recording": src, "scans": len(names),
                               "names_sha1": hashlib.sha1("\n".join(names).encode()).hexdigest()[:12]}
        if len(names) <= 50:
            rec["names"] = names
        out.append(rec)
    return out


# --------------------------------------------------------------------------------------------------------
# 1. normalisation statistics


@torch.no_grad()
def recompute_norm_stats(model: CenterPointNet, scans: Sequence[F32], batch_size: int = 2,
                         progress: Callable[[int], None] | None = None) -> int:
    """AdaBN: reset every BatchNorm's running statistics and re-estimate them as the cumulative average over
    ``scans`` (sensor-frame points) with the network in train mode; returns the number of batches used. The
    model is left in eval mode."""
    bns = [m for m in model.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)]
    saved = [m.momentum for m in bns]
    for m in bns:
        m.reset_running_stats()
        m.momentum = None  # cumulative moving average
    model.train()
    nf = model.config.num_point_features
    n = 0
    try:
        for i in range(0, len(scans), batch_size):
            chunk = scans[i:i + batch_size]
            model([torch.from_numpy(np.ascontiguousarray(p[:, :nf], np.float32)) for p in chunk])
            n += 1
            if progress:
                progress(len(chunk))
    finally:
        for m, mom in zip(bns, saved):
            m.momentum = mom
        model.eval()
    return n


# --------------------------------------------------------------------------------------------------------
# 2. pseudo-labels


def pseudo_samples(scans: Sequence[UnlabelledScan], detections: Sequence[Detections3D],
                   thresholds: Sequence[float] = DEFAULT_PSEUDO_THRESHOLDS, min_points: int = 3) -> list[Sample]:
    """Pseudo-labelled samples: each scan with its detections scoring at least ``thresholds[class]`` and
    holding at least ``min_points`` returns as boxes (``pseudo=True``: heatmap targets only)."""
    out = []
    thr = np.asarray(thresholds, np.float64)
    for k, (scan, det) in enumerate(zip(scans, detections, strict=True)):
        keep = det.scores >= thr[det.labels] if len(det) else np.zeros(0, bool)
        boxes = det.boxes[keep].astype(np.float32)
        counts = points_in_boxes(scan.points, boxes).sum(axis=0) if len(boxes) else np.zeros(0, np.int64)
        ok = counts >= min_points
        out.append(Sample(points=scan.points, boxes=boxes[ok], labels=det.labels[keep][ok].astype(np.int64),
                          num_points=counts[ok].astype(np.int64), token=f"pseudo/{scan.source}/{k}", pseudo=True))
    return out


def propagate_static(pseudo: Sequence[Sample], scans: Sequence[UnlabelledScan], grounds: Sequence[GroundPlane], *,
                     gate_m: float = 1.0, min_scans: int = 3, min_points: int = 1) -> tuple[list[Sample], int]:
    """Pseudo-labels carried over time to the scans where the model missed them: in each recording with ego poses,
    every pseudo-label is placed in the world; a place where one class was pseudo-labelled in ``min_scans`` or more
    scans, every time within ``gate_m`` of the place's running mean, is a static object, and its box (the first
    one's size and heading at the members' median centre) is put back into every other scan of the recording
    that holds at least ``min_points`` returns inside it and no pseudo-label within ``gate_m`` — the frames where
    the object was hidden, far or seen from a worse side, which are the examples the model lacks. Moving objects
    never stay at one place, so they are not carried; a scan without a pose keeps its own labels only. The boxes
    stay heatmap targets (``pseudo``), as every pseudo-label. Returns the samples and the number of boxes added.

    ``scans`` hold the points in the trained frame that ``grounds`` describe (:func:`~.ground.to_trained_frame`, as
    :meth:`~.inference.Detector.detect` moves a scan): x and y are the sensor's, z the height over the scan's road
    less the trained sensor height."""
    by_source: dict[str, list[int]] = {}
    for k, scan in enumerate(scans):
        if scan.has_pose:
            by_source.setdefault(scan.source, []).append(k)
    extra: dict[int, list[tuple[F64, int]]] = {}  # per scan: static boxes in the world to carry there, class
    for ks in by_source.values():
        places: list[dict[str, Any]] = []  # class, member world centres, their sum, their scans, the first box
        grid: dict[tuple[int, int, int], list[int]] = {}  # (class, cell of the place's mean): places, cells gate_m wide

        def cell(label: int, xy: F64) -> tuple[int, int, int]:
            return label, math.floor(xy[0] / gate_m), math.floor(xy[1] / gate_m)

        for k in ks:
            sample, pose = pseudo[k], scans[k].pose
            if not len(sample.boxes):
                continue
            world = _boxes_to_world(boxes_to_scan_frame(sample.boxes.astype(np.float64), grounds[k]), pose)
            for box, label in zip(world, sample.labels.tolist()):
                c = cell(label, box[:2])
                near = [i for dx in (-1, 0, 1) for dy in (-1, 0, 1) for i in grid.get((label, c[1] + dx, c[2] + dy), ())
                        if k not in places[i]["scans"]]
                d, i = min(((math.dist(places[i]["sum"] / len(places[i]["xyz"]), box[:2]), i) for i in near),
                           default=(math.inf, -1))
                if d < gate_m:
                    q = places[i]
                    before = cell(label, q["sum"] / len(q["xyz"]))
                    q["xyz"].append(box[:3])
                    q["sum"] = q["sum"] + box[:2]
                    q["scans"].add(k)
                    after = cell(label, q["sum"] / len(q["xyz"]))
                    if after != before:  # the mean crossed into another cell: file the place there
                        grid[before].remove(i)
                        grid.setdefault(after, []).append(i)
                else:
                    grid.setdefault(c, []).append(len(places))
                    places.append({"label": label, "xyz": [box[:3]], "sum": box[:2].copy(), "scans": {k}, "box": box})
        for q in places:
            if len(q["scans"]) < min_scans:
                continue
            box = q["box"].copy()
            box[:3] = np.median(np.asarray(q["xyz"]), axis=0)
            box[7:9] = 0.0  # static: no velocity
            for k in ks:
                if k not in q["scans"]:
                    extra.setdefault(k, []).append((box, q["label"]))
    out, added = [], 0
    for k, sample in enumerate(pseudo):
        if k not in extra:
            out.append(sample)
            continue
        world = np.stack([b for b, _ in extra[k]])
        boxes = boxes_to_trained_frame(_boxes_from_world(world, scans[k].pose), grounds[k]).astype(np.float32)
        labels = np.asarray([lab for _, lab in extra[k]], np.int64)
        counts = points_in_boxes(scans[k].points, boxes).sum(axis=0)
        taken = sample.boxes[:, :2].astype(np.float64) if len(sample.boxes) else np.zeros((0, 2))
        free = np.array([not len(taken) or np.min(np.hypot(*(taken - b[:2]).T)) >= gate_m for b in boxes])
        keep = (counts >= min_points) & free
        if not keep.any():
            out.append(sample)
            continue
        added += int(keep.sum())
        out.append(replace(sample, boxes=np.concatenate([sample.boxes, boxes[keep]]),
                           labels=np.concatenate([sample.labels, labels[keep]]),
                           num_points=np.concatenate([sample.num_points, counts[keep].astype(np.int64)])))
    return out, added


def _boxes_to_world(boxes: F64, pose: F64) -> F64:
    """Boxes of a scan's sensor frame in the world of its pose (centre rotated and moved, heading turned)."""
    out = boxes.copy()
    out[:, :3] = boxes[:, :3] @ pose[:3, :3].T + pose[:3, 3]
    out[:, 6] = boxes[:, 6] + np.arctan2(pose[1, 0], pose[0, 0])
    return out


def _boxes_from_world(boxes: F64, pose: F64) -> F64:
    """The inverse of :func:`_boxes_to_world`."""
    out = boxes.copy()
    out[:, :3] = (boxes[:, :3] - pose[:3, 3]) @ pose[:3, :3]
    out[:, 6] = boxes[:, 6] - np.arctan2(pose[1, 0], pose[0, 0])
    return out


class Mixed(Sequence[Sample]):
    """Pseudo-labelled real samples repeated ``repeat`` times, then labelled synthetic ones: one epoch of
    self-training sees both (the loader shuffles)."""

    def __init__(self, real: Sequence[Sample], synthetic: Sequence[Sample], repeat: int) -> None:
        self.real, self.synthetic, self.repeat = real, synthetic, max(1, repeat)

    def __len__(self) -> int:
        return len(self.real) * self.repeat + len(self.synthetic)

    def __getitem__(self, i: Any) -> Any:
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        n_real = len(self.real) * self.repeat
        return self.real[i % len(self.real)] if i < n_real else self.synthetic[i - n_real]


# --------------------------------------------------------------------------------------------------------
# 3. recalibration from tracked residuals


@dataclass(frozen=True)
class TrackedResiduals:
    """Residuals of tracked detections about their track's fit, in each detection's sensor axes: ``z2`` (N, 2)
    squared residuals over predicted variances, ``dof`` the degrees of freedom they carry (Σ n − p over
    tracks), and how many tracks and detections went in."""

    z2_sum: F64
    dof: float
    num_tracks: int
    num_detections: int

    @property
    def scales(self) -> tuple[float, float]:
        s = self.z2_sum / max(self.dof, 1e-9)
        return float(s[0]), float(s[1])


def tracked_residuals(frames: Sequence[tuple[Detections3D, F64]], *, min_score: float = 0.4, gate_m: float = 1.5,
                      min_hits: int = 4, static_speed: float = 1.0) -> TrackedResiduals:
    """Associate confident detections over a sequence of (detections, sensor pose 4×4) in the world frame
    (greedy nearest neighbour per class within ``gate_m`` of each track's predicted position), then fit every
    track of ≥ ``min_hits`` detections: a constant position if its fitted speed is below ``static_speed`` m/s
    (p = 1 parameter per axis), else a constant velocity (p = 2; frames are taken as equally spaced). Each
    residual is rotated into its own frame's sensor axes and divided by its predicted σ²."""
    tracks: list[dict[str, Any]] = []
    for k, (det, pose) in enumerate(frames):
        if det.log_variances is None:
            raise ValueError("tracked recalibration needs predicted variances")
        sel = np.flatnonzero(det.scores >= min_score)
        xyz = _boxes_to_world(det.boxes[sel].astype(np.float64), pose)[:, :3]
        live = [t for t in tracks if t["last"] == k - 1 or t["last"] == k - 2]
        taken: set[int] = set()
        pairs = []
        for ti, t in enumerate(live):
            pred = _predict(t["frames"], t["xy"], k)
            for j, d in enumerate(sel):
                if det.labels[d] != t["label"]:
                    continue
                dist = float(np.hypot(*(xyz[j, :2] - pred)))
                if dist < gate_m:
                    pairs.append((dist, ti, j))
        used_t: set[int] = set()
        for dist, ti, j in sorted(pairs):
            if ti in used_t or j in taken:
                continue
            used_t.add(ti)
            taken.add(j)
            t = live[ti]
            t["xy"].append(xyz[j, :2])
            t["frames"].append(k)
            t["rows"].append(int(sel[j]))
            t["last"] = k
        for j, d in enumerate(sel):
            if j not in taken:
                tracks.append({"label": int(det.labels[d]), "xy": [xyz[j, :2]], "frames": [k], "rows": [int(d)],
                               "last": k})
    z2 = np.zeros(2)
    dof = 0.0
    n_tracks = n_det = 0
    for t in tracks:
        n = len(t["frames"])
        if n < min_hits:
            continue
        f = np.asarray(t["frames"], np.float64)
        xy = np.asarray(t["xy"])
        a = np.column_stack([np.ones(n), f - f.mean()])
        coef, *_ = np.linalg.lstsq(a, xy, rcond=None)
        dt = 0.5  # nuScenes key frames: speed only decides static vs moving, so the exact rate matters little
        p = 2 if float(np.hypot(*coef[1])) / dt >= static_speed else 1
        fit = a[:, :p] @ np.linalg.lstsq(a[:, :p], xy, rcond=None)[0]
        res_w = xy - fit
        for r_w, k, row in zip(res_w, t["frames"], t["rows"]):
            det, pose = frames[k]
            rot = pose[:2, :2]
            r_s = rot.T @ r_w  # world → this frame's sensor axes (the sensor is upright to within degrees)
            z2 += r_s ** 2 / np.exp(det.log_variances[row, :2].astype(np.float64))
        dof += n - p
        n_tracks += 1
        n_det += n
    return TrackedResiduals(z2, dof, n_tracks, n_det)


def _predict(frames: list[int], xy: list[F64], k: int) -> F64:
    """Where a track should be at frame ``k``: its last position while short, else its least-squares constant
    velocity line over all its detections (one noisy step must not throw the prediction off)."""
    if len(frames) < 3:
        return xy[-1]
    f = np.asarray(frames, np.float64)
    a = np.column_stack([np.ones(len(f)), f - f.mean()])
    coef, *_ = np.linalg.lstsq(a, np.asarray(xy), rcond=None)
    return coef[0] + coef[1] * (k - f.mean())


# --------------------------------------------------------------------------------------------------------
# the whole adaptation


@dataclass
class AdaptConfig:
    """Settings of :func:`adapt` (``jitterguard adapt`` flags)."""

    rounds: int = 2
    epochs: int = 2
    batch_size: int = 2
    lr: float = 5e-4
    seed: int = 0
    thresholds: tuple[float, ...] = DEFAULT_PSEUDO_THRESHOLDS
    real_repeat: int = 2
    recalibrate: bool = True
    min_tracks: int = 5
    self_crop: tuple[float, float, float, float] | None = SELF_CROP_M
    """The vehicle's own body, dropped from every real scan first (None keeps it), as the service drops it."""
    flips: bool = False
    """Pseudo-label (and fit the tracked recalibration) with the network averaged over each scan's mirror images
    (:mod:`.flips`): clutter that one view mistakes for a car is diluted before it becomes a label."""
    sensor_height_m: float | None = None
    """Height of the real scans' frame above the road (None: measured in each scan, :mod:`.ground`): the scans are
    moved to the height the network was trained at before anything else, as the service moves them."""
    sensor_tilt: bool = True
    """Take each real scan's road slope out as well (measured, :mod:`.ground`), as the service does."""
    propagate: bool = False
    """Carry pseudo-labels of static objects to the scans of the same recording where the model missed them
    (recordings with ego poses; :func:`propagate_static`)."""
    propagate_min_scans: int = 3
    """Scans a place must be pseudo-labelled in before it counts as a static object and is carried."""


def adapt(model: CenterPointNet, scans: Sequence[UnlabelledScan], synthetic: Sequence[Sample], cfg: AdaptConfig,
          out_dir: Path, *, augment: Any = None, progress: bool = True) -> dict[str, Any]:
    """Run the three steps on ``model`` in place (see the module doc); returns a report: per round the number
    of pseudo-labels per class, and the recalibration fitted (or why none was)."""
    from .decode import decode
    from .train import TrainConfig, progress_bar, train

    def bar(desc: str) -> Any:  # a bar per step over the real scans, as train draws its own (None: no bar)
        return progress_bar(progress, len(scans), unit="scan", desc=desc)

    def norm_stats(desc: str) -> None:
        b = bar(desc)
        recompute_norm_stats(model, pts, progress=b.update if b is not None else None)
        if b is not None:
            b.close()

    def detect_all(desc: str) -> list[Detections3D]:
        b = bar(desc)
        out = _detect_all(model, pts, decode, flips=cfg.flips, progress=b.update if b is not None else None)
        if b is not None:
            b.close()
        return out

    pcr = model.config.point_cloud_range
    # the scans as the detector would see them: in range, and without the vehicle's own body (a roof return
    # pseudo-labelled "car" in every scan would teach the ghost the service's self-crop exists to prevent)
    cropped = [crop_box(s.points, cfg.self_crop) for s in scans]
    grounds = [scan_ground(p, cfg.sensor_height_m, cfg.sensor_tilt) for p in cropped]
    pts = [_in_range(to_trained_frame(p, g), pcr) for p, g in zip(cropped, grounds)]
    scans = [replace(s, points=p) for s, p in zip(scans, pts)]
    report: dict[str, Any] = {"rounds": []}
    norm_stats("BatchNorm statistics")
    for r in range(cfg.rounds):
        dets = detect_all(f"round {r + 1}: pseudo-labels")
        pseudo = pseudo_samples(scans, dets, cfg.thresholds)
        carried = None
        if cfg.propagate:
            pseudo, carried = propagate_static(pseudo, scans, grounds, min_scans=cfg.propagate_min_scans)
            log.info("round %d: %d pseudo-labels carried to scans where the model missed a static object", r + 1,
                     carried)
        counts = np.bincount(np.concatenate([p.labels for p in pseudo]) if pseudo else np.zeros(0, np.int64),
                             minlength=len(CLASS_NAMES))
        log.info("round %d: pseudo-labels %s", r + 1, dict(zip(CLASS_NAMES, counts.tolist())))
        data = Mixed(pseudo, synthetic, cfg.real_repeat)
        tcfg = TrainConfig(epochs=cfg.epochs, batch_size=cfg.batch_size, lr=cfg.lr, seed=cfg.seed + r,
                           pct_start=0.3)
        train(model, data, [], tcfg, out_dir / f"round{r + 1}", augment=augment, progress=progress)
        model.cpu()
        norm_stats(f"round {r + 1}: BatchNorm statistics")
        report["rounds"].append({"pseudo_labels": dict(zip(CLASS_NAMES, counts.tolist())),
                                 "samples": len(data), **({"carried": carried} if carried is not None else {})})
    report["recalibration"] = None
    if cfg.recalibrate and model.config.uncertainty:
        dets = detect_all("tracked recalibration")
        by_source: dict[str, list[tuple[Detections3D, F64]]] = {}
        for s, d in zip(scans, dets):
            if s.has_pose:
                by_source.setdefault(s.source, []).append((d, s.pose))
        pooled = np.zeros(2)
        dof, nt, nd = 0.0, 0, 0
        for seq in by_source.values():
            tr = tracked_residuals(seq)
            pooled += tr.z2_sum
            dof += tr.dof
            nt += tr.num_tracks
            nd += tr.num_detections
        if nt >= cfg.min_tracks:
            s2 = pooled / dof
            report["recalibration"] = {"scales": [float(s2[0]), float(s2[1])], "tracks": nt, "detections": nd,
                                       "dof": dof, "fit_on": "tracked residuals (no labels)"}
        else:
            report["recalibration_skipped"] = (f"{nt} tracks of >= 4 detections in recordings with poses; need"
                                               f" {cfg.min_tracks}")
    return report


def _in_range(points: F32, pcr: Sequence[float]) -> F32:
    p = points
    keep = ((p[:, 0] >= pcr[0]) & (p[:, 0] < pcr[3]) & (p[:, 1] >= pcr[1]) & (p[:, 1] < pcr[4])
            & (p[:, 2] >= pcr[2]) & (p[:, 2] < pcr[5]))
    return np.ascontiguousarray(p[keep], np.float32)


@torch.no_grad()
def _detect_all(model: CenterPointNet, pts: Sequence[F32], decode: Any, *, flips: bool = False,
                progress: Callable[[int], None] | None = None) -> list[Detections3D]:
    """The raw network's detections of each scan (no recalibration: adapt refits it); with ``flips`` averaged over
    the scan's mirror images, as the detector's ``flips`` setting does. ``progress`` is called with 1 per scan."""
    model.eval()
    if flips:
        check_symmetric(model.config)
    nf = model.config.num_point_features
    out: list[Detections3D] = []
    for p in pts:
        x = torch.from_numpy(np.ascontiguousarray(p[:, :nf], np.float32))
        raw = merge_mirrored(model(mirrored_views(x))) if flips else model([x])
        out.extend(decode(raw, model.config))
        if progress is not None:
            progress(1)
    return out

