"""The GPU lease scripts (``scripts/gpu_lease_train.sh``, ``scripts/gpu_lease_continue.sh``,
``scripts/gpu_lease_paper.sh``) are the recorded recipes of the 28 Nov GPU runs and what a user with a GPU machine would run again; their ``SMOKE=1`` mode runs
every step on a few scans on the CPU (torchrun with gloo, parallel ray-casting, the probe, the side-by-side runs,
the copying of results), so the scripts cannot rot unnoticed between leases."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from jitterguard.services.detector.inference import load_weights, shipped_weights

ROOT = Path(__file__).resolve().parents[2]


def _run(script: str, out: Path, work: Path, **env: str) -> subprocess.CompletedProcess[str]:
    full = {**os.environ, "PY": sys.executable, "SMOKE": "1", "OUT": str(out), "WORK": str(work),
            "BUDGET_S": "400", "OMP_NUM_THREADS": "1", **env}
    return subprocess.run(["bash", f"scripts/{script}"], cwd=ROOT, env=full, capture_output=True, text=True,
                          timeout=600)


@pytest.mark.slow
def test_the_first_lease_script_benches_probes_and_trains_two_detectors(tmp_path: Path) -> None:
    out = tmp_path / "out"
    res = _run("gpu_lease_train.sh", out, tmp_path / "work", SCENARIOS="screened-lot", DISTILL="2")
    assert res.returncode == 0, (res.stdout + res.stderr)[-3000:]
    benches = [json.loads(line) for line in (out / "bench.json").read_text().splitlines() if line.strip()]
    assert [sorted(b) for b in benches] == [["lite", "paper"], ["lite"]]
    assert all(row["device"] == "cpu" for b in benches for row in b.values())  # no GPU here: both on the CPU
    assert len(json.loads((out / "probe.json").read_text())) == 1
    for run, init in (("A", True), ("B", False)):
        model, _, meta = load_weights(out / f"{run}.pt")
        assert model.config.name == "lite"
        assert "--train-seeds 100-101" in meta["command"] and ("--init" in meta["command"]) == init
        assert meta["source"]["scenarios"] == ["screened-lot"]  # SCENARIOS reaches train
        assert ("distilled" in meta) == init and (not init or meta["distilled"]["weight"] == 2.0)  # DISTILL: A only
        assert [r["epoch"] for r in json.loads((out / f"{run}_hist.json").read_text())] == [1, 2]
    assert "training A and B, 2 epochs each" in (out / "run.log").read_text()


@pytest.mark.slow
def test_the_second_lease_script_continues_a_run_beside_a_tilted_twin_and_the_paper_preset(tmp_path: Path) -> None:
    out = tmp_path / "out"
    res = _run("gpu_lease_continue.sh", out, tmp_path / "work", INIT=str(shipped_weights("lite")))
    assert res.returncode == 0, (res.stdout + res.stderr)[-3000:]
    metas = {run: load_weights(out / f"{run}.pt") for run in ("B2", "B2t", "P")}
    assert metas["P"][0].config.name == "paper" and metas["B2"][0].config.name == "lite"
    assert "--tilt-aug 2" in metas["B2t"][2]["command"] and "--tilt-aug" not in metas["B2"][2]["command"]
    assert all("--train-seeds 200-201" in m[2]["command"] for m in metas.values())


@pytest.mark.slow
def test_the_third_lease_script_returns_the_paper_weights_in_parts_that_join_to_the_trained_file(tmp_path: Path) -> None:
    out = tmp_path / "out"
    res = _run("gpu_lease_paper.sh", out, tmp_path / "work")
    assert res.returncode == 0, (res.stdout + res.stderr)[-3000:]
    parts = sorted(out.glob("P.pt.part*"))
    assert len(parts) >= 2 and all(p.stat().st_size <= 15 * 2**20 for p in parts)  # a paper file is ~20 MB
    joined = tmp_path / "P.pt"
    joined.write_bytes(b"".join(p.read_bytes() for p in parts))
    model, _, meta = load_weights(joined)
    assert model.config.name == "paper" and "--train-seeds 300-301" in meta["command"]
    assert hashlib.sha256(joined.read_bytes()).hexdigest() in (out / "run.log").read_text()
    assert [r["epoch"] for r in json.loads((out / "P_hist.json").read_text())] == [1]


@pytest.mark.slow
def test_the_voxeliser_ab_times_both_paths_to_the_same_pillars(tmp_path: Path) -> None:
    """``scripts/gpu_voxelize_ab.py`` (the fourth lease's A/B) loads the old voxeliser from a file beside the new
    one and refuses to time two voxelisers that disagree; here the "old" one is a copy that moves every pillar one
    cell, which must be caught (exit 1), and the shipped one against itself must time both paths."""
    new = ROOT / "jitterguard/services/detector/pillars.py"
    same = subprocess.run([sys.executable, "scripts/gpu_voxelize_ab.py", "--old", str(new), "--smoke"], cwd=ROOT,
                          capture_output=True, text=True, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert same.returncode == 0, same.stderr
    out = json.loads(same.stdout.strip().splitlines()[-1])
    assert out["same_pillars"] is True and out["batch"] == 2
    assert all(out["step_ms_p50"][k] > 0 and out["voxelize_batch_ms_p50"][k] > 0 for k in ("batched", "per_scan"))
    text = new.read_text()
    anchor = "    return Pillars("
    assert text.count(anchor) == 1
    off = tmp_path / "pillars_off.py"
    off.write_text(text.replace(anchor, "    coords = coords + 1\n" + anchor))
    bad = subprocess.run([sys.executable, "scripts/gpu_voxelize_ab.py", "--old", str(off), "--smoke"], cwd=ROOT,
                         capture_output=True, text=True, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert bad.returncode == 1 and json.loads(bad.stdout.strip().splitlines()[-1])["same_pillars"] is False
