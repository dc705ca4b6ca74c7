"""The offline pipeline: ground-truth frames → detections → tracker core → classifier cores.

Detections come from the detection-level noise model (:func:`run_pipeline`, ``--input gt-noise``) or from the
CenterPoint detector on ray-cast / recorded scans (:mod:`.detector_input`, ``--input detector``); both hand
(ground truth, ``DetectedObjects``) pairs to :func:`track_and_classify`.

Why in-process and through the same functions as the services: what is measured offline must be what runs
live. Each frame goes through exactly the services' seams — the ``detections`` payload read by
:func:`~jitterguard.schemas.read_detected_objects` into the tracker core through the tracker's adapter, the
``tracks/{id}`` and ``tracked`` payloads it writes fed, as bytes, to two :class:`ClassifierAdapter` s (z-test and
velocity threshold) exactly as the classifier service feeds its own. Both see the identical payloads, so their
comparison is not confounded by tracking.

Pure: frames in, a :class:`Records` table out; no files, no clock. Deterministic given ``seed``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment  # type: ignore[import-untyped]

from ..geometry import nearest_within
from ..schemas import DetectedColumns, decode, encode, read_detected_objects, wire
from ..schemas.models import ClassifierConfig, DetectedObjects, MotionState, TrackedObjects
from ..services.bridge.joiner import FrameJoiner, JoinedFrame
from ..services.replay.truth import truth_message
from ..services.classifier.adapter import ClassifierAdapter, FrameOutput
from ..services.classifier.calibration import NoiseModel, OnlineCalibration
from ..services.tracker.adapter import detection_frame, observation_payloads, tracked_payload
from ..services.tracker.config import TrackerConfig, default_config
from ..services.tracker.core import FrameRejected, TrackerCore
from ..sim.detection_model import DetectionModel, NoiseConfig
from ..sim.world import GroundTruthFrame
from .groundtruth import group_of, is_dynamic

VARIANCE_SCALE_AT = ("detector", "classifier")
"""Where ``--variance-scale`` applies: the detector's output (the tracker sees it too) or the classifier's input."""

MATCH_DISTANCE_M = 2.0
"""A track is the ground-truth object whose centre is within this distance (optimal one-to-one per frame)."""

NOISE_PRESETS: dict[str, Callable[[], NoiseConfig]] = {
    "clean": NoiseConfig.clean,
    "jittery": NoiseConfig.jittery,
    "paper": NoiseConfig.paper_like,
    "oracle": NoiseConfig.oracle,  # exact variances: for ablations, never behind a headline figure
}


def match_tracks(track_xy: NDArray[np.float64], gt_xy: NDArray[np.float64],
                 max_dist: float = MATCH_DISTANCE_M) -> NDArray[np.int64]:
    """Per track, the row of its ground-truth object (−1: none within ``max_dist``).

    Hungarian assignment on centre distance, pairs farther than ``max_dist`` forbidden, so two tracks never
    share one object and a near object is not stolen by a greedy earlier track.
    """
    out = np.full(len(track_xy), -1, dtype=np.int64)
    if len(track_xy) == 0 or len(gt_xy) == 0:
        return out
    d = np.hypot(track_xy[:, None, 0] - gt_xy[None, :, 0], track_xy[:, None, 1] - gt_xy[None, :, 1])
    big = 1e6
    cost = np.where(d <= max_dist, d, big)
    rows, cols = linear_sum_assignment(cost)
    ok = cost[rows, cols] < big
    out[rows[ok]] = cols[ok]
    return out


NOTHING_LABELLED = "nothing labelled"
"""What a ghost track stands on when no labelled object is near it (``Records.ghost_on``)."""


@dataclass
class Records:
    """One row per (frame, observed track): the tracker/classifier outputs and the matched ground truth.

    ``z`` is max(z_x, z_y) of the z-test core (with ``mode: chi2``, the normal score of its χ², :func:`chi2_as_z`),
    0 where the jump veto called a rejecting window static (``vetoed``): the veto does not depend on α, so a vetoed
    row is static at every α, and AP, α sweeps and ``matched`` score the decisions the classifier makes (below the
    deployed α they count a window the veto never examined as unvetoed); ``speed`` the tracker's speed (what the velocity-threshold rule
    reads, against its per-class ``speed_threshold``); ``state_z`` / ``state_v`` the two cores' decisions
    (0 undecided, 1 static, 2 dynamic). ``group`` is the matched object's evaluation group, '' for tracks
    matched to no ground truth (ghosts: scored as static truth in ``ghost.*`` by ``track_group``, the group
    of the track's own label); ``gt_attribute`` / ``gt_speed`` the matched object's attribute and speed;
    ``ghost_on`` what a ghost track stands on (:func:`ghost_footing`), '' for a matched one.
    """

    t_s: NDArray[np.float64]
    seq: NDArray[np.int64]
    track_id: NDArray[np.str_]
    label: NDArray[np.int64]
    z: NDArray[np.float64]
    speed: NDArray[np.float64]
    window: NDArray[np.int64]
    state_z: NDArray[np.int8]
    state_v: NDArray[np.int8]
    gt_instance: NDArray[np.int64]
    gt_dynamic: NDArray[np.bool_]
    group: NDArray[np.str_]
    alpha: NDArray[np.float64]
    velocity_threshold: float
    min_window: int
    gt_attribute: NDArray[np.str_] = field(default_factory=lambda: np.empty(0, dtype="U32"))
    gt_speed: NDArray[np.float64] = field(default_factory=lambda: np.empty(0))
    speed_threshold: NDArray[np.float64] = field(default_factory=lambda: np.empty(0))
    track_group: NDArray[np.str_] = field(default_factory=lambda: np.empty(0, dtype="U12"))
    window_size: int = 10
    window_stride: int = 1  # the window took every k-th frame (a stream faster than window_reference_hz)
    vetoed: NDArray[np.bool_] = field(default_factory=lambda: np.empty(0, dtype=bool))
    ghost_on: NDArray[np.str_] = field(default_factory=lambda: np.empty(0, dtype="U40"))

    def __post_init__(self) -> None:
        """Tables built without the planner-view columns get neutral ones: no attribute, unknown speed, the
        single velocity threshold, and the track's group taken from its match."""
        n = len(self)
        if len(self.gt_attribute) != n:
            self.gt_attribute = np.full(n, "", dtype="U32")
        if len(self.gt_speed) != n:
            self.gt_speed = np.full(n, np.nan)
        if len(self.speed_threshold) != n:
            self.speed_threshold = np.full(n, float(self.velocity_threshold))
        if len(self.track_group) != n:
            self.track_group = np.asarray(self.group, dtype="U12").copy()
        if len(self.vetoed) != n:
            self.vetoed = np.zeros(n, dtype=bool)
        if len(self.ghost_on) != n:
            self.ghost_on = np.where(self.gt_instance < 0, NOTHING_LABELLED, "").astype("U40")

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    def subset(self, mask: NDArray[np.bool_]) -> "Records":
        """The rows where ``mask`` holds (scalars kept)."""
        kw = {k: (v[mask] if isinstance(v, np.ndarray) else v) for k, v in self.__dict__.items()}
        return Records(**kw)  # type: ignore[arg-type]


def ghost_footing(track_xy: NDArray[np.float64], matched: NDArray[np.int64], gt: GroundTruthFrame
                  ) -> NDArray[np.str_]:
    """What each track matched to no object stands on: the nearest labelled object that is no road user
    (``gt.unscored``: nuScenes' barriers, cones, debris) within :data:`~jitterguard.geometry.STANDS_ON_M`, else
    :data:`NOTHING_LABELLED`; '' for a matched track. A ghost pedestrian on a pile of debris is a real static
    obstacle the detector named wrongly — calling it static is right — where one on nothing is a phantom."""
    out = np.full(len(matched), "", dtype="U40")
    ghost = matched < 0
    names = [u[0] for u in gt.unscored]
    near = nearest_within(track_xy[ghost], [u[1:] for u in gt.unscored])
    out[ghost] = [names[j] if j >= 0 else NOTHING_LABELLED for j in near.tolist()]
    return out


def _id_factory() -> Callable[[], str]:
    """Deterministic 32-hex track IDs (the live tracker's are random UUIDs; the evaluator must repeat)."""
    counter = iter(range(1, 1 << 62))
    return lambda: f"{next(counter):032x}"


def run_pipeline(frames: Iterable[GroundTruthFrame], noise: NoiseConfig, seed: int,
                 classifier: ClassifierConfig | None = None, tracker: TrackerConfig | None = None,
                 match_distance_m: float = MATCH_DISTANCE_M,
                 progress: Callable[[Iterable[GroundTruthFrame]], Iterable[GroundTruthFrame]] | None = None,
                 calibration: OnlineCalibration | None = None, variance_scale: float = 1.0,
                 calibration_model: NoiseModel | None = None, variance_scale_at: str = "detector",
                 on_frame: Callable[[JoinedFrame], None] | None = None) -> Records:
    """Run GT → DetectionModel → TrackerCore → MotionClassifierCore (the test — z_test, or chi2 where ``classifier``
    says so — and velocity_threshold).

    ``classifier`` supplies alpha / window / velocity threshold; its ``mode`` is overridden per core.
    ``progress`` wraps the frame iterable (e.g. tqdm) — the caller's choice, so this stays I/O-free. The other
    arguments as in :func:`track_and_classify`.
    """
    det_model = DetectionModel(noise, seed)
    it = progress(frames) if progress is not None else frames
    return track_and_classify(((gt, encode(det_model.detect(gt).detections)) for gt in it), classifier, tracker,
                              match_distance_m, calibration=calibration, variance_scale=variance_scale,
                              calibration_model=calibration_model, variance_scale_at=variance_scale_at,
                              on_frame=on_frame)


def scale_variances(det: DetectedColumns, factor: float) -> DetectedColumns:
    """``det`` with every detection's reported position covariance (the x/y block and its cross terms with
    z / roll / pitch / yaw, so the 6×6 stays consistent) multiplied by ``factor``: a detector off by a
    constant factor (``jitterguard eval --variance-scale``). ``factor`` 0: no covariance reported at all —
    ``has_position_covariance`` false and every entry 0, as Autoware's lidar_centerpoint publishes its boxes."""
    if factor == 1.0:
        return det
    objects = wire.DETECTED.copy(det.objects)
    if factor == 0.0:
        objects[wire.POSE_COV]["v"] = 0.0
        objects[wire.HAS_POSITION_COV] = 0xC2  # msgpack false, as the record stores a bool
        return replace(det, objects=objects)
    cov = objects[wire.POSE_COV]["v"]
    for i in range(6):
        for j in range(6):
            k = (i < 2) + (j < 2)
            if k:
                cov[:, 6 * i + j] *= factor if k == 2 else math.sqrt(factor)
    return replace(det, objects=objects)


def track_and_classify(inputs: Iterable[tuple[GroundTruthFrame | None, bytes]],
                       classifier: ClassifierConfig | None = None, tracker: TrackerConfig | None = None,
                       match_distance_m: float = MATCH_DISTANCE_M, *, calibration: OnlineCalibration | None = None,
                       variance_scale: float = 1.0, calibration_model: NoiseModel | None = None,
                       variance_scale_at: str = "detector",
                       on_frame: Callable[[JoinedFrame], None] | None = None) -> Records:
    """TrackerCore → MotionClassifierCore (the test — z_test, or chi2 where ``classifier`` says so — and
    velocity_threshold) over (ground truth, detections) pairs.

    The detections are the ``DetectedObjects`` payloads that feed the live tracker — the noise model's output as
    the replay publishes it, or the detector service's — so both ``--input`` modes share everything from here on;
    the ground truth (world frame) only labels the tracks; a frame without one (``None``: a sweep between
    labelled key frames) is tracked and classified like any other, and not scored. ``classifier``'s ``mode`` is
    overridden per core.

    ``calibration``: the online calibration to continue (pooled recordings of one drive share it; it is
    updated in place); ``variance_scale`` multiplies every reported variance — at the detector's output, so
    the tracker sees it too (``variance_scale_at="detector"``, :func:`scale_variances`), or only in the
    ``tracks/{id}`` payloads the classifier receives (``"classifier"``: the classifier's own invariance, with
    identical tracks); ``calibration_model``: the scales for ``calibration: file``; ``on_frame`` receives every
    decided frame as the bridges see it (:func:`join_frame`: detections, tracks, the z-test's objects and
    motion states, ground truth), e.g. to record it to MCAP.
    """
    if variance_scale_at not in VARIANCE_SCALE_AT:
        raise ValueError(f"variance_scale_at must be one of {VARIANCE_SCALE_AT}, got {variance_scale_at!r}")
    at_detector = variance_scale if variance_scale_at == "detector" else 1.0
    at_classifier = variance_scale if variance_scale_at == "classifier" else 1.0
    base = classifier or ClassifierConfig()
    trk = TrackerCore(tracker or default_config(), _id_factory())
    limits = trk.config.limits
    test_mode = scored_test(base)
    adapter_z = ClassifierAdapter(base.model_copy(update={"mode": test_mode}), limits=limits,
                                  calibration_model=calibration_model, calibration=calibration)
    # the baseline reads only speeds: it needs no calibration
    adapter_v = ClassifierAdapter(base.model_copy(update={"mode": "velocity_threshold", "calibration": "off"}),
                                  limits=limits)
    joiner = FrameJoiner() if on_frame is not None else None
    cols: dict[str, list] = {k: [] for k in ("t_s", "seq", "track_id", "label", "z", "speed", "window", "state_z",
                                             "state_v", "gt_instance", "gt_dynamic", "group", "alpha",
                                             "gt_attribute", "gt_speed", "speed_threshold", "track_group", "vetoed",
                                             "ghost_on")}
    t0: int | None = None
    for gt, payload in inputs:
        det = scale_variances(read_detected_objects(payload, limits), at_detector)
        if t0 is None:  # the run's clock starts at its first frame, labelled or not
            t0 = gt.stamp_ns if gt is not None else int(det.header.stamp)
        frame = detection_frame(det)
        try:
            result = trk.step(frame)
        except FrameRejected:
            continue
        observations = [p for _, p in observation_payloads(scale_variances(det, at_classifier), frame, result)]
        closing = tracked_payload(det, frame, result)
        now_s = frame.stamp_ns * 1e-9
        oz, ov = (_classify(a, observations, closing, now_s) for a in (adapter_z, adapter_v))
        if oz is None or ov is None or oz.decided is None or ov.decided is None or gt is None:
            continue
        if joiner is not None and on_frame is not None:
            for joined in join_frame(joiner, gt, payload, closing, oz, adapter_z):
                on_frame(joined)
        obs, dz, dv = oz.observed, oz.decided, ov.decided
        where = {t.encode(): k for k, t in enumerate(result.tracks.ids)}
        rows = np.array([where[t] for t in obs.track_ids.tolist()], dtype=np.intp)
        txy = np.column_stack([result.tracks.x[rows], result.tracks.y[rows]])
        gi = match_tracks(txy, gt.centers[:, :2], match_distance_m)
        n = len(obs)
        cols["t_s"].append(np.full(n, (gt.stamp_ns - t0) * 1e-9))
        cols["seq"].append(np.full(n, gt.seq))
        cols["track_id"].append(obs.track_ids.astype("U32"))
        cols["label"].append(obs.labels.astype(np.int64))
        score = np.maximum(dz.z_x, dz.z_y) if test_mode == "z_test" else chi2_as_z(dz.chi2)
        cols["z"].append(np.where(dz.vetoed, 0.0, score))  # a vetoed window is static at every α
        cols["vetoed"].append(dz.vetoed.astype(bool))
        cols["speed"].append(np.asarray(obs.speed, dtype=np.float64))
        cols["window"].append(dz.window_length.astype(np.int64))
        cols["state_z"].append(dz.state.astype(np.int8))
        cols["state_v"].append(dv.state.astype(np.int8))
        cols["alpha"].append(dz.alpha.astype(np.float64))
        inst = np.where(gi >= 0, gt.instance_ids[np.maximum(gi, 0)] if gt.num_objects else -1, -1)
        cols["gt_instance"].append(inst.astype(np.int64))
        cols["gt_dynamic"].append(np.array(
            [is_dynamic(gt.attributes[g], bool(gt.moving[g])) if g >= 0 else False for g in gi.tolist()],
            dtype=bool))
        cols["group"].append(np.array(
            [(group_of(int(gt.labels[g])) or "") if g >= 0 else "" for g in gi.tolist()], dtype="U12"))
        cols["gt_attribute"].append(np.array([gt.attributes[g] if g >= 0 else "" for g in gi.tolist()], dtype="U32"))
        gspeed = np.hypot(gt.velocities[:, 0], gt.velocities[:, 1]) if gt.num_objects else np.zeros(0)
        cols["gt_speed"].append(np.where(gi >= 0, gspeed[np.maximum(gi, 0)] if gt.num_objects else 0.0, np.nan))
        cols["speed_threshold"].append(dv.threshold.astype(np.float64))
        cols["track_group"].append(np.array([group_of(int(lb)) or "" for lb in obs.labels.tolist()], dtype="U12"))
        cols["ghost_on"].append(ghost_footing(txy, gi, gt))

    if joiner is not None and on_frame is not None:
        for joined in joiner.flush():
            on_frame(joined)

    def cat(k: str, dtype: Any) -> np.ndarray:
        return np.concatenate(cols[k]).astype(dtype) if cols[k] else np.empty(0, dtype=dtype)

    return Records(
        t_s=cat("t_s", np.float64), seq=cat("seq", np.int64), track_id=cat("track_id", "U32"),
        label=cat("label", np.int64), z=cat("z", np.float64), speed=cat("speed", np.float64),
        window=cat("window", np.int64), state_z=cat("state_z", np.int8), state_v=cat("state_v", np.int8),
        gt_instance=cat("gt_instance", np.int64), gt_dynamic=cat("gt_dynamic", bool), group=cat("group", "U12"),
        alpha=cat("alpha", np.float64), velocity_threshold=float(base.velocity_threshold),
        min_window=int(base.min_window), gt_attribute=cat("gt_attribute", "U32"), gt_speed=cat("gt_speed", np.float64),
        speed_threshold=cat("speed_threshold", np.float64), track_group=cat("track_group", "U12"),
        window_size=adapter_z.core.window, window_stride=adapter_z.core.stride, vetoed=cat("vetoed", bool),
        ghost_on=cat("ghost_on", "U40"),
    )


def scored_test(config: ClassifierConfig) -> str:
    """The test the evaluator scores against the speed threshold: ``chi2`` where the config says so, else the
    paper's ``z_test`` (a config in ``velocity_threshold`` mode still has its test scored beside the baseline)."""
    return "chi2" if config.mode == "chi2" else "z_test"


def chi2_as_z(chi2: NDArray[np.float64]) -> NDArray[np.float64]:
    """The two-sided normal score with the χ²₂ value's tail probability, p = exp(−χ²/2): the ``chi2`` mode fires
    exactly where this exceeds α (its threshold is the χ²₂ quantile of P(|Z| > α)), so the records' ``z`` means
    one thing in either mode and the α sweep and PR curves score the test that decided (p floored at 1e-300:
    a χ² beyond ~1380 reads as z ≈ 37)."""
    from scipy.special import ndtri  # type: ignore[import-untyped]

    p = np.clip(np.exp(-0.5 * np.asarray(chi2, dtype=np.float64)), 1e-300, 1.0)
    return -ndtri(p / 2)


def join_frame(joiner: FrameJoiner, gt: GroundTruthFrame, detections: bytes, tracked: bytes, out: FrameOutput,
               adapter: ClassifierAdapter) -> list[JoinedFrame]:
    """Hand one evaluated frame to the live bridges' own joiner — the very payloads the services would publish:
    the detections as published (before any ``--variance-scale``), the tracker's ``tracked``, the z-test's
    ``objects`` and ``motion/{id}``, decoded by the wire's own models, plus the frame's ground truth — and return
    the frames it releases (a track not decided this frame carries its last decision, as in Foxglove live)."""
    objects = decode(TrackedObjects, out.payload)
    joiner.add_detections(decode(DetectedObjects, detections))
    joiner.add_tracked(decode(TrackedObjects, tracked))
    joiner.add_groundtruth(truth_message(gt).model_copy(
        update={"header": objects.header.model_copy(update={"frame_id": "map"})}))
    for _, payload in adapter.motion_payloads(out):
        joiner.add_motion(decode(MotionState, payload))
    joiner.add_objects(objects, 0.0)
    return joiner.poll(0.0)


def _classify(adapter: ClassifierAdapter, observations: list[bytes], closing: bytes, now_s: float
              ) -> FrameOutput | None:
    """One frame through a classifier adapter as the service runs it: the observations, then the close; every
    observation is in, so the frame is complete at once. ``now_s``: the receiver's clock, here the stream's own
    (the frame's stamp): a discontinuity the tracker has followed (a gap over ``max_stamp_step_s``, a rewind) is
    held by the classifier's stream guard until a run of frames confirms it, as live; such a frame gives None
    (with a constant clock the run never confirmed, and ``calibrate``/``eval`` died on a recording's pause)."""
    adapter.observations(observations)
    adapter.close(closing, now_s)
    ready = adapter.ready(now_s)
    if not ready:
        return None
    (frame,) = ready
    out = adapter.finish(frame)
    adapter.settle(out)
    return out


def concat_records(parts: list[Records], tags: list[str]) -> Records:
    """Pool several runs (e.g. seeds) into one table; track IDs get ``tag/`` prefixes because the evaluator's
    deterministic IDs restart in every run, and two runs' tracks must never merge."""
    if not parts:
        raise ValueError("nothing to pool")
    if len({(p.velocity_threshold, p.min_window, p.window_size, p.window_stride) for p in parts}) != 1:
        raise ValueError("pooled runs must share the classifier operating point")
    kw: dict[str, Any] = {}
    for k, v in parts[0].__dict__.items():
        if isinstance(v, np.ndarray):
            arrays = [getattr(p, k) for p in parts]
            if k == "track_id":
                arrays = [np.char.add(f"{t}/", a.astype(str)) for a, t in zip(arrays, tags)]
            kw[k] = np.concatenate(arrays)
        else:
            kw[k] = v
    return Records(**kw)
