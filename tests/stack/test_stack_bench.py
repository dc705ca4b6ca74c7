"""`jitterguard bench pipeline` end to end on a tiny load: real router, tracker and classifier processes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.integration


def test_bench_pipeline_smoke(tmp_path):
    logs = tmp_path / "logs"
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "bench", "pipeline", "--json", "--objects", "20",
                          "--rate", "10", "--duration", "3", "--log-dir", str(logs)],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-3000:]
    out = json.loads(res.stdout)
    assert out["logs"] == str(logs)  # the services' logs where asked, not a stray temporary folder
    assert {p.name for p in logs.iterdir()} == {"router.log", "tracker.log", "classifier.log"}
    for key in ("objects", "rate_hz", "duration_s", "frames_in", "frames_out", "p50_ms", "p99_ms", "rss_growth_pct"):
        assert key in out
    assert out["objects"] == 20 and out["frames_in"] == 30
    assert 0 < out["frames_out"] <= out["frames_in"]
    assert set(out["rss_growth_pct"]) == {"router", "tracker", "classifier"}


def test_scene_generator_frames_validate():
    from jitterguard.schemas import decode, peek_header
    from jitterguard.schemas.models import DetectedObjects
    from jitterguard.bench.pipeline import SceneGenerator

    gen = SceneGenerator(200, 20.0, seed=1)
    a, b = decode(DetectedObjects, gen.frame(0, 10)), decode(DetectedObjects, gen.frame(1, 20))
    assert 150 < len(a.objects) <= 200 and b.header.seq == 1 and peek_header(gen.frame(7, 30)) == (7, 30)
    assert all(o.kinematics.has_position_covariance for o in a.objects)


@pytest.mark.parametrize("flag,text,field", [("--classifier-config", "alpha_default: -1\n", "alpha_default"),
                                             ("--tracker-config", "bogus_key: 1\n", "bogus_key")])
def test_bench_pipeline_refuses_a_bad_parameter_file_before_starting_anything(tmp_path, flag, text, field):
    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    for path, reason in ((bad, field), (tmp_path / "missing.yaml", "not found")):
        res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "bench", "pipeline", "--duration", "2", flag,
                              str(path)], capture_output=True, text=True, timeout=60)
        assert res.returncode == 2 and res.stdout == ""
        lines = res.stderr.strip().splitlines()
        assert len(lines) == 1 and flag in lines[0] and reason in lines[0]


def test_bench_pipeline_runs_the_classifier_with_the_given_parameter_file(tmp_path):
    """The paper preset's file reaches the classifier: it says so in its log (the configuration it runs)."""
    from jitterguard.config import param_file

    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "bench", "pipeline", "--json", "--objects", "20",
                          "--rate", "10", "--duration", "2", "--log-dir", str(tmp_path / "logs"), "--classifier-config",
                          str(param_file("classifier", "paper"))], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-3000:]
    out = json.loads(res.stdout)
    assert out["frames_out"] > 0
    log = (Path(out["logs"]) / "classifier.log").read_text()
    assert "calibration off" in log and "effective_n cluster" in log, log[-2000:]


@pytest.mark.slow
def test_bench_pipeline_waits_for_a_classifier_that_is_still_compiling(tmp_path):
    """With numba's cache empty (the first run after the compiled loops' source changed) the classifier compiles
    them for seconds after its liveliness token is out, subscribed to nothing yet. The bench waits until its
    heartbeat says ready; it had started on the token and sent a short run's every frame into the compilation
    (30 in, 0 out)."""
    import os

    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba-cache")}  # empty: every compiled loop compiles
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "bench", "pipeline", "--json", "--objects", "20",
                          "--rate", "10", "--duration", "3", "--log-dir", str(tmp_path / "logs")],
                         capture_output=True, text=True, timeout=240, env=env)
    assert res.returncode == 0, res.stderr[-3000:]
    out = json.loads(res.stdout)
    log = (Path(out["logs"]) / "classifier.log").read_text()
    assert "calibrated statistic ready in" in log
    assert out["frames_in"] == 30 and out["frames_out"] >= 27, out
