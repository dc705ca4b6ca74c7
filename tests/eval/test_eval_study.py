"""The jitter-band study's criteria and the alpha-from-labels preset (pure functions, no runs)."""

from __future__ import annotations

from jitterguard.eval.cli import labels_preset
from jitterguard.eval.study import check_jitter_band, check_parity, study_markdown, summarize
from jitterguard.schemas.models import ClassifierConfig


def test_parity_criterion() -> None:
    assert check_parity({"ap_z": 0.95, "ap_speed": 0.94}) is True
    assert check_parity({"ap_z": 0.95, "ap_speed": 0.90}) is False
    assert check_parity({"ap_z": None, "ap_speed": 0.9}) is None


def test_jitter_band_criterion() -> None:
    base = {"false_dynamic_z": 0.01, "false_dynamic_speed": 0.1, "missed_dynamic_z": 0.05,
            "missed_dynamic_speed": 0.04}
    assert check_jitter_band(base) is True
    assert check_jitter_band({**base, "false_dynamic_z": 0.03}) is False  # > 20 % of the threshold's
    assert check_jitter_band({**base, "missed_dynamic_z": 0.07}) is False  # > 2 points more misses
    assert check_jitter_band({**base, "missed_dynamic_z": None}) is None


def test_summary_and_markdown() -> None:
    veh = {"ap_z": 0.99, "ap_speed": 0.98, "false_dynamic_z": 0.0, "false_dynamic_speed": 0.1,
           "missed_dynamic_z": 0.0, "missed_dynamic_speed": 0.0, "n_static": 5, "n_dynamic": 3}
    ped = {"ap_z": 1.0, "ap_speed": 1.0, "missed_dynamic_z": 0.0, "missed_dynamic_speed": 0.0}
    res = {"a/clean": {"run": {"noise": "clean"}, "motion": {"vehicle": veh, "pedestrian": ped}},
           "a/jittery": {"run": {"noise": "jittery"}, "motion": {"vehicle": {**veh, "false_dynamic_z": 0.05},
                                                                  "pedestrian": ped}}}
    s = summarize(res)
    assert s["a/clean"]["met"] is True and s["a/jittery"]["met"] is False
    md = study_markdown(s)
    assert md.count("\n") == 4 and all(line.count("|") == 10 for line in md.splitlines())


def test_labels_preset_is_a_valid_config() -> None:
    p = labels_preset({"vehicle": 2.345, "pedestrian": 1.1, "bicycle": None})
    cfg = ClassifierConfig.model_validate({**ClassifierConfig().model_dump(), **p})
    assert cfg.alpha_for(1) == 2.35 and cfg.alpha_for(4) == 2.35 and cfg.alpha_for(7) == 1.1
    assert cfg.alpha_for(6) == cfg.alpha_for(5) == 1.96  # no labels for cycles (motorcycles among them): default
