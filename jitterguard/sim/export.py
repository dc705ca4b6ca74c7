"""Export a scenario as a nuScenes-format dataroot (``v1.0-mini`` tables + LIDAR_TOP ``.pcd.bin`` keyframes).

Why nuScenes: the detector's training code, the evaluation and every nuScenes tool read it, and the real scene
in ``shared/data/nuscenes-scene-0523`` has the same layout — synthetic and real data are interchangeable.
``nuscenes.nuscenes.NuScenes(version='v1.0-mini', dataroot=...)`` loads the result.

Layout: every scenario frame is a keyframe (``sample``) with one LIDAR_TOP sweep of 5 float32 per point
(x, y, z, intensity 0…255, ring). The ego frame is the sensor's ground footprint (ego_pose z = 0), the LiDAR is
mounted the exported sensor's ``mount_height_m`` above it (the height its scans were cast from, so ego_pose ∘
calibrated_sensor puts their ground at world z = 0) without rotation (x forward, y left). Annotation sizes are
nuScenes' (width, length, height); quaternions are (w, x, y, z); timestamps are microseconds. Tokens are derived
from the scenario's name and seed, so a re-export is byte-identical. Attribute, visibility and category tokens
are nuScenes' published constants where nuScenes has them.

:func:`nuscenes_tables` is pure (frames and scans in, tables out); :func:`write_dataroot` does the I/O.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import math
import os
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .lidar import ScanResult, cast_frame
from .sensors import LidarSpec, hdl32e
from .world import GroundTruthFrame, Scenario

VERSION = "v1.0-mini"
CHANNEL = "LIDAR_TOP"
SENSOR_TOKEN = "dc8b396651c05aedbb9cdaae573bb567"

ATTRIBUTE_TOKENS = {
    "vehicle.moving": "cb5118da1ab342aa947717dc53544259",
    "vehicle.stopped": "c3246a1e22a14fcb878aa61e69ae3329",
    "vehicle.parked": "58aa28b1c2a54dc88e169808c07331e3",
    "cycle.with_rider": "a14936d865eb4216b396adae8cb3939c",
    "cycle.without_rider": "5a655f9751944309a277276b8f473452",
    "pedestrian.sitting_lying_down": "03aa62109bf043afafdea7d875dd4f43",
    "pedestrian.standing": "4d8821270b4a47e3a8a300cbec48188e",
    "pedestrian.moving": "ab83627ff28b465b85c427162dec722f",
}
ATTRIBUTE_DESCRIPTIONS = {
    "vehicle.moving": "Vehicle is moving.",
    "vehicle.stopped": "Vehicle, with a driver or rider in or on it, is stationary.",
    "vehicle.parked": "Vehicle is stationary (usually for longer duration) with no immediate intent to move.",
    "cycle.with_rider": "There is a rider on the bicycle or motorcycle.",
    "cycle.without_rider": "There is NO rider on the bicycle or motorcycle.",
    "pedestrian.sitting_lying_down": "The human is sitting or lying down.",
    "pedestrian.standing": "The human is standing.",
    "pedestrian.moving": "The human is moving.",
}
# (token or None, lidarseg index)
CATEGORIES: dict[str, tuple[str | None, int]] = {
    "human.pedestrian.adult": ("1fa93b757fc74fb197cdd60001ad8abf", 2),
    "human.pedestrian.child": (None, 3),
    "vehicle.bicycle": ("fc95c87b806f48f8a1faea2dcc2222a4", 14),
    "vehicle.bus.rigid": ("fedb11688db84088883945752e480c2c", 16),
    "vehicle.car": ("fd69059b62a3469fbaef25340c0eab7f", 17),
    "vehicle.motorcycle": ("dfd26f200ade4d24b540184e16050022", 21),
    "vehicle.trailer": ("90d0f6f8e7c749149b1b6c3a029841a8", 22),
    "vehicle.truck": ("6021b5187b924d64be64a702e5570edf", 23),
}
VISIBILITY = (("1", "v0-40", 0.0, 0.4), ("2", "v40-60", 0.4, 0.6), ("3", "v60-80", 0.6, 0.8),
              ("4", "v80-100", 0.8, 1.01))


def token(*parts: object) -> str:
    """A deterministic 32-hex-digit token."""
    return hashlib.md5("/".join(str(p) for p in parts).encode()).hexdigest()


def quaternion_wxyz(yaw: float) -> list[float]:
    return [math.cos(yaw / 2.0), 0.0, 0.0, math.sin(yaw / 2.0)]


def visibility_token(v: float) -> str:
    for tok, _, lo, hi in VISIBILITY:
        if lo <= v < hi:
            return tok
    return "4"


@dataclass(frozen=True)
class SweepFile:
    """One LIDAR_TOP sweep to write: path relative to the dataroot and the (P, 5) float32 payload."""

    filename: str
    data: NDArray[np.float32]


def nuscenes_tables(scenario_name: str, seed: int, frames: Iterable[tuple[GroundTruthFrame, ScanResult]],
                    categories: dict[int, str], *, description: str = "", min_points: int = 0,
                    sensor: LidarSpec | None = None) -> tuple[dict[str, list[dict[str, object]]], list[SweepFile]]:
    """All nuScenes tables for a scenario's (frame, scan) pairs, and the sweep files to write.

    ``categories`` maps instance id → nuScenes category name. ``sensor`` is the LiDAR the scans were cast with
    (default the HDL-32E): its ``mount_height_m`` is the calibrated sensor's height, since the scans' ground lies
    that far below the sensor — a constant height put a replayed scan's ground above or below world z = 0. Objects
    with fewer than ``min_points`` LiDAR points in a frame are not annotated in it (nuScenes' own annotations
    include zero-point boxes)."""
    key = f"jitterguard-sim/{scenario_name}/{seed}"
    log_name = f"jg-sim-{scenario_name}-{seed}"
    scene_token, log_token = token(key, "scene"), token(key, "log")
    calib_token = token(key, "calibrated_sensor")
    cat_tokens = {name: tok or token("category", name) for name, (tok, _) in CATEGORIES.items()}
    mount_height_m = float((sensor or hdl32e()).mount_height_m)

    samples: list[dict[str, object]] = []
    sample_data: list[dict[str, object]] = []
    ego_poses: list[dict[str, object]] = []
    annotations: list[dict[str, object]] = []
    sweeps: list[SweepFile] = []
    by_instance: dict[int, list[int]] = {}
    first_ts = None
    for frame, res in frames:
        ts = frame.stamp_ns // 1000
        first_ts = ts if first_ts is None else first_ts
        s_tok, sd_tok = token(key, "sample", frame.seq), token(key, "sample_data", frame.seq)
        samples.append({"token": s_tok, "timestamp": ts, "prev": "", "next": "", "scene_token": scene_token})
        filename = f"samples/{CHANNEL}/{log_name}__{CHANNEL}__{ts}.pcd.bin"
        sample_data.append({
            "token": sd_tok, "sample_token": s_tok, "ego_pose_token": sd_tok, "calibrated_sensor_token": calib_token,
            "timestamp": ts, "fileformat": "pcd", "is_key_frame": True, "height": 0, "width": 0,
            "filename": filename, "prev": "", "next": "",
        })
        ego_poses.append({"token": sd_tok, "timestamp": ts, "rotation": quaternion_wxyz(frame.ego_yaw),
                          "translation": [frame.ego_x, frame.ego_y, 0.0]})
        data = np.empty((len(res.points), 5), np.float32)
        data[:, :4] = res.points
        data[:, 4] = res.ring
        sweeps.append(SweepFile(filename, data))
        for n in range(frame.num_objects):
            if frame.num_points[n] < min_points:
                continue
            iid = int(frame.instance_ids[n])
            a_tok = token(key, "ann", frame.seq, iid)
            by_instance.setdefault(iid, []).append(len(annotations))
            L, W, H = (float(v) for v in frame.sizes[n])
            annotations.append({
                "token": a_tok, "sample_token": s_tok, "instance_token": token(key, "instance", iid),
                "visibility_token": visibility_token(float(frame.visibility[n])),
                "attribute_tokens": [ATTRIBUTE_TOKENS[frame.attributes[n]]],
                "translation": [float(v) for v in frame.centers[n]], "size": [W, L, H],
                "rotation": quaternion_wxyz(float(frame.yaws[n])), "prev": "", "next": "",
                "num_lidar_pts": int(frame.num_points[n]), "num_radar_pts": 0,
            })
    for seq in (samples, sample_data):
        for a, b in zip(seq, seq[1:]):
            a["next"], b["prev"] = b["token"], a["token"]
    instances = []
    for iid, rows in sorted(by_instance.items()):
        for ra, rb in zip(rows, rows[1:]):
            annotations[ra]["next"], annotations[rb]["prev"] = annotations[rb]["token"], annotations[ra]["token"]
        cat = categories[iid]
        instances.append({"token": token(key, "instance", iid), "category_token": cat_tokens[cat],
                          "nbr_annotations": len(rows), "first_annotation_token": annotations[rows[0]]["token"],
                          "last_annotation_token": annotations[rows[-1]]["token"]})
    date = _dt.datetime.fromtimestamp((first_ts or 0) / 1e6, tz=_dt.timezone.utc).strftime("%Y-%m-%d")
    tables: dict[str, list[dict[str, object]]] = {
        "attribute": [{"token": t, "name": n, "description": ATTRIBUTE_DESCRIPTIONS[n]}
                      for n, t in ATTRIBUTE_TOKENS.items()],
        "calibrated_sensor": [{"token": calib_token, "sensor_token": SENSOR_TOKEN,
                               "translation": [0.0, 0.0, mount_height_m], "rotation": [1.0, 0.0, 0.0, 0.0],
                               "camera_intrinsic": []}],
        "category": [{"token": cat_tokens[n], "name": n, "description": f"{n} (synthetic)", "index": idx}
                     for n, (_, idx) in CATEGORIES.items()],
        "ego_pose": ego_poses,
        "instance": instances,
        "log": [{"token": log_token, "logfile": log_name, "vehicle": "jitterguard-sim", "date_captured": date,
                 "location": f"synthetic-{scenario_name}"}],
        "map": [{"token": token(key, "map"), "category": "semantic_prior", "filename": "", "log_tokens": [log_token]}],
        "sample": samples,
        "sample_annotation": annotations,
        "sample_data": sample_data,
        "scene": [{"token": scene_token, "log_token": log_token, "nbr_samples": len(samples),
                   "first_sample_token": samples[0]["token"] if samples else "",
                   "last_sample_token": samples[-1]["token"] if samples else "",
                   "name": f"sim-{scenario_name}-{seed}",
                   "description": description or f"jitterguard synthetic scenario {scenario_name}, seed {seed}"}],
        "sensor": [{"token": SENSOR_TOKEN, "channel": CHANNEL, "modality": "lidar"}],
        "visibility": [{"token": t, "level": lvl, "description": f"visibility of whole object is between "
                        f"{int(lo * 100)} and {min(int(hi * 100), 100)}%"} for t, lvl, lo, hi in VISIBILITY],
    }
    return tables, sweeps


def write_dataroot(dataroot: str, tables: dict[str, list[dict[str, object]]], sweeps: Iterable[SweepFile]) -> None:
    """Write the sweeps below ``dataroot``, then the tables to ``dataroot/v1.0-mini/*.json``.

    All or nothing: the tables — what makes a folder a dataroot to every reader — are written last, into a
    temporary folder renamed into place, and a write that fails (a full disk, a path that is not a folder) removes
    every file and folder this call made before the error is raised. A failed export had left a half-written
    dataroot behind, tables first, which ``jitterguard sim export`` then refused to overwrite."""
    made: list[str] = []  # files and folders this call created, in order

    def makedirs(path: str) -> None:
        missing = []
        while path and not os.path.isdir(path):
            missing.append(path)
            path = os.path.dirname(path)
        for d in reversed(missing):
            os.mkdir(d)
            made.append(d)

    final = os.path.join(dataroot, VERSION)
    part = os.path.join(dataroot, f".{VERSION}.{os.getpid()}.part")
    try:
        for sw in sweeps:
            path = os.path.join(dataroot, sw.filename)
            makedirs(os.path.dirname(path))
            existed = os.path.exists(path)
            if not existed:
                made.append(path)
            sw.data.astype("<f4").tofile(path)
        makedirs(part)
        for name, rows in tables.items():
            with open(os.path.join(part, f"{name}.json"), "w", encoding="utf-8") as fh:
                json.dump(rows, fh, indent=0)
        if os.path.isdir(final):  # a re-export over an existing dataroot: its tables replaced one by one
            for name in tables:
                os.replace(os.path.join(part, f"{name}.json"), os.path.join(final, f"{name}.json"))
            os.rmdir(part)
        else:
            os.rename(part, final)
    except BaseException:
        import shutil

        shutil.rmtree(part, ignore_errors=True)
        for path in reversed(made):
            try:
                if os.path.isdir(path):
                    os.rmdir(path)
                else:
                    os.unlink(path)
            except OSError:
                pass
        raise


def export_scenario(scenario: Scenario, dataroot: str, sensor: LidarSpec | None = None, seed: int = 0, *,
                    min_points: int = 0, progress: Callable[[Iterable[GroundTruthFrame]], Iterable[GroundTruthFrame]]
                    | None = None) -> dict[str, int]:
    """Scan every frame of ``scenario`` and write it as a nuScenes dataroot; returns table sizes."""
    spec = sensor or hdl32e()
    frames: Iterable[GroundTruthFrame] = iter(scenario)
    if progress is not None:
        frames = progress(frames)
    pairs = []
    for f in frames:
        res, g = cast_frame(f, spec, seed)
        pairs.append((g, res))
    tables, sweeps = nuscenes_tables(scenario.name, scenario.seed, pairs, scenario.categories, min_points=min_points,
                                     sensor=spec)
    write_dataroot(dataroot, tables, sweeps)
    return {name: len(rows) for name, rows in tables.items()}
