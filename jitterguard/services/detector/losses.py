"""Training losses: Gaussian focal loss on the heatmap; L1 or Gaussian NLL on the regression targets (paper eq. in §III-A).

The uncertainty-aware model replaces L1 by the Gaussian NLL ½·exp(−s)·(x̄ − x)² + ½·s for x, y, vx, vy and
yaw, with s = log σ² clamped to [−10, ∞). Position residuals are taken in metres (not output cells) so that
the predicted σ² is in m² and goes onto the wire as is. z, dimensions and the (sin, cos) of yaw keep
CenterPoint's L1.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .config import DetectorConfig

VEL_WEIGHT = 0.2
"""CenterPoint's code weight on the velocity targets (nuScenes config)."""
REG_WEIGHT = 0.25
"""CenterPoint's weight of the regression loss against the heatmap loss."""


def gaussian_focal_loss(logits: Tensor, target: Tensor, num_pos: float | None = None) -> Tensor:
    """CornerNet's penalty-reduced focal loss (α = 2, β = 4), normalised by the number of object centres
    (``num_pos`` when given: the count over a whole global batch split into micro-batches)."""
    p = torch.sigmoid(logits).clamp(1e-4, 1 - 1e-4)
    pos = target.eq(1).float()
    pos_loss = torch.log(p) * (1 - p).pow(2) * pos
    neg_loss = torch.log(1 - p) * p.pow(2) * (1 - target).pow(4) * (1 - pos)
    denom = pos.sum().clamp(min=1.0) if num_pos is None else max(float(num_pos), 1.0)
    return -(pos_loss.sum() + neg_loss.sum()) / denom


def distillation_loss(student_logits: Tensor, teacher_logits: Tensor, channels: tuple[int, ...],
                      num_pos: float | None = None) -> Tensor:
    """Learning without forgetting on the heatmap: the Bernoulli KL divergence of the student's per-cell class
    probabilities from a fixed teacher's, summed over the cells of ``channels`` and normalised like the focal loss
    (by the object centres, ``num_pos``). Why: a fine-tune that teaches the network new scenes also moves what it
    had learnt of the classes it is not meant to change (docs/detector.md 'Keeping what a fine-tune would
    forget'); this term holds those classes' heatmaps to the teacher's, cell by cell, wherever the scan puts them."""
    idx = list(channels)
    s = student_logits[:, idx]
    t = torch.sigmoid(teacher_logits[:, idx]).clamp(1e-4, 1 - 1e-4)
    log_p, log_q = torch.nn.functional.logsigmoid(s), torch.nn.functional.logsigmoid(-s)
    kl = t * (torch.log(t) - log_p) + (1 - t) * (torch.log(1 - t) - log_q)
    denom = max(float(num_pos), 1.0) if num_pos is not None else 1.0
    return kl.sum() / denom


def loss_normalisers(batch: dict[str, Tensor]) -> Tensor:
    """(heatmap peaks, regression targets) in a batch of targets, float64: what :func:`centerpoint_loss`
    divides by. Summed over the micro-batches of a global batch (and all-reduced over processes) they make
    the split batch's loss exactly the whole batch's."""
    return torch.tensor([float(batch["heatmap"].eq(1).sum()), float(batch["mask"].sum())], dtype=torch.float64)


def gaussian_nll(mean: Tensor, target: Tensor, logvar: Tensor, logvar_min: float = -10.0) -> Tensor:
    """Element-wise ½·exp(−s)·(mean − target)² + ½·s with s clamped at ``logvar_min`` (below it s gets no gradient)."""
    s = logvar.clamp(min=logvar_min)
    return 0.5 * torch.exp(-s) * (mean - target).pow(2) + 0.5 * s


def gather(feature: Tensor, ind: Tensor) -> Tensor:
    """(B, C, H, W) map, (B, K) flat cell indices → (B, K, C)."""
    b, c = feature.shape[:2]
    flat = feature.view(b, c, -1)
    return flat.gather(2, ind.unsqueeze(1).expand(b, c, ind.shape[1])).transpose(1, 2)


def wrap_angle(a: Tensor) -> Tensor:
    return torch.remainder(a + math.pi, 2 * math.pi) - math.pi


def centerpoint_loss(out: dict[str, Tensor], batch: dict[str, Tensor], config: DetectorConfig, *,
                     num_pos: float | None = None, num_obj: float | None = None) -> dict[str, Tensor]:
    """All loss terms of one batch; ``loss`` is what to minimise. ``batch`` holds stacked
    :class:`~.targets.Targets` fields: heatmap (B, C, H, W), ind/mask/yaw (B, K), box (B, K, 10).
    ``num_pos`` / ``num_obj`` replace the batch's own heatmap-peak and object counts as normalisers (a
    micro-batch of a larger global batch, see :func:`loss_normalisers`)."""
    hm = gaussian_focal_loss(out["heatmap"], batch["heatmap"], num_pos)
    ind, mask = batch["ind"], batch["mask"].float()
    tgt = batch["box"]
    num = mask.sum().clamp(min=1.0) if num_obj is None else torch.tensor(max(float(num_obj), 1.0), device=mask.device)
    m = mask.unsqueeze(-1)
    reg = gather(out["reg"], ind)
    height = gather(out["height"], ind)
    dim = gather(out["dim"], ind)
    rot = gather(out["rot"], ind)
    vel = gather(out["vel"], ind)
    l1_shape = ((height - tgt[..., 2:3]).abs() + (dim - tgt[..., 3:6]).abs().sum(-1, keepdim=True)
                + (rot - tgt[..., 6:8]).abs().sum(-1, keepdim=True))
    terms = {"heatmap": hm, "shape": (l1_shape * m).sum() / num}
    if config.uncertainty:
        s = gather(out["logvar"], ind)
        cell = torch.tensor([config.voxel_size[0] * config.out_size_factor,
                             config.voxel_size[1] * config.out_size_factor], dtype=reg.dtype, device=reg.device)
        nll_xy = gaussian_nll(reg * cell, tgt[..., 0:2] * cell, s[..., 0:2], config.logvar_min)
        nll_v = gaussian_nll(vel, tgt[..., 8:10], s[..., 2:4], config.logvar_min)
        # yaw: the NLL trains the variance only; the mean is learned through (sin, cos) above, because
        # atan2's gradient is unbounded where the predicted (sin, cos) is near zero.
        yaw_pred = torch.atan2(rot[..., 0], rot[..., 1]).detach()
        yaw_err = wrap_angle(yaw_pred - batch["yaw"]).unsqueeze(-1)
        nll_yaw = gaussian_nll(torch.zeros_like(yaw_err), yaw_err, s[..., 4:5], config.logvar_min)
        terms["position"] = (nll_xy.sum(-1, keepdim=True) * m).sum() / num
        terms["velocity"] = VEL_WEIGHT * (nll_v.sum(-1, keepdim=True) * m).sum() / num
        terms["yaw_var"] = (nll_yaw * m).sum() / num
    else:
        terms["position"] = ((reg - tgt[..., 0:2]).abs().sum(-1, keepdim=True) * m).sum() / num
        terms["velocity"] = VEL_WEIGHT * ((vel - tgt[..., 8:10]).abs().sum(-1, keepdim=True) * m).sum() / num
    regression = sum(v for k, v in terms.items() if k != "heatmap")
    terms["loss"] = hm + REG_WEIGHT * regression
    return terms
