"""An audit's cross-check: metrics.json's rates on a real pipeline run equal their documented definitions, computed
here row by row in plain Python (not with the evaluator's functions), and no label reaches the classifier."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from jitterguard.eval.metrics import compute_metrics, planner_metrics
from jitterguard.eval.pipeline import NOISE_PRESETS, run_pipeline
from jitterguard.schemas.models import ClassifierConfig
from jitterguard.sim.world import make_scenario

STATIC, DYNAMIC = 1, 2
VEHICLE_LABELS, CYCLE_LABELS, PEDESTRIAN, MOTORCYCLE = {1, 2, 3, 4}, {5, 6}, 7, 5


def _frames(seed: int = 2000):
    return list(make_scenario("mixed", seed, duration_s=6.0, rate_hz=10.0))


@pytest.fixture(scope="module")
def run():
    rec = run_pipeline(_frames(), NOISE_PRESETS["jittery"](), 2000, ClassifierConfig())
    rows = [dict(tid=str(rec.track_id[i]), label=int(rec.label[i]), z=float(rec.z[i]), speed=float(rec.speed[i]),
                 win=int(rec.window[i]), sz=int(rec.state_z[i]), sv=int(rec.state_v[i]), inst=int(rec.gt_instance[i]),
                 dyn=bool(rec.gt_dynamic[i]), grp=str(rec.group[i]), alpha=float(rec.alpha[i]),
                 thr=float(rec.speed_threshold[i]), attr=str(rec.gt_attribute[i])) for i in range(len(rec))]
    return rec, rows, {"motion": compute_metrics(rec), **planner_metrics(rec)}


def _group(label: int) -> str:
    return ("vehicle" if label in VEHICLE_LABELS else "bicycle" if label in CYCLE_LABELS
            else "pedestrian" if label == PEDESTRIAN else "")


def _frac(rows, pred):
    return None if not rows else sum(1 for r in rows if pred(r)) / len(rows)


def _same(mine, theirs) -> bool:
    return (mine is None and theirs is None) or (mine is not None and theirs is not None and abs(mine - theirs) < 2e-6)


def test_the_rows_decide_as_documented(run) -> None:
    """Baseline: dynamic iff speed > the class's threshold (1.0 m/s car/truck/bus/trailer and motorcycle, as
    Autoware's static_obstacle_avoidance.param.yaml; 0.28 the others; no
    sustain by default); z-test: dynamic iff max(z_x, z_y) > the class's α once the window can decide."""
    _, rows, _ = run
    for r in rows:
        assert r["thr"] == (1.0 if r["label"] in VEHICLE_LABELS | {MOTORCYCLE} else 0.28)
        assert (r["sv"] == DYNAMIC) == (r["speed"] > r["thr"])
        if r["win"] >= 2:
            assert (r["sz"] == DYNAMIC) == (r["z"] > r["alpha"])


def test_rates_ghosts_attributes_and_nulls_equal_their_definitions(run) -> None:
    _, rows, m = run
    for g in ("vehicle", "pedestrian", "bicycle"):
        scored = [r for r in rows if r["inst"] >= 0 and r["grp"] == g and r["win"] >= 2]
        st, dy = [r for r in scored if not r["dyn"]], [r for r in scored if r["dyn"]]
        mine = {"n_static": len(st), "n_dynamic": len(dy),
                "false_dynamic_z": _frac(st, lambda r: r["sz"] == DYNAMIC),
                "false_dynamic_speed": _frac(st, lambda r: r["sv"] == DYNAMIC),
                "missed_dynamic_z": _frac(dy, lambda r: r["sz"] != DYNAMIC),
                "missed_dynamic_speed": _frac(dy, lambda r: r["sv"] != DYNAMIC)}
        for k, v in mine.items():
            assert _same(v, m["motion"][g][k]), (g, k, v, m["motion"][g][k])
        ghosts = [r for r in rows if r["inst"] < 0 and _group(r["label"]) == g and r["win"] >= 2]
        assert m["ghost"][g]["n"] == len(ghosts)
        assert _same(_frac(ghosts, lambda r: r["sz"] == DYNAMIC), m["ghost"][g]["false_dynamic_z"])
        assert _same(_frac(ghosts, lambda r: r["sv"] == DYNAMIC), m["ghost"][g]["false_dynamic_speed"])
    attrs = {r["attr"] for r in rows if r["inst"] >= 0 and r["grp"] and r["win"] >= 2} - {""}
    assert set(m["by_attribute"]) == attrs
    for a in attrs:
        sel = [r for r in rows if r["inst"] >= 0 and r["grp"] and r["win"] >= 2 and r["attr"] == a]
        st, dy = [r for r in sel if not r["dyn"]], [r for r in sel if r["dyn"]]
        assert m["by_attribute"][a]["n"] == len(sel)
        assert _same(_frac(st, lambda r: r["sz"] == DYNAMIC), m["by_attribute"][a]["false_dynamic_z"])
        assert _same(_frac(dy, lambda r: r["sv"] != DYNAMIC), m["by_attribute"][a]["missed_dynamic_speed"])


def test_matched_is_the_lowest_cut_within_the_other_rules_false_alarms(run) -> None:
    """Brute force over every cut: the lowest one whose false-dynamic rate (score > cut) is within the other rule's."""
    _, rows, m = run

    def missed_at(st, dy, target):
        if target is None or not st or not dy:
            return None
        cut = next(t for t in sorted(set(st) | set(dy) | {-math.inf})
                   if sum(s > t for s in st) / len(st) <= target + 1e-12)
        return sum(s <= cut for s in dy) / len(dy)

    for g in ("vehicle", "pedestrian", "bicycle"):
        scored = [r for r in rows if r["inst"] >= 0 and r["grp"] == g and r["win"] >= 2]
        st, dy = [r for r in scored if not r["dyn"]], [r for r in scored if r["dyn"]]
        zs, vs = (lambda r: r["z"] / r["alpha"]), (lambda r: r["speed"] / r["thr"])
        fdv, fdz = _frac(st, lambda r: r["sv"] == DYNAMIC), _frac(st, lambda r: r["sz"] == DYNAMIC)
        assert _same(missed_at([zs(r) for r in st], [zs(r) for r in dy], fdv),
                     m["matched"][g]["missed_dynamic_z_at_speed_false_dynamic"])
        assert _same(missed_at([vs(r) for r in st], [vs(r) for r in dy], fdz),
                     m["matched"][g]["missed_dynamic_speed_at_z_false_dynamic"])


def test_intervals_resample_tracks_and_zero_rates_get_clopper_pearson(run) -> None:
    """A track-level bootstrap is wider than a row-level one on this run (rows of a track move together), and a
    rate of 0 reads [0, 1 − 0.05^(1/tracks)]."""
    rec, rows, m = run
    st = [r for r in rows if r["inst"] >= 0 and r["grp"] == "vehicle" and r["win"] >= 2 and not r["dyn"]]
    lo, hi = m["motion"]["vehicle"]["ci90"]["false_dynamic_speed"]
    hits = np.array([r["sv"] == DYNAMIC for r in st], float)
    rng = np.random.default_rng(1)
    row_lo, row_hi = np.percentile([hits[rng.integers(0, len(hits), len(hits))].mean() for _ in range(400)], [5, 95])
    assert hi - lo > row_hi - row_lo
    zeros = 0
    for g, block in m["motion"].items():
        scored = [r for r in rows if r["inst"] >= 0 and r["grp"] == g and r["win"] >= 2]
        for key, dyn in (("false_dynamic_z", False), ("false_dynamic_speed", False), ("missed_dynamic_z", True),
                         ("missed_dynamic_speed", True)):
            if block[key] == 0.0:
                n_tracks = len({r["tid"] for r in scored if r["dyn"] == dyn})
                assert block["ci90"][key] == [0.0, round(1.0 - 0.05 ** (1.0 / n_tracks), 6)], (g, key)
                zeros += 1
    assert zeros  # this run has rates of 0 (vehicle false_dynamic_z among them)


def test_no_label_reaches_the_classifier() -> None:
    """Flipping every motion attribute and moving flag of the ground truth changes the labels of the rows and not
    one decision, statistic or speed."""
    frames = _frames(2001)
    flip = {"vehicle.parked": "vehicle.moving", "vehicle.moving": "vehicle.parked", "vehicle.stopped": "vehicle.moving",
            "pedestrian.moving": "pedestrian.standing", "pedestrian.standing": "pedestrian.moving",
            "cycle.with_rider": "cycle.without_rider", "cycle.without_rider": "cycle.with_rider"}
    flipped = [dataclasses.replace(f, attributes=tuple(flip.get(a, a) for a in f.attributes), moving=~f.moving)
               for f in frames]
    a, b = (run_pipeline(fr, NOISE_PRESETS["jittery"](), 2001, ClassifierConfig()) for fr in (frames, flipped))
    assert (a.gt_dynamic != b.gt_dynamic).any()
    for k in ("track_id", "z", "speed", "state_z", "state_v", "window", "alpha"):
        assert np.array_equal(getattr(a, k), getattr(b, k)), k
