"""The FastAPI app: routes, auth, error bodies. Every rule lives in ``core``; every Zenoh call in ``client``.

Reads of live state are ``async`` and return bytes pre-rendered by the client's poll thread (no thread hop,
no serialisation per request). Config endpoints are plain ``def``: each makes blocking Zenoh queries, so they
run in the server's thread pool and never stall the event loop.

No ``from __future__ import annotations`` here: FastAPI resolves the closures' ``Annotated`` dependencies
at runtime, and those name locals of :func:`create_app`.
"""

import hmac
import os
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from importlib import resources
from typing import Annotated, Any

from fastapi import Depends, FastAPI, HTTPException, Path, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import HTMLResponse, JSONResponse, Response, StreamingResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

from ...runtime import ZenohOptions
from ...schemas.models import ClassifierConfig
from ..classifier.config import PRESETS
from .client import ClassifierClient, ClassifierRejected, ClassifierUnavailable
from .core import (
    RenderedState,
    CLASS_NAMES,
    ConfigError,
    ConfigModel,
    ConfigPatchModel,
    ErrorBody,
    HealthView,
    PresetName,
    ReadyView,
    StateView,
    TrackView,
    apply_preset,
    config_to_api,
    dumps,
    jsonable_errors,
    merge_patch,
    validate_config,
)
from .events import EventBroker
from .metrics import SidecarMetrics

ENV_TOKEN = "JG_API_TOKEN"
CSP = ("default-src 'self'; script-src 'self' 'unsafe-inline'; style-src 'self' 'unsafe-inline'; "
       "img-src 'self' data:; connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'")

_E503 = {"model": ErrorBody, "description": "The classifier is unreachable or did not confirm; nothing applied"}
_E502 = {"model": ErrorBody, "description": "The classifier refused the config"}
_E401 = {"model": ErrorBody, "description": "Missing or wrong bearer token (JG_API_TOKEN is set)"}


@dataclass(frozen=True)
class SidecarSettings:
    """Everything the app needs; the CLI builds it from flags and the environment."""

    zenoh: ZenohOptions = field(default_factory=ZenohOptions)
    api_token: str | None = None
    cors_origins: tuple[str, ...] = ()
    poll_period_s: float = 0.05
    query_timeout_s: float = 3.0
    stale_after_s: float = 3.0

    @staticmethod
    def token_from_env() -> str | None:
        """``JG_API_TOKEN``; empty counts as unset (an empty secret protects nothing)."""
        return os.environ.get(ENV_TOKEN) or None


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("jitterguard")
    except Exception:
        return "0"


def _page() -> str:
    return resources.files(__package__).joinpath("static/index.html").read_text(encoding="utf-8")


def create_app(settings: SidecarSettings) -> FastAPI:
    """Build the sidecar app; its Zenoh session opens at startup and closes at shutdown (lifespan)."""
    metrics = SidecarMetrics()
    broker = EventBroker(on_drop=metrics.sse_dropped.inc, on_count=metrics.sse_clients.set)
    page = _page()
    holder: dict[str, ClassifierClient] = {}

    @asynccontextmanager
    async def lifespan(_app: FastAPI) -> AsyncIterator[None]:
        client = ClassifierClient(settings.zenoh, poll_period_s=settings.poll_period_s,
                                  query_timeout_s=settings.query_timeout_s, stale_after_s=settings.stale_after_s,
                                  metrics=metrics)
        client.add_listener(broker.publish)
        holder["client"] = client
        _app.state.client = client
        try:
            yield
        finally:
            broker.close()
            client.close()

    app = FastAPI(
        title="jitterguard sidecar",
        version=_version(),
        summary="Live motion-classifier state and tunable thresholds over HTTP.",
        description=("Reads are open. Writes (PUT/PATCH/POST under /v1/config) need `Authorization: Bearer "
                     "<JG_API_TOKEN>` when that variable is set. A write is applied by the classifier between "
                     "two frames before the reply, which returns the config now in force."),
        lifespan=lifespan,
        # Swagger UI / ReDoc would pull their scripts from a CDN: nothing here loads assets from the internet
        # (vehicle networks are often offline). The schema itself stays at /openapi.json.
        docs_url=None,
        redoc_url=None,
    )
    if settings.cors_origins:
        app.add_middleware(CORSMiddleware, allow_origins=list(settings.cors_origins),
                           allow_methods=["GET", "PUT", "PATCH", "POST"],
                           allow_headers=["Authorization", "Content-Type"])

    def client() -> ClassifierClient:
        c = holder.get("client")
        if c is None:  # only between construction and startup
            raise ClassifierUnavailable("the sidecar is starting")
        return c

    # ------------------------------------------------------------------ auth

    write_deps: list[Any] = []
    write_errors: dict[int | str, dict[str, Any]] = {
        503: _E503, 502: _E502, 400: {"model": ErrorBody, "description": "The body is not readable text"}}
    if settings.api_token:
        bearer = HTTPBearer(auto_error=False, description="the value of JG_API_TOKEN")
        token = settings.api_token.encode()

        def require_token(creds: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]) -> None:
            if creds is None or not hmac.compare_digest(creds.credentials.encode(), token):
                raise HTTPException(401, "missing or wrong bearer token (JG_API_TOKEN)",
                                    headers={"WWW-Authenticate": "Bearer"})

        write_deps.append(Depends(require_token))
        write_errors[401] = _E401

    # ------------------------------------------------------------------ error bodies

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        # Starlette's 405 lists only the first matching route's methods; FastAPI has one route per method,
        # so ``Allow`` would omit PUT/PATCH on /v1/config. List every method the path really serves.
        headers = dict(exc.headers or {})
        if exc.status_code == 405:
            allowed: set[str] = set()
            for route in app.router.routes:
                match, _ = route.matches(request.scope)
                if match != Match.NONE:
                    allowed |= set(getattr(route, "methods", None) or ())
            headers["Allow"] = ", ".join(sorted(allowed))
        return JSONResponse({"detail": exc.detail}, status_code=exc.status_code, headers=headers)

    @app.exception_handler(RequestValidationError)
    async def _invalid_request(_r: Request, exc: RequestValidationError) -> JSONResponse:
        # FastAPI's own handler echoes inputs as-is; a NaN input would then fail to serialise (a 500).
        return JSONResponse({"detail": jsonable_errors(exc.errors())}, status_code=422)

    @app.exception_handler(ConfigError)
    async def _config_error(_r: Request, exc: ConfigError) -> JSONResponse:
        return JSONResponse({"detail": exc.errors}, status_code=422)

    @app.exception_handler(ClassifierUnavailable)
    async def _unavailable(_r: Request, exc: ClassifierUnavailable) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=503, headers={"Retry-After": "1"})

    @app.exception_handler(ClassifierRejected)
    async def _rejected(_r: Request, exc: ClassifierRejected) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=502)

    def _live_state(c: ClassifierClient) -> tuple[RenderedState, dict[str, str]]:
        """The cached snapshot while the classifier is alive, with freshness headers; 503 once it is gone.

        A late heartbeat alone does not hide the state: an overloaded classifier is exactly when an operator
        needs to see it. ``X-Classifier-Ready`` and ``X-State-Age-Ms`` say how far to trust it.
        """
        if not c.is_alive():
            raise ClassifierUnavailable(f"classifier not ready: {c.readiness()['reason']}")
        st = c.rendered_state()
        if st is None:
            raise ClassifierUnavailable("no state from the classifier yet")
        age_ms = max(0.0, (time.time_ns() - st.polled_at_ns) / 1e6)
        return st, {"X-Classifier-Seq": str(st.seq), "X-Classifier-Ready": str(c.readiness_flag()).lower(),
                    "X-State-Age-Ms": f"{age_ms:.1f}"}

    # ------------------------------------------------------------------ health

    @app.get("/healthz", tags=["health"], response_model=HealthView,
             summary="The sidecar process is up (says nothing about the classifier)")
    async def healthz() -> dict[str, str]:
        return {"status": "ok"}

    @app.get("/readyz", tags=["health"], response_model=ReadyView,
             responses={503: {"model": ReadyView, "description": "The classifier is not reachable"}},
             summary="The classifier is reachable: liveliness token present and a recent heartbeat")
    async def readyz() -> JSONResponse:
        ready = client().readiness()
        return JSONResponse(ready, status_code=200 if ready["ready"] else 503)

    # ------------------------------------------------------------------ state

    StateFilter = Annotated[str | None, Query(pattern="^(static|dynamic|undecided)$",
                                              description="only tracks in this state")]
    ClassFilter = Annotated[str | None, Query(alias="class", pattern="^(" + "|".join(CLASS_NAMES) + ")$",
                                              description="only tracks of this class")]

    @app.get("/v1/state", tags=["state"], response_model=StateView, responses={503: _E503},
             summary="Every track the classifier decided in its latest frame",
             description=("Served from a cache refreshed every poll period. Headers: `X-Classifier-Seq` (the "
                          "frame), `X-Classifier-Ready` (false while the heartbeat is late: the state may be "
                          "stale), `X-State-Age-Ms` (since the sidecar fetched it). 503 once the classifier's "
                          "liveliness token is gone."))
    async def get_state(state: StateFilter = None, cls: ClassFilter = None) -> Response:
        st, headers = _live_state(client())
        if state is None and cls is None:
            return Response(st.body, media_type="application/json", headers=headers)
        tracks = [t for t in st.tracks.values()
                  if (state is None or t["state"] == state) and (cls is None or t["class"] == cls)]
        view = {"seq": st.seq, "stamp_ns": st.stamp_ns, "frame_id": st.frame_id, "mode": st.config.mode,
                "polled_at_ns": st.polled_at_ns, "counts": st.counts, "tracks": tracks}
        return Response(dumps(view), media_type="application/json", headers=headers)

    @app.get("/v1/state/{track_id}", tags=["state"], response_model=TrackView,
             responses={404: {"model": ErrorBody, "description": "No such track in the latest frame"}, 503: _E503},
             summary="One track by ID")
    async def get_track(track_id: Annotated[str, Path(pattern="^[0-9a-fA-F]{32}$",
                                                      description="32 hex digits")]) -> Response:
        st, headers = _live_state(client())
        t = st.tracks.get(track_id.lower())
        if t is None:
            raise HTTPException(404, f"no track {track_id.lower()} in the classifier's frame {st.seq}")
        return Response(dumps(t), media_type="application/json", headers=headers)

    # ------------------------------------------------------------------ config

    def _reply(cfg: ClassifierConfig) -> dict[str, Any]:
        return config_to_api(cfg)

    @app.get("/v1/config", tags=["config"], response_model=ConfigModel, responses={503: _E503, 502: _E502},
             summary="The config in force now (asked from the classifier, not cached)")
    def get_config() -> dict[str, Any]:
        return _reply(client().get_config())

    @app.put("/v1/config", tags=["config"], response_model=ConfigModel, dependencies=write_deps,
             responses=write_errors, summary="Replace the whole config (omitted fields take their defaults)")
    def put_config(body: ConfigModel) -> dict[str, Any]:  # type: ignore[valid-type]
        cfg = validate_config(body.model_dump(), touched=body.model_fields_set)  # type: ignore[attr-defined]
        return _write(lambda: client().replace_config(cfg))

    @app.patch("/v1/config", tags=["config"], response_model=ConfigModel, dependencies=write_deps,
               responses=write_errors,
               summary="Change some fields (JSON merge patch: null resets a field, a null class alpha drops it)")
    def patch_config(body: ConfigPatchModel) -> dict[str, Any]:  # type: ignore[valid-type]
        patch = body.model_dump(exclude_unset=True)  # type: ignore[attr-defined]
        return _write(lambda: client().update_config(lambda cur: merge_patch(cur, patch)))

    @app.get("/v1/config/presets", tags=["config"], summary="The named presets and the fields each one sets")
    async def list_presets() -> dict[str, dict[str, Any]]:
        return {name: dict(fields) for name, fields in PRESETS.items()}

    @app.post("/v1/config/preset/{name}", tags=["config"], response_model=ConfigModel, dependencies=write_deps,
              responses=write_errors, summary="Apply a named preset; every field it does not name stays")
    def post_preset(name: Annotated[PresetName, Path(description="preset name")]) -> dict[str, Any]:  # type: ignore[valid-type]
        return _write(lambda: client().update_config(lambda cur: apply_preset(cur, name)))

    def _write(do: Any) -> dict[str, Any]:
        try:
            cfg = do()
        except ConfigError:
            metrics.config_writes.labels("invalid").inc()
            raise
        except ClassifierUnavailable:
            metrics.config_writes.labels("unavailable").inc()
            raise
        except ClassifierRejected:
            metrics.config_writes.labels("rejected").inc()
            raise
        metrics.config_writes.labels("ok").inc()
        return _reply(cfg)

    # ------------------------------------------------------------------ metrics, events, page

    @app.get("/metrics", tags=["metrics"], response_class=Response,
             responses={200: {"content": {CONTENT_TYPE_LATEST.split(";")[0]: {"schema": {"type": "string"}}},
                              "description": "Prometheus text exposition"}},
             summary="Prometheus metrics: frames, tracks, static/dynamic by class, rejects, frame latency")
    def get_metrics() -> Response:
        return Response(generate_latest(metrics.registry), media_type=CONTENT_TYPE_LATEST)

    @app.get("/v1/events", tags=["state"], response_class=StreamingResponse,
             responses={200: {"content": {"text/event-stream": {"schema": {"type": "string"}}},
                              "description": (
                                  "Server-sent events. `hello` (counts, seq, ready) on connect; `changes` "
                                  "{seq, changes: [{id, class, from, to, statistic, threshold, x, y}]} when "
                                  "tracks appear (from null), vanish (to null) or change state; `config` "
                                  "(the config now in force); `ready` {ready, reason}; `resync` if this "
                                  "client fell behind and lost events.")}},
             summary="Server-sent events of state changes")
    async def events(request: Request) -> StreamingResponse:
        c = client()
        st = c.rendered_state()
        ready = c.readiness()
        hello = {"ready": ready["ready"], "reason": ready["reason"], "seq": st.seq if st else None,
                 "counts": st.counts if st else None}
        return StreamingResponse(broker.stream(hello, request.is_disconnected), media_type="text/event-stream",
                                 headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})

    @app.get("/", response_class=HTMLResponse, tags=["page"], summary="Live bird's-eye view of the tracks")
    async def index() -> HTMLResponse:
        return HTMLResponse(page, headers={"Content-Security-Policy": CSP, "Cache-Control": "no-cache"})

    return app
