"""Export the detector to ONNX, with its variance heads, for ONNX Runtime, TensorRT or Autoware.

Two layouts:

- ``single`` (one file, ``detector.onnx``): the network from pillars to head maps. Inputs are exactly what
  :func:`~.pillars.voxelize` returns for one scan — ``points`` (N, 4) the kept points (x, y, z, intensity/255),
  ``pillar`` (N,) int64 the pillar of each point, ``num_points`` (V,) int64 points per pillar, ``coords`` (V, 3)
  int64 (0, iy, ix) — with N and V dynamic. The pillar encoder, the scatter onto the BEV canvas, SECOND, the FPN
  and every head run inside the graph.
- ``autoware`` (two files, the split of Autoware's ``lidar_centerpoint``): ``pts_voxel_encoder.onnx`` maps
  padded per-pillar point features ``input_features`` (V, M, 9) to ``pillar_features`` (V, C), V and M dynamic
  (it reads the first ``max_points_per_pillar`` of the M slots; lidar_centerpoint binds M = 32);
  the host scatters them onto the canvas; ``pts_backbone_neck_head.onnx`` maps ``spatial_features``
  (1, C, ny, nx) to the head maps. The nine features are PointPillars' (x, y, z, intensity/255, offsets to the
  pillar's point mean, offsets to the pillar centre); padded rows are all zero and the encoder ignores them.

Outputs, both layouts: ``heatmap`` (classes), ``reg`` (2), ``height`` (1), ``dim`` (3, log metres), ``rot``
(sin, cos), ``vel`` (2) and — the uncertainty-aware model — ``logvar`` (5: x, y, vx, vy, yaw), each
(1, ·, H, W) at ``out_size_factor`` times the pillar grid. Decoding (sigmoid, 3×3 peak pooling, top-K, box
assembly, per-class circle NMS) stays outside the graph, as in Autoware; ``detector.json`` beside the model
carries every constant pre- and post-processing needs, and the variance recalibration of the weights.

Everything here imports torch; onnx and onnxscript (needed by torch's exporter) are imported when an export
runs, so the detector's other commands work without them.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import glob
import hashlib
import io
import json
import logging
import os
import secrets
import shutil
import stat
import warnings
from dataclasses import dataclass
from pathlib import Path
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from ...stack.control import pid_alive
from .adapter import INTENSITY_MAX
from .config import CLASS_LABELS, SELF_CROP_M, VAR_NAMES, DetectorConfig
from .evaluate import Recalibration
from .ground import TRAINED_SENSOR_HEIGHT_M
from .inference import config_to_dict
from .network import HEAD_CHANNELS, CenterPointNet
from .pillars import NUM_PILLAR_FEATURES, PillarFeatureNet, Pillars, voxelize

log = logging.getLogger(__name__)

FORMAT = "jitterguard-detector-onnx"
FORMAT_VERSION = 1
MANIFEST = "detector.json"
SINGLE_FILE = "detector.onnx"
ENCODER_FILE = "pts_voxel_encoder.onnx"
HEAD_FILE = "pts_backbone_neck_head.onnx"
LAYOUTS = ("single", "autoware")
EXPORT_FILES = (SINGLE_FILE, ENCODER_FILE, HEAD_FILE, MANIFEST)
"""Every name an export writes: a folder holding only these (or nothing) is an earlier export, replaced whole."""
DEFAULT_OPSET = 18
MIN_OPSET = 17
SINGLE_INPUTS = ("points", "pillar", "num_points", "coords")
POINT_FEATURES = ("x", "y", "z", "intensity/255", "x - x_mean", "y - y_mean", "z - z_mean", "x - x_centre",
                  "y - y_centre")
"""The nine per-point features of the pillar encoder, in order (the ``autoware`` layout's ``input_features``)."""
AUTOWARE_POINTS_PER_PILLAR = 32
"""Point slots per pillar that lidar_centerpoint binds to the encoder (``MAX_POINT_IN_VOXEL_SIZE`` in its kernels,
``max_point_in_voxel_size_`` in its config; not a parameter). The ``autoware`` encoder takes any M and reads the
first ``max_points_per_pillar`` slots."""
LOG_DIM_MAX = 5.0
"""The decoder clamps the log dimensions at this value before ``exp`` (:func:`~.decode.decode`)."""


def max_opset() -> int | None:
    """The newest opset the installed ``onnx`` package defines (None without it; the export then says what is
    missing). Asked at run time, since it grows with onnx: a higher opset had made the exporter's version converter
    print a traceback and the export silently write opset 18."""
    try:
        import onnx.defs
    except ImportError:
        return None
    return int(onnx.defs.onnx_opset_version())


def opset_refusal(opset: int) -> str | None:
    """Why ``opset`` cannot be exported (``must be >= 17 … , got N``), or None: the one rule of the CLI and the
    exporter."""
    hi = max_opset()
    if opset < MIN_OPSET or (hi is not None and opset > hi):
        upto = f" and <= {hi} (the installed onnx's newest)" if hi is not None else ""
        return f"must be >= {MIN_OPSET}{upto}, got {opset}"
    return None


class ExportError(RuntimeError):
    """An export that could not be written or did not reproduce the torch model (the message says which)."""


class ExportRefused(ExportError):
    """The ``accept`` check of :func:`export_onnx` refused the written export: it was removed, and an earlier export
    at ``out_dir`` is as it was."""


def output_names(config: DetectorConfig) -> tuple[str, ...]:
    """Head outputs in graph order: the heatmap, CenterPoint's regression heads, then the log-variances."""
    return ("heatmap", *HEAD_CHANNELS, *(("logvar",) if config.uncertainty else ()))


# ------------------------------------------------------------------------------------------- graphs


def bev_scatter(features: Tensor, coords: Tensor, config: DetectorConfig) -> Tensor:
    """(V, C) pillar features onto the (1, C, ny, nx) canvas — the same values as :func:`~.pillars.scatter_to_bev`
    for one scan.

    Written with ``index_put`` on a cell-major canvas because ``index_copy_`` (what the torch path uses, to spare
    a transposing copy on CPU) decomposes under ``torch.export`` into ops that pin the number of pillars to the
    sample's; ONNX Runtime fuses the transpose away.
    """
    nx, ny = config.grid_size
    lin = coords[:, 1] * nx + coords[:, 2]
    canvas = features.new_zeros(ny * nx, features.shape[1]).index_put((lin,), features)
    return canvas.t().reshape(1, features.shape[1], ny, nx)


def _head_tuple(net: CenterPointNet, bev: Tensor) -> tuple[Tensor, ...]:
    out = net.head(net.neck(net.backbone(bev)))
    return tuple(out[name] for name in output_names(net.config))


class SingleGraph(nn.Module):
    """The ``single`` layout: pillars (point-major, as :func:`voxelize` gives them) → head maps."""

    def __init__(self, net: CenterPointNet) -> None:
        super().__init__()
        self.net = net

    def forward(self, points: Tensor, pillar: Tensor, num_points: Tensor, coords: Tensor) -> tuple[Tensor, ...]:
        feats = self.net.pfn(Pillars(points, pillar, num_points, coords, 1))
        return _head_tuple(self.net, bev_scatter(feats, coords, self.net.config))


class VoxelEncoderGraph(nn.Module):
    """The ``autoware`` layout's first file: padded point features (V, M, 9) → pillar features (V, C).

    The same Linear + BatchNorm + ReLU + max as :class:`~.pillars.PillarFeatureNet`; a padded row (all nine
    features zero) is masked out, which reproduces the point-major encoder exactly: there the maximum starts
    from zero and every activation is ≥ 0, so a masked row (0) can never win.

    With ``max_points`` the graph reads only the first ``max_points`` slots of each pillar (the most the model was
    trained on) and M may be any size: lidar_centerpoint binds 32 slots per pillar (its
    ``MAX_POINT_IN_VOXEL_SIZE``, fixed in its kernels), our presets train on 16 or 20.
    """

    def __init__(self, pfn: PillarFeatureNet, max_points: int | None = None) -> None:
        super().__init__()
        self.linear, self.norm = pfn.linear, pfn.norm
        self.max_points = max_points

    def forward(self, input_features: Tensor) -> Tensor:
        if self.max_points is not None:
            input_features = input_features[:, : self.max_points]
        v, m, f = input_features.shape
        mask = (input_features != 0).any(dim=2, keepdim=True).to(input_features.dtype)
        # the channel count spelt out, not -1: with no pillar (a scan whose every return is out of range or cropped)
        # ONNX Runtime cannot infer a -1 from zero elements and had returned (0, 2), which the head then refused
        x = torch.relu(self.norm(self.linear(input_features.reshape(v * m, f)))).reshape(v, m, self.linear.out_features)
        return (x * mask).amax(dim=1)


class BackboneNeckHeadGraph(nn.Module):
    """The ``autoware`` layout's second file: the BEV canvas (1, C, ny, nx) → head maps."""

    def __init__(self, net: CenterPointNet) -> None:
        super().__init__()
        self.net = net

    def forward(self, spatial_features: Tensor) -> tuple[Tensor, ...]:
        return _head_tuple(self.net, spatial_features)


def padded_point_features(pillars: Pillars, pfn: PillarFeatureNet, max_points: int) -> Tensor:
    """The ``autoware`` layout's ``input_features``: each kept point's nine features in its pillar's row, in input
    order, zero-padded to ``max_points`` slots. :func:`voxelize` keeps a pillar's points contiguous."""
    feats = pfn.point_features(pillars)
    v = pillars.num_points.shape[0]
    starts = torch.cumsum(pillars.num_points, 0) - pillars.num_points
    slot = torch.arange(feats.shape[0]) - starts[pillars.pillar]
    out = feats.new_zeros(v, max_points, feats.shape[1])
    out[pillars.pillar, slot] = feats
    return out


# ------------------------------------------------------------------------------------------- export


def sample_pillars(config: DetectorConfig, n_points: int = 6000, seed: int = 0) -> Pillars:
    """A deterministic random scan's pillars: the example input the exporter traces (its sizes are only an
    example; N and V stay dynamic). Fewer pillars than ``max_pillars``, so no size is pinned by the cap."""
    r = config.point_cloud_range
    rng = np.random.default_rng(seed)
    pts = np.column_stack([rng.uniform(r[0] * 0.6, r[3] * 0.6, n_points), rng.uniform(r[1] * 0.6, r[4] * 0.6, n_points),
                           rng.uniform(r[2], r[5], n_points), rng.uniform(0, 255, n_points)]).astype(np.float32)
    return voxelize([torch.from_numpy(pts)], config)


@contextlib.contextmanager
def _quiet_exporter() -> Any:
    """torch's exporter prints progress lines on stdout (which carries JSON for our commands) and warns about
    torchvision ops it cannot register; keep both off the user's terminal unless something fails. onnxscript's
    version converter logs a traceback when it cannot take the graph down to a requested opset 17 (the pillar
    max needs 18), which the export then keeps and reports (``opset``, ``opset_requested``): no failure either."""
    names = ("torch.onnx", "torch.onnx._internal.exporter._registration", "torch._export", "torch.export",
             "onnxscript.version_converter")
    levels = {n: logging.getLogger(n).level for n in names}
    for n in names:
        logging.getLogger(n).setLevel(logging.ERROR)
    buf = io.StringIO()
    try:
        with contextlib.redirect_stdout(buf), warnings.catch_warnings():
            warnings.simplefilter("ignore", FutureWarning)  # torch.export's own deprecations, not ours to fix
            warnings.filterwarnings("ignore", message=".*axis name.*will not be used", category=UserWarning)
            yield buf
    finally:
        for n, lvl in levels.items():
            logging.getLogger(n).setLevel(lvl)


def _export(module: nn.Module, args: tuple[Tensor, ...], path: Path, inputs: tuple[str, ...],
            outputs: tuple[str, ...], dynamic: tuple[dict[int, Any], ...], opset: int) -> None:
    try:
        import onnxscript  # noqa: F401  (torch's exporter needs it; a clear message beats its ImportError)
    except ImportError:
        raise ExportError("exporting needs the 'onnx' and 'onnxscript' packages (pip install 'jitterguard[onnx]')") from None
    with _quiet_exporter() as log_buf:
        try:
            torch.onnx.export(module.eval(), args, str(path), dynamo=True, opset_version=opset, external_data=False,
                              input_names=list(inputs), output_names=list(outputs), dynamic_shapes=dynamic)
        except Exception as exc:  # noqa: BLE001 - the exporter raises many types; one line with its tail
            tail = " ".join(log_buf.getvalue().split()[-40:])
            raise ExportError(f"torch.onnx.export of {path.name} failed: {type(exc).__name__}: {exc} {tail}".strip()) from exc


def graph_opset(path: Path) -> int:
    """The default-domain opset a written graph declares. torch's exporter raises it above the requested one where
    an operator needs it (the pillar max is a ``max`` reduction: ScatterElements / ReduceMax of opset 18)."""
    import onnx

    model = onnx.load(str(path), load_external_data=False)
    return max(o.version for o in model.opset_import if o.domain in ("", "ai.onnx"))


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@dataclass(frozen=True)
class ExportResult:
    """What :func:`export_onnx` wrote: the model file(s), the manifest and its content."""

    out_dir: Path
    files: tuple[Path, ...]
    manifest_path: Path
    manifest: dict[str, Any]


def manifest_for(config: DetectorConfig, layout: str, opset: int, files: dict[str, Path],
                 recalibration: Recalibration | tuple[float, float] | None, meta: dict[str, Any]) -> dict[str, Any]:
    """The JSON beside the model: every constant a runtime needs to feed it and to decode its outputs."""
    nx, ny = config.grid_size
    fx, fy = config.feature_map_size
    c = config.pfn_channels
    graphs: dict[str, Any]
    if layout == "single":
        graphs = {"detector": {
            "file": files["detector"].name, "sha256": _sha256(files["detector"]),
            "inputs": {"points": ["N", 4, "float32", "x, y, z, intensity * intensity_scale of the kept points,"
                                  " grouped by pillar"],
                       "pillar": ["N", "int64", "pillar index of each point"],
                       "num_points": ["V", "int64", "points per pillar (<= max_points_per_pillar)"],
                       "coords": ["V", 3, "int64", "(0, iy, ix) of each pillar"]},
            "outputs": {n: [1, w, fy, fx] for n, w in head_widths(config).items()},
        }}
    else:
        graphs = {
            "voxel_encoder": {"file": files["voxel_encoder"].name, "sha256": _sha256(files["voxel_encoder"]),
                              "inputs": {"input_features": [
                                  "V", "M", NUM_PILLAR_FEATURES, "float32",
                                  f"M slots per pillar, any number (lidar_centerpoint binds {AUTOWARE_POINTS_PER_PILLAR});"
                                  f" the graph reads the first {config.max_points_per_pillar}; zero rows are padding"]},
                              "outputs": {"pillar_features": ["V", c, "float32"]}},
            "backbone_neck_head": {"file": files["backbone_neck_head"].name, "sha256": _sha256(files["backbone_neck_head"]),
                                   "inputs": {"spatial_features": [1, c, ny, nx, "float32"]},
                                   "outputs": {n: [1, w, fy, fx] for n, w in head_widths(config).items()}},
        }
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "layout": layout,
        "opset": opset,
        "graphs": graphs,
        "config": config_to_dict(config),
        "recalibration": rec.to_payload() if (rec := Recalibration.of(recalibration)) else None,
        "preprocessing": {
            "frame": "sensor (x forward, y left, z up, level), metres, the road trained_sensor_height_m below the"
                     " origin: a cloud from another mount (height h above the road) or in base_link (h = 0) is"
                     " moved by z + h - trained_sensor_height_m first and the boxes' z back by as much after; a"
                     " frame pitched or rolled against the road (road plane z = sx*x + sy*y - h) by"
                     " z - sx*x - sy*y + h - trained_sensor_height_m, the boxes' z back by sx*x + sy*y - h +"
                     " trained_sensor_height_m at their centres (the jitterguard detector measures h, sx and sy"
                     " in every scan: sensor_height_m and sensor_tilt auto)",
            "trained_sensor_height_m": TRAINED_SENSOR_HEIGHT_M,
            "self_crop_m": list(SELF_CROP_M),
            "self_crop": "before anything else the jitterguard detector drops every return whose x and y lie strictly"
                         " inside self_crop_m (x_min, y_min, x_max, y_max; the ego's own body; its self_crop parameter,"
                         " this is the default): a runtime without a crop box filter of its own must do the same, or"
                         " the body's returns come back as a car that moves with the ego",
            "point_cloud_range": list(config.point_cloud_range),
            "in_range": "a point is kept when x_min <= x < x_max, y_min <= y < y_max and z_min <= z < z_max (after"
                        " the frame's move) and its fields are finite",
            "voxel_size": list(config.voxel_size),
            "grid_size_xy": [nx, ny],
            "max_points_per_pillar": config.max_points_per_pillar,
            "max_pillars": config.max_pillars,
            "pillar_selection": "points in range sorted by cell (iy * nx + ix), stable; a pillar keeps its first "
                                "max_points_per_pillar points; over max_pillars, the most populated pillars are kept",
            "intensity_scale": 1.0 / 255.0 if config.use_intensity else 0.0,  # 0: a model without intensity
            "intensity_input": f"the intensity_scale applies to intensities on 0-{INTENSITY_MAX:g}: a cloud whose every"
                               f" intensity but at most 0.1 % lies in [0, 1], some fractional (a reflectance, as KITTI's), is"
                               f" multiplied by"
                               f" {INTENSITY_MAX:g} first; values outside 0-{INTENSITY_MAX:g} are clipped to it; a cloud"
                               " without an intensity field is fed 0",
            "point_features": list(POINT_FEATURES) if config.use_intensity else
            [f if f != "intensity/255" else "0 (the model takes no intensity)" for f in POINT_FEATURES],
            "pillar_centre": "x = ix * vx + vx / 2 + x_min, y = iy * vy + vy / 2 + y_min",
        },
        "postprocessing": {
            "heatmap": "sigmoid; peaks = cells equal to their 3x3 max; top max_objects over classes and cells",
            "out_size_factor": config.out_size_factor,
            "cell_size_m": [config.voxel_size[0] * config.out_size_factor, config.voxel_size[1] * config.out_size_factor],
            "x": "(ix + reg[0]) * cell_size_m[0] + x_min", "y": "(iy + reg[1]) * cell_size_m[1] + y_min",
            "z": "height", "dims": f"exp(min(dim, {LOG_DIM_MAX})) as length, width, height",
            "yaw": "atan2(rot[0], rot[1])", "velocity": "vel (m/s, sensor frame)",
            "log_variances": f"max(logvar, logvar_min) in m^2, m^2, m^2/s^2, m^2/s^2, rad^2 for {', '.join(VAR_NAMES)};"
                             " then + log(recalibration) on x and y when recalibration is set: [s2_x, s2_y], or"
                             " {scales: [[s2_x, s2_y], ...], score_edges: [...]} where a box scored s takes the row"
                             " numbered by the edges <= s",
            "score_threshold": config.score_threshold,
            "score_rule": "a peak is kept when its score > score_threshold (strictly), before NMS",
            "max_objects": config.max_objects,
            "nms": "per class, greedy circle NMS on squared BEV centre distance",
            "nms_dist2_m2": dict(zip(config.class_names, config.nms_dist2, strict=True)),
            "post_max_size": config.post_max_size,
            "logvar_min": config.logvar_min,
            "class_names": list(config.class_names),
            "autoware_labels": [int(v) for v in CLASS_LABELS[: config.num_classes]],
        },
        "meta": meta,
    }


def head_widths(config: DetectorConfig) -> dict[str, int]:
    """Channels of each head output, in graph order (:func:`output_names`)."""
    w = {"heatmap": config.num_classes, **HEAD_CHANNELS}
    if config.uncertainty:
        w["logvar"] = len(VAR_NAMES)
    return w


def export_onnx(net: CenterPointNet, out_dir: str | Path, *, layout: str = "single", opset: int = DEFAULT_OPSET,
                recalibration: Recalibration | tuple[float, float] | None = None,
                meta: dict[str, Any] | None = None, accept: Callable[[Path], bool] | None = None) -> ExportResult:
    """Write ``net`` in ``layout`` plus ``detector.json`` into ``out_dir`` (created): into a new folder beside it,
    which replaces ``out_dir`` whole once written, so an earlier export there (the other layout's graphs included)
    stays as it was until then and, the export failing or stopped, untouched. ``accept``, given the new folder
    before it replaces anything, may refuse it (:class:`ExportRefused`): ``export-onnx --check-scans`` runs its
    torch/onnxruntime comparison there, so an export that fails it leaves the earlier one in place (it had been
    swapped in first, then disabled, and the earlier good export was gone). Raises :class:`ExportError` (also for
    an ``out_dir`` holding anything but an earlier export, see :func:`foreign_entries`) and ``OSError``."""
    if layout not in LAYOUTS:
        raise ExportError(f"layout must be one of {', '.join(LAYOUTS)}, got {layout!r}")
    refused = opset_refusal(opset)
    if refused:
        raise ExportError(f"opset {refused}")
    if net.config.num_point_features != 4:
        raise ExportError(f"weights trained on stacked sweeps ({net.config.num_point_features} point features) are "
                          "not exported to ONNX yet: export the single-sweep model (x, y, z, intensity)")
    out = Path(out_dir)
    foreign = foreign_entries(out)
    if foreign:
        raise ExportError(f"{out} holds more than an earlier export ({', '.join(foreign[:5])}"
                          f"{', ...' if len(foreign) > 5 else ''}): an export replaces the whole folder")
    place = Path(os.path.realpath(out))  # through a symlink the folder it names is replaced, the link kept
    place.parent.mkdir(parents=True, exist_ok=True)
    for p in _remove_abandoned(place):
        log.info("removed %s, left by an export that was killed midway", p)
    tmp = _fresh_sibling(place, "export")
    try:
        if place.is_dir():  # the new folder is readable by whoever read the old one (not mkdtemp's 0700)
            os.chmod(tmp, stat.S_IMODE(place.stat().st_mode))
        files, manifest = _write_export(net, tmp, layout, opset, recalibration, meta)
        if accept is not None and not accept(tmp):
            raise ExportRefused(f"the export was refused by its check and not written to {out}")
        _swap_in(tmp, place)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return ExportResult(out, tuple(out / p.name for p in files.values()), out / MANIFEST, manifest)


def foreign_entries(out_dir: str | Path) -> list[str]:
    """What ``out_dir`` holds besides an export's own files (nothing when it does not exist). An export replaces
    the whole folder, so one holding anything else (``--out .``, a deployment folder with notes in it) is not
    exported into: that would delete the rest."""
    try:
        return sorted(set(os.listdir(out_dir)) - set(EXPORT_FILES))
    except (FileNotFoundError, NotADirectoryError):
        return []


def _fresh_sibling(place: Path, tag: str) -> Path:
    """A new empty folder beside ``place``, hidden and named after it and this process
    (``.NAME.TAG-PID-RANDOM``): on the same file system, so renaming it to ``place`` is atomic, and a later export
    can tell one left by a killed export (:func:`_remove_abandoned`). Made with the umask's mode, not mkdtemp's
    0700."""
    while True:
        p = place.with_name(f".{place.name}.{tag}-{os.getpid()}-{secrets.token_hex(4)}")
        try:
            p.mkdir()
            return p
        except FileExistsError:
            continue


def _remove_abandoned(place: Path) -> list[Path]:
    """Remove the hidden folders beside ``place`` that an export killed midway (SIGKILL, a power cut) left: those
    of :func:`_fresh_sibling` whose process is gone. One whose process lives (an export running now, or a pid
    reused since) is left alone. Returns what was removed."""
    removed = []
    for tag in ("export", "old"):
        for p in place.parent.glob(f".{glob.escape(place.name)}.{tag}-*-*"):
            pid = p.name[len(place.name) + len(tag) + 3:].split("-", 1)[0]
            if not pid.isdigit() or pid_alive(int(pid)):
                continue
            shutil.rmtree(p, ignore_errors=True)
            removed.append(p)
    return removed


_RENAME_EXCHANGE = 2
"""``renameat2``'s flag: swap two paths in one step (Linux 3.15; ext4, xfs, btrfs, tmpfs, overlayfs)."""


def _exchange(a: Path, b: Path) -> bool:
    """Swap the folders ``a`` and ``b`` in one atomic step; ``False`` where the kernel, the C library or the file
    system cannot (the caller then renames twice)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    at_fdcwd = -100
    if renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):
        return False
    raise OSError(err, os.strerror(err), str(a), None, str(b))


def _swap_in(new: Path, place: Path) -> None:
    """Put the folder ``new`` at ``place``: one rename where ``place`` is missing or empty; else one atomic exchange
    of the two, after which the earlier export (now at ``new``) is removed. At every moment ``place`` is the old
    export whole or the new one whole: an export written into the folder itself had, stopped or failing midway, left
    a mix of both. Where the file system cannot exchange, the earlier export is renamed aside first (and put back if
    the second rename fails): ``place`` is then absent for the instant between the two renames."""
    try:
        os.rename(new, place)
        return
    except OSError as exc:
        if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST):
            raise
    if _exchange(new, place):
        shutil.rmtree(new, ignore_errors=True)
        return
    old = _fresh_sibling(place, "old")
    os.rename(place, old)
    try:
        os.rename(new, place)
    except BaseException:
        os.rename(old, place)
        raise
    shutil.rmtree(old, ignore_errors=True)


def _write_export(net: CenterPointNet, out: Path, layout: str, opset: int,
                  recalibration: Recalibration | tuple[float, float] | None,
                  meta: dict[str, Any] | None) -> tuple[dict[str, Path], dict[str, Any]]:
    """The graphs of ``layout`` and ``detector.json`` written into the empty folder ``out``: the files by graph
    name, and the manifest."""
    net = net.eval()
    config = net.config
    sample = sample_pillars(config)
    v_dim, n_dim = torch.export.Dim("V", min=2, max=max(config.max_pillars, 3)), torch.export.Dim("N", min=2)
    files: dict[str, Path] = {}
    names = output_names(config)
    with torch.no_grad():
        if layout == "single":
            files["detector"] = out / SINGLE_FILE
            args = (sample.points, sample.pillar, sample.num_points, sample.coords)
            _export(SingleGraph(net), args, files["detector"], SINGLE_INPUTS, names,
                    ({0: n_dim}, {0: n_dim}, {0: v_dim}, {0: v_dim}), opset)
        else:
            files["voxel_encoder"] = out / ENCODER_FILE
            files["backbone_neck_head"] = out / HEAD_FILE
            # traced with lidar_centerpoint's 32 slots per pillar (more than any preset keeps), M left dynamic
            slots = max(AUTOWARE_POINTS_PER_PILLAR, config.max_points_per_pillar)
            feats = padded_point_features(sample, net.pfn, slots)
            m_dim = torch.export.Dim("M", min=2)
            _export(VoxelEncoderGraph(net.pfn, config.max_points_per_pillar), (feats,), files["voxel_encoder"],
                    ("input_features",), ("pillar_features",), ({0: v_dim, 1: m_dim},), opset)
            nx, ny = config.grid_size
            canvas = torch.zeros(1, config.pfn_channels, ny, nx)
            _export(BackboneNeckHeadGraph(net), (canvas,), files["backbone_neck_head"], ("spatial_features",), names,
                    ({},), opset)
    actual = {name: graph_opset(path) for name, path in files.items()}
    manifest = manifest_for(config, layout, max(actual.values()), files, recalibration, dict(meta or {}))
    manifest["opset_requested"] = opset
    for name, v in actual.items():
        manifest["graphs"][name]["opset"] = v
    (out / MANIFEST).write_text(json.dumps(manifest, indent=2) + "\n")
    return files, manifest
