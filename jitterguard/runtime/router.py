"""A Zenoh router inside a Python process, so a deployment needs no separate ``zenohd`` binary."""

from __future__ import annotations

import json
import logging
import signal
import threading

import zenoh

from .zenoh_config import ZenohOptions, build_config

log = logging.getLogger("jitterguard.router")


def router_config(listen: list[str], config_file: str | None = None) -> zenoh.Config:
    """Router mode, listening on ``listen``, multicast scouting off (services connect explicitly)."""
    cfg = build_config(ZenohOptions(config_file=config_file, listen=tuple(listen), mode="router"))
    cfg.insert_json5("scouting/multicast/enabled", json.dumps(False))
    return cfg


def run_router(listen: list[str], config_file: str | None = None, stop: threading.Event | None = None) -> None:
    """Serve until SIGINT/SIGTERM (or ``stop`` is set)."""
    stop = stop or threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stop.set())
    session = zenoh.open(router_config(listen, config_file))
    log.info("zenoh router %s listening on %s", session.zid(), ", ".join(listen))
    try:
        while not stop.wait(0.5):
            pass
    finally:
        session.close()
        log.info("router stopped")
