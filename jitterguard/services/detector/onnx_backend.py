"""Run an exported detector (:mod:`.onnx_export`) with ONNX Runtime in place of the torch network.

:class:`OnnxNetwork` stands where :class:`~.network.CenterPointNet` stands in :class:`~.inference.Detector`: it
takes the same :class:`~.pillars.Pillars` and returns the same head maps, so voxelisation, decoding, NMS and the
variance recalibration are the very code the torch backend runs — the backends differ only in what evaluates
the network. The ``autoware`` layout runs its two graphs with the BEV scatter between them on the host, as
Autoware's ``lidar_centerpoint`` does.

onnxruntime is an optional dependency, imported when a model is opened.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .config import SELF_CROP_M, DetectorConfig
from .evaluate import Recalibration
from .inference import Detector, WeightsError, config_from_dict
from .onnx_export import FORMAT, FORMAT_VERSION, MANIFEST, head_widths, bev_scatter, output_names, padded_point_features
from .pillars import PillarFeatureNet, Pillars, pillar_features

BACKENDS = ("torch", "onnxruntime")
LAYOUT_GRAPHS: dict[str, tuple[str, ...]] = {"single": ("detector",), "autoware": ("voxel_encoder", "backbone_neck_head")}
"""The graphs (the manifest's ``graphs`` keys) each layout runs."""


def _session(path: Path, threads: int | None) -> Any:
    try:
        import onnxruntime as ort
    except ImportError:
        raise WeightsError("the onnxruntime backend needs the 'onnxruntime' package (pip install 'jitterguard[onnx]')") from None
    opts = ort.SessionOptions()
    # idle ORT workers sleep instead of spinning, as OpenMP's do for torch (cli.passive_openmp): on cores shared
    # with the tracker, classifier and this process's own decode, a spinning pool steals the CPU they need
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    if threads:
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
    try:
        return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    except Exception as exc:  # noqa: BLE001 - ORT raises its own exception types for bad files
        raise WeightsError(f"{path}: onnxruntime cannot load it ({type(exc).__name__}: {exc})") from None


def read_manifest(model_dir: str | Path) -> dict[str, Any]:
    """``detector.json`` of an export folder, checked (format, files present and matching their sha256)."""
    d = Path(model_dir)
    path = d / MANIFEST
    if not path.is_file():
        raise WeightsError(f"{d}: no {MANIFEST} (export one with `jitterguard export-onnx --out {d}`)")
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise WeightsError(f"{path}: not readable JSON ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT or doc.get("format_version") != FORMAT_VERSION:
        raise WeightsError(f"{path}: not a {FORMAT} v{FORMAT_VERSION} manifest")
    # the graphs the layout runs, each named with its file: a manifest whose graphs do not fit its layout (edited by
    # hand, or another layout's) had escaped as a KeyError or AttributeError traceback from `jitterguard detector`
    layout, graphs = doc.get("layout"), doc.get("graphs")
    if layout not in LAYOUT_GRAPHS:
        raise WeightsError(f"{path}: unknown layout {layout!r} (expected one of {', '.join(LAYOUT_GRAPHS)})")
    want = LAYOUT_GRAPHS[layout]
    if not isinstance(graphs, dict) or set(graphs) != set(want):
        got = sorted(graphs) if isinstance(graphs, dict) else type(graphs).__name__
        raise WeightsError(f"{path}: layout {layout!r} has the graphs {', '.join(want)}, the manifest lists {got}")
    if not all(isinstance(g, dict) for g in graphs.values()):
        raise WeightsError(f"{path}: every entry of 'graphs' must be an object with its file and sha256")
    if not isinstance(doc.get("meta") or {}, dict):  # a list there had ended `detector` in a TypeError traceback
        raise WeightsError(f"{path}: 'meta' must be an object")
    for name, graph in graphs.items():
        f = d / str(graph.get("file", ""))
        if not f.is_file():
            raise WeightsError(f"{path}: graph {name!r} file {f.name} is missing")
        if hashlib.sha256(f.read_bytes()).hexdigest() != graph.get("sha256"):
            raise WeightsError(f"{f}: sha256 does not match {MANIFEST} (a partial copy or a different export)")
    return doc


class OnnxNetwork:
    """The network of an export folder under ONNX Runtime, with :class:`~.network.CenterPointNet`'s inference
    interface (``config``, ``eval()``, ``forward_pillars``)."""

    def __init__(self, model_dir: str | Path, *, threads: int | None = None) -> None:
        self.dir = Path(model_dir)
        self.manifest = read_manifest(self.dir)
        if not isinstance(self.manifest.get("config"), dict):
            raise WeightsError(f"{self.dir / MANIFEST}: its config is {type(self.manifest.get('config')).__name__},"
                               " not an object")
        try:
            self.config: DetectorConfig = config_from_dict(self.manifest["config"])
        except WeightsError as exc:
            raise WeightsError(f"{self.dir / MANIFEST}: {exc}") from None
        self.layout = str(self.manifest["layout"])
        graphs = self.manifest["graphs"]
        self._names = list(output_names(self.config))
        if self.layout == "single":
            self._net = _session(self.dir / graphs["detector"]["file"], threads)
        elif self.layout == "autoware":
            self._encoder = _session(self.dir / graphs["voxel_encoder"]["file"], threads)
            self._head = _session(self.dir / graphs["backbone_neck_head"]["file"], threads)
            self._features = PillarFeatureNet(self.config)  # its weightless point_features only
        else:
            raise WeightsError(f"{self.dir / MANIFEST}: unknown layout {self.layout!r}")
        self._check_graphs()
        try:
            self.recalibration = Recalibration.of(self.manifest.get("recalibration") or None)
        except (ValueError, TypeError, KeyError, OverflowError) as exc:  # OverflowError: a 400-digit integer
            raise WeightsError(f"{self.dir / MANIFEST}: bad recalibration entry: {exc}") from None

    def _check_graphs(self) -> None:
        """The graphs take and give what the manifest's config says: the outputs the config names, the point
        fields, the pillar channels and the grid. ``detector.json`` is not among the checksummed files, so a config
        edited there (another grid, no variance heads, five point fields) had loaded and then failed scan by scan
        in ONNX Runtime, or published detections without their variances."""
        c = self.config
        nx, ny = c.grid_size
        fx, fy = c.feature_map_size
        maps = {n: [1, w, fy, fx] for n, w in head_widths(c).items()}
        if self.layout == "single":
            expect = {"detector": (self._net, {"points": [None, c.num_point_features]}, maps)}
        else:
            expect = {"voxel_encoder": (self._encoder, {"input_features": [None, None, pillar_features(c)]},
                                        {"pillar_features": [None, c.pfn_channels]}),
                      "backbone_neck_head": (self._head, {"spatial_features": [1, c.pfn_channels, ny, nx]}, maps)}
        for graph, (sess, inputs, outputs) in expect.items():
            have_in = {i.name: i.shape for i in sess.get_inputs()}
            have_out = {o.name: o.shape for o in sess.get_outputs()}
            if list(have_out) != list(outputs):
                raise WeightsError(f"{self.dir / MANIFEST}: graph {graph!r} gives {', '.join(have_out)}; its config"
                                   f" wants {', '.join(outputs)}")
            for kind, have, want in (("input", have_in, inputs), ("output", have_out, outputs)):
                for name, shape in want.items():
                    got = have.get(name)
                    if got is None or len(got) != len(shape) or any(
                            w is not None and isinstance(g, int) and g != w for g, w in zip(got, shape, strict=True)):
                        raise WeightsError(f"{self.dir / MANIFEST}: graph {graph!r} {kind} {name!r} is {got}; its"
                                           f" config wants {['?' if w is None else w for w in shape]}")

    def eval(self) -> "OnnxNetwork":
        return self

    def forward_pillars(self, p: Pillars) -> dict[str, Tensor]:
        """Head maps for one scan's pillars (batch size 1), as torch tensors for :func:`~.decode.decode`."""
        if p.batch_size != 1:
            raise ValueError(f"the ONNX graphs take one scan at a time, got a batch of {p.batch_size}")
        if self.layout == "single":
            outs = self._net.run(self._names, {"points": p.points.numpy(), "pillar": p.pillar.numpy(),
                                               "num_points": p.num_points.numpy(), "coords": p.coords.numpy()})
        else:
            if len(p.num_points):
                feats = padded_point_features(p, self._features, self.config.max_points_per_pillar)
                (pillar_feats,) = self._encoder.run(["pillar_features"], {"input_features": feats.numpy()})
            else:  # no pillar (every return out of range or cropped): an empty canvas, as the torch path scatters
                # (an encoder exported before its channel count was spelt out gives (0, 2) for no pillar)
                pillar_feats = np.zeros((0, self.config.pfn_channels), np.float32)
            canvas = bev_scatter(torch.from_numpy(pillar_feats), p.coords, self.config)
            outs = self._head.run(self._names, {"spatial_features": np.ascontiguousarray(canvas.numpy())})
        return {n: torch.from_numpy(o) for n, o in zip(self._names, outs, strict=True)}


def load_onnx_detector(model_dir: str | Path, *, threads: int | None = None, score_threshold: float | None = None,
                       recalibrate: bool = True, self_crop: Sequence[float] | None = SELF_CROP_M,
                       flips: bool = False, sensor_height_m: float | None = None, sensor_tilt: bool = True
                       ) -> Detector:
    """A :class:`~.inference.Detector` whose network runs under ONNX Runtime (recalibration from the manifest;
    ``flips``, ``sensor_height_m`` and ``sensor_tilt`` as in :class:`~.inference.Detector`)."""
    net = OnnxNetwork(model_dir, threads=threads)
    return Detector(net, recalibration=net.recalibration if recalibrate else None,  # type: ignore[arg-type]
                    score_threshold=score_threshold, threads=threads, self_crop=self_crop, flips=flips,
                    sensor_height_m=sensor_height_m, sensor_tilt=sensor_tilt, meta={**dict(net.manifest.get("meta") or {}), "backend": "onnxruntime", "layout": net.layout})


def open_onnx_detector(model_dir: str | Path | None, weights: str | Path | None, preset: str | None, *,
                       threads: int | None = None, score_threshold: float | None = None,
                       self_crop: Sequence[float] | None = SELF_CROP_M, flips: bool = False,
                       sensor_height_m: float | None = None, sensor_tilt: bool = True) -> Detector:
    """The onnxruntime-backed detector the service runs: from an export folder, or — without one — the torch
    weights (``weights`` / ``preset``, as :meth:`Detector.load` picks them) exported into a temporary folder first
    (needs onnx + onnxscript; the folder is removed as soon as ONNX Runtime has loaded it: a service stopped by a
    signal before its handlers are installed — while it waits for the router — had left it in the temp folder)."""
    if model_dir is not None:
        return load_onnx_detector(model_dir, threads=threads, score_threshold=score_threshold, self_crop=self_crop,
                                  flips=flips, sensor_height_m=sensor_height_m, sensor_tilt=sensor_tilt)
    import atexit
    import logging
    import shutil
    import tempfile

    from .onnx_export import ExportError, export_onnx

    src = Detector.load(weights, preset, threads=threads)
    tmp = tempfile.mkdtemp(prefix="jitterguard-onnx-")
    atexit.register(shutil.rmtree, tmp, ignore_errors=True)
    logging.getLogger(__name__).info("exporting %s to ONNX in %s for the onnxruntime backend", src.config.name, tmp)
    try:
        try:
            export_onnx(src.model, tmp, recalibration=src.recalibration, meta=src.meta)
        except ExportError as exc:
            raise WeightsError(str(exc)) from None
        # ONNX Runtime holds the graphs in memory once the sessions are made: the files are not read again
        return load_onnx_detector(tmp, threads=threads, score_threshold=score_threshold, self_crop=self_crop,
                                  flips=flips, sensor_height_m=sensor_height_m, sensor_tilt=sensor_tilt)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
