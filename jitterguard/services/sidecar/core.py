"""The sidecar's pure core: HTTP view models, snapshot → JSON, config merge and validation, change
detection, metric aggregation and the bind policy.

Nothing here does I/O or reads a clock, so every rule the HTTP API promises (what a track looks like, what
PATCH means, which field a 422 names, when a bind is refused) is unit-tested without a network.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Annotated, Any, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, Strict, ValidationError, create_model
from pydantic.fields import FieldInfo

from ...runtime.bind_policy import is_loopback
from ...schemas.models import (
    LABEL_NAMES,
    CalibrationState,
    ETAG_HEX,
    ClassifierConfig,
    ClassifierStateSnapshot,
)
from ..classifier.config import PRESETS

STATES: tuple[str, ...] = ("static", "dynamic", "undecided")
CLASS_NAMES: tuple[str, ...] = tuple(LABEL_NAMES[i] for i in sorted(LABEL_NAMES))
ClassName = Literal[CLASS_NAMES]  # type: ignore[valid-type]
PresetName = Literal[tuple(PRESETS)]  # type: ignore[valid-type]

# ----------------------------------------------------------------------------------------- view models
# These models document the JSON the API returns (OpenAPI) and are what the tests validate against. The hot
# path (``GET /v1/state``) builds the same shape as plain dicts and serialises them once per snapshot.


class TrackView(BaseModel):
    """One track as the classifier decided it in its latest frame."""

    model_config = ConfigDict(populate_by_name=True)

    id: str = Field(description="track ID: 32 hex digits (a 16-byte UUID)")
    label: int = Field(ge=0, le=7, description="Autoware ObjectClassification label (0..7)")
    class_: str = Field(alias="class", description="lowercase class name (car, truck, ..., pedestrian)")
    state: Literal["static", "dynamic", "undecided"]
    z_x: float = Field(description="two-sample z statistic along world x")
    z_y: float = Field(description="two-sample z statistic along world y")
    z: float = Field(description="max(z_x, z_y): what the z-test compares with alpha")
    chi2: float = Field(description="the chi2 statistic (chi2 mode)")
    statistic: float = Field(description="the value compared with `threshold` in the mode in force "
                                         "(z, chi2, or speed in m/s)")
    alpha: float = Field(description="the alpha used for this track's class")
    threshold: float = Field(description="what `statistic` was compared with (alpha, chi2 quantile or m/s)")
    window_length: int = Field(ge=0, description="observations in the track's window")
    window_size: int = Field(ge=0, description="the window's capacity (config `window_size`)")
    window_fill: float = Field(ge=0.0, le=1.0, description="window_length / window_size")
    speed: float = Field(description="the tracker's speed estimate, m/s")
    x: float = Field(description="position x, world frame, m (static tracks: the window mean)")
    y: float = Field(description="position y, world frame, m (static tracks: the window mean)")
    yaw: float = Field(description="heading, rad")
    length: float = Field(description="box length, m")
    width: float = Field(description="box width, m")
    last_update_ns: int = Field(ge=0, description="stamp of the track's latest observation, ns")
    last_seq: int = Field(ge=0, description="frame seq of the track's latest observation")
    frames_since_update: int = Field(ge=0, description="frames between the snapshot and the last observation")


class StateCounts(BaseModel):
    static: int = Field(ge=0)
    dynamic: int = Field(ge=0)
    undecided: int = Field(ge=0)
    total: int = Field(ge=0)


class StateView(BaseModel):
    """The classifier's live state after its latest frame, as last polled by the sidecar."""

    seq: int = Field(ge=0, description="seq of the classifier's latest frame")
    stamp_ns: int = Field(ge=0, description="stamp of the classifier's latest frame, ns")
    frame_id: str
    mode: Literal["z_test", "chi2", "velocity_threshold"]
    polled_at_ns: int = Field(ge=0, description="wall time (ns since epoch) when the sidecar fetched it")
    counts: StateCounts
    tracks: list[TrackView]
    calibration: CalibrationState | None = Field(
        None, description="the variance calibration the frame was decided with: scales per class group, "
        "line-of-sight axis, range band and track age, and the measured serial correlation (docs/calibration.md)")


class ErrorBody(BaseModel):
    """Why a request could not be served (503/502/401/404)."""

    detail: str


class HealthView(BaseModel):
    status: Literal["ok"]


class ServiceHealthView(BaseModel):
    """One service of the pipeline as its latest heartbeat describes it."""

    health: Literal["ok", "failing", "stalled", "silent"] = Field(
        description="ok, failing (frames keep failing), stalled (input arrives, no output) or silent (no recent "
                    "heartbeat: frozen, stopped, or gone; what its last heartbeat said is then out of date)")
    reason: str = Field(description="why not ok ('' when ok)")
    heartbeat_age_s: float = Field(ge=0.0, description="seconds since this heartbeat arrived")
    last_seq: int = Field(description="the last frame seq the service reported")


class ReadyView(BaseModel):
    """Readiness: the classifier's liveliness token is present and its heartbeat is recent, and no service of the
    pipeline reports (in a recent heartbeat) that its frames fail or its output stalled, or is silent while its
    liveliness token is present (frozen), and frames that enter the pipeline come out (:func:`frames_standing`)."""

    ready: bool
    reason: str = Field(description="why not ready, or 'ok'")
    liveliness: bool = Field(description="the classifier's liveliness token is present")
    heartbeat_age_s: float | None = Field(description="seconds since the last classifier heartbeat, if any")
    last_seq: int | None = Field(description="the last frame seq the classifier reported in its heartbeat")
    state_seq: int | None = Field(description="seq of the state snapshot the sidecar serves, if any")
    services: dict[str, ServiceHealthView] = Field(
        default_factory=dict, description="every service heard from in the namespace, by name")
    warnings: list[str] = Field(
        default_factory=list, description="why a ready pipeline may serve no new objects, without being a fault"
        " (no input is none: a sensor may be off): a source that left the bus, the classifier's frames standing"
        " still")


PIPELINE_STAGES: frozenset[str] = frozenset({"detector", "tracker"})
"""The services between the source and the classifier: while one of them is away, no frame reaches the classifier.
A source (``replay``, ``feed-tracks``) leaves when its recording ends; bridges and recorders are not in the path."""
SOURCES: frozenset[str] = frozenset({"replay", "feed-tracks", "ros2-in"})
"""The services that feed the pipeline. One that leaves the bus is no readiness fault (a sensor may be off, a
recording may end), but it is what an operator looking at a ready sidecar with no objects needs to know:
``/readyz`` names it under ``warnings``."""


def service_problems(services: Mapping[str, Mapping[str, Any]], stale_after_s: float,
                     on_bus: set[str] | frozenset[str] = frozenset(),
                     left: set[str] | frozenset[str] = frozenset()) -> list[tuple[str, str]]:
    """``(name, "tracker failing: ...")`` for each service whose heartbeat, still recent, reports no progress;
    ``"tracker: no heartbeat for 8.2 s ..."`` for each whose heartbeat is stale while its liveliness token is still
    present (``on_bus``): a process frozen (stopped, hung without the GIL), which no watchdog inside it can catch;
    and ``"tracker: left the bus ..."`` for a pipeline stage (:data:`PIPELINE_STAGES`) whose heartbeat is stale and
    whose token was withdrawn (``left``): crashed and not restarted, or frozen past its Zenoh lease (~10 s), when a
    frozen process's token expires and it had looked like one that left. A service outside the pipeline that left
    the same way (the monitor, a bridge) gets the same line, a warning: a monitor frozen past its lease had
    dropped out of ``warnings`` after ~10 s while it stayed frozen. A source (:data:`SOURCES`) that left is said
    elsewhere (the end of a recording is no fault), and a stale heartbeat that never had a token, nothing.

    Only the pipeline's own (:func:`is_pipeline`) make ``/readyz`` fail; the rest are its ``warnings``: a monitor
    that cannot write its summary, a frozen Foxglove bridge or a failing source do not stop the classifier's
    objects from being right (a monitor on a full disk had made the classifier "not ready")."""
    out = []
    for name, v in sorted(services.items()):
        if v["heartbeat_age_s"] <= stale_after_s:
            if v["health"] != "ok":
                out.append((name, f"{name} {v['health']}: {v['reason']}"))
        elif name in on_bus:
            out.append((name, f"{name}: no heartbeat for {v['heartbeat_age_s']:.1f} s while its liveliness token is "
                              "present (frozen?)"))
        elif name in left and name not in SOURCES and name != "classifier":
            out.append((name, f"{name}: left the bus (no heartbeat for {v['heartbeat_age_s']:.1f} s, liveliness "
                              "token withdrawn): " + ("crashed, or frozen past its Zenoh lease" if name in PIPELINE_STAGES
                                                       else "stopped, crashed, or frozen past its Zenoh lease")))
    return out


def silenced(services: Mapping[str, Mapping[str, Any]], stale_after_s: float,
             problems: list[tuple[str, str]]) -> dict[str, dict[str, Any]]:
    """``services`` with every entry whose heartbeat is stale marked ``silent``, its reason the problem found for
    it (or how long it has been quiet): ``/readyz`` had listed a frozen tracker as ``"health": "ok"`` — its last
    heartbeat's word — beside a reason that blamed it, and ``jitterguard_service_healthy`` 0."""
    why = dict(problems)
    return {name: (dict(v, health="silent", reason=why.get(name, f"no heartbeat for {v['heartbeat_age_s']:.1f} s"))
                   if v["heartbeat_age_s"] > stale_after_s else dict(v))
            for name, v in services.items()}


PIPELINE_STALL_S = 30.0
"""Frames entering the pipeline this long while not one comes out of the classifier is a readiness fault: as long
as the slowest stage may hold a frame by its own account (the detector's stall limit: a CPU network under load)."""


def frames_standing(frames_at: tuple[int, float] | None, sources_moved: Mapping[str, tuple[int, float]], now: float,
                    *, warn_s: float, fault_s: float = PIPELINE_STALL_S, recent_s: float) -> tuple[str, bool] | None:
    """Why the classifier's frames stand still, and whether that is a fault: ``(message, True)`` once a source's
    heartbeat seq has moved in the last ``recent_s`` while the classifier has processed no frame for ``fault_s``
    (frames enter the pipeline and none come out: a stage between them is missing, stuck or cut off);
    ``(message, False)`` — a warning — once it has processed none for ``warn_s`` (no input is no fault: a sensor may
    be off); None before. ``frames_at``: the classifier's last seq and when it was first seen; ``sources_moved``:
    per source, its last seq and when it last changed (the caller's monotonic clock).

    Readiness had held a stage that left the bus against the pipeline only if this sidecar had seen it leave: one
    restarted after a tracker had stopped for good answered 200 "ok", the tracker unlisted, while the replay
    published and no object came out — with a warning that said "no input"."""
    if frames_at is None:
        return None
    seq, since = frames_at
    still = now - since
    last = f" (last seq {seq})" if seq >= 0 else ""
    moving = sorted((name, s) for name, (s, at) in sources_moved.items() if now - at <= recent_s)
    feeding = ", ".join(f"{name} at seq {s}" for name, s in moving)
    if moving and still >= fault_s:
        return (f"frames enter the pipeline ({feeding}) but the classifier has processed none for {still:.0f} s"
                f"{last}: a stage between them is missing, stuck or cut off (jitterguard status)"), True
    if still < warn_s:
        return None
    if not moving:
        return f"no input: the classifier has processed no frame for {still:.0f} s{last}", False
    return f"the classifier has processed no frame for {still:.0f} s{last} while frames enter ({feeding})", False


MAX_REFUSAL_COUNTERS = 16
"""Refusal counters kept per heartbeat (a real service has a few; a crafted heartbeat may carry 512)."""


def refusal_counts(counters: Mapping[str, int]) -> dict[str, int]:
    """The counters of a heartbeat that count messages a service refused: ``rejected.<key>`` (malformed, over a
    limit, of another track) and ``invalid`` (a ROS 2 bridge's messages that break the sender's contract); the
    first :data:`MAX_REFUSAL_COUNTERS` by name."""
    names = sorted(k for k in counters if k.startswith("rejected.") or k == "invalid")[:MAX_REFUSAL_COUNTERS]
    return {k: counters[k] for k in names}


def refusals_since(history: Iterable[tuple[float, Mapping[str, int]]], now: float, window_s: float) -> dict[str, int]:
    """How far each refusal counter rose over the last ``window_s``, from a service's heartbeats in order
    (``(receive time, refusal_counts)``): its newest value less its value in the newest heartbeat at least
    ``window_s`` old (or the oldest kept), counters that did not rise left out. A counter that fell (the service
    restarted) counts from 0."""
    beats = list(history)
    if len(beats) < 2:
        return {}
    base = beats[0][1]
    for at, counts in beats:
        if now - at >= window_s:
            base = counts
    newest = beats[-1][1]
    rose = {k: v - base.get(k, 0) if v >= base.get(k, 0) else v for k, v in newest.items()}
    return {k: n for k, n in sorted(rose.items()) if n > 0}


def refusal_warning(name: str, rose: Mapping[str, int], window_s: float) -> str:
    """The warning that a service refused messages: why no object, or fewer, comes although something is sent (a
    bridge fed messages that break their contract stays ``ok``: a restart cannot mend the sender's messages)."""
    parts = ", ".join(f"{k} +{n}" for k, n in list(rose.items())[:4]) + (", ..." if len(rose) > 4 else "")
    return (f"{name} refused {sum(rose.values())} messages in the last {window_s:.0f} s ({parts}): what it was sent"
            f" went no further (jitterguard logs {name})")


def is_pipeline(name: str) -> bool:
    """The services between the sensor's frames and the classifier's objects, the classifier included: a fault of
    one of them is a readiness fault."""
    return name in PIPELINE_STAGES or name == "classifier"


# ----------------------------------------------------------------------------------------- config models

_CONFIG_DOCS: dict[str, str] = {
    "mode": "test: `z_test` (the paper), `chi2` (joint x/y), or `velocity_threshold` (Autoware's baseline)",
    "alpha_default": "z threshold for classes without an override (1.96 ≈ 95 %)",
    "alpha_per_class": "per-class alpha overrides keyed by lowercase class name",
    "window_size": "observations kept per track (sliding window) at window_reference_hz; a slower stream keeps "
                   "proportionally fewer (at least 10), a faster one takes every k-th frame",
    "min_window": "observations needed before a track is tested (must not exceed window_size)",
    "variance_floor": "lower bound on the smaller eigenvalue of each predicted covariance, m²",
    "effective_n": "`measured` (default): the variance of the half-mean difference under the calibrated serial "
                   "correlation; `cluster`: each half counts as one sample (the paper); `independent`: real counts",
    "velocity_threshold": "speed above which the baseline calls a track dynamic, m/s (classes not in "
                          "velocity_threshold_per_class)",
}
_CONFIG_DOCS.update({name: (info.description or name) for name, info in ClassifierConfig.model_fields.items()
                     if name not in _CONFIG_DOCS and name != "schema_version"})
CONFIG_FIELDS: tuple[str, ...] = tuple(n for n in ClassifierConfig.model_fields if n != "schema_version")


def _json_integer(value: Any) -> Any:
    """JSON Schema's ``integer`` includes ``213.0``; it never includes ``true`` or ``"213"``."""
    if isinstance(value, (bool, str)):
        raise ValueError("Input should be a valid integer")
    return value


def _strict_json(tp: Any, metadata: list[Any]) -> Any:
    """``tp`` with its constraints, accepting exactly the JSON values its JSON Schema type admits.

    pydantic's lax mode would take ``false`` or ``"1.5"`` for a number, or ``0`` for a bool (a client bug silently
    applied);
    its strict mode would refuse ``213.0`` for an integer, which JSON Schema calls an integer.
    """
    if tp in (float, bool):  # a bool is exactly true or false, never 0 or "yes"
        return Annotated[(tp, Strict(), *metadata)]  # type: ignore[misc]
    if tp is int:
        # bounds before the validator, so the JSON Schema keeps them as minimum/maximum
        return Annotated[(int, *metadata, BeforeValidator(_json_integer))]  # type: ignore[misc]
    return Annotated[(tp, *metadata)] if metadata else tp  # type: ignore[misc]  # Literal: exact strings only


PER_CLASS_FIELDS: tuple[str, ...] = tuple(n for n in CONFIG_FIELDS if n.endswith("_per_class"))
"""Config maps keyed by lowercase class name (every ``*_per_class`` field): the keys are an enum in the OpenAPI
schema, and a merge patch merges them key by key."""


def _alpha_type(info: FieldInfo) -> Any:
    """The value type of a per-class map (Annotated[float, …] in the wire model), JSON-strict."""
    value = info.annotation.__args__[1]  # type: ignore[union-attr]
    return _strict_json(float, list(getattr(value, "__metadata__", ())))


def _build_config_models() -> tuple[type[BaseModel], type[BaseModel]]:
    """Derive the HTTP config models from the wire model so the constraints can never drift apart.

    ``Config`` is the full config (PUT body, GET reply): every field with its default. ``ConfigPatch`` is a
    JSON merge patch (RFC 7386) of it: absent = unchanged, ``null`` = back to the default, and inside
    a per-class map (:data:`PER_CLASS_FIELDS`) a ``null`` value removes that class's entry.
    """
    full: dict[str, Any] = {}
    patch: dict[str, Any] = {}
    for name in CONFIG_FIELDS:
        info = ClassifierConfig.model_fields[name]
        doc = _CONFIG_DOCS[name]
        if name in PER_CLASS_FIELDS:  # class-name keys as an enum, so the OpenAPI schema lists them
            constrained: Any = dict[ClassName, _alpha_type(info)]  # type: ignore[valid-type,misc]
        else:
            constrained = _strict_json(info.annotation, list(info.metadata))
        if info.default_factory is not None:
            spec = Field(default_factory=info.default_factory, description=doc)  # type: ignore[arg-type]
        else:
            spec = Field(default=info.default, description=doc)
        full[name] = (constrained, spec)
        if name in PER_CLASS_FIELDS:
            pann = dict[ClassName, _alpha_type(info) | None] | None  # type: ignore[valid-type,misc]
        else:
            pann = constrained | None
        patch[name] = (pann, Field(default=None, description=doc + "; null resets it to the default"))
    cfg = ConfigDict(extra="forbid", allow_inf_nan=False)
    config_model = create_model("Config", __config__=cfg, **full)  # type: ignore[call-overload]
    config_model.__doc__ = "The motion classifier's tunables (what is in force, or what to put in force)."
    patch_model = create_model("ConfigPatch", __config__=cfg, **patch)  # type: ignore[call-overload]
    patch_model.__doc__ = ("A JSON merge patch of the config: absent fields stay, `null` resets a field to its "
                           "default, a `null` inside a per-class map removes that class's entry.")
    return config_model, patch_model


ConfigModel, ConfigPatchModel = _build_config_models()


class ConfigError(ValueError):
    """A config that the classifier would refuse; ``errors`` is FastAPI's 422 ``detail`` list."""

    def __init__(self, errors: list[dict[str, Any]]) -> None:
        self.errors = jsonable_errors(errors)  # the one place inputs are made safe for a strict-JSON, UTF-8 422
        super().__init__("; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in self.errors))


IF_MATCH_PATTERN = rf'^(\*|"[0-9a-f]{{{ETAG_HEX}}}"|[0-9a-f]{{{ETAG_HEX}}})$'
"""An ``If-Match`` the sidecar takes: ``*``, or one strong etag of ``GET /v1/config``, quoted as RFC 9110 writes it
(bare too: curl users type it so). A weak tag (``W/…``, never equal under If-Match's strong comparison) or a list
of several is refused (422 naming the header); the route's schema carries the same pattern."""


def parse_if_match(value: str | None) -> str | None:
    """The etag an ``If-Match`` header names, or None for none or ``*`` (whatever is in force: unconditional)."""
    if value is None or value == "*":
        return None
    if re.fullmatch(IF_MATCH_PATTERN, value) is None:
        raise ConfigError([{"type": "string_pattern_mismatch", "loc": ["header", "If-Match"], "input": value,
                            "msg": f'must be "*" or one etag of GET /v1/config: {ETAG_HEX} lowercase hex digits '
                                   f'in double quotes'}])
    return value.strip('"')


def config_to_api(cfg: ClassifierConfig) -> dict[str, Any]:
    """The HTTP form of a config: the wire model without its schema version."""
    return cfg.model_dump(mode="json", exclude={"schema_version"})


def _window_field(touched: Iterable[str]) -> str:
    """Which field the window-order error should name: the one the request changed (min_window if both)."""
    touched = set(touched)
    if "window_size" in touched and "min_window" not in touched:
        return "window_size"
    return "min_window"


def validate_config(data: Mapping[str, Any], touched: Iterable[str] | None = None) -> ClassifierConfig:
    """Validate a full config dict with the classifier's own model; raise :class:`ConfigError` naming fields.

    The model's cross-field rules have no field of its own in pydantic's error: ``calibration: file`` without
    a file is attributed to ``calibration_file``, min_window ≤ window_size to the window field the request
    touched; a 422 always names a field.
    """
    try:
        return ClassifierConfig.model_validate(dict(data))
    except ValidationError as exc:
        errors = []
        for err in exc.errors(include_url=False, include_context=False):
            loc = tuple(err.get("loc", ()))
            value = err.get("input")
            if not loc:  # a model-level rule: name the field it is about, echo its value
                name = ("calibration_file" if "calibration_file" in err.get("msg", "")
                        else _window_field(touched if touched is not None else data))
                loc, value = (name,), data.get(name)
            errors.append({"type": err.get("type", "value_error"), "loc": ["body", *loc], "msg": err.get("msg", ""),
                           "input": value})
        raise ConfigError(errors) from None


def _utf8(text: str) -> str:
    """``text`` as UTF-8 can carry it: a lone surrogate (valid in escaped JSON input, not encodable in a UTF-8
    response) is echoed as its ``\\udXXX`` escape."""
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return text.encode("utf-8", "backslashreplace").decode("utf-8")
    return text


def _jsonable(value: Any, depth: int = 0) -> Any:
    """An offending input made safe to echo in strict JSON: non-finite numbers and unknown objects become
    their ``repr``, containers are walked (bounded depth). A 422 must never turn into a 500 because the bad
    value itself cannot be serialised (``NaN`` is valid Python JSON input but not valid JSON output)."""
    if isinstance(value, str):
        return _utf8(value)
    if value is None or isinstance(value, (bool, int)):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else repr(value)
    if depth > 20:
        return "..."
    if isinstance(value, Mapping):
        return {_utf8(str(k)): _jsonable(v, depth + 1) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v, depth + 1) for v in value]
    return repr(value)


def jsonable_errors(errors: Iterable[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Validation errors (pydantic's or ours) as a strict-JSON 422 ``detail`` list."""
    out = []
    for e in errors:
        item: dict[str, Any] = {"type": str(e.get("type", "value_error")), "loc": [
            p if isinstance(p, int) else _utf8(str(p)) for p in e.get("loc", ())], "msg": _utf8(str(e.get("msg", "")))}
        if "input" in e:
            item["input"] = _jsonable(e["input"])
        if e.get("ctx"):
            item["ctx"] = _jsonable(dict(e["ctx"]))
        out.append(item)
    return out


# ----------------------------------------------------------------------------------------- JSON bodies

MAX_JSON_INT_DIGITS = 309
"""Digits an integer literal of a request body may have: as many as the largest float (1.8e308) has. A longer one
is no value any field takes, and Python refuses to turn one of over 4300 digits into an int at all (the body had
come back as a 400 naming nothing)."""


class BodyError(ValueError):
    """A request body that cannot be read as the JSON it claims to be: ``status`` and the ``detail`` to answer with
    (a 422's list of errors naming the field, or a 400's sentence)."""

    def __init__(self, status: int, detail: Any) -> None:
        self.status, self.detail = status, detail
        super().__init__(str(detail))


class _LongInt:
    """Stands in for an integer literal of more than :data:`MAX_JSON_INT_DIGITS` digits until its field is named."""

    __slots__ = ("digits",)

    def __init__(self, digits: str) -> None:
        self.digits = digits


class _Repeated:
    """Stands in for the value of a key an object gives more than once until its field is named."""

    __slots__ = ()


_REPEATED = _Repeated()


def _parse_int(text: str) -> Any:
    return int(text) if len(text) - text.startswith("-") <= MAX_JSON_INT_DIGITS else _LongInt(text)


def _object(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        out[key] = _REPEATED if key in out else value
    return out


def parse_json_body(body: bytes) -> Any:
    """A request body as JSON, read the way the API's 4xx rules need (``json.JSONDecodeError`` for bad syntax,
    which FastAPI answers with its own 422; :class:`BodyError` for the rest):

    - an integer literal longer than :data:`MAX_JSON_INT_DIGITS` digits is a 422 naming its field (Python's own
      parser raises for over 4300 digits, which FastAPI answered with a 400 naming nothing);
    - a key that is no Unicode text (a lone surrogate escape, ``{"\\ud800": 1}``) is a 422 naming it by its escape
      (pydantic had named only ``body``, or shown the key as three U+FFFD inside a per-class map);
    - a key given twice in one object is a 422 naming it: JSON leaves open which one counts (Python keeps the
      last, a proxy or a log reader may see the first), as the wire codec refuses a repeated msgpack key;
    - text that is not UTF-8 and nesting beyond what the parser can recurse into are a 400 saying so (they had
      been "There was an error parsing the body"). UTF-8 only, as RFC 8259 (§8.1) asks of JSON between systems:
      Python's parser also guesses UTF-16 and UTF-32 from the bytes, and had applied such a body while a stray
      byte got "not UTF-8 text".
    """
    try:
        data = json.loads(body.decode("utf-8"), parse_int=_parse_int, object_pairs_hook=_object)
    except UnicodeDecodeError as exc:
        raise BodyError(400, f"the body is not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except RecursionError:
        raise BodyError(400, "the JSON body is nested too deeply to read") from None
    errors = []
    stack: list[tuple[tuple[Any, ...], Any]] = [((), data)]
    while stack:  # iterative: a body as deep as the parser allows must not exhaust the stack here
        loc, value = stack.pop()
        if isinstance(value, _LongInt):
            n = len(value.digits) - value.digits.startswith("-")
            errors.append({"type": "int_too_long", "loc": ["body", *loc],
                           "msg": f"Integer of {n} digits: beyond any number this API takes (at most "
                                  f"{MAX_JSON_INT_DIGITS} digits)", "input": value.digits[:20] + "…"})
        elif value is _REPEATED:
            errors.append({"type": "duplicate_key", "loc": ["body", *loc],
                           "msg": "Key given more than once in one JSON object", "input": None})
        elif isinstance(value, dict):
            for k in value:
                if isinstance(k, str) and _utf8(k) != k:  # a lone surrogate: pydantic had named only ["body"]
                    errors.append({"type": "string_unicode", "loc": ["body", *loc, _utf8(k)],
                                   "msg": "Key is not valid Unicode (a lone surrogate escape)", "input": _utf8(k)})
            stack.extend(((*loc, k), v) for k, v in reversed(value.items()))
        elif isinstance(value, list):
            stack.extend(((*loc, i), v) for i, v in reversed(list(enumerate(value))))
    if errors:
        raise BodyError(422, jsonable_errors(errors))
    return data


def merge_patch(current: ClassifierConfig, patch: Mapping[str, Any]) -> ClassifierConfig:
    """Apply a JSON merge patch (RFC 7386) to ``current`` and validate the result.

    ``patch`` holds only the fields the client sent. ``null`` resets a field to its default; in
    a per-class map (:data:`PER_CLASS_FIELDS`) the patch merges key by key and a ``null`` value drops that
    class's entry.
    """
    unknown = sorted(set(patch) - set(CONFIG_FIELDS))
    if unknown:
        raise ConfigError([{"type": "extra_forbidden", "loc": ["body", unknown[0]],
                            "msg": "Extra inputs are not permitted", "input": patch[unknown[0]]}])
    merged = config_to_api(current)
    defaults = config_to_api(ClassifierConfig())
    for name, value in patch.items():
        if value is None:
            merged[name] = defaults[name]
        elif name in PER_CLASS_FIELDS:
            if not isinstance(value, Mapping):
                merged[name] = value  # let validation name it
                continue
            per_class = dict(merged[name])
            for cls, alpha in value.items():
                if alpha is None:
                    per_class.pop(cls, None)
                else:
                    per_class[cls] = alpha
            merged[name] = per_class
        else:
            merged[name] = value
    return validate_config(merged, touched=patch.keys())


def apply_preset(current: ClassifierConfig, name: str) -> ClassifierConfig:
    """A named preset on top of ``current``: the preset's fields replace, every other field stays."""
    if name not in PRESETS:
        raise KeyError(name)
    return validate_config({**config_to_api(current), **PRESETS[name]}, touched=PRESETS[name].keys())


# ----------------------------------------------------------------------------------------- state → JSON


def track_view(e: Mapping[str, Any], mode: str, snapshot_seq: int) -> dict[str, Any]:
    """One wire track entry (the validated msgpack map of a ``TrackStateEntry``) → the HTTP track dict.

    Works on the map rather than the model: it runs for every track of every new snapshot, and reading a
    dict is the cheapest way to build another one.
    """
    z_x, z_y = e["z_x"], e["z_y"]
    z = z_x if z_x >= z_y else z_y
    size, length = e["window_size"], e["window_length"]
    if mode == "chi2":
        stat = e["chi2"]
    elif mode == "velocity_threshold":
        stat = e["speed"]
    else:
        stat = z
    return {
        "id": e["track_id"], "label": e["label"], "class": LABEL_NAMES.get(e["label"], "unknown"),
        "state": e["state"], "z_x": z_x, "z_y": z_y, "z": z, "chi2": e["chi2"], "statistic": stat,
        "alpha": e["alpha"], "threshold": e["threshold"], "window_length": length, "window_size": size,
        "window_fill": min(1.0, length / size) if size else 0.0, "speed": e["speed"],
        "x": e["x"], "y": e["y"], "yaw": e.get("yaw", 0.0), "length": e.get("length", 0.0),
        "width": e.get("width", 0.0),  # defaulted wire fields: a producer may leave them out
        "last_update_ns": e["last_update_ns"], "last_seq": e["last_seq"],
        "frames_since_update": max(0, snapshot_seq - e["last_seq"]),
    }


_orjson: Any
try:  # optional: ~10x faster on the 500-track body; the stdlib fallback gives the same JSON
    import orjson as _orjson
except ImportError:  # pragma: no cover - depends on the environment
    _orjson = None


def dumps(obj: Any) -> bytes:
    """Compact JSON. Every number here passed the wire model's finite-float check first, so neither
    encoder ever meets a NaN (orjson would write it as null, the stdlib would raise)."""
    if _orjson is not None:
        return _orjson.dumps(obj)
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()


@dataclass(frozen=True)
class RenderedState:
    """One classifier snapshot, rendered once for every reader until the next one arrives."""

    seq: int
    stamp_ns: int
    frame_id: str
    polled_at_ns: int
    config: ClassifierConfig
    counters: dict[str, int]
    tracks: dict[str, dict[str, Any]]  # id -> track dict, in id order
    calibration: dict[str, Any] | None
    counts: dict[str, int]
    by_class_state: dict[tuple[str, str], int]
    body: bytes  # the whole ``GET /v1/state`` response

    def states(self) -> dict[str, str]:
        return {tid: t["state"] for tid, t in self.tracks.items()}


def render_state(snap: ClassifierStateSnapshot, polled_at_ns: int,
                 raw: Mapping[str, Any] | None = None) -> RenderedState:
    """Snapshot → the ``/v1/state`` body, the per-track dicts and the aggregates, computed once.

    ``raw`` is the validated msgpack map of ``snap`` (from ``decode_with_raw``), if the caller has it.
    """
    mode = snap.config.mode
    seq = snap.header.seq
    data = raw or snap.model_dump(mode="python")
    entries = data["tracks"]
    entries = sorted(entries, key=lambda e: e["track_id"])
    tracks = {e["track_id"]: track_view(e, mode, seq) for e in entries}
    by_class_state = aggregate_by_class_state(tracks.values())
    counts = {s: 0 for s in STATES}
    for (_, state), n in by_class_state.items():
        counts[state] += n
    counts["total"] = len(tracks)
    view = {
        "seq": seq, "stamp_ns": snap.header.stamp, "frame_id": snap.header.frame_id, "mode": mode,
        "polled_at_ns": polled_at_ns, "counts": counts, "tracks": list(tracks.values()),
        "calibration": data.get("calibration"),
    }
    return RenderedState(seq=seq, stamp_ns=snap.header.stamp, frame_id=snap.header.frame_id,
                         polled_at_ns=polled_at_ns, config=snap.config,
                         counters=dict(snap.counters), tracks=tracks, calibration=data.get("calibration"),
                         counts=counts,
                         by_class_state=by_class_state, body=dumps(view))


# ----------------------------------------------------------------------------------------- changes (SSE)


def diff_states(prev: RenderedState | None, new: RenderedState) -> list[dict[str, Any]]:
    """State transitions between two snapshots: a track that appeared (``from`` null), vanished (``to``
    null) or changed state. Sorted by track ID so the event stream is deterministic."""
    old = prev.states() if prev is not None else {}
    changes = []
    for tid in sorted(set(old) | set(new.tracks)):
        before, t = old.get(tid), new.tracks.get(tid)
        after = t["state"] if t is not None else None
        if before == after:
            continue
        src = t if t is not None else prev.tracks[tid]  # type: ignore[union-attr]
        changes.append({"id": tid, "class": src["class"], "from": before, "to": after,
                        "statistic": src["statistic"], "threshold": src["threshold"],
                        "x": src["x"], "y": src["y"]})
    return changes


# ----------------------------------------------------------------------------------------- metrics


def aggregate_by_class_state(tracks: Iterable[Mapping[str, Any]]) -> dict[tuple[str, str], int]:
    """Track counts for every (class, state) pair, zeros included so every series always exists."""
    out = {(c, s): 0 for c in CLASS_NAMES for s in STATES}
    for t in tracks:
        key = (t["class"], t["state"])
        out[key] = out.get(key, 0) + 1
    return out


LATENCY_PREFIX = "frame_latency_ms.bucket."
LATENCY_SUM = "frame_latency_ms.sum_us"
LATENCY_COUNT = "frame_latency_ms.count"


@dataclass(frozen=True)
class Histogram:
    """A Prometheus histogram in seconds: cumulative ``(upper bound, count)`` pairs ending at +Inf."""

    buckets: list[tuple[float, int]] = field(default_factory=list)
    sum_s: float = 0.0
    count: int = 0


def latency_histogram(counters: Mapping[str, int]) -> Histogram | None:
    """Rebuild the classifier's frame-latency histogram from its integer counters, if it exports them.

    Counters, per frame one bucket incremented (not cumulative): ``frame_latency_ms.bucket.<le>`` where
    ``<le>`` is the bucket's upper bound in ms (``inf`` for the overflow bucket), ``frame_latency_ms.sum_us``
    (total µs) and ``frame_latency_ms.count``. Integers only, because heartbeat/snapshot counters are ints.
    """
    raw: list[tuple[float, int]] = []
    for name, value in counters.items():
        if name.startswith(LATENCY_PREFIX):
            try:
                le = float(name[len(LATENCY_PREFIX):])
            except ValueError:
                continue
            if math.isnan(le):
                continue
            raw.append((le, int(value)))
    if not raw:
        return None
    raw.sort()
    buckets, total = [], 0
    for le_ms, n in raw:
        total += n
        buckets.append((le_ms / 1e3 if math.isfinite(le_ms) else math.inf, total))
    count = int(counters.get(LATENCY_COUNT, total))
    if buckets[-1][0] != math.inf:
        buckets.append((math.inf, max(count, total)))
    return Histogram(buckets=buckets, sum_s=counters.get(LATENCY_SUM, 0) / 1e6, count=max(count, total))


# ----------------------------------------------------------------------------------------- bind policy


def bind_refusal(host: str, token: str | None) -> str | None:
    """Why the sidecar must not start on ``host`` (None if it may): a non-loopback bind needs a token,
    or anyone on the network could retune the classifier."""
    if token:
        return None
    if is_loopback(host):
        return None
    return (f"refusing to bind {host} without JG_API_TOKEN: the config endpoints would be writable from the "
            f"network; set JG_API_TOKEN or bind 127.0.0.1")
