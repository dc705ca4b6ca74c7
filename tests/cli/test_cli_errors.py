"""Bad CLI input: one line on stderr and exit status 2, never a traceback."""

from __future__ import annotations

import subprocess
import sys

import pytest

CASES = [
    ["classifier", "--bogus"],
    ["classifier", "--alpha", "-1"],
    ["classifier", "--mode", "zz"],
    ["classifier", "--ns", "a/b"],
    ["classifier", "--window-size", "3", "--min-window", "5"],
    ["classifier", "--config", "/nonexistent/x.yaml"],
    ["classifier", "--preset", "nope"],
    ["classifier", "--connect", "nonsense"],
    ["classifier", "--zenoh-config", "/nonexistent.json5"],
    ["bench", "classifier", "--tracks", "0"],
    ["feed-tracks", "--rate", "0"],
    ["up", "--input", "video"],
    ["logs", "classifier", "--run-dir", "/nonexistent-run-dir"],
    ["no-such-command"],
]


def run(args: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "jitterguard.cli", *args], capture_output=True, text=True, timeout=60)


@pytest.mark.parametrize("args", CASES, ids=[" ".join(c) for c in CASES])
def test_bad_input_is_one_line_and_exit_2(args):
    res = run(args)
    assert res.returncode == 2, res
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, res.stderr
    assert "error" in lines[0] and "Traceback" not in res.stderr


def test_config_file_values_are_validated(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("alpha_per_class: {spaceship: 2.0}\n")
    res = run(["classifier", "--config", str(cfg)])
    assert res.returncode == 2 and "alpha_per_class" in res.stderr


def test_help_lists_the_commands():
    res = run(["--help"])
    assert res.returncode == 0
    for cmd in ("classifier", "router", "up", "down", "status", "logs", "bench", "feed-tracks"):
        assert cmd in res.stdout


def test_an_unwritable_config_store_names_where_it_came_from(tmp_path):
    """``config_store`` is a field of the classifier's parameter file as well as a flag: a bad one is refused
    before anything starts, named as the user gave it."""
    bad = tmp_path / "no-such-dir" / "store.json"
    res = run(["classifier", "--config-store", str(bad)])
    assert res.returncode == 2 and res.stderr.count("\n") == 1 and "--config-store" in res.stderr
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"/**:\n  ros__parameters:\n    config_store: {bad}\n    open_config_writes: true\n")
    res = run(["classifier", "--config", str(cfg)])
    assert res.returncode == 2 and "config_store" in res.stderr and "--config-store" not in res.stderr
