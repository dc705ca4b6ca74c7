"""The offline pipeline end to end: determinism, both classifier rules on identical inputs, the CLI's files."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from jitterguard.cli import main
from jitterguard.eval.pipeline import NOISE_PRESETS, run_pipeline
from jitterguard.schemas.models import ClassifierConfig
from jitterguard.services.classifier.core import DYNAMIC, JUMP_VETO_MIN_VEHICLE, STATIC, UNDECIDED
from jitterguard.sim.world import make_scenario
from helpers import NUSC

GROUP_KEYS = ("ap_z", "ap_speed", "false_dynamic_z", "false_dynamic_speed", "missed_dynamic_z",
              "missed_dynamic_speed", "n_static", "n_dynamic")


@pytest.fixture(scope="module")
def records():
    sc = make_scenario("parking-street", 3, duration_s=5.0, rate_hz=10.0)
    return run_pipeline(sc, NOISE_PRESETS["jittery"](), 3, ClassifierConfig())


def test_pipeline_is_deterministic(records) -> None:
    again = run_pipeline(make_scenario("parking-street", 3, duration_s=5.0, rate_hz=10.0),
                         NOISE_PRESETS["jittery"](), 3, ClassifierConfig())
    for k, v in records.__dict__.items():
        if isinstance(v, np.ndarray):
            np.testing.assert_array_equal(v, getattr(again, k), err_msg=k)
    other = run_pipeline(make_scenario("parking-street", 3, duration_s=5.0, rate_hz=10.0),
                         NOISE_PRESETS["jittery"](), 4, ClassifierConfig())
    assert len(other) != len(records) or not np.array_equal(other.z, records.z)


def test_both_rules_decide_identical_rows(records) -> None:
    assert len(records) > 100
    assert (records.gt_instance >= 0).mean() > 0.8  # most tracks sit on a real object
    decided = records.window >= records.min_window
    z_dyn = records.state_z == DYNAMIC
    # the test decides where its score exceeds α; a window the jump veto called static scores 0 (static at every α),
    # and only a window the test rejected is ever vetoed: a vehicle's from JUMP_VETO_MIN_VEHICLE observations
    np.testing.assert_array_equal(z_dyn[decided], records.z[decided] > records.alpha[decided])
    vehicle_veto = records.vetoed & (records.track_group == "vehicle")
    assert records.vetoed.any() and (records.window[vehicle_veto] >= JUMP_VETO_MIN_VEHICLE).all()
    assert (records.window[records.vetoed & ~vehicle_veto] == records.window_size).all()
    assert (records.z[records.vetoed] == 0).all() and (records.state_z[records.vetoed] == STATIC).all()
    assert (records.state_z[~decided] == UNDECIDED).all()
    np.testing.assert_array_equal(records.state_v == DYNAMIC, records.speed > records.speed_threshold)
    # Autoware's per-class thresholds: 1.0 m/s for cars, 0.28 for pedestrians
    assert set(np.unique(records.speed_threshold[records.label == 1])) == {1.0}
    assert set(np.unique(records.speed_threshold[records.label == 7])) <= {0.28}
    assert set(np.unique(records.state_v)) <= {STATIC, DYNAMIC}
    # GT labels are both present in this scenario (parked cars, moving traffic)
    veh = records.group == "vehicle"
    assert records.gt_dynamic[veh].any() and (~records.gt_dynamic[veh]).any()


def test_chi2_mode_is_scored_as_the_test_that_decides(records) -> None:
    """``mode: chi2`` puts the χ² test in the z-test's place: its records' ``z`` (the normal score of χ²) exceeds α
    exactly where it called a window dynamic, so rates, α sweeps and PR curves score the χ² decisions; on the same
    tracks it decides differently from max(z_x, z_y) somewhere, and the speed threshold's rows are untouched."""
    chi = run_pipeline(make_scenario("parking-street", 3, duration_s=5.0, rate_hz=10.0),
                       NOISE_PRESETS["jittery"](), 3, ClassifierConfig(mode="chi2"))
    decided = chi.window >= chi.min_window
    np.testing.assert_array_equal((chi.state_z == DYNAMIC)[decided], chi.z[decided] > chi.alpha[decided])
    np.testing.assert_array_equal(chi.state_v, records.state_v)
    np.testing.assert_array_equal(chi.window, records.window)
    assert (chi.state_z != records.state_z).any()


def test_eval_cli_mode_chi2_and_a_bad_mode(tmp_path: Path, capsys) -> None:
    out = tmp_path / "ev"
    with pytest.raises(SystemExit) as exc:
        main(["eval", "--scenario", "parking-street", "--seed", "1", "--duration", "5", "--mode", "chi2",
              "--out", str(out)])
    assert exc.value.code == 0
    assert json.loads((out / "metrics.json").read_text())["run"]["mode"] == "chi2"
    assert "χ² test" in (out / "report.md").read_text()
    with pytest.raises(SystemExit) as exc:
        main(["eval", "--scenario", "parking-street", "--mode", "velocity_threshold", "--out", str(out)])
    assert exc.value.code == 2
    assert "--mode" in capsys.readouterr().err


def test_cli_writes_report_metrics_and_figures(tmp_path: Path, capsys) -> None:
    out = tmp_path / "ev"
    with pytest.raises(SystemExit) as exc:
        main(["eval", "--scenario", "parking-street", "--seed", "1", "--duration", "5", "--noise", "clean",
              "--input", "gt-noise", "--out", str(out), "--json"])
    assert exc.value.code == 0
    printed = json.loads(capsys.readouterr().out)
    on_disk = json.loads((out / "metrics.json").read_text())
    assert printed == on_disk
    for g in ("vehicle", "pedestrian"):
        for k in GROUP_KEYS:
            assert k in on_disk["motion"][g], (g, k)
    assert on_disk["motion"]["vehicle"]["ap_z"] > 0.9  # clean noise: motion is easy to see
    for name in ("report.md", "speed_vs_z.png", "pr_curves.png", "alpha_sweep.png", "calibration.png"):
        assert (out / name).stat().st_size > 0
    assert "| vehicle |" in (out / "report.md").read_text()
    for block in ("ghost", "matched", "by_attribute", "full_window", "calibration"):
        assert on_disk[block], block
    assert set(on_disk["ghost"]) == {"vehicle", "pedestrian", "bicycle"}
    assert set(on_disk["ghost"]["vehicle"]) >= {"false_dynamic_z", "false_dynamic_speed", "n", "ci90"}
    ci = on_disk["motion"]["vehicle"]["ci90"]
    for key in ("ap_z", "ap_speed", "false_dynamic_z", "false_dynamic_speed", "missed_dynamic_z",
                "missed_dynamic_speed"):
        assert ci[key] is None or ci[key][0] <= on_disk["motion"]["vehicle"][key] <= ci[key][1], key
    assert on_disk["by_attribute"]["vehicle.parked"]["missed_dynamic_z"] is None
    assert on_disk["run"]["calibration"] == "online" and on_disk["run"]["effective_n"] == "measured"
    assert on_disk["run"]["tracker_measurement_scale"] == "off"


def _eval_runs(tmp_path: Path, capsys, source: list[str], **variants: list[str]) -> dict[str, dict]:
    """metrics.json of one `eval` of ``source`` (its flags) per variant (name → extra flags), each in
    tmp_path/name."""
    runs = {}
    for name, extra in variants.items():
        with pytest.raises(SystemExit) as exc:
            main(["eval", *source, "--out", str(tmp_path / name), "--json", *extra])
        assert exc.value.code == 0
        runs[name] = json.loads(capsys.readouterr().out)
    return runs


def _short_mixed_runs(tmp_path: Path, capsys, **variants: list[str]) -> dict[str, dict]:
    """metrics.json of one short `mixed` run per variant (name → extra eval flags), each in tmp_path/name."""
    return _eval_runs(tmp_path, capsys, ["--scenario", "mixed", "--seed", "5", "--duration", "8"], **variants)


def test_cli_takes_a_tracker_parameter_file(tmp_path: Path, capsys) -> None:
    """`--tracker-config` runs the tracker as that file says (here its measurement scale switched on): the run
    says so, and the tracks, hence the speed rule's rows, are not those of the shipped file."""
    cfg = tmp_path / "tracker.yaml"
    cfg.write_text("measurement_scale: online\n")
    runs = _short_mixed_runs(tmp_path, capsys, shipped=[], online=["--tracker-config", str(cfg)])
    assert runs["online"]["run"]["tracker_measurement_scale"] == "online"
    assert runs["online"]["motion"]["vehicle"] != runs["shipped"]["motion"]["vehicle"]


def test_cli_hold_preset_holds_the_z_test_only(tmp_path: Path, capsys) -> None:
    """`--preset hold` holds the z-test's dynamic calls 0.3 s over the window of 10 it was chosen with: the run
    says so, the z-test calls no more static rows dynamic and catches moving objects no sooner than the same
    window at once, and the speed rule's figures are untouched."""
    runs = _short_mixed_runs(tmp_path, capsys, **{"at-once": ["--window-size", "10"], "hold": ["--preset", "hold"]})
    now, held = runs["at-once"], runs["hold"]
    assert held["run"]["dynamic_hold_s_per_class"]["car"] == 0.3 and now["run"]["dynamic_hold_s_per_class"] == {}
    assert held["run"]["window_size"] == now["run"]["window_size"] == 10
    assert "held {" in (tmp_path / "hold" / "report.md").read_text()
    for g in ("vehicle", "pedestrian"):
        a, b = now["motion"][g], held["motion"][g]
        for k in ("false_dynamic_speed", "missed_dynamic_speed", "time_to_dynamic_s_median_speed"):
            assert a[k] == b[k], (g, k)
        assert b["false_dynamic_z"] <= a["false_dynamic_z"] and b["missed_dynamic_z"] >= a["missed_dynamic_z"]
        assert b["time_to_dynamic_s_median_z"] >= a["time_to_dynamic_s_median_z"]
    assert held["motion"]["vehicle"] != now["motion"]["vehicle"]  # the hold changed something


def test_cli_window_size_sets_the_window_and_the_default_is_20(tmp_path: Path, capsys) -> None:
    """`--window-size 10` runs the paper's window: the run says so, full windows are those of 10 observations,
    and the z-test's figures differ from the default window of 20 on the same tracks (the speed rule's do not)."""
    runs = _short_mixed_runs(tmp_path, capsys, default=[], ten=["--window-size", "10"])
    assert runs["default"]["run"]["window_size"] == 20 and runs["ten"]["run"]["window_size"] == 10
    a, b = runs["default"]["motion"]["vehicle"], runs["ten"]["motion"]["vehicle"]
    assert a["false_dynamic_speed"] == b["false_dynamic_speed"] and a["missed_dynamic_speed"] == b["missed_dynamic_speed"]
    assert (a["false_dynamic_z"], a["missed_dynamic_z"]) != (b["false_dynamic_z"], b["missed_dynamic_z"])
    assert runs["ten"]["full_window"]["vehicle"]["n_static"] > runs["default"]["full_window"]["vehicle"]["n_static"]


def test_cli_a_slow_stream_gets_the_window_of_its_span(tmp_path: Path, capsys) -> None:
    """At 2 Hz the default window (20 observations at 10 Hz) holds 10 — the run says so and its every figure is
    the fixed window of 10's — and `--fixed-window` keeps 20 observations (10 s) whatever the rate."""
    slow = ["--rate", "2", "--duration", "25"]
    runs = _short_mixed_runs(tmp_path, capsys, default=slow, ten=[*slow, "--window-size", "10", "--fixed-window"],
                             fixed=[*slow, "--fixed-window"])
    assert runs["default"]["run"]["window_size"] == 10 and runs["default"]["run"]["window_reference_hz"] == 10.0
    assert runs["default"]["run"]["window_stride"] == 1
    assert runs["fixed"]["run"]["window_size"] == 20 and runs["fixed"]["run"]["window_reference_hz"] is None
    assert runs["default"]["motion"] == runs["ten"]["motion"]
    assert runs["default"]["calibration"] == runs["ten"]["calibration"]
    assert runs["default"]["motion"]["vehicle"] != runs["fixed"]["motion"]["vehicle"]


def test_cli_a_fast_stream_takes_every_kth_frame(tmp_path: Path, capsys) -> None:
    """At 20 Hz the default window takes every second frame (the 2 s of 20 observations at 10 Hz): the run and its
    report say so; `--fixed-window` takes every frame (1 s), and the z-test's figures are not the same."""
    fast = ["--rate", "20"]
    runs = _short_mixed_runs(tmp_path, capsys, default=fast, fixed=[*fast, "--fixed-window"])
    assert (runs["default"]["run"]["window_size"], runs["default"]["run"]["window_stride"]) == (20, 2)
    assert (runs["fixed"]["run"]["window_size"], runs["fixed"]["run"]["window_stride"]) == (20, 1)
    assert "window 20 observations, one every 2 frames" in (tmp_path / "default" / "report.md").read_text()
    assert "one every" not in (tmp_path / "fixed" / "report.md").read_text()
    a, b = runs["default"]["motion"]["vehicle"], runs["fixed"]["motion"]["vehicle"]
    assert (a["false_dynamic_z"], a["missed_dynamic_z"]) != (b["false_dynamic_z"], b["missed_dynamic_z"])


@pytest.mark.skipif(not NUSC.is_dir(), reason="../shared/data/nuscenes-scene-0523 absent")
def test_cli_real_key_frames_get_the_window_of_their_span(tmp_path: Path, capsys) -> None:
    """nuScenes' 2 Hz key frames: the default window holds 10 observations there (the span of 20 at 10 Hz, floored
    at the paper's 10) and scores exactly as a fixed window of 10 — rates, calibration and all."""
    runs = _eval_runs(tmp_path, capsys, ["--nuscenes", str(NUSC), "--input", "gt-noise", "--noise", "clean"],
                      default=[], ten=["--window-size", "10", "--fixed-window"])
    assert runs["default"]["run"]["window_size"] == 10
    assert "window 10 observations (window_size at 10 Hz" in (tmp_path / "default" / "report.md").read_text()
    fixed = (tmp_path / "ten" / "report.md").read_text()
    assert "window 10 observations" in fixed and "window_size at" not in fixed
    for block in ("motion", "full_window", "ghost", "by_attribute", "calibration"):
        assert runs["default"][block] == runs["ten"][block], block


@pytest.mark.parametrize("argv", [
    ["--window-size", "1"],
    ["--window-size", "65"],
    ["--input", "detector", "--noise", "clean"],
    ["--input", "lidar"],
    ["--noise", "loud"],
    ["--scenario", "moon"],
    ["--nuscenes", "/nonexistent/dataroot"],
    ["--variance-scale", "-1"],
    ["--calibration", "sometimes"],
    ["--calibration", "file"],
    ["--calibration-file", "/nonexistent/cal.yaml"],
    ["--effective-n", "many"],
    ["--tracker-config", "/nonexistent/tracker.yaml"],
    ["--view-slide", "-1"],
])
def test_cli_bad_input_is_one_line_exit_2(tmp_path: Path, capsys, argv: list[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["eval", "--out", str(tmp_path / "x"), *argv])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    if "detector" in argv:
        assert "--noise applies to --input gt-noise" in err
    if argv == ["--calibration", "file"]:  # had said "classifier config: Value error, …", naming no flag
        assert err.startswith("jitterguard: error: --calibration file: needs --calibration-file"), err


@pytest.mark.skipif(not NUSC.is_dir(), reason="../shared/data/nuscenes-scene-0523 absent")
def test_nuscenes_scene_loads_and_scores(tmp_path: Path) -> None:
    from jitterguard.eval.groundtruth import load_nuscenes_frames
    from jitterguard.eval.metrics import compute_metrics

    name, frames = load_nuscenes_frames(NUSC)
    assert name == "scene-0523" and len(frames) >= 30
    f = frames[0]
    assert f.num_objects > 0 and (f.sizes[:, 0] >= f.sizes[:, 1] - 1e-6).mean() > 0.8  # (length, width, h)
    rec = run_pipeline(frames, NOISE_PRESETS["clean"](), 0, ClassifierConfig())
    m = compute_metrics(rec)
    assert m["vehicle"]["n_static"] > 0 and m["vehicle"]["n_dynamic"] > 0
    assert m["vehicle"]["ap_z"] is not None and m["vehicle"]["ap_z"] > 0.8


@pytest.mark.skipif(not NUSC.is_dir(), reason="../shared/data/nuscenes-scene-0523 absent")
def test_each_nuscenes_box_carries_its_own_visibility() -> None:
    """The noise model scales a box's error by its visibility: each box gets its annotation's bin (read with an
    independent reader: the tables as plain JSON), not one value for all (until 3 Dec every box read 0.9)."""
    import json
    from collections import Counter

    from jitterguard.eval.groundtruth import VISIBILITY_FRACTION, load_nuscenes_frames

    _, frames = load_nuscenes_frames(NUSC)
    table = NUSC / "v1.0-mini"
    level = {v["token"]: v["level"] for v in json.loads((table / "visibility.json").read_text())}
    first = sorted(json.loads((table / "scene.json").read_text()), key=lambda s: s["name"])[0]["first_sample_token"]
    anns = [a for a in json.loads((table / "sample_annotation.json").read_text()) if a["sample_token"] == first]
    got = Counter(np.round(frames[0].visibility, 3).tolist())
    want = Counter(VISIBILITY_FRACTION[level[a["visibility_token"]]] for a in anns)
    assert len(got) > 1  # the scene's first frame holds boxes of several bins
    assert sum(got.values()) <= sum(want.values()) and all(got[v] <= want[v] for v in got)


@pytest.mark.skipif(not NUSC.is_dir(), reason="../shared/data/nuscenes-scene-0523 absent")
def test_an_annotated_box_that_returned_nothing_is_never_detected() -> None:
    """Annotators interpolate a box through the frames its object is hidden in (scene-0523: 1,016 of 2,625 boxes
    hold no LiDAR return; one construction vehicle drifts 6.9 m that way). The noise model stands for a LiDAR
    detector, so it detects only boxes with a return, as nuScenes' own evaluation keeps only those; the counts are
    the table's ``num_lidar_pts`` (read here with an independent reader: the tables as plain JSON)."""
    import json
    from collections import Counter

    from jitterguard.eval.groundtruth import load_nuscenes_frames
    from jitterguard.sim import DetectionModel

    _, frames = load_nuscenes_frames(NUSC)
    table = NUSC / "v1.0-mini"
    first = sorted(json.loads((table / "scene.json").read_text()), key=lambda s: s["name"])[0]["first_sample_token"]
    anns = [a for a in json.loads((table / "sample_annotation.json").read_text()) if a["sample_token"] == first]
    f = frames[0]
    assert f.points_counted
    got, want = Counter(f.num_points.tolist()), Counter(a["num_lidar_pts"] for a in anns)
    assert all(got[k] <= want[k] for k in got) and got[0] > 0 and sum(got.values()) > got[0]
    counted = uncounted = 0
    for fr in frames:
        seen = DetectionModel(NOISE_PRESETS["clean"](), 0).detect(fr).gt_index
        in_range = np.hypot(fr.centers[:, 0] - fr.ego_x, fr.centers[:, 1] - fr.ego_y) <= NOISE_PRESETS["clean"]().max_range_m
        assert sorted(seen.tolist()) == np.flatnonzero((fr.num_points >= 1) & in_range).tolist()  # clean misses none
        counted += len(seen)
        uncounted += len(DetectionModel(replace(NOISE_PRESETS["clean"](), use_point_counts=False), 0).detect(fr).gt_index)
    assert uncounted > counted  # without the counts the hidden boxes come back


def _scene_copy(root: Path) -> Path:
    """scene-0523's tables copied under ``root`` (to be broken by a test), its scans linked."""
    import shutil

    shutil.copytree(NUSC / "v1.0-mini", root / "v1.0-mini")
    (root / "samples").symlink_to(NUSC / "samples")
    return root


@pytest.mark.skipif(not NUSC.is_dir(), reason="../shared/data/nuscenes-scene-0523 absent")
@pytest.mark.parametrize("damage", ["loop", "dangling attribute", "cut neighbour"])
def test_broken_nuscenes_tables_are_one_line_errors_or_read_as_far_as_they_go(tmp_path: Path, damage: str) -> None:
    """A sample chain that loops back would have grown without end; a token no table holds was a KeyError
    traceback; a box whose neighbour was cut out of the table (a scene extracted from a larger set) has no
    velocity there, as at a track's ends."""
    import json

    from jitterguard.eval.detector_input import nuscenes_scans
    from jitterguard.eval.groundtruth import NuScenesError, load_nuscenes_frames

    root = _scene_copy(tmp_path / "nusc")
    tables = root / "v1.0-mini"

    def edit(name: str, change) -> None:
        rows = json.loads((tables / f"{name}.json").read_text())
        change(rows)
        (tables / f"{name}.json").write_text(json.dumps(rows))

    if damage == "loop":
        def loop(scenes):
            scenes[0]["last_sample_token"] = "nowhere"  # the chain's end is never met ...
        edit("scene", loop)
        first = json.loads((tables / "scene.json").read_text())[0]["first_sample_token"]
        edit("sample", lambda rows: [r.update(next=first) for r in rows if not r["next"]])  # ... and it loops
        with pytest.raises(NuScenesError, match="loops back"):
            load_nuscenes_frames(root)
    elif damage == "dangling attribute":
        edit("sample_annotation", lambda rows: [r.update(attribute_tokens=["deadbeef"]) for r in rows])
        with pytest.raises(NuScenesError, match="deadbeef"):
            load_nuscenes_frames(root)
    else:
        cut: list[str] = []

        def drop_one(rows):
            victim = next(r for r in rows if r["prev"] and r["next"])
            cut.append(victim["token"])
            rows.remove(victim)
        edit("sample_annotation", drop_one)
        _, frames = load_nuscenes_frames(root)
        scans = nuscenes_scans(root, None, frames)  # the detector's loader: was a KeyError on the cut token
        assert len(scans) == len(frames) and cut


def test_pooled_runs_keep_tracks_apart(records) -> None:
    from jitterguard.eval.pipeline import concat_records

    pooled = concat_records([records, records], ["0", "1"])
    assert len(pooled) == 2 * len(records)
    n_tracks = len(np.unique(records.track_id))
    assert len(np.unique(pooled.track_id)) == 2 * n_tracks  # same IDs in both runs, never merged
    np.testing.assert_array_equal(pooled.z[: len(records)], records.z)


def _vehicle_rates(scale: float, at: str = "classifier") -> tuple[float, float]:
    """Pooled full-window vehicle false- and missed-dynamic rates of the z-test, honest noise, every reported
    variance ×``scale`` (in what the classifier receives: the tracks are identical); two seeds of one drive
    (the calibration carries over)."""
    from jitterguard.eval.metrics import planner_metrics
    from jitterguard.eval.pipeline import concat_records
    from jitterguard.services.classifier.calibration import OnlineCalibration

    cfg = ClassifierConfig()
    drive = OnlineCalibration(tuple(cfg.calibration_range_bands_m), cfg.calibration_prior_blocks,
                              cfg.calibration_half_life_s, cfg.window_size)
    parts = [run_pipeline(make_scenario("mixed", s, 15.0, 10.0), NOISE_PRESETS["jittery"](), s, cfg,
                          calibration=drive, variance_scale=scale, variance_scale_at=at) for s in (40, 41)]
    m = planner_metrics(concat_records(parts, ["40", "41"]), intervals=False)["full_window"]["vehicle"]
    return m["false_dynamic_z"], m["missed_dynamic_z"]


@pytest.mark.slow
def test_variance_scale_quarter_or_four_moves_vehicle_rates_by_at_most_one_point() -> None:
    """The issue's acceptance: a detector whose every variance is off by ×¼ or ×4 leaves the z-test's vehicle
    false- and missed-dynamic rates (rows whose window has filled) within 1 point of the unscaled run — the
    classifier is invariant to its detector's calibration error. Scaled in what the classifier receives, so
    the tracks are the same; at the detector's output the tracker's gates change the tracks themselves
    (docs/results.md measures both)."""
    fd1, md1 = _vehicle_rates(1.0)
    for scale in (0.25, 4.0):
        fd, md = _vehicle_rates(scale)
        assert abs(fd - fd1) <= 0.01, (scale, fd, fd1)
        assert abs(md - md1) <= 0.01, (scale, md, md1)
    # without calibration the same scaling moves the false-dynamic rate by far more than a point
    off = ClassifierConfig(calibration="off")
    rates = []
    for scale in (0.25, 1.0):
        rec = run_pipeline(make_scenario("mixed", 40, 15.0, 10.0), NOISE_PRESETS["jittery"](), 40, off,
                           variance_scale=scale, variance_scale_at="classifier")
        from jitterguard.eval.metrics import planner_metrics

        rates.append(planner_metrics(rec, intervals=False)["full_window"]["vehicle"]["false_dynamic_z"])
    # 4.4 points with the jump veto (it weighs the window's shape, not its variances), over 5 without it
    assert rates[0] - rates[1] > 0.03


def test_detections_without_covariance_are_tested_with_the_trackers_and_calibrated() -> None:
    """A detector that reports no position covariance (``--variance-scale 0``; Autoware's lidar_centerpoint):
    the classifier receives the tracker's measurement covariance for each such detection and calibrates it, so its
    full-window static vehicles are called moving at under half the speed threshold's rate. (When the zero was
    floored at 1 cm instead, 14 % of them were, against the threshold's 9 %.)"""
    from jitterguard.eval.metrics import planner_metrics
    from jitterguard.eval.pipeline import DetectionModel, scale_variances
    from jitterguard.schemas import encode, read_detected_objects, wire

    rec = run_pipeline(make_scenario("mixed", 40, 15.0, 10.0), NOISE_PRESETS["jittery"](), 40, ClassifierConfig(),
                       variance_scale=0.0)
    v = planner_metrics(rec, intervals=False)["full_window"]["vehicle"]
    assert v["false_dynamic_z"] <= 0.5 * v["false_dynamic_speed"], v
    assert v["missed_dynamic_z"] <= v["missed_dynamic_speed"] + 0.03, v
    # what --variance-scale 0 sends: no covariance at all
    frames = make_scenario("mixed", 40, 2.0, 10.0)
    det = read_detected_objects(encode(DetectionModel(NOISE_PRESETS["jittery"](), 40).detect(next(iter(frames)))
                                       .detections))
    dropped = scale_variances(det, 0.0).objects
    assert len(dropped) and (dropped[wire.HAS_POSITION_COV] == 0xC2).all()
    assert not dropped[wire.POSE_COV]["v"].any() and (det.objects[wire.HAS_POSITION_COV] == 0xC3).all()


def test_cli_jump_veto_counts_the_rows_it_turned_and_nothing_else_moves(tmp_path: Path, capsys) -> None:
    """metrics.json's ``run.vetoed_rows`` says what the jump veto did: it only turns rows the test rejected to
    static, so without it (``--no-jump-veto``) each group's z-test false-dynamic rate is the veto's static rows
    higher and its missed rate the veto's moving rows lower, to the row; the speed rule is untouched."""
    runs = _short_mixed_runs(tmp_path, capsys, on=[], off=["--no-jump-veto"])
    on, off = runs["on"], runs["off"]
    assert on["run"]["jump_veto"] is True and off["run"]["jump_veto"] is False
    assert all(v == 0 for g in off["run"]["vetoed_rows"].values() for v in g.values())
    veto = on["run"]["vetoed_rows"]
    assert veto["vehicle"]["static"] > 0  # parked cars' re-placed boxes
    report = (tmp_path / "on" / "report.md").read_text()
    assert f"jump veto (rows it turned static: vehicle {veto['vehicle']['static']} static" in report
    assert "jump veto" not in (tmp_path / "off" / "report.md").read_text()
    for g in ("vehicle", "pedestrian"):
        a, b = on["motion"][g], off["motion"][g]
        assert a["false_dynamic_speed"] == b["false_dynamic_speed"] and a["n_static"] == b["n_static"]
        if a["n_static"]:
            assert a["false_dynamic_z"] * a["n_static"] == pytest.approx(
                b["false_dynamic_z"] * b["n_static"] - veto[g]["static"], abs=1e-5 * a["n_static"] + 1e-9)
        if a["n_dynamic"]:
            assert a["missed_dynamic_z"] * a["n_dynamic"] == pytest.approx(
                b["missed_dynamic_z"] * b["n_dynamic"] + veto[g]["moving"], abs=1e-5 * a["n_dynamic"] + 1e-9)


def test_cli_view_slide_only_ever_lowers_the_vehicle_statistic(tmp_path: Path, capsys) -> None:
    """`--view-slide 0` switches the view term off: the run says which, the speed rule's figures are untouched, and
    the term (a positive semi-definite addition to the denominator) calls no more vehicle rows dynamic than none —
    fewer static ones wrongly, no fewer moving ones missed; pedestrians are not touched. The lot: an ego driving past
rows of parked cars, where the term acts."""
    runs = _eval_runs(tmp_path, capsys, ["--scenario", "diagonal-lot", "--seed", "5", "--duration", "8"],
                      default=[], off=["--view-slide", "0"], wide=["--view-slide", "6"])
    on, off, wide = runs["default"], runs["off"], runs["wide"]
    assert on["run"]["view_slide_m_per_class"] == {"car": 2.0, "truck": 2.0, "bus": 2.0, "trailer": 2.0}
    assert off["run"]["view_slide_m_per_class"] == {} and wide["run"]["view_slide_m_per_class"]["bus"] == 6.0
    assert "view term {" in (tmp_path / "default" / "report.md").read_text()
    for a, b in ((off, on), (on, wide)):
        v, w = a["motion"]["vehicle"], b["motion"]["vehicle"]
        for k in ("false_dynamic_speed", "missed_dynamic_speed"):
            assert v[k] == w[k], k
        assert w["false_dynamic_z"] <= v["false_dynamic_z"]
        assert (v["missed_dynamic_z"] is None) == (w["missed_dynamic_z"] is None)  # no movers: null on both sides
        assert v["missed_dynamic_z"] is None or w["missed_dynamic_z"] >= v["missed_dynamic_z"]
        assert a["motion"]["pedestrian"] == b["motion"]["pedestrian"]
    assert wide["motion"]["vehicle"]["false_dynamic_z"] < off["motion"]["vehicle"]["false_dynamic_z"]  # it acts


def test_a_rerun_into_the_same_folder_leaves_no_figure_of_the_earlier_run(tmp_path: Path, capsys) -> None:
    """`eval --out o` then `eval --out o --calibration off`: the first run's calibration.png stayed beside the
    second run's report and metrics, and "wrote … 4 figures" counted it (the second drew 3)."""
    out = tmp_path / "ev"
    (tmp_path / "ev").mkdir()
    (out / "notes.png").write_bytes(b"\x89PNG a user's own picture")  # not ours: neither counted nor touched
    base = ["eval", "--scenario", "parking-street", "--seed", "1", "--duration", "3", "--noise", "clean",
            "--out", str(out)]
    for extra, figures in (([], 4), (["--calibration", "off"], 3)):
        with pytest.raises(SystemExit) as exc:
            main(base + extra)
        assert exc.value.code == 0
        assert f"metrics.json and {figures} figures" in capsys.readouterr().out
    assert not (out / "calibration.png").exists()
    assert "calibration.png" not in (out / "report.md").read_text()
    assert json.loads((out / "metrics.json").read_text())["run"]["calibration"] == "off"
    assert (out / "notes.png").read_bytes() == b"\x89PNG a user's own picture"


def test_a_ghost_track_is_told_what_it_stands_on() -> None:
    """A track matched to no object stands on the nearest labelled object that is no road user within 1 m (a
    barrier, a cone, a pile of debris), else on nothing labelled; a matched track on nothing at all."""
    from jitterguard.eval.pipeline import NOTHING_LABELLED, ghost_footing

    f = replace(make_scenario("parking-street", 0).frame(0),
                unscored=(("movable_object.trafficcone", 10.0, 2.0), ("movable_object.debris", 30.0, -1.0)))
    xy = np.array([[10.4, 2.3], [30.0, -2.1], [50.0, 0.0], [10.2, 2.0]])  # 0.5, 1.1 m off: on the cone, by the debris
    got = ghost_footing(xy, np.array([-1, -1, -1, 3]), f)
    assert got.tolist() == ["movable_object.trafficcone", NOTHING_LABELLED, NOTHING_LABELLED, ""]
    assert ghost_footing(xy[:1], np.array([-1]), make_scenario("parking-street", 0).frame(0)).tolist() == [
        NOTHING_LABELLED]


@pytest.mark.skipif(not NUSC.is_dir(), reason="../shared/data/nuscenes-scene-0523 absent")
def test_nuscenes_objects_that_are_no_road_user_are_kept_unscored_and_ghosts_report_them(tmp_path: Path) -> None:
    """The loader keeps every annotation of a category that is no road user (barriers, cones, debris) as the
    frame's ``unscored`` objects, at its annotated place (read here with an independent reader: the tables as
    plain JSON), never among the scored boxes; ``ghost.<group>.on`` splits the ghost rows by what they stand on
    and adds up to them."""
    from jitterguard.eval.groundtruth import load_nuscenes_frames, nuscenes_label
    from jitterguard.eval.metrics import planner_metrics

    _, frames = load_nuscenes_frames(NUSC)
    table = NUSC / "v1.0-mini"
    cats = {c["token"]: c["name"] for c in json.loads((table / "category.json").read_text())}
    inst = {i["token"]: cats[i["category_token"]] for i in json.loads((table / "instance.json").read_text())}
    first = sorted(json.loads((table / "scene.json").read_text()), key=lambda s: s["name"])[0]["first_sample_token"]
    anns = [a for a in json.loads((table / "sample_annotation.json").read_text()) if a["sample_token"] == first]
    want = sorted((inst[a["instance_token"]], round(a["translation"][0], 6), round(a["translation"][1], 6))
                  for a in anns if nuscenes_label(inst[a["instance_token"]]) is None)
    got = sorted((c, round(x, 6), round(y, 6)) for c, x, y in frames[0].unscored)
    assert got == want and len(want) > 5 and {c for c, _, _ in got} >= {"movable_object.barrier"}
    assert frames[0].num_objects == len(anns) - len(want)
    rec = run_pipeline(frames, NOISE_PRESETS["jittery"](), 0, ClassifierConfig())
    for g, m in planner_metrics(rec)["ghost"].items():
        assert sum(w["n"] for w in m["on"].values()) == m["n"], g
        assert all("ci90" in w for w in m["on"].values()), g  # few rows: each rate with its interval
