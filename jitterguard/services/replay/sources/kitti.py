"""Raw float32 scan files: KITTI velodyne ``.bin`` (x, y, z, reflectance) and nuScenes ``.pcd.bin``
(x, y, z, intensity, ring), one file per scan, with optional KITTI odometry poses and times.

KITTI odometry poses (``poses/NN.txt``) are 3x4 ``[R|t]`` per line: the pose of the *left camera* at scan i
in the camera frame of scan 0 (x right, y down, z forward). The replay contract wants the LiDAR's pose in a
z-up world, so each pose is conjugated with the velodyne-to-camera extrinsic ``Tr`` from ``calib.txt``:
``T_world_velo(i) = Tr⁻¹ · P_i · Tr`` — the world is the LiDAR frame of scan 0. Without a calib file the
nominal axis permutation (camera x = −velo y, y = −velo z, z = velo x) stands in for ``Tr``; it ignores the
≈0.3 m lever arm and sub-degree mounting error, which is why a calib file found next to the data wins.
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ....schemas.models import INT64_MAX
from ..frames import (DEFAULT_PERIOD_NS, IDENTITY, MAX_SCAN_BYTES, EgoPose, FrameError, Item, ScanFrame, SourceError,
                      SourceInfo, finite_rows, mib)
from .base import Source, listed_scans

log = logging.getLogger("jitterguard.replay")

KITTI_FIELDS = ("x", "y", "z", "intensity")
NUSCENES_FIELDS = ("x", "y", "z", "intensity", "ring")

NOMINAL_TR = np.array(
    [[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)
"""Velodyne -> camera axes of the KITTI rig without its lever arm: the fallback when no calib.txt is given."""


def fields_for(path: Path) -> tuple[str, ...]:
    """Column names implied by the file name: ``*.pcd.bin`` is nuScenes (5 columns), ``*.bin`` is KITTI (4)."""
    return NUSCENES_FIELDS if path.name.lower().endswith(".pcd.bin") else KITTI_FIELDS


def read_bin(path: Path, num_fields: int, max_bytes: int = MAX_SCAN_BYTES) -> NDArray[np.float32]:
    """Read one raw float32 scan as (P, num_fields), read-only. Raises ``ValueError`` on a size that is not whole
    rows, or over ``max_bytes`` (the detector's ``max_scan_bytes``: such a scan is refused unread downstream) — told
    from the open file's ``fstat`` before a byte is read: a mistaken multi-gigabyte file named ``.bin`` had been read
    whole into memory. The open file's ``fstat``, not a ``stat`` of the path: no second lookup on a network file
    system, where a stat per scan had cost more than the read. 0 bytes is a scan of 0 points, as a PCD's ``POINTS
    0`` is: a raw scan has no header, and nothing is how it writes a LiDAR that returned nothing."""
    row = 4 * num_fields
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        if size > max_bytes:
            raise ValueError(f"{size} bytes ({mib(size)}) is over the {mib(max_bytes)} a scan may be (the detector's"
                             " max_scan_bytes): not read")
        raw = f.read(size)  # the size it had when checked, should the file grow meanwhile
    if len(raw) % row:
        raise ValueError(
            f"{len(raw)} bytes is not a whole number of {num_fields}-float32 points ({row} bytes each): truncated or not a scan"
        )
    return np.frombuffer(raw, dtype="<f4").reshape(-1, num_fields)


def _read_matrix_lines(path: Path, what: str) -> list[NDArray[np.float64]]:
    """Lines of 12 floats as 4x4 homogeneous matrices; errors name the file and line. A rotation part whose
    determinant is not positive (a reflection, or all zeros as a placeholder line) is refused: the first had ended
    the replay with "matrix is a reflection" naming neither file nor line, the second was silently replaced by
    whatever rotation its re-orthonormalisation gave."""
    out: list[NDArray[np.float64]] = []
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise SourceError(f"{path}: cannot read {what}: {exc}") from None
    for lineno, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        try:
            vals = [float(v) for v in line.split()]
        except ValueError:
            raise SourceError(f"{path}:{lineno}: {what} line is not 12 numbers") from None
        if len(vals) != 12 or not np.all(np.isfinite(vals)):  # "got 12" had been the answer to 12 with a nan
            bad = next((v for v in vals if not np.isfinite(v)), None)
            got = f"a non-finite one ({bad})" if len(vals) == 12 else str(len(vals))
            raise SourceError(f"{path}:{lineno}: {what} line must hold 12 finite numbers, got {got}")
        m = np.eye(4)
        m[:3, :] = np.array(vals).reshape(3, 4)
        if not np.linalg.det(m[:3, :3]) > 0:
            raise SourceError(f"{path}:{lineno}: {what} line's 3x3 part is no rotation (determinant"
                              f" {np.linalg.det(m[:3, :3]):.3g})")
        out.append(m)
    return out


def read_poses(path: Path) -> list[NDArray[np.float64]]:
    """KITTI odometry poses file: one 3x4 row-major ``[R|t]`` per line."""
    poses = _read_matrix_lines(path, "pose")
    if not poses:
        raise SourceError(f"{path}: poses file holds no pose")
    return poses


def read_calib_tr(path: Path) -> NDArray[np.float64]:
    """The ``Tr:`` (velodyne -> camera 0) line of a KITTI odometry ``calib.txt``."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise SourceError(f"{path}: cannot read calib: {exc}") from None
    for line in text.splitlines():
        if line.startswith("Tr:") or line.startswith("Tr_velo_to_cam:"):
            vals = line.split(":", 1)[1].split()
            try:
                arr = np.array([float(v) for v in vals])
            except ValueError:
                break
            if arr.size == 12 and np.all(np.isfinite(arr)):
                m = np.eye(4)
                m[:3, :] = arr.reshape(3, 4)
                if np.linalg.det(m[:3, :3]) > 0:  # a rotation, not a reflection or zeros (_read_matrix_lines)
                    return m
            break
    raise SourceError(f"{path}: no valid 'Tr:' line (12 numbers, its 3x3 part a rotation) in calib file")


def read_times(path: Path) -> list[int]:
    """KITTI ``times.txt``: seconds since the start of the sequence, one per line, as integer ns."""
    out: list[int] = []
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise SourceError(f"{path}: cannot read times: {exc}") from None
    for lineno, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            t = float(line.split()[0])
        except ValueError:
            raise SourceError(f"{path}:{lineno}: not a time in seconds") from None
        if not np.isfinite(t) or t < 0:
            raise SourceError(f"{path}:{lineno}: time must be finite and >= 0")
        if t * 1e9 >= INT64_MAX:  # a header stamp is int64 ns: had been a ValidationError traceback at the replay
            raise SourceError(f"{path}:{lineno}: time {t:g} s is past what an int64 stamp in ns holds (~9.2e9 s)")
        out.append(int(round(t * 1e9)))
    return out


def velo_poses(cam_poses: list[NDArray[np.float64]], tr: NDArray[np.float64]) -> list[EgoPose]:
    """``Tr⁻¹ · P_i · Tr`` for each camera pose: LiDAR poses in the z-up frame of the first scan."""
    tr_inv = np.linalg.inv(tr)
    return [EgoPose.from_matrix(tr_inv @ p @ tr) for p in cam_poses]


def _first_existing(*candidates: Path | None) -> Path | None:
    for c in candidates:
        if c is not None and c.is_file():
            return c
    return None


_NUM = re.compile(r"^(\d+)")


def _nuscenes_root_above(folder: Path) -> Path | None:
    """The nuScenes dataroot that ``folder`` lies in (``samples/LIDAR_TOP`` or ``sweeps/LIDAR_TOP`` of it), if any."""
    from .nuscenes import is_nuscenes_root

    for up in list(folder.parents)[:3]:
        if is_nuscenes_root(up):
            return up
    return None


class BinScanSource(Source):
    """A folder of ``.bin`` / ``.pcd.bin`` scans (in numeric order of their names, hidden ones such as macOS'
    ``._*`` skipped) or one such file."""

    def __init__(
        self,
        path: Path,
        *,
        poses: Path | None = None,
        calib: Path | None = None,
        times: Path | None = None,
        fields: tuple[str, ...] | None = None,
        period_ns: int = DEFAULT_PERIOD_NS,
        frame_id: str | None = None,
    ) -> None:
        path = Path(path)
        if path.is_dir():
            files = listed_scans(path, lambda name: name.lower().endswith(".bin"))
            if not files:
                raise SourceError(f"{path}: no .bin scans in this folder")
        elif path.is_file():
            files = [path]
        else:
            raise SourceError(f"{path}: no such file or folder")
        self.path = path
        self.files = files
        # each file in its own layout (a folder may mix nuScenes' 5-column and KITTI's 4-column scans, as
        # ../shared/data/single-frames does), unless --bin-fields names one for all
        self.file_fields = [tuple(fields) if fields else fields_for(f) for f in files]
        if fields and tuple(fields[:3]) != ("x", "y", "z"):  # the file-name layouts all start x, y, z
            raise SourceError(f"--bin-fields must start with x,y,z, got {','.join(fields)}")
        if fields and (not all(fields) or len(set(fields)) != len(fields)):  # as the wire's PointCloud wants them:
            # "x,y,z,x" had ended the replay at its first scan with a multi-line validation error and exit 1, and
            # "x,y,z,,i" had published a column without a name
            raise SourceError(f"--bin-fields: each column needs a name of its own, got {','.join(fields)}")
        self.period_ns = period_ns
        nusc = [f.name.lower().endswith(".pcd.bin") for f in files]
        self.file_frame_ids = [frame_id or ("LIDAR_TOP" if n else "velodyne") for n in nusc]
        folder = path if path.is_dir() else path.parent
        notes: list[str] = []

        self.poses: list[EgoPose] | None = None
        if poses is not None:
            if not Path(poses).is_file():
                raise SourceError(f"{poses}: poses file not found")
            calib_path = _first_existing(calib, folder / "calib.txt", folder.parent / "calib.txt")
            if calib is not None and calib_path != calib:
                raise SourceError(f"{calib}: calib file not found")
            if calib_path is not None:
                tr = read_calib_tr(calib_path)
                notes.append(f"poses from {poses} with Tr from {calib_path}")
            else:
                tr = NOMINAL_TR
                notes.append(f"poses from {poses}; no calib.txt found, using the nominal velodyne->camera axes")
            self.poses = velo_poses(read_poses(Path(poses)), tr)
        elif calib is not None:
            raise SourceError("--calib only makes sense with --poses")

        times_path = _first_existing(times, folder / "times.txt", folder.parent / "times.txt")
        if times is not None and times_path != times:
            raise SourceError(f"{times}: times file not found")
        self.times = read_times(times_path) if times_path else None
        if times_path:
            notes.append(f"stamps from {times_path}")
        # KITTI numbers scans 000000.bin, 000001.bin...: the poses/times row is the file number when every
        # name is a number, so a folder holding a slice of a sequence still finds its own poses.
        nums = [_NUM.match(p.name) for p in files]
        self.rows = [int(m.group(1)) for m in nums] if all(nums) and not any(nusc) else list(range(len(files)))
        warnings = []
        if len(set(nusc)) > 1 and fields is None:
            warnings.append(f"{path}: mixes nuScenes .pcd.bin and KITTI .bin scans: each is read in its own "
                            "layout, but as one stream their stamps and poses mean nothing")
        if any(nusc):  # what a file name says it is, whatever columns --bin-fields reads from it
            root = _nuscenes_root_above(folder)
            how = (f"; replay the dataroot {root} instead, which turns them into the vehicle's axes and gives each its"
                   " ego pose" if root is not None else "")
            warnings.append(f"{path}: nuScenes .pcd.bin scans are in LIDAR_TOP's own frame (x to the right, not level),"
                            f" not the level x-forward frame the detector works in{how}")
        if self.times is not None and max(self.rows) >= len(self.times):
            warnings.append(f"{times_path}: {len(self.times)} times for scan rows up to {max(self.rows)}: the scans past"
                            " its end have no stamp and are skipped")
        if self.poses is None and len(files) > 1:
            warnings.append(f"{path}: {len(files)} scans and no --poses: every scan is published at the identity"
                            " pose, so if the sensor moved, static objects will look dynamic")
        self.info = SourceInfo(name=str(path), kind="points", num_frames=len(files), notes=notes, warnings=warnings,
                               period_ns=period_ns if self.times is None else None)

    def _pose(self, i: int) -> EgoPose | str:
        if self.poses is None:
            return IDENTITY
        row = self.rows[i]
        if row >= len(self.poses):
            return f"no pose for scan row {row} (poses file has {len(self.poses)} lines)"
        return self.poses[row]

    def _stamp(self, i: int) -> int | str:
        """The scan's stamp, or why it has none: a scan past the end of times.txt had taken ``row × period`` after
        the file's last time — back in time, which the replay then stamped 1 ns apart. Without times the scans are
        ``period`` apart in the folder's order, as .pcd files are: the file number had been taken for the row of
        time too, so scans named by their own timestamp (``1733450000123456.bin``, µs) were stamped 10⁵ periods
        apart (hours at ``--rate 1``) or past the wire's int64 nanoseconds (a multi-line error, nothing replayed)."""
        if self.times is None:
            return i * self.period_ns
        row = self.rows[i]
        if row >= len(self.times):
            return f"no time for scan row {row} (times file has {len(self.times)} lines)"
        return self.times[row]

    def frames(self, start: int = 0) -> Iterator[Item]:
        for i in range(start, len(self.files)):
            f = self.files[i]
            try:
                pts = read_bin(f, len(self.file_fields[i]))
            except (OSError, ValueError) as exc:
                yield FrameError(str(f), str(exc) if isinstance(exc, ValueError) else f"cannot read: {exc.strerror or exc}")
                continue
            pose = self._pose(i)
            if isinstance(pose, str):
                yield FrameError(str(f), pose)
                continue
            stamp = self._stamp(i)
            if isinstance(stamp, str):
                yield FrameError(str(f), stamp)
                continue
            pts, _ = finite_rows(pts)
            yield ScanFrame(stamp, pose, pts, self.file_fields[i], str(f), self.file_frame_ids[i])
