"""A/B of a training step with the batched voxelisation (one sort per batch, since 59896b6) against the scan-by-scan
one it replaced, back to back in one process on one device: the number docs/detector.md had left "not yet measured"
(the per-scan loop had cost 2.5 ms a scan on an H200, about half of a 16-scan step).

    python scripts/gpu_voxelize_ab.py --old OLD_PILLARS.py [--device cuda] [--preset lite] [--batch 16]
        [--steps 20] [--rounds 3] [--workers 16] [--smoke]

``OLD_PILLARS.py`` is ``git show 59896b6^:jitterguard/services/detector/pillars.py``. Each round times ``--steps``
full training steps (forward under bfloat16 autocast on CUDA, CenterPoint's loss, backward, AdamW) with each
voxeliser in turn (the order alternating between rounds), plus the voxelisation of one batch alone; prints one
JSON object. ``--smoke``: a few scans on the CPU (tests/detector/test_gpu_lease_scripts.py).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from jitterguard.services.detector import network
from jitterguard.services.detector.config import PRESETS
from jitterguard.services.detector.data import synthetic_samples
from jitterguard.services.detector.losses import centerpoint_loss, loss_normalisers
from jitterguard.services.detector.pillars import voxelize as batched_voxelize
from jitterguard.services.detector.train import TargetDataset, _autocast, collate


def _load_old(path: Path) -> Callable[..., Any]:
    """The old module, imported as a sibling of the new one (it imports ``.config`` relatively)."""
    spec = importlib.util.spec_from_file_location("jitterguard.services.detector._pillars_before", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod.voxelize  # type: ignore[no-any-return]


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old", type=Path, required=True)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--preset", default="lite")
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--workers", type=int, default=16)
    ap.add_argument("--smoke", action="store_true")
    a = ap.parse_args()
    if a.smoke:
        a.batch, a.steps, a.rounds, a.workers = 2, 1, 1, 0
    dev = torch.device(a.device)
    torch.manual_seed(0)
    cfg = PRESETS[a.preset]
    seeds = range(0, 1) if a.smoke else range(0, max(1, a.batch // 4))
    samples = list(synthetic_samples(["mixed", "diagonal-lot", "parking-street", "intersection"], list(seeds),
                                     frames_per_scenario=1 if a.smoke else 4, workers=a.workers))[: a.batch]
    ds = TargetDataset(samples, cfg, None, seed=0)
    points, batch = collate([ds[i] for i in range(len(ds))])
    points = [p.to(dev) for p in points]
    batch = {k: v.to(dev) for k, v in batch.items()}
    norm = loss_normalisers({k: v.cpu() for k, v in batch.items()})
    model = network.CenterPointNet(cfg).to(dev).train()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
    autocast, _ = _autocast(dev, amp=True)
    voxelisers = {"batched": batched_voxelize, "per_scan": _load_old(a.old)}
    # equal results first: the A/B compares two ways to the same pillars
    p_new, p_old = (v(points, cfg) for v in voxelisers.values())
    same = all(torch.equal(x, y) if isinstance(x, torch.Tensor) else x == y
               for x, y in ((getattr(p_new, f), getattr(p_old, f)) for f in p_new.__dataclass_fields__))
    if not same:  # two ways to different pillars: timing them would compare different work
        print(json.dumps({"same_pillars": False}))
        return 1

    def step() -> None:
        opt.zero_grad(set_to_none=True)
        with autocast():
            raw = model(points)
        terms = centerpoint_loss({k: v.float() for k, v in raw.items()}, batch, cfg,
                                 num_pos=float(norm[0]), num_obj=float(norm[1]))
        terms["loss"].backward()
        opt.step()

    step_ms: dict[str, list[float]] = {k: [] for k in voxelisers}
    vox_ms: dict[str, list[float]] = {k: [] for k in voxelisers}
    for r in range(a.rounds):
        order = list(voxelisers) if r % 2 == 0 else list(voxelisers)[::-1]
        for name in order:
            network.voxelize = voxelisers[name]  # what CenterPointNet.forward calls
            step()  # warm-up of this path
            _sync(dev)
            for _ in range(a.steps):
                t0 = time.perf_counter()
                step()
                _sync(dev)
                step_ms[name].append((time.perf_counter() - t0) * 1e3)
            for _ in range(a.steps):
                t0 = time.perf_counter()
                voxelisers[name](points, cfg)
                _sync(dev)
                vox_ms[name].append((time.perf_counter() - t0) * 1e3)
    network.voxelize = batched_voxelize
    med = {k: statistics.median(v) for k, v in step_ms.items()}
    out = {
        "device": torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu",
        "torch": torch.__version__, "preset": a.preset, "batch": len(points), "steps_per_round": a.steps,
        "rounds": a.rounds, "same_pillars": same,
        "step_ms_p50": {k: round(v, 2) for k, v in med.items()},
        "step_ms_per_round": {k: [round(statistics.median(v[i * a.steps:(i + 1) * a.steps]), 2)
                                  for i in range(a.rounds)] for k, v in step_ms.items()},
        "voxelize_batch_ms_p50": {k: round(statistics.median(v), 2) for k, v in vox_ms.items()},
        "step_speedup": round(med["per_scan"] / med["batched"], 3),
    }
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
