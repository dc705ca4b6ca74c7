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

import re
import sys
from typing import Annotated, Any, Generic, Literal, TypeVar

import msgspec
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


class _Builder:
    """Turns one model's core schema into msgspec types; one Struct per model class, shared by reference."""

    def __init__(self) -> None:
        self.structs: dict[type, type[msgspec.Struct]] = {}
        self.defs: dict[str, dict] = {}

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
                fields.append((name, ftype, self._default(fs)))
            else:
                fields.append((name, self.type_of(fs, config)))
        struct = msgspec.defstruct(f"{cls.__name__}Struct", fields, kw_only=True, forbid_unknown_fields=True,
                                   gc=False, module=__name__)
        self.structs[cls] = struct
        return struct

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


def struct_type(model: type[BaseModel]) -> type[msgspec.Struct]:
    """The msgspec Struct type that validates exactly as ``model`` does (TypeError where it cannot)."""
    try:
        builder = _Builder()
        return builder.struct(builder._model_schema(model))
    except _Unsupported as exc:
        raise TypeError(f"{model.__name__}: no exact msgspec equivalent ({exc})") from None


class StructCodec(Generic[M]):
    """Decode payloads of ``model`` into its generated Struct (mutable, attribute access as on the model),
    and encode Structs back; ``decode`` raises :class:`~.codec.DecodeError` as :func:`~.codec.decode` would.

    Encoding a decoded Struct gives the payload ``encode(decode(model, data))`` gives: every field, in the
    model's order, defaults filled in.
    """

    def __init__(self, model: type[M]) -> None:
        self.model = model
        self.type = struct_type(model)
        self._decoder = msgspec.msgpack.Decoder(self.type)
        self._encoder = msgspec.msgpack.Encoder()

    def decode(self, data: bytes | bytearray | memoryview) -> Any:
        try:
            return self._decoder.decode(data)
        except (msgspec.ValidationError, msgspec.DecodeError):
            pass
        # msgspec refused it: pydantic decides (and names the field when it refuses too)
        valid = validate_map(self.model, unpack_map(self.model, data))
        try:
            return msgspec.convert(valid, self.type)
        except msgspec.ValidationError as exc:  # never seen; would be a generator bug: refuse, do not guess
            raise DecodeError(self.model.__name__, "", f"accepted by the model but not by its fast decoder: {exc}") from None

    def encode(self, obj: msgspec.Struct) -> bytes:
        return self._encoder.encode(obj)
