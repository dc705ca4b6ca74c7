"""``jitterguard tracker`` and ``jitterguard bench tracker`` from the command line."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from typer.testing import CliRunner

from jitterguard.cli import app
from jitterguard.runtime import free_tcp_port
from jitterguard.services.tracker.config import load_config

runner = CliRunner()


def test_bench_tracker_json_has_the_documented_shape() -> None:
    res = runner.invoke(app, ["bench", "tracker", "--json", "--sizes", "20,50", "--frames", "5", "--warmup", "3"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert set(doc) == {"objects_20", "objects_50"}
    for row in doc.values():
        assert row["median_ms"] > 0 and row["p90_ms"] >= row["median_ms"] and row["frames"] == 5
    assert doc["objects_50"]["confirmed_tracks"] >= 40


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["tracker", "--measurement-covariance", "psychic"], "--measurement-covariance"),
        (["tracker", "--config", "/nonexistent/tracker.yaml"], "not found"),
        (["tracker", "--ns", "bad/ns"], "--ns"),
        (["tracker", "--connect", "nonsense"], "endpoint"),
        (["bench", "tracker", "--sizes", "ten"], "--sizes"),
        (["bench", "tracker", "--sizes", "0"], "--sizes"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(args: list[str], needle: str) -> None:
    res = runner.invoke(app, args)
    assert res.exit_code == 2
    lines = [ln for ln in res.output.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and needle in lines[0], res.output


def test_bad_config_file_names_the_key(tmp_path: Path) -> None:
    p = tmp_path / "t.yaml"
    p.write_text("max_dist_matrix: [1.0]\n")
    res = runner.invoke(app, ["tracker", "--config", str(p)])
    assert res.exit_code == 2 and "max_dist_matrix" in res.output


def test_print_config_round_trips_with_overrides(tmp_path: Path) -> None:
    res = runner.invoke(app, ["tracker", "--print-config", "--measurement-covariance", "class"])
    assert res.exit_code == 0
    p = tmp_path / "effective.yaml"
    p.write_text(res.stdout)
    cfg = load_config(p)
    assert cfg.measurement_covariance == "class"
    assert cfg.max_dist_matrix[9] == 2.0  # car-car, Autoware's default


@pytest.mark.integration
def test_tracker_process_starts_and_stops_cleanly_on_sigterm() -> None:
    port = free_tcp_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "jitterguard.cli", "tracker", "--ns", "cli_test", "--listen", f"tcp/127.0.0.1:{port}",
         "--static-hints", "--log-level", "INFO"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    lines: list[str] = []
    up = threading.Event()

    def read() -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            lines.append(line)
            if "tracker up" in line:
                up.set()  # logged once the signal handlers are installed

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        assert up.wait(30), "".join(lines)
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=20)
        reader.join(timeout=5)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    err = "".join(lines)
    assert proc.returncode == 0, err
    assert "tracker stopped" in err
