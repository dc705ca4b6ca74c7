"""Build a Zenoh session config from the flags every service shares.

Precedence: ``--zenoh-config FILE`` (json5), else the ``JG_ZENOH_CONFIG`` environment variable, else Zenoh's
defaults (peer mode with multicast scouting, which finds the other services on one host with no flags).
``--connect`` / ``--listen`` endpoints are added on top; giving either turns multicast scouting off, because
explicit endpoints mean the user chose the topology (and tests must not find each other's sessions).
"""

from __future__ import annotations

import json
import os
import socket
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from ..schemas import keys

ENV_CONFIG = "JG_ZENOH_CONFIG"
ENV_NS = "JG_NS"


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


def build_config(opts: ZenohOptions) -> zenoh.Config:
    """Turn :class:`ZenohOptions` into a ``zenoh.Config`` (raises ``ValueError`` naming the bad input)."""
    path = opts.config_file or os.environ.get(ENV_CONFIG) or None
    if path:
        p = Path(path)
        if not p.is_file():
            raise ValueError(f"zenoh config file not found: {path}")
        try:
            cfg = zenoh.Config.from_file(str(p))
        except Exception as exc:  # zenoh raises ZError with the parser's message
            raise ValueError(f"zenoh config {path}: {exc}") from None
    else:
        cfg = zenoh.Config()
    try:
        if opts.mode:
            cfg.insert_json5("mode", json.dumps(opts.mode))
        if opts.connect or opts.listen:
            cfg.insert_json5("scouting/multicast/enabled", "false")
        if opts.connect:
            cfg.insert_json5("connect/endpoints", json.dumps(list(opts.connect)))
        if opts.listen:
            cfg.insert_json5("listen/endpoints", json.dumps(list(opts.listen)))
        for key, value in opts.extra.items():
            cfg.insert_json5(key, json.dumps(value))
    except Exception as exc:
        raise ValueError(f"invalid zenoh endpoint or setting: {exc}") from None
    return cfg


def free_tcp_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free a moment ago (for tests and local stacks)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def loopback_options(ns: str, port: int, *, listen_self: bool = False, mode: str = "peer") -> ZenohOptions:
    """Options for a single-host mesh around one listening endpoint on ``tcp/127.0.0.1:port``.

    The session that owns ``port`` passes ``listen_self=True``; everyone else connects to it.
    """
    ep = f"tcp/127.0.0.1:{port}"
    if listen_self:
        return ZenohOptions(ns=ns, listen=(ep,), mode=mode)
    return ZenohOptions(ns=ns, connect=(ep,), listen=("tcp/127.0.0.1:0",), mode=mode)
