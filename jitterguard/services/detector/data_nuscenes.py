"""nuScenes-format dataroots (the real scene in ``shared/data`` and ``jitterguard sim export`` output) as
detector :class:`~jitterguard.services.detector.config.Sample`s, read straight from the JSON tables.

For every LIDAR_TOP key frame: the sweep's points (``.pcd.bin``, 5 float32 per point; x, y, z, intensity kept,
the ring dropped) and the sample's annotations moved global → ego (``ego_pose``) → sensor
(``calibrated_sensor``) exactly as nuscenes-devkit's ``get_sample_data`` does, then both turned into the
vehicle's axes at the sensor (the sensor's mounting rotation applied: level and x forward, the frame the
replay publishes, :func:`~jitterguard.services.replay.sources.nuscenes.vehicle_axes`), so boxes are devkit's
turned by that rotation (the tests compare them). nuScenes stores sizes as (width, length, height) and
quaternions as (w, x, y, z).

Velocities: nuScenes has none; like devkit's ``box_velocity`` they are the centre difference of the previous
and next annotation of the instance over their sample timestamps (one-sided at a track's ends; none when the
gap exceeds ``max_time_diff`` — doubled for a centred difference — or the instance has a single annotation).
Where there is no estimate the velocity is set to 0, as mmdet3d's NuScenesDataset does, rather than NaN:
``Sample`` carries no per-box validity flag and a NaN would poison any loss that forgets to mask it. Such boxes
are few (single-annotation instances) and mostly static clutter at the edge of the range.

The table readers and pose records are the replay's (``replay/sources/nuscenes.py``), so replay, evaluation and
training walk a scene identically.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...files import not_a_folder
from ..replay.frames import SourceError
from ..replay.sources.kitti import read_bin
from ..replay.sources.nuscenes import _load_table, consistent_tables, find_version, turn_points, vehicle_axes
from .config import BOX_DIM, CLASS_NAMES, LazySamples, Sample
from .sweeps import EarlierSweep, relative_transform, stack_sweeps

F64 = NDArray[np.float64]

CHANNEL = "LIDAR_TOP"
NUSCENES_FIELDS = 5

NUSCENES_TO_CLASS: dict[str, int] = {
    "vehicle.car": CLASS_NAMES.index("car"),
    "vehicle.emergency.police": CLASS_NAMES.index("car"),
    "vehicle.truck": CLASS_NAMES.index("truck"),
    "vehicle.trailer": CLASS_NAMES.index("truck"),
    "vehicle.construction": CLASS_NAMES.index("truck"),
    "vehicle.emergency.ambulance": CLASS_NAMES.index("truck"),
    "vehicle.bus.rigid": CLASS_NAMES.index("bus"),
    "vehicle.bus.bendy": CLASS_NAMES.index("bus"),
    "vehicle.bicycle": CLASS_NAMES.index("bicycle"),
    "vehicle.motorcycle": CLASS_NAMES.index("bicycle"),
}
"""nuScenes category → detector class (Autoware's CenterPoint folding: trailers and construction vehicles are
trucks, motorcycles bicycles; emergency vehicles as the evaluator maps them). ``human.pedestrian.*`` →
pedestrian; every other category (barriers, cones, debris, animals, bicycle racks) is no target: neither trained
on nor scored, kept only as :attr:`~.config.Sample.unscored` to say what a false positive stands on."""


def nuscenes_class(category: str) -> int:
    """Detector class index of a nuScenes category name, −1 if it is not a detector target."""
    if category.startswith("human.pedestrian."):
        return CLASS_NAMES.index("pedestrian")
    return NUSCENES_TO_CLASS.get(category, -1)


def _rotations_wxyz(q: F64) -> F64:
    """(N, 3, 3) rotation matrices of (N, 4) quaternions stored w, x, y, z (normalised first)."""
    q = np.asarray(q, np.float64).reshape(-1, 4)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], 1)


def box_velocity(ann: dict[str, Any], anns: dict[str, dict[str, Any]], sample_ts: dict[str, int],
                 max_time_diff: float = 1.5) -> F64:
    """devkit's ``NuScenes.box_velocity`` on plain tables: global (vx, vy, vz) in m/s, NaN when unknown. A
    neighbour the table does not hold (a scene cut out of a larger set) counts as none, where devkit raises."""
    prev, nxt = anns.get(ann["prev"]) if ann["prev"] else None, anns.get(ann["next"]) if ann["next"] else None
    has_prev, has_next = prev is not None, nxt is not None
    if not has_prev and not has_next:
        return np.full(3, np.nan)
    first = prev if prev is not None else ann
    last = nxt if nxt is not None else ann
    dt = 1e-6 * (sample_ts[last["sample_token"]] - sample_ts[first["sample_token"]])
    limit = max_time_diff * (2.0 if has_prev and has_next else 1.0)
    if dt > limit or dt <= 0:
        return np.full(3, np.nan)
    return (np.asarray(last["translation"], np.float64) - np.asarray(first["translation"], np.float64)) / dt


def annotations_to_sensor(anns: Sequence[dict[str, Any]], velocities: F64, ego: dict[str, Any],
                          calib: dict[str, Any]) -> F64:
    """(N, 9) sensor-frame boxes of global-frame annotations: centre, size and orientation moved through the
    inverse ego pose and the inverse sensor calibration (devkit's ``get_sample_data`` chain), velocity rotated
    the same way (3-D rotations throughout: nuScenes' ego poses are not flat). Yaw is the heading of the
    rotated box's forward axis projected on the ground (devkit's evaluation ``quaternion_yaw``; pyquaternion's
    ``yaw_pitch_roll[0]``, which mmdet3d's converter uses, differs by ~1e-4 rad where the ego is pitched or
    rolled). NaN velocities stay NaN."""
    n = len(anns)
    out = np.zeros((n, BOX_DIM), np.float64)
    if n == 0:
        return out
    r_ego = _rotations_wxyz(np.asarray(ego["rotation"]))[0]
    r_cal = _rotations_wxyz(np.asarray(calib["rotation"]))[0]
    r = r_cal.T @ r_ego.T  # global → sensor
    t = np.array([a["translation"] for a in anns], np.float64)
    centre = ((t - np.asarray(ego["translation"], np.float64)) @ r_ego - np.asarray(calib["translation"])) @ r_cal
    rb = r[None] @ _rotations_wxyz(np.array([a["rotation"] for a in anns], np.float64))
    size = np.array([a["size"] for a in anns], np.float64)  # (w, l, h)
    out[:, 0:3] = centre
    out[:, 3] = size[:, 1]
    out[:, 4] = size[:, 0]
    out[:, 5] = size[:, 2]
    out[:, 6] = np.arctan2(rb[:, 1, 0], rb[:, 0, 0])
    out[:, 7:9] = (np.asarray(velocities, np.float64).reshape(n, 3) @ r.T)[:, :2]
    return out


def _scene_chain(scene: dict[str, Any], samples: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    chain: list[dict[str, Any]] = []
    token, seen = scene["first_sample_token"], set()
    while token and token not in seen:
        seen.add(token)
        chain.append(samples[token])
        if token == scene["last_sample_token"]:
            break
        token = samples[token]["next"]
    return chain


@dataclass(frozen=True)
class SweepRef:
    """One LIDAR_TOP sweep stacked onto a key frame: its file, the rigid transform of its sensor frame into the
    key frame's (``rotation`` 3×3, ``translation`` 3) and how much older it is (seconds, ≥ 0)."""

    path: Path
    rotation: F64
    translation: F64
    time_lag_s: float


@dataclass(frozen=True)
class _Keyframe:
    token: str
    path: Path
    boxes: NDArray[np.float32]
    labels: NDArray[np.int64]
    num_points: NDArray[np.int64]
    sweeps: tuple[SweepRef, ...]
    mount_rotation: F64  # sensor axes → vehicle axes (its points are turned by it when read)
    unscored: tuple[tuple[str, float, float], ...] = ()


def _pose_matrix(rec: dict[str, Any]) -> tuple[F64, F64]:
    return _rotations_wxyz(np.asarray(rec["rotation"]))[0], np.asarray(rec["translation"], np.float64)


def _levelled(calib: dict[str, Any]) -> dict[str, Any]:
    """A ``calibrated_sensor`` record without its rotation: the sensor frame in the vehicle's axes."""
    return {**calib, "rotation": [1.0, 0.0, 0.0, 0.0]}


class NuScenesKeyframes(LazySamples):
    """The LIDAR_TOP key frames of a nuScenes-format dataroot as a lazy random-access sequence of
    :class:`~.config.Sample`: the tables are read once (boxes in the sensor frame, the sweep chain of every key
    frame), the point files only when a sample is asked for, so a DataLoader over full nuScenes
    (v1.0-trainval, ~28k key frames, ~300k sweeps) holds no points in memory.

    ``sweeps`` > 1 stacks the key frame with up to ``sweeps − 1`` earlier LIDAR_TOP sweeps no more than
    ``max_sweep_lag_s`` older, each moved into the key frame's sensor frame through the ego poses (CenterPoint's
    nuScenes input: 10 sweeps, 0.5 s), with the time lag in seconds as a fifth point column (0 for the key frame),
    and points within ``min_sweep_range_m`` of an earlier sweep's sensor dropped (the ego's own body). With
    ``sweeps == 1`` points are (P, 4) x, y, z, intensity. A dataroot without sweeps (``shared/data``'s
    keyframes-only scene, where ``prev`` links key frames 0.5 s apart) stacks what there is within the lag.

    Raises :class:`~jitterguard.services.replay.frames.SourceError` (one-line message) for a folder that is not
    a dataroot or an unknown scene; a missing point file raises it when the sample is read.
    """

    def __init__(self, dataroot: str | Path, version: str | None = None, scene_names: Sequence[str] | None = None,
                 *, sweeps: int = 1, max_sweep_lag_s: float = 0.55, min_sweep_range_m: float = 1.0,
                 max_time_diff: float = 1.5, nan_velocity: float = 0.0) -> None:
        if sweeps < 1:
            raise ValueError("sweeps must be >= 1")
        self.root = Path(dataroot)
        self.sweeps, self.min_sweep_range_m = int(sweeps), float(min_sweep_range_m)
        root = self.root
        if why := not_a_folder(root):
            raise SourceError(why)
        self.version = find_version(root, version)
        folder = root / self.version
        t = {n: _load_table(folder, n) for n in ("scene", "sample", "sample_data", "ego_pose", "calibrated_sensor",
                                                 "sensor", "sample_annotation", "instance", "category")}
        with consistent_tables(folder):  # a damaged table: one line, not a traceback
            self._frames = self._index(t, root, scene_names, max_time_diff, nan_velocity, max_sweep_lag_s)

    def _index(self, t: dict[str, list[dict[str, Any]]], root: Path, scene_names: Sequence[str] | None,
               max_time_diff: float, nan_velocity: float, max_sweep_lag_s: float) -> list[_Keyframe]:
        """The key frames of the scenes ``scene_names`` names (every scene for None), from the tables ``t``."""
        scenes = t["scene"]
        if scene_names is not None:
            by_name = {s["name"]: s for s in scenes}
            missing = [n for n in scene_names if n not in by_name]
            if missing:
                shown = ", ".join(sorted(by_name)[:20]) + (" …" if len(by_name) > 20 else "")
                raise SourceError(f"{root}: no scene {', '.join(missing[:5])} (have: {shown})")
            scenes = [by_name[n] for n in scene_names]
        samples = {s["token"]: s for s in t["sample"]}
        sample_ts = {k: int(s["timestamp"]) for k, s in samples.items()}
        ego = {e["token"]: e for e in t["ego_pose"]}
        calib = {c["token"]: c for c in t["calibrated_sensor"]}
        channel_of = {s["token"]: s["channel"] for s in t["sensor"]}
        lidar: dict[str, dict[str, Any]] = {}
        key_sd: dict[str, dict[str, Any]] = {}
        for rec in t["sample_data"]:
            if channel_of[calib[rec["calibrated_sensor_token"]]["sensor_token"]] != CHANNEL:
                continue
            lidar[rec["token"]] = rec
            if rec.get("is_key_frame"):
                key_sd[rec["sample_token"]] = rec
        cat_name = {c["token"]: c["name"] for c in t["category"]}
        inst_class = {i["token"]: nuscenes_class(cat_name[i["category_token"]]) for i in t["instance"]}
        anns = {a["token"]: a for a in t["sample_annotation"]}
        by_sample: dict[str, list[dict[str, Any]]] = {}
        others: dict[str, list[dict[str, Any]]] = {}  # annotations of no detector class: told apart, never trained on
        for a in t["sample_annotation"]:
            (by_sample if inst_class[a["instance_token"]] >= 0 else others).setdefault(a["sample_token"], []).append(a)
        inst_cat = {i["token"]: cat_name[i["category_token"]] for i in t["instance"]}
        frames: list[_Keyframe] = []
        for sc in scenes:
            for smp in _scene_chain(sc, samples):
                sd = key_sd.get(smp["token"])
                if sd is None:
                    continue
                rows = by_sample.get(smp["token"], [])
                vel = np.array([box_velocity(a, anns, sample_ts, max_time_diff) for a in rows],
                               np.float64).reshape(-1, 3)
                mount_rot, _ = vehicle_axes(calib[sd["calibrated_sensor_token"]])
                boxes = annotations_to_sensor(rows, vel, ego[sd["ego_pose_token"]],
                                              _levelled(calib[sd["calibrated_sensor_token"]]))
                boxes[:, 7:9] = np.where(np.isnan(boxes[:, 7:9]), nan_velocity, boxes[:, 7:9])
                rest = others.get(smp["token"], [])
                centres = annotations_to_sensor(rest, np.zeros((len(rest), 3)), ego[sd["ego_pose_token"]],
                                                _levelled(calib[sd["calibrated_sensor_token"]]))[:, :2]
                frames.append(_Keyframe(
                    token=f"nuscenes/{sc['name']}/{smp['token']}", path=root / sd["filename"],
                    boxes=boxes.astype(np.float32),
                    labels=np.array([inst_class[a["instance_token"]] for a in rows], np.int64),
                    num_points=np.array([int(a.get("num_lidar_pts", 0)) for a in rows], np.int64),
                    sweeps=self._sweep_chain(sd, lidar, ego, calib, max_sweep_lag_s), mount_rotation=mount_rot,
                    unscored=tuple((inst_cat[a["instance_token"]], float(x), float(y))
                                   for a, (x, y) in zip(rest, centres))))
        return frames

    def _sweep_chain(self, sd: dict[str, Any], lidar: dict[str, dict[str, Any]], ego: dict[str, Any],
                     calib: dict[str, Any], max_lag: float) -> tuple[SweepRef, ...]:
        """Earlier sweeps of key frame ``sd`` (newest first) as :class:`SweepRef`: sensor_j → ego_j → global →
        ego_key → sensor_key, as CenterPoint's and mmdet3d's nuScenes converters chain them, the key frame's
        sensor frame in the vehicle's axes (its mounting rotation left out: the key frame's own points are
        turned into those axes when read)."""
        if self.sweeps <= 1:
            return ()
        r_ck, t_ck = _pose_matrix(_levelled(calib[sd["calibrated_sensor_token"]]))
        r_ek, t_ek = _pose_matrix(ego[sd["ego_pose_token"]])
        out: list[SweepRef] = []
        ts0 = int(sd["timestamp"])
        prev = sd.get("prev")
        while prev and len(out) < self.sweeps - 1 and prev in lidar:
            rec = lidar[prev]
            lag = 1e-6 * (ts0 - int(rec["timestamp"]))
            if lag > max_lag:
                break
            r_c, t_c = _pose_matrix(calib[rec["calibrated_sensor_token"]])
            r_e, t_e = _pose_matrix(ego[rec["ego_pose_token"]])
            # each sensor's pose in the world is ego ∘ calibrated sensor: (R_e R_c, R_e t_c + t_e)
            rot, trans = relative_transform(r_ek @ r_ck, r_ek @ t_ck + t_ek, r_e @ r_c, r_e @ t_c + t_e)
            out.append(SweepRef(self.root / rec["filename"], rot, trans, lag))
            prev = rec.get("prev")
        return tuple(out)

    def __len__(self) -> int:
        return len(self._frames)

    @property
    def tokens(self) -> list[str]:
        return [f.token for f in self._frames]

    def _read(self, path: Path) -> NDArray[np.float32]:
        try:
            raw = read_bin(path, NUSCENES_FIELDS)
        except FileNotFoundError:
            raise SourceError(f"{path}: LIDAR_TOP sweep missing from the dataroot") from None
        except (OSError, ValueError) as exc:
            raise SourceError(f"{path}: {exc}") from None
        pts = np.ascontiguousarray(raw[:, :4], np.float32)
        return pts[np.isfinite(pts).all(axis=1)]

    def points(self, i: int) -> NDArray[np.float32]:
        """The (stacked) points of key frame ``i`` in the vehicle's axes at the sensor: (P, 4), or (P, 5) with the
        time lag when ``sweeps`` > 1."""
        f = self._frames[i]
        key = self._read(f.path)
        key = turn_points(key, f.mount_rotation)
        if self.sweeps <= 1:
            return key
        earlier = [EarlierSweep(self._read(sw.path), sw.rotation, sw.translation, sw.time_lag_s) for sw in f.sweeps]
        return stack_sweeps(key, earlier, self.min_sweep_range_m)

    def _sample(self, i: int) -> Sample:
        f = self._frames[i]
        return Sample(points=self.points(i), boxes=f.boxes, labels=f.labels, num_points=f.num_points, token=f.token,
                      unscored=f.unscored)


def iter_nuscenes_samples(dataroot: str | Path, version: str | None = None,
                          scene_names: Sequence[str] | None = None, *, max_time_diff: float = 1.5,
                          nan_velocity: float = 0.0, sweeps: int = 1) -> Iterator[Sample]:
    """Like :func:`nuscenes_samples`, one key frame at a time.

    ``nan_velocity``: the value given to velocities devkit cannot estimate (0.0, see the module docstring; pass
    ``float('nan')`` to keep devkit's NaN); ``sweeps`` as :class:`NuScenesKeyframes` (a model's
    :attr:`~.inference.Detector.sweeps`)."""
    yield from NuScenesKeyframes(dataroot, version, scene_names, max_time_diff=max_time_diff,
                                 nan_velocity=nan_velocity, sweeps=sweeps)


def nuscenes_samples(dataroot: str | Path, version: str | None = None, scene_names: Sequence[str] | None = None,
                     *, max_time_diff: float = 1.5, nan_velocity: float = 0.0, sweeps: int = 1) -> list[Sample]:
    """Every LIDAR_TOP key frame of ``scene_names`` (default: all scenes, table order) of a nuScenes dataroot,
    in scene order, as sensor-frame Samples. Tokens are ``nuscenes/{scene name}/{sample token}``.

    Raises :class:`~jitterguard.services.replay.frames.SourceError` (one-line message) for a folder that is not
    a dataroot, an unknown scene or a missing sweep."""
    return list(iter_nuscenes_samples(dataroot, version, scene_names, max_time_diff=max_time_diff,
                                      nan_velocity=nan_velocity, sweeps=sweeps))


def official_split(name: str) -> list[str]:
    """Scene names of a nuScenes split (``train``, ``val``, ``test``, ``mini_train``, ``mini_val``) as
    nuscenes-devkit defines them (``nuscenes.utils.splits``; an optional dependency)."""
    try:
        from nuscenes.utils.splits import create_splits_scenes  # optional: the devkit
    except ImportError:  # pragma: no cover - depends on the environment
        raise SourceError("official nuScenes splits need nuscenes-devkit (pip install nuscenes-devkit)") from None
    splits = create_splits_scenes()
    if name not in splits:
        raise SourceError(f"unknown nuScenes split {name!r}; expected one of {', '.join(sorted(splits))}")
    return list(splits[name])


def scene_of(token: str) -> str:
    """The group a Sample token belongs to: everything before its last ``/`` (``nuscenes/scene-0523``,
    ``synthetic/mixed/3``)."""
    return token.rsplit("/", 1)[0] if "/" in token else ""


def split_holdout(samples: Sequence[Sample], last_n: int = 10) -> tuple[list[Sample], list[Sample]]:
    """(train, holdout): the last ``last_n`` samples of every scene (grouped by :func:`scene_of` of the token,
    in the order given) are held out, the rest trained on. Holding out the *end* of a scene rather than random
    key frames keeps near-duplicate neighbours (0.5 s apart) out of the held-out set."""
    if last_n < 0:
        raise ValueError("last_n must be >= 0")
    by_scene: dict[str, list[int]] = {}
    for i, s in enumerate(samples):
        by_scene.setdefault(scene_of(s.token), []).append(i)
    held = {i for rows in by_scene.values() for i in (rows[-last_n:] if last_n else [])}
    return ([s for i, s in enumerate(samples) if i not in held], [s for i, s in enumerate(samples) if i in held])

