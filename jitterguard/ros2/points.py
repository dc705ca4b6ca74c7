"""A wire scan's float32 columns as the bytes of a ``sensor_msgs/PointCloud2`` in one of two layouts:

- ``xyzirc`` — Autoware's ``autoware_point_types::PointXYZIRC``, what its LiDAR pipeline (the pointcloud
  preprocessor, CenterPoint, BEVFusion) takes: float32 x, y, z; uint8 intensity; uint8 return_type; uint16 channel,
  in that order at offsets 0, 4, 8, 12, 13, 14, 16-byte points. Autoware checks each of the first six fields' name,
  offset, datatype and count (``is_data_layout_compatible_with_point_xyzirc``) and refuses a cloud that differs.
  The intensity goes on its drivers' 0–255 scale (a 0–1 reflectance such as KITTI's is scaled by the rule the
  detector reads scans with; rounded, clamped, a non-finite one 0); the
  channel is the wire's ``channel`` or ``ring`` column (the laser's index), return_type its ``return_type``, each 0
  where the scan has none (unknown), clamped to the type's range.
- ``float32`` — every wire column as it came, float32 at 4-byte offsets (the bytes the wire sent; lossless for
  fields XYZIRC has no room for, such as a sweep's time lag).

Pure: column names and bytes in, PointField tuples and bytes out.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..services.detector.adapter import intensity_to_network_scale

FLOAT32, UINT8, UINT16 = 7, 2, 4
"""``sensor_msgs/msg/PointField`` datatypes."""
LAYOUTS = ("xyzirc", "float32")
DEFAULT_LAYOUT = "xyzirc"
XYZIRC_DTYPE = np.dtype({"names": ["x", "y", "z", "intensity", "return_type", "channel"],
                         "formats": ["<f4", "<f4", "<f4", "u1", "u1", "<u2"],
                         "offsets": [0, 4, 8, 12, 13, 14], "itemsize": 16})
XYZIRC_FIELDS = (("x", 0, FLOAT32), ("y", 4, FLOAT32), ("z", 8, FLOAT32), ("intensity", 12, UINT8),
                 ("return_type", 13, UINT8), ("channel", 14, UINT16))
"""(name, offset, datatype) of PointXYZIRC's fields, in Autoware's ``PointXYZIRCIndex`` order."""


def _clamped(col: np.ndarray, hi: int, dtype: str) -> np.ndarray:
    """``col`` rounded into 0..``hi`` as ``dtype``; a non-finite value is 0 (a NaN has no integer, and a dark
    return is what a driver writes for one it could not measure)."""
    out = np.where(np.isfinite(col), np.rint(col), 0.0)
    return np.clip(out, 0, hi).astype(dtype)


def cloud_layout(fields: Sequence[str], data: bytes, layout: str = DEFAULT_LAYOUT
                 ) -> tuple[list[tuple[str, int, int]], int, bytes, bool]:
    """The PointCloud2 of a wire scan (``fields`` names its float32 columns, ``data`` their rows): the fields as
    (name, offset, datatype), the point step, the bytes, and ``is_dense`` (every x, y, z finite — PCL's sense,
    which a reader trusts to skip its NaN checks; in the float32 layout every value, as it is all of the point)."""
    if layout not in LAYOUTS:
        raise ValueError(f"points layout {layout!r}: use one of {', '.join(LAYOUTS)}")
    cols = np.frombuffer(data, dtype="<f4").reshape(-1, len(fields))
    if layout == "float32":
        return ([(name, 4 * j, FLOAT32) for j, name in enumerate(fields)], 4 * len(fields), bytes(data),
                bool(np.isfinite(cols).all()))
    index = {name: j for j, name in enumerate(fields)}
    out = np.zeros(cols.shape[0], dtype=XYZIRC_DTYPE)
    for axis in ("x", "y", "z"):
        out[axis] = cols[:, index[axis]]
    if "intensity" in index:  # a 0–1 reflectance (KITTI) to 0–255 by the detector's own rule, then rounded
        pts = np.zeros((cols.shape[0], 4), dtype=np.float32)
        pts[:, 3] = np.nan_to_num(cols[:, index["intensity"]], nan=0.0)
        out["intensity"] = _clamped(intensity_to_network_scale(pts)[:, 3], 255, "u1")
    if "return_type" in index:
        out["return_type"] = _clamped(cols[:, index["return_type"]], 255, "u1")
    channel = index.get("channel", index.get("ring"))
    if channel is not None:
        out["channel"] = _clamped(cols[:, channel], 65535, "<u2")
    dense = bool(np.isfinite(cols[:, [index["x"], index["y"], index["z"]]]).all())
    return list(XYZIRC_FIELDS), XYZIRC_DTYPE.itemsize, out.tobytes(), dense
