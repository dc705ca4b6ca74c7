"""msgpack codec for the wire models: ``encode(model) -> bytes`` and ``decode(ModelClass, data) -> model``.

``decode`` is the only door into the process for Zenoh payloads, so it raises exactly one exception type,
:class:`DecodeError`, whose message names the model and the field that failed — whatever the input was
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


def encode(model: BaseModel) -> bytes:
    """Serialise a model (all fields, defaults included) to msgpack bytes."""
    return msgpack.packb(model.model_dump(mode="python"), use_bin_type=True)


def decode(cls: type[M], data: bytes | bytearray | memoryview) -> M:
    """Parse msgpack ``data`` and validate it as ``cls``; any failure raises :class:`DecodeError`."""
    name = cls.__name__
    try:
        raw = msgpack.unpackb(bytes(data), raw=False, strict_map_key=True, use_list=True)
    except Exception as exc:  # msgpack raises several unrelated types (ExtraData, ValueError, ...)
        raise DecodeError(name, "", f"not valid msgpack ({type(exc).__name__}: {exc})") from None
    if not isinstance(raw, dict):
        raise DecodeError(name, "", f"expected a msgpack map, got {type(raw).__name__}")
    try:
        return cls.model_validate(raw)
    except ValidationError as exc:
        err = exc.errors(include_url=False)[0]
        field = ".".join(str(p) for p in err.get("loc", ())) or ""
        more = f" (+{exc.error_count() - 1} more errors)" if exc.error_count() > 1 else ""
        raise DecodeError(name, field, f"{err.get('msg', 'invalid')}{more}") from None
    except (RecursionError, TypeError, ValueError) as exc:  # pathological nesting or unhashable keys
        raise DecodeError(name, "", f"{type(exc).__name__}: {exc}") from None
