"""The FastAPI app: settings, lifespan, error bodies and the request guard around the routers of ``routes``.

Layers of a request, outermost first: :class:`~.guard.RequestGuard` (foreign Host, cross-site or non-JSON
writes, bodies over 64 KB, writes without the bearer token when ``JG_API_TOKEN`` is set: refused before anything
reads the body), CORS when ``--cors-origin`` is given, the routes (the token checked again, and declared in the
schema), and the exception handlers below, which turn
every error into ``{"detail": ...}``.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from importlib import resources

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

from ...runtime import ZenohOptions
from ..classifier.config_writes import api_token_from_env
from .client import ClassifierClient, ClassifierRejected, ClassifierUnavailable, ConfigConflict, ConfigContended
from .core import ConfigError, jsonable_errors
from .events import MAX_STREAMS, EventBroker
from .guard import MAX_BODY_BYTES, HostPolicy, RequestGuard
from .metrics import SidecarMetrics
from .routes import NO_QUERY, ROUTERS, SidecarContext


@dataclass(frozen=True)
class SidecarSettings:
    """Everything the app needs; the CLI builds it from flags and the environment."""

    zenoh: ZenohOptions = field(default_factory=ZenohOptions)
    api_token: str | None = None
    cors_origins: tuple[str, ...] = ()
    poll_period_s: float = 0.05
    query_timeout_s: float = 3.0
    stale_after_s: float = 3.0
    bind_host: str = "127.0.0.1"
    allowed_hosts: tuple[str, ...] = ()
    max_body_bytes: int = MAX_BODY_BYTES
    max_event_streams: int = MAX_STREAMS

    @staticmethod
    def token_from_env() -> str | None:
        """``JG_API_TOKEN`` as the classifier reads it (blank counts as unset)."""
        return api_token_from_env()


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("jitterguard")
    except Exception:
        return "0"


def _page() -> str:
    return resources.files(__package__).joinpath("static/index.html").read_text(encoding="utf-8")


def create_app(settings: SidecarSettings, *, stopping: threading.Event | None = None) -> FastAPI:
    """Build the sidecar app; its Zenoh session opens at startup and closes at shutdown (lifespan).

    ``stopping``: set by the server on SIGINT/SIGTERM. The session's open waits for the router as long as it is
    not up, inside the server's startup, where the server only notes a signal; this event ends that wait, and
    the app then starts without a session so the server can carry out the stop it was asked for."""
    metrics = SidecarMetrics()
    ctx = SidecarContext(api_token=settings.api_token, metrics=metrics, page=_page(),
                         broker=EventBroker(on_drop=metrics.sse_dropped.inc, on_count=metrics.sse_clients.set,
                                            max_streams=settings.max_event_streams))

    @asynccontextmanager
    async def lifespan(_app: FastAPI) -> AsyncIterator[None]:
        try:
            ctx.client = ClassifierClient(settings.zenoh, poll_period_s=settings.poll_period_s,
                                          query_timeout_s=settings.query_timeout_s,
                                          stale_after_s=settings.stale_after_s, metrics=metrics,
                                          api_token=settings.api_token, stop_event=stopping)
        except Exception:
            if stopping is None or not stopping.is_set():
                raise
            logging.getLogger("jitterguard.sidecar").info("stopped while waiting for the router")
            yield  # nothing opened: the server goes on to the stop it was asked for
            return
        ctx.client.add_listener(ctx.broker.publish)
        try:
            yield
        finally:
            ctx.broker.close()
            ctx.client.close()

    app = FastAPI(
        title="jitterguard sidecar",
        version=_version(),
        summary="Live motion-classifier state and tunable thresholds over HTTP.",
        description=("Reads are open. Writes (PUT/PATCH/POST under /v1/config) need `Content-Type: "
                     "application/json`, no foreign `Origin`, a body under 64 KB, and `Authorization: Bearer "
                     "<JG_API_TOKEN>` when that variable is set. A write is applied by the classifier between two "
                     "frames before the reply, which returns the config now in force."),
        lifespan=lifespan,
        # Swagger UI / ReDoc would pull their scripts from a CDN: nothing here loads assets from the internet
        # (vehicle networks are often offline). The schema itself stays at /openapi.json.
        docs_url=None,
        redoc_url=None,
        openapi_url=None,  # served below as every route is: a query parameter it does not take is a 422
        # /v1/state/ is no route: a 404, not a 307 to /v1/state (a client that follows it re-sends a write to
        # another path; one that does not gets nothing it asked for)
        redirect_slashes=False,
    )
    app.state.sidecar = ctx
    for router in ROUTERS:
        app.include_router(router)

    @app.get("/openapi.json", include_in_schema=False, dependencies=NO_QUERY)
    async def openapi_schema() -> JSONResponse:
        return JSONResponse(app.openapi())

    for exc_type, handler in _HANDLERS.items():
        app.add_exception_handler(exc_type, handler)
    if settings.cors_origins:
        app.add_middleware(CORSMiddleware, allow_origins=list(settings.cors_origins),
                           allow_methods=["GET", "HEAD", "PUT", "PATCH", "POST"],
                           allow_headers=["Authorization", "Content-Type"])
    policy = HostPolicy(settings.bind_host, frozenset(h.lower() for h in settings.allowed_hosts),
                        frozenset(settings.cors_origins))


    def is_route(scope: dict) -> bool:  # a route serves this method here (else the app answers 404/405)
        return any(route.matches(scope)[0] == Match.FULL for route in app.router.routes)

    app.add_middleware(RequestGuard, policy=policy, is_route=is_route, head_as_get=lambda scope: serves_head(app, scope),
                       max_body=settings.max_body_bytes, token=settings.api_token,
                       on_refuse=lambda status: metrics.refused_requests.labels(str(status)).inc())
    return app


# ------------------------------------------------------------------------------------------------ error bodies


HTTP_METHODS = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS")

STREAM_PATHS = frozenset({"/v1/events"})
"""GET routes that answer with an endless stream: a HEAD there would hold a stream's place for nothing (405)."""


def _full_match(app: FastAPI, scope: dict, method: str) -> bool:
    return any(route.matches({**scope, "method": method})[0] == Match.FULL for route in app.router.routes)


def serves_head(app: FastAPI, scope: dict) -> bool:
    """Whether a HEAD here is answered as the path's GET (RFC 9110 §9.3.2: every general-purpose server supports
    HEAD where it supports GET). FastAPI registers GET alone, so a HEAD had been a 405 on every route but the two
    health routes that declared it. The guard serves it as the GET; uvicorn, whose own scope still says HEAD,
    sends the headers (``ETag``, ``Content-Length``) and drops the body. Not on :data:`STREAM_PATHS`."""
    return scope.get("path") not in STREAM_PATHS and _full_match(app, scope, "GET")


async def _http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    # Starlette's 405 lists only the first matching route's methods; FastAPI has one route per method,
    # so ``Allow`` would omit PUT/PATCH on /v1/config. List every method the path really serves.
    # Asked per method (a full match), not read off ``route.methods``: routes of an included router sit behind
    # one entry that has no ``methods`` of its own.
    headers = dict(exc.headers or {})
    if exc.status_code == 405:
        allowed = {m for m in HTTP_METHODS if _full_match(request.app, request.scope, m)}
        if serves_head(request.app, request.scope):
            allowed.add("HEAD")
        headers["Allow"] = ", ".join(sorted(allowed))
    return JSONResponse({"detail": exc.detail}, status_code=exc.status_code, headers=headers)


async def _invalid_request(_r: Request, exc: RequestValidationError) -> JSONResponse:
    # FastAPI's own handler echoes inputs as-is; a NaN input would then fail to serialise (a 500).
    return JSONResponse({"detail": jsonable_errors(exc.errors())}, status_code=422)


async def _config_error(_r: Request, exc: ConfigError) -> JSONResponse:
    return JSONResponse({"detail": exc.errors}, status_code=422)


async def _unavailable(_r: Request, exc: ClassifierUnavailable) -> JSONResponse:
    return JSONResponse({"detail": str(exc)}, status_code=503, headers={"Retry-After": "1"})


async def _rejected(_r: Request, exc: ClassifierRejected) -> JSONResponse:
    return JSONResponse({"detail": str(exc)}, status_code=502)


async def _conflict(_r: Request, exc: ConfigConflict) -> JSONResponse:
    """412 for a write whose ``If-Match`` is not the version in force (its ``ETag`` names the one that is), 409 for
    a read-modify-write that lost to other writers every time; nothing applied either way."""
    status = 409 if isinstance(exc, ConfigContended) else 412
    return JSONResponse({"detail": str(exc)}, status_code=status,
                        headers={"ETag": f'"{exc.etag}"'} if exc.etag else None)


_HANDLERS = {StarletteHTTPException: _http_error, RequestValidationError: _invalid_request,
             ConfigError: _config_error, ClassifierUnavailable: _unavailable, ClassifierRejected: _rejected,
             ConfigConflict: _conflict}
