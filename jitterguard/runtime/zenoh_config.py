"""Build a Zenoh session config from the flags every service shares, and open it.

Only the router listens (DESIGN "Security defaults"): a service is a Zenoh *client* of the router unless told
otherwise. Precedence for the mode: ``ZenohOptions.mode``, else the mode a ``--zenoh-config FILE`` (json5, or
the ``JG_ZENOH_CONFIG`` environment variable) sets, else ``peer`` when ``--listen`` endpoints are given (the user
chose a mesh), else ``client``. A client with no endpoint connects to the local router on
``tcp/127.0.0.1:7447`` (what ``jitterguard router`` listens on by default). ``--connect`` / ``--listen`` are added
on top; giving either, or running as a client, turns multicast scouting off unless a config file says
otherwise (explicit endpoints mean the user chose the topology, and tests must not find each other's sessions).

Every listener must pass :func:`~.bind_policy.listen_refusal` (loopback, or mutual TLS): :func:`build_config`
raises ``ValueError`` otherwise. A peer with no listen endpoint would listen on ``tcp/[::]:0`` (Zenoh's
default), so that is refused too.

A client's ``open`` fails at once while the router is not up (under supervisord the services start beside
it, in any order): :func:`open_session` retries until it is, and once connected Zenoh itself reconnects a
client whose router went away (``connect/retry`` below: 0.1 s, doubling to at most 1 s).
"""

from __future__ import annotations

import json
import logging
import os
import random
import re
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from ..files import not_a_file
from ..schemas import keys
from .bind_policy import listen_refusal

ENV_CONFIG = "JG_ZENOH_CONFIG"
ENV_NS = "JG_NS"
DEFAULT_ROUTER = "tcp/127.0.0.1:7447"
CLIENT_RETRY = {"period_init_ms": 100, "period_max_ms": 1000, "period_increase_factor": 2}
"""How fast a client reconnects to a router that went away (Zenoh's default backs off to 4 s)."""
OPEN_RETRY_S = 0.25
OPEN_LOG_EVERY_S = 30.0


@dataclass(frozen=True)
class ZenohOptions:
    """The shared service flags: namespace and how to reach the other services."""

    ns: str = keys.DEFAULT_NS
    config_file: str | None = None
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    mode: str | None = None
    extra: dict[str, object] = field(default_factory=dict)

    def __post_init__(self) -> None:
        keys.check_namespace(self.ns)


def _get(cfg: zenoh.Config, key: str) -> object:
    try:
        return json.loads(cfg.get_json(key))
    except Exception:
        return None


def _for_mode(value: object, mode: str) -> object:
    """A Zenoh "mode dependent" value: either the value or ``{router: ..., peer: ..., client: ...}``."""
    if isinstance(value, dict) and set(value) <= {"router", "peer", "client"}:
        return value.get(mode)
    return value


def _load(opts: ZenohOptions) -> tuple[zenoh.Config, bool]:
    path = opts.config_file or os.environ.get(ENV_CONFIG) or None
    if not path:
        return zenoh.Config(), False
    p = Path(path)
    if why := not_a_file(p):
        raise ValueError(f"zenoh config {why}")
    if _first_token(p) not in ("{", None):  # zenoh reads a list's first item as the config's id: "expected An hex…"
        raise ValueError(f"zenoh config {path}: expected an object {{…}} at the top level")
    try:
        return zenoh.Config.from_file(str(p)), True
    except Exception as exc:  # zenoh raises ZError with the parser's message
        raise ValueError(f"zenoh config {path}: {parser_message(str(exc))}") from None


def _first_token(path: Path) -> str | None:
    """The first character of a JSON5 / JSON / YAML file's content past comments and blanks (None: unreadable or
    none): ``{`` for a config object. YAML files (``.yaml``/``.yml``) are not judged by it."""
    if path.suffix in (".yaml", ".yml"):
        return None
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError:
        return None
    text = re.sub(r"/\*.*?\*/|//[^\n]*", "", text, flags=re.S).lstrip()
    return text[0] if text else None


def parser_message(text: str) -> str:
    """Zenoh's config parser's error in one line: ``line L, column C: what`` from its multi-line caret display, without
    the Rust source path it ends with (``… at /root/.cargo/…/lib.rs:1486.``)."""
    where = re.search(r"-->\s*(\d+):(\d+)", text)
    said = [line.strip()[1:].strip() for line in text.splitlines() if line.strip().startswith("= ")]
    what = said[-1] if said else " ".join(text.split())
    what = re.sub(r"\s+at\s+\S+\.rs:\d+\.?$", "", what)
    return f"line {where[1]}, column {where[2]}: {what}" if where else what


def build_config(opts: ZenohOptions) -> zenoh.Config:
    """Turn :class:`ZenohOptions` into a ``zenoh.Config`` (raises ``ValueError`` naming the bad input, including
    a listener that :func:`~.bind_policy.listen_refusal` refuses)."""
    cfg, from_file = _load(opts)
    mode = opts.mode or _get(cfg, "mode") or ("peer" if opts.listen else "client")
    if mode not in ("client", "peer", "router"):
        raise ValueError(f"zenoh mode must be client, peer or router, got {mode!r}")
    try:
        cfg.insert_json5("mode", json.dumps(mode))
        file_says = from_file and _get(cfg, "scouting/multicast/enabled") is not None
        if (opts.connect or opts.listen or mode == "client") and not file_says:
            # explicit endpoints or a client: multicast scouting off unless a file says otherwise (a client file
            # silent on it had left Zenoh's default on, binding 224.0.0.224:7446; a file that turned it on had been
            # overridden by --connect)
            cfg.insert_json5("scouting/multicast/enabled", "false")
        if opts.connect:
            cfg.insert_json5("connect/endpoints", json.dumps(list(opts.connect)))
        elif mode == "client" and not _for_mode(_get(cfg, "connect/endpoints"), mode):
            cfg.insert_json5("connect/endpoints", json.dumps([DEFAULT_ROUTER]))
        if mode == "client" and _get(cfg, "connect/retry") is None:
            cfg.insert_json5("connect/retry", json.dumps(CLIENT_RETRY))
        if opts.listen:
            cfg.insert_json5("listen/endpoints", json.dumps(list(opts.listen)))
        for key, value in opts.extra.items():
            cfg.insert_json5(key, json.dumps(value))
    except Exception as exc:
        raise ValueError(f"invalid zenoh endpoint or setting: {exc}") from None
    reason = listen_refusal(listen_endpoints(cfg, mode), mtls=_get(cfg, "transport/link/tls/enable_mtls") is True)
    if reason:
        raise ValueError(reason)
    return cfg


def listen_endpoints(cfg: zenoh.Config, mode: str | None = None) -> list[str]:
    """The endpoints a session opened with ``cfg`` listens on, Zenoh's defaults included (a peer with none
    listens on ``tcp/[::]:0``, a router on ``tcp/[::]:7447``; a client on nothing by default — but on whatever
    ``listen/endpoints`` names: Zenoh 1.x clients do listen, and a client file naming ``tcp/0.0.0.0:…`` had
    opened a plain listener on every interface unchecked)."""
    mode = mode or _get(cfg, "mode") or "peer"
    eps = _for_mode(_get(cfg, "listen/endpoints"), mode)
    if mode == "client":
        return [str(e) for e in eps] if eps else []  # type: ignore[union-attr]
    if eps:
        return [str(e) for e in eps]  # type: ignore[union-attr]
    return ["tcp/[::]:7447"] if mode == "router" else ["tcp/[::]:0"]


def config_endpoints(cfg: zenoh.Config) -> list[str]:
    """Every endpoint a session opened with ``cfg`` connects to or listens on, in its mode."""
    mode = str(_get(cfg, "mode") or "peer")
    endpoints = [str(e) for e in (_for_mode(_get(cfg, "connect/endpoints"), mode) or [])]  # type: ignore[union-attr]
    return endpoints + listen_endpoints(cfg, mode)


class UnusableConfig(ValueError):
    """The session cannot open whatever the wait: its config names a file that is not there or not usable (a TLS
    key or certificate). Waiting for a router would hide it for ever."""


UNUSABLE_MARKERS = ("No such file or directory", "Permission denied", "Invalid TLS", "Missing TLS")
"""Words of zenoh's open error that no wait will cure (the router's TLS files are missing or unreadable)."""


TLS_FILE_KEYS = ("root_ca_certificate", "listen_certificate", "listen_private_key", "connect_certificate",
                 "connect_private_key")
"""The TLS settings of a Zenoh config that name files (the ``*_base64`` twins carry the bytes themselves)."""


def tls_file_refusal(cfg: zenoh.Config) -> str | None:
    """Why the TLS files ``cfg`` names cannot be used (one line naming the setting and the file), or ``None``.

    Checked before the open because a *client* need not report them: with ``connect/timeout_ms: -1`` (as the
    service hosts' template once set) its open retries the TLS link for ever without a word, and otherwise its
    failure reads as a router that is not up yet. Only a config with a ``tls/`` or ``quic/`` endpoint is checked (the others never read them)."""
    endpoints = config_endpoints(cfg)
    if not any(e.startswith(("tls/", "quic/")) for e in endpoints):
        return None
    # a TLS listener needs its certificate and key: zenoh's own "Missing TLS private key" came only once the
    # session was tried, as a log line
    tls_listen = [e for e in listen_endpoints(cfg) if e.startswith(("tls/", "quic/"))]
    missing = [key for key in ("listen_certificate", "listen_private_key")
               if not _get(cfg, f"transport/link/tls/{key}") and not _get(cfg, f"transport/link/tls/{key}_base64")]
    if tls_listen and missing:
        return (f"the listener {tls_listen[0]} needs transport/link/tls/{missing[0]} (its file) in the --zenoh-config"
                " file (see docs/deployment.md)")
    for key in TLS_FILE_KEYS:
        path = _get(cfg, f"transport/link/tls/{key}")
        if not isinstance(path, str) or not path:
            continue
        try:
            with open(path, "rb"):
                pass
        except OSError as exc:
            return f"transport/link/tls/{key} {path}: {exc.strerror or exc}"
        if not Path(path).is_file():
            return f"transport/link/tls/{key} {path}: not a file"
    return None


def open_session(cfg: zenoh.Config, *, stop: threading.Event | None = None, timeout_s: float | None = None,
                 log: logging.Logger | None = None, retry_if: Callable[[str], bool] | None = None,
                 waiting_for: str | None = None, on_retry: Callable[[], None] | None = None) -> zenoh.Session:
    """``zenoh.open(cfg)``, retried every 0.25 s while it fails (a client whose router is not up yet), until
    ``stop`` is set or ``timeout_s`` passes (then the last error is raised). Says so in ``log`` at the first
    failure and every 30 s after. An error no wait will cure raises :class:`UnusableConfig` at once, in one line:
    a TLS file the config names that cannot be read (:func:`tls_file_refusal`), or an open error that says so;
    with ``retry_if``, also every open error whose text it does not accept (the router waits only for its port,
    see :mod:`.router`). ``waiting_for`` is what the log says it waits for (default: the router at the
    ``connect/endpoints``). ``on_retry`` is called before each wait (a watchdog ping: waiting is not hanging)."""
    reason = tls_file_refusal(cfg)
    if reason:
        raise UnusableConfig(f"cannot open the Zenoh session: {reason}")
    stop = stop or threading.Event()
    deadline = None if timeout_s is None else time.monotonic() + timeout_s
    last_log = None
    while True:
        try:
            return zenoh.open(cfg)
        except Exception as exc:  # zenoh.ZError: e.g. "Unable to connect to any of [tcp/127.0.0.1:7447]"
            text = str(exc)
            # zenoh appends the Rust source location of each cause: not the user's business
            line = re.sub(r" at \S+\.rs:\d+\.?", "", text.splitlines()[0] if text else "").strip()
            if any(m in text for m in UNUSABLE_MARKERS) or (retry_if is not None and not retry_if(text)):
                raise UnusableConfig(f"cannot open the Zenoh session: {line}") from None
            now = time.monotonic()
            if stop.is_set() or (deadline is not None and now >= deadline):
                raise
            if log is not None and (last_log is None or now - last_log >= OPEN_LOG_EVERY_S):
                what = waiting_for or _awaited(cfg)
                log.warning("cannot open the Zenoh session (%s); retrying until %s", line or type(exc).__name__, what)
                last_log = now
            if on_retry is not None:
                on_retry()
            stop.wait(OPEN_RETRY_S if deadline is None else max(0.0, min(OPEN_RETRY_S, deadline - now)))


def _awaited(cfg: zenoh.Config) -> str:
    """What a failing open waits for, in the log's words: the router it connects to, or (a session that only
    listens) its own listen endpoint, held by a process still ending."""
    mode = _get(cfg, "mode") or "peer"
    connect = _for_mode(_get(cfg, "connect/endpoints"), str(mode))
    if connect:
        return f"the router at {connect} is up"
    listen = listen_endpoints(cfg, str(mode))
    return f"it can listen on {', '.join(listen)}" if listen else "it can open (no endpoint to connect to)"


EPHEMERAL_RANGE_FILE = Path("/proc/sys/net/ipv4/ip_local_port_range")
"""Linux's range of ports the kernel hands out by itself (to ``bind(port 0)`` and to every outgoing connect)."""

LOWEST_CHOSEN_PORT = 20000
"""The lowest port :func:`free_tcp_port` picks: above the registered ports services usually take (5432, 7447, 8080)."""

FREE_PORT_TRIES = 64


def free_tcp_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free on ``host`` (an IPv4 or IPv6 literal, or a name) a moment ago (for tests and local
    stacks: ``up --port 0``).

    Picked *outside* the kernel's ephemeral range where it is known (Linux), at random among the ports that bind.
    A port from that range is handed out again by the kernel itself between this check and its use: to a peer's
    ``listen tcp/127.0.0.1:0``, or as the local end of any connect, including one to that very port while nothing
    listens there yet (TCP self-connect). Either way the session meant to listen there waited for the port for
    ever (CI, 7 Dec: a test's own client session held it). Outside the range only another explicit choice can take
    it. The pick is deliberately unseeded: processes choosing side by side (the two halves of the test run) must
    not draw the same sequence."""
    family, _, _, _, addr = socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM)[0]
    pool = _ports_outside_ephemeral_range()
    rng = random.SystemRandom()
    for _ in range(FREE_PORT_TRIES if pool else 0):
        port = rng.choice(pool)
        with socket.socket(family, socket.SOCK_STREAM) as s:
            try:
                s.bind((addr[0], port, *addr[2:]))
            except OSError:
                continue
            return port
    with socket.socket(family, socket.SOCK_STREAM) as s:  # no known range, or every try was taken
        s.bind(addr)
        return int(s.getsockname()[1])


def _ports_outside_ephemeral_range() -> list[int]:
    """The ports from :data:`LOWEST_CHOSEN_PORT` up that the kernel never hands out by itself (empty where the
    ephemeral range is not known)."""
    try:
        low, high = (int(v) for v in EPHEMERAL_RANGE_FILE.read_text().split())
    except (OSError, ValueError):
        return []
    return [p for p in range(LOWEST_CHOSEN_PORT, 65536) if not low <= p <= high]


def loopback_options(ns: str, port: int, *, listen_self: bool = False, mode: str = "peer") -> ZenohOptions:
    """Options for a single-host mesh around one listening endpoint on ``tcp/127.0.0.1:port`` (tests, benches).

    The session that owns ``port`` passes ``listen_self=True``; everyone else connects to it.
    """
    ep = f"tcp/127.0.0.1:{port}"
    if listen_self:
        return ZenohOptions(ns=ns, listen=(ep,), mode=mode)
    if mode == "client":
        return ZenohOptions(ns=ns, connect=(ep,), mode=mode)
    return ZenohOptions(ns=ns, connect=(ep,), listen=("tcp/127.0.0.1:0",), mode=mode)
