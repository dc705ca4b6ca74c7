"""Fixed-shape msgpack records, many at a time: a numpy structured array whose bytes *are* the msgpack.

Why: the tracker publishes, and the classifier reads and republishes, ~200 ``TrackedObject``s 20 times a
second. Each is a nested map of ~150 numbers; building and walking those maps in Python cost several
milliseconds a frame, most of the pipeline's latency budget. But msgpack lets a map of a fixed shape be written
with fixed widths — a float is always ``0xcb`` + 8 big-endian bytes, a small bounded int a one-byte fixint, a
bool one byte, a string of known length its header + bytes — and msgspec and msgpack-python write exactly that
for these types. So one record of a given shape has the same bytes everywhere except its values, and N records
are a numpy structured array with one field per value: writing them is a few column assignments, and reading
them back is a ``frombuffer`` plus vectorised checks.

A :class:`RecordLayout` is built from a message type's generated Struct (:func:`~.fast.struct_type`, so the
value rules are the contract's: bounds, patterns, finiteness) and an example that fixes the shape (list lengths,
string lengths). :meth:`RecordLayout.pack` writes records; :meth:`RecordLayout.view` reads a buffer back only if
every record has exactly that shape *and* every value passes the model's rules — otherwise it returns ``None``
and the caller uses the general decoder, which decides (so the fast path never accepts what the model refuses).
"""

from __future__ import annotations

import re
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import msgspec
import numpy as np


@dataclass(frozen=True)
class Slot:
    """One value (or a fixed-length tuple of floats) inside a record: where it is and what it may hold."""

    name: str
    kind: str  # "float", "floats" (a tuple), "fixint", "int64", "bool", "str"
    offset: int
    count: int = 1  # items of a "floats" tuple; bytes of a "str"
    lo: Any = None  # inclusive bounds (floats: per item for "floats"; ints)
    hi: Any = None
    lo_open: bool = False  # gt rather than ge
    hi_open: bool = False
    pattern: re.Pattern[str] | None = None


class RecordLayout:
    """Records of one Struct type and one shape. Build with :meth:`of`."""

    def __init__(self, template: bytes, slots: list[Slot]) -> None:
        self.itemsize = len(template)
        self.template = np.frombuffer(template, dtype=np.uint8).copy()
        self.slots = {s.name: s for s in slots}
        mask = np.ones(self.itemsize, dtype=bool)  # bytes that are the same in every record of this shape
        names, formats, offsets = [], [], []
        for s in slots:
            names.append(s.name)
            offsets.append(s.offset)
            if s.kind == "floats":
                item = np.dtype({"names": ["v"], "formats": [">f8"], "offsets": [1], "itemsize": 9})
                formats.append((item, (s.count,)))
                for k in range(s.count):
                    mask[s.offset + 9 * k + 1: s.offset + 9 * k + 9] = False
            else:
                fmt = {"float": ">f8", "int64": ">i8", "fixint": "u1", "bool": "u1", "str": f"S{s.count}"}[s.kind]
                formats.append(fmt)
                mask[s.offset: s.offset + np.dtype(fmt).itemsize] = False
        self.dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": self.itemsize})
        self._const_idx = np.flatnonzero(mask)
        self._const = self.template[self._const_idx]
        # Every float of a record (single or in a tuple) gathered by one fancy index, checked in one pass.
        starts, lo, hi, lo_open, hi_open = [], [], [], [], []
        for s in slots:
            if s.kind == "float":
                starts.append(s.offset)
                lo.append(s.lo)
                hi.append(s.hi)
                lo_open.append(s.lo_open)
                hi_open.append(s.hi_open)
            elif s.kind == "floats":
                starts += [s.offset + 9 * k + 1 for k in range(s.count)]
                lo += list(s.lo)
                hi += list(s.hi)
                lo_open += [False] * s.count
                hi_open += [False] * s.count
        self._float_idx = (np.asarray(starts, dtype=np.intp)[:, None] + np.arange(8)).ravel()
        self._float_lo, self._float_hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
        self._float_lo_open, self._float_hi_open = np.asarray(lo_open), np.asarray(hi_open)
        small = [s for s in slots if s.kind in ("fixint", "bool")]
        self._byte_idx = np.asarray([s.offset for s in small], dtype=np.intp)
        self._byte_lo = np.asarray([0xC2 if s.kind == "bool" else s.lo + s.lo_open for s in small])
        self._byte_hi = np.asarray([0xC3 if s.kind == "bool" else s.hi - s.hi_open for s in small])
        self._other = [s for s in slots if s.kind in ("int64", "str")]

    # ------------------------------------------------------------------ building

    @classmethod
    def of(cls, struct_type: type[msgspec.Struct], example: msgspec.Struct) -> RecordLayout:
        """The layout of ``example``'s shape (its list and string lengths) under ``struct_type``'s rules."""
        out = bytearray()
        slots: list[Slot] = []
        _emit(msgspec.inspect.type_info(struct_type), example, "", out, slots)
        return cls(bytes(out), slots)

    # ------------------------------------------------------------------ writing

    def pack(self, n: int, columns: Mapping[str, Any]) -> np.ndarray:
        """``n`` records, the example's values except where ``columns`` (slot name -> length-``n`` values;
        ``(n, count)`` for a float tuple) says otherwise. Bools are given as bools, strings as str or bytes of
        the slot's exact length. Raises ValueError for a value the layout cannot hold (wrong string length)."""
        raw = np.tile(self.template, n)
        rec = raw.view(self.dtype)
        for name, values in columns.items():
            s = self.slots[name]
            if s.kind == "floats":
                rec[name]["v"] = values
            elif s.kind == "bool":
                rec[name] = np.where(np.asarray(values, dtype=bool), 0xC3, 0xC2)
            elif s.kind == "str":
                arr = np.asarray([v.encode() if isinstance(v, str) else v for v in values], dtype=f"S{s.count}")
                if n and (np.char.str_len(arr) != s.count).any():
                    raise ValueError(f"{name}: every value must be {s.count} bytes long")
                rec[name] = arr
            else:
                rec[name] = values
        return rec

    # ------------------------------------------------------------------ reading

    def view(self, data: bytes | memoryview, n: int) -> np.ndarray | None:
        """``data`` as ``n`` records, read-only, if it is exactly that and every value is valid; else None."""
        if len(data) != n * self.itemsize:
            return None
        raw = np.frombuffer(data, dtype=np.uint8)
        if n == 0:
            return raw.view(self.dtype)
        rows = raw.reshape(n, self.itemsize)
        if not (rows[:, self._const_idx] == self._const).all():
            return None
        small = rows[:, self._byte_idx]
        if not ((small >= self._byte_lo) & (small <= self._byte_hi)).all():
            return None
        v = np.ascontiguousarray(rows[:, self._float_idx]).view(">f8")  # (n, floats a record); NaN fails all
        ok = np.where(self._float_lo_open, v > self._float_lo, v >= self._float_lo)
        ok &= np.where(self._float_hi_open, v < self._float_hi, v <= self._float_hi)
        if not ok.all():
            return None
        rec = raw.view(self.dtype)
        for s in self._other:
            if not _valid(s, rec[s.name]):
                return None
        return rec

    @staticmethod
    def to_bytes(records: np.ndarray) -> bytes:
        """The records' msgpack bytes (the constant bytes between fields included)."""
        return records.view(np.uint8).tobytes()

    @staticmethod
    def copy(records: np.ndarray) -> np.ndarray:
        """A writable copy of ``records``. Not ``ndarray.copy``: that leaves out the bytes between fields."""
        return records.view(np.uint8).copy().view(records.dtype)


def _valid(s: Slot, col: np.ndarray) -> bool:
    """The checks :meth:`RecordLayout.view` does not batch: strings and 64-bit ints."""
    if s.kind == "str":
        if (np.char.str_len(col) != s.count).any():  # a trailing NUL byte: let the general decoder decide
            return False
        try:
            values = [b.decode() for b in col.tolist()]
        except UnicodeDecodeError:
            return False
        return s.pattern is None or all(map(s.pattern.fullmatch, values))
    ok = (col > s.lo) if s.lo_open else (col >= s.lo)
    ok &= (col < s.hi) if s.hi_open else (col <= s.hi)
    return bool(ok.all())


def _bounds(t: Any, lo: float, hi: float) -> tuple[Any, Any, bool, bool]:
    glo = t.gt if t.gt is not None else t.ge
    ghi = t.lt if t.lt is not None else t.le
    return (lo if glo is None else glo, hi if ghi is None else ghi, t.gt is not None, t.lt is not None)


def _str_header(n: int) -> bytes:
    if n < 32:
        return bytes([0xA0 | n])
    if n < 256:
        return bytes([0xD9, n])
    return bytes([0xDA]) + n.to_bytes(2, "big")


def array_header(n: int) -> bytes:
    """A msgpack array header for ``n`` items."""
    if n < 16:
        return bytes([0x90 | n])
    if n < 0x10000:
        return bytes([0xDC]) + n.to_bytes(2, "big")
    return bytes([0xDD]) + n.to_bytes(4, "big")


def _map_header(n: int) -> bytes:
    return bytes([0x80 | n]) if n < 16 else bytes([0xDE]) + n.to_bytes(2, "big")


def _emit(t: Any, value: Any, name: str, out: bytearray, slots: list[Slot]) -> None:
    """Append ``value``'s fixed-width bytes under type info ``t``, recording where each value sits."""
    ti = msgspec.inspect
    if isinstance(t, ti.StructType):
        out += _map_header(len(t.fields))
        for f in t.fields:
            out += msgspec.msgpack.encode(f.encode_name)
            _emit(f.type, getattr(value, f.name), f"{name}.{f.encode_name}" if name else f.encode_name, out, slots)
    elif isinstance(t, ti.FloatType):
        lo, hi, lo_open, hi_open = _bounds(t, -np.inf, np.inf)
        out += b"\xcb"
        slots.append(Slot(name, "float", len(out), lo=lo, hi=hi, lo_open=lo_open, hi_open=hi_open))
        out += struct.pack(">d", value)
    elif isinstance(t, ti.BoolType):
        slots.append(Slot(name, "bool", len(out)))
        out += b"\xc3" if value else b"\xc2"
    elif isinstance(t, ti.IntType):
        lo, hi, lo_open, hi_open = _bounds(t, -(2**63), 2**63 - 1)
        if t.multiple_of is not None:
            raise TypeError(f"{name}: multiple_of is not supported in a record layout")
        least, most = (lo + 1 if lo_open else lo), (hi - 1 if hi_open else hi)
        if least >= 0 and most <= 127:  # always written as one byte (a positive fixint)
            slots.append(Slot(name, "fixint", len(out), lo=lo, hi=hi, lo_open=lo_open, hi_open=hi_open))
            out += bytes([int(value)])
        else:
            out += b"\xd3"
            slots.append(Slot(name, "int64", len(out), lo=lo, hi=hi, lo_open=lo_open, hi_open=hi_open))
            out += int(value).to_bytes(8, "big", signed=True)
    elif isinstance(t, ti.StrType):
        data = value.encode()
        if (t.min_length is not None and len(value) < t.min_length) or \
                (t.max_length is not None and len(value) > t.max_length):
            raise ValueError(f"{name}: the example's length breaks the field's rules")
        out += _str_header(len(data))
        pattern = re.compile(t.pattern) if t.pattern else None
        slots.append(Slot(name, "str", len(out), count=len(data), pattern=pattern))
        out += data
    elif isinstance(t, ti.TupleType) and t.item_types and all(isinstance(i, ti.FloatType) for i in t.item_types):
        n = len(t.item_types)
        out += array_header(n)
        bounds = [_bounds(i, -np.inf, np.inf) for i in t.item_types]
        if any(b[2] or b[3] for b in bounds):
            raise TypeError(f"{name}: open bounds in a float tuple are not supported")
        slots.append(Slot(name, "floats", len(out), count=n, lo=np.array([b[0] for b in bounds]),
                          hi=np.array([b[1] for b in bounds])))
        for v in value:
            out += b"\xcb" + struct.pack(">d", v)
    elif isinstance(t, (ti.ListType, ti.VarTupleType)):
        out += array_header(len(value))
        for k, item in enumerate(value):
            _emit(t.item_type, item, f"{name}.{k}", out, slots)
    elif isinstance(t, ti.LiteralType):
        out += msgspec.msgpack.encode(value)
    else:
        raise TypeError(f"{name}: {type(t).__name__} has no fixed-width form")
