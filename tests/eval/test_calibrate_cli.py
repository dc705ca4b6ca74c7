"""`jitterguard calibrate`: a recording through the live path to a calibration file the classifier loads, and its
blocks as long as the classifier's windows on that recording's stream."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from jitterguard.cli import main
from jitterguard.services.classifier.calibration_file import read_calibration


def _calibrate(tmp_path: Path, name: str, *extra: str) -> dict:
    out = tmp_path / f"{name}.yaml"
    with pytest.raises(SystemExit) as exc:
        main(["calibrate", "synthetic:mixed", "--level", "detections", "--seed", "3", "--out", str(out), *extra])
    assert exc.value.code == 0
    read_calibration(str(out))  # the classifier's own reader takes it
    return yaml.safe_load(out.read_text())


def test_calibrate_writes_scales_from_windows_of_the_streams_span(tmp_path: Path, capsys) -> None:
    """At 10 Hz the blocks are the classifier's windows of 20; a 2 Hz recording's are 10 long, as the classifier's
    windows on it, and a 20 Hz recording's 20 observations of every second frame (2 s, as at 10 Hz); all learnt
    from the recording's tracks (blocks pooled, scales off the prior of 1)."""
    fast = _calibrate(tmp_path, "fast", "--duration", "12")
    slow = _calibrate(tmp_path, "slow", "--duration", "40", "--hz", "2")
    faster = _calibrate(tmp_path, "faster", "--duration", "12", "--hz", "20")
    assert fast["window"] == 20 and slow["window"] == 10 and faster["window"] == 20
    # the mean time between a block's observations (a track missed in a frame spans two frames)
    assert 0.1 <= fast["frame_interval_s"] < 0.15 and 0.5 <= slow["frame_interval_s"] < 0.75
    assert 0.1 <= faster["frame_interval_s"] < 0.15  # every second frame of 20 Hz, not 0.05 s
    for data in (fast, slow, faster):
        assert data["source"]["blocks"] > 0
        along = data["groups"]["vehicle"]["along"]
        assert sum(along["blocks"].values()) > 0 and any(abs(v - 1.0) > 0.05 for v in along["scale"].values())
    assert "wrote" in capsys.readouterr().out


def test_calibrate_bad_window_is_one_line_exit_2(tmp_path: Path, capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["calibrate", "synthetic:mixed", "--level", "detections", "--out", str(tmp_path / "c.yaml"),
              "--window-size", "3"])
    assert exc.value.code == 2
    assert "--window-size" in capsys.readouterr().err


@pytest.mark.parametrize(("flag", "value"), [("--hz", "0"), ("--hz", "inf"), ("--duration", "0"), ("--duration", "4000")])
def test_calibrate_names_the_one_flag_out_of_range(tmp_path: Path, capsys, flag: str, value: str) -> None:
    """One message had named both --hz and --duration, whichever was wrong."""
    with pytest.raises(SystemExit) as exc:
        main(["calibrate", "synthetic:mixed", "--level", "detections", "--out", str(tmp_path / "c.yaml"), flag, value])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    other = "--duration" if flag == "--hz" else "--hz"
    assert flag in err and other not in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "c.yaml").exists()


@pytest.mark.parametrize("gap_s", [30.0, -30.0])
def test_a_recording_that_pauses_or_rewinds_is_calibrated_across_it(gap_s: float) -> None:
    """A bag with a 30 s pause, or two recordings joined with time going back: the tracker follows once a run of
    frames confirms it, and so does the classifier — `calibrate` (and `eval`) had died with a ValueError
    because the classifier's stream guard, given a constant clock, never confirmed the run."""
    from jitterguard.eval.calibrate import calibrate_detections, recording_detections
    from jitterguard.schemas import decode, encode
    from jitterguard.schemas.models import ClassifierConfig, DetectedObjects
    from jitterguard.services.replay.sources import SourceOptions, open_source

    opts = SourceOptions(level="detections", seed=0, duration_s=12.0, rate_hz=10.0, period_ns=100_000_000)
    with open_source("synthetic:mixed", opts) as src:
        msgs = list(recording_detections(src, None, 0, None, []))
    moved = []
    for i, p in enumerate(msgs):
        if i >= len(msgs) // 2:
            d = decode(DetectedObjects, p)
            p = encode(d.model_copy(update={"header": d.header.model_copy(
                update={"stamp": d.header.stamp + int(gap_s * 1e9)})}))
        moved.append(p)
    _, seen = calibrate_detections(moved, ClassifierConfig())
    assert len(msgs) - 4 <= seen["frames"] < len(msgs) and seen["blocks"] > 50


def test_a_bag_without_poses_is_warned_about_as_the_replay_does(tmp_path: Path, capsys) -> None:
    """Calibrated on the identity pose, a moving sensor's static objects look like motion and the scales come
    out wrong: `replay` said so, `calibrate` had run silently."""
    from replay.bagfixture import DET_TOPIC, write_bag

    bag = write_bag(tmp_path / "bag", n=3)
    with pytest.raises(SystemExit):
        main(["calibrate", str(bag.path), "--topic", DET_TOPIC, "--out", str(tmp_path / "c.yaml")])
    err = capsys.readouterr().err
    assert f"jitterguard: warning: {bag.path}: no --pose-topic" in err, err


def _calibrate_fails(argv: list[str], capsys) -> str:
    with pytest.raises(SystemExit) as exc:
        main(["calibrate", *argv])
    err = capsys.readouterr().err
    assert exc.value.code == 2, err
    lines = [ln for ln in err.splitlines() if ln.startswith("jitterguard: error:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def test_calibrate_does_not_overwrite_a_file_that_is_not_a_calibration(tmp_path: Path, capsys) -> None:
    """`--out` naming a user's own file (a typo, a config) had been overwritten without a word; an earlier
    calibration file is still replaced, as a re-run expects."""
    mine = tmp_path / "classifier.param.yaml"
    mine.write_text("alpha_default: 2.58\n")
    line = _calibrate_fails(["synthetic:mixed", "--level", "detections", "--duration", "3", "--out", str(mine)],
                            capsys)
    assert "exists and is not a calibration file" in line
    assert mine.read_text() == "alpha_default: 2.58\n"
    first = _calibrate(tmp_path, "again", "--duration", "12")
    second = _calibrate(tmp_path, "again", "--duration", "12", "--seed", "4")  # --seed again: the last one wins
    assert first["source"]["blocks"] > 0 and second["source"]["blocks"] > 0


def test_calibrate_says_why_it_got_no_frame(tmp_path: Path, capsys) -> None:
    """A recording none of whose frames reads, or a --start past its end, had been told "no track stood still
    long enough ... use a longer recording"."""
    bad = tmp_path / "bad scans"
    bad.mkdir()
    (bad / "000000.bin").write_bytes(b"\x00" * 3)  # cut short (0 bytes is an empty scan)
    (bad / "000001.bin").write_bytes(b"\x00" * 7)
    line = _calibrate_fails([str(bad), "--out", str(tmp_path / "c.yaml")], capsys)
    assert "none of its 2 frame(s) read" in line and "000000.bin" in line, line
    line = _calibrate_fails(["synthetic:mixed", "--level", "detections", "--duration", "3", "--start", "500",
                             "--out", str(tmp_path / "c.yaml")], capsys)
    assert "--start 500 is past the end" in line, line
    assert not (tmp_path / "c.yaml").exists()


def test_a_recording_with_nothing_to_track_says_so(tmp_path: Path, capsys) -> None:
    """A folder of empty scans (0-byte .bin files) gives the detector nothing, one frame of detections no track: the
    refusal had been "no track stood still long enough ... use a longer recording" for both, as if tracks had been
    there and moving. Now it says what was missing (a longer recording of empty scans would not help)."""
    empty = tmp_path / "empty scans"
    empty.mkdir()
    for i in range(5):
        (empty / f"{i:06d}.bin").write_bytes(b"")
    line = _calibrate_fails([str(empty), "--out", str(tmp_path / "c.yaml"), "--threads", "1"], capsys)
    assert line.startswith(f"jitterguard: error: {empty}: no detections in any of its 5 frames"), line
    assert "no tracks to calibrate from" in line and "longer recording" not in line, line
    line = _calibrate_fails(["synthetic:mixed", "--level", "detections", "--duration", "0.1",
                             "--out", str(tmp_path / "c.yaml")], capsys)
    assert "detections in 1 frames formed no track" in line and "no tracks to calibrate from" in line, line
    assert not (tmp_path / "c.yaml").exists()


def test_a_recording_of_moving_objects_only_is_refused_for_what_it_lacks(tmp_path: Path, capsys) -> None:
    """Two objects driving at 3 m/s for 8 s: every window the tracks fill is too fast to pool. The refusal had said
    "no track stood still long enough ... use a longer recording", which no length of such a recording helps."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from replay.bagfixture import DET_TOPIC, DETECTED_OBJECTS, T0, _detections, typestore

    ts, bag = typestore(), tmp_path / "moving"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.SQLITE3) as w:
        conn = w.add_connection(DET_TOPIC, DETECTED_OBJECTS, typestore=ts)
        for i in range(80):
            t = T0 + i * 100_000_000
            msg = _detections(ts, t, [(10.0 + 0.3 * i, 2.0), (-5.0, 3.0 - 0.3 * i)])
            w.write(conn, t, ts.serialize_cdr(msg, DETECTED_OBJECTS))
    line = _calibrate_fails([str(bag), "--topic", DET_TOPIC, "--out", str(tmp_path / "c.yaml")], capsys)
    assert "track windows was of an object moving faster than 1 m/s" in line, line
    assert "use a recording that has some" in line and "longer recording" not in line, line
    assert not (tmp_path / "c.yaml").exists()


def test_eval_names_the_calibration_file_it_used_by_its_bytes(tmp_path: Path) -> None:
    """metrics.json named the detector's weights with a checksum but a calibration file only as `calibration:
    file`: a run could not say which fitted scales it was scored with."""
    import hashlib
    import json

    _calibrate(tmp_path, "cal", "--duration", "12")
    cal = tmp_path / "cal.yaml"
    with pytest.raises(SystemExit) as exc:
        main(["eval", "--scenario", "mixed", "--seed", "3", "--duration", "4", "--input", "gt-noise",
              "--calibration-file", str(cal), "--out", str(tmp_path / "o")])
    assert exc.value.code in (0, None)
    run = json.loads((tmp_path / "o" / "metrics.json").read_text())["run"]
    assert run["calibration"] == "file"
    named = f"{cal} (sha256 {hashlib.sha256(cal.read_bytes()).hexdigest()[:12]})"
    assert run["calibration_file"] == named
    assert f"calibration `file` from `{named}`" in (tmp_path / "o" / "report.md").read_text()


def test_a_file_fitted_on_few_blocks_is_written_with_a_warning(tmp_path: Path, capsys) -> None:
    """The classifier applies a file's scales in full (no prior tempers them there), and a file fitted from a
    handful of blocks had been written without a word: now a warning says how few and what to do. Two parked cars
    for 8 s give a few windows; the synthetic street's 40-odd tracks give enough and no warning."""
    import numpy as np
    from rosbags.rosbag2 import StoragePlugin, Writer

    from replay.bagfixture import DET_TOPIC, DETECTED_OBJECTS, T0, _detections, typestore

    rng = np.random.default_rng(5)
    ts, bag = typestore(), tmp_path / "two-cars"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.SQLITE3) as w:
        conn = w.add_connection(DET_TOPIC, DETECTED_OBJECTS, typestore=ts)
        for i in range(80):
            t = T0 + i * 100_000_000
            jx, jy = rng.normal(0.0, 0.05, 2)
            msg = _detections(ts, t, [(10.0 + jx, 2.0 + jy), (-5.0 - jy, 3.0 + jx)])
            w.write(conn, t, ts.serialize_cdr(msg, DETECTED_OBJECTS))
    out = tmp_path / "c.yaml"
    with pytest.raises(SystemExit) as exc:
        main(["calibrate", str(bag), "--topic", DET_TOPIC, "--out", str(out)])
    err = capsys.readouterr().err
    blocks = yaml.safe_load(out.read_text())["source"]["blocks"]
    assert exc.value.code == 0 and 0 < blocks < 20, (blocks, err)
    assert f"only {blocks} blocks (fewer than the prior's 20)" in err, err
    enough = _calibrate(tmp_path, "street", "--duration", "3")
    assert enough["source"]["blocks"] >= 20 and "blocks (fewer than" not in capsys.readouterr().err
