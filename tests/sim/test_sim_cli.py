"""``jitterguard sim`` and ``jitterguard bench sim``: outputs, files, and one-line errors with exit 2."""

from __future__ import annotations

import errno
import json
import os

import pytest
from typer.testing import CliRunner

from jitterguard.cli import app

runner = CliRunner()


def run(*args: str):
    return runner.invoke(app, list(args))


def test_list_names_scenarios_and_sensors() -> None:
    r = run("sim", "list")
    assert r.exit_code == 0
    out = json.loads(r.stdout)
    assert out["scenarios"] == ["parking-street", "diagonal-lot", "intersection", "mixed", "loading-street",
                                "perpendicular-lot", "screened-lot"]
    assert out["sensors"]["hdl32e"]["beams"] == 32


def test_generate_writes_ground_truth_lines(tmp_path) -> None:
    path = tmp_path / "gt.jsonl"
    r = run("sim", "generate", "parking-street", "--seed", "2", "--duration", "1", "--rate", "5", "--out", str(path),
            "--lidar", "vlp16", "--no-progress")
    assert r.exit_code == 0, r.output
    summary = json.loads(r.stdout)
    assert summary["frames"] == 5 and summary["attributes"]["vehicle.parked"] > 0
    lines = [json.loads(x) for x in path.read_text().splitlines()]
    assert len(lines) == 5 and lines[0]["objects"][0]["category"].count(".") >= 1
    assert any(o["num_points"] > 0 for o in lines[0]["objects"])


def test_export_and_bev_write_files(tmp_path) -> None:
    root = tmp_path / "nusc"
    r = run("sim", "export", "diagonal-lot", str(root), "--duration", "1", "--rate", "2", "--no-progress")
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["tables"]["sample"] == 2
    assert len(list((root / "samples" / "LIDAR_TOP").glob("*.pcd.bin"))) == 2
    again = run("sim", "export", "diagonal-lot", str(root), "--duration", "1")
    assert again.exit_code == 2 and "already holds" in again.output
    png = tmp_path / "bev.png"
    r = run("sim", "bev", "intersection", "--frame", "3", "--duration", "1", "--out", str(png))
    assert r.exit_code == 0, r.output
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("args, message", [
    (("sim", "generate", "highway"), "unknown scenario"),
    (("sim", "generate", "mixed", "--duration", "0"), "--duration"),
    (("sim", "generate", "mixed", "--rate", "-1"), "--rate"),
    (("sim", "bev", "mixed", "--out", "x.jpg"), ".png"),
    (("sim", "bev", "mixed", "--out", "x.png", "--frame", "99999"), "--frame"),
    (("sim", "export", "mixed", "/tmp/x", "--lidar", "hdl64"), "--lidar"),
    (("sim", "export", "mixed", "/tmp/x", "--duration", "0.4", "--rate", "2"), "no whole frame"),
    (("sim", "generate", "mixed", "--duration", "1", "--rate", "0.5"), "no whole frame"),
    (("sim", "bev", "mixed", "--out", "x.png", "--duration", "0.05"), "no whole frame"),
    (("bench", "sim", "--scans", "0"), "--scans"),
])
def test_bad_input_is_one_line_and_exit_2(args, message) -> None:
    r = run(*args)
    assert r.exit_code == 2
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and message in lines[0] and lines[0].startswith("jitterguard: error:")


def test_bench_prints_json() -> None:
    r = run("bench", "sim", "--json", "--scans", "2", "--repeat", "1", "--objects", "10", "--replay-scans", "20")
    assert r.exit_code == 0, r.output
    out = json.loads(r.stdout)
    rc, rp = out["raycast"], out["replay"]
    assert rc["sensor"] == "hdl32e" and rc["rays"] == 34720 and rc["objects"] == 10
    assert rc["scans_per_s"] > 0
    assert rp["points_per_scan"] == 35_000 and rp["dropped"] == 0 and rp["scans_per_s"] > 0


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full")
def test_generate_to_a_full_device_is_one_line_and_exit_2() -> None:
    """A write that fails (here at the flush on close) is one line and exit 2, not an OSError traceback."""
    r = run("sim", "generate", "parking-street", "--duration", "2", "--out", "/dev/full", "--no-progress")
    assert r.exit_code == 2, r.output
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("jitterguard: error: --out: cannot write /dev/full")


def test_a_write_failing_halfway_leaves_the_old_file_and_no_partial_one(tmp_path, monkeypatch) -> None:
    """Ground truth goes to a temporary file renamed over --out only when complete: a disk that fills on the
    third frame leaves the previous file as it was and no truncated one (nor the temporary file) behind."""
    from jitterguard.sim import cli as sim_cli

    path = tmp_path / "gt.jsonl"
    previous = '{"seq": 0, "stamp_ns": 0, "objects": []}\n'  # an earlier run's ground truth
    path.write_text(previous)

    class FillsUp:
        """A file whose third write finds the disk full."""

        def __init__(self, fh):
            self.fh, self.writes = fh, 0

        def write(self, text):
            self.writes += 1
            if self.writes == 3:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            return self.fh.write(text)

        def __getattr__(self, name):
            return getattr(self.fh, name)

    monkeypatch.setattr(sim_cli, "open", lambda *a, **k: FillsUp(open(*a, **k)), raising=False)
    r = run("sim", "generate", "mixed", "--seed", "1", "--duration", "1", "--rate", "5", "--out", str(path),
            "--no-progress")
    assert r.exit_code == 2, r.output
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and "cannot write" in lines[0] and "No space left" in lines[0]
    assert path.read_text() == previous
    assert sorted(p.name for p in tmp_path.iterdir()) == ["gt.jsonl"]
    monkeypatch.delattr(sim_cli, "open")
    r = run("sim", "generate", "mixed", "--seed", "1", "--duration", "1", "--rate", "5", "--out", str(path),
            "--no-progress")
    assert r.exit_code == 0, r.output
    assert len(path.read_text().splitlines()) == 5
    assert sorted(p.name for p in tmp_path.iterdir()) == ["gt.jsonl"]


def test_an_out_file_of_another_kind_is_refused_and_the_commands_own_is_replaced(tmp_path) -> None:
    """`sim generate --out notes.txt` and `sim bev --out mine.png` had overwritten whatever was there; a file holding
    something else than the command's kind of output is refused now, its own earlier output still replaced."""
    notes = tmp_path / "notes.txt"
    notes.write_text("my notes\n")
    r = run("sim", "generate", "mixed", "--duration", "0.5", "--out", str(notes), "--no-progress")
    assert r.exit_code == 2 and "exists and is not ground truth written by `sim generate`" in r.output, r.output
    assert notes.read_text() == "my notes\n"
    gt = tmp_path / "gt.jsonl"
    for seed in ("1", "2"):  # the second run replaces the first's lines
        r = run("sim", "generate", "mixed", "--seed", seed, "--duration", "0.5", "--out", str(gt), "--no-progress")
        assert r.exit_code == 0, r.output
    assert len(gt.read_text().splitlines()) == 5
    picture = tmp_path / "mine.png"
    picture.write_text("not a picture\n")
    r = run("sim", "bev", "mixed", "--duration", "0.5", "--out", str(picture))
    assert r.exit_code == 2 and "exists and is not a PNG" in r.output, r.output
    assert picture.read_text() == "not a picture\n"


@pytest.mark.parametrize("command", ["generate", "export"])
def test_a_sigterm_mid_run_leaves_nothing_half_written(tmp_path, command) -> None:
    """SIGTERM had ended `sim generate` at once, leaving its `.NAME.PID.part` file, and Ctrl-C or SIGTERM left
    `sim export`'s dataroot folder behind, empty. Both now clean up as for a failed write, exit 143."""
    import signal
    import subprocess
    import sys
    import time

    target = tmp_path / ("gt.jsonl" if command == "generate" else "root")
    args = (["generate", "mixed", "--lidar", "hdl32e", "--out", str(target)] if command == "generate"
            else ["export", "mixed", str(target)])
    proc = subprocess.Popen([sys.executable, "-m", "jitterguard.cli", "sim", *args, "--duration", "60",
                             "--no-progress"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not any(tmp_path.iterdir()):  # the part file or the folder is made
        time.sleep(0.05)
    time.sleep(1.0)  # and the scans are being cast
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, err[-2000:]
    assert list(tmp_path.iterdir()) == [], list(tmp_path.iterdir())
