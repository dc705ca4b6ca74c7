"""`jitterguard train` under torchrun: two gloo processes on CPU train the same weights as one process that runs
the same micro-batches itself (gradient accumulation), and the global-batch bookkeeping behind it."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from jitterguard.runtime import free_tcp_port
from jitterguard.services.detector.train import step_schedule

JG = [sys.executable, "-m", "jitterguard.cli"]
# a tiny run: one scenario seed, 4 scans of which 2 steps × 2 micro-batches × 1 scan are used
TRAIN = ["train", "--scenarios", "parking-street", "--train-seeds", "0", "--val-seeds", "1", "--frames-per-scenario",
         "4", "--effects", "none", "--epochs", "1", "--batch-size", "1", "--lr", "1e-3", "--seed", "3", "--threads",
         "1", "--no-progress", "--max-steps-per-epoch", "2"]


def test_schedule_splits_global_batches_the_same_for_any_world_and_accumulation() -> None:
    one = step_schedule(11, seed=4, epoch=2, batch=2, world=1, accumulate=2)
    two = step_schedule(11, seed=4, epoch=2, batch=2, world=2, accumulate=1)
    assert one == two and len(one) == 2 and all(len(mb) == 2 for step in one for mb in step)
    used = [i for step in one for mb in step for i in mb]
    assert len(set(used)) == 8 and set(used) <= set(range(11))  # disjoint, the remainder dropped
    assert step_schedule(11, 4, 3, 2, 1, 2) != one  # a new order every epoch
    small = step_schedule(3, 0, 0, batch=4, world=2, accumulate=1)  # fewer samples than one global batch
    assert len(small) == 1 and [len(mb) for mb in small[0]] == [1, 1]
    with pytest.raises(ValueError, match="micro-batches"):
        step_schedule(1, 0, 0, batch=1, world=2, accumulate=1)


def _env() -> dict[str, str]:
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONHASHSEED="0")
    env.pop("WORLD_SIZE", None)
    return env


@pytest.mark.slow
def test_two_gloo_processes_train_the_weights_of_one_process_on_the_same_batches(tmp_path: Path) -> None:
    single = tmp_path / "single"
    res = subprocess.run([*JG, *TRAIN, "--out", str(single), "--accumulate", "2"], capture_output=True, text=True,
                         timeout=300, env=_env())
    assert res.returncode == 0, res.stderr[-3000:]
    ddp = tmp_path / "ddp"
    res = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_addr",
                          "127.0.0.1", "--master_port", str(free_tcp_port()), "-m", "jitterguard.cli", *TRAIN,
                          "--out", str(ddp)], capture_output=True, text=True, timeout=300, env=_env())
    assert res.returncode == 0, res.stderr[-3000:]
    a = torch.load(single / "weights.pt", weights_only=True)
    b = torch.load(ddp / "weights.pt", weights_only=True)
    assert b["meta"]["world_size"] == 2 and a["meta"]["world_size"] == 1
    assert "torchrun" in b["meta"]["launcher"]
    moved = 0
    for name, wa in a["state_dict"].items():
        wb = b["state_dict"][name]
        assert wa.shape == wb.shape, name
        if wa.is_floating_point():
            np.testing.assert_allclose(wa.numpy(), wb.numpy(), rtol=1e-4, atol=2e-6, err_msg=name)
        else:
            assert torch.equal(wa, wb), name
    # and training did something: two steps of AdamW at lr 1e-3 moved every trained tensor
    torch.manual_seed(3)
    from jitterguard.services.detector.config import LITE
    from jitterguard.services.detector.network import CenterPointNet

    fresh = CenterPointNet(LITE).state_dict()
    for name, w in a["state_dict"].items():
        if w.is_floating_point() and not torch.equal(w, fresh[name]):
            moved += 1
    assert moved > 0.9 * sum(1 for w in a["state_dict"].values() if w.is_floating_point())
