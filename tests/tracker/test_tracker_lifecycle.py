"""Track lifecycle rules: confirmation by hits per class and by existence, final confirmation, never a tentative
track in the output."""

from __future__ import annotations

import numpy as np
import pytest

from jitterguard.config import ConfigError
from jitterguard.services.tracker.config import default_config, load_config
from jitterguard.services.tracker.core import TrackerCore
from jitterguard.services.tracker.arrays import DetectionFrame
from jitterguard.bench.tracker_sequences import CAR, PED

DT = 0.1
T0 = 1_700_000_000_000_000_000


def frame(seq: int, xy: list[list[float]], labels: list[int], existence: list[float]) -> DetectionFrame:
    a = np.asarray(xy, dtype=float).reshape(-1, 2)
    dims = np.array([(0.6, 0.6) if lb == PED else (4.5, 1.9) for lb in labels]).reshape(-1, 2)
    return DetectionFrame(seq=seq, stamp_ns=T0 + seq * int(DT * 1e9), ego_x=0.0, ego_y=0.0, ego_yaw=0.0,
                          x=a[:, 0], y=a[:, 1], yaw=np.zeros(len(a)), label=np.asarray(labels),
                          length=dims[:, 0], width=dims[:, 1],
                          existence=np.asarray(existence, dtype=float))


def test_a_recurring_low_score_detection_stays_tentative_and_is_never_published() -> None:
    cfg = default_config()
    assert cfg.confirm_min_existence > 0.12
    core = TrackerCore(cfg)
    for k in range(40):  # a clutter return in the same place every frame, scored 0.12
        res = core.step(frame(k, [[10.0, 0.0], [-20.0, 5.0]], [CAR, CAR], [0.12, 0.9]))
        assert all(core.tracks.confirmed[core.tracks.row_of()[t]] for t in res.tracks.ids)
        if k >= cfg.confirm_hits - 1:
            assert len(res.tracks) == 1 and res.tracks.x[0] == pytest.approx(-20.0, abs=0.5)
    assert len(core.tracks) == 2  # the low one is kept alive (tentative), just never published


def test_existence_gate_off_confirms_on_hits_alone() -> None:
    core = TrackerCore(default_config(confirm_min_existence=0.0))
    for k in range(3):
        res = core.step(frame(k, [[10.0, 0.0]], [CAR], [0.12]))
    assert len(res.tracks) == 1


def test_confirmation_is_final_when_the_score_drops() -> None:
    core = TrackerCore(default_config())
    scores = [0.9] * 3 + [0.05] * 20
    ids = []
    for k, s in enumerate(scores):
        res = core.step(frame(k, [[10.0 + 0.5 * k * DT, 0.0]], [CAR], [s]))
        ids.append(tuple(res.tracks.ids))
    assert ids[:2] == [(), ()]
    assert len(set(ids[2:])) == 1 and len(ids[2]) == 1  # the same ID every frame once confirmed


def test_per_class_confirm_hits_override_the_global_one(tmp_path) -> None:
    path = tmp_path / "t.yaml"
    path.write_text("confirm_hits: 2\nclasses:\n  pedestrian:\n    confirm_hits: 5\n")
    cfg = load_config(path)
    core = TrackerCore(cfg)
    first_seen: dict[int, int] = {}
    for k in range(8):
        res = core.step(frame(k, [[10.0, 0.0], [0.0, 15.0]], [CAR, PED], [0.9, 0.9]))
        for lbl in res.tracks.label.tolist():
            first_seen.setdefault(int(lbl), k)
    assert first_seen == {CAR: 1, PED: 4}


def test_bad_lifecycle_values_are_rejected(tmp_path) -> None:
    path = tmp_path / "t.yaml"
    path.write_text("confirm_min_existence: 1.5\n")
    with pytest.raises(ConfigError, match="confirm_min_existence"):
        load_config(path)
    path.write_text("classes:\n  car:\n    confirm_hits: 0\n")
    with pytest.raises(ConfigError, match="confirm_hits"):
        load_config(path)
