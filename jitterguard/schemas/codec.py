"""msgpack codec for the wire models: ``encode(model) -> bytes`` and ``decode(ModelClass, data) -> model``.

``decode`` (and its plain-map twin :func:`decode_map`, same rules, no model instances) is the only door into
the process for Zenoh payloads, so it raises exactly one exception type, :class:`DecodeError`, whose message
names the model and the field that failed — whatever the input was (random bytes, a truncated buffer, a
valid msgpack map of the wrong shape, a non-finite number).
"""

from __future__ import annotations

from typing import Any, TypeVar

import msgpack
import msgspec
from pydantic import BaseModel, ValidationError
from pydantic_core import SchemaValidator

M = TypeVar("M", bound=BaseModel)
_ENCODER = msgspec.msgpack.Encoder()
"""msgspec writes the same bytes as ``msgpack.packb(data, use_bin_type=True)`` for these maps, ~4x faster."""


class DecodeError(ValueError):
    """A payload that could not be decoded or failed validation. ``field`` is the dotted path, if known."""

    def __init__(self, model: str, field: str, reason: str) -> None:
        self.model = model
        self.field = field
        self.reason = reason
        super().__init__(f"{model}.{field}: {reason}" if field else f"{model}: {reason}")


def encode(model: BaseModel | dict) -> bytes:
    """Serialise a model (all fields, defaults included) — or a map from :func:`decode_with_raw` — to msgpack."""
    data = model if isinstance(model, dict) else model.model_dump(mode="python")
    return _ENCODER.encode(data)


def decode(cls: type[M], data: bytes | bytearray | memoryview) -> M:
    """Parse msgpack ``data`` and validate it as ``cls``; any failure raises :class:`DecodeError`."""
    return decode_with_raw(cls, data)[0]


def decode_with_raw(cls: type[M], data: bytes | bytearray | memoryview) -> tuple[M, dict]:
    """Like :func:`decode`, also returning the validated msgpack map.

    For adapters that forward a payload with small edits: editing the already-validated map and packing it
    is several times cheaper than dumping the model again.
    """
    name = cls.__name__
    raw = unpack_map(cls, data)
    try:
        return cls.model_validate(raw), raw
    except ValidationError as exc:
        raise _validation_error(name, exc) from None
    except (RecursionError, TypeError, ValueError) as exc:  # pathological nesting or unhashable keys
        raise DecodeError(name, "", f"{type(exc).__name__}: {exc}") from None


def decode_map(cls: type[BaseModel], data: bytes | bytearray | memoryview) -> dict[str, Any]:
    """Validate ``data`` exactly as :func:`decode` would for ``cls``, but return plain maps, not models.

    The validator is pydantic-core's own, built from ``cls``'s core schema with every nested model turned
    into a typed dict of the *same* field validators (same constraints, same ``extra="forbid"``, same
    ``allow_inf_nan=False``), so the accept/reject set and the error's field path are those of ``cls``
    (``tests/test_schemas.py`` checks both on mutated payloads). What it saves is building a model
    instance per nested object: at 200 tracked objects a frame that is half the validation cost, and the
    classifier's per-frame hot path is validation. The result equals ``decode(cls, data).model_dump()``:
    defaults filled in, unknown input never kept. Models with Python validators are refused (TypeError).
    """
    return validate_map(cls, unpack_map(cls, data))


def validate_map(cls: type[BaseModel], raw: dict) -> dict[str, Any]:
    """:func:`decode_map` for an already unpacked msgpack map (``raw`` is not modified)."""
    name = cls.__name__
    validator = plain_validator(cls)  # TypeError for a model it cannot mirror: a caller's bug, not bad input
    try:
        return validator.validate_python(raw)
    except ValidationError as exc:
        raise _validation_error(name, exc) from None
    except (RecursionError, TypeError, ValueError) as exc:
        raise DecodeError(name, "", f"{type(exc).__name__}: {exc}") from None


_PLAIN_VALIDATORS: dict[type, SchemaValidator] = {}


def plain_validator(cls: type[BaseModel]) -> SchemaValidator:
    """The cached plain-map validator of ``cls`` (see :func:`decode_map`)."""
    v = _PLAIN_VALIDATORS.get(cls)
    if v is None:
        v = _PLAIN_VALIDATORS[cls] = SchemaValidator(_as_typed_dicts(cls.__pydantic_core_schema__, cls.__name__))
    return v


_FIELD_KEYS_OK = {"type", "schema", "metadata"}


def _model_default_factory(model_cls: type[BaseModel]):
    def factory() -> dict:
        return model_cls().model_dump(mode="python")

    return factory


def _as_typed_dicts(schema: Any, root: str) -> Any:
    """Rewrite a pydantic core schema: each ``model`` node becomes a ``typed-dict`` with the same fields.

    Only plain data models are supported: anything that runs Python during validation or dumping
    (validators, custom ``__init__``, computed fields, aliases, serializers) is refused, because the plain
    path could then disagree with the model.
    """
    if isinstance(schema, list):
        return [_as_typed_dicts(s, root) for s in schema]
    if not isinstance(schema, dict):
        return schema
    kind = schema.get("type")
    if isinstance(kind, str) and (kind.startswith("function-") or kind in ("model-fields", "dataclass", "call")):
        raise TypeError(f"{root}: a {kind!r} schema cannot be validated as plain maps")
    if "serialization" in schema:
        raise TypeError(f"{root}: custom serialization cannot be reproduced as plain maps")
    if kind == "model":
        inner = schema["schema"]
        if schema.get("custom_init") or schema.get("post_init") or schema.get("root_model") \
                or inner.get("type") != "model-fields" or inner.get("computed_fields") or inner.get("extras_schema"):
            raise TypeError(f"{root}: model {schema['cls'].__name__} is not a plain data model")
        config = dict(schema.get("config") or {})
        if config.get("extra_fields_behavior", "ignore") != "forbid" or config.get("revalidate_instances", "never") != "never":
            raise TypeError(f"{root}: model {schema['cls'].__name__} must forbid extra fields")
        fields = {}
        for fname, field in inner["fields"].items():
            if set(field) - _FIELD_KEYS_OK:
                raise TypeError(f"{root}: field {fname} uses {sorted(set(field) - _FIELD_KEYS_OK)}")
            fs = _as_typed_dicts(field["schema"], root)
            fields[fname] = {"type": "typed-dict-field", "schema": fs, "required": fs.get("type") != "default"}
        out = {"type": "typed-dict", "fields": fields, "extra_behavior": "forbid", "config": config}
        if "ref" in schema:
            out["ref"] = schema["ref"]
        return out
    if kind == "default":
        out = {k: _as_typed_dicts(v, root) for k, v in schema.items() if k != "default_factory"}
        if "default_factory" in schema:
            factory = schema["default_factory"]
            if schema.get("default_factory_takes_data"):
                raise TypeError(f"{root}: a default factory that takes data is not supported")
            if isinstance(factory, type) and issubclass(factory, BaseModel):
                factory = _model_default_factory(factory)  # a nested model's default, as its dump
            out["default_factory"] = factory
        elif isinstance(schema.get("default"), BaseModel):
            raise TypeError(f"{root}: a model instance as default is not supported")
        return out
    return {k: _as_typed_dicts(v, root) for k, v in schema.items()}


def unpack_map(cls: type[BaseModel], data: bytes | bytearray | memoryview) -> dict:
    """Unpack msgpack ``data`` into a map, *not yet validated* as ``cls`` (errors are named after ``cls``).

    With :func:`validate_map`, the two halves of :func:`decode_map`, for a caller that looks at one field
    first (the classifier reads ``header.seq`` to skip validating stragglers it would drop anyway).
    """
    name = cls.__name__
    try:
        raw = msgpack.unpackb(bytes(data), raw=False, strict_map_key=True, use_list=True)
    except Exception as exc:  # msgpack raises several unrelated types (ExtraData, ValueError, ...)
        raise DecodeError(name, "", f"not valid msgpack ({type(exc).__name__}: {exc})") from None
    if not isinstance(raw, dict):
        raise DecodeError(name, "", f"expected a msgpack map, got {type(raw).__name__}")
    return raw


def _validation_error(name: str, exc: ValidationError) -> DecodeError:
    err = exc.errors(include_url=False)[0]
    field = ".".join(str(p) for p in err.get("loc", ())) or ""
    more = f" (+{exc.error_count() - 1} more errors)" if exc.error_count() > 1 else ""
    return DecodeError(name, field, f"{err.get('msg', 'invalid')}{more}")


def peek_header_seq(data: bytes | bytearray | memoryview) -> int | None:
    """``header.seq`` of an encoded message, read without validating the rest (``None`` if not found).

    For load shedding only: a service that is behind can tell a stale payload from a current one for a few
    microseconds instead of a full validation. Anything it then keeps still goes through :func:`decode`.
    """
    up = msgpack.Unpacker(raw=False)
    try:
        up.feed(bytes(data))
        for _ in range(up.read_map_header()):
            key = up.unpack()
            if key == "header":
                header = up.unpack()
                seq = header.get("seq") if isinstance(header, dict) else None
                return seq if isinstance(seq, int) and not isinstance(seq, bool) else None
            up.skip()
    except Exception:
        return None
    return None
