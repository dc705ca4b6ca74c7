"""The sidecar's pure core: config merge/validation, views, change detection, metrics, bind policy."""

from __future__ import annotations

import json
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from jitterguard.schemas.models import (
    LABEL_NAMES,
    ClassifierConfig,
    ClassifierStateSnapshot,
    Header,
    TrackStateEntry,
)
from jitterguard.services.classifier.config import PRESETS
from jitterguard.services.sidecar.core import (
    CLASS_NAMES,
    CONFIG_FIELDS,
    ConfigError,
    ConfigModel,
    ConfigPatchModel,
    StateView,
    TrackView,
    aggregate_by_class_state,
    apply_preset,
    bind_refusal,
    config_to_api,
    diff_states,
    is_loopback,
    latency_histogram,
    merge_patch,
    refusal_counts,
    refusal_warning,
    refusals_since,
    render_state,
    validate_config,
)
from jitterguard.services.sidecar.events import format_event

# ----------------------------------------------------------------------------------------- config


def test_http_config_model_carries_the_wire_constraints() -> None:
    """The HTTP models are derived from ClassifierConfig: same fields, same bounds, same defaults."""
    wire = ClassifierConfig.model_json_schema()["properties"]
    api = ConfigModel.model_json_schema()["properties"]
    assert set(api) == set(CONFIG_FIELDS) == set(wire) - {"schema_version"}
    for name in CONFIG_FIELDS:
        for bound in ("minimum", "maximum", "exclusiveMinimum", "enum", "default"):
            assert api[name].get(bound) == wire[name].get(bound), (name, bound)
    per_class_fields = ("alpha_per_class", "velocity_threshold_per_class", "velocity_sustain_s_per_class",
                        "dynamic_hold_s_per_class", "view_slide_m_per_class")
    assert {n for n in wire if n.endswith("_per_class")} == set(per_class_fields)
    for per_class in per_class_fields:
        assert api[per_class]["propertyNames"]["enum"] == list(CLASS_NAMES), per_class  # keys an enum
    assert ConfigModel().model_dump() == config_to_api(ClassifierConfig())


def test_patch_model_accepts_null_and_rejects_unknown_fields() -> None:
    assert ConfigPatchModel.model_validate({"alpha_default": None}).model_dump(exclude_unset=True) == {
        "alpha_default": None}
    with pytest.raises(ValidationError) as exc:
        ConfigPatchModel.model_validate({"alpha": 1.0})
    assert exc.value.errors()[0]["loc"] == ("alpha",)
    with pytest.raises(ValidationError):
        ConfigPatchModel.model_validate({"alpha_default": float("nan")})


def test_merge_patch_semantics() -> None:
    cur = ClassifierConfig(alpha_default=2.5, alpha_per_class={"car": 2.0, "bus": 3.0}, window_size=12)
    assert merge_patch(cur, {}) == cur
    out = merge_patch(cur, {"alpha_default": 1.0})
    assert out.alpha_default == 1.0 and out.window_size == 12 and out.alpha_per_class == cur.alpha_per_class
    out = merge_patch(cur, {"alpha_default": None, "window_size": None})  # null resets to the default
    assert out.alpha_default == ClassifierConfig().alpha_default and out.window_size == 20
    out = merge_patch(cur, {"alpha_per_class": {"car": None, "pedestrian": 1.28}})  # per-key merge
    assert out.alpha_per_class == {"bus": 3.0, "pedestrian": 1.28}
    assert merge_patch(cur, {"alpha_per_class": None}).alpha_per_class == ClassifierConfig().alpha_per_class
    # every per-class map merges key by key, a null value drops that class
    out = merge_patch(cur, {"velocity_threshold_per_class": {"pedestrian": None, "car": 2.0}})
    assert out.velocity_threshold_per_class == {"bicycle": 0.28, "unknown": 0.28, "car": 2.0}
    out = merge_patch(out, {"velocity_sustain_s_per_class": {"car": 2.0}})
    assert out.velocity_sustain_s_per_class == {"car": 2.0} and out.velocity_threshold_per_class["car"] == 2.0
    out = merge_patch(out, {"dynamic_hold_s_per_class": {"pedestrian": 0.3}})
    out = merge_patch(out, {"dynamic_hold_s_per_class": {"car": 0.5}})
    assert out.dynamic_hold_s_per_class == {"pedestrian": 0.3, "car": 0.5} and out.hold_for(1) == 0.5
    out = merge_patch(out, {"view_slide_m_per_class": {"car": 2.5, "bus": 2.0}})
    out = merge_patch(out, {"view_slide_m_per_class": {"bus": None}})
    assert out.view_slide_m_per_class == {"car": 2.5, "truck": 2.0, "trailer": 2.0}  # bus dropped, car changed
    assert out.view_slide_for(1) == 2.5 and out.view_slide_for(3) == 0


@pytest.mark.parametrize(("patch", "field"), [
    ({"alpha_default": 0.0}, "alpha_default"),
    ({"alpha_default": 101.0}, "alpha_default"),
    ({"alpha_default": "high"}, "alpha_default"),
    ({"window_size": 1}, "window_size"),
    ({"window_size": 5000}, "window_size"),
    ({"min_window": 21}, "min_window"),       # > window_size 20: the cross-field rule names min_window
    ({"window_size": 3, "min_window": None}, "window_size"),  # ok: min_window resets to 2
    ({"variance_floor": -1.0}, "variance_floor"),
    ({"velocity_threshold": -0.1}, "velocity_threshold"),
    ({"mode": "magic"}, "mode"),
    ({"effective_n": "many"}, "effective_n"),
    ({"alpha_per_class": {"spaceship": 1.0}}, "alpha_per_class"),
    ({"alpha_per_class": {"car": -1.0}}, "alpha_per_class"),
    ({"alpha": 1.0}, "alpha"),
])
def test_invalid_values_name_the_field(patch: dict, field: str) -> None:
    cur = ClassifierConfig()
    if patch == {"window_size": 3, "min_window": None}:
        assert merge_patch(cur, patch).window_size == 3
        return
    with pytest.raises(ConfigError) as exc:
        merge_patch(cur, patch)
    locs = [e["loc"] for e in exc.value.errors]
    assert locs and locs[0][0] == "body" and locs[0][1] == field, locs
    json.dumps(exc.value.errors, allow_nan=False)  # the 422 body is strict JSON


def test_window_order_error_names_the_field_the_request_changed() -> None:
    cur = ClassifierConfig(window_size=10, min_window=8)
    with pytest.raises(ConfigError) as exc:
        merge_patch(cur, {"window_size": 5})
    assert exc.value.errors[0]["loc"] == ["body", "window_size"] and exc.value.errors[0]["input"] == 5
    with pytest.raises(ConfigError) as exc:
        validate_config({"window_size": 5, "min_window": 8})
    assert exc.value.errors[0]["loc"] == ["body", "min_window"]


def test_presets_keep_every_other_field() -> None:
    cur = ClassifierConfig(window_size=20, min_window=4, mode="chi2", alpha_default=3.0)
    out = apply_preset(cur, "authors")
    assert out.alpha_per_class == PRESETS["authors"]["alpha_per_class"]
    assert (out.window_size, out.min_window, out.mode) == (20, 4, "chi2")
    assert apply_preset(out, "paper").alpha_per_class == {}
    with pytest.raises(KeyError):
        apply_preset(cur, "nope")


_alpha = st.floats(min_value=0.01, max_value=100.0, allow_nan=False)
_patch = st.fixed_dictionaries({}, optional={
    "alpha_default": st.one_of(st.none(), _alpha),
    "window_size": st.one_of(st.none(), st.integers(2, 1000)),
    "min_window": st.one_of(st.none(), st.integers(2, 1000)),
    "mode": st.one_of(st.none(), st.sampled_from(["z_test", "chi2", "velocity_threshold"])),
    "alpha_per_class": st.one_of(st.none(), st.dictionaries(st.sampled_from(CLASS_NAMES),
                                                            st.one_of(st.none(), _alpha), max_size=4)),
})


@settings(max_examples=200, deadline=None)
@given(patch=_patch)
def test_merge_patch_is_a_validated_merge(patch: dict) -> None:
    """Any patch either yields a valid config that holds every field it set, or a 422 naming a field it
    touched; applying the same patch twice changes nothing more (idempotent)."""
    cur = ClassifierConfig(alpha_per_class={"car": 2.58}, window_size=10, min_window=3)
    try:
        out = merge_patch(cur, patch)
    except ConfigError as exc:
        assert exc.errors[0]["loc"][1] in patch
        return
    defaults = ClassifierConfig()
    for name, value in patch.items():
        if name == "alpha_per_class":
            continue
        assert getattr(out, name) == (getattr(defaults, name) if value is None else value)
    for cls, alpha in (patch.get("alpha_per_class") or {}).items():
        assert out.alpha_per_class.get(cls) == alpha
    assert merge_patch(out, patch) == out


# ----------------------------------------------------------------------------------------- views


def _entry(i: int, state: str, label: int = 1, **kw: float) -> TrackStateEntry:
    base = dict(track_id=f"{i:032x}", label=label, state=state, z_x=0.5, z_y=2.5, chi2=6.0, alpha=1.96,
                threshold=1.96, window_length=4, window_size=10, speed=3.0, x=1.0 * i, y=-2.0, yaw=0.1,
                length=4.5, width=1.9, last_update_ns=10**18, last_seq=7)
    base.update(kw)
    return TrackStateEntry(**base)


def _snap(entries: list[TrackStateEntry], seq: int = 9, **cfg: object) -> ClassifierStateSnapshot:
    return ClassifierStateSnapshot(header=Header(stamp=123, seq=seq), config=ClassifierConfig(**cfg),
                                   tracks=entries, counters={"frames_processed": 10, "rejected": 2})


def test_render_state_matches_the_documented_view() -> None:
    snap = _snap([_entry(3, "dynamic"), _entry(1, "static", label=7), _entry(2, "undecided", label=0)])
    r = render_state(snap, polled_at_ns=5)
    body = json.loads(r.body)
    view = StateView.model_validate(body)  # the OpenAPI response model accepts it
    assert [t.id for t in view.tracks] == sorted(t.id for t in view.tracks)
    assert body["counts"] == {"static": 1, "dynamic": 1, "undecided": 1, "total": 3}
    t = TrackView.model_validate(r.tracks[f"{3:032x}"])
    assert t.class_ == "car" and t.z == 2.5 and t.statistic == 2.5 and t.window_fill == 0.4
    assert t.frames_since_update == 2  # snapshot seq 9, last observed in 7
    assert r.tracks[f"{1:032x}"]["class"] == "pedestrian"
    assert r.by_class_state[("car", "dynamic")] == 1 and r.by_class_state[("bus", "static")] == 0


def test_render_from_the_raw_wire_map_equals_render_from_the_model() -> None:
    """The client renders from decode_with_raw's map (faster); a producer may omit defaulted fields."""
    import msgpack

    from jitterguard.schemas import decode_with_raw
    snap = _snap([_entry(2, "dynamic"), _entry(1, "static", label=7)])
    data = msgpack.packb(snap.model_dump(mode="python", exclude={"tracks": {0: {"yaw", "length", "width"}}}))
    model, raw = decode_with_raw(ClassifierStateSnapshot, data)
    fast, slow = render_state(model, 5, raw), render_state(model, 5)
    assert json.loads(fast.body) == json.loads(slow.body)
    assert fast.tracks[f"{2:032x}"]["yaw"] == 0.0


def test_statistic_follows_the_mode() -> None:
    e = _entry(1, "dynamic")
    assert render_state(_snap([e], mode="chi2"), 0).tracks[e.track_id]["statistic"] == 6.0
    assert render_state(_snap([e], mode="velocity_threshold"), 0).tracks[e.track_id]["statistic"] == 3.0


def test_diff_states_reports_appear_vanish_and_flip() -> None:
    a = render_state(_snap([_entry(1, "static"), _entry(2, "static"), _entry(3, "undecided")], seq=1), 0)
    b = render_state(_snap([_entry(1, "static"), _entry(2, "dynamic"), _entry(4, "undecided")], seq=2), 0)
    changes = {c["id"][-1]: (c["from"], c["to"]) for c in diff_states(a, b)}
    assert changes == {"2": ("static", "dynamic"), "3": ("undecided", None), "4": (None, "undecided")}
    assert diff_states(b, b) == []
    assert len(diff_states(None, a)) == 3


# ----------------------------------------------------------------------------------------- metrics


def test_aggregate_by_class_state_has_every_series() -> None:
    agg = aggregate_by_class_state([{"class": "car", "state": "static"}, {"class": "car", "state": "static"}])
    assert len(agg) == len(LABEL_NAMES) * 3 and agg[("car", "static")] == 2 and sum(agg.values()) == 2


def test_latency_histogram_is_cumulative_in_seconds() -> None:
    assert latency_histogram({"frames_processed": 3}) is None
    h = latency_histogram({"frame_latency_ms.bucket.1": 2, "frame_latency_ms.bucket.5": 3,
                           "frame_latency_ms.bucket.inf": 1, "frame_latency_ms.sum_us": 12000,
                           "frame_latency_ms.count": 6, "frame_latency_ms.bucket.x": 9})
    assert h is not None
    assert h.buckets == [(0.001, 2), (0.005, 5), (math.inf, 6)]
    assert h.count == 6 and h.sum_s == pytest.approx(0.012)


# ----------------------------------------------------------------------------------------- bind policy


@pytest.mark.parametrize("host", ["127.0.0.1", "127.0.0.2", "::1", "localhost", "[::1]"])
def test_loopback_binds_need_no_token(host: str) -> None:
    assert is_loopback(host)
    assert bind_refusal(host, None) is None


@pytest.mark.parametrize("host", ["0.0.0.0", "::", "10.1.2.3", "192.168.0.10", "no-such-host.invalid"])
def test_non_loopback_binds_need_a_token(host: str) -> None:
    reason = bind_refusal(host, None)
    assert reason is not None and "JG_API_TOKEN" in reason and "\n" not in reason
    assert bind_refusal(host, "secret") is None


def test_sse_frame_format() -> None:
    frame = format_event(7, "changes", {"a": [1, 2]}).decode()
    assert frame == 'id: 7\nevent: changes\ndata: {"a":[1,2]}\n\n'
    with pytest.raises(ValueError):
        format_event(1, "x", {"v": float("nan")})


@pytest.mark.parametrize("body", [{"velocity_threshold": False}, {"alpha_default": "1.5"}, {"window_size": "10"},
                                  {"window_size": True}, {"window_size": 10.5}, {"alpha_per_class": {"car": "1"}},
                                  {"jump_veto": 0}, {"jump_veto": "true"}])
def test_http_models_take_only_the_json_types_they_document(body: dict) -> None:
    """No lax coercion at the HTTP boundary: ``false`` is not 0 m/s, ``"10"`` is not a window size, ``0`` is not
    ``false`` (schemathesis found the last one)."""
    for model in (ConfigModel, ConfigPatchModel):
        with pytest.raises(ValidationError) as exc:
            model.model_validate(body)
        assert exc.value.errors()[0]["loc"][0] == next(iter(body))


def test_json_integers_may_be_written_as_integral_floats() -> None:
    assert ConfigModel.model_validate({"window_size": 12.0, "alpha_default": 2}).window_size == 12


def test_refusals_since_counts_what_rose_over_the_window_from_the_beat_at_its_start() -> None:
    """Heartbeats at 1 Hz: the base is the newest beat at least the window old, so what rose before it is not
    counted; a counter that fell (the service restarted) counts from 0; one that did not rise is left out."""
    beats = [(t, {"invalid": v, "rejected.points": 7}) for t, v in ((0.0, 3), (5.0, 10), (12.0, 14), (20.0, 25))]
    assert refusals_since(beats, now=20.0, window_s=10.0) == {"invalid": 15}  # 25 - 10 (the beat at 5 s)
    assert refusals_since(beats[:2], now=5.0, window_s=10.0) == {"invalid": 7}  # young: from the oldest kept
    assert refusals_since(beats[:1], now=0.0, window_s=10.0) == {}
    restarted = [(0.0, {"rejected.detections": 900}), (1.0, {"rejected.detections": 4, "invalid": 0})]
    assert refusals_since(restarted, now=1.0, window_s=10.0) == {"rejected.detections": 4}


def test_refusal_counts_keep_only_refusals_and_at_most_sixteen_of_them() -> None:
    counters = {"published": 9, "invalid": 2, "rejected": 5, "over_limit.points": 1,
                **{f"rejected.k{i:02d}": i for i in range(40)}}
    kept = refusal_counts(counters)
    assert "published" not in kept and "rejected" not in kept and "over_limit.points" not in kept
    assert len(kept) == 16 and kept["invalid"] == 2 and kept["rejected.k00"] == 0


def test_a_refusal_warning_names_the_service_the_total_and_the_counters() -> None:
    msg = refusal_warning("ros2-in", {"invalid": 40, "rejected.sensing/lidar": 2}, 10.0)
    assert msg.startswith("ros2-in refused 42 messages in the last 10 s (invalid +40, rejected.sensing/lidar +2)")
    assert "jitterguard logs ros2-in" in msg
