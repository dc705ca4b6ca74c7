"""Training loop: AdamW + one-cycle schedule, gradient clipping, a checkpoint per epoch, resume, evaluation each epoch.

Everything that decides a result is seeded: the torch initialisation, the sample order and each sample's
augmentation (a generator seeded by (seed, epoch, index), so a resumed run sees exactly the augmentations the
uninterrupted run would have). Checkpoints hold only tensors and builtins and load with
``torch.load(weights_only=True)``.
"""

from __future__ import annotations

import json
import logging
import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from .config import DetectorConfig, Detections3D, Sample
from .decode import decode
from .inference import save_weights
from .losses import centerpoint_loss
from .network import CenterPointNet
from .targets import build_targets

log = logging.getLogger(__name__)

Augment = Callable[[Sample, np.random.Generator], Sample]
Evaluate = Callable[[Sequence[Detections3D], Sequence[Sample]], dict[str, Any]]


@dataclass
class TrainConfig:
    """Optimisation settings (CenterPoint's nuScenes recipe scaled to small CPU batches)."""

    epochs: int = 20
    batch_size: int = 4
    lr: float = 2e-3
    weight_decay: float = 0.01
    grad_clip: float = 35.0
    pct_start: float = 0.4
    seed: int = 0
    num_workers: int = 0
    eval_every: int = 1
    max_eval_samples: int = 200
    max_steps_per_epoch: int | None = None


class TargetDataset(Dataset[tuple[torch.Tensor, dict[str, np.ndarray]]]):
    """Samples → (points, targets); augmentation seeded per (seed, epoch, index)."""

    def __init__(self, samples: Sequence[Sample], config: DetectorConfig, augment: Augment | None, seed: int) -> None:
        self.samples, self.config, self.augment, self.seed = samples, config, augment, seed
        self.epoch = 0

    def __len__(self) -> int:
        return len(self.samples)

    def __getitem__(self, i: int) -> tuple[torch.Tensor, dict[str, np.ndarray]]:
        s = self.samples[i]
        if self.augment is not None:
            s = self.augment(s, np.random.default_rng([self.seed, self.epoch, i]))
        t = build_targets(s, self.config)
        return torch.from_numpy(np.ascontiguousarray(s.points[:, :4], np.float32)), {
            "heatmap": t.heatmap, "ind": t.ind, "mask": t.mask, "box": t.box, "yaw": t.yaw}


def collate(items: list[tuple[torch.Tensor, dict[str, np.ndarray]]]) -> tuple[list[torch.Tensor], dict[str, torch.Tensor]]:
    points = [p for p, _ in items]
    batch = {k: torch.from_numpy(np.stack([t[k] for _, t in items])) for k in items[0][1]}
    return points, batch


@torch.no_grad()
def predict(model: CenterPointNet, samples: Sequence[Sample], batch_size: int = 4,
            progress: Callable[[int], None] | None = None) -> list[Detections3D]:
    """Detections for every sample (eval mode; no augmentation)."""
    was_training = model.training
    model.eval()
    out: list[Detections3D] = []
    for i in range(0, len(samples), batch_size):
        chunk = samples[i: i + batch_size]
        pts = [torch.from_numpy(np.ascontiguousarray(s.points[:, :4], np.float32)) for s in chunk]
        out.extend(decode(model(pts), model.config))
        if progress:
            progress(len(chunk))
    model.train(was_training)
    return out


@dataclass
class TrainState:
    epoch: int = 0
    history: list[dict[str, Any]] = field(default_factory=list)


def _checkpoint(path: Path, model: CenterPointNet, opt: torch.optim.Optimizer, sched: Any, state: TrainState,
                tcfg: TrainConfig) -> None:
    from .inference import config_to_dict

    tmp = path.with_suffix(".tmp")
    torch.save({"format": 1, "config": config_to_dict(model.config), "model": model.state_dict(),
                "optimizer": opt.state_dict(), "scheduler": sched.state_dict(), "epoch": state.epoch,
                "history": json.dumps(state.history), "train_config": asdict(tcfg)}, str(tmp))
    tmp.replace(path)


def train(model: CenterPointNet, train_samples: Sequence[Sample], val_samples: Sequence[Sample], tcfg: TrainConfig,
          out_dir: str | Path, *, augment: Augment | None = None, evaluate: Evaluate | None = None,
          resume: bool = False, progress: bool = True, meta: dict[str, Any] | None = None,
          stop_after: int | None = None) -> TrainState:
    """Train ``model`` in place; write ``checkpoint.pt`` each epoch, ``history.json`` and finally ``weights.pt``.

    ``resume`` continues from ``out_dir/checkpoint.pt`` (same data and settings expected). ``evaluate`` gets
    the validation detections and samples each ``eval_every`` epochs; its dict lands in the history.
    ``stop_after`` ends this run after that many epochs (a time-boxed job); ``weights.pt`` is then not
    written, and a later ``resume`` finishes the schedule exactly as one uninterrupted run would have.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(tcfg.seed)
    ds = TargetDataset(train_samples, model.config, augment, tcfg.seed)
    gen = torch.Generator().manual_seed(tcfg.seed)
    loader = DataLoader(ds, batch_size=tcfg.batch_size, shuffle=True, drop_last=len(ds) >= tcfg.batch_size,
                        num_workers=tcfg.num_workers, collate_fn=collate, generator=gen,
                        persistent_workers=False)
    steps = len(loader) if tcfg.max_steps_per_epoch is None else min(len(loader), tcfg.max_steps_per_epoch)
    opt = torch.optim.AdamW(model.parameters(), lr=tcfg.lr, weight_decay=tcfg.weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=tcfg.lr, total_steps=max(1, tcfg.epochs * steps),
                                                pct_start=tcfg.pct_start, div_factor=10.0, final_div_factor=1e3)
    state = TrainState()
    ckpt = out / "checkpoint.pt"
    if resume and ckpt.is_file():
        c = torch.load(str(ckpt), map_location="cpu", weights_only=True)
        model.load_state_dict(c["model"])
        opt.load_state_dict(c["optimizer"])
        sched.load_state_dict(c["scheduler"])
        state = TrainState(int(c["epoch"]), json.loads(c["history"]))
        log.info("resumed from %s at epoch %d", ckpt, state.epoch)
    bar = _bar(progress, tcfg.epochs * steps, state.epoch * steps)
    last = tcfg.epochs if stop_after is None else min(tcfg.epochs, state.epoch + stop_after)
    for epoch in range(state.epoch, last):
        ds.epoch = epoch
        gen.manual_seed(tcfg.seed * 1000 + epoch)  # same order for an epoch whether resumed or not
        model.train()
        sums: dict[str, float] = {}
        t0 = time.perf_counter()
        n = 0
        for step, (points, batch) in enumerate(loader):
            if step >= steps:
                break
            terms = centerpoint_loss(model(points), batch, model.config)
            loss = terms["loss"]
            if not torch.isfinite(loss):
                raise FloatingPointError(f"non-finite loss at epoch {epoch} step {step}: "
                                         f"{ {k: float(v) for k, v in terms.items()} }")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), tcfg.grad_clip)
            opt.step()
            sched.step()
            for k, v in terms.items():
                sums[k] = sums.get(k, 0.0) + float(v.detach())
            n += 1
            if bar is not None:
                bar.update(1)
                bar.set_postfix(epoch=epoch + 1, loss=f"{sums['loss'] / n:.3f}")
        record: dict[str, Any] = {"epoch": epoch + 1, "seconds": round(time.perf_counter() - t0, 1),
                                  "lr": sched.get_last_lr()[0], **{k: v / max(n, 1) for k, v in sums.items()}}
        if evaluate is not None and val_samples and ((epoch + 1) % tcfg.eval_every == 0 or epoch + 1 == tcfg.epochs):
            vs = val_samples[: tcfg.max_eval_samples]
            record["eval"] = evaluate(predict(model, vs), vs)
        state.epoch = epoch + 1
        state.history.append(record)
        _checkpoint(ckpt, model, opt, sched, state, tcfg)
        (out / "history.json").write_text(json.dumps(state.history, indent=1, default=_json_default))
        log.info("epoch %d: %s", epoch + 1, _summary(record))
        if bar is not None:
            bar.write(f"epoch {epoch + 1}/{tcfg.epochs}: {_summary(record)}")
    if bar is not None:
        bar.close()
    if state.epoch < tcfg.epochs:
        return state
    save_weights(out / "weights.pt", model, meta={**(meta or {}), "epochs": state.epoch,
                                                  "train_config": asdict(tcfg)})
    return state


def _summary(record: dict[str, Any]) -> str:
    parts = [f"loss {record.get('loss', math.nan):.3f}", f"{record['seconds']:.0f} s"]
    ev = record.get("eval") or {}
    for key in ("mAP", "map"):
        if key in ev:
            parts.append(f"mAP {ev[key]:.3f}")
    return ", ".join(parts)


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)


def _bar(enabled: bool, total: int, initial: int) -> Any:
    if not enabled:
        return None
    from tqdm import tqdm  # only when a bar is asked for

    return tqdm(total=total, initial=initial, unit="step", file=sys.stderr, dynamic_ncols=True)
