"""Key-expression builders: the only place key strings are spelled (DESIGN.md, "The contract")."""

from __future__ import annotations

import re

PREFIX = "jg"
DEFAULT_NS = "default"
_NS = re.compile(r"^[A-Za-z0-9_\-]+$")


def check_namespace(ns: str) -> str:
    """A namespace is one key chunk: letters, digits, ``_`` and ``-`` (no ``/``, ``*``, ``$``, ``?``, ``#``)."""
    if not _NS.match(ns):
        raise ValueError(f"namespace {ns!r} must be letters, digits, '_' or '-'")
    return ns


def _base(ns: str) -> str:
    return f"{PREFIX}/{check_namespace(ns)}"


def points(ns: str = DEFAULT_NS) -> str:
    return f"{_base(ns)}/points"


def groundtruth(ns: str = DEFAULT_NS) -> str:
    """Optional: the replay's labels of the frame it publishes (sources with ground truth only)."""
    return f"{_base(ns)}/groundtruth"


def detections(ns: str = DEFAULT_NS) -> str:
    return f"{_base(ns)}/detections"


def track(ns: str, track_id: str) -> str:
    return f"{_base(ns)}/tracks/{track_id}"


def tracks_all(ns: str = DEFAULT_NS) -> str:
    return f"{_base(ns)}/tracks/*"


def tracked(ns: str = DEFAULT_NS) -> str:
    return f"{_base(ns)}/tracked"


def tracks_and_tracked(ns: str = DEFAULT_NS) -> str:
    """``tracks/{id}`` and ``tracked`` in one key expression (``track$*``: a chunk that starts with "track"), for a
    subscriber that must see a frame's observations and its close in the order they were put."""
    return f"{_base(ns)}/track$*/**"


def motion(ns: str, track_id: str) -> str:
    return f"{_base(ns)}/motion/{track_id}"


def motion_all(ns: str = DEFAULT_NS) -> str:
    return f"{_base(ns)}/motion/*"


def objects(ns: str = DEFAULT_NS) -> str:
    return f"{_base(ns)}/objects"


def classifier_config(ns: str = DEFAULT_NS) -> str:
    return f"{_base(ns)}/classifier/config"


IF_MATCH = "if_match"
"""The selector parameter of a conditional config write (``classifier/config?if_match=ETAG``): applied only while
the config in force has that etag (:func:`~.models.config_etag`)."""


def classifier_state(ns: str = DEFAULT_NS) -> str:
    return f"{_base(ns)}/classifier/state"


def alive(ns: str, service: str) -> str:
    return f"{_base(ns)}/alive/{service}"


def alive_all(ns: str = DEFAULT_NS) -> str:
    return f"{_base(ns)}/alive/*"


def heartbeat(ns: str, service: str) -> str:
    return f"{_base(ns)}/heartbeat/{service}"


def heartbeat_all(ns: str = DEFAULT_NS) -> str:
    return f"{_base(ns)}/heartbeat/*"


def last_chunk(key: str) -> str:
    """The final chunk of a key expression: the track ID of ``.../tracks/{id}``, the service of ``alive/{s}``."""
    return key.rsplit("/", 1)[-1]
