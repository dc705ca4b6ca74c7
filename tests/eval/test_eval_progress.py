"""Long commands draw progress bars on a terminal only: a redirected log gets no tqdm carriage returns."""

from __future__ import annotations

import subprocess
import sys


def test_eval_into_a_redirected_log_has_no_progress_bar(tmp_path):
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "eval", "--scenario", "parking-street",
                          "--duration", "3", "--out", str(tmp_path / "out")], capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr
    assert "\r" not in res.stderr and "frame/s" not in res.stderr and "it/s" not in res.stderr, res.stderr[-500:]
    assert (tmp_path / "out" / "metrics.json").is_file()
