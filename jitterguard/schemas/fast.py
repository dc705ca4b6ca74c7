"""A fast decoder for hot-path payloads: msgspec Structs generated from the pydantic models' own core schemas.

Why: the classifier validates ~4,000 ``TrackObservation``s and 20 ``TrackedObjects`` of 200 objects per
second, and with msgpack + pydantic that validation was most of its CPU (unpack into dicts, then build ~20
models per object). msgspec validates *while* it parses the msgpack bytes, so no intermediate maps are built;
the same frame costs about a quarter.

Why it is still the contract's validation: the Struct types are not written by hand but generated from each
model's pydantic core schema (fields, defaults, ``extra="forbid"``, ``allow_inf_nan=False``, ``ge``/``le``,
patterns, fixed-length covariance tuples), and anything the generator does not translate exactly (a Python
validator, a regex it cannot carry over, …) makes it refuse the model. msgspec is stricter than pydantic's
lax mode in places (it refuses ``"1.5"`` for a float or ``1`` for a bool); whatever msgspec refuses goes to
pydantic, which then either rejects it, with its usual :class:`~.codec.DecodeError` naming the field, or
accepts it, and its result is used. So the accepted set is pydantic's exactly as long as msgspec accepts
nothing pydantic refuses, and returns what pydantic would: ``tests/test_schemas.py`` checks both on
generated mutations of valid payloads.
"""

from __future__ import annotations

import operator
import re
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from itertools import chain
from typing import Annotated, Any, Generic, Literal, TypeVar, get_args, get_origin

import msgpack
import msgspec
import numpy as np
from pydantic import BaseModel

from .codec import DecodeError, unpack_map, validate_map

M = TypeVar("M", bound=BaseModel)
_MAX = sys.float_info.max
_SIMPLE_PATTERN = re.compile(r"^\^([\[\]\w{},\-]*)\$$")
"""Patterns carried over: anchored, made of character classes and counted repetitions only, where Python's
``re`` and pydantic-core's Rust regex agree (``$`` becomes ``\\Z``: Python's ``$`` also matches before a
trailing newline)."""


class _Unsupported(TypeError):
    pass


def _float(schema: dict, config: dict) -> Any:
    _only(schema, {"type", "ge", "le", "gt", "lt", "allow_inf_nan", "metadata"})
    allow_inf_nan = schema.get("allow_inf_nan", config.get("allow_inf_nan", True))
    meta: dict[str, Any] = {k: float(schema[k]) for k in ("ge", "le", "gt", "lt") if k in schema}
    if not allow_inf_nan:  # any bound rejects NaN; finite bounds on both sides reject the infinities
        if "ge" not in meta and "gt" not in meta:
            meta["ge"] = -_MAX
        if "le" not in meta and "lt" not in meta:
            meta["le"] = _MAX
    return Annotated[float, msgspec.Meta(**meta)] if meta else float


def _int(schema: dict) -> Any:
    _only(schema, {"type", "ge", "le", "gt", "lt", "metadata"})
    meta = {k: schema[k] for k in ("ge", "le", "gt", "lt") if k in schema}
    return Annotated[int, msgspec.Meta(**meta)] if meta else int


def _str(schema: dict) -> Any:
    _only(schema, {"type", "pattern", "min_length", "max_length", "metadata"})
    meta: dict[str, Any] = {k: schema[k] for k in ("min_length", "max_length") if k in schema}
    if "pattern" in schema:
        m = _SIMPLE_PATTERN.match(schema["pattern"])
        if m is None:
            raise _Unsupported(f"pattern {schema['pattern']!r}")
        meta["pattern"] = rf"\A{m.group(1)}\Z"
    return Annotated[str, msgspec.Meta(**meta)] if meta else str


def _only(schema: dict, allowed: set[str]) -> None:
    extra = set(schema) - allowed
    if extra:
        raise _Unsupported(f"{schema.get('type')} schema with {sorted(extra)}")


@dataclass(frozen=True)
class _Block:
    """A fixed-length tuple of bounded floats kept as raw msgpack bytes (``raw_float_blocks``)."""

    n: int
    lo: tuple[float, ...]  # inclusive bounds per item (±float max where only finiteness is asked)
    hi: tuple[float, ...]

    @property
    def size(self) -> int:
        return 3 + 9 * self.n  # array16 header, then one float64 (0xcb + 8 bytes) per item

    @cached_property
    def header(self) -> np.ndarray:
        return np.array([0xDC, self.n >> 8, self.n & 0xFF], dtype=np.uint8)

    @cached_property
    def lo_array(self) -> np.ndarray:
        return np.asarray(self.lo, dtype=np.float64)

    @cached_property
    def hi_array(self) -> np.ndarray:
        return np.asarray(self.hi, dtype=np.float64)


@dataclass
class _Plan:
    """Where a struct type's raw blocks are: direct ones by dotted path, and those inside list fields."""

    leaves: list[tuple[str, _Block]] = field(default_factory=list)
    lists: list[tuple[str, "_Plan"]] = field(default_factory=list)


class _Builder:
    """Turns one model's core schema into msgspec types; one Struct per model class, shared by reference."""

    def __init__(self, raw_float_blocks: int | None = None) -> None:
        self.structs: dict[type, type[msgspec.Struct]] = {}
        self.defs: dict[str, dict] = {}
        self.raw_min = raw_float_blocks
        self.plans: dict[type, _Plan] = {}  # per Struct type, when raw blocks are on

    def type_of(self, schema: dict, config: dict) -> Any:
        kind = schema.get("type")
        if kind == "definitions":
            for d in schema["definitions"]:
                self.defs[d["ref"]] = d
            return self.type_of(schema["schema"], config)
        if kind == "definition-ref":
            _only(schema, {"type", "schema_ref", "metadata"})
            return self.type_of(self.defs[schema["schema_ref"]], config)
        if kind == "model":
            return self.struct(schema)
        if kind == "float":
            return _float(schema, config)
        if kind == "int":
            return _int(schema)
        if kind == "str":
            return _str(schema)
        if kind == "bool":
            _only(schema, {"type", "metadata"})
            return bool
        if kind == "literal":
            _only(schema, {"type", "expected", "metadata"})
            expected = schema["expected"]
            if not all(type(v) in (int, str) for v in expected):  # bools and enums compare loosely
                raise _Unsupported(f"literal {expected!r}")
            return Literal[tuple(expected)]
        if kind == "list":
            _only(schema, {"type", "items_schema", "min_length", "max_length", "metadata"})
            item = self.type_of(schema["items_schema"], config) if "items_schema" in schema else Any
            if item is Any:
                raise _Unsupported("list of Any")
            meta = {k: schema[k] for k in ("min_length", "max_length") if k in schema}
            return Annotated[list[item], msgspec.Meta(**meta)] if meta else list[item]  # type: ignore[valid-type]
        if kind == "tuple":
            _only(schema, {"type", "items_schema", "metadata"})  # no variadic item: a fixed length
            block = self._block(schema["items_schema"], config)
            if block is not None:
                return block
            items = tuple(self.type_of(s, config) for s in schema["items_schema"])
            if not items:
                raise _Unsupported("empty tuple")
            return tuple[items]  # type: ignore[valid-type]
        raise _Unsupported(f"{kind!r} schema")

    def struct(self, schema: dict) -> type[msgspec.Struct]:
        cls = schema["cls"]
        if cls in self.structs:
            return self.structs[cls]
        _only(schema, {"type", "cls", "config", "custom_init", "metadata", "ref", "root_model", "schema"})
        inner = schema["schema"]
        config = dict(schema.get("config") or {})
        if schema.get("custom_init") or schema.get("root_model") or inner.get("type") != "model-fields":
            raise _Unsupported(f"model {cls.__name__}")
        _only(inner, {"type", "fields", "model_name", "computed_fields"})
        if inner.get("computed_fields") or config.get("extra_fields_behavior") != "forbid" or config.get("strict"):
            raise _Unsupported(f"model {cls.__name__} (computed fields, extra fields allowed, or strict)")
        fields: list[tuple[Any, ...]] = []
        for name, field in inner["fields"].items():
            _only(field, {"type", "schema", "metadata"})
            fs = field["schema"]
            if fs.get("type") == "default":
                _only(fs, {"type", "schema", "default", "default_factory", "default_factory_takes_data", "metadata"})
                if fs.get("default_factory_takes_data"):
                    raise _Unsupported(f"field {name}: a default factory that takes data")
                ftype = self.type_of(fs["schema"], config)
                default = self._default(fs)
                if isinstance(ftype, _Block):  # a raw block's default is its canonical bytes
                    default = msgspec.Raw(msgpack.packb([float(v) for v in default], use_bin_type=True))
                fields.append((name, ftype, default))
            else:
                fields.append((name, self.type_of(fs, config)))
        struct = msgspec.defstruct(f"{cls.__name__}Struct", [_raw_if_block(f) for f in fields], kw_only=True, forbid_unknown_fields=True,
                                   gc=False, module=__name__)
        self.structs[cls] = struct
        if self.raw_min is not None:
            self.plans[struct] = self._plan(fields)
        return struct

    def _block(self, items: list[dict], config: dict) -> _Block | None:
        """A :class:`_Block` for a long tuple of finite, inclusively bounded floats; None to keep a tuple."""
        if self.raw_min is None or len(items) < self.raw_min or len(items) > 0xFFFF:
            return None
        lo, hi = [], []
        for item in items:
            if item.get("type") != "float" or set(item) - {"type", "ge", "le", "allow_inf_nan", "metadata"} \
                    or item.get("allow_inf_nan", config.get("allow_inf_nan", True)):
                return None
            lo.append(max(float(item.get("ge", -_MAX)), -_MAX))
            hi.append(min(float(item.get("le", _MAX)), _MAX))
        return _Block(len(items), tuple(lo), tuple(hi))

    def _plan(self, fields: list[tuple[Any, ...]]) -> _Plan:
        plan = _Plan()
        for name, ftype, *_ in fields:
            if isinstance(ftype, _Block):
                plan.leaves.append((name, ftype))
            elif isinstance(ftype, type) and issubclass(ftype, msgspec.Struct):
                sub = self.plans[ftype]
                plan.leaves += [(f"{name}.{path}", block) for path, block in sub.leaves]
                plan.lists += [(f"{name}.{path}", p) for path, p in sub.lists]
            else:
                item = _list_item(ftype)
                if item is not None and (self.plans[item].leaves or self.plans[item].lists):
                    plan.lists.append((name, self.plans[item]))
        return plan

    def _default(self, schema: dict) -> Any:
        if "default_factory" in schema:
            factory = schema["default_factory"]
            if isinstance(factory, type) and issubclass(factory, BaseModel):
                return msgspec.field(default_factory=self.struct(self._model_schema(factory)))
            if factory in (list, dict):
                return msgspec.field(default_factory=factory)
            value = factory()
            if isinstance(value, tuple) and all(type(v) in (int, float, str, bool) for v in value):
                return value
            raise _Unsupported(f"default factory {factory!r}")
        value = schema["default"]
        if isinstance(value, bool) or value is None or type(value) in (float, str):
            return value
        if isinstance(value, int):  # an IntEnum member encodes as its int
            return int(value)
        raise _Unsupported(f"default {value!r}")

    def _model_schema(self, cls: type[BaseModel]) -> dict:
        """A model's ``model`` schema node (its core schema may wrap it in ``definitions``)."""
        schema: dict = dict(cls.__pydantic_core_schema__)
        if schema["type"] == "definitions":
            for d in schema["definitions"]:
                self.defs.setdefault(d["ref"], d)
            schema = schema["schema"]
        if schema["type"] == "definition-ref":
            schema = self.defs[schema["schema_ref"]]
        if schema["type"] != "model":
            raise _Unsupported(f"model {cls.__name__}")
        return schema


def _raw_if_block(f: tuple[Any, ...]) -> tuple[Any, ...]:
    return (f[0], msgspec.Raw, *f[2:]) if isinstance(f[1], _Block) else f


def _list_item(ftype: Any) -> type[msgspec.Struct] | None:
    """The Struct type of a ``list[Struct]`` field (possibly ``Annotated``), else None."""
    if get_origin(ftype) is Annotated:
        ftype = get_args(ftype)[0]
    if get_origin(ftype) is list:
        (item,) = get_args(ftype)
        if isinstance(item, type) and issubclass(item, msgspec.Struct):
            return item
    return None


def _build(model: type[BaseModel], raw_float_blocks: int | None) -> tuple[type[msgspec.Struct], _Plan | None]:
    try:
        builder = _Builder(raw_float_blocks)
        struct = builder.struct(builder._model_schema(model))
    except _Unsupported as exc:
        raise TypeError(f"{model.__name__}: no exact msgspec equivalent ({exc})") from None
    return struct, builder.plans.get(struct)


def struct_type(model: type[BaseModel]) -> type[msgspec.Struct]:
    """The msgspec Struct type that validates exactly as ``model`` does (TypeError where it cannot)."""
    return _build(model, None)[0]


def _compile(plan: _Plan, index: dict[_Block, int]) -> Callable[[Any, list[list]], None]:
    """A collector of every raw block under an object into ``out[index[block]]``.

    Built from C-level pieces (``attrgetter`` over the dotted paths, ``map``/``chain`` over list items), so a
    200-object message costs a few hundred microseconds, not a Python call per block.
    """
    leaf_get = operator.attrgetter(*[p for p, _ in plan.leaves]) if plan.leaves else None
    leaf_ids = [index.setdefault(b, len(index)) for _, b in plan.leaves]
    subs: list[tuple[Any, Any, Any, int]] = []  # (list getter, item collector or None, item getter, block id)
    for path, sub in plan.lists:
        uniform = not sub.lists and len(sub.leaves) > 1 and len({b for _, b in sub.leaves}) == 1
        if uniform:  # every item contributes a tuple of same-spec blocks: one C-level pass over the list
            subs.append((operator.attrgetter(path), None, operator.attrgetter(*[p for p, _ in sub.leaves]),
                         index.setdefault(sub.leaves[0][1], len(index))))
        else:
            subs.append((operator.attrgetter(path), _compile(sub, index), None, -1))

    def collect(obj: Any, out: list[list]) -> None:
        if leaf_get is not None:
            got = leaf_get(obj)
            for i, raw in zip(leaf_ids, got if len(leaf_ids) > 1 else (got,)):
                out[i].append(raw)
        for get_list, sub_collect, item_get, bid in subs:
            items = get_list(obj)
            if sub_collect is None:
                out[bid].extend(chain.from_iterable(map(item_get, items)))
            else:
                for item in items:
                    sub_collect(item, out)

    return collect


def _blocks_valid(raws: list, block: _Block) -> bool:
    """Every raw block is an array16 of ``block.n`` float64s within the block's bounds (NaN never is)."""
    if not raws:
        return True
    size = block.size
    joined = b"".join(raws)
    if len(joined) != size * len(raws) or min(map(len, raws)) != size:  # each exactly `size` bytes long
        return False
    a = np.frombuffer(joined, dtype=np.uint8).reshape(len(raws), size)
    if not (a[:, :3] == block.header).all():
        return False
    items = a[:, 3:].reshape(len(raws), block.n, 9)
    if not (items[:, :, 0] == 0xCB).all():
        return False
    values = np.ascontiguousarray(items[:, :, 1:]).view(">f8").reshape(len(raws), block.n)
    return bool(((values >= block.lo_array) & (values <= block.hi_array)).all())


def block_rows(raws: list[msgspec.Raw], n: int) -> np.ndarray:
    """``(len(raws), n)`` float64: the floats of raw blocks of ``n`` items from a ``raw_float_blocks`` codec
    (already validated), all read in one pass."""
    size = 3 + 9 * n  # array16 header, then one float64 (0xcb + 8 bytes) per item
    a = np.frombuffer(b"".join(raws), dtype=np.uint8).reshape(len(raws), size)
    return np.ascontiguousarray(a[:, 3:].reshape(len(raws), n, 9)[:, :, 1:]).view(">f8")[:, :, 0].astype(np.float64)


def raw_blocks(rows: np.ndarray) -> list[msgspec.Raw]:
    """The inverse of :func:`block_rows`: each row of floats as a canonical raw block (what such a codec keeps
    and its encoder writes back verbatim)."""
    m, n = rows.shape
    size = 3 + 9 * n
    out = np.empty((m, size), dtype=np.uint8)
    out[:, :3] = (0xDC, n >> 8, n & 0xFF)
    items = out[:, 3:].reshape(m, n, 9)
    items[:, :, 0] = 0xCB
    items[:, :, 1:] = np.ascontiguousarray(rows, dtype=">f8").view(np.uint8).reshape(m, n, 8)
    data = out.tobytes()
    return [msgspec.Raw(data[i * size:(i + 1) * size]) for i in range(m)]


def block_values(raw: msgspec.Raw) -> np.ndarray:
    """The floats of one raw block from a ``raw_float_blocks`` codec (already validated), as float64."""
    return block_rows([raw], (len(raw) - 3) // 9)[0]


class StructCodec(Generic[M]):
    """Decode payloads of ``model`` into its generated Struct (mutable, attribute access as on the model),
    and encode Structs back; ``decode`` raises :class:`~.codec.DecodeError` as :func:`~.codec.decode` would.

    Encoding a decoded Struct gives the payload ``encode(decode(model, data))`` gives: every field, in the
    model's order, defaults filled in.

    ``raw_float_blocks=N``: fixed-length tuples of at least N finite, bounded floats (the 36-float
    covariances) are not turned into Python floats but kept as :class:`msgspec.Raw` (a view of their msgpack
    bytes) and checked for all blocks of a message at once with numpy: canonical float64 arrays within the
    bounds pass, anything else (ints, float32, NaN, a wrong length, ...) sends the message to pydantic. On a
    200-object ``tracked`` that skips 21,600 float objects; :func:`block_values` reads a block back.
    """

    def __init__(self, model: type[M], *, raw_float_blocks: int | None = None) -> None:
        self.model = model
        self.type, plan = _build(model, raw_float_blocks)
        self._collect = None
        if plan is not None and (plan.leaves or plan.lists):
            index: dict[_Block, int] = {}
            self._collect = _compile(plan, index)
            self._block_specs = sorted(index, key=index.__getitem__)
        self._decoder = msgspec.msgpack.Decoder(self.type)
        self._encoder = msgspec.msgpack.Encoder()

    def _fast(self, data: bytes | bytearray | memoryview) -> Any | None:
        try:
            obj = self._decoder.decode(data)
        except (msgspec.DecodeError, ValueError):  # ValueError: e.g. a key that is not UTF-8
            return None
        if self._collect is not None:
            found: list[list] = [[] for _ in self._block_specs]
            self._collect(obj, found)
            if not all(_blocks_valid(raws, b) for raws, b in zip(found, self._block_specs)):
                return None
        return obj

    def decode(self, data: bytes | bytearray | memoryview) -> Any:
        obj = self._fast(data)
        if obj is not None:
            return obj
        # msgspec refused it: pydantic decides (and names the field when it refuses too)
        valid = validate_map(self.model, unpack_map(self.model, data))
        obj = self._fast(msgpack.packb(valid, use_bin_type=True))  # now in canonical form
        if obj is None:  # never seen; would be a generator bug: refuse, do not guess
            raise DecodeError(self.model.__name__, "", "accepted by the model but not by its fast decoder")
        return obj

    def encode(self, obj: msgspec.Struct) -> bytes:
        return self._encoder.encode(obj)
