"""The jitter-band study's criteria, its --seeds and the alpha-from-labels preset (no runs)."""

from __future__ import annotations

import json

import pytest

from jitterguard.cli import main
from jitterguard.eval import cli as eval_cli
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


def test_study_seeds_take_ranges_as_every_other_command(monkeypatch, tmp_path) -> None:
    """``eval-study --seeds`` reads ``2000-2009`` and ``1,2,5-7`` as every other ``--seeds`` does (it had taken a
    comma list only, and refused a range); each run pools the same seeds."""
    veh = {"ap_z": 0.99, "ap_speed": 0.98, "false_dynamic_z": 0.0, "false_dynamic_speed": 0.1,
           "missed_dynamic_z": 0.0, "missed_dynamic_speed": 0.0, "n_static": 5, "n_dynamic": 3}
    pooled: list[tuple[int, tuple[int, ...]]] = []

    def fake_evaluate(out, *, seed, noise, extra_seeds, **_):  # the study's bookkeeping, not its minutes of runs
        pooled.append((seed, tuple(extra_seeds)))
        return {"run": {"noise": noise}, "motion": {"vehicle": veh, "pedestrian": veh}}

    monkeypatch.setattr(eval_cli, "evaluate", fake_evaluate)
    with pytest.raises(SystemExit) as exc:
        main(["eval-study", "--out", str(tmp_path / "st"), "--seeds", "2000-2002,2005", "--json"])
    assert exc.value.code in (0, None)
    assert pooled and set(pooled) == {(2000, (2001, 2002, 2005))}
    assert json.loads((tmp_path / "st" / "study.json").read_text())["seeds"] == [2000, 2001, 2002, 2005]
