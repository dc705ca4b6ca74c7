"""PCL ``.pcd`` files (ascii, binary and binary_compressed), one scan per file, read with numpy only.

Every numeric single-count field is kept as a float32 column, ``x, y, z`` first; padding (``_``) and
multi-count fields (descriptors) are dropped. The header's ``VIEWPOINT`` (tx ty tz qw qx qy qz) is the
sensor pose that PCL writes, so it becomes the frame's ego pose. Rows with a non-finite x, y or z (how
organised clouds mark missing returns) are dropped.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ..frames import (DEFAULT_PERIOD_NS, MAX_SCAN_BYTES, EgoPose, FrameError, Item, ScanFrame, SourceError, SourceInfo,
                      finite_rows, mib)
from .base import Source, listed_scans

_TYPES = {("F", 4): "<f4", ("F", 8): "<f8", ("I", 1): "i1", ("I", 2): "<i2", ("I", 4): "<i4", ("I", 8): "<i8",
          ("U", 1): "u1", ("U", 2): "<u2", ("U", 4): "<u4", ("U", 8): "<u8"}


@dataclass(frozen=True)
class PcdHeader:
    fields: list[str]
    sizes: list[int]
    types: list[str]
    counts: list[int]
    width: int
    height: int
    points: int
    viewpoint: tuple[float, ...]
    data: str
    data_offset: int

    def dtype(self) -> np.dtype:
        """Structured dtype of one point (binary layout; padding fields get unique names)."""
        parts = []
        for i, (name, size, typ, count) in enumerate(zip(self.fields, self.sizes, self.types, self.counts)):
            base = _TYPES.get((typ, size))
            if base is None:
                raise ValueError(f"field {name!r}: unsupported TYPE {typ} with SIZE {size}")
            key = name if name != "_" else f"_pad{i}"
            parts.append((key, base, (count,)) if count > 1 else (key, base))
        return np.dtype(parts)


def parse_header(raw: bytes) -> PcdHeader:
    """Parse the text header that precedes the data. Raises ``ValueError`` naming the bad line."""
    values: dict[str, list[str]] = {}
    pos = 0
    while True:
        end = raw.find(b"\n", pos)
        if end < 0:
            raise ValueError("header ends before its DATA line")
        line = raw[pos:end].decode("ascii", errors="replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *rest = line.split()
        values[key.upper()] = rest
        if key.upper() == "DATA":
            break
        if pos > 64_000:
            raise ValueError("no DATA line in the first 64 kB: not a PCD file")
    for required in ("FIELDS", "SIZE", "TYPE", "WIDTH", "HEIGHT", "DATA"):
        if required not in values:
            raise ValueError(f"header has no {required} line")
    try:
        fields = values["FIELDS"]
        sizes = [int(v) for v in values["SIZE"]]
        types = [v.upper() for v in values["TYPE"]]
        counts = [int(v) for v in values.get("COUNT", ["1"] * len(fields))]
        width, height = int(values["WIDTH"][0]), int(values["HEIGHT"][0])
        points = int(values["POINTS"][0]) if "POINTS" in values else width * height
        viewpoint = tuple(float(v) for v in values.get("VIEWPOINT", ["0", "0", "0", "1", "0", "0", "0"]))
    except (ValueError, IndexError):
        raise ValueError("malformed header numbers") from None
    if not (len(fields) == len(sizes) == len(types) == len(counts)):
        raise ValueError("FIELDS, SIZE, TYPE and COUNT disagree in length")
    if len(viewpoint) != 7:
        raise ValueError("VIEWPOINT must hold 7 numbers")
    if points != width * height or points < 0:
        raise ValueError(f"POINTS {points} != WIDTH {width} x HEIGHT {height}")
    if not {"x", "y", "z"} <= set(fields):
        raise ValueError(f"no x, y, z fields (have {fields})")
    data = values["DATA"][0].lower() if values["DATA"] else ""
    if data not in ("ascii", "binary", "binary_compressed"):
        raise ValueError(f"unsupported DATA {data!r}")
    return PcdHeader(fields, sizes, types, counts, width, height, points, viewpoint, data, pos)


def lzf_decompress(data: bytes, out_len: int) -> bytes:
    """Decompress liblzf data (what PCL's ``binary_compressed`` uses). Raises ``ValueError`` if corrupt."""
    out = bytearray()
    ip, n = 0, len(data)
    while ip < n:
        ctrl = data[ip]
        ip += 1
        if ctrl < 32:  # literal run of ctrl + 1 bytes
            run = ctrl + 1
            if ip + run > n:
                raise ValueError("compressed data truncated (literal run)")
            out += data[ip : ip + run]
            ip += run
        else:  # back reference
            length = ctrl >> 5
            if ip >= n:
                raise ValueError("compressed data truncated (back reference)")
            if length == 7:
                length += data[ip]
                ip += 1
                if ip >= n:
                    raise ValueError("compressed data truncated (back reference)")
            ref = len(out) - ((ctrl & 0x1F) << 8) - 1 - data[ip]
            ip += 1
            length += 2
            if ref < 0:
                raise ValueError("compressed data corrupt (reference before start)")
            if ref + length <= len(out):
                out += out[ref : ref + length]
            else:  # an overlapping copy repeats the last (len - ref) bytes: copied as whole repeats, not byte by
                # byte (an organised cloud's empty returns, runs at distance 1, had cost 0.3 s per 6 MB scan)
                pattern = out[ref:]
                out += (pattern * (length // len(pattern) + 1))[:length]
        if len(out) > out_len:
            raise ValueError("compressed data expands past its declared size")
    if len(out) != out_len:
        raise ValueError(f"compressed data expands to {len(out)} bytes, header says {out_len}")
    return bytes(out)


def _columns(h: PcdHeader, structured: NDArray[np.void]) -> tuple[NDArray[np.float32], tuple[str, ...]]:
    keep = [f for f, c in zip(h.fields, h.counts) if c == 1 and f != "_" and f not in ("x", "y", "z")]
    names = ("x", "y", "z", *keep)
    cols = np.empty((structured.shape[0], len(names)), dtype=np.float32)
    for j, name in enumerate(names):
        cols[:, j] = structured[name]
    return cols, names


ASCII_CHUNK_BYTES = 4 << 20
"""ASCII data is parsed this many bytes (whole lines) at a time: one ``split`` of a whole 5-million-point file had
held 20 million Python strings at once (2 GB for a 160 MB file)."""


def _ascii_values(body: bytes) -> NDArray[np.float64]:
    """Every number of an ascii PCD's data, in order; ``ValueError`` on bytes that are not text or a token that is no
    number. Parsed in whole-line chunks of :data:`ASCII_CHUNK_BYTES`, so memory grows with the values, not with a
    Python string per value."""
    parts: list[NDArray[np.float64]] = []
    pos = 0
    while pos < len(body):
        end = body.find(b"\n", pos + ASCII_CHUNK_BYTES)
        end = len(body) if end < 0 else end + 1
        try:
            parts.append(np.array(body[pos:end].decode("ascii").split(), dtype=np.float64))
        except UnicodeDecodeError:
            raise ValueError("ascii data holds non-text bytes") from None
        except ValueError:
            raise ValueError("ascii data holds a value that is not a number") from None
        pos = end
    return np.concatenate(parts) if parts else np.empty(0, dtype=np.float64)


TEXT_FACTOR = 4
"""How much larger than a scan its PCD file may be: an ``ascii`` value takes up to about four times the bytes of
its float32 ("-123.456789 "); a binary file is the scan plus its header."""


def read_pcd(path: Path, max_bytes: int = MAX_SCAN_BYTES) -> tuple[NDArray[np.float32], tuple[str, ...], EgoPose]:
    """Read a PCD file: (points (P, F) float32 with x, y, z first, field names, viewpoint pose).

    Bounded before the work, as :func:`~.kitti.read_bin` is: a file over :data:`TEXT_FACTOR` × ``max_bytes`` (the
    detector's ``max_scan_bytes``) is refused from its ``fstat`` unread, and a header whose ``POINTS`` × point size
    is over ``max_bytes`` before its data is decoded — a few MB of ``binary_compressed`` data whose header claimed
    a billion points had been expanded (and its buffer allocated) in full, and any file had been read whole."""
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        if size > TEXT_FACTOR * max_bytes:
            raise ValueError(f"{size} bytes ({mib(size)}) is over the {mib(TEXT_FACTOR * max_bytes)} a PCD file of a "
                             f"scan may be ({TEXT_FACTOR} × the detector's max_scan_bytes): not read")
        raw = f.read(size)
    h = parse_header(raw)
    dt = h.dtype()
    if h.points * dt.itemsize > max_bytes:
        raise ValueError(f"its {h.points} points of {dt.itemsize} bytes ({mib(h.points * dt.itemsize)}) are over the "
                         f"{mib(max_bytes)} a scan may be (the detector's max_scan_bytes): not decoded")
    body = raw[h.data_offset :]
    if h.data == "binary":
        need = h.points * dt.itemsize
        if len(body) < need:
            raise ValueError(f"binary data holds {len(body)} bytes, {h.points} points need {need}: truncated")
        arr = np.frombuffer(body, dtype=dt, count=h.points)
    elif h.data == "binary_compressed":
        if len(body) < 8:
            raise ValueError("binary_compressed data truncated (no size words)")
        csize, usize = struct.unpack("<II", body[:8])
        if usize != h.points * dt.itemsize:
            raise ValueError(f"uncompressed size {usize} != {h.points} points x {dt.itemsize} bytes")
        if len(body) < 8 + csize:
            raise ValueError(f"compressed data holds {len(body) - 8} bytes, header says {csize}: truncated")
        flat = lzf_decompress(body[8 : 8 + csize], usize)
        # Field-major layout: all points' first field, then all points' second field, ...
        arr = np.empty(h.points, dtype=dt)
        off = 0
        for name in dt.names or ():
            sub = dt.fields[name][0]  # type: ignore[index]
            n = sub.itemsize * h.points
            arr[name] = np.frombuffer(flat[off : off + n], dtype=sub.base).reshape((h.points, *sub.shape))
            off += n
    else:
        total = sum(h.counts)
        vals = _ascii_values(body)
        if vals.size < h.points * total:
            raise ValueError(f"ascii data holds {vals.size} values, {h.points} points need {h.points * total}: truncated")
        flat = vals[: h.points * total].reshape(h.points, total)
        arr = np.empty(h.points, dtype=dt)
        col = 0
        for name, count in zip(dt.names or (), h.counts):
            arr[name] = flat[:, col] if count == 1 else flat[:, col : col + count]
            col += count
    pts, names = _columns(h, arr)
    tx, ty, tz, qw, qx, qy, qz = h.viewpoint
    return pts, names, EgoPose(tx, ty, tz, qx, qy, qz, qw if (qw or qx or qy or qz) else 1.0)


class PcdSource(Source):
    """A folder of ``.pcd`` files (in numeric order of their names, hidden ones skipped; 10 Hz stamps unless
    ``period_ns`` says otherwise) or one file."""

    def __init__(self, path: Path, *, period_ns: int = DEFAULT_PERIOD_NS, frame_id: str = "lidar") -> None:
        path = Path(path)
        if path.is_dir():
            files = listed_scans(path, lambda name: name.lower().endswith(".pcd"))
            if not files:
                raise SourceError(f"{path}: no .pcd files in this folder")
        elif path.is_file():
            files = [path]
        else:
            raise SourceError(f"{path}: no such file or folder")
        self.files = files
        self.period_ns = period_ns
        self.frame_id = frame_id
        self.info = SourceInfo(name=str(path), kind="points", num_frames=len(files), period_ns=period_ns)

    def frames(self, start: int = 0) -> Iterator[Item]:
        for i in range(start, len(self.files)):
            f = self.files[i]
            try:
                pts, names, pose = read_pcd(f)
            except OSError as exc:
                yield FrameError(str(f), f"cannot read: {exc.strerror or exc}")
                continue
            except ValueError as exc:
                yield FrameError(str(f), f"not a valid PCD file: {exc}")
                continue
            pts, _ = finite_rows(pts)
            yield ScanFrame(i * self.period_ns, pose, pts, names, str(f), self.frame_id)
