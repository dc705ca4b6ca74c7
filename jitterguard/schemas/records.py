"""Fixed-shape msgpack records: a numpy structured array whose bytes *are* the msgpack of N messages or objects.

Why: the hot messages carry hundreds of nested maps of ~150 numbers each, 20 times a second; building and walking
them in Python costs milliseconds a frame. msgpack lets a map of one shape be written with fixed widths (a float
is ``0xcb`` + 8 big-endian bytes, a small bounded int one fixint byte, a bool one byte, a string its header and
bytes), and msgpack writers write exactly that for such values. So every record of one shape has the same bytes
except its values, and N records are a numpy structured array with one field per value: writing them is a few
column assignments, reading them back a ``frombuffer`` and vectorised checks.

A :class:`RecordLayout` is derived from a pydantic model's own core schema (field order, bounds, patterns,
literals), so the value rules are the contract's, and from an example instance that fixes the shape (list and
string lengths). :meth:`RecordLayout.view` accepts a buffer only where every record has exactly that shape *and*
every value passes the model's rules; anything else is left to the model itself (:mod:`.wire`), which decides.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np
from pydantic import BaseModel

_INT64 = (-(2**63), 2**63 - 1)
_FMT = {"float": ">f8", "int64": ">i8", "fixint": "u1", "bool": "u1"}


@dataclass(frozen=True)
class Slot:
    """One value (or a fixed-length tuple of floats) inside a record: where it is and what it may hold."""

    name: str
    kind: str  # "float", "floats" (a tuple), "fixint", "int64", "bool", "str"
    offset: int
    count: int = 1  # items of a "floats" tuple; bytes of a "str"
    lo: Any = None  # inclusive bounds (per item for "floats")
    hi: Any = None
    pattern: re.Pattern[str] | None = None
    table: np.ndarray | None = None  # for a pattern ``[class]{count}``: which byte values the class allows


class RecordLayout:
    """Records of one model and one shape. Build with :meth:`of`; ``spans`` maps a nested model's dotted path to
    its byte range inside a record (a sub-record can be copied whole)."""

    def __init__(self, template: bytes, slots: list[Slot], spans: dict[str, tuple[int, int]]) -> None:
        self.itemsize = len(template)
        self.template = np.frombuffer(template, dtype=np.uint8).copy()
        self.slots = {s.name: s for s in slots}
        self.spans = spans
        const = np.ones(self.itemsize, dtype=bool)  # bytes that are the same in every record of this shape
        fmts, floats, lo, hi = [], [], [], []
        for s in slots:
            if s.kind == "floats":
                fmts.append((np.dtype({"names": ["v"], "formats": [">f8"], "offsets": [1], "itemsize": 9}), (s.count,)))
                starts = [s.offset + 9 * k + 1 for k in range(s.count)]
                lo += list(s.lo)
                hi += list(s.hi)
            else:
                fmts.append(f"S{s.count}" if s.kind == "str" else _FMT[s.kind])
                starts = [s.offset] if s.kind == "float" else []
                if s.kind == "float":
                    lo.append(s.lo)
                    hi.append(s.hi)
            for a in starts:
                const[a: a + 8] = False
            if s.kind != "floats":
                const[s.offset: s.offset + np.dtype(fmts[-1]).itemsize] = False
            floats += starts
        self.dtype = np.dtype({"names": [s.name for s in slots], "formats": fmts,
                               "offsets": [s.offset for s in slots], "itemsize": self.itemsize})
        self._const_idx = np.flatnonzero(const)
        self._const = self.template[self._const_idx]
        # Every float's sign-and-exponent half-word (all exponent bits set: not finite), and the values of those
        # with bounds beyond finiteness (probabilities, variances): two gathers instead of all 8 bytes of each.
        starts, lo, hi = np.asarray(floats, dtype=np.intp), np.asarray(lo), np.asarray(hi)
        self._exp_idx = (starts[:, None] + np.arange(2)).reshape(-1)
        bounded = (lo > -np.finfo(float).max) | (hi < np.finfo(float).max)
        self._float_idx = (starts[bounded][:, None] + np.arange(8)).reshape(-1)
        self._float_lo, self._float_hi = lo[bounded].astype(np.float64), hi[bounded].astype(np.float64)
        small = [s for s in slots if s.kind in ("fixint", "bool")]
        self._byte_idx = np.asarray([s.offset for s in small], dtype=np.intp)
        self._byte_lo = np.asarray([0xC2 if s.kind == "bool" else s.lo for s in small])
        self._byte_hi = np.asarray([0xC3 if s.kind == "bool" else s.hi for s in small])
        self._other = [s for s in slots if s.kind in ("int64", "str")]

    @classmethod
    def of(cls, model: type[BaseModel], example: BaseModel) -> RecordLayout:
        """The layout of ``example``'s shape under ``model``'s rules (TypeError for a rule it cannot carry)."""
        out, slots, spans = bytearray(), [], {}
        schema = model.__pydantic_core_schema__
        defs = {d["ref"]: d for d in schema.get("definitions", ())}
        _emit(schema, example.model_dump(mode="python"), "", out, slots, spans, defs)
        return cls(bytes(out), slots, spans)

    def pack(self, n: int, columns: Mapping[str, Any]) -> np.ndarray:
        """``n`` records: the example's values except where ``columns`` (slot name -> length-``n`` values, or
        ``(n, count)`` for a float tuple) says otherwise. Strings must have the slot's exact length in bytes."""
        rec = np.tile(self.template, n).view(self.dtype)
        for name, values in columns.items():
            s = self.slots[name]
            if s.kind == "floats":
                rec[name]["v"] = values
            elif s.kind == "bool":
                rec[name] = np.where(np.asarray(values, dtype=bool), 0xC3, 0xC2)
            elif s.kind == "str":
                try:  # numpy encodes ASCII str itself, in C
                    arr = np.asarray(values, dtype=f"S{s.count}")
                except UnicodeEncodeError:
                    arr = np.asarray([v.encode() if isinstance(v, str) else v for v in values], dtype=f"S{s.count}")
                if n and (np.char.str_len(arr) != s.count).any():
                    raise ValueError(f"{name}: every value must be {s.count} bytes long")
                rec[name] = arr
            else:
                rec[name] = values
        return rec

    def valid_rows(self, data: bytes | memoryview, n: int) -> np.ndarray:
        """Per record of ``data`` (exactly ``n`` records long): does it have this shape with valid values?"""
        rows = np.frombuffer(data, dtype=np.uint8).reshape(n, self.itemsize)
        ok = (rows[:, self._const_idx] == self._const).all(axis=1)
        small = rows[:, self._byte_idx]
        ok &= ((small >= self._byte_lo) & (small <= self._byte_hi)).all(axis=1)
        ok &= ((np.ascontiguousarray(rows[:, self._exp_idx]).view(">u2") & 0x7FF0) != 0x7FF0).all(axis=1)
        v = np.ascontiguousarray(rows[:, self._float_idx]).view(">f8")
        ok &= ((v >= self._float_lo) & (v <= self._float_hi)).all(axis=1)
        rec = rows.reshape(-1).view(self.dtype)
        for s in self._other:
            ok &= _valid(s, rec[s.name], rows)
        return ok

    def view(self, data: bytes | memoryview, n: int) -> np.ndarray | None:
        """``data`` as ``n`` read-only records if it is exactly that and every value is valid; else None."""
        if len(data) != n * self.itemsize:
            return None
        if n and not self.valid_rows(data, n).all():
            return None
        return np.frombuffer(data, dtype=np.uint8).view(self.dtype)

    @staticmethod
    def to_bytes(records: np.ndarray) -> bytes:
        """The records' msgpack bytes (the constant bytes between fields included)."""
        return records.view(np.uint8).tobytes()

    @staticmethod
    def copy(records: np.ndarray) -> np.ndarray:
        """A writable copy of ``records``. Not ``ndarray.copy``: that leaves out the bytes between fields."""
        return records.view(np.uint8).copy().view(records.dtype)

    def select(self, records: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """Whole records ``rows`` of ``records`` (a copy, the bytes between fields included)."""
        raw = records.view(np.uint8).reshape(len(records), self.itemsize)
        return np.ascontiguousarray(raw[rows]).reshape(-1).view(self.dtype)


def _valid(s: Slot, col: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Per value: the checks :meth:`RecordLayout.valid_rows` does not batch (strings, 64-bit ints)."""
    if s.kind == "int64":
        return (col >= s.lo) & (col <= s.hi)
    raw = rows[:, s.offset:s.offset + s.count]
    if s.table is not None:  # one lookup per byte instead of a regex per value (NUL is never in the class)
        return s.table[raw].all(axis=1)
    ok = (raw != 0).all(axis=1)  # a NUL byte: the model decides
    for i in np.flatnonzero(ok & ~(raw < 0x80).all(axis=1)).tolist():  # ASCII is valid UTF-8; the rest, one by one
        try:
            text = col[i].decode()
        except UnicodeDecodeError:
            ok[i] = False
            continue
        ok[i] = s.pattern is None or s.pattern.fullmatch(text) is not None
    return ok


def _byte_table(pattern: str, count: int) -> np.ndarray | None:
    """For ``[class]{count}`` (the 32-hex-digit IDs): the ASCII bytes the class allows; None for other patterns."""
    m = re.fullmatch(r"(\[[^\]]+\])\{(\d+)\}", pattern)
    if m is None or int(m.group(2)) != count:
        return None
    cls = re.compile(m.group(1))
    return np.array([b < 128 and cls.fullmatch(chr(b)) is not None for b in range(256)])


def array_header(n: int) -> bytes:
    """A msgpack array header for ``n`` items."""
    if n < 16:
        return bytes([0x90 | n])
    return (b"\xdc" + n.to_bytes(2, "big")) if n < 0x10000 else (b"\xdd" + n.to_bytes(4, "big"))


def _bounds(schema: dict, lo: Any, hi: Any) -> tuple[Any, Any]:
    if "gt" in schema or "lt" in schema or "multiple_of" in schema:
        raise TypeError(f"{schema}: open bounds are not carried into a record layout")
    return max(schema.get("ge", lo), lo), min(schema.get("le", hi), hi)


def _emit(schema: dict, value: Any, name: str, out: bytearray, slots: list[Slot],
          spans: dict[str, tuple[int, int]], defs: dict[str, dict]) -> None:
    """Append ``value``'s fixed-width bytes under core schema ``schema``, recording where each value sits."""
    kind = schema["type"]
    if kind == "definitions":
        return _emit(schema["schema"], value, name, out, slots, spans, defs)
    if kind == "definition-ref":
        return _emit(defs[schema["schema_ref"]], value, name, out, slots, spans, defs)
    if kind in ("default", "function-before"):  # a before-validator that keeps the shape (an array as a tuple)
        return _emit(schema["schema"], value, name, out, slots, spans, defs)
    if kind == "model":
        start = len(out)
        fields = schema["schema"]["fields"]
        out += bytes([0x80 | len(fields)]) if len(fields) < 16 else b"\xde" + len(fields).to_bytes(2, "big")
        for fname, field in fields.items():
            out += msgpack.packb(fname)
            _emit(field["schema"], value[fname], f"{name}.{fname}" if name else fname, out, slots, spans, defs)
        spans[name] = (start, len(out))
    elif kind == "float":
        lo, hi = _bounds(schema, -np.inf, np.inf)
        out += b"\xcb"
        slots.append(Slot(name, "float", len(out), lo=max(lo, -np.finfo(float).max), hi=min(hi, np.finfo(float).max)))
        out += struct.pack(">d", value)
    elif kind == "bool":
        slots.append(Slot(name, "bool", len(out)))
        out += b"\xc3" if value else b"\xc2"
    elif kind == "int":
        lo, hi = _bounds(schema, *_INT64)
        if lo >= 0 and hi <= 127:  # always one byte (a positive fixint), as every msgpack writer writes it
            slots.append(Slot(name, "fixint", len(out), lo=lo, hi=hi))
            out += bytes([int(value)])
        else:  # fixed width (msgpack int64): writers of other widths are read by the model instead
            out += b"\xd3"
            slots.append(Slot(name, "int64", len(out), lo=lo, hi=hi))
            out += int(value).to_bytes(8, "big", signed=True)
    elif kind == "str":
        if set(schema) - {"type", "pattern", "metadata"}:
            raise TypeError(f"{name}: string rules {sorted(schema)} are not carried into a record layout")
        pattern = schema.get("pattern")
        if pattern is not None and not (pattern.startswith("^") and pattern.endswith("$")):
            raise TypeError(f"{name}: only anchored patterns are carried into a record layout")
        data = value.encode()
        out += msgpack.packb(value)[: -len(data) or None]  # the string's header
        slots.append(Slot(name, "str", len(out), count=len(data), pattern=re.compile(pattern[1:-1]) if pattern else None,
                          table=_byte_table(pattern[1:-1], len(data)) if pattern else None))
        out += data
    elif kind == "tuple" and all(s["type"] == "float" for s in schema["items_schema"]):
        bounds = [_bounds(s, -np.finfo(float).max, np.finfo(float).max) for s in schema["items_schema"]]
        out += array_header(len(bounds))
        slots.append(Slot(name, "floats", len(out), count=len(bounds), lo=[b[0] for b in bounds],
                          hi=[b[1] for b in bounds]))
        for v in value:
            out += b"\xcb" + struct.pack(">d", v)
    elif kind == "list":
        out += array_header(len(value))
        for k, item in enumerate(value):
            _emit(schema["items_schema"], item, f"{name}.{k}", out, slots, spans, defs)
    elif kind == "literal" and all(type(v) in (int, str) for v in schema["expected"]):
        out += msgpack.packb(value)  # constant bytes: a record of this layout holds exactly this value
    else:
        raise TypeError(f"{name}: a {kind!r} schema has no fixed-width form")
