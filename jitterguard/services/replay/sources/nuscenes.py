"""A nuScenes scene's LiDAR, read straight from the dataroot's JSON tables (no devkit needed at run time).

It walks the scene the way ``nuscenes-devkit`` does: ``scene.first_sample_token`` → ``sample.next`` …, and
for each sample the ``sample_data`` record of the channel (default ``LIDAR_TOP``) that is a key frame —
devkit's ``sample['data'][channel]``. With ``sweeps=True`` it follows that record's ``sample_data.next``
chain instead, which in a full dataroot adds the 20 Hz non-key sweeps between key frames.

Frame. The points are published in the *vehicle's axes at the sensor*: the LiDAR's returns turned by the
sensor's mounting rotation (``calibrated_sensor.rotation``), the origin left at the sensor. nuScenes' LIDAR_TOP
frame has x to the right and y forward, and is tilted against the vehicle (2.7° on scene-0523, the ground 1–2 m
higher on one side of the scan than the other at 30–40 m); the detector was trained in a level, x-forward
sensor frame, as Autoware runs CenterPoint in the vehicle's ``base_link`` axes. The published pose is then
``ego_pose ∘ (calibrated_sensor.translation, no rotation)``, so pose ∘ point is the same world point as devkit's
``ego_pose ∘ calibrated_sensor ∘ raw point`` (nuScenes quaternions are stored w, x, y, z). The tests check
tokens, files, stamps, poses and world points against devkit itself when it is installed.
"""

from __future__ import annotations

import json
import logging
from contextlib import contextmanager
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ....files import not_a_folder
from ....geometry import rotation_from_quaternion
from ..frames import EgoPose, FrameError, Item, ScanFrame, SourceError, SourceInfo, compose, finite_rows
from .base import Source
from .kitti import NUSCENES_FIELDS, read_bin

log = logging.getLogger("jitterguard.replay")

TABLES = ("scene", "sample", "sample_data", "ego_pose", "calibrated_sensor", "sensor")
FRAME_SUFFIX = "_vehicle_axes"
"""Appended to the channel in the scans' ``frame_id``: their axes are the vehicle's, not the LiDAR's own (module
doc), so a consumer holding nuScenes' own calibration cannot mistake them for ``LIDAR_TOP``."""


def find_version(dataroot: Path, version: str | None) -> str:
    """The table folder to use: ``version`` if given, else the only ``v1.0-*`` folder holding ``scene.json``."""
    if version:
        if not (dataroot / version / "scene.json").is_file():
            raise SourceError(f"{dataroot / version}: no nuScenes tables (scene.json) for version {version!r}")
        return version
    found = sorted(p.name for p in dataroot.iterdir() if p.is_dir() and (p / "scene.json").is_file())
    if not found:
        raise SourceError(f"{dataroot}: not a nuScenes dataroot (no <version>/scene.json)")
    if len(found) > 1:
        raise SourceError(f"{dataroot}: several versions {found}; pick one with --nuscenes-version")
    return found[0]


def select_scenes(scenes: list[dict[str, Any]], scene: str | None, where: object, *,
                  several: bool = False) -> list[dict[str, Any]]:
    """The rows of the ``scene`` table that ``--scene`` names: ``None`` the only scene (an error when there are
    several), else a name or token; with ``several`` also comma-separated names or tokens, in the order given
    (duplicates dropped), or ``all`` (the table's order). Raises :class:`SourceError` naming the scenes there are."""
    names = ", ".join(sorted(s["name"] for s in scenes))
    if scene is None:
        if len(scenes) != 1:
            pick = "pick with --scene NAME[,NAME…] or --scene all" if several else "pick one with --scene"
            raise SourceError(f"{where}: {len(scenes)} scenes, {pick} ({names})")
        return list(scenes)
    if several and scene.strip() == "all":
        return list(scenes)
    wanted = [w.strip() for w in scene.split(",") if w.strip()] if several else [scene]
    by_key: dict[str, dict[str, Any]] = {}
    for s in reversed(scenes):  # the first row in the table's order wins a key, as a linear search would
        by_key[s["token"]] = by_key[s["name"]] = s
    unknown = [w for w in wanted if w not in by_key]
    if unknown or not wanted:
        raise SourceError(f"{where}: no scene {', '.join(map(repr, unknown)) or repr(scene)} (have: {names})")
    return list({by_key[w]["token"]: by_key[w] for w in wanted}.values())


def is_nuscenes_root(path: Path) -> bool:
    try:
        return path.is_dir() and any((p / "scene.json").is_file() for p in path.iterdir() if p.is_dir())
    except OSError:
        return False


def _load_table(folder: Path, name: str) -> list[dict[str, Any]]:
    path = folder / f"{name}.json"
    try:
        with path.open() as fh:
            table = json.load(fh)
    except FileNotFoundError:
        raise SourceError(f"{path}: nuScenes table missing") from None
    except (OSError, ValueError) as exc:
        raise SourceError(f"{path}: unreadable nuScenes table: {exc}") from None
    if not isinstance(table, list) or not all(isinstance(row, dict) for row in table):
        raise SourceError(f"{path}: nuScenes table must be a JSON list of objects")
    return table


TABLE_FAULTS = (KeyError, TypeError, ValueError, IndexError, AttributeError)
"""What reading rows that lack a field, hold the wrong type or name a token no table holds raises."""


@contextmanager
def consistent_tables(where: object) -> Iterator[None]:
    """Run a reading of nuScenes tables, its :data:`TABLE_FAULTS` said as one :class:`SourceError` naming
    ``where``: every reader of the tables (replay, ground truth, training, adaptation) refuses a damaged dataroot
    alike, in one line (a scene row without ``first_sample_token`` had ended ``train`` in a traceback)."""
    try:
        yield
    except TABLE_FAULTS as exc:
        raise SourceError(f"{where}: inconsistent nuScenes tables ({type(exc).__name__}: {exc})") from None


def pose_from_record(rec: dict[str, Any]) -> EgoPose:
    """A nuScenes ``translation`` + ``rotation`` (w, x, y, z) record as an :class:`EgoPose`."""
    t = rec["translation"]
    w, x, y, z = rec["rotation"]
    return EgoPose(float(t[0]), float(t[1]), float(t[2]), float(x), float(y), float(z), float(w))


def turn_points(points: NDArray[np.float32], rotation: NDArray[np.float64]) -> NDArray[np.float32]:
    """``points`` (P, ≥3) with x, y, z turned by ``rotation`` (p' = R p, in float64), the other columns as they
    are: a new array (the input may be a read-only view of a file)."""
    xyz = (points[:, :3].astype(np.float64) @ rotation.T).astype(points.dtype)
    return np.column_stack([xyz, points[:, 3:]])


def vehicle_axes(calib: dict[str, Any]) -> tuple[NDArray[np.float64], EgoPose]:
    """For a ``calibrated_sensor`` record: the rotation R that turns the sensor's axes into the vehicle's
    (p_vehicle-axes = R p_sensor) and the sensor's mount with that rotation taken out (its translation only) —
    the frame every nuScenes reader here hands on (module doc)."""
    m = pose_from_record(calib)
    r = rotation_from_quaternion(m.qx, m.qy, m.qz, m.qw)
    return r, EgoPose(m.x, m.y, m.z)


class NuScenesSource(Source):
    """One scene of a nuScenes dataroot, as LiDAR scans with the sensor's world pose."""

    def __init__(
        self,
        dataroot: Path,
        *,
        scene: str | None = None,
        version: str | None = None,
        channel: str = "LIDAR_TOP",
        sweeps: bool = False,
    ) -> None:
        dataroot = Path(dataroot)
        if why := not_a_folder(dataroot):
            raise SourceError(why)
        self.dataroot = dataroot
        self.version = find_version(dataroot, version)
        folder = dataroot / self.version
        t = {name: _load_table(folder, name) for name in TABLES}
        with consistent_tables(folder):
            self._index(t, scene, channel, sweeps)
        self.channel = channel
        self.frame_id = f"{channel}{FRAME_SUFFIX}"
        self._truth: dict[int, Any] | None = None  # key-frame stamp → GroundTruthObjects, built on the first pass
        self.info = SourceInfo(
            name=f"{dataroot} ({self.scene_name}, {channel})",
            kind="points",
            num_frames=len(self.records),
            notes=[f"nuScenes {self.version} scene {self.scene_name}: {len(self.records)} {channel} scans"],
            warnings=([f"{dataroot}: the sweep chain breaks after {self.sweep_gaps} key frame(s) (a sample_data row "
                       "it names is missing): those stretches hold only the sweeps before the break"]
                      if self.sweep_gaps else [])
            + ([f"{dataroot}: --sweeps, but the scene holds no sweeps between its key frames (a keyframes-only "
                f"dataroot): replaying its {self.key_frames} key frames"]
               if sweeps and len(self.records) == self.key_frames else []),
        )

    def _index(self, t: dict[str, list[dict[str, Any]]], scene: str | None, channel: str, sweeps: bool) -> None:
        sc = select_scenes(t["scene"], scene, self.dataroot)[0]
        self.scene_name: str = sc["name"]
        self.scene_token: str = sc["token"]
        samples = {s["token"]: s for s in t["sample"]}
        ego = {e["token"]: e for e in t["ego_pose"]}
        calib = {c["token"]: c for c in t["calibrated_sensor"]}
        sensor_channel = {s["token"]: s["channel"] for s in t["sensor"]}
        sd_by_token = {sd["token"]: sd for sd in t["sample_data"]}
        keyframe_sd: dict[str, dict[str, Any]] = {}
        for sd in t["sample_data"]:
            if sd.get("is_key_frame") and sensor_channel[calib[sd["calibrated_sensor_token"]]["sensor_token"]] == channel:
                keyframe_sd[sd["sample_token"]] = sd
        chain: list[dict[str, Any]] = []
        token = sc["first_sample_token"]
        seen: set[str] = set()
        while token and token not in seen:
            seen.add(token)
            sample = samples[token]
            if token in keyframe_sd:
                chain.append(keyframe_sd[token])
            if token == sc["last_sample_token"]:
                break
            token = sample["next"]
        if not chain:
            raise SourceError(f"{self.dataroot}: scene {self.scene_name} has no {channel} key frames")
        self.sweep_gaps = 0
        self.key_frames = len(chain)
        if sweeps:  # from each key frame the sweeps up to the next: a missing row costs its stretch, not the rest
            full: list[dict[str, Any]] = []
            taken: set[str] = set()
            for k, kf in enumerate(chain):
                stop = chain[k + 1]["timestamp"] if k + 1 < len(chain) else kf["timestamp"]
                sd = kf
                while sd is not None and sd["token"] not in taken and (sd is kf or sd["timestamp"] < stop):
                    full.append(sd)
                    taken.add(sd["token"])
                    sd = sd_by_token.get(sd.get("next", ""))
                if sd is None and k + 1 < len(chain):
                    self.sweep_gaps += 1
            chain = full
        self.records = []
        for sd in chain:
            rot, mount = vehicle_axes(calib[sd["calibrated_sensor_token"]])
            self.records.append((int(sd["timestamp"]) * 1000, compose(pose_from_record(ego[sd["ego_pose_token"]]), mount),
                                 sd["filename"], rot))

    def truth(self) -> dict[int, Any]:
        """The scene's annotations per key-frame stamp (for ``jg/{ns}/groundtruth``); empty when the tables cannot
        give them (a note says why once)."""
        if self._truth is None:
            from ....eval.groundtruth import NuScenesError, load_nuscenes_frames
            from ..truth import truth_message

            try:
                _, gts = load_nuscenes_frames(self.dataroot, scene=self.scene_token, version=self.version)
                self._truth = {int(g.stamp_ns): truth_message(g) for g in gts}
            except (NuScenesError, OSError, KeyError, ValueError, TypeError, IndexError) as exc:
                # a malformed annotation row (a null translation) had raised TypeError out of the first pass: the
                # scans, which read fine, all went unpublished ("no frame could be read", exit 2)
                log.info("%s: no ground truth published: %s: %s", self.dataroot, type(exc).__name__, exc)
                self._truth = {}
        return self._truth

    def frames(self, start: int = 0) -> Iterator[Item]:
        truth = self.truth() if self.channel == "LIDAR_TOP" else {}
        for stamp_ns, pose, filename, rot in self.records[start:]:
            path = self.dataroot / filename
            try:
                pts = read_bin(path, len(NUSCENES_FIELDS))
            except FileNotFoundError:
                yield FrameError(str(path), "scan file missing from the dataroot")
                continue
            except (OSError, ValueError) as exc:
                yield FrameError(str(path), str(exc) if isinstance(exc, ValueError) else f"cannot read: {exc}")
                continue
            pts, _ = finite_rows(np.asarray(pts))
            pts = turn_points(pts, rot)  # into the vehicle's axes
            yield ScanFrame(stamp_ns, pose, pts, NUSCENES_FIELDS, str(path), self.frame_id, truth=truth.get(stamp_ns))
