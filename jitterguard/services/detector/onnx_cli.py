"""``jitterguard export-onnx``: write the detector (with its variance heads) as ONNX plus ``detector.json``.

After writing, the export is checked: ONNX Runtime runs it on real HDL-32E scans of the synthetic world and the
raw head maps and the decoded boxes, scores and log-variances are compared with torch's; the maximum absolute
differences are printed (and the command fails, exit 1, if the decoded detections differ beyond ``--tolerance`` —
``--yaw-tolerance`` for the yaw angle —, the raw maps beyond :data:`MAP_TOLERANCE`, or the detections differ in
number or class; ``detector.json`` is then removed, so no backend loads the failed export). Bad input (a stacked-sweep model, a ``--preset`` other than the ``--weights``' architecture, a check asked for
without onnxruntime installed) is exit 2 before any export. Randomly initialised weights (a preset without
shipped weights) are checked on the raw head maps only: they score every cell about alike, and which of hundreds
of near-ties make the top-K is float32 noise.
"""

from __future__ import annotations

import importlib.util
import json
import os
import sys
from pathlib import Path
from typing import Annotated, Any

import typer

from ...cli_common import fail, float_option, out_dir
from ...files import not_a_file
from .cli import ThreadsOpt, WeightsOpt, _one_line, passive_openmp
from .config import PRESETS

LayoutOpt = Annotated[str, typer.Option("--layout", help="single (one file) or autoware (voxel encoder + backbone/neck/head, as lidar_centerpoint).")]


BOX_COLUMNS = ("x", "y", "z", "length", "width", "height", "yaw", "vx", "vy")
MAP_TOLERANCE = 1e-3
"""Largest accepted difference anywhere in the raw head maps. Two correct float32 evaluations of this network
differ by up to ~2e-4 in the raw maps of a real scan (against a float64 evaluation of the lite model: torch 3e-5,
onnxruntime 5e-5 on the log-variance map), while a wrong graph differs by O(1); the decoded detections are what
``--tolerance`` bounds."""


def pair_detections(a: Any, b: Any) -> Any:
    """Row of ``b`` paired with each row of ``a``: the same detection, found by class and BEV centre (an optimal
    assignment), not by list position — two detections whose scores differ by float32 noise may swap places in the
    score order without being different detections."""
    import numpy as np
    from scipy.optimize import linear_sum_assignment

    cost = np.linalg.norm(a.boxes[:, None, :2].astype(np.float64) - b.boxes[None, :, :2], axis=2)
    cost += 1e6 * (a.labels[:, None] != b.labels[None, :])
    rows, cols = linear_sum_assignment(cost)
    order = np.empty(len(a), dtype=np.int64)
    order[rows] = cols
    return order


def compare_detections(a: Any, b: Any) -> dict[str, Any]:
    """Max |a − b| per box column, over scores and over log-variances of two decodings of one scan, detections
    paired by :func:`pair_detections` (None where either is empty); ``count_mismatch`` is the difference in the
    number of detections (then nothing else is compared); ``labels_equal`` whether every pair has one class."""
    out: dict[str, Any] = {"detections": len(a), "count_mismatch": abs(len(a) - len(b)), "labels_equal": True,
                           "box_columns": None, "scores": None, "log_variances": None}
    if len(a) != len(b) or len(a) == 0:
        return out
    import numpy as np

    j = pair_detections(a, b)
    out["labels_equal"] = bool((a.labels == b.labels[j]).all())
    diff = np.abs(a.boxes - b.boxes[j]).astype(np.float64)
    d_yaw = a.boxes[:, 6].astype(np.float64) - b.boxes[j, 6]
    diff[:, 6] = np.abs(np.arctan2(np.sin(d_yaw), np.cos(d_yaw)))  # ±π is one heading
    cols = diff.max(axis=0)
    out["box_columns"] = {c: float(v) for c, v in zip(BOX_COLUMNS, cols, strict=True)}
    out["scores"] = float(np.abs(a.scores - b.scores[j]).max())
    if a.log_variances is not None and b.log_variances is not None:
        out["log_variances"] = float(np.abs(a.log_variances - b.log_variances[j]).max())
    out["pairing"] = j
    return out


def check_export(torch_det: Any, onnx_det: Any, scans: list[Any], *, decoded: bool = True) -> dict[str, Any]:
    """Both detectors on ``scans``: maximum absolute differences of the raw head maps (every cell of every map)
    and of the decoded detections (per box column, scores, log-variances), and whether labels agree.

    ``yaw`` is reported on its own: it is ``atan2`` of the rot head's (sin, cos), so a float32 difference ε in the
    maps becomes ε / |(sin, cos)| in the angle; ``yaw_worst_rot_norm`` is that norm where the yaw differs most.
    """
    import numpy as np
    import torch

    from .pillars import voxelize

    maps: dict[str, float] = {}
    cols = dict.fromkeys(BOX_COLUMNS, 0.0)
    worst = {"scores": 0.0, "log_variances": 0.0}
    mismatched, labels_equal, yaw_norm = 0, True, None
    for pts in scans:
        p = voxelize([torch.from_numpy(np.ascontiguousarray(pts[:, :4], dtype=np.float32))], torch_det.config)
        with torch.inference_mode():
            ra, rb = torch_det.model.forward_pillars(p), onnx_det.model.forward_pillars(p)
        for k, v in ra.items():
            maps[k] = max(maps.get(k, 0.0), float((v - rb[k]).abs().max()))
        if not decoded:
            continue
        a, b = torch_det.detect(pts), onnx_det.detect(pts)
        cmp = compare_detections(a, b)
        if cmp["count_mismatch"]:
            mismatched += 1
            continue
        if not len(a):
            continue
        labels_equal &= cmp["labels_equal"]
        for k in worst:
            if cmp[k] is not None:
                worst[k] = max(worst[k], float(cmp[k]))
        d = a.boxes[:, 6].astype(np.float64) - b.boxes[cmp["pairing"], 6]
        dyaw = np.abs(np.arctan2(np.sin(d), np.cos(d)))
        if float(dyaw.max()) >= cols["yaw"]:
            i = int(dyaw.argmax())
            yaw_norm = _rot_norm_at(ra["rot"], a.boxes[i], torch_det.config)
        for c, v in cmp["box_columns"].items():
            cols[c] = max(cols[c], v)
    boxes_but_yaw = max(v for c, v in cols.items() if c != "yaw")
    if not decoded:
        return {"scans": len(scans), "decoded": False, "head_maps": maps}
    return {"scans": len(scans), "decoded": True, "scans_with_count_mismatch": mismatched, "labels_equal": labels_equal,
            "max_abs_error": {"boxes": max(cols.values()), "boxes_except_yaw": boxes_but_yaw, "yaw": cols["yaw"],
                              "scores": worst["scores"], "log_variances": worst["log_variances"]},
            "box_columns": cols, "head_maps": maps, "yaw_worst_rot_norm": yaw_norm}


def _rot_norm_at(rot: Any, box: Any, config: Any) -> float | None:
    """|(sin, cos)| of the rot head at the output cell a decoded box came from (the nearest cell centre)."""
    r = config.point_cloud_range
    cell = (config.voxel_size[0] * config.out_size_factor, config.voxel_size[1] * config.out_size_factor)
    h, w = rot.shape[2], rot.shape[3]
    ix, iy = int((box[0] - r[0]) // cell[0]), int((box[1] - r[1]) // cell[1])
    if not (0 <= ix < w and 0 <= iy < h):
        return None
    return float(rot[0, :, iy, ix].norm())


def export_ok(check: dict[str, Any], tolerance: float, yaw_tolerance: float) -> bool:
    """The export check passes: same detections, labels, and every difference within its tolerance (the head maps
    only when the decoded detections were not compared)."""
    if not check["decoded"]:
        return max(check["head_maps"].values()) <= MAP_TOLERANCE
    err = check["max_abs_error"]
    return (not check["scans_with_count_mismatch"] and check["labels_equal"]
            and max(err["boxes_except_yaw"], err["scores"], err["log_variances"]) <= tolerance
            and max(check["head_maps"].values()) <= MAP_TOLERANCE and err["yaw"] <= yaw_tolerance)


def _replaceable(flag: str, out: str) -> None:
    """``out`` can be replaced by a new export (exit 2 naming ``flag`` if not): the export is written into a new
    folder beside it and swapped in whole, so ``out`` must hold nothing but an earlier export (the swap would delete
    the rest) and its parent must be writable."""
    from .onnx_export import foreign_entries

    foreign = foreign_entries(out)
    if foreign:
        fail(f"{flag}: {out} holds more than an earlier export ({', '.join(foreign[:5])}"
             f"{', ...' if len(foreign) > 5 else ''}), and an export replaces the whole folder: give a new or empty one")
    parent = Path(os.path.realpath(out)).parent
    if not os.access(parent, os.W_OK | os.X_OK):
        fail(f"{flag}: cannot write into {parent}, where the export is written before it replaces {out}")


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    @app.command("export-onnx")
    def export_onnx_cmd(
        out: Annotated[str, typer.Option("--out", help="Folder to write the ONNX file(s) and detector.json into: new, empty"
                                         " or an earlier export's, replaced whole once the new export is written (a"
                                         " failed or stopped export leaves the earlier one as it was).")],
        preset: Annotated[str | None, typer.Option("--preset", help=f"Architecture preset: {', '.join(PRESETS)}"
                                                   " (default lite): its shipped weights; with --weights only the"
                                                   " weights' own architecture.")] = None,
        weights: WeightsOpt = None,
        layout: LayoutOpt = "single",
        opset: Annotated[int, typer.Option("--opset", help="ONNX opset: 17 up to the newest the installed onnx"
                                           " package defines (onnx.defs.onnx_opset_version()).")] = 18,
        check_scans: Annotated[int, typer.Option("--check-scans", min=0, max=100, help="Synthetic scans to compare ONNX Runtime with torch on (0: skip).")] = 3,
        tolerance: Annotated[float, float_option("--tolerance", min=0.0, help="Largest accepted |onnxruntime - torch| on the decoded boxes (but yaw), scores and log-variances (the raw head maps are held to a fixed"
                                                 f" {MAP_TOLERANCE:g}).")] = 1e-4,
        yaw_tolerance: Annotated[float, float_option("--yaw-tolerance", min=0.0, help="Largest accepted yaw difference, rad (atan2 of the rot head amplifies float32 noise where |(sin, cos)| is small).")] = 1e-3,
        threads: ThreadsOpt = None,
    ) -> None:
        """Export the detector with its variance heads to ONNX (dynamic number of pillars) plus detector.json."""
        from .onnx_export import LAYOUTS, opset_refusal

        if preset is not None and preset not in PRESETS:
            fail(f"--preset: expected one of {', '.join(PRESETS)}, got {preset!r}")
        from .train_cli import check_preset
        if layout not in LAYOUTS:
            fail(f"--layout: expected one of {', '.join(LAYOUTS)}, got {layout!r}")
        refused = opset_refusal(opset)  # without onnx only the minimum: the export names the missing packages
        if refused:
            fail(f"--opset: {refused}")
        if weights is not None and (why := not_a_file(weights)):
            fail(f"--weights: {why}")
        if check_scans and importlib.util.find_spec("onnxruntime") is None:
            # refused before the export: the check had died in a WeightsError traceback after writing an unchecked
            # export, detector.json included
            fail("--check-scans: checking the export needs the onnxruntime package (pip install 'jitterguard[onnx]');"
                 " --check-scans 0 exports without the check")
        passive_openmp()
        from .inference import Detector, WeightsError, shipped_weights
        from .onnx_backend import load_onnx_detector
        from .onnx_export import ExportError, ExportRefused, export_onnx

        preset_given, preset = preset, preset or "lite"
        try:
            det = Detector.load(weights, preset, threads=threads)
        except WeightsError as exc:
            fail(f"--weights: {_one_line(exc)}")
        check_preset(preset_given, weights, det.config.name)
        if det.config.num_point_features != 4:  # bad input, not a failed export: name the flag, exit 2
            fail(f"--weights: the model takes stacked sweeps ({det.config.num_point_features} point fields), which"
                 " is not exported to ONNX yet: export the single-sweep weights (x, y, z, intensity)")
        out_dir("--out", out)  # after the flags and weights are checked, before the export
        _replaceable("--out", out)
        source = weights or (str(shipped_weights(preset)) if shipped_weights(preset).is_file() else "random-init")
        meta = {**det.meta, "preset": det.config.name, "weights": Path(source).name if source != "random-init" else source}
        checked: dict[str, Any] = {}

        def agrees(folder: Path) -> bool:
            """The written export (not yet in ``--out``) against torch on ``check_scans`` scans."""
            from ...bench.detector import bench_scans

            onnx_det = load_onnx_detector(folder, threads=threads)
            # randomly initialised weights score every cell about alike: which of hundreds of near-ties make the
            # top-K is float32 noise, so only the raw head maps are a meaningful comparison there
            decoded = not det.meta.get("random_init")
            checked["check"] = check_export(det, onnx_det, bench_scans(check_scans), decoded=decoded)
            return export_ok(checked["check"], tolerance, yaw_tolerance)

        try:
            res = export_onnx(det.model, out, layout=layout, opset=opset, recalibration=det.recalibration, meta=meta,
                              accept=agrees if check_scans else None)
        except ExportRefused:
            # checked before it replaced anything: an earlier export in --out stays whole and loadable (it had been
            # replaced by the failing one, then disabled)
            check = checked["check"]
            print(json.dumps({"out": str(out), "layout": layout, "preset": det.config.name,
                              "weights": meta["weights"], "check": check}))
            print(f"jitterguard: error: onnxruntime and torch disagree beyond --tolerance {tolerance:g} / --yaw-tolerance"
                  f" {yaw_tolerance:g}: {check.get('max_abs_error', check['head_maps'])}; nothing written to {out}"
                  f" (an earlier export there, if any, is kept)", file=sys.stderr)
            raise typer.Exit(1) from None
        except (ExportError, OSError) as exc:  # OSError: the new folder not written or not swapped in
            print(f"jitterguard: error: {_one_line(exc, 600)}", file=sys.stderr)
            raise typer.Exit(1) from None
        report: dict[str, Any] = {"out": str(res.out_dir), "files": [p.name for p in (*res.files, res.manifest_path)],
                                  "layout": layout, "opset": res.manifest["opset"], "opset_requested": opset,
                                  "graph_opsets": {k: g["opset"] for k, g in res.manifest["graphs"].items()},
                                  "preset": det.config.name, "weights": meta["weights"]}
        if check_scans:
            report["check"] = checked["check"]
        print(json.dumps(report))
