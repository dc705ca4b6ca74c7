"""Training loop: AdamW + one-cycle schedule, gradient clipping, checkpoints, resume, evaluation each epoch —
on one CPU or on many GPUs under ``torchrun`` with DistributedDataParallel.

Everything that decides a result is seeded: the torch initialisation, the sample order and each sample's
augmentation (a generator seeded by (seed, epoch, index), so a resumed run sees exactly the augmentations the
uninterrupted run would have). Checkpoints hold only tensors and builtins and load with
``torch.load(weights_only=True)``.

**One step, many micro-batches.** An optimiser step consumes a *global batch* of ``batch_size × world_size ×
accumulate`` samples: the epoch's seeded permutation is cut into global batches, and process ``r`` runs the
micro-batches ``r·accumulate … (r+1)·accumulate − 1`` of each. The loss of a micro-batch is normalised by the
object and heatmap-peak counts of the *whole* global batch (all-reduced), so the summed gradients are exactly
those of the global batch in one piece — whether it is split over processes, over accumulation steps, or not
at all. BatchNorm normalises each micro-batch by its own statistics (as on separate GPUs); its running
statistics are the mean of what each micro-batch would have produced from the step's starting values, again
the same however the global batch is split. Hence two gloo processes with ``accumulate=1`` and one process
with ``accumulate=2`` train the same weights (up to float summation order; ``tests/detector/test_distributed.py``).
On CUDA with several processes BatchNorm can instead be synchronised (``sync_bn``, CenterPoint's multi-GPU
recipe), which normalises by the statistics of all processes' micro-batches together.

**Mixed precision** (``amp``, CUDA only): the network runs under autocast (bfloat16 where the GPU supports it,
else float16 with a gradient scaler); losses are computed in float32.
"""

from __future__ import annotations

import json
import logging
import math
import os
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import nullcontext
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
from torch import nn
from torch.utils.data import DataLoader, Dataset

from .config import DetectorConfig, Detections3D, Sample
from .decode import decode
from .inference import atomic_save, config_to_dict, load_refusal, save_weights
from .losses import centerpoint_loss, distillation_loss, loss_normalisers
from .network import CenterPointNet
from .targets import build_targets

log = logging.getLogger(__name__)

Augment = Callable[[Sample, np.random.Generator], Sample]
Evaluate = Callable[[Sequence[Detections3D], Sequence[Sample]], dict[str, Any]]

CHECKPOINT_FORMAT = 3
"""3 added the number of processes, the run's metadata and the running loss sums of a mid-epoch checkpoint."""

SCHEDULE_FIELDS = ("epochs", "batch_size", "accumulate", "max_steps_per_epoch", "lr", "weight_decay", "grad_clip",
                   "pct_start", "seed")
"""The :class:`TrainConfig` fields that define a run's learning-rate schedule, batches and augmentations: a resumed
run must have them exactly as the checkpoint's (the one-cycle schedule's length is fixed when it is built, so even a
longer ``epochs`` would not continue the same run). The other fields (workers, evaluation, checkpointing, ``amp``,
``sync_bn``) may change between the parts of a run — e.g. a checkpoint written on a GPU finished on a CPU."""

UNCHECKED_META = ("command", "launcher")
"""Keys of the caller's ``meta`` that may differ on resume (how the run was started, not what it trains on)."""


class CheckpointError(ValueError):
    """A checkpoint that cannot be resumed: unreadable, or written by a run with other settings."""


@dataclass
class TrainConfig:
    """Optimisation settings (CenterPoint's nuScenes recipe scaled to small CPU batches). ``batch_size`` is per
    process and micro-batch; an optimiser step sees ``batch_size × world size × accumulate`` samples."""

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
    accumulate: int = 1
    amp: bool = False
    """Mixed precision on CUDA (ignored on CPU)."""
    sync_bn: bool = True
    """Synchronise BatchNorm over processes on CUDA (ignored on CPU and in a single process)."""
    checkpoint_every: int = 0
    """Also checkpoint every this many optimiser steps within an epoch (0: at the end of each epoch only); a
    resumed run continues from the step after the checkpoint with the same batches."""
    distill_channels: tuple[int, ...] = ()
    """Heatmap channels (classes) held to a teacher's by :func:`~.losses.distillation_loss` (``train``'s
    ``teacher``; none: no such term)."""
    distill_weight: float = 1.0
    """Weight of that term against the heatmap's focal loss."""


@dataclass(frozen=True)
class Dist:
    """Where this process runs: its rank among ``world`` processes, its device, and whether it is rank 0."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0
    device: torch.device = torch.device("cpu")

    @property
    def main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world > 1

    def barrier(self) -> None:
        if self.distributed:
            dist.barrier()


def init_distributed() -> Dist:
    """Join the process group ``torchrun`` describes in the environment (``WORLD_SIZE`` > 1): NCCL with one GPU
    per process when CUDA is available, gloo on CPU. A plain process (no ``WORLD_SIZE``) gets a one-process
    :class:`Dist` on the first GPU, or the CPU."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    cuda = torch.cuda.is_available()
    if world <= 1:
        return Dist(device=torch.device("cuda", 0) if cuda else torch.device("cpu"))
    rank, local = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
    if not dist.is_initialized():
        if cuda:
            torch.cuda.set_device(local)
        dist.init_process_group("nccl" if cuda else "gloo")
    return Dist(rank, world, local, torch.device("cuda", local) if cuda else torch.device("cpu"))


def step_schedule(n: int, seed: int, epoch: int, batch: int, world: int, accumulate: int) -> list[list[list[int]]]:
    """The epoch's global batches: ``[step][world · accumulate micro-batches][batch sample indices]`` from a
    permutation seeded by (seed, epoch); a remainder that fills no global batch is dropped (all of it is one
    smaller global batch when the data set is smaller than one)."""
    perm = np.random.default_rng([seed, epoch]).permutation(n)
    micro = world * accumulate
    per_step = batch * micro
    if n < per_step:
        if n < micro:
            raise ValueError(f"{n} samples cannot fill {micro} micro-batches (world {world} × accumulate {accumulate})")
        b = n // micro
        return [[perm[m * b:(m + 1) * b].tolist() for m in range(micro)]]
    return [[perm[k * per_step + m * batch: k * per_step + (m + 1) * batch].tolist() for m in range(micro)]
            for k in range(n // per_step)]


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
        nf = self.config.num_point_features
        return torch.from_numpy(np.ascontiguousarray(s.points[:, :nf], np.float32)), {
            "heatmap": t.heatmap, "ind": t.ind, "mask": t.mask, "box": t.box, "yaw": t.yaw}


def collate(items: list[tuple[torch.Tensor, dict[str, np.ndarray]]]) -> tuple[list[torch.Tensor], dict[str, torch.Tensor]]:
    points = [p for p, _ in items]
    batch = {k: torch.from_numpy(np.stack([t[k] for _, t in items])) for k in items[0][1]}
    return points, batch


@torch.no_grad()
def predict(model: CenterPointNet, samples: Sequence[Sample], batch_size: int = 4,
            progress: Callable[[int], None] | None = None, device: torch.device | None = None) -> list[Detections3D]:
    """Detections for every sample (eval mode; no augmentation)."""
    was_training = model.training
    model.eval()
    dev = device or next(model.parameters()).device
    nf = model.config.num_point_features
    out: list[Detections3D] = []
    for i in range(0, len(samples), batch_size):
        chunk = samples[i: i + batch_size]
        pts = [torch.from_numpy(np.ascontiguousarray(s.points[:, :nf], np.float32)).to(dev) for s in chunk]
        out.extend(decode(model(pts), model.config))
        if progress:
            progress(len(chunk))
    model.train(was_training)
    return out


@dataclass
class TrainState:
    epoch: int = 0
    step: int = 0
    """Optimiser steps done within ``epoch`` (a mid-epoch checkpoint); 0 at an epoch boundary."""
    history: list[dict[str, Any]] = field(default_factory=list)
    sums: dict[str, float] = field(default_factory=dict)
    """Loss terms summed over the ``step`` steps done in ``epoch`` (saved in a mid-epoch checkpoint, so that a
    resumed run's epoch record averages every step of the epoch, as the uninterrupted run's does)."""
    meta: dict[str, Any] | None = None
    """What ``weights.pt`` holds (or would hold) as its metadata, once the schedule is complete."""


def _bn_buffers(model: nn.Module) -> list[torch.Tensor]:
    return [b for m in model.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)
            for b in (m.running_mean, m.running_var, m.num_batches_tracked) if b is not None]


def _checkpoint(path: Path, model: nn.Module, opt: torch.optim.Optimizer, sched: Any, scaler: Any,
                state: TrainState, tcfg: TrainConfig, config: DetectorConfig, world: int, meta: dict[str, Any]) -> None:
    atomic_save({"format": CHECKPOINT_FORMAT, "config": config_to_dict(config), "model": model.state_dict(),
                 "optimizer": opt.state_dict(), "scheduler": sched.state_dict(),
                 "scaler": scaler.state_dict() if scaler is not None else None, "epoch": state.epoch,
                 "step": state.step, "history": json.dumps(state.history, default=_json_default),
                 "sums": json.dumps(state.sums), "train_config": asdict(tcfg), "world_size": world,
                 "meta": json.dumps(_run_meta(meta), default=_json_default)}, path)


def _run_meta(meta: dict[str, Any] | None) -> dict[str, Any]:
    """The part of the caller's metadata that defines the run (data, augmentation), as JSON would store it."""
    kept = {k: v for k, v in (meta or {}).items() if k not in UNCHECKED_META}
    return json.loads(json.dumps(kept, default=_json_default))


def _differences(name: str, saved: Any, now: Any) -> list[str]:
    """``name.key: checkpoint A, this run B`` for every leaf where two (nested) dicts differ."""
    if isinstance(saved, dict) and isinstance(now, dict):
        return [d for k in sorted(set(saved) | set(now), key=str)
                for d in _differences(f"{name}.{k}", saved.get(k), now.get(k))]
    return [] if saved == now else [f"{name}: checkpoint {saved!r}, this run {now!r}"]


def read_checkpoint(path: Path, device: torch.device | str = "cpu") -> dict[str, Any]:
    """A training checkpoint's content, or :class:`CheckpointError` (one line) for a file that is none: what
    ``train --resume`` checks before it prepares any data (a damaged ``checkpoint.pt`` had been refused only after
    minutes of casting scans), and again, against the run's settings, when it resumes."""
    try:
        c = torch.load(str(path), map_location=device, weights_only=True)
    except Exception as exc:  # noqa: BLE001 - torch raises many types for a damaged file
        raise CheckpointError(f"{path}: not a loadable checkpoint ({load_refusal(exc)})") from None
    if not isinstance(c, dict) or c.get("format") not in (2, CHECKPOINT_FORMAT):
        raise CheckpointError(f"{path}: not a jitterguard training checkpoint (format {CHECKPOINT_FORMAT})")
    return c


def _load_checkpoint(path: Path, model: nn.Module, opt: torch.optim.Optimizer, sched: Any, scaler: Any,
                     tcfg: TrainConfig, world: int, meta: dict[str, Any] | None, device: torch.device) -> TrainState:
    """Restore a checkpoint into ``model``/``opt``/``sched``/``scaler`` after checking that it belongs to this run:
    the same model config, :data:`SCHEDULE_FIELDS`, number of processes and data/augmentation metadata.
    Raises :class:`CheckpointError` (one line) before anything is loaded otherwise: a different schedule crashes
    steps later (OneCycleLR's fixed length) or silently trains, and records, something neither run asked for."""
    c = read_checkpoint(path, device)
    diffs = _differences("config", c.get("config"), config_to_dict(model.config))  # type: ignore[arg-type]
    saved_tc = c.get("train_config") or {}
    diffs += [d for f in SCHEDULE_FIELDS for d in _differences(f"train_config.{f}", saved_tc.get(f), getattr(tcfg, f))]
    if c["format"] >= 3:
        diffs += _differences("processes", c.get("world_size"), world)
        diffs += _differences("meta", json.loads(c.get("meta") or "{}"), _run_meta(meta))
    else:
        log.warning("%s: an older checkpoint (format 2): its number of processes and data were not recorded and"
                    " are not checked", path)
    if diffs:
        shown = "; ".join(diffs[:4]) + (f"; and {len(diffs) - 4} more" if len(diffs) > 4 else "")
        raise CheckpointError(f"{path} was written by a run with other settings ({shown}); --resume"
                              " continues only the same run (same model, data, schedule and number of processes):"
                              " rerun with the checkpoint's settings, or train into a new --out")
    try:
        model.load_state_dict(c["model"])
        opt.load_state_dict(c["optimizer"])
        sched.load_state_dict(c["scheduler"])
        if scaler is not None and c.get("scaler"):
            scaler.load_state_dict(c["scaler"])
        return TrainState(int(c["epoch"]), int(c.get("step", 0)), json.loads(c["history"]),
                          json.loads(c.get("sums") or "{}") if int(c.get("step", 0)) else {})
    except (KeyError, RuntimeError, ValueError, TypeError) as exc:
        raise CheckpointError(f"{path}: damaged checkpoint ({type(exc).__name__}: "
                              f"{' '.join(str(exc).split())[:200]})") from None


def _autocast(device: torch.device, amp: bool) -> tuple[Any, Any]:
    """(context factory, gradient scaler or None) for mixed precision on CUDA; plain float32 elsewhere."""
    if not (amp and device.type == "cuda"):
        return nullcontext, None
    dtype = torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16
    scaler = torch.amp.GradScaler("cuda") if dtype == torch.float16 else None
    return (lambda: torch.autocast("cuda", dtype=dtype)), scaler


def train(model: CenterPointNet, train_samples: Sequence[Sample], val_samples: Sequence[Sample], tcfg: TrainConfig,
          out_dir: str | Path, *, augment: Augment | None = None, evaluate: Evaluate | None = None,
          resume: bool = False, progress: bool = True, meta: dict[str, Any] | None = None,
          stop_after: int | None = None, dist_ctx: Dist | None = None, write_weights: bool = True,
          teacher: CenterPointNet | None = None) -> TrainState:
    """Train ``model`` in place; write ``checkpoint.pt`` each epoch, ``history.json`` and finally ``weights.pt``
    (unless ``write_weights`` is False: a caller that adds to the weights, e.g. a fitted recalibration, then writes
    the file once itself, with the metadata the returned state's ``meta`` holds).

    ``resume`` continues from ``out_dir/checkpoint.pt``; a checkpoint of another run (model config, schedule,
    number of processes or ``meta`` other than its ``command``/``launcher``) or a damaged one raises
    :class:`CheckpointError`, and a missing one is logged as a warning (the run starts afresh). ``evaluate`` gets
    the validation detections and samples each ``eval_every`` epochs; its dict lands in the history.
    ``stop_after`` ends this run after that many epochs (a time-boxed job); ``weights.pt`` is then not
    written, and a later ``resume`` finishes the schedule exactly as one uninterrupted run would have.
    ``dist_ctx`` (from :func:`init_distributed`) places the run on its device and process group; only rank 0
    writes files and evaluates. ``teacher`` (a fixed network, in inference mode) is what ``tcfg.distill_channels``
    are held to.
    """
    if tcfg.distill_channels and teacher is None:
        raise ValueError("distill_channels need a teacher")
    dc = dist_ctx or Dist()
    out = Path(out_dir)
    if dc.main:
        out.mkdir(parents=True, exist_ok=True)
    if tcfg.accumulate < 1:
        raise ValueError("accumulate must be >= 1")
    torch.manual_seed(tcfg.seed)
    model.to(dc.device)
    net: nn.Module = model
    if dc.distributed:
        if tcfg.sync_bn and dc.device.type == "cuda":
            net = nn.SyncBatchNorm.convert_sync_batchnorm(model)
        net = nn.parallel.DistributedDataParallel(
            net, device_ids=[dc.local_rank] if dc.device.type == "cuda" else None, broadcast_buffers=False)
    ds = TargetDataset(train_samples, model.config, augment, tcfg.seed)
    schedule = step_schedule(len(ds), tcfg.seed, 0, tcfg.batch_size, dc.world, tcfg.accumulate)
    steps = len(schedule) if tcfg.max_steps_per_epoch is None else min(len(schedule), tcfg.max_steps_per_epoch)
    opt = torch.optim.AdamW(model.parameters(), lr=tcfg.lr, weight_decay=tcfg.weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=tcfg.lr, total_steps=max(1, tcfg.epochs * steps),
                                                pct_start=tcfg.pct_start, div_factor=10.0, final_div_factor=1e3)
    autocast, scaler = _autocast(dc.device, tcfg.amp)
    state = TrainState()
    ckpt = out / "checkpoint.pt"
    if resume and ckpt.is_file():
        state = _load_checkpoint(ckpt, model, opt, sched, scaler, tcfg, dc.world, meta, dc.device)
        log.info("resumed from %s at epoch %d step %d", ckpt, state.epoch, state.step)
    elif resume and dc.main:
        log.warning("--resume: no checkpoint at %s; training from the start", ckpt)
    bar = progress_bar(progress and dc.main, tcfg.epochs * steps, state.epoch * steps + state.step)
    last = tcfg.epochs if stop_after is None else min(tcfg.epochs, state.epoch + stop_after)
    buffers = _bn_buffers(model)
    if teacher is not None:
        teacher.to(dc.device).eval()
        for p in teacher.parameters():
            p.requires_grad_(False)
    for epoch in range(state.epoch, last):
        ds.epoch = epoch
        schedule = step_schedule(len(ds), tcfg.seed, epoch, tcfg.batch_size, dc.world, tcfg.accumulate)[:steps]
        mine = [sch[dc.rank * tcfg.accumulate:(dc.rank + 1) * tcfg.accumulate] for sch in schedule]
        first = state.step
        loader = DataLoader(ds, batch_sampler=[mb for step in mine[first:] for mb in step],
                            num_workers=tcfg.num_workers, collate_fn=collate, persistent_workers=False)
        model.train()
        sums = state.sums if first else {}  # a mid-epoch checkpoint's sums over its first `first` steps
        state.sums = sums
        t0 = time.perf_counter()
        n = first
        micro = iter(loader)
        for step in range(first, len(mine)):
            terms = _train_step(net, model, micro, tcfg, dc, buffers, autocast, scaler, epoch, step, teacher)
            if scaler is not None:
                scaler.unscale_(opt)
            torch.nn.utils.clip_grad_norm_(model.parameters(), tcfg.grad_clip)
            if scaler is not None:
                scaler.step(opt)
                scaler.update()
            else:
                opt.step()
            opt.zero_grad(set_to_none=True)
            sched.step()
            for k, v in terms.items():
                sums[k] = sums.get(k, 0.0) + v
            n += 1
            state.step = step + 1
            if bar is not None:
                bar.update(1)
                bar.set_postfix(epoch=epoch + 1, loss=f"{sums['loss'] / n:.3f}")
            if tcfg.checkpoint_every and state.step % tcfg.checkpoint_every == 0 and state.step < len(mine):
                if dc.main:
                    _checkpoint(ckpt, model, opt, sched, scaler, state, tcfg, model.config, dc.world, meta or {})
                dc.barrier()
        record: dict[str, Any] = {"epoch": epoch + 1, "seconds": round(time.perf_counter() - t0, 1),
                                  "lr": sched.get_last_lr()[0], **{k: v / max(n, 1) for k, v in sums.items()}}
        if (dc.main and evaluate is not None and val_samples
                and ((epoch + 1) % tcfg.eval_every == 0 or epoch + 1 == tcfg.epochs)):
            vs = val_samples[: tcfg.max_eval_samples]
            record["eval"] = evaluate(predict(model, vs), vs)
        state.epoch, state.step, state.sums = epoch + 1, 0, {}
        state.history.append(record)
        if dc.main:
            _checkpoint(ckpt, model, opt, sched, scaler, state, tcfg, model.config, dc.world, meta or {})
            (out / "history.json").write_text(json.dumps(state.history, indent=1, default=_json_default))
        dc.barrier()
        log.info("epoch %d: %s", epoch + 1, _summary(record))
        if bar is not None:
            bar.write(f"epoch {epoch + 1}/{tcfg.epochs}: {_summary(record)}", file=sys.stderr)  # stdout: the JSON
    if bar is not None:
        bar.close()
    if state.epoch < tcfg.epochs:
        return state
    state.meta = {**(meta or {}), "epochs": state.epoch, "train_config": asdict(tcfg), "world_size": dc.world}
    if dc.main and write_weights:
        save_weights(out / "weights.pt", model, meta=state.meta)
    dc.barrier()
    return state


def _train_step(net: nn.Module, model: CenterPointNet, micro: Iterator[Any], tcfg: TrainConfig, dc: Dist,
                buffers: list[torch.Tensor], autocast: Any, scaler: Any, epoch: int, step: int,
                teacher: CenterPointNet | None = None) -> dict[str, float]:
    """Forward and backward of this process's micro-batches of one global batch (gradients left in ``.grad``);
    returns the global batch's loss terms (all-reduced)."""
    batches = [next(micro) for _ in range(tcfg.accumulate)]
    # normalisers of the whole global batch (every process's micro-batches)
    norm = sum((loss_normalisers(b) for _, b in batches), torch.zeros(2, dtype=torch.float64))
    if dc.distributed:
        norm = norm.to(dc.device)
        dist.all_reduce(norm)
        norm = norm.cpu()
    start = [b.clone() for b in buffers]
    after = [torch.zeros_like(b, dtype=torch.float64) for b in buffers]
    sums: dict[str, torch.Tensor] = {}
    for a, (points, batch) in enumerate(batches):
        for b, s in zip(buffers, start):
            b.copy_(s)
        points = [p.to(dc.device, non_blocking=True) for p in points]
        batch = {k: v.to(dc.device, non_blocking=True) for k, v in batch.items()}
        sync = nullcontext() if (a == len(batches) - 1 or not dc.distributed) else net.no_sync()  # type: ignore[operator]
        with sync:
            with autocast():
                raw = net(points)
            terms = centerpoint_loss({k: v.float() for k, v in raw.items()}, batch, model.config,
                                     num_pos=float(norm[0]), num_obj=float(norm[1]))
            if teacher is not None and tcfg.distill_channels:
                with torch.no_grad(), autocast():
                    held = teacher(points)["heatmap"]
                terms["distill"] = tcfg.distill_weight * distillation_loss(
                    raw["heatmap"].float(), held.float(), tcfg.distill_channels, float(norm[0]))
                terms["loss"] = terms["loss"] + terms["distill"]
            loss = terms["loss"]
            if not torch.isfinite(loss):
                raise FloatingPointError(f"non-finite loss at epoch {epoch} step {step}: "
                                         f"{ {k: float(v) for k, v in terms.items()} }")
            scaled = loss * dc.world  # DDP averages gradients over processes; the global loss is their sum
            (scaler.scale(scaled) if scaler is not None else scaled).backward()
        for acc, b in zip(after, buffers):
            acc += b.double()
        for k, v in terms.items():
            sums[k] = sums.get(k, 0.0) + v.detach().double()
    # BatchNorm running statistics: the mean over every micro-batch of the global batch
    for acc, b in zip(after, buffers):
        acc /= len(batches)
    if dc.distributed:
        flat = torch.cat([acc.reshape(-1) for acc in after]).to(dc.device)
        dist.all_reduce(flat)
        flat = flat.cpu() / dc.world
        off = 0
        for acc in after:
            acc.copy_(flat[off: off + acc.numel()].view_as(acc))
            off += acc.numel()
    for acc, b in zip(after, buffers):
        b.copy_(acc.round() if not b.is_floating_point() else acc.to(b.dtype))
    vals = torch.stack([sums[k] for k in sorted(sums)])
    if dc.distributed:
        vals = vals.to(dc.device)
        dist.all_reduce(vals)
        vals = vals.cpu()
    return {k: float(v) for k, v in zip(sorted(sums), vals)}


def _summary(record: dict[str, Any]) -> str:
    parts = [f"loss {record.get('loss', math.nan):.3f}", f"{record['seconds']:.0f} s"]
    ev = record.get("eval") or {}
    for key in ("mAP", "map"):
        if key in ev and ev[key] is not None:
            parts.append(f"mAP {ev[key]:.3f}")
    return ", ".join(parts)


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)


def progress_bar(enabled: bool, total: int | None, initial: int = 0, unit: str = "step", desc: str | None = None) -> Any:
    """A tqdm bar on stderr, or None when not ``enabled`` (the caller's ``--progress`` / terminal decision)."""
    if not enabled:
        return None
    from tqdm import tqdm  # only when a bar is asked for

    return tqdm(total=total, initial=initial, unit=unit, desc=desc, file=sys.stderr, dynamic_ncols=True)
