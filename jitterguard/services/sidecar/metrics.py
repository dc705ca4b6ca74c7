"""Prometheus exposition for ``GET /metrics``.

The classifier's figures are read from the sidecar's latest state snapshot at scrape time (a custom
collector), not mirrored into live metric objects on every poll: a scrape then costs one pass over the
cached aggregates, and what ``/metrics`` says always matches what ``/v1/state`` serves. The sidecar's own
figures (poll timing, config writes, SSE clients) are ordinary metric objects in a private registry, so two
apps in one process (tests) never collide in the global registry.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily
from prometheus_client.registry import Collector

from ...stack.summary import is_gauge
from .core import CLASS_NAMES, STATES, latency_histogram

if TYPE_CHECKING:
    from .client import ClassifierClient

FRAMES_COUNTER = "frames_processed"
REJECTED_COUNTER = "rejected"


class SidecarMetrics:
    """The sidecar's own metric objects, in a registry of their own."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        r = self.registry
        self.poll_seconds = Histogram(
            "jitterguard_sidecar_state_poll_seconds", "Round trip of one classifier/state query",
            buckets=(0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0), registry=r)
        self.poll_failures = Counter(
            "jitterguard_sidecar_state_poll_failures", "classifier/state polls with no valid reply", registry=r)
        self.rejected = Counter(
            "jitterguard_sidecar_rejected_messages", "Zenoh payloads the sidecar dropped as invalid",
            ["key"], registry=r)
        self.config_writes = Counter(
            "jitterguard_sidecar_config_writes", "Config writes through the API by outcome",
            ["result"], registry=r)
        self.refused_requests = Counter(
            "jitterguard_sidecar_refused_requests", "HTTP requests refused before routing (foreign Host, "
            "cross-site or non-JSON write, write without the token, body too large), by status", ["status"], registry=r)
        self.sse_clients = Gauge("jitterguard_sidecar_sse_clients", "Open /v1/events streams", registry=r)
        self.sse_dropped = Counter(
            "jitterguard_sidecar_sse_dropped_events", "Events dropped for SSE clients that read too slowly",
            registry=r)

    def attach(self, client: "ClassifierClient") -> None:
        """Expose the classifier's figures through ``client``'s snapshot cache, and every service's heartbeat."""
        self.registry.register(ClassifierCollector(client.served_state, client.classifier_up))
        self.registry.register(ServiceCollector(client.service_beats, client.stale_after_s))


class ServiceCollector(Collector):
    """Every pipeline service's health as its heartbeats tell it, at scrape time: what ``/readyz`` judges, in a
    form an alert rule can read (``jitterguard_service_healthy == 0`` for a minute) — a frozen tracker or a detector
    that stalls had been visible only to someone who asked ``/readyz`` or ``jitterguard status``."""

    def __init__(self, beats: Callable[[], list], stale_after_s: float) -> None:
        self._beats = beats
        self._stale_after_s = stale_after_s

    def describe(self) -> list:
        return []

    def collect(self) -> Iterator:
        label = ["service"]
        up = GaugeMetricFamily("jitterguard_service_up", "1 while the service's liveliness token is present", labels=label)
        healthy = GaugeMetricFamily(
            "jitterguard_service_healthy", "1 if its latest heartbeat is recent and says it turns its input into "
            "output (health ok); 0 when it is failing, stalled or silent", labels=label)
        age = GaugeMetricFamily("jitterguard_service_heartbeat_age_seconds", "Seconds since its latest heartbeat",
                                labels=label)
        seq = GaugeMetricFamily("jitterguard_service_last_seq", "Seq of the latest frame it handled", labels=label)
        uptime = GaugeMetricFamily("jitterguard_service_uptime_seconds", "Its process's uptime, as it last said",
                                   labels=label)
        raw = CounterMetricFamily("jitterguard_service_counter", "Every running count a service reports, by name "
                                  "(from 0 again when its process restarts)", labels=["service", "name"])
        now = GaugeMetricFamily("jitterguard_service_current", "A service's counters that hold a current value "
                                "(now.*, *_last), by name", labels=["service", "name"])
        gauges = GaugeMetricFamily("jitterguard_service_gauge", "A service's gauges (values that are not counts), by "
                                   "name", labels=["service", "name"])
        for name, hb, since, on_bus in self._beats():
            up.add_metric([name], 1.0 if on_bus else 0.0)
            healthy.add_metric([name], 1.0 if hb.health == "ok" and since <= self._stale_after_s else 0.0)
            age.add_metric([name], since)
            seq.add_metric([name], float(hb.last_seq))
            uptime.add_metric([name], hb.uptime_s)
            for counter, value in sorted(hb.counters.items()):
                (now if is_gauge(counter) else raw).add_metric([name, counter], float(value))
            for gauge, value in sorted(hb.gauges.items()):
                gauges.add_metric([name, gauge], float(value))
        yield from (up, healthy, age, seq, uptime, raw, now, gauges)


class ClassifierCollector(Collector):
    """Classifier metrics computed at scrape time from the cached snapshot, exported only while that snapshot is
    current (``rendered`` returns None otherwise): absent series go stale in Prometheus, where a frozen value would
    read as a live count."""

    def __init__(self, rendered: Callable[[], object], up: Callable[[], bool]) -> None:
        """``up``: whether the classifier itself is on the bus with a recent heartbeat (not the pipeline's
        readiness, which ``/readyz`` and ``jitterguard_service_healthy`` tell)."""
        self._rendered = rendered
        self._up = up

    def describe(self) -> list:
        return []  # families vary with what the classifier exports; skip describe-time collection

    def collect(self) -> Iterator:
        up = GaugeMetricFamily("jitterguard_classifier_up",
                               "1 if the classifier's liveliness token is present and its heartbeat is recent")
        up.add_metric([], 1.0 if self._up() else 0.0)
        yield up
        st = self._rendered()
        if st is None:
            return
        counters: dict[str, int] = st.counters  # type: ignore[attr-defined]
        frames = CounterMetricFamily("jitterguard_classifier_frames", "Frames the classifier has processed")
        frames.add_metric([], float(counters.get(FRAMES_COUNTER, 0)))
        yield frames
        seq = GaugeMetricFamily("jitterguard_classifier_last_seq", "Seq of the classifier's latest frame")
        seq.add_metric([], float(st.seq))  # type: ignore[attr-defined]
        yield seq
        tracks = GaugeMetricFamily("jitterguard_classifier_tracks", "Tracks in the classifier's latest frame")
        tracks.add_metric([], float(st.counts["total"]))  # type: ignore[attr-defined]
        yield tracks
        by = GaugeMetricFamily("jitterguard_classifier_tracks_by_state",
                               "Tracks in the latest frame by class and motion state", labels=["class", "state"])
        agg = st.by_class_state  # type: ignore[attr-defined]
        for cls in CLASS_NAMES:
            for state in STATES:
                by.add_metric([cls, state], float(agg.get((cls, state), 0)))
        yield by
        rej = CounterMetricFamily("jitterguard_classifier_rejected_messages",
                                  "Payloads the classifier dropped as invalid")
        rej.add_metric([], float(counters.get(REJECTED_COUNTER, 0)))
        yield rej
        rej_key = CounterMetricFamily("jitterguard_classifier_rejected_messages_by_key",
                                      "Payloads the classifier dropped as invalid, by key", labels=["key"])
        for name, value in sorted(counters.items()):
            if name.startswith(REJECTED_COUNTER + "."):
                rej_key.add_metric([name[len(REJECTED_COUNTER) + 1:]], float(value))
        yield rej_key
        raw = CounterMetricFamily("jitterguard_classifier_counter",
                                  "Every running count the classifier reports, by name", labels=["name"])
        now = GaugeMetricFamily("jitterguard_classifier_current",
                                "The classifier's counters that hold a current value (now.*, *_last), by name",
                                labels=["name"])
        for name, value in sorted(counters.items()):
            # a value that goes down exported as a counter reads as a reset to rate() and increase()
            (now if is_gauge(name) else raw).add_metric([name], float(value))
        yield raw
        yield now
        cfg = st.config  # type: ignore[attr-defined]
        alpha = GaugeMetricFamily("jitterguard_classifier_alpha", "Alpha in force per class", labels=["class"])
        for label, cls in enumerate(CLASS_NAMES):
            alpha.add_metric([cls], float(cfg.alpha_for(label)))
        yield alpha
        yield from calibration_families(getattr(st, "calibration", None))
        hist = latency_histogram(counters)
        if hist is not None:
            fam = HistogramMetricFamily("jitterguard_classifier_frame_latency_seconds",
                                        "Classifier latency per frame: closing message in to objects out")
            fam.add_metric([], [(_le(le), float(n)) for le, n in hist.buckets], sum_value=hist.sum_s)
            yield fam


def calibration_families(cal: dict | None) -> Iterator:
    """The classifier's variance calibration as gauges (absent before its first snapshot)."""
    if not cal:
        return
    scale = GaugeMetricFamily("jitterguard_classifier_variance_scale",
                              "True / reported positional variance the classifier applies, by class group, "
                              "line-of-sight axis, range band and track age", labels=["group", "axis", "band", "age"])
    corr = GaugeMetricFamily("jitterguard_classifier_serial_correlation",
                             "Serially correlated share m of the detection error", labels=["group", "axis"])
    tau = GaugeMetricFamily("jitterguard_classifier_correlation_time_seconds",
                            "Correlation time of the serially correlated error", labels=["group", "axis"])
    factor = GaugeMetricFamily("jitterguard_classifier_variance_factor",
                               "Var(half-mean difference) under the serial correlation / under independence, "
                               "full window", labels=["group", "axis"])
    for g, entry in cal.get("groups", {}).items():
        for axis in ("along", "across"):
            a = entry[axis]
            for key, age in (("scale", "established"), ("scale_young", "young")):
                for band, v in a[key].items():
                    scale.add_metric([g, axis, band, age], float(v))
            corr.add_metric([g, axis], float(a["correlation"]))
            tau.add_metric([g, axis], float(a["correlation_time_s"]))
            factor.add_metric([g, axis], float(a["variance_factor"]))
    yield from (scale, corr, tau, factor)
    if cal.get("scale_dof") is not None:
        yield GaugeMetricFamily("jitterguard_classifier_calibration_scale_dof",
                                "Degrees of freedom of the calibration's scales (2 at a cold start, 8 more per "
                                "block of evidence)", value=float(cal["scale_dof"]))


def _le(bound: float) -> str:
    return "+Inf" if math.isinf(bound) else repr(bound)
