"""Configuration files: the shipped defaults and JSON schemas match their pydantic models, the presets load, and
``--config`` takes a flat file or Autoware's ``ros__parameters`` form through the one loader."""

from __future__ import annotations

import json

import pytest
import yaml

from jitterguard.config import ConfigError, load, param_file, presets, read_params, schema_file
from jitterguard.config.generate import expected_files
from jitterguard.services.classifier.config import ClassifierParams
from jitterguard.services.detector.config import PRESETS as DETECTOR_PRESETS
from jitterguard.services.detector.config import DetectorConfig, DetectorParams
from jitterguard.services.tracker.config import TrackerConfig


def test_checked_in_defaults_and_schemas_are_what_the_models_generate() -> None:
    stale = [str(p) for p, text in expected_files().items() if not p.is_file() or p.read_text() != text]
    assert not stale, f"run `python -m jitterguard.config.generate` and commit: {stale}"


@pytest.mark.parametrize(("service", "model"), [("tracker", TrackerConfig), ("classifier", ClassifierParams),
                                                ("detector", DetectorParams)])
def test_each_default_file_is_its_model_defaults_and_validates_against_its_schema(service, model) -> None:
    import jsonschema

    values = read_params(param_file(service))
    assert load(model, param_file(service)) == load(model)  # the file holds exactly the defaults
    doc = yaml.safe_load(param_file(service).read_text())
    assert list(doc) == ["/**"] and list(doc["/**"]) == ["ros__parameters"]  # Autoware's layout
    jsonschema.validate(values, json.loads(schema_file(service).read_text()))


@pytest.mark.parametrize(("service", "bad"), [("classifier", {"alpha_per_class": {"cat": 1.0}}),
                                              ("classifier", {"dynamic_hold_s_per_class": {"lorry": 1.0}}),
                                              ("tracker", {"max_dist_matrix": [1.0, 2.0, 3.0]})])
def test_the_schemas_refuse_what_the_models_refuse(service, bad) -> None:
    """The schemas had taken a per-class map keyed by any name and a matrix of any length, which the models refuse:
    an editor validating a file against them said it was fine."""
    import jsonschema

    schema = json.loads(schema_file(service).read_text())
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(bad, schema)
    model = ClassifierParams if service == "classifier" else TrackerConfig
    with pytest.raises(ValueError):
        model(**bad)


def test_shipped_presets_load_and_differ_where_they_should() -> None:
    assert presets("classifier") == ["authors", "autoware-sustain", "hold", "paper"]
    assert presets("detector") == ["lite", "paper"]
    authors = load(ClassifierParams, service="classifier", preset="authors")
    assert authors.alpha_per_class["pedestrian"] == 1.28
    paper = load(ClassifierParams, service="classifier", preset="paper")  # the paper's statistic, whole
    assert (paper.alpha_per_class, paper.effective_n, paper.calibration, paper.min_speed_mps) == ({}, "cluster",
                                                                                                  "off", 0.0)
    assert paper.window_size == 10 and authors.window_size == ClassifierParams().window_size == 20  # ten cycles
    sustain = load(ClassifierParams, service="classifier", preset="autoware-sustain")
    assert sustain.sustain_for(1) == 2.0 and sustain.sustain_for(7) == 1.0  # car, pedestrian
    hold = load(ClassifierParams, service="classifier", preset="hold")
    assert hold.hold_for(1) == 0.3 and hold.hold_for(7) == 0.3 and hold.sustain_for(1) == 0.0
    assert hold.window_size == 10  # the window the hold was chosen and validated with
    assert DETECTOR_PRESETS["paper"].grid_size == (512, 512) and DETECTOR_PRESETS["lite"].grid_size == (256, 256)
    for name in ("lite", "paper"):
        assert DetectorConfig.model_validate(read_params(param_file("detector", name))) == DETECTOR_PRESETS[name]
    with pytest.raises(ConfigError, match="unknown classifier preset 'fast'; expected one of authors, autoware-sustain, hold, paper"):
        load(ClassifierParams, service="classifier", preset="fast")


@pytest.mark.parametrize("wrap", [lambda d: d, lambda d: {"/**": {"ros__parameters": d}},
                                  lambda d: {"tracker_node": {"ros__parameters": d}}])
def test_config_takes_a_flat_file_or_the_ros_parameters_form(tmp_path, wrap) -> None:
    p = tmp_path / "t.param.yaml"
    p.write_text(yaml.safe_dump(wrap({"confirm_hits": 5, "limits": {"max_objects": 100}})))
    cfg = load(TrackerConfig, p)
    assert cfg.confirm_hits == 5 and cfg.limits.max_objects == 100
    assert cfg.limits.max_payload_bytes == TrackerConfig().limits.max_payload_bytes  # one key of a mapping tuned


def test_a_per_class_map_in_a_file_tunes_its_classes_over_the_layer_below_and_empty_clears_it(tmp_path) -> None:
    """Without a preset a file's ``alpha_per_class: {pedestrian: 1.5}`` had replaced the default map (every vehicle
    fell from 2.58 to alpha_default without a word) while under a preset it merged; a file's ``{}`` under the hold
    preset had been ignored. One rule now: entries over what is below, ``{}`` clears."""
    one = tmp_path / "one.yaml"
    one.write_text("alpha_per_class: {pedestrian: 1.5}\n")
    for preset in (None, "authors"):
        cfg = load(ClassifierParams, one, service="classifier", preset=preset)
        assert cfg.alpha_per_class["pedestrian"] == 1.5 and cfg.alpha_per_class["car"] == 2.58, preset
    cfg = load(ClassifierParams, one, service="classifier", preset="paper")  # the paper's map is empty
    assert cfg.alpha_per_class == {"pedestrian": 1.5}
    off = tmp_path / "off.yaml"
    off.write_text("dynamic_hold_s_per_class: {}\nalpha_per_class: {}\n")
    cfg = load(ClassifierParams, off, service="classifier", preset="hold")
    assert cfg.dynamic_hold_s_per_class == {} and cfg.hold_for(1) == 0.0 and cfg.alpha_per_class == {}


def test_a_bad_file_names_the_file_and_the_key(tmp_path) -> None:
    p = tmp_path / "c.yaml"
    p.write_text("windw_size: 5\n")
    with pytest.raises(ConfigError, match=r"c.yaml: windw_size: Extra inputs are not permitted"):
        load(ClassifierParams, p)
    p.write_text("limits: {max_objects: 0}\n")
    with pytest.raises(ConfigError, match="limits.max_objects"):
        load(ClassifierParams, p)
    p.write_text("[1, 2]\n")
    with pytest.raises(ConfigError, match="expected a mapping"):
        load(DetectorParams, p)
    with pytest.raises(ConfigError, match="not found"):
        load(DetectorParams, tmp_path / "nope.yaml")
    with pytest.raises(ConfigError, match=f"^{tmp_path}: not a file$"):  # a folder is there, not missing
        load(DetectorParams, tmp_path)


@pytest.mark.parametrize(("text", "says"), [
    ("max_candidates: " + "9" * 5000, "a value cannot be read"),  # Python reads no int of > 4300 digits
    ("confirm_hits: 2024-02-30", "day is out of range"),  # a date YAML resolves, no calendar holds
    ("max_candidates: !!int 1.5", "a value cannot be read"),  # an explicit tag it cannot convert
    ("max_candidates: " + "[" * 30000 + "]" * 30000, "nested too deeply"),
])
def test_a_value_yaml_parses_but_python_cannot_hold_is_a_config_error(tmp_path, text, says) -> None:
    """Each had escaped as a ValueError or RecursionError: a traceback and exit 1 from every --config option."""
    p = tmp_path / "t.yaml"
    p.write_text(text + "\n")
    with pytest.raises(ConfigError, match=f"t.yaml: .*{says}"):
        read_params(p)


def test_a_bad_value_of_an_optional_bounded_field_is_named_by_its_key_alone(tmp_path) -> None:
    """pydantic's step of an optional bounded float had been shown as part of the key (sensor_height_m.constrained-float)."""
    p = tmp_path / "d.yaml"
    p.write_text("sensor_height_m: .nan\n")
    with pytest.raises(ConfigError, match=r"d.yaml: sensor_height_m: Input should be a finite number$"):
        load(DetectorParams, p)


def test_a_file_is_read_strictly_keys_once_limits_typed_and_scalars_as_yaml_1_2(tmp_path) -> None:
    """A key given twice had let the last one win; `limits:`/`stream:` took `true` as 1 and "5" as 5; the docs'
    own `variance_floor: 1e-4` was refused as a string and `calibration: off` read as False."""
    p = tmp_path / "c.yaml"
    p.write_text("window_size: 20\nwindow_size: 30\n")
    with pytest.raises(ConfigError, match=r"c.yaml: key 'window_size' given twice \(line 2\)"):
        load(ClassifierParams, p)
    for text, kind in (("? [a, b]\n: 1\n", "list"), ("limits:\n  ? {a: 1}\n  : 2\n", "dict")):
        p.write_text(text)  # a TypeError (unhashable key) had escaped as a traceback from every --config
        with pytest.raises(ConfigError, match=rf"c.yaml: a key must be a name, got a {kind} \(line \d\)"):
            load(ClassifierParams, p)
    for text, key in (("limits:\n  max_objects: true\n", "limits.max_objects"),
                      ('limits:\n  max_objects: "5"\n', "limits.max_objects"),
                      ("stream:\n  confirm_frames: true\n", "stream.confirm_frames"),
                      ('stream:\n  max_stamp_step_s: "10"\n', "stream.max_stamp_step_s")):
        p.write_text(text)
        with pytest.raises(ConfigError, match=key):
            load(TrackerConfig, p)
    p.write_text("variance_floor: 1e-4\ncalibration: off\n")
    cfg = load(ClassifierParams, p)
    assert cfg.variance_floor == pytest.approx(1e-4) and cfg.calibration == "off"


def test_a_rule_across_fields_is_told_in_its_own_words(tmp_path) -> None:
    """Broken by flags, the rule alone (it had read 'ClassifierParams: (top level): Value error, …'); broken by a
    file, the file first."""
    with pytest.raises(ConfigError) as exc:
        load(ClassifierParams, overrides={"min_window": 30})
    assert str(exc.value) == "min_window (30) must not exceed window_size (20)"
    p = tmp_path / "c.yaml"
    p.write_text("min_window: 30\n")
    with pytest.raises(ConfigError) as exc:
        load(ClassifierParams, p)
    assert str(exc.value) == f"{p}: min_window (30) must not exceed window_size (20)"


def test_the_classifiers_process_fields_come_from_its_file_but_never_travel(tmp_path) -> None:
    """``config_store`` and ``open_config_writes`` (start-up only) are read from the parameter file; the config
    that travels on the queryable (``wire()``) has neither."""
    from jitterguard.services.classifier.config import ClassifierParams

    path = tmp_path / "c.param.yaml"
    path.write_text("/**:\n  ros__parameters:\n    config_store: /var/lib/jg/c.json\n    open_config_writes: true\n"
                    "    alpha_default: 3.0\n")
    params = load(ClassifierParams, path, service="classifier")
    assert params.config_store == "/var/lib/jg/c.json" and params.open_config_writes is True
    wire = params.wire().model_dump()
    assert wire["alpha_default"] == 3.0 and "config_store" not in wire and "open_config_writes" not in wire
