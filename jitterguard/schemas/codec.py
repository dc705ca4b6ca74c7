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


def encode(model: BaseModel | dict) -> bytes:
    """Serialise a model (all fields, defaults included) — or a map from :func:`decode_with_raw` — to msgpack."""
    data = model if isinstance(model, dict) else model.model_dump(mode="python")
    return msgpack.packb(data, use_bin_type=True)


def decode(cls: type[M], data: bytes | bytearray | memoryview) -> M:
    """Parse msgpack ``data`` and validate it as ``cls``; any failure raises :class:`DecodeError`."""
    return decode_with_raw(cls, data)[0]


def decode_with_raw(cls: type[M], data: bytes | bytearray | memoryview) -> tuple[M, dict]:
    """Like :func:`decode`, also returning the validated msgpack map.

    For adapters that forward a payload with small edits (the classifier re-publishes the tracker's
    objects): editing the already-validated map and packing it is several times cheaper than dumping the
    model again, and this is the per-frame hot path.
    """
    name = cls.__name__
    try:
        raw = msgpack.unpackb(bytes(data), raw=False, strict_map_key=True, use_list=True)
    except Exception as exc:  # msgpack raises several unrelated types (ExtraData, ValueError, ...)
        raise DecodeError(name, "", f"not valid msgpack ({type(exc).__name__}: {exc})") from None
    if not isinstance(raw, dict):
        raise DecodeError(name, "", f"expected a msgpack map, got {type(raw).__name__}")
    try:
        return cls.model_validate(raw), raw
    except ValidationError as exc:
        err = exc.errors(include_url=False)[0]
        field = ".".join(str(p) for p in err.get("loc", ())) or ""
        more = f" (+{exc.error_count() - 1} more errors)" if exc.error_count() > 1 else ""
        raise DecodeError(name, field, f"{err.get('msg', 'invalid')}{more}") from None
    except (RecursionError, TypeError, ValueError) as exc:  # pathological nesting or unhashable keys
        raise DecodeError(name, "", f"{type(exc).__name__}: {exc}") from None


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
