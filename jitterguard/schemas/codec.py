"""The general msgpack codec of the wire models: ``encode(model) -> bytes`` and ``decode(ModelClass, data)``.

``decode`` is the model's own reading of a payload: the hot messages' read functions (:mod:`.wire`) fall back to
it for any payload not in their record shape, so it decides what is valid. It raises exactly one exception
type, :class:`DecodeError`, whose message names the model and the field that failed — whatever the input was
(random bytes, a truncated buffer, a valid msgpack map of the wrong shape, a non-finite number).
"""

from __future__ import annotations

from typing import TypeVar

import msgpack
from pydantic import BaseModel, ValidationError

M = TypeVar("M", bound=BaseModel)


class DecodeError(ValueError):
    """A payload that could not be decoded or failed validation. ``field`` is the dotted path, if known."""

    def __init__(self, model: str, field: str, reason: str) -> None:
        self.model = model
        self.field = field
        self.reason = reason
        super().__init__(f"{model}.{field}: {reason}" if field else f"{model}: {reason}")


def encode(model: BaseModel | dict) -> bytes:
    """Serialise a model (all fields, defaults included) — or a map from :func:`decode_with_raw` — to msgpack."""
    return msgpack.packb(model if isinstance(model, dict) else model.model_dump(mode="python"), use_bin_type=True)


def decode(cls: type[M], data: bytes | bytearray | memoryview) -> M:
    """Parse msgpack ``data`` and validate it as ``cls``; any failure raises :class:`DecodeError`."""
    return validate(cls, unpack_map(cls, data))


def decode_with_raw(cls: type[M], data: bytes | bytearray | memoryview) -> tuple[M, dict]:
    """Like :func:`decode`, also returning the validated msgpack map (for a caller that renders from the map)."""
    raw = unpack_map(cls, data)
    return validate(cls, raw), raw


def validate(cls: type[M], raw: dict) -> M:
    """An unpacked msgpack map validated as ``cls`` (:class:`DecodeError` naming the field if it is not)."""
    try:
        return cls.model_validate(raw)
    except ValidationError as exc:
        err = exc.errors(include_url=False)[0]
        field = ".".join(str(p) for p in err.get("loc", ())) or ""
        more = f" (+{exc.error_count() - 1} more errors)" if exc.error_count() > 1 else ""
        raise DecodeError(cls.__name__, field, f"{err.get('msg', 'invalid')}{more}") from None
    except (RecursionError, TypeError, ValueError) as exc:  # pathological nesting or unhashable keys
        raise DecodeError(cls.__name__, "", f"{type(exc).__name__}: {exc}") from None


def unpack_map(cls: type[BaseModel], data: bytes | bytearray | memoryview) -> dict:
    """Unpack msgpack ``data`` into a map, *not yet validated* as ``cls`` (errors are named after ``cls``)."""
    try:
        raw = msgpack.unpackb(bytes(data), raw=False, strict_map_key=True, use_list=True)
    except Exception as exc:  # msgpack raises several unrelated types (ExtraData, ValueError, ...)
        raise DecodeError(cls.__name__, "", f"not valid msgpack ({type(exc).__name__}: {exc})") from None
    if not isinstance(raw, dict):
        raise DecodeError(cls.__name__, "", f"expected a msgpack map, got {type(raw).__name__}")
    return raw
