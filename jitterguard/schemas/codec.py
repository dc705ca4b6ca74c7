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

from .models import SCHEMA_VERSION, Message

M = TypeVar("M", bound=BaseModel)


class DecodeError(ValueError):
    """A payload that could not be decoded or failed validation. ``field`` is the dotted path, if known."""

    def __init__(self, model: str, field: str, reason: str) -> None:
        self.model = model
        self.field = field
        self.reason = reason
        super().__init__(f"{model}.{field}: {reason}" if field else f"{model}: {reason}")


class LimitExceeded(DecodeError):
    """A payload beyond a bound on the work one message may cause (:class:`~.wire.Limits`): rejected before (or
    instead of) being read in full."""


BYTES_PER_CONTAINER = 16
"""At most one map or list built per this many bytes of a payload (beyond :data:`CONTAINER_FLOOR`). The bounds on
each list and map leave their number open: nested lists of 1024 empty maps each (one byte apiece) had made a 6 MiB
``tracks/{id}`` payload 7 million dicts — 0.5 GB and seconds of a worker — before it was refused. Real messages
spend far more per map or list (a footprint point as a map of three floats: 34 bytes; an object: hundreds)."""

CONTAINER_FLOOR = 4096


class ContainerBudget:
    """The ``object_hook`` and ``list_hook`` of an unpack of a ``model`` payload of ``size`` bytes: it counts the maps
    and lists the unpack builds and stops it with :class:`LimitExceeded` past ``CONTAINER_FLOOR + size //
    BYTES_PER_CONTAINER`` of them, the work of an unpack in proportion to its payload's size, whatever the payload
    holds. A model whose bulk is one byte string says how few it holds whatever its size (``MAX_CONTAINERS``:
    ``PointCloud``'s 64), so its bound need not grow with it (a hostile 64 MiB scan would otherwise still build 4
    million). Every reader of a payload builds its budget here, so each refuses it in the same words."""

    __slots__ = ("left", "limit", "model", "size")

    def __init__(self, model: type[BaseModel], size: int) -> None:
        limit = CONTAINER_FLOOR + size // BYTES_PER_CONTAINER
        cap = getattr(model, "MAX_CONTAINERS", None)
        self.limit = self.left = limit if cap is None else min(limit, cap)
        self.model, self.size = model, size

    def __call__(self, built: object) -> object:
        self.left -= 1
        if self.left < 0:
            raise LimitExceeded(self.model.__name__, "", f"more than {self.limit} maps and lists in {self.size} bytes")
        return built

    def hooks(self) -> dict[str, "ContainerBudget"]:
        return {"object_hook": self, "list_hook": self}


def encode(model: BaseModel | dict) -> bytes:
    """Serialise a model (all fields, defaults included) — or a map from :func:`decode_with_raw` — to msgpack."""
    return msgpack.packb(model if isinstance(model, dict) else model.model_dump(mode="python"), use_bin_type=True)


def decode(cls: type[M], data: bytes | bytearray | memoryview, *, max_bytes: int | None = None,
           max_array_len: int | None = None, max_map_len: int | None = None) -> M:
    """Parse msgpack ``data`` and validate it as ``cls``; any failure raises :class:`DecodeError`.
    ``max_bytes``, ``max_array_len`` and ``max_map_len`` bound the work before it is done (:func:`unpack_map`)."""
    return validate(cls, unpack_map(cls, data, max_bytes=max_bytes, max_array_len=max_array_len,
                                    max_map_len=max_map_len))


def decode_with_raw(cls: type[M], data: bytes | bytearray | memoryview, *, max_bytes: int | None = None,
                    max_array_len: int | None = None, max_map_len: int | None = None) -> tuple[M, dict]:
    """Like :func:`decode` (with the same bounds), also returning the validated msgpack map (for a caller that
    renders from the map)."""
    raw = unpack_map(cls, data, max_bytes=max_bytes, max_array_len=max_array_len, max_map_len=max_map_len)
    return validate(cls, raw), raw


def validate(cls: type[M], raw: dict) -> M:
    """An unpacked msgpack map validated as ``cls`` (:class:`DecodeError` naming the field if it is not)."""
    if issubclass(cls, Message):  # a payload says which contract it was written to: never assumed, never True
        version = raw.get("schema_version")
        if type(version) is not int or version != SCHEMA_VERSION:
            got = "missing" if "schema_version" not in raw else f"got {version!r}"
            raise DecodeError(cls.__name__, "schema_version", f"must be {SCHEMA_VERSION} ({got})")
    try:
        return cls.model_validate(raw)
    except ValidationError as exc:
        err = exc.errors(include_url=False)[0]
        field = ".".join(str(p) for p in err.get("loc", ())) or ""
        more = f" (+{exc.error_count() - 1} more errors)" if exc.error_count() > 1 else ""
        raise DecodeError(cls.__name__, field, f"{err.get('msg', 'invalid')}{more}") from None
    except (RecursionError, TypeError, ValueError) as exc:  # pathological nesting or unhashable keys
        raise DecodeError(cls.__name__, "", f"{type(exc).__name__}: {exc}") from None


def unpack_map(cls: type[BaseModel], data: bytes | bytearray | memoryview, *, max_bytes: int | None = None,
               max_array_len: int | None = None, max_map_len: int | None = None) -> dict:
    """Unpack msgpack ``data`` into a map, *not yet validated* as ``cls`` (errors are named after ``cls``).

    A top-level key given twice is refused: msgpack keeps the last, while a reader that looks at the first (the
    services judge a frame's order by :func:`~.wire.peek_header` before reading it) would see another message.
    A payload over ``max_bytes`` is refused unread, and ``max_array_len`` refuses any longer list before it is
    built (the hot messages' readers pass their bounds, so a payload of millions of one-byte maps costs no more
    than its size says); ``max_map_len`` refuses any larger map, the top-level one included, before it is built
    (a model with a fixed set of fields takes no map of thousands of keys, and pydantic lists every unknown key of
    one as an error of its own: 4 MB of one map had cost 2 s); and the maps and lists built in all are bounded by the
    payload's size (:class:`ContainerBudget`): all :class:`LimitExceeded`."""
    if max_bytes is not None and len(data) > max_bytes:
        raise LimitExceeded(cls.__name__, "", f"{len(data)} bytes exceed {max_bytes}")
    data = bytes(data)
    bound = {k: v for k, v in (("max_array_len", max_array_len), ("max_map_len", max_map_len)) if v is not None}
    try:
        raw = msgpack.unpackb(data, raw=False, strict_map_key=True, use_list=True, **bound,
                              **ContainerBudget(cls, len(data)).hooks())
    except LimitExceeded:  # the budget's, raised from its hook
        raise
    except Exception as exc:  # msgpack raises several unrelated types (ExtraData, ValueError, ...)
        if max_array_len is not None and "max_array_len" in str(exc):
            raise LimitExceeded(cls.__name__, "", f"a list holds more than {max_array_len} items") from None
        if max_map_len is not None and "max_map_len" in str(exc):
            raise LimitExceeded(cls.__name__, "", f"a map holds more than {max_map_len} entries") from None
        raise DecodeError(cls.__name__, "", f"not valid msgpack ({type(exc).__name__}: {exc})") from None
    if not isinstance(raw, dict):
        raise DecodeError(cls.__name__, "", f"expected a msgpack map, got {type(raw).__name__}")
    if len(raw) != _map_length(data):
        raise DecodeError(cls.__name__, "", "a top-level key is given more than once")
    return raw


def _map_length(data: bytes) -> int:
    """The entry count of the msgpack map ``data`` starts with (fixmap, map 16 or map 32)."""
    head = data[0]
    if head & 0xF0 == 0x80:
        return head & 0x0F
    return int.from_bytes(data[1:3] if head == 0xDE else data[1:5], "big")
