"""The runtime every service stands on: a Zenoh session, liveliness, heartbeat, counters, clean shutdown.

Health means progress (:mod:`.progress`): a service with an input → output relation calls
:meth:`Service.monitor_progress` and reports inputs, outputs and failures; its heartbeat carries the verdict,
and under :meth:`Service.run_forever` (the CLI processes) a service that stays failing or stalled for
``JG_WATCHDOG_S`` seconds (default 10; 0 turns the watchdog off) exits with status 70 for supervisord or
systemd to restart it. A process hung so hard that its heartbeat thread cannot run (a deadlock, a C call that
never returns) is caught by :mod:`faulthandler`'s timer thread, which needs no GIL: it dumps every thread's
stack to stderr and exits with status 1.

A service subclass declares its subscriptions with :meth:`Service.subscribe`, which decodes and validates
every payload on Zenoh's callback thread and hands only valid models to the handler; anything malformed is
rejected, counted (``rejected`` and ``rejected.<key>``) and logged once per burst, and the service keeps
running. Handlers must be short (decode, enqueue): Zenoh runs each subscriber's callbacks on its own thread
behind a bounded FIFO, so a slow handler stalls the receive path.
"""

from __future__ import annotations

import faulthandler
import functools
import logging
import os
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

import zenoh
from pydantic import BaseModel

from ..schemas import DecodeError, LimitExceeded, decode, encode, keys
from ..schemas.models import Heartbeat
from . import memtrace
from .envvars import HANG_GRACE_S, watchdog_period  # there, not here: the stack's Zenoh-free monitor-watch reads it too
from .exit_codes import EXIT_BAD_INPUT, EXIT_NO_PROGRESS  # noqa: F401  (EXIT_BAD_INPUT re-exported; there for the stack)
from .ingest_queue import IngestQueue
from .keyed_publishers import KeyedPublishers
from .progress import STALLED, Health, ProgressMonitor, ProgressPolicy
from .sd_notify import Notifier
from .signals import stop_on_signals
from .zenoh_config import UnusableConfig, ZenohOptions, build_config, open_session

M = TypeVar("M", bound=BaseModel)
log = logging.getLogger("jitterguard")

HEARTBEAT_PERIOD_S = 1.0
REJECT_LOG_QUIET_S = 5.0
REJECT_LOG_SUMMARY_S = 60.0
"""While a burst of one kind goes on, one line at least this often (with how many were not logged)."""
MAX_LOG_KINDS = 64
SHUTDOWN_LIMIT_S = 20.0
"""A watched service's shutdown taking longer than this is hung: faulthandler dumps the stacks and exits."""
DRAIN_S = 0.2
"""How long a closing service leaves its last puts to leave its session (``Service._drain``): two 64 KB batches
take ~0.1 s at 10 Mbit/s."""
QUEUE_BYTES = 64 << 20
"""The bytes a subscription's queue holds at most by default (:meth:`Service.subscribe_queue`): 8 of the largest
payload a service lets in by default (``max_payload_bytes``, 8 MiB), 40,000 of a ~1.5 kB observation."""


class Counters:
    """Thread-safe named counters (received / rejected / published / anything a service adds)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._values: dict[str, int] = {}

    def inc(self, name: str, n: int = 1) -> None:
        with self._lock:
            self._values[name] = self._values.get(name, 0) + n

    def set(self, name: str, value: int) -> None:
        with self._lock:
            self._values[name] = value

    def get(self, name: str) -> int:
        with self._lock:
            return self._values.get(name, 0)

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            return dict(self._values)


class _BurstLogger:
    """Log the first of a burst of similar events, then stay quiet until the burst has passed — per kind of event,
    and at least one line every :data:`REJECT_LOG_SUMMARY_S` while a burst goes on. One quiet period for every
    event of a service, restarted by each one, had let a trickle of junk payloads (one a second) keep an
    unauthorised config write, of another kind, out of the log altogether."""

    def __init__(self, logger: logging.Logger, quiet_s: float = REJECT_LOG_QUIET_S,
                 summary_s: float = REJECT_LOG_SUMMARY_S) -> None:
        self._log = logger
        self._quiet = quiet_s
        self._summary = summary_s
        self._lock = threading.Lock()
        self._kinds: dict[str, list[float]] = {}  # kind -> [last event, last logged, suppressed since]

    def warn(self, msg: str, kind: str = "") -> None:
        now = time.monotonic()
        with self._lock:
            state = self._kinds.get(kind)
            if state is None:
                if len(self._kinds) >= MAX_LOG_KINDS:  # bounded: the kind seen longest ago makes room
                    del self._kinds[min(self._kinds, key=lambda k: self._kinds[k][0])]
                state = self._kinds[kind] = [-1e18, -1e18, 0]
            if now - state[0] < self._quiet and now - state[1] < self._summary:
                state[0], state[2] = now, state[2] + 1
                return
            suppressed = int(state[2])
            state[0], state[1], state[2] = now, now, 0
        extra = f" ({suppressed} similar since the last message)" if suppressed else ""
        self._log.warning("%s%s", one_line(msg), extra)


def one_line(text: str) -> str:
    """``text`` with every character that is not printable (newline, CR, escape sequences, NUL) written as its
    Python escape. Why: what these messages quote comes from the wire — Zenoh keys may hold a newline, and an error
    names a payload's unknown field — and verbatim a put on ``tracks/x\\n<date> ERROR ...`` forged a line in the
    service's log."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in text)


class Service:
    """Base class of every jitterguard process: owns one Zenoh session and its lifecycle."""

    name = "service"

    def __init_subclass__(cls, **kwargs: Any) -> None:
        """A subclass's constructor that fails after the session opened (a key Zenoh refuses, a second session that
        cannot open) undeclares what it declared and closes its sessions before the error goes on: Zenoh runs each
        Python callback on a thread the interpreter waits for at exit, and ``ros2-in`` given a topic Zenoh refused
        had printed its traceback and then never exited — under supervisord a program RUNNING that does nothing."""
        super().__init_subclass__(**kwargs)
        init = cls.__dict__.get("__init__")
        if init is None:
            return

        @functools.wraps(init)
        def init_or_close(self: "Service", *args: Any, **kw: Any) -> None:
            try:
                init(self, *args, **kw)
            except BaseException:
                self._close_opened()
                raise

        cls.__init__ = init_or_close  # type: ignore[method-assign]

    def _close_opened(self) -> None:
        """Undeclare everything and close the sessions of a service whose construction failed (once; nothing waited
        for: its workers are daemon threads)."""
        if "session" not in self.__dict__ or self.__dict__.get("_closed_opened"):
            return
        self._closed_opened = True
        self.stop_event.set()
        self._release_session()
        self._notifier.close()

    def _release_session(self) -> None:
        """Undeclare everything declared (newest first), then the heartbeat publisher, and close the session: the
        end of :meth:`close`, and all of a failed construction's (:meth:`_close_opened`)."""
        for entity in reversed(self._declared):
            try:
                entity.undeclare()
            except Exception:
                pass
        self._declared.clear()
        try:
            self._hb_pub.undeclare()
        except Exception:  # also: a construction that failed before declaring it
            pass
        try:
            self.session.close()
        except Exception:
            pass

    def __init__(self, opts: ZenohOptions, *, stop_event: threading.Event | None = None) -> None:
        """Opens the session, waiting for the router while it is not up; ``stop_event`` (default: a new one)
        ends that wait — set by whoever handles the process's signals before the service runs (the sidecar's
        server) — and then the service's life."""
        self.opts = opts
        self.ns = opts.ns
        self.log = logging.getLogger(f"jitterguard.{self.name}")
        self.counters = Counters()
        self.stop_event = stop_event or threading.Event()
        self.started_at = time.monotonic()
        self.last_seq = -1
        self.progress: ProgressMonitor | None = None
        self.starting: str | None = None
        """What a service still sets up after its session opened (its heartbeat and token are already out): while
        set, its health is ``stalled`` with the reason ``starting: …``, so ``/readyz`` does not call the pipeline
        ready while this service would drop what reaches it."""
        self.exit_code = 0
        self._watchdog_s: float | None = None  # armed by run_forever
        try:  # read before the session opens: a bad value must not wait for a router to be refused
            self._watchdog_env = watchdog_period()
        except ValueError as exc:
            self.log.error("%s", exc)
            raise SystemExit(2) from None
        self._reject_log = _BurstLogger(self.log)
        self._declared: list[Any] = []
        self._threads: list[threading.Thread] = []
        # systemd's watchdog (WatchdogSec= in the units): pinged while the router is awaited, then by the heartbeat
        self._notifier = Notifier()
        try:
            self.session: zenoh.Session = open_session(build_config(opts), stop=self.stop_event, log=self.log,
                                                       on_retry=self._ping)
        except UnusableConfig as exc:  # a missing TLS file: one line and exit 2, not a wait for ever
            self.log.error("%s", exc)
            raise SystemExit(2) from None
        self._declared.append(self.session.liveliness().declare_token(keys.alive(self.ns, self.name)))
        self._hb_pub = self.session.declare_publisher(keys.heartbeat(self.ns, self.name))
        self.spawn(self._heartbeat_loop, "heartbeat")
        memtrace.start_from_env(self.name, self.stop_event, self.log)

    # ------------------------------------------------------------------ wiring helpers for subclasses

    def accept(self, model: type[M], data: bytes, sub_key: str, sample_key: str | None = None,
               max_bytes: int | None = None, max_array_len: int | None = None,
               max_map_len: int | None = None) -> M | None:
        """Decode and validate one payload; a bad one — or one over ``max_bytes``, or with a list or map beyond
        ``max_array_len`` / ``max_map_len``, refused before it is built — is counted (``rejected`` and
        ``rejected.<sub_key>`` without the ``jg/{ns}/`` prefix, and ``over_limit.<key>``), logged once per burst, and
        ``None`` comes back."""
        try:
            return decode(model, data, max_bytes=max_bytes, max_array_len=max_array_len, max_map_len=max_map_len)
        except DecodeError as exc:
            self.reject(exc, sub_key, sample_key)
            return None

    def reject(self, exc: DecodeError, sub_key: str, sample_key: str | None = None) -> None:
        """Count and log (once per burst) a payload that failed to decode, as :meth:`accept` does; for services
        that read on their own path (the read functions of :mod:`jitterguard.schemas.wire`). A payload beyond a
        limit is also counted ``over_limit.<key>``."""
        key = counter_key(sub_key)
        self.counters.inc("rejected")
        self.counters.inc(f"rejected.{key}")
        if isinstance(exc, LimitExceeded):
            self.counters.inc(f"over_limit.{key}")
        self._reject_log.warn(f"rejected payload on {sample_key or sub_key}: {exc}", kind=f"rejected {key}")

    def foreign_track(self, model: str, track_id: str, key: str, sub_key: str) -> bool:
        """Whether a per-track message (``tracks/{id}``, ``motion/{id}``) names another track than its key does; if
        so it is refused and counted as :meth:`reject` counts (``rejected.<sub_key>``). Why: Zenoh's ACL grants keys,
        so a publisher allowed one track's key must not be able to speak for another track."""
        if track_id == keys.last_chunk(key):
            return False
        self.reject(DecodeError(model, "track_id", "not the track its key names"), sub_key, key)
        return True

    def oversized(self, sample: zenoh.Sample, max_bytes: int | None, what: str, sub_key: str,
                  limit_name: str = "") -> bool:
        """Whether ``sample`` is over ``max_bytes``; if so it is refused from its size, as :meth:`reject` counts a
        :class:`LimitExceeded` (``what``: the message, or ``payload``; ``limit_name``: the limit's name for the
        log), before its bytes are copied or queued."""
        n = len(sample.payload)
        if max_bytes is None or n <= max_bytes:
            return False
        limit = f"{limit_name} {max_bytes}" if limit_name else str(max_bytes)
        self.reject(LimitExceeded(what, "", f"{n} bytes exceed {limit}"), sub_key, str(sample.key_expr))
        return True

    def subscribe(self, key: str, model: type[M], handler: Callable[[M, str], None], *,
                  max_bytes: int | None = None, max_array_len: int | None = None,
                  max_map_len: int | None = None) -> None:
        """Subscribe ``key``; ``handler(message, key)`` gets only payloads that validate as ``model`` (and, with
        the bounds, are no larger and hold no longer list or map: :meth:`accept`)."""

        def on_sample(sample: zenoh.Sample) -> None:
            self.counters.inc("received")
            if self.deleted(sample, key):
                return
            msg = self.accept(model, sample.payload.to_bytes(), key, str(sample.key_expr), max_bytes, max_array_len,
                              max_map_len)
            if msg is None:
                return
            try:
                handler(msg, str(sample.key_expr))
            except Exception:  # a bug in a handler must not kill the subscriber thread
                self.counters.inc("handler_errors")
                self.log.exception("handler for %s failed", key)

        self._declared.append(self.session.declare_subscriber(key, on_sample))

    def deleted(self, sample: zenoh.Sample, key: str) -> bool:
        """Whether ``sample`` is a Zenoh DELETE (a storage's or an admin tool's ``session.delete``), counted as
        ``deletes.{key}`` and otherwise ignored: the contract has no deletes, and each had been logged as a corrupt
        payload ("not valid msgpack") and counted ``rejected``, pointing at a broken writer that was not there."""
        if sample.kind != zenoh.SampleKind.DELETE:
            return False
        self.counters.inc(f"deletes.{counter_key(key)}")
        return True

    def monitor_progress(self, policy: ProgressPolicy | None = None) -> ProgressMonitor:
        """Report health as progress (:mod:`.progress`): the subclass calls ``input`` / ``output`` / ``failure``
        on the returned monitor (``subscribe_queue(..., progress=True)`` records arrivals itself)."""
        self.progress = ProgressMonitor(policy)
        return self.progress

    def health(self) -> Health:
        """The progress verdict now (``ok`` for a service with no input → output relation); ``stalled`` while
        :attr:`starting` (never counted towards the watchdog: ``unhealthy_for_s`` stays 0)."""
        if self.starting is not None:
            return Health(STALLED, f"starting: {self.starting}")
        return self.progress.assess(time.monotonic()) if self.progress is not None else Health("ok")

    def subscribe_queue(self, key: str, capacity: int, *, max_queued_bytes: int = QUEUE_BYTES,
                        max_bytes: int | None = None, what: str = "payload", limit_name: str = "",
                        progress: bool = False, wake: threading.Event | None = None,
                        session: zenoh.Session | None = None) -> IngestQueue:
        """Subscribe ``key`` into a bounded :class:`~.ingest_queue.IngestQueue` of ``(payload, key, arrival time)``
        (``time.monotonic()``) for a worker of the service's own: ``take(limit)`` drains a batch (thousands of small
        ``tracks/*`` messages a second), ``get(timeout)`` wakes the moment one arrives (a few large messages a second:
        a frame's ``detections``). One route of :meth:`subscribe_queues`, which says what the options do."""
        route = QueueRoute(key, capacity, max_queued_bytes, what, progress, wake)
        return self.subscribe_queues(key, (route,), _only_route, max_bytes=max_bytes, limit_name=limit_name,
                                     session=session)[0]

    def subscribe_queues(self, key_expr: str, routes: Sequence[QueueRoute], route_of: Callable[[str], int | None], *,
                         max_bytes: int | None = None, limit_name: str = "",
                         session: zenoh.Session | None = None) -> list[IngestQueue]:
        """Subscribe ``key_expr`` once and put each sample into the queue of ``routes[route_of(its key)]`` (a key
        routed to ``None`` is left alone, as a narrower subscription would never have seen it).

        One subscription has one callback thread, so the samples of all its keys reach the queues in the order they
        arrived: the classifier's observations (``tracks/{id}``) are queued before the ``tracked`` put after them
        (two subscriptions have a thread each, and a close had been able to overtake its frame's observations).
        The callback only checks the size, copies the payload and appends it. When a route's ``capacity`` payloads
        (or ``max_queued_bytes`` of them) wait, its oldest go, counted ``dropped_queue.<route key>``: a worker that
        fell behind catches up on the newest, and a flood costs a bounded amount of memory, never Zenoh's receive
        path. Zenoh's ``RingChannel``, used for ``tracks/*`` before, dropped its oldest uncounted, and each Sample it
        held kept Zenoh's receive buffer alive (~85 kB for a 1.4 kB payload that came in a batch of its own): a flood
        of unbatched puts had grown the classifier by 1.1–1.5 GB. ``max_bytes``: a larger payload is refused here,
        from its size, before it is copied or queued (counted as :meth:`reject` counts under the route's key, the
        route's ``what`` and ``limit_name`` naming it, and ``received``; a flood of 50 MB ones had been queued for
        the worker to refuse). A route's ``progress``: each arrival is an input of :attr:`progress` (a worker stuck
        on one message then shows as stalled while more arrive); its ``wake``: set after each push, for a worker
        that waits on more than its queue. ``session``: another session of the service's (a ROS 2 system's router)
        instead of its own.
        """
        if any(r.progress for r in routes) and self.progress is None:
            raise RuntimeError("a queue route with progress=True needs monitor_progress() first")
        queues = [IngestQueue(r.capacity, r.max_queued_bytes) for r in routes]
        plans = [(q.push, f"dropped_queue.{counter_key(r.key)}", self.progress if r.progress else None, r.wake, r)
                 for q, r in zip(queues, routes)]
        monotonic = time.monotonic

        def on_sample(sample: zenoh.Sample) -> None:
            # thousands a second: the size checked here, 1.6 µs a sample (2.9 µs calling self.oversized for each)
            key = str(sample.key_expr)
            i = route_of(key)
            if i is None:
                return
            push, counter, monitor, wake, route = plans[i]
            payload = sample.payload
            size = len(payload)
            if not size and self.deleted(sample, route.key):  # a delete has no payload: its kind read only then
                self.counters.inc("received")
                return
            if max_bytes is not None and size > max_bytes:
                self.oversized(sample, max_bytes, route.what, route.key, limit_name)  # counts and logs it
                self.counters.inc("received")
                return
            now = monotonic()
            if monitor is not None:
                monitor.input(now)
            dropped = push(payload.to_bytes(), key, now)
            if dropped:
                self.counters.inc(counter, dropped)
            if wake is not None:
                wake.set()

        self._declared.append((session or self.session).declare_subscriber(key_expr, on_sample))
        return queues

    def publisher(self, key: str, *, block: bool = True, session: zenoh.Session | None = None) -> zenoh.Publisher:
        """A declared publisher; BLOCK congestion control by default (losing a frame is wrong); on ``session``
        (another session of the service's) if given."""
        cc = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        pub = (session or self.session).declare_publisher(key, congestion_control=cc)
        self._declared.append(pub)
        return pub

    def keyed_publishers(self, key_of: Callable[[str], str], *,
                         priority: zenoh.Priority = zenoh.Priority.DATA) -> KeyedPublishers:
        """Puts on ``key_of(id)`` per track ID (:mod:`.keyed_publishers`)."""
        pubs = KeyedPublishers(self.session, key_of, priority=priority)
        self._declared.append(pubs)
        return pubs

    def publish(self, pub: zenoh.Publisher, model: BaseModel) -> None:
        pub.put(encode(model))
        self.counters.inc("published")

    def put(self, key: str, model: BaseModel | bytes, *, block: bool = True) -> None:
        """Publish on a key that changes per message (``tracks/{id}``, ``motion/{id}``)."""
        payload = model if isinstance(model, bytes) else encode(model)
        cc = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        self.session.put(key, payload, congestion_control=cc)
        self.counters.inc("published")

    def queryable(self, key: str, handler: Callable[[zenoh.Query], None]) -> None:
        """Serve ``key``; the query is always finalised, even if ``handler`` raises."""

        def on_query(query: zenoh.Query) -> None:
            with query:
                try:
                    handler(query)
                except Exception as exc:
                    self.counters.inc("query_errors")
                    self.log.exception("query on %s failed", key)
                    query.reply_err(f"internal error: {type(exc).__name__}: {exc}".encode())

        self._declared.append(self.session.declare_queryable(key, on_query))

    def another_session(self, opts: ZenohOptions) -> zenoh.Session:
        """A second Zenoh session (the ROS 2 adapters': a ROS 2 system's own router), opened as the service's own is
        — waiting for its router while systemd's watchdog is pinged, a bad TLS file one line and exit 2 — and closed
        with the service, after everything declared on it (it is undeclared in reverse order)."""
        try:
            session = open_session(build_config(opts), stop=self.stop_event, log=self.log, on_retry=self._ping)
        except UnusableConfig as exc:
            self.log.error("%s", exc)
            raise SystemExit(2) from None
        self._declared.append(_ClosedWithService(session))
        return session

    def spawn(self, target: Callable[[], None], name: str) -> threading.Thread:
        """Start a daemon worker thread that the service joins on shutdown."""
        t = threading.Thread(target=target, name=f"{self.name}-{name}", daemon=True)
        t.start()
        self._threads.append(t)
        return t

    # ------------------------------------------------------------------ lifecycle

    def heartbeat(self, health: Health | None = None) -> Heartbeat:
        health = health or self.health()
        return Heartbeat(
            service=self.name,
            pid=os.getpid(),
            stamp=time.time_ns(),
            last_seq=self.last_seq,
            uptime_s=time.monotonic() - self.started_at,
            counters=self.counters.snapshot(),
            gauges=self.gauges(),
            health=health.state,
            health_reason=health.reason[:500],
        )

    def gauges(self) -> dict[str, float]:
        """Current values for the heartbeat besides the counters (none by default; called off the worker, so
        a service returns what its worker last stored)."""
        return {}

    def _ping(self) -> None:
        """Tell systemd's watchdog that this process still runs Python code (nothing without ``NOTIFY_SOCKET``).
        Sent whatever the health: a service that is alive but failing is the progress watchdog's to end
        (:meth:`_watch`); systemd's is for one stopped or hung so hard that neither runs (:mod:`.sd_notify`)."""
        self._notifier.send("WATCHDOG=1")

    def _heartbeat_loop(self) -> None:
        while not self.stop_event.wait(HEARTBEAT_PERIOD_S):
            self._ping()
            health = self.health()
            try:
                self._hb_pub.put(encode(self.heartbeat(health)))
            except Exception:  # session closing underneath us
                if self.stop_event.is_set():
                    return
                self.log.exception("heartbeat failed")
            self._watch(health)

    def _watch(self, health: Health) -> None:
        """Under :meth:`run_forever`: re-arm the hang timer; stop with :data:`EXIT_NO_PROGRESS` once the
        service has been failing or stalled for the watchdog period."""
        if self._watchdog_s is None:
            return
        faulthandler.dump_traceback_later(self._watchdog_s + HANG_GRACE_S, exit=True)
        if not health.ok and health.unhealthy_for_s >= self._watchdog_s and not self.stop_event.is_set():
            self.log.error("no progress for %.0f s (%s: %s); exiting with status %d for the supervisor to "
                           "restart this process", health.unhealthy_for_s, health.state, health.reason,
                           EXIT_NO_PROGRESS)
            self.exit_code = EXIT_NO_PROGRESS
            self.stop()

    def run_forever(self) -> None:
        """Block until SIGINT/SIGTERM (main thread) or :meth:`stop`, then close everything. With the watchdog on
        (``JG_WATCHDOG_S``, default 10 s), a service that stopped making progress exits with status 70."""
        stop_on_signals(self.stop)
        self._watchdog_s = self._watchdog_env
        if self._watchdog_s is not None:  # armed now: a worker may hang before the first heartbeat
            faulthandler.dump_traceback_later(self._watchdog_s + HANG_GRACE_S, exit=True)
        self.log.info("%s up (ns=%s, pid=%d)", self.name, self.ns, os.getpid())
        try:
            while not self.stop_event.wait(0.2):
                pass
        finally:
            self.close()
            if self._watchdog_s is not None:
                faulthandler.cancel_dump_traceback_later()
        if self.exit_code:
            raise SystemExit(self.exit_code)

    def stop(self) -> None:
        self.stop_event.set()

    def close(self) -> None:
        """Stop workers, undeclare everything and close the session (no hang at exit)."""
        self.stop_event.set()
        if self._watchdog_s is not None:  # a shutdown that hangs (a put blocked for good) still ends
            faulthandler.dump_traceback_later(SHUTDOWN_LIMIT_S, exit=True)
        self.on_close()
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(timeout=2.0)
        try:  # the final counts, for whoever sums the run up (the stack's monitor)
            self._hb_pub.put(encode(self.heartbeat()))
        except Exception:
            pass
        self._drain()
        self._release_session()
        self._notifier.close()
        self.log.info("%s stopped: %s", self.name, self.counters.snapshot())

    def _drain(self) -> None:
        """Give what this session has put :data:`DRAIN_S` to leave it before the session closes. Closing straight
        after the last put lost what still sat in its transmit queue (at most two 64 KB batches a priority: a BLOCK
        put returns once its last fragment is queued) — a ``replay --rate max`` of three scans delivered one or
        two of them in 5 of 12 runs — and a service's final heartbeat, whose counts the stack's monitor sums,
        could go the same way. Zenoh has no flush to wait on, and a query to a key nobody serves is answered
        inside the session without a round trip (0.2 ms), so the wait is a bounded pause."""
        time.sleep(DRAIN_S)

    def on_close(self) -> None:
        """Hook for subclasses: called once the stop event is set, before the session closes."""

    def __enter__(self) -> "Service":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _ClosedWithService:
    """A session in the service's list of declared entities: "undeclaring" it closes it."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session

    def undeclare(self) -> None:
        self.session.close()


@dataclass(frozen=True)
class QueueRoute:
    """One queue of :meth:`Service.subscribe_queues`: the samples routed to it and how it reports them."""

    key: str
    """What its counters are named by (``dropped_queue.<key>``, ``rejected.<key>``): the key its samples come on."""
    capacity: int
    max_queued_bytes: int = QUEUE_BYTES
    what: str = "payload"
    """The message's name in a refusal from its size."""
    progress: bool = False
    wake: threading.Event | None = None


def _only_route(_key: str) -> int:
    return 0


def counter_key(key: str) -> str:
    """The part of a key a per-key counter is named by: ``jg/{ns}/`` left out (``rejected.tracked``), a key outside
    jitterguard's namespace whole (a ROS 2 topic's, ``rejected.sensing/lidar/top/pointcloud``)."""
    return key.split("/", 2)[-1] if key.startswith("jg/") else key


QUIET_LIBRARIES = ("onnxscript", "onnx_ir", "torch.onnx")
"""Libraries that log their own progress at INFO (the ONNX export behind ``detector --backend onnxruntime``: ~65
lines of passes): a service's INFO log is for its operator, so they speak from WARNING up unless DEBUG is asked."""


def setup_logging(level: str = "INFO") -> None:
    """One log line format for every service (supervisord captures stderr)."""
    numeric = getattr(logging, level.upper(), logging.INFO)
    logging.basicConfig(level=numeric, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    for name in QUIET_LIBRARIES:
        logging.getLogger(name).setLevel(max(numeric, logging.WARNING) if numeric > logging.DEBUG else numeric)
