"""The sidecar's HTTP routes, as module-level FastAPI routers: health, state, config, and the rest (metrics,
events, the page). Every rule lives in ``core``; every Zenoh call in ``client``; what a route needs at run time
(settings, client, metrics, event broker) it takes from :class:`SidecarContext` on ``app.state``.

Reads of live state are ``async`` and return bytes pre-rendered by the client's poll thread (no thread hop,
no serialisation per request). Config endpoints are plain ``def``: each makes blocking Zenoh queries, so they
run in the server's thread pool and never stall the event loop.

No ``from __future__ import annotations`` here: FastAPI reads the routes' ``Annotated`` parameters at import.
"""

import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Header, HTTPException, Path, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import HTMLResponse, JSONResponse, Response, StreamingResponse
from fastapi.routing import APIRoute
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from ...schemas.models import ConfigReply
from ..classifier.config import PRESETS
from .client import ClassifierClient, ClassifierRejected, ClassifierUnavailable, ConfigConflict
from .core import (
    CLASS_NAMES,
    IF_MATCH_PATTERN,
    BodyError,
    ConfigError,
    ConfigModel,
    ConfigPatchModel,
    ErrorBody,
    HealthView,
    PresetName,
    ReadyView,
    RenderedState,
    StateView,
    TrackView,
    apply_preset,
    config_to_api,
    dumps,
    merge_patch,
    parse_if_match,
    parse_json_body,
    validate_config,
)
from .events import EventBroker
from .guard import TOKEN_REFUSAL, bearer_matches
from .metrics import SidecarMetrics

CSP = ("default-src 'self'; script-src 'self' 'unsafe-inline'; style-src 'self' 'unsafe-inline'; "
       "img-src 'self' data:; connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'")

E503 = {"model": ErrorBody, "description": "The classifier is unreachable or did not confirm; nothing applied"}
E502 = {"model": ErrorBody, "description": "The classifier refused the config"}
E502_STATE = {"model": ErrorBody, "description": "The classifier's latest replies are not signed with the sidecar's "
                                                  "JG_API_TOKEN (the tokens differ): no state can be read"}
WRITE_ERRORS: dict[int | str, dict[str, Any]] = {
    503: E503, 502: E502,
    400: {"model": ErrorBody, "description": "The body is not readable text, or the Host header is foreign"},
    401: {"model": ErrorBody, "description": "Missing or wrong bearer token (only when JG_API_TOKEN is set)"},
    403: {"model": ErrorBody, "description": "A cross-site write (Origin not this sidecar's)"},
    413: {"model": ErrorBody, "description": "Body over 64 KB"},
    415: {"model": ErrorBody, "description": "A body or Content-Type other than application/json"},
    412: {"model": ErrorBody, "description": "If-Match names another version than the one in force (its ETag header "
                                             "names that one); nothing applied"},
    409: {"model": ErrorBody, "description": "Other writers changed the config during each of 5 read-modify-writes; "
                                             "nothing applied"},
}


@dataclass
class SidecarContext:
    """What the routes share for the app's lifetime; ``client`` exists between startup and shutdown."""

    api_token: str | None
    metrics: SidecarMetrics
    broker: EventBroker
    page: str
    client: ClassifierClient | None = None


def context(request: Request) -> SidecarContext:
    return request.app.state.sidecar


def client(ctx: Annotated[SidecarContext, Depends(context)]) -> ClassifierClient:
    if ctx.client is None:  # only between construction and startup
        raise ClassifierUnavailable("the sidecar is starting")
    return ctx.client


Ctx = Annotated[SidecarContext, Depends(context)]
Client = Annotated[ClassifierClient, Depends(client)]
_bearer = HTTPBearer(auto_error=False, description="the value of JG_API_TOKEN (writes need it when it is set)")


def require_writer(ctx: Ctx, creds: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> None:
    """Writes need ``Authorization: Bearer <JG_API_TOKEN>`` when the sidecar has a token."""
    if ctx.api_token is None:
        return
    if creds is None or not bearer_matches(f"Bearer {creds.credentials}", ctx.api_token):  # the guard's own test
        raise HTTPException(401, TOKEN_REFUSAL, headers={"WWW-Authenticate": "Bearer"})


def only_query(*names: str) -> Any:
    """A dependency that refuses (422, naming it) a query parameter the route does not take, or one given twice:
    FastAPI ignores the first and keeps the last of the second, so ``/v1/state?sate=dynamic`` (a typo) had
    returned every track and ``?state=static&state=dynamic`` only the dynamic ones, both with a 200."""
    allowed = frozenset(names)

    def check(request: Request) -> None:
        seen: set[str] = set()
        errors = []
        for key, value in request.query_params.multi_items():
            if key not in allowed:
                taken = ", ".join(sorted(allowed)) or "none"
                errors.append({"type": "extra_forbidden", "loc": ["query", key], "input": value[:40],
                               "msg": f"Query parameter not taken here (this route takes: {taken})"})
            elif key in seen:
                errors.append({"type": "duplicate_query", "loc": ["query", key], "input": value[:40],
                               "msg": "Query parameter given more than once"})
            seen.add(key)
        if errors:
            raise RequestValidationError(errors)

    return Depends(check)


NO_QUERY = [only_query()]


# ---------------------------------------------------------------------------------------------- health

health_routes = APIRouter(tags=["health"], dependencies=NO_QUERY)


@health_routes.get("/healthz", response_model=HealthView, summary="The sidecar process is up (says nothing about the classifier)")
async def healthz() -> dict[str, str]:
    return {"status": "ok"}


@health_routes.get("/readyz", response_model=ReadyView,
            responses={503: {"model": ReadyView, "description": "The classifier is not reachable, or a service of "
                                                                "the pipeline reports no progress"}},
            summary="The classifier is reachable (liveliness and a recent heartbeat) and no service of the pipeline "
                    "reports failing or stalled frames")
async def readyz(c: Client) -> JSONResponse:
    ready = c.readiness(refusals=True)
    return JSONResponse(ready, status_code=200 if ready["ready"] else 503)


# ---------------------------------------------------------------------------------------------- state

state_routes = APIRouter(tags=["state"])
StateFilter = Annotated[str | None, Query(pattern="^(static|dynamic|undecided)$", description="only tracks in this state")]
ClassFilter = Annotated[str | None, Query(alias="class", pattern="^(" + "|".join(CLASS_NAMES) + ")$",
                                          description="only tracks of this class")]


def _live_state(c: ClassifierClient) -> tuple[RenderedState, dict[str, str]]:
    """The cached snapshot while the classifier is alive, with freshness headers; 503 once it is gone, 502 while
    the classifier refuses this sidecar's polls.

    A late heartbeat alone does not hide the state: an overloaded classifier is exactly when an operator
    needs to see it. ``X-Classifier-Ready`` and ``X-State-Age-Ms`` say how far to trust it. A refused poll does:
    a classifier restarted with another ``JG_API_TOKEN`` answers no poll of this sidecar's again, and the state
    read before it had been served as 200 for ever, only its age header growing.
    """
    if not c.is_alive():
        raise ClassifierUnavailable(f"classifier not ready: {c.readiness()['reason']}")
    refusal = c.poll_refusal()
    if refusal is not None:
        raise ClassifierRejected(f"no state from the classifier: {refusal}")
    st = c.rendered_state()
    if st is None:
        raise ClassifierUnavailable("no state from the classifier yet")
    age_ms = max(0.0, (time.time_ns() - st.polled_at_ns) / 1e6)
    return st, {"X-Classifier-Seq": str(st.seq), "X-Classifier-Ready": str(c.readiness_flag()).lower(),
                "X-State-Age-Ms": f"{age_ms:.1f}"}


@state_routes.get("/v1/state", response_model=StateView, responses={503: E503, 502: E502_STATE},
           summary="Every track the classifier decided in its latest frame",
           description=("Served from a cache refreshed every poll period. Headers: `X-Classifier-Seq` (the frame), "
                        "`X-Classifier-Ready` (what `/readyz` says: false while the classifier's heartbeat is late — the "
                        "state may be stale — or another stage fails or stalls), "
                        "`X-State-Age-Ms` (since the sidecar fetched it). 503 once the classifier's liveliness "
                        "token is gone; 502 while the classifier refuses this sidecar's polls (another token)."), dependencies=[only_query("state", "class")])
async def get_state(c: Client, state: StateFilter = None, cls: ClassFilter = None) -> Response:
    st, headers = _live_state(c)
    if state is None and cls is None:
        return Response(st.body, media_type="application/json", headers=headers)
    tracks = [t for t in st.tracks.values()
              if (state is None or t["state"] == state) and (cls is None or t["class"] == cls)]
    view = {"seq": st.seq, "stamp_ns": st.stamp_ns, "frame_id": st.frame_id, "mode": st.config.mode,
            "polled_at_ns": st.polled_at_ns, "counts": st.counts, "tracks": tracks, "calibration": st.calibration}
    return Response(dumps(view), media_type="application/json", headers=headers)


@state_routes.get("/v1/state/{track_id}", response_model=TrackView,
           responses={404: {"model": ErrorBody, "description": "No such track in the latest frame"}, 503: E503,
                      502: E502_STATE},
           summary="One track by ID", dependencies=NO_QUERY)
async def get_track(c: Client, track_id: Annotated[str, Path(pattern="^[0-9a-fA-F]{32}$",
                                                             description="32 hex digits")]) -> Response:
    st, headers = _live_state(c)
    t = st.tracks.get(track_id.lower())
    if t is None:
        raise HTTPException(404, f"no track {track_id.lower()} in the classifier's frame {st.seq}")
    return Response(dumps(t), media_type="application/json", headers=headers)


@state_routes.get("/v1/events", response_class=StreamingResponse,
           responses={200: {"content": {"text/event-stream": {"schema": {"type": "string"}}},
                            "description": (
                                "Server-sent events. `hello` (counts, seq, ready) on connect; `changes` "
                                "{seq, changes: [{id, class, from, to, statistic, threshold, x, y}]} when "
                                "tracks appear (from null), vanish (to null) or change state; `config` "
                                "(the config now in force); `ready` {ready, reason}; `resync` where this "
                                "client fell behind and lost events (refetch /v1/state: every event after it is "
                                "newer than those lost). `Last-Event-ID` is not read: no replay on reconnect.")},
                      503: {"model": ErrorBody, "description": "As many event streams are open as the sidecar "
                                                               "serves (64)"}},
           summary="Server-sent events of state changes", dependencies=NO_QUERY)
async def events(request: Request, ctx: Ctx, c: Client) -> StreamingResponse:
    st = c.served_state()
    ready = c.readiness()
    hello = {"ready": ready["ready"], "reason": ready["reason"], "seq": st.seq if st else None,
             "counts": st.counts if st else None}
    body = ctx.broker.open(hello, request.is_disconnected)
    if body is None:
        raise HTTPException(503, "too many open event streams; try again later", headers={"Retry-After": "5"})
    return StreamingResponse(body, media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})


# ---------------------------------------------------------------------------------------------- config

class _JSONBodyRequest(Request):
    """A request whose JSON body is read by :func:`~.core.parse_json_body`: a 5000-digit integer or a key given
    twice is a 422 naming the field, undecodable text or nesting too deep a 400 saying so (FastAPI's own reading
    answered all of these with a 400 "There was an error parsing the body"). FastAPI passes an ``HTTPException``
    raised here through unchanged; a syntax error stays its own 422."""

    async def json(self) -> Any:
        if not hasattr(self, "_json"):
            try:
                self._json = parse_json_body(await self.body())
            except BodyError as exc:
                raise HTTPException(exc.status, exc.detail) from None
        return self._json


class JSONBodyRoute(APIRoute):
    """A route whose handler sees a :class:`_JSONBodyRequest` (the routes with a JSON body)."""

    def get_route_handler(self) -> Callable[[Request], Any]:
        handler = super().get_route_handler()

        async def with_json_body(request: Request) -> Response:
            return await handler(_JSONBodyRequest(request.scope, request.receive))

        return with_json_body


config_routes = APIRouter(tags=["config"], route_class=JSONBodyRoute, dependencies=NO_QUERY)
Writer = [Depends(require_writer)]


async def no_body(request: Request) -> None:
    """A route that takes no body accepts none, or ``{}``; anything else is refused (422; 400 if unreadable) and
    nothing is applied: a preset POST had applied its preset whatever came with it, malformed JSON included."""
    if not (await request.body()).strip():
        return
    try:
        value = await request.json()
    except json.JSONDecodeError as exc:
        raise RequestValidationError([{"type": "json_invalid", "loc": ["body", exc.pos], "input": None,
                                       "msg": f"JSON decode error: {exc.msg}"}]) from None
    if value != {}:
        raise RequestValidationError([{"type": "no_body", "loc": ["body"], "input": None,
                                       "msg": "This route takes no body (none, or {})"}])


def if_match(request: Request, value: Annotated[str, Header(  # `str`, not `str | None`: absent, never null
        alias="If-Match", pattern=IF_MATCH_PATTERN,
        description='the ETag of GET /v1/config this write is meant for: applied only while that version is in '
                    'force (412 otherwise); "*" or none: whatever is in force')] = None,  # type: ignore[assignment]
             ) -> str | None:
    """The version a write is meant for. A header given twice is a list (RFC 9110 §5.3), refused as a list on one
    line is: FastAPI reads the first, so ``If-Match: *`` before a stale tag had applied the write unconditionally."""
    if len(request.headers.getlist("if-match")) > 1:
        raise RequestValidationError([{"type": "duplicate_header", "loc": ["header", "If-Match"], "input": None,
                                       "msg": "If-Match given more than once: name one version"}])
    return parse_if_match(value)


IfMatch = Annotated[str | None, Depends(if_match)]


def _tagged(reply: ConfigReply, response: Response) -> dict[str, Any]:
    """The config of a reply, its etag in the ``ETag`` header (what a later ``If-Match`` names)."""
    response.headers["ETag"] = f'"{reply.etag}"'
    return config_to_api(reply.config)


def _write(ctx: SidecarContext, response: Response, do: Callable[[], ConfigReply]) -> dict[str, Any]:
    """Run one write and count its outcome (``jitterguard_sidecar_config_writes{result}``)."""
    try:
        reply = do()
    except ConfigConflict:
        ctx.metrics.config_writes.labels("conflict").inc()
        raise
    except ConfigError:
        ctx.metrics.config_writes.labels("invalid").inc()
        raise
    except ClassifierUnavailable:
        ctx.metrics.config_writes.labels("unavailable").inc()
        raise
    except ClassifierRejected:
        ctx.metrics.config_writes.labels("rejected").inc()
        raise
    ctx.metrics.config_writes.labels("ok").inc()
    return _tagged(reply, response)


@config_routes.get("/v1/config", response_model=ConfigModel, responses={503: E503, 502: E502},
            summary="The config in force now (asked from the classifier, not cached); ETag: its version")
def get_config(c: Client, response: Response) -> dict[str, Any]:
    return _tagged(c.get_config(), response)


@config_routes.put("/v1/config", response_model=ConfigModel, dependencies=Writer, responses=WRITE_ERRORS,
            summary="Replace the whole config (omitted fields take their defaults)")
def put_config(ctx: Ctx, c: Client, body: ConfigModel, tag: IfMatch,  # type: ignore[valid-type]
               response: Response) -> dict[str, Any]:
    def put() -> ConfigReply:  # validated inside the counted write: a refusal counts `invalid`, as a PATCH's does
        cfg = validate_config(body.model_dump(), touched=body.model_fields_set)  # type: ignore[attr-defined]
        return c.replace_config(cfg, if_match=tag)

    return _write(ctx, response, put)


@config_routes.patch("/v1/config", response_model=ConfigModel, dependencies=Writer, responses=WRITE_ERRORS,
              summary="Change some fields (JSON merge patch: null resets a field, a null class alpha drops it)")
def patch_config(ctx: Ctx, c: Client, body: ConfigPatchModel, tag: IfMatch,  # type: ignore[valid-type]
                 response: Response) -> dict[str, Any]:
    patch = body.model_dump(exclude_unset=True)  # type: ignore[attr-defined]
    return _write(ctx, response, lambda: c.update_config(lambda cur: merge_patch(cur, patch), if_match=tag))


@config_routes.get("/v1/config/presets", summary="The named presets and the fields each one sets")
async def list_presets() -> dict[str, dict[str, Any]]:
    return {name: dict(fields) for name, fields in PRESETS.items()}


@config_routes.post("/v1/config/preset/{name}", response_model=ConfigModel, dependencies=[*Writer, Depends(no_body)],
                    responses=WRITE_ERRORS,
             summary="Apply a named preset; every field it does not name stays")
def post_preset(ctx: Ctx, c: Client, name: Annotated[PresetName, Path(description="preset name")],  # type: ignore[valid-type]
                tag: IfMatch, response: Response) -> dict[str, Any]:
    return _write(ctx, response, lambda: c.update_config(lambda cur: apply_preset(cur, name), if_match=tag))


# ---------------------------------------------------------------------------------------------- metrics, page

misc_routes = APIRouter()
PAGE_QUERY = ("view", "refresh", "track")
"""What the page reads from its own address (in the browser): a fixed view ``x0,y0,x1,y1`` [m], the refresh period
[ms], the track selected."""


@misc_routes.get("/metrics", tags=["metrics"], response_class=Response, dependencies=NO_QUERY,
          responses={200: {"content": {CONTENT_TYPE_LATEST.split(";")[0]: {"schema": {"type": "string"}}},
                           "description": "Prometheus text exposition"}},
          summary="Prometheus metrics: frames, tracks, static/dynamic by class, rejects, frame latency")
def get_metrics(ctx: Ctx) -> Response:
    return Response(generate_latest(ctx.metrics.registry), media_type=CONTENT_TYPE_LATEST)


@misc_routes.get("/", response_class=HTMLResponse, tags=["page"], summary="Live bird's-eye view of the tracks",
                 dependencies=[only_query(*PAGE_QUERY)])
async def index(ctx: Ctx) -> HTMLResponse:
    return HTMLResponse(ctx.page, headers={"Content-Security-Policy": CSP, "Cache-Control": "no-cache"})


ROUTERS = (health_routes, state_routes, config_routes, misc_routes)
