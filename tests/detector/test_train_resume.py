"""Resuming a training run: a checkpoint of other settings or a damaged one is refused in one line, a missing one is
said, a mid-epoch resume keeps the epoch's loss record, and weight files are replaced atomically."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from jitterguard.services.detector import train as train_mod
from jitterguard.services.detector.config import LITE, Sample
from jitterguard.services.detector.inference import load_weights, save_weights
from jitterguard.services.detector.network import CenterPointNet
from jitterguard.services.detector.train import CheckpointError, TrainConfig, train

TINY = LITE.model_copy(update=dict(
    name="tiny", point_cloud_range=(-12.8, -12.8, -3.0, 12.8, 12.8, 3.0), voxel_size=(0.2, 0.2, 6.0),
    pfn_channels=8, backbone_layers=(1, 1, 1), backbone_channels=(8, 16, 16), neck_channels=(8, 8, 8),
    head_channels=8, max_pillars=4000,
))
CFG = TrainConfig(epochs=1, batch_size=2, lr=5e-3, seed=1)
META = {"source": {"scenarios": ["a"]}, "augment": {"rotation_deg": 45.0}, "command": "jitterguard train A"}


@pytest.fixture(autouse=True)
def _one_thread() -> None:
    torch.set_num_threads(1)


def _scene(seed: int) -> Sample:
    rng = np.random.default_rng(seed)
    boxes = np.array([[4.0 + seed, 2.0, -1.0, 4.2, 1.8, 1.5, 0.3, 0, 0],
                      [-5.0, -3.0 - seed, -1.2, 0.6, 0.6, 1.7, 0.0, 0, 0]], np.float32)
    pts = [np.column_stack([rng.uniform(-12, 12, (2000, 2)), rng.uniform(-2.5, 0.5, 2000), rng.uniform(0, 40, 2000)])]
    for b in boxes:
        pts.append(np.column_stack([rng.normal(b[0], b[3] / 4, (300,)), rng.normal(b[1], b[4] / 4, (300,)),
                                    rng.normal(b[2], b[5] / 4, (300,)), rng.uniform(50, 200, 300)]))
    return Sample(np.concatenate(pts).astype(np.float32), boxes, np.array([0, 4]), np.array([300, 300]))


SAMPLES = [_scene(i) for i in range(4)]


def _model(seed: int = 0, **update: object) -> CenterPointNet:
    torch.manual_seed(seed)
    return CenterPointNet(TINY.model_copy(update=update) if update else TINY)


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A finished one-epoch run (its checkpoint is what each test resumes from)."""
    out = tmp_path_factory.mktemp("run")
    train(_model(), SAMPLES, [], CFG, out, progress=False, meta=META)
    return out


@pytest.mark.parametrize("change, field", [
    ({"epochs": 2}, "train_config.epochs"),  # OneCycleLR's length is fixed: it crashed steps later
    ({"batch_size": 1}, "train_config.batch_size"),
    ({"accumulate": 2}, "train_config.accumulate"),
    ({"max_steps_per_epoch": 1}, "train_config.max_steps_per_epoch"),
    ({"lr": 1e-3}, "train_config.lr"),  # silently taken (and recorded) before
    ({"seed": 2}, "train_config.seed"),
])
def test_resume_refuses_another_schedule_naming_the_field(tmp_path: Path, run: Path, change: dict, field: str) -> None:
    out = tmp_path / "r"
    shutil.copytree(run, out)
    before = (out / "checkpoint.pt").read_bytes()
    with pytest.raises(CheckpointError, match=field) as err:
        train(_model(), SAMPLES, [], TrainConfig(**{**CFG.__dict__, **change}), out, resume=True, progress=False,
              meta=META)
    assert "\n" not in str(err.value) and "new --out" in str(err.value)
    assert (out / "checkpoint.pt").read_bytes() == before  # nothing was trained or written


def test_resume_refuses_another_model_data_or_augmentation(tmp_path: Path, run: Path) -> None:
    out = tmp_path / "r"
    shutil.copytree(run, out)
    with pytest.raises(CheckpointError, match=r"config\.use_intensity"):  # --no-intensity
        train(_model(use_intensity=False), SAMPLES, [], CFG, out, resume=True, progress=False, meta=META)
    with pytest.raises(CheckpointError, match=r"meta\.augment\.rotation_deg: checkpoint 45\.0, this run 10\.0"):
        train(_model(), SAMPLES, [], CFG, out, resume=True, progress=False,
              meta={**META, "augment": {"rotation_deg": 10.0}})
    # the number of processes: another world size cuts other global batches
    with pytest.raises(CheckpointError, match="processes: checkpoint 1, this run 2"):
        model = _model()
        opt = torch.optim.AdamW(model.parameters())
        sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=1.0, total_steps=2)
        train_mod._load_checkpoint(out / "checkpoint.pt", model, opt, sched, None, CFG, 2, META, torch.device("cpu"))


def test_resume_accepts_what_does_not_define_the_run(tmp_path: Path, run: Path) -> None:
    """How the run is started (the command line, workers, evaluation cadence) may change between its parts."""
    out = tmp_path / "r"
    shutil.copytree(run, out)
    cfg = TrainConfig(**{**CFG.__dict__, "eval_every": 5, "checkpoint_every": 3, "amp": False})
    state = train(_model(7), SAMPLES, [], cfg, out, resume=True, progress=False,
                  meta={**META, "command": "jitterguard train B"})
    assert state.epoch == 1 and len(state.history) == 1


def test_damaged_checkpoint_is_one_line_error(tmp_path: Path, run: Path) -> None:
    out = tmp_path / "r"
    shutil.copytree(run, out)
    good = (out / "checkpoint.pt").read_bytes()
    (out / "checkpoint.pt").write_bytes(good[: len(good) // 3])  # a truncated copy
    with pytest.raises(CheckpointError, match="not a loadable checkpoint") as err:
        train(_model(), SAMPLES, [], CFG, out, resume=True, progress=False, meta=META)
    assert "\n" not in str(err.value)
    (out / "checkpoint.pt").write_text("not a checkpoint at all\n")  # torch advises weights_only=False: unsafe
    with pytest.raises(CheckpointError, match="not a loadable checkpoint") as err:
        train(_model(), SAMPLES, [], CFG, out, resume=True, progress=False, meta=META)
    assert "weights_only" not in str(err.value) and "\n" not in str(err.value)
    c = torch.load(str(run / "checkpoint.pt"), weights_only=True)
    del c["optimizer"]
    torch.save(c, str(out / "checkpoint.pt"))
    with pytest.raises(CheckpointError, match="damaged checkpoint.*optimizer"):
        train(_model(), SAMPLES, [], CFG, out, resume=True, progress=False, meta=META)


def test_resume_without_a_checkpoint_warns(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING, logger=train_mod.__name__):
        train(_model(), SAMPLES, [], CFG, tmp_path / "fresh", resume=True, progress=False)
    assert any("no checkpoint" in r.getMessage() for r in caplog.records)


def test_mid_epoch_resume_keeps_the_epoch_loss_record(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A run resumed from a mid-epoch checkpoint writes the history the uninterrupted run writes (the epoch's loss
    is the mean over all its steps, not over those after the resume)."""
    cfg = TrainConfig(epochs=2, batch_size=1, lr=5e-3, seed=1, checkpoint_every=2)  # 4 steps an epoch
    full = train(_model(), SAMPLES, [], cfg, tmp_path / "full", progress=False)
    saved = tmp_path / "cut"
    saved.mkdir()
    real = train_mod._checkpoint

    def keep_mid_epoch(path: Path, *args: object) -> None:  # the file an interruption after epoch 2 step 2 leaves
        real(path, *args)
        state = args[4]
        if state.epoch == 1 and state.step == 2:  # type: ignore[attr-defined]
            shutil.copy(path, saved / "checkpoint.pt")

    monkeypatch.setattr(train_mod, "_checkpoint", keep_mid_epoch)
    train(_model(), SAMPLES, [], cfg, tmp_path / "first", progress=False)
    monkeypatch.setattr(train_mod, "_checkpoint", real)
    resumed = train(_model(5), SAMPLES, [], cfg, saved, resume=True, progress=False)
    for a, b in zip(full.history, resumed.history, strict=True):
        assert {k for k in a if k != "seconds"} == {k for k in b if k != "seconds"}
        for k in ("loss", "heatmap", "lr"):
            assert b[k] == pytest.approx(a[k], rel=1e-5), k
    hist = json.loads((saved / "history.json").read_text())
    assert hist[1]["loss"] == pytest.approx(full.history[1]["loss"], rel=1e-5)


def test_train_can_leave_weights_to_the_caller_and_returns_their_meta(tmp_path: Path) -> None:
    state = train(_model(), SAMPLES, [], CFG, tmp_path, progress=False, meta=META, write_weights=False)
    assert not (tmp_path / "weights.pt").exists()
    assert state.meta is not None and state.meta["train_config"]["lr"] == CFG.lr
    assert state.meta["world_size"] == 1 and state.meta["epochs"] == 1 and state.meta["source"] == META["source"]


def test_a_failed_save_leaves_the_previous_weights_whole(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "weights.pt"
    model = _model()
    save_weights(path, model, meta={"good": True})
    before = path.read_bytes()

    def broken_save(obj: object, f) -> None:  # a save that fails half-way through
        f.write(b"half a file")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(torch, "save", broken_save)
    with pytest.raises(OSError):
        save_weights(path, _model(1), meta={"good": False})
    monkeypatch.undo()
    assert path.read_bytes() == before and load_weights(path)[2] == {"good": True}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["weights.pt"]  # no temporary file left behind

    import jitterguard.files

    def broken_replace(src: str, dst: object) -> None:  # the new file written, the rename over the old one fails
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(jitterguard.files.os, "replace", broken_replace)
    with pytest.raises(OSError):
        save_weights(path, _model(1), meta={"good": False})
    monkeypatch.undo()
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["weights.pt"]
