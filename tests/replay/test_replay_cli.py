"""The commands' bad-input contract: one line on stderr, exit 2, never a traceback (no Zenoh session opens)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from jitterguard.bench.cli import register as register_bench
from jitterguard.services.replay.cli import register

from .helpers import write_bin


@pytest.fixture(scope="module")
def app() -> typer.Typer:
    app = typer.Typer(pretty_exceptions_enable=False)
    bench = typer.Typer()
    register(app, bench)
    register_bench(app, bench)
    app.add_typer(bench, name="bench")
    return app


@pytest.fixture
def kitti(tmp_path: Path) -> Path:
    write_bin(tmp_path / "k" / "000000.bin", np.zeros((2, 4)))
    return tmp_path / "k"


CASES = [
    (["replay", "no/such/dir"], "no such file or folder"),
    (["replay", "synthetic:moon"], "unknown scenario"),
    (["replay", "{k}", "--rate", "fast"], "--rate must be"),
    (["replay", "{k}", "--rate", "0"], "--rate must be"),
    (["replay", "{k}", "--poses", "/no/such/poses.txt"], "--poses: file not found"),
    (["replay", "{k}", "--start", "-2"], "--start must be >= 0"),
    (["replay", "{k}", "--limit", "0"], "--limit must be >= 1"),
    (["replay", "{k}", "--on-error", "explode"], "--on-error"),
    (["replay", "{k}", "--stamps", "now"], "--stamps must be"),
    (["replay", "{k}", "--topic", "/x"], "--topic does not apply"),
    # a scenario's length and seed: scans on disk have neither (the replay had read them all in silence)
    (["replay", "{k}", "--duration", "5"], "--duration does not apply to a KITTI .bin source"),
    (["replay", "{k}", "--seed", "3"], "--seed does not apply to a KITTI .bin source"),
    (["replay", "{k}", "--hz", "0"], "--hz must be positive"),
    (["replay", "{k}", "--bin-fields", "x,y,z,x", "--rate", "max"], "--bin-fields: each column needs a name"),
    (["replay", "{k}", "--bin-fields", "x,y,z,,i", "--rate", "max"], "--bin-fields: each column needs a name"),
    (["replay", "{k}", "--hz", "1e-9", "--rate", "max"], "--hz must be positive, from 0.001"),  # stamps past int64
    (["replay", "{k}", "--ns", "a/b"], "--ns"),
    (["replay", "{k}", "--connect", "nonsense"], "must look like tcp/HOST:PORT"),
    (["replay", "{k}", "--start", "5"], "past the end"),
    (["replay", "{k}", "--wait-for", "detecter"], "--wait-for must be detector or tracker"),  # had waited for nobody
    (["bench", "replay", "--frames", "0"], "--frames"),
]


@pytest.mark.parametrize("argv,message", CASES)
def test_bad_input_is_one_line_and_exit_2(app: typer.Typer, kitti: Path, argv: list[str], message: str) -> None:
    argv = [a.format(k=kitti) for a in argv]
    if ("--start" in argv and "5" in argv) or "--bin-fields" in argv:  # refused after a session opens: on loopback
        argv += ["--listen", "tcp/127.0.0.1:0", "--wait-subscriber", "0", "--no-progress"]
    result = CliRunner().invoke(app, argv)
    assert result.exit_code == 2, result.output
    err = result.stderr if hasattr(result, "stderr") and result.stderr else result.output
    lines = [ln for ln in err.splitlines() if ln.startswith("jitterguard: error:")]
    assert len(lines) == 1 and message in lines[0], err
    assert "Traceback" not in err
    assert result.exception is None or isinstance(result.exception, SystemExit)


def test_a_recording_none_of_whose_frames_reads_is_an_error(app: typer.Typer, tmp_path: Path) -> None:
    """A folder of scans every one of which is unreadable replayed nothing: that is no success (it exited 0 with
    "replayed 0 frame(s)"). Each bad file still gets its own line, then one error line and exit 2."""
    folder = tmp_path / "bad scans"
    folder.mkdir()
    (folder / "000000.bin").write_bytes(b"\x00" * 3)  # cut short (0 bytes is an empty scan)
    (folder / "000001.bin").write_bytes(b"\x00" * 7)
    argv = ["replay", str(folder), "--listen", "tcp/127.0.0.1:0", "--wait-subscriber", "0", "--no-progress"]
    result = CliRunner().invoke(app, argv)
    err = result.stderr if hasattr(result, "stderr") and result.stderr else result.output
    assert result.exit_code == 2, err
    assert sum("unreadable frame skipped" in ln for ln in err.splitlines()) == 2, err
    lines = [ln for ln in err.splitlines() if ln.startswith("jitterguard: error:")]
    assert len(lines) == 1 and "no frame of" in lines[0] and "2 unreadable" in lines[0], err
    assert "Traceback" not in err


def test_one_unreadable_frame_among_good_ones_is_no_error(app: typer.Typer, tmp_path: Path) -> None:
    folder = tmp_path / "scans"
    write_bin(folder / "000000.bin", np.zeros((2, 4)))
    (folder / "000001.bin").write_bytes(b"\x00" * 7)
    argv = ["replay", str(folder), "--listen", "tcp/127.0.0.1:0", "--wait-subscriber", "0", "--no-progress"]
    result = CliRunner().invoke(app, argv)
    err = result.stderr if hasattr(result, "stderr") and result.stderr else result.output
    assert result.exit_code == 0, err
    assert "replayed 1 frame(s)" in err and "1 unreadable" in err, err


def test_scans_named_by_their_timestamp_replay_a_period_apart(app: typer.Typer, tmp_path: Path) -> None:
    """Scans named by their µs timestamp (no times.txt): the file number had been taken for the row of time, so
    they were stamped 10⁵ periods apart and past the wire's int64 nanoseconds — a multi-line validation error,
    exit 1, nothing replayed. They go out ``--hz`` apart in the folder's order, as .pcd files do."""
    from jitterguard.services.replay.sources.kitti import BinScanSource

    folder = tmp_path / "stamped"
    for k in range(3):
        write_bin(folder / f"{1733450000123456 + k * 100_000}.bin", np.zeros((2, 4)))
    assert [f.stamp_ns for f in BinScanSource(folder).frames()] == [0, 100_000_000, 200_000_000]
    argv = ["replay", str(folder), "--rate", "max", "--listen", "tcp/127.0.0.1:0", "--wait-subscriber", "0",
            "--no-progress"]
    result = CliRunner().invoke(app, argv)
    err = result.stderr if hasattr(result, "stderr") and result.stderr else result.output
    assert result.exit_code == 0, err
    assert "replayed 3 frame(s)" in err and "0 unreadable" in err, err


@pytest.mark.parametrize("name,short", [
    ("/data/day 2/velodyne", "velodyne"),  # was "day": the name cut at its first space
    ("/data/nu sc (scene-0523, LIDAR_TOP)", "nu sc"),
    ("synthetic:parking-street (seed 0)", "synthetic:parking-street"),
    ("/data/run bag:/velodyne_points", "velodyne_points"),
])
def test_the_progress_label_is_the_sources_last_path_part(name: str, short: str) -> None:
    from jitterguard.services.replay.cli import short_name

    assert short_name(name) == short


def test_stamps_the_replay_had_to_rewrite_are_named_in_its_summary(app: typer.Typer, tmp_path: Path) -> None:
    """A times.txt going back a little (reordered frames) and then an hour (a clock reset): the replay keeps its
    timeline increasing, and now says what it rewrote instead of publishing other stamps than recorded in silence."""
    folder = tmp_path / "scans"
    for k in range(5):
        write_bin(folder / f"{k:06d}.bin", np.zeros((2, 4)))
    (folder / "times.txt").write_text("3600.0\n3600.1\n3600.05\n3600.2\n1.0\n")
    argv = ["replay", str(folder), "--rate", "max", "--listen", "tcp/127.0.0.1:0", "--wait-subscriber", "0",
            "--no-progress"]
    result = CliRunner().invoke(app, argv)
    err = result.stderr if hasattr(result, "stderr") and result.stderr else result.output
    assert result.exit_code == 0, err
    assert "replayed 5 frame(s)" in err and "1 stamp(s) not after the previous one" in err, err
    assert "clock stepped back 1 time(s)" in err, err
