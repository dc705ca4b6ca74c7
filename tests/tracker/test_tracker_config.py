"""The shipped association matrices are Autoware's, and user files override them strictly."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from jitterguard.config import ConfigError
from jitterguard.services.tracker.config import default_config, dump_config, load_config

# Autoware's data_association_matrix.param.yaml, row CAR (tracker) — spelled out here on purpose
AUTOWARE_CAR_ROW = {
    "can_assign_matrix": [0, 1, 1, 1, 1, 0, 0, 0],
    "max_dist_matrix": [4.0, 2.0, 5.0, 5.0, 5.0, 1.0, 1.0, 1.0],
    "max_area_matrix": [12.10, 12.10, 36.00, 40.00, 3600.00, 10000.00, 10000.00, 10000.00],
    "min_area_matrix": [3.600, 3.600, 6.000, 10.000, 10.000, 0.000, 0.000, 0.000],
    "max_rad_matrix": [3.150, 1.047, 1.047, 1.047, 1.047, 3.150, 3.150, 3.150],
}


def test_defaults_are_autowares() -> None:
    cfg = default_config()
    for key, row in AUTOWARE_CAR_ROW.items():
        assert getattr(cfg, key)[8:16] == pytest.approx(row), key
    assert cfg.mahalanobis_gate == pytest.approx(3.035)
    assert cfg.score_threshold == pytest.approx(0.01)
    t = cfg.tables()
    assert t.max_dist[7, 7] == 2.0 and t.max_dist[7, 0] == 2.0 and t.max_area[7, 7] == 1.0
    assert t.can_assign[0, 0] and not t.can_assign[0, 1]


def test_autoware_ros_parameters_file_loads_as_is(tmp_path: Path) -> None:
    rows = ", ".join(["0.5"] * 64)
    (tmp_path / "aw.yaml").write_text(
        "/**:\n  ros__parameters:\n"
        f"    max_dist_matrix: [{rows}]\n"
        f"    min_iou_matrix: [{rows}]\n"
    )
    cfg = load_config(tmp_path / "aw.yaml")
    assert cfg.max_dist_matrix == [0.5] * 64
    assert cfg.can_assign_matrix == default_config().can_assign_matrix  # keys not given keep the defaults


def test_partial_class_override_keeps_other_fields(tmp_path: Path) -> None:
    (tmp_path / "c.yaml").write_text("classes:\n  pedestrian:\n    r_long: 0.9\nconfirm_hits: 5\n")
    cfg = load_config(tmp_path / "c.yaml", measurement_covariance="class")
    assert cfg.classes["pedestrian"].r_long == 0.9
    assert cfg.classes["pedestrian"].q_acc == default_config().classes["pedestrian"].q_acc
    assert cfg.classes["car"].model == "ctrv"
    assert cfg.confirm_hits == 5 and cfg.measurement_covariance == "class"


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("max_dist_matrix: [1, 2, 3]\n", "at least 64 items"),
        ("can_assign_matrix: [" + ", ".join(["2"] * 64) + "]\n", "0 or 1"),
        ("mahalanobis_gate: -1\n", "mahalanobis_gate"),
        ("measurement_covariance: magic\n", "measurement_covariance"),
        ("classes:\n  spaceship: {}\n", "unknown class"),
        ("bogus_key: 1\n", "bogus_key"),
        ("min_area_matrix: [" + ", ".join(["20000"] * 64) + "]\n", "min_area_matrix exceeds"),
        ("[1, 2\n", "not valid YAML"),
        ("- 1\n- 2\n", "mapping"),
        ("observe_tentative: 1\n", "observe_tentative"),  # strict types: no 1 for true, no "3" for 3
        ("confirm_hits: '3'\n", "confirm_hits"),
        ("classes:\n  car: {q_acc: yes}\n", "q_acc"),
    ],
)
def test_bad_config_is_one_clear_error(tmp_path: Path, text: str, needle: str) -> None:
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=needle):
        load_config(p)


def test_missing_file_is_an_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.yaml")


def test_dumped_config_loads_back_identically(tmp_path: Path) -> None:
    cfg = load_config(None, measurement_covariance="class")
    (tmp_path / "dump.yaml").write_text(dump_config(cfg))
    again = load_config(tmp_path / "dump.yaml")
    assert again == cfg
    assert np.array_equal(again.tables().max_area, cfg.tables().max_area)
