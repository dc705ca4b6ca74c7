"""What the sidecar refuses before a request reaches a route: foreign ``Host``, cross-site writes, non-JSON
writes and oversized bodies.

Why each rule (all reproduced against an unguarded sidecar, issue 18):

- ``Host`` (400): a page on ``http://attacker.example:8000`` whose name is re-pointed at 127.0.0.1 (DNS
  rebinding) is same-origin with the sidecar as far as the browser knows; only the ``Host`` header gives it
  away. Allowed: IP literals (the bound address; any when bound to a wildcard), ``localhost`` when bound to
  loopback, and names given with ``--allowed-host``.
- Cross-site writes (403): a page anywhere can send ``POST /v1/config/preset/authors`` with a "simple"
  content type and no preflight. A write whose ``Origin`` is not the sidecar's own (nor a ``--cors-origin``),
  or that a browser marks ``Sec-Fetch-Site: cross-site``, is refused.
- Non-JSON writes (415): a write with a body, or with any ``Content-Type``, must say ``application/json`` (or a
  ``+json`` type such as ``application/merge-patch+json``); browsers cannot send that cross-site without a CORS
  preflight, which the sidecar does not grant unless told to. A bodyless write (``POST .../preset/NAME``) may
  omit the header: a browser always sends ``Origin`` with it, so the Origin rule covers it.
- Encoded writes (415): a ``Content-Encoding`` other than ``identity`` is refused; the body had been read as if
  it were not encoded.
- Bodies over 64 KB (413): refused from ``Content-Length`` before reading a byte, and a chunked body is cut off
  at the cap (a 33 MB body used to take 4.5 GB and block ``/healthz`` for 35 s).

The rules are pure functions of the request line and headers; :class:`RequestGuard` is the ASGI middleware
that applies them (outermost, so nothing else reads a refused body).
"""

from __future__ import annotations

import hmac
import ipaddress
import json
from collections.abc import Awaitable, Callable, Iterable, MutableMapping
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import urlsplit

from ...runtime.bind_policy import is_loopback

MAX_BODY_BYTES = 64 * 1024
WRITE_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]


@dataclass(frozen=True)
class HostPolicy:
    """Which ``Host`` names the sidecar answers to, derived from its bind address."""

    bind_host: str
    extra_hosts: frozenset[str] = field(default_factory=frozenset)
    cors_origins: frozenset[str] = field(default_factory=frozenset)

    @property
    def wildcard(self) -> bool:
        return self.bind_host.strip("[]") in ("0.0.0.0", "::", "")

    def host_allowed(self, host: str) -> bool:
        """``host`` is the name part of a ``Host`` header (no port), lowercase."""
        if host in self.extra_hosts:
            return True
        try:
            addr = ipaddress.ip_address(host.strip("[]"))
        except ValueError:
            return host == "localhost" and is_loopback(self.bind_host)
        if self.wildcard:
            return True
        try:
            bound = ipaddress.ip_address(self.bind_host.strip("[]"))
        except ValueError:  # bound by name: that name's loopback-ness decides for loopback literals
            return addr.is_loopback and is_loopback(self.bind_host)
        return addr == bound or (addr.is_loopback and bound.is_loopback)


def split_host(value: str) -> str:
    """The name part of a ``Host`` header value: ``example.com:8000`` → ``example.com``, ``[::1]:80`` → ``[::1]``."""
    value = value.strip().lower()
    if value.startswith("["):
        return value.split("]", 1)[0] + "]"
    return value.rsplit(":", 1)[0] if value.count(":") == 1 else value


def is_json_type(content_type: str | None) -> bool:
    """``application/json`` or ``application/<anything>+json``, parameters (charset) ignored."""
    if not content_type:
        return False
    mime = content_type.split(";", 1)[0].strip().lower()
    return mime == "application/json" or (mime.startswith("application/") and mime.endswith("+json"))


def refusal(method: str, headers: dict[str, str], policy: HostPolicy, max_body: int = MAX_BODY_BYTES, *,
            is_write_route: bool = True) -> tuple[int, str] | None:
    """``(status, detail)`` if the request must be refused from its headers alone, else None.

    ``headers`` are lowercase names to values (the last of repeated headers: :data:`SINGLE_HEADERS` given twice are
    refused before this). ``is_write_route``: whether a route serves this method on this path (if not, the app's
    own 404/405 is the better answer)."""
    if "content-length" in headers and "transfer-encoding" in headers:
        # the server frames the body by Transfer-Encoding (RFC 9112 §6.3) while a small Content-Length had let a
        # write's body past the size check unbuffered: 32 MB read and parsed, without a token, before the 401
        return 400, "Content-Length and Transfer-Encoding given together; send one of them"
    host_header = headers.get("host")
    if host_header is not None and not policy.host_allowed(split_host(host_header)):
        return 400, (f"Host {host_header!r} is not this sidecar's (DNS rebinding?); use its address, or start "
                     f"it with --allowed-host NAME")
    length = headers.get("content-length")
    if length is not None:
        try:
            n = int(length)
        except ValueError:
            return 400, "Content-Length is not an integer"
        if n > max_body:
            return 413, f"request body of {n} bytes is over the limit of {max_body} bytes"
    if method.upper() not in WRITE_METHODS or not is_write_route:
        return None
    origin = headers.get("origin")
    if headers.get("sec-fetch-site") == "cross-site" or (origin is not None and not _origin_allowed(
            origin, host_header, policy)):
        told = f"Origin {origin!r}" if origin is not None else "Sec-Fetch-Site: cross-site"
        return 403, f"cross-site write refused ({told}); writes come from this sidecar's own page or a client " \
                    f"that sends neither a foreign Origin nor Sec-Fetch-Site: cross-site (or an origin given " \
                    f"with --cors-origin)"
    content_type = headers.get("content-type")
    has_body = (length is not None and length.strip() != "0") or "transfer-encoding" in headers
    if (content_type is not None or has_body) and not is_json_type(content_type):
        return 415, "writes must be sent with Content-Type: application/json"
    encoding = headers.get("content-encoding", "identity").strip().lower()
    if encoding not in ("", "identity"):  # a gzip body had been read as plain JSON (applied if it happened to parse)
        return 415, f"Content-Encoding {encoding!r} is not taken; send the JSON body as it is"
    return None


def _origin_allowed(origin: str, host_header: str | None, policy: HostPolicy) -> bool:
    if origin in policy.cors_origins:
        return True
    if origin == "null" or host_header is None:
        return False
    parts = urlsplit(origin)
    return parts.scheme in ("http", "https") and parts.netloc.lower() == host_header.strip().lower()


SINGLE_HEADERS = ("host", "content-length", "transfer-encoding", "content-type", "origin", "sec-fetch-site",
                  "authorization", "content-encoding")
"""Headers the guard or a route reads one value of. Given twice, the guard (reading the last) and FastAPI (reading
the first) had judged different values: a write sent with ``Content-Type: text/plain`` then ``application/json``
passed the guard's 415 and met the app as text."""


def repeated_header(raw: Iterable[tuple[bytes, bytes]]) -> str | None:
    """The first of :data:`SINGLE_HEADERS` that ``raw`` (an ASGI scope's headers) holds more than once, or None."""
    seen: set[str] = set()
    for k, _ in raw:
        name = k.decode("latin-1").lower()
        if name in SINGLE_HEADERS:
            if name in seen:
                return name
            seen.add(name)
    return None


TOKEN_REFUSAL = "missing or wrong bearer token (JG_API_TOKEN)"


def bearer_matches(authorization: str | None, token: str | None) -> bool:
    """Whether an ``Authorization`` header carries ``token`` as a bearer credential (always, with no token): the
    one test of a write's token, made by the guard before the body is read and by the routes' ``require_writer``."""
    if token is None:
        return True
    scheme, _, credentials = (authorization or "").partition(" ")
    return scheme.lower() == "bearer" and hmac.compare_digest(credentials.encode(), token.encode())


class RequestGuard:
    """ASGI middleware applying :func:`refusal`, then — with a ``token`` — :func:`bearer_matches` to every write
    (401 before its body is read: a write without the token had been read and parsed, up to 64 KB, before the
    route refused it), and reading every write's body itself, cut off at ``max_body`` bytes (whatever its
    Content-Length said). A HEAD for which ``head_as_get`` holds goes on as a GET."""

    def __init__(self, app: Callable[[Scope, Receive, Send], Awaitable[None]], policy: HostPolicy, *,
                 is_route: Callable[[Scope], bool] = lambda _scope: True,
                 head_as_get: Callable[[Scope], bool] = lambda _scope: False, max_body: int = MAX_BODY_BYTES,
                 token: str | None = None, on_refuse: Callable[[int], None] | None = None) -> None:
        self.app, self.policy, self.is_route, self.head_as_get = app, policy, is_route, head_as_get
        self.token = token
        self.max_body, self.on_refuse = max_body, on_refuse

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        raw = scope.get("headers", ())
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in raw}
        write = scope["method"].upper() in WRITE_METHODS
        write_route = write and self.is_route(scope)
        twice = repeated_header(raw)
        refused = (400, f"{twice.title()} given more than once") if twice is not None else refusal(
            scope["method"], headers, self.policy, self.max_body, is_write_route=write_route)
        if refused is None and write_route and not bearer_matches(headers.get("authorization"), self.token):
            refused = (401, TOKEN_REFUSAL)
        if refused is None and write:  # every write's body read here, up to the cap, whatever its headers said
            receive, refused = await self._buffer(receive)
        if refused is not None:
            if self.on_refuse is not None:
                self.on_refuse(refused[0])
            await _respond(send, *refused)
            return
        if scope["method"] == "HEAD" and self.head_as_get(scope):  # the server's own scope stays HEAD: no body sent
            scope = {**scope, "method": "GET"}
        await self.app(scope, receive, send)

    async def _buffer(self, receive: Receive) -> tuple[Receive, tuple[int, str] | None]:
        """Read a body of unknown length up to the cap; a longer one is refused without reading the rest."""
        chunks: list[bytes] = []
        size = 0
        while True:
            message = await receive()
            if message["type"] != "http.request":
                return _replay([message], receive), None
            size += len(message.get("body", b""))
            if size > self.max_body:
                return receive, (413, f"request body over the limit of {self.max_body} bytes")
            chunks.append(message.get("body", b""))
            if not message.get("more_body", False):
                body = {"type": "http.request", "body": b"".join(chunks), "more_body": False}
                return _replay([body], receive), None


def _replay(messages: Iterable[Message], then: Receive) -> Receive:
    """``messages`` first, then the server's own ``receive`` (which reports a disconnect when it happens)."""
    pending = list(messages)

    async def replayed() -> Message:
        if pending:
            return pending.pop(0)
        return await then()

    return replayed


async def _respond(send: Send, status: int, detail: str) -> None:
    body = json.dumps({"detail": detail}).encode()
    challenge = [(b"www-authenticate", b"Bearer")] if status == 401 else []
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                            (b"connection", b"close"), *challenge]})
    await send({"type": "http.response.body", "body": body})
