"""`jitterguard bench pipeline` end to end on a tiny load: real router, tracker and classifier processes."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

pytestmark = pytest.mark.integration


def test_bench_pipeline_smoke(tmp_path):
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "bench", "pipeline", "--json", "--objects", "20",
                          "--rate", "10", "--duration", "3"], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-3000:]
    out = json.loads(res.stdout)
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
