"""Run a trained detector on one scan; load and save weight files.

A weight file is a plain dict saved with ``torch.save``: ``{"format": 1, "config": {...}, "state_dict": {...},
"recalibration": [s2_x, s2_y] | {"scales": [[s2_x, s2_y], …], "score_edges": […]} | None, "meta": {...}}``
(the variance scales per detection-score bin, :class:`~.evaluate.Recalibration`). It holds only tensors and builtins so that it loads
with ``torch.load(weights_only=True)`` — no pickled code runs when a file is opened. The package ships the
``lite`` weights (``weights/lite.pt``); presets without shipped weights start from random initialisation,
loudly.
"""

from __future__ import annotations

import io
import logging
import os
import pickle
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from pydantic import ValidationError

from ...files import write_atomically
from .config import PRESETS, SELF_CROP_M, DetectorConfig, Detections3D, check_crop_box
from .decode import decode
from .evaluate import Recalibration, apply_recalibration
from .flips import check_symmetric, merge_mirrored, mirrored_views
from .ground import TRAINED_SENSOR_HEIGHT_M, GroundPlane, boxes_to_scan_frame, ground_of, ground_plane, to_trained_frame
from .network import CenterPointNet
from .pillars import voxelize
from .sweeps import stack_sweeps, sweeps_of

log = logging.getLogger(__name__)

WEIGHTS_DIR = Path(__file__).with_name("weights")
FORMAT = 1


class WeightsError(ValueError):
    """A weight file that cannot be used (missing, wrong format, or not matching its config)."""


def shipped_weights(preset: str) -> Path:
    """Where the package keeps the weights of ``preset`` (may not exist)."""
    return WEIGHTS_DIR / f"{preset}.pt"


def config_to_dict(config: DetectorConfig) -> dict[str, Any]:
    return config.model_dump(mode="json")


def config_from_dict(d: dict[str, Any]) -> DetectorConfig:
    unknown = set(d) - set(DetectorConfig.model_fields)
    if unknown:
        raise WeightsError(f"weights config has unknown fields {sorted(unknown)}")
    try:
        return DetectorConfig.model_validate(d)
    except ValidationError as exc:
        err = exc.errors(include_url=False)[0]
        raise WeightsError(f"weights config: {'.'.join(map(str, err['loc']))}: {err['msg']}") from None


def save_weights(path: str | Path, model: CenterPointNet, *,
                 recalibration: Recalibration | tuple[float, float] | None = None,
                 meta: dict[str, Any] | None = None) -> None:
    """Write ``model`` as a weights-only file (fp32 state dict + config + optional variance recalibration)."""
    state = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
    rec = Recalibration.of(recalibration)
    payload = {"format": FORMAT, "config": config_to_dict(model.config), "state_dict": state,
               "recalibration": rec.to_payload() if rec else None, "meta": meta or {}}
    atomic_save(payload, path)


def atomic_save(obj: Any, path: str | Path) -> None:
    """``torch.save`` of ``obj`` to ``path`` through :func:`~jitterguard.files.write_atomically`: a save that fails
    or is interrupted (disk full, a killed job) leaves the previous file whole instead of a truncated one (weights
    and training checkpoints are the result of hours of work)."""
    buf = io.BytesIO()
    torch.save(obj, buf)
    write_atomically(path, buf.getvalue())


def load_refusal(exc: Exception) -> str:
    """Why ``torch.load(weights_only=True)`` refused a file, in a few words. torch's own message runs to
    paragraphs and, for any file that is not plain tensors (a text file, a raw scan, a pickled object), advises
    loading it with ``weights_only=False`` — running whatever code the file holds: advice not to pass on."""
    if isinstance(exc, pickle.UnpicklingError) or "weights_only" in str(exc):
        return "torch.load finds no plain tensors in it"
    return f"{type(exc).__name__}: {' '.join(str(exc).split()).split('. ')[0][:160]}"


def load_weights(path: str | Path) -> tuple[CenterPointNet, Recalibration | None, dict[str, Any]]:
    """Load a weights file (``weights_only=True``) → (model in eval mode, recalibration, meta)."""
    p = Path(path)
    if not p.is_file():
        raise WeightsError(f"{p}: no such weights file")
    try:
        payload = torch.load(str(p), map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - torch raises many types for a bad file
        raise WeightsError(f"{p}: not a jitterguard detector weights file ({load_refusal(exc)})") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT or "state_dict" not in payload:
        raise WeightsError(f"{p}: not a jitterguard detector weights file (format {FORMAT})")
    # each entry's type checked before it is used: a file without a config, or whose state dict or meta is no dict,
    # had escaped as a KeyError or TypeError traceback (eval-detector blamed --flips for one)
    for key, optional in (("config", False), ("state_dict", False), ("meta", True)):
        if not isinstance(payload.get(key), dict) and not (optional and payload.get(key) is None):
            raise WeightsError(f"{p}: not a jitterguard detector weights file (its {key!r} is"
                               f" {type(payload.get(key)).__name__}, not a dict)")
    config = config_from_dict(payload["config"])
    model = CenterPointNet(config)
    try:
        model.load_state_dict(payload["state_dict"])
    except RuntimeError as exc:
        raise WeightsError(f"{p}: weights do not match their config: {exc}") from None
    model.eval()
    try:
        rec = Recalibration.of(payload.get("recalibration") or None)
    except (ValueError, TypeError, KeyError) as exc:
        raise WeightsError(f"{p}: bad recalibration entry: {exc}") from None
    return model, rec, dict(payload.get("meta") or {})


def crop_box(points: np.ndarray, box: Sequence[float] | None) -> np.ndarray:
    """``points`` without the rows whose x, y lie strictly inside ``box`` (x_min, y_min, x_max, y_max); all of
    them when ``box`` is None."""
    if box is None or len(points) == 0:
        return points
    x, y = points[:, 0], points[:, 1]
    inside = (x > box[0]) & (x < box[2]) & (y > box[1]) & (y < box[3])
    return points if not inside.any() else points[~inside]


class Detector:
    """A detector ready for inference on single scans (sensor frame in, sensor frame out)."""

    def __init__(self, model: CenterPointNet, *, recalibration: Recalibration | tuple[float, float] | None = None,
                 score_threshold: float | None = None, threads: int | None = None,
                 meta: dict[str, Any] | None = None, self_crop: Sequence[float] | None = SELF_CROP_M,
                 device: str | torch.device = "cpu", flips: bool = False,
                 sensor_height_m: float | None = None, sensor_tilt: bool = True) -> None:
        """``self_crop``: returns inside this (x_min, y_min, x_max, y_max) box of the sensor frame are the
        vehicle's own body and never reach the network (:data:`~.config.SELF_CROP_M`; None keeps them).
        ``device``: where voxelisation and the network run (``cuda`` on a GPU machine; decoding and NMS stay on
        the CPU, where the boxes are needed). ``flips``: average the network over the scan and its three mirror
        images (:mod:`.flips`; about four times the network's time). ``sensor_height_m``: the scans' frame's
        height above the road (None: measured in every scan, :mod:`.ground`); ``sensor_tilt``: take the road
        plane's slope out of every scan (measured; false: the frame is level). Scans are moved to the level frame
        and height the network was trained at and the boxes back."""
        self.self_crop = check_crop_box(self_crop)
        self.device = torch.device(device)
        if self.device.type != "cpu":  # (the ONNX Runtime stand-in for the network is CPU-only and has no .to)
            model = model.to(self.device)
        self.model = model.eval()
        self.config = model.config
        if flips:
            check_symmetric(self.config)
        self.flips = flips
        self.recalibration = Recalibration.of(recalibration)
        self.score_threshold = score_threshold
        self.meta = meta or {}
        self.sweeps = sweeps_of(self.config.num_point_features, self.meta)
        """Sweeps the network was trained on (1 for a four-field model): what a caller stacks
        (:class:`~.sweeps.SweepStacker`) before :meth:`detect`."""
        self.sensor_height_m = sensor_height_m
        self.sensor_tilt = sensor_tilt
        self.ground_last = GroundPlane(TRAINED_SENSOR_HEIGHT_M if sensor_height_m is None else sensor_height_m)
        """The road plane the latest scan was taken to have (the declared height or the latest estimate, its slope
        measured or none: a scan too bare to measure keeps the one before)."""
        self.plane_measured: GroundPlane | None = None
        """The plane measured in the latest scan (None: none found there, or nothing to measure:
        :attr:`measures_ground`)."""
        self.timings: dict[str, float] = {}
        torch.set_num_threads(threads or os.cpu_count() or 1)

    @classmethod
    def load(cls, weights: str | Path | None = None, preset: str | None = "lite", *, threads: int | None = None,
             score_threshold: float | None = None, recalibrate: bool = True,
             self_crop: Sequence[float] | None = SELF_CROP_M, device: str | torch.device = "cpu",
             flips: bool = False, sensor_height_m: float | None = None, sensor_tilt: bool = True) -> "Detector":
        """``weights`` if given; else the shipped weights of ``preset``; else a randomly initialised ``preset``
        (logged as a warning — its detections are meaningless). ``recalibrate`` applies the file's fitted
        per-axis variance scales when it has them; ``self_crop``, ``flips``, ``sensor_height_m`` and ``sensor_tilt``
        as in the constructor."""
        if weights is None and preset is not None and shipped_weights(preset).is_file():
            weights = shipped_weights(preset)
        if weights is not None:
            model, rec, meta = load_weights(weights)
            return cls(model, recalibration=rec if recalibrate else None, score_threshold=score_threshold,
                       threads=threads, meta=meta, self_crop=self_crop, device=device, flips=flips,
                       sensor_height_m=sensor_height_m, sensor_tilt=sensor_tilt)
        if preset not in PRESETS:
            raise WeightsError(f"unknown preset {preset!r}; expected one of {', '.join(PRESETS)}")
        log.warning("no weights for preset %r: using a randomly initialised network", preset)
        torch.manual_seed(0)
        return cls(CenterPointNet(PRESETS[preset]), score_threshold=score_threshold, threads=threads,
                   meta={"random_init": True}, self_crop=self_crop, device=device, flips=flips,
                   sensor_height_m=sensor_height_m, sensor_tilt=sensor_tilt)

    @property
    def measures_ground(self) -> bool:
        """Whether every scan's road plane is measured (an ``auto`` height or tilt)."""
        return self.sensor_height_m is None or self.sensor_tilt

    @torch.inference_mode()
    def detect(self, points: np.ndarray) -> Detections3D:
        """Detections of one scan: ``points`` (P, ≥4) float32 x, y, z, intensity (0–255) in the sensor frame (and
        the time lag in seconds as a fifth column for a model trained on stacked sweeps: :mod:`.sweeps`; a scan
        without it is the newest sweep alone, lag 0), whose origin is :attr:`sensor_height_m` above the road
        (None: measured); the boxes come back in the same frame."""
        t0 = time.perf_counter()
        nf = self.config.num_point_features
        if nf == 5 and points.shape[1] == 4:
            points = stack_sweeps(points, ())
        points = crop_box(points, self.self_crop)
        plane = self.plane_measured = ground_plane(points) if self.measures_ground else None
        ground = self.ground_last = ground_of(plane, self.sensor_height_m, self.sensor_tilt, self.ground_last)
        points = to_trained_frame(points, ground)
        pts = torch.from_numpy(np.ascontiguousarray(points[:, :nf], dtype=np.float32)).to(self.device)
        views = mirrored_views(pts) if self.flips else [pts]
        pillars = [voxelize([v], self.config) for v in views]  # one scan per call: an ONNX export takes batch 1
        self._sync()
        t1 = time.perf_counter()
        outs = [self.model.forward_pillars(p) for p in pillars]
        out = merge_mirrored({k: torch.cat([o[k] for o in outs]) for k in outs[0]}) if self.flips else outs[0]
        self._sync()
        t2 = time.perf_counter()
        det = decode(out, self.config, self.score_threshold)[0]
        if self.recalibration is not None and det.log_variances is not None:
            det = apply_recalibration(det, self.recalibration)
        if len(det):
            det = replace(det, boxes=boxes_to_scan_frame(det.boxes, ground))
        t3 = time.perf_counter()
        self.timings = {"voxelize": (t1 - t0) * 1e3, "network": (t2 - t1) * 1e3, "decode": (t3 - t2) * 1e3}
        return det

    def _sync(self) -> None:
        """Wait for the GPU, so that the stage timings are the stages' and not the kernel launches'."""
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
