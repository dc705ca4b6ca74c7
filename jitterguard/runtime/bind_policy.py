"""Who may listen where: the one rule every listener of jitterguard follows (Zenoh endpoints, the HTTP sidecar).

Only the Zenoh router listens; on loopback unless a deployment says otherwise, and then only with mutual TLS
(a listener reachable from the network with no client certificate lets anyone on that network read every
message and write the classifier's config). The HTTP sidecar may leave loopback only with a token
(:func:`jitterguard.services.sidecar.core.bind_refusal`).
"""

from __future__ import annotations

import ipaddress
import socket

SECURE_PROTOCOLS = ("tls", "quic")
"""Zenoh link protocols that can authenticate the other side with a certificate."""
LOCAL_PROTOCOLS = ("unixsock-stream", "unixpipe", "vsock")
"""Links that never leave this machine."""


def is_loopback(host: str) -> bool:
    """True if every address ``host`` names is a loopback address (``localhost`` and 127/8, ::1)."""
    h = host.strip("[]")
    try:
        return ipaddress.ip_address(h.split("%", 1)[0]).is_loopback
    except ValueError:
        pass
    try:
        infos = socket.getaddrinfo(h, None)
    except (socket.gaierror, UnicodeError):
        return False
    addrs = {str(info[4][0]) for info in infos}
    return bool(addrs) and all(ipaddress.ip_address(a.split("%", 1)[0]).is_loopback for a in addrs)


def endpoint_host(endpoint: str) -> tuple[str, str]:
    """``(protocol, host)`` of a Zenoh endpoint such as ``tcp/127.0.0.1:7447#iface=lo`` or ``tls/[::1]:7447``."""
    proto, _, rest = endpoint.partition("/")
    address = rest.split("#", 1)[0].split("?", 1)[0]
    if address.startswith("["):
        return proto, address[1:].split("]", 1)[0]
    return proto, address.rsplit(":", 1)[0] if ":" in address else address


def endpoint_settings(endpoint: str) -> dict[str, str]:
    """The per-endpoint settings after ``#`` (``tls/0.0.0.0:7447#enable_mtls=false;…``), which Zenoh applies
    over the config's ``transport/link/tls`` ones."""
    _, _, tail = endpoint.partition("#")
    pairs = (item.partition("=") for item in tail.split(";") if item.strip())
    return {k.strip(): v.strip() for k, _, v in pairs}


def listen_refusal(endpoints: list[str], *, mtls: bool) -> str | None:
    """Why listening on ``endpoints`` would expose this process (None if it would not): every endpoint must be
    on loopback or a local link, or use TLS/QUIC with mutual TLS — ``mtls`` (the config's
    ``transport/link/tls/enable_mtls``) unless the endpoint's own ``#enable_mtls=…`` says otherwise (Zenoh lets
    that win: ``tls/0.0.0.0:7447#enable_mtls=false`` had opened a listener any certificate-less client reached)."""
    for ep in endpoints:
        proto, host = endpoint_host(ep)
        if proto in LOCAL_PROTOCOLS or is_loopback(host):
            continue
        own = endpoint_settings(ep).get("enable_mtls")
        if proto in SECURE_PROTOCOLS and (mtls if own is None else own.lower() == "true"):
            continue
        if proto in SECURE_PROTOCOLS:
            return (f"refusing to listen on {ep}: a non-loopback listener needs mutual TLS "
                    f"(transport/link/tls/enable_mtls: true in the Zenoh config)")
        return (f"refusing to listen on {ep}: only loopback may be served in plain {proto}; off this host, listen "
                f"with tls/ and mutual TLS (see deploy/zenoh/router-host.json5)")
    return None
