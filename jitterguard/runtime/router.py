"""A Zenoh router inside a Python process, so a deployment needs no separate ``zenohd`` binary.

The router is the one process of the stack that listens (DESIGN "Security defaults"): on loopback by default,
and off loopback only with mutual TLS (:func:`~.bind_policy.listen_refusal` refuses anything else).
"""

from __future__ import annotations

import json
import logging
import os
import threading
from pathlib import Path

import zenoh

from .sd_notify import Notifier
from .signals import stop_on_signals
from .zenoh_config import (DEFAULT_ROUTER, ENV_CONFIG, UnusableConfig, ZenohOptions, build_config, listen_endpoints,
                           open_session)

log = logging.getLogger("jitterguard.router")

BLOCK_WAIT_KEY = "transport/link/tx/queue/congestion_control/block/wait_before_close"
BLOCK_WAIT_US = 1_000_000
"""How long the router holds a message sent with BLOCK (every frame message) for a peer whose queue toward it is
full, before it closes that peer's transport: 1 s, where Zenoh's default is 5 s. While it holds one, the router
reads nothing more from the sender, so one stopped subscriber (a SIGSTOPped classifier) held every heartbeat and
frame on the bus up for 5–10 s (6 Dec); with 1 s, 1–2.6 s. A peer that leaves its queue full for a second after
its socket's buffer has filled is stopped, not slow: every service drains its socket in a thread of its own into
a bounded queue (:class:`~.ingest_queue.IngestQueue`). A Zenoh config file that names ``wait_before_close`` keeps
its own value."""


def _file_listen(path: str | None) -> tuple[str, ...]:
    """The router endpoints the Zenoh config file at ``path`` names (none if it names none or cannot be read: then
    :func:`build_config` reports the file's problem). A file that does not name ``listen`` names none: Zenoh fills in
    its own default, ``tcp/[::]:7447``, which had been taken as the file's choice and refused as off loopback where
    the router's own default, ``tcp/127.0.0.1:7447``, was meant."""
    if not path or not _file_names(path, "listen"):
        return ()
    try:
        eps = json.loads(zenoh.Config.from_file(path).get_json("listen/endpoints"))
    except Exception:
        return ()
    if isinstance(eps, dict):  # mode dependent
        eps = eps.get("router")
    return tuple(str(e) for e in eps or ())


def _may_wait(error: str) -> bool:
    """Whether a failed router open is worth retrying: its listen port is still held (e.g. by the router that
    supervisord or systemd is replacing), or the address it listens on is not up yet (early at boot)."""
    return any(m in error for m in ("Address already in use", "os error 98", "Cannot assign requested address",
                                    "os error 99"))


def _file_names(path: str | None, word: str) -> bool:
    """Whether the Zenoh config file at ``path`` names ``word`` — a setting its author chose, which the router
    keeps (Zenoh reports a default and a chosen value alike)."""
    try:
        return bool(path) and word in Path(path).read_text(errors="replace")
    except OSError:
        return False


def router_config(listen: list[str], config_file: str | None = None) -> zenoh.Config:
    """Router mode, listening on ``listen``; with none, on the config file's endpoints, else on
    ``tcp/127.0.0.1:7447``. Multicast scouting off (services connect explicitly); a stopped peer's transport
    closed after :data:`BLOCK_WAIT_US`. Raises ``ValueError`` for a listener off loopback without mutual TLS, or
    a bad config file."""
    path = config_file or os.environ.get(ENV_CONFIG)  # the file build_config reads too
    endpoints = tuple(listen) or _file_listen(path) or (DEFAULT_ROUTER,)
    cfg = build_config(ZenohOptions(config_file=config_file, listen=endpoints, mode="router"))
    cfg.insert_json5("scouting/multicast/enabled", json.dumps(False))
    if not _file_names(path, BLOCK_WAIT_KEY.rsplit("/", 1)[-1]):
        cfg.insert_json5(BLOCK_WAIT_KEY, json.dumps(BLOCK_WAIT_US))
    return cfg


def run_router(listen: list[str], config_file: str | None = None, stop: threading.Event | None = None) -> None:
    """Serve until SIGINT/SIGTERM (or ``stop`` is set). Raises :class:`UnusableConfig` when no wait would let it
    listen (a TLS file zenoh rejects, an access-control policy it cannot read)."""
    stop = stop or threading.Event()
    stop_on_signals(stop.set)
    cfg = router_config(listen, config_file)
    notifier = Notifier()  # systemd's watchdog (WatchdogSec=): a stopped or hung router stops pinging
    try:
        # only a port still held (by a router that just died) is worth a wait; anything else — a missing or
        # unreadable TLS file, a certificate that is not PEM, an access-control policy Zenoh rejects — had been
        # retried for ever as "retrying until the router at [] is up", and SIGTERM then ended it in a traceback
        session = open_session(cfg, stop=stop, log=log, retry_if=_may_wait,
                               waiting_for=f"it can listen on {', '.join(listen_endpoints(cfg, 'router'))}",
                               on_retry=lambda: notifier.send("WATCHDOG=1"))
    except UnusableConfig:  # the caller's one line and exit 2, not a retry for ever
        raise
    except Exception:
        if stop.is_set():  # stopped while waiting for the port: a clean stop, not a traceback
            log.info("router stopped before it could listen")
            return
        raise
    log.info("zenoh router %s listening on %s", session.zid(), cfg.get_json("listen/endpoints"))
    try:
        while not stop.wait(0.5):
            notifier.send("WATCHDOG=1")
    finally:
        notifier.close()
        session.close()
        log.info("router stopped")
