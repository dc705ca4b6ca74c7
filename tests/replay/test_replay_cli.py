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
    (["replay", "{k}", "--hz", "0"], "--hz must be positive"),
    (["replay", "{k}", "--ns", "a/b"], "--ns"),
    (["replay", "{k}", "--connect", "nonsense"], "must look like tcp/HOST:PORT"),
    (["replay", "{k}", "--start", "5"], "past the end"),
    (["bench", "replay", "--frames", "0"], "--frames"),
]


@pytest.mark.parametrize("argv,message", CASES)
def test_bad_input_is_one_line_and_exit_2(app: typer.Typer, kitti: Path, argv: list[str], message: str) -> None:
    argv = [a.format(k=kitti) for a in argv]
    if "--start" in argv and "5" in argv:
        argv += ["--listen", "tcp/127.0.0.1:0", "--wait-subscriber", "0", "--no-progress"]
    result = CliRunner().invoke(app, argv)
    assert result.exit_code == 2, result.output
    err = result.stderr if hasattr(result, "stderr") and result.stderr else result.output
    lines = [ln for ln in err.splitlines() if ln.startswith("jitterguard: error:")]
    assert len(lines) == 1 and message in lines[0], err
    assert "Traceback" not in err
    assert result.exception is None or isinstance(result.exception, SystemExit)
