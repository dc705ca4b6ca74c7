"""Shared service runtime: Zenoh config from flags, the Service base class, counters, logging.

The names below are imported when first asked for (PEP 562), not with the package: a part that needs no Zenoh
session — the stack's monitor-watch (:mod:`jitterguard.stack.watch`), a supervisord event listener that reads
``JG_WATCHDOG_S`` through :mod:`.envvars` — then starts in ~20 MB, not the ~60 MB that Zenoh and pydantic take."""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .service import Counters, Service, setup_logging
    from .zenoh_config import ENV_CONFIG, ZenohOptions, build_config, free_tcp_port, loopback_options, open_session

_HOME = {"Counters": "service", "Service": "service", "setup_logging": "service", "ENV_CONFIG": "zenoh_config",
         "ZenohOptions": "zenoh_config", "build_config": "zenoh_config", "free_tcp_port": "zenoh_config",
         "loopback_options": "zenoh_config", "open_session": "zenoh_config"}

__all__ = ["Counters", "Service", "setup_logging", "ENV_CONFIG", "ZenohOptions", "build_config",
           "free_tcp_port", "loopback_options", "open_session"]


def __getattr__(name: str) -> Any:
    """``from jitterguard.runtime import Service``: the submodule that holds it, imported now."""
    home = _HOME.get(name)
    if home is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f".{home}", __name__), name)
