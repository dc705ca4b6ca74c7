"""The sidecar's one Zenoh session: the classifier seen from outside, over queries and subscriptions only.

:class:`ClassifierClient` is a :class:`~jitterguard.runtime.Service` (so the sidecar has its own liveliness
token and heartbeat like every process), and it

- watches the classifier's liveliness token and heartbeat (readiness: both must hold);
- polls ``classifier/state`` in a background thread and renders each new snapshot to JSON once, so that
  ``GET /v1/state`` is a pointer read however many tracks there are and however many clients ask;
- turns consecutive snapshots into change events (state transitions, config changes, readiness flips) for
  listeners (the SSE broker). Events come from snapshots rather than ``motion/*``: at 500 tracks × 20 Hz
  that subscription is 10 000 Python callbacks a second in this process for no information a viewer at the
  poll rate could see;
- reads and writes the config through the ``classifier/config`` queryable. A write returns only what the
  classifier replied is in force; the classifier swaps its config whole between two frames, so a write is
  applied entirely or not at all.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import zenoh

from ...runtime import Service, ZenohOptions
from ...runtime.service import counter_key
from ...schemas import DecodeError, decode, decode_with_raw, encode, keys
from ...runtime.config_auth import NONCE_BYTES, challenge_attachment, reply_is_authentic, write_attachment
from ...schemas.models import ClassifierConfig, ClassifierStateSnapshot, ConfigReply, Heartbeat
from ...schemas.wire import CONFIG_REPLY_BOUNDS, HEARTBEAT_BOUNDS, STATE_REPLY_BOUNDS
from .core import (PIPELINE_STAGES, PIPELINE_STALL_S, SOURCES, ConfigError, RenderedState, config_to_api, diff_states,
                   frames_standing, is_pipeline, refusal_counts, refusal_warning, refusals_since, render_state,
                   service_problems, silenced)
from .metrics import SidecarMetrics

CLASSIFIER = "classifier"
NO_INPUT_S = 10.0
"""The classifier's frame count standing still this long, while it is alive, is named under ``warnings``."""
REFUSAL_BEATS = 32
"""Heartbeats of a service kept to tell what it refused over the last :data:`NO_INPUT_S` (one a second; more only
from a service that beats faster, which then reaches back less far)."""
MAX_SERVICES = 64
"""Heartbeats kept by service name (the namespace's services; a flood of made-up names cannot grow this)."""
MAX_TOKENS = 4 * MAX_SERVICES
"""Liveliness tokens kept by name: the pipeline's stages and sources always, others while fewer are held (a flood of
made-up tokens had grown this set, and every readiness check's copy of it, without bound)."""
Listener = Callable[[str, dict[str, Any]], None]
PAUSE_MARGIN_S = 1.0
"""How much longer than a poll turn (its period plus a state query's timeout) the gap between two turns must be to
count as this process's own pause."""


def own_pause(last_top: float, top: float, turn_s: float) -> float:
    """Seconds this process stood still between two turns of a loop that takes at most ``turn_s`` (0 if none): far
    longer than a turn, it was stopped (SIGSTOP, a debugger, a host that slept), not slow."""
    gap = top - last_top - turn_s
    return gap if gap > PAUSE_MARGIN_S else 0.0


class ClassifierUnavailable(RuntimeError):
    """The classifier cannot be reached or did not confirm in time (HTTP 503)."""


class ClassifierRejected(RuntimeError):
    """The classifier answered with an error reply (HTTP 502: the sidecar validated, the classifier refused)."""


class ConfigConflict(RuntimeError):
    """A conditional write found another config in force, nothing applied (HTTP 412: the client named the version
    it read with ``If-Match``). ``etag``: the version in force now, when known."""

    def __init__(self, message: str, etag: str | None) -> None:
        super().__init__(message)
        self.etag = etag


class ConfigContended(ConfigConflict):
    """The sidecar's read-modify-write lost to other writers :data:`WRITE_ATTEMPTS` times in a row (HTTP 409)."""


WRITE_ATTEMPTS = 5
"""Tries of one read-modify-write (a PATCH, a preset) whose conditional put loses to another writer each time."""

ZENOH_TIMEOUT = b"Timeout"
"""The payload of the error reply Zenoh makes up when a get times out."""


class ClassifierClient(Service):
    """Owns the sidecar's Zenoh session and everything it knows about the classifier."""

    name = "sidecar"

    def __init__(self, opts: ZenohOptions, *, poll_period_s: float = 0.05, query_timeout_s: float = 3.0,
                 state_timeout_s: float = 1.0, stale_after_s: float = 3.0,
                 metrics: SidecarMetrics | None = None, api_token: str | None = None,
                 stop_event: threading.Event | None = None, pipeline_stall_s: float = PIPELINE_STALL_S) -> None:
        """``api_token``: the key that signs every config write and checks every reply of the classifier's
        (:mod:`~jitterguard.runtime.config_auth`; the classifier holds the same ``JG_API_TOKEN``, and the token
        itself is never sent). ``stop_event``: ends the wait for the router (:class:`Service`).
        ``pipeline_stall_s``: frames entering this long with none classified is a readiness fault
        (:func:`~.core.frames_standing`)."""
        super().__init__(opts, stop_event=stop_event)
        self._api_token = api_token
        self.poll_period_s = poll_period_s
        self.query_timeout_s = query_timeout_s
        self.state_timeout_s = state_timeout_s
        self.stale_after_s = stale_after_s
        self.pipeline_stall_s = pipeline_stall_s
        self.metrics = metrics or SidecarMetrics()
        self._lock = threading.Lock()
        self._write_lock = threading.Lock()
        self._on_bus: set[str] = set()  # every service whose liveliness token is present (the classifier's: alive)
        self._left: set[str] = set()  # pipeline stages, or services heard, whose token went and has not come back
        self._sources_left: dict[str, float] = {}  # a source whose token was withdrawn: since when (monotonic)
        self._frames_at: tuple[int, float] | None = None  # the classifier's last_seq and when it was first seen
        self._sources_moved: dict[str, tuple[int, float]] = {}  # a source's last_seq and when it last changed
        self._hb: Heartbeat | None = None
        self._hb_at: float | None = None  # monotonic receive time of the last classifier heartbeat
        self._beats: dict[str, tuple[Heartbeat, float]] = {}  # every service's latest heartbeat, receive time
        # per service in _beats: its refusal counters over the last NO_INPUT_S, (receive time, counts), bounded
        self._refused: dict[str, deque[tuple[float, dict[str, int]]]] = {}
        self._rendered: RenderedState | None = None
        self._last_payload: bytes | None = None
        self._poll_refusal: str | None = None  # why the last state poll's replies were all refused (unsigned)
        self._answered_at: float | None = None  # monotonic time of the last state poll the classifier answered
        self._listeners: list[Listener] = []
        self._last_config_event: dict[str, Any] | None = None
        self._alive_key = keys.alive(self.ns, CLASSIFIER)
        self._declared.append(self.session.liveliness().declare_subscriber(
            keys.alive_all(self.ns), self._on_liveliness, history=True))
        self.subscribe(keys.heartbeat_all(self.ns), Heartbeat, self._on_heartbeat, **HEARTBEAT_BOUNDS)
        self.metrics.attach(self)
        self.spawn(self._poll_loop, "poll")

    # ------------------------------------------------------------------ liveliness, heartbeat, readiness

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        name, alive = keys.last_chunk(str(sample.key_expr)), sample.kind == zenoh.SampleKind.PUT
        with self._lock:
            if not alive:
                self._on_bus.discard(name)
            elif len(self._on_bus) < MAX_TOKENS or name == CLASSIFIER or name in PIPELINE_STAGES or name in SOURCES:
                self._on_bus.add(name)
            else:
                self.counters.inc("liveliness_tokens_ignored")
            if alive:
                self._left.discard(name)
            elif name in PIPELINE_STAGES or name in self._beats:  # names a withdrawal counts for: the set stays bounded
                self._left.add(name)
            if name in SOURCES:
                if alive:
                    self._sources_left.pop(name, None)
                else:
                    self._sources_left.setdefault(name, time.monotonic())
            if name == CLASSIFIER and not alive:
                self._hb_at = None  # a new instance must prove itself with a fresh heartbeat

    def _on_heartbeat(self, hb: Heartbeat, key: str) -> None:
        name, now = keys.last_chunk(key), time.monotonic()
        with self._lock:
            if name not in self._beats and len(self._beats) >= MAX_SERVICES:
                victim = self._evictable(name)
                if victim is None:  # every slot holds a service on the bus: the newcomer waits for a free one
                    self.counters.inc("heartbeats_dropped")
                    return
                del self._beats[victim]
                self._refused.pop(victim, None)
                if victim not in PIPELINE_STAGES:
                    self._left.discard(victim)
            self._beats[name] = (hb, now)
            refused = self._refused.setdefault(name, deque(maxlen=REFUSAL_BEATS))
            while len(refused) > 1 and now - refused[1][0] >= NO_INPUT_S:  # one at least NO_INPUT_S old is the base
                refused.popleft()
            refused.append((now, refusal_counts(hb.counters)))
            if name == CLASSIFIER:
                self._hb, self._hb_at = hb, now
                if self._frames_at is None or self._frames_at[0] != hb.last_seq:
                    self._frames_at = (hb.last_seq, now)
            elif name in SOURCES and hb.last_seq >= 0:  # a fixed set of names: bounded
                moved = self._sources_moved.get(name)
                if moved is None or moved[0] != hb.last_seq:  # the first one heard says nothing of moving yet
                    self._sources_moved[name] = (hb.last_seq, now if moved is not None else -math.inf)

    def _evictable(self, newcomer: str) -> str | None:
        """Which heartbeat makes room for ``newcomer``'s once :data:`MAX_SERVICES` are kept (under ``_lock``): the
        oldest of a service whose liveliness token is gone; else, for the classifier or a pipeline stage, the oldest
        of any service but those; else none.

        It had been the oldest of all: a flood of made-up service names then pushed out a frozen tracker's last
        heartbeat (token still present), and ``/readyz`` went from 503 "tracker: no heartbeat ... (frozen?)" to 200.
        A name on the bus keeps its slot; a made-up one (no token) only ever displaces another."""
        def oldest(names: list[str]) -> str | None:
            return min(names, key=lambda n: self._beats[n][1]) if names else None

        gone = oldest([n for n in self._beats if n not in self._on_bus])
        if gone is not None or newcomer not in PIPELINE_STAGES | {CLASSIFIER}:
            return gone
        return oldest([n for n in self._beats if n not in PIPELINE_STAGES | {CLASSIFIER}])

    def reject(self, exc: DecodeError, sub_key: str, sample_key: str | None = None) -> None:
        """As every service counts a payload it refuses (its heartbeat's ``rejected.<key>``), and in ``/metrics``
        too (``jitterguard_sidecar_rejected_messages{key}``): a malformed heartbeat had been counted only in the
        sidecar's own heartbeat, and ``/metrics`` showed no rejected message at all."""
        super().reject(exc, sub_key, sample_key)
        self.metrics.rejected.labels(counter_key(sub_key)).inc()

    def readiness(self, refusals: bool = False) -> dict[str, Any]:
        """Whether the classifier is usable now and the pipeline makes progress, and why not (``/readyz``).
        ``refusals``: also warn of each service that refused messages in the last 10 s — worked out only for the
        ``/readyz`` body, not for the 20 readiness checks a second of the state poll and ``X-Classifier-Ready``."""
        now = time.monotonic()
        with self._lock:
            alive, hb, hb_at = CLASSIFIER in self._on_bus, self._hb, self._hb_at
            services = {name: {"health": b.health, "reason": b.health_reason,
                               "heartbeat_age_s": round(now - at, 3), "last_seq": b.last_seq}
                        for name, (b, at) in self._beats.items()}
            on_bus, left = set(self._on_bus), set(self._left)
            sources_left, frames_at, moved = dict(self._sources_left), self._frames_at, dict(self._sources_moved)
            refused = {name: list(h) for name, h in self._refused.items()} if refusals else {}
        age = now - hb_at if hb_at is not None else None
        found = service_problems(services, self.stale_after_s, on_bus, left)
        services = silenced(services, self.stale_after_s, found)
        problems = [msg for name, msg in found if is_pipeline(name)]
        classifier_up = self._up(alive, hb_at, now)
        moved = {name: m for name, m in moved.items()  # a source heard now: one that left feeds nothing
                 if name in services and services[name]["heartbeat_age_s"] <= self.stale_after_s}
        standing = (frames_standing(frames_at, moved, now, warn_s=NO_INPUT_S, fault_s=self.pipeline_stall_s,
                                    recent_s=NO_INPUT_S) if classifier_up else None)
        if standing is not None and standing[1]:
            problems.append(standing[0])
        if not alive:
            reason = f"no classifier: liveliness token {self._alive_key} is absent"
        elif age is None:
            reason = f"no heartbeat yet on {keys.heartbeat(self.ns, CLASSIFIER)}"
        elif age > self.stale_after_s:
            reason = f"classifier heartbeat is {age:.1f} s old (stale after {self.stale_after_s:g} s)"
        elif self._poll_refusal is not None:  # answering, but not to this sidecar's token: its state cannot be read
            reason = f"the classifier's state cannot be read: {self._poll_refusal}"
        elif problems:
            reason = "; ".join(problems)
        else:
            reason = "ok"
        st = self._rendered
        return {"ready": reason == "ok", "reason": reason, "liveliness": alive,
                "heartbeat_age_s": round(age, 3) if age is not None else None,
                "last_seq": hb.last_seq if hb is not None and hb_at is not None else None,
                "state_seq": st.seq if st is not None else None, "services": services,
                "warnings": [msg for name, msg in found if not is_pipeline(name)] + self._input_warnings(
                    now, services, sources_left, standing, refused)}

    def _input_warnings(self, now: float, services: dict[str, dict[str, Any]], sources_left: dict[str, float],
                        standing: tuple[str, bool] | None,
                        refused: dict[str, list[tuple[float, dict[str, int]]]]) -> list[str]:
        """What keeps objects from coming without being a readiness fault (DESIGN: no input at all is not a fault,
        a sensor may be off): a source that left the bus, the classifier's frames standing still, and each service
        (of ``refused``) that refused messages in the last 10 s. Readiness stays as it was; these only say why a
        ready sidecar serves no new objects, or fewer. A looping replay that supervisord had given up on (FATAL) had
        left ``/readyz`` at 200 "ok" with nothing to say it; a ROS 2 bridge fed only scans that break their contract
        (each refused, counted ``invalid``; ``ok``, as a restart cannot mend them) had left a warning of "no input"
        alone; and one that refused part of what it was sent while frames flowed had shown only in its counters."""
        out = []
        for name, since in sorted(sources_left.items()):
            beat = services.get(name)
            if beat is not None and beat["heartbeat_age_s"] <= self.stale_after_s:
                continue  # its token went, its heartbeats did not: a new process of it is taking over
            out.append(f"{name} left the bus {now - since:.0f} s ago (liveliness token withdrawn, no heartbeat since):"
                       " no frames enter the pipeline; its recording ended, or it failed and was not restarted")
        if standing is not None and not standing[1]:  # the classifier's frames standing still (a fault: in reason)
            out.append(standing[0])
        for name, history in sorted(refused.items()):
            rose = refusals_since(history, now, NO_INPUT_S)
            if rose:
                out.append(refusal_warning(name, rose, NO_INPUT_S))
        return out

    def readiness_flag(self) -> bool:
        return bool(self.readiness()["ready"])

    def classifier_up(self) -> bool:
        """The classifier's liveliness token is present and its heartbeat recent: the classifier itself, what
        ``jitterguard_classifier_up`` says. Not :meth:`readiness_flag`, which also fails for a fault of another
        stage: a frozen tracker had set ``jitterguard_classifier_up`` to 0 beside a classifier that was on the bus,
        heartbeating and healthy (``jitterguard_service_healthy{service="classifier"}`` 1), pointing an alert at the
        wrong process."""
        now = time.monotonic()
        with self._lock:
            return self._up(CLASSIFIER in self._on_bus, self._hb_at, now)

    def _up(self, alive: bool, hb_at: float | None, now: float) -> bool:
        """The classifier is up: its token present and its heartbeat no older than ``stale_after_s`` (what
        :meth:`classifier_up` reports and :meth:`readiness` judges the pipeline's progress under)."""
        return alive and hb_at is not None and now - hb_at <= self.stale_after_s

    def service_beats(self) -> list[tuple[str, Heartbeat, float, bool]]:
        """Every service heard: (name, its latest heartbeat, seconds since it came, liveliness token present), by
        name — what ``/metrics`` exports per service."""
        now = time.monotonic()
        with self._lock:
            return [(name, hb, now - at, name in self._on_bus) for name, (hb, at) in sorted(self._beats.items())]

    def is_alive(self) -> bool:
        with self._lock:
            return CLASSIFIER in self._on_bus

    # ------------------------------------------------------------------ state cache

    def rendered_state(self) -> RenderedState | None:
        """The latest rendered snapshot (an immutable object; replaced, never mutated)."""
        return self._rendered

    def served_state(self) -> RenderedState | None:
        """The latest snapshot while it is still what the classifier says: the classifier up (on the bus, its
        heartbeat recent), its latest poll answered, and a poll answered no more than ``stale_after_s`` ago;
        None otherwise. What ``/metrics`` exports its track gauges and counters from: a snapshot kept after the
        classifier left or began refusing this sidecar's polls (another ``JG_API_TOKEN``) had gone on being scraped
        as the current count of moving tracks, with nothing in it to say it was old — and so had one of a
        classifier stopped (SIGSTOP: its token stays until the router drops it), ``jitterguard_classifier_up`` 0
        beside a frame count standing still, or of the process before a restart until the new one answered."""
        st, answered_at = self._rendered, self._answered_at
        if st is None or answered_at is None or not self.classifier_up() or self._poll_refusal is not None:
            return None
        return st if time.monotonic() - answered_at <= self.stale_after_s else None

    def poll_refusal(self) -> str | None:
        """Why the last state poll took no reply although the classifier answered (no reply signed with this
        sidecar's token: the tokens differ), or None. A state read with no state yet names it (502) instead of
        "no state yet" (503), which had sent the operator to wait for a classifier that was there all along."""
        return self._poll_refusal

    def add_listener(self, fn: Listener) -> None:
        """``fn(kind, data)`` for every change event; called on the poll or request thread, keep it short."""
        self._listeners.append(fn)

    def _emit(self, kind: str, data: dict[str, Any]) -> None:
        if kind == "config":  # a write reports it, then the next snapshot carries it: say it once
            with self._lock:
                if data == self._last_config_event:
                    return
                self._last_config_event = data
        for fn in list(self._listeners):
            try:
                fn(kind, data)
            except Exception:
                self.log.exception("event listener failed")

    def _poll_loop(self) -> None:
        next_t = last_top = time.monotonic()
        was_ready: bool | None = None
        while not self.stop_event.is_set():
            top = time.monotonic()
            paused = own_pause(last_top, top, self.poll_period_s + self.state_timeout_s)
            if paused > 0:
                self._shift_clocks(paused, top)
            last_top = top
            ready = self.readiness()
            if ready["ready"] != was_ready:
                was_ready = ready["ready"]
                self._emit("ready", {"ready": ready["ready"], "reason": ready["reason"]})
            if self.is_alive():
                try:
                    self.poll_once()
                except Exception:  # never let the cache thread die
                    if self.stop_event.is_set():
                        return
                    self.log.exception("state poll failed")
            next_t += self.poll_period_s
            delay = next_t - time.monotonic()
            if delay < 0:  # fell behind (a slow reply): start afresh rather than burst
                next_t, delay = time.monotonic(), 0.0
            self.stop_event.wait(delay)

    def _shift_clocks(self, by: float, now: float) -> None:
        """Move every time this client judges ages by ``by`` seconds later (never past ``now``): this process was
        paused that long, and the heartbeats, frames and polls it could not take meanwhile are not the others'
        silence. After an 8 s SIGSTOP of the sidecar alone, its event streams had said ``ready: false`` —
        "classifier heartbeat is 8.1 s old" — blaming the classifier (the stack's monitor does the same for its own
        pauses). A time taken after the pause (a heartbeat heard on resume) stays at most ``now``."""
        def later(t: float) -> float:
            return max(t, min(t + by, now))

        with self._lock:
            if self._hb_at is not None:
                self._hb_at = later(self._hb_at)
            if self._answered_at is not None:
                self._answered_at = later(self._answered_at)
            if self._frames_at is not None:
                self._frames_at = (self._frames_at[0], later(self._frames_at[1]))
            self._beats = {n: (hb, later(at)) for n, (hb, at) in self._beats.items()}
            self._sources_left = {n: later(t) for n, t in self._sources_left.items()}
            self._sources_moved = {n: (seq, later(t)) for n, (seq, t) in self._sources_moved.items()}
            for history in self._refused.values():
                shifted = [(later(t), counts) for t, counts in history]
                history.clear()
                history.extend(shifted)

    def poll_once(self) -> RenderedState | None:
        """Fetch ``classifier/state`` once; render and publish it if it changed. Returns what is cached."""
        t0 = time.perf_counter()
        try:
            kind, data = self._query(keys.classifier_state(self.ns), None, self.state_timeout_s)
        except ClassifierUnavailable:
            self.metrics.poll_failures.inc()
            return self._rendered
        except ClassifierRejected as exc:  # no reply signed with the token (counted rejected.classifier/state)
            self.metrics.poll_failures.inc()
            self._poll_refusal = str(exc)
            return self._rendered
        self._poll_refusal = None
        self.metrics.poll_seconds.observe(time.perf_counter() - t0)
        if kind != "ok":
            self.metrics.poll_failures.inc()
            return self._rendered
        self._answered_at = time.monotonic()  # the cached state is the classifier's now, changed or not
        if data == self._last_payload:
            return self._rendered
        try:
            snap, raw = decode_with_raw(ClassifierStateSnapshot, data, **STATE_REPLY_BOUNDS)
        except DecodeError as exc:
            self._reject("classifier/state", exc)
            return self._rendered
        prev = self._rendered
        new = render_state(snap, time.time_ns(), raw)
        self._last_payload = data
        self._rendered = new
        if prev is None or new.seq != prev.seq or new.tracks.keys() != prev.tracks.keys():
            changes = diff_states(prev, new)
            if changes:
                self._emit("changes", {"seq": new.seq, "stamp_ns": new.stamp_ns, "changes": changes})
        if prev is None:
            with self._lock:
                self._last_config_event = config_to_api(new.config)
        elif prev.config != new.config:
            self._emit("config", config_to_api(new.config))
        return new

    def _reject(self, key: str, exc: Exception) -> None:
        self.counters.inc("rejected")
        self.counters.inc(f"rejected.{key}")
        self.metrics.rejected.labels(key).inc()
        self._reject_log.warn(f"rejected payload on {key}: {exc}", kind=f"rejected {key}")

    # ------------------------------------------------------------------ config

    def _query(self, key: str, payload: bytes | None, timeout: float,
               if_match: str | None = None) -> tuple[str, bytes]:
        """One get on ``key`` (a write when ``payload`` is given, conditional on ``if_match``); ``("ok"|"err",
        payload)`` of the reply taken, or :class:`ClassifierUnavailable`.

        Every queryable on the key is asked. Without a token: the first reply, as it comes. With one: the query
        is signed (a write) or carries a challenge (a read), and the first success reply signed back with the
        token is taken for the classifier's; any other success reply is counted ``rejected.{key}`` and skipped.
        Zenoh's error replies cannot be signed: one is taken only when no signed success came by the end of the
        query (all repliers done, or ``timeout``)."""
        selector = key if if_match is None else f"{key}?{keys.IF_MATCH}={if_match}"
        nonce = attachment = None
        if self._api_token:
            nonce = os.urandom(NONCE_BYTES)
            attachment = challenge_attachment(nonce) if payload is None else \
                write_attachment(self._api_token, key, if_match, payload, time.time_ns(), nonce)
        try:  # every queryable on the key, each reply as it comes: a node that declared a "complete" queryable on
            # jg/** had been the only one asked (the default target), and the first reply was taken whoever sent it
            replies = self.session.get(selector, payload=payload, timeout=timeout, attachment=attachment,
                                       target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE)
        except Exception as exc:  # session closing, or a zenoh error
            raise ClassifierUnavailable(f"query on {key} failed: {exc}") from None
        refusal, unsigned = None, 0
        for reply in replies:
            if reply.ok is not None:
                data = reply.ok.payload.to_bytes()
                if nonce is None:
                    return "ok", data
                signed = reply.ok.attachment
                if reply_is_authentic(self._api_token or "", key, nonce, data,
                                      signed.to_bytes() if signed is not None else None):
                    return "ok", data
                unsigned += 1
                continue
            if reply.err is not None and refusal is None:
                data = reply.err.payload.to_bytes()
                # Zenoh's own "Timeout" (from no replier, or from a node on the way) is not a refusal: the write may
                # still be applied. The classifier's refusals are ConfigReply maps, never these bare bytes.
                if reply.replier_id is not None and data != ZENOH_TIMEOUT:
                    if nonce is None:
                        return "err", data
                    refusal = data
        if unsigned:
            self._reject(f"classifier/{keys.last_chunk(key)}",
                         ValueError(f"{unsigned} reply(ies) not signed with the sidecar's JG_API_TOKEN"))
        if refusal is not None:
            return "err", refusal
        if unsigned:
            raise ClassifierRejected(
                f"no reply on {key} was signed with the sidecar's JG_API_TOKEN ({unsigned} unsigned or wrongly "
                f"signed): the classifier's JG_API_TOKEN differs from the sidecar's, or another node answers "
                f"on this key")
        raise ClassifierUnavailable(f"no reply on {key} within {timeout:g} s")

    def _require_alive(self, action: str) -> None:
        if not self.is_alive():
            raise ClassifierUnavailable(
                f"classifier unreachable (liveliness token {self._alive_key} is absent); {action}")

    def _config_reply(self, kind: str, data: bytes, key: str, sent: ClassifierConfig | None = None) -> ConfigReply:
        try:
            reply = decode(ConfigReply, data, **CONFIG_REPLY_BOUNDS)
        except DecodeError as exc:
            self._reject("classifier/config", exc)
            if kind == "ok":
                raise ClassifierRejected(f"the classifier's reply on {key} is invalid: {exc}") from None
            raise ClassifierRejected(f"the classifier refused: {data[:200].decode(errors='replace')}") from None
        if kind != "ok" or not reply.ok:
            if reply.conflict:
                raise ConfigConflict(reply.error or "the config changed since it was read", reply.etag)
            if (reply.error or "").startswith("not applied"):
                raise ClassifierUnavailable(f"the classifier did not apply the write: {reply.error}")
            field, sep, why = (reply.error or "").partition(": ")
            if sep and sent is not None and field in ClassifierConfig.model_fields:
                # a field only the classifier can check (calibration_file: a path on its host): the client's
                # input, so a 422 naming it
                raise ConfigError([{"type": "value_error", "loc": ["body", field], "msg": why,
                                    "input": getattr(sent, field)}])
            raise ClassifierRejected(f"the classifier refused the config: {reply.error}")
        return reply

    def get_config(self, action: str = "cannot read the config") -> ConfigReply:
        """The config the classifier has in force now (asked, not cached), with its etag."""
        self._require_alive(action)
        key = keys.classifier_config(self.ns)
        try:
            kind, data = self._query(key, None, self.query_timeout_s)
        except ClassifierUnavailable as exc:
            raise ClassifierUnavailable(f"classifier unreachable: {exc}; {action}") from None
        return self._config_reply(kind, data, key)

    def put_config(self, cfg: ClassifierConfig, if_match: str | None = None) -> ConfigReply:
        """Put ``cfg`` in force; returns what the classifier says is in force after applying it. With
        ``if_match`` (an etag) the classifier applies it only while that config is in force
        (:class:`ConfigConflict` otherwise)."""
        self._require_alive("nothing was applied")
        key = keys.classifier_config(self.ns)
        try:
            kind, data = self._query(key, encode(cfg), self.query_timeout_s, if_match)
        except ClassifierUnavailable as exc:
            raise ClassifierUnavailable(
                f"the classifier did not confirm the write ({exc}); a config is applied whole or not at all — "
                f"GET /v1/config shows what is in force") from None
        reply = self._config_reply(kind, data, key, cfg)
        self._emit("config", config_to_api(reply.config))
        return reply

    def update_config(self, change: Callable[[ClassifierConfig], ClassifierConfig],
                      if_match: str | None = None) -> ConfigReply:
        """Read, change, and put back only if no other write came in between (a conditional put on the etag
        read), so a write over Zenoh or from another sidecar is never overwritten unseen: on a conflict the
        change is redone on the new config, up to :data:`WRITE_ATTEMPTS` times. With ``if_match`` the client
        named the version its change is meant for: a different one is a :class:`ConfigConflict` at once.

        ``change`` may raise (e.g. a validation error): then nothing is sent to the classifier.
        """
        with self._write_lock:  # this sidecar's own writes queue here rather than race each other
            for _ in range(WRITE_ATTEMPTS):
                current = self.get_config("nothing was applied")
                if if_match is not None and current.etag != if_match:
                    raise ConfigConflict(f"the config in force is {current.etag}, not {if_match} (If-Match); "
                                         f"nothing applied", current.etag)
                try:
                    return self.put_config(change(current.config), if_match=current.etag)
                except ConfigConflict:
                    if if_match is not None:
                        raise
            raise ConfigContended(f"another writer changed the config between each of {WRITE_ATTEMPTS} reads and "
                                  f"writes; nothing applied — try again", None)

    def replace_config(self, cfg: ClassifierConfig, if_match: str | None = None) -> ConfigReply:
        """Put a whole config in force (PUT), serialised with the read-modify-writes; conditional on
        ``if_match`` when given."""
        with self._write_lock:
            return self.put_config(cfg, if_match=if_match)
