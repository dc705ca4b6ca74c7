"""CenterPoint-PointPillars in pure PyTorch: PFN → scatter → SECOND → SECONDFPN → CenterHead (+ variance heads).

The head predicts, per BEV cell of the output map: a heatmap per class, the centre offset (reg, 2), height
(1), log dimensions (3), yaw as (sin, cos), velocity (2) and — for the uncertainty-aware model — the
log-variances of x, y, vx, vy, yaw in m², m²/s² and rad² (paper §III-A). The log-variances are clamped to
``config.logvar_min`` (−10) where they are used, not here, so the raw output stays differentiable.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from .config import VAR_NAMES, DetectorConfig
from .pillars import PillarFeatureNet, Pillars, scatter_to_bev, voxelize

HEAD_CHANNELS: dict[str, int] = {"reg": 2, "height": 1, "dim": 3, "rot": 2, "vel": 2}
"""Regression heads and their widths (CenterPoint's ``common_heads``)."""


def _conv_bn_relu(cin: int, cout: int, stride: int = 1) -> list[nn.Module]:
    return [nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False),
            nn.BatchNorm2d(cout, eps=1e-3, momentum=0.1), nn.ReLU(inplace=True)]


class SecondBackbone(nn.Module):
    """SECOND's 2-D backbone: per stage one strided conv and ``layers[i]`` plain convs."""

    def __init__(self, cin: int, layers: tuple[int, ...], strides: tuple[int, ...], channels: tuple[int, ...]) -> None:
        super().__init__()
        blocks = []
        for n, s, c in zip(layers, strides, channels, strict=True):
            mods = _conv_bn_relu(cin, c, s)
            for _ in range(n):
                mods += _conv_bn_relu(c, c)
            blocks.append(nn.Sequential(*mods))
            cin = c
        self.blocks = nn.ModuleList(blocks)

    def forward(self, x: Tensor) -> list[Tensor]:
        outs = []
        for block in self.blocks:
            x = block(x)
            outs.append(x)
        return outs


class SecondFPN(nn.Module):
    """SECONDFPN: bring every stage to one resolution (deconv up, strided conv down) and concatenate."""

    def __init__(self, in_channels: tuple[int, ...], upsample: tuple[float, ...], out_channels: tuple[int, ...]) -> None:
        super().__init__()
        deblocks = []
        for cin, u, cout in zip(in_channels, upsample, out_channels, strict=True):
            if u >= 1:
                k = round(u)
                conv: nn.Module = nn.ConvTranspose2d(cin, cout, k, stride=k, bias=False)
            else:
                k = round(1 / u)
                conv = nn.Conv2d(cin, cout, k, stride=k, bias=False)
            deblocks.append(nn.Sequential(conv, nn.BatchNorm2d(cout, eps=1e-3, momentum=0.1), nn.ReLU(inplace=True)))
        self.deblocks = nn.ModuleList(deblocks)

    def forward(self, feats: list[Tensor]) -> Tensor:
        return torch.cat([d(f) for d, f in zip(self.deblocks, feats, strict=True)], dim=1)


class CenterHead(nn.Module):
    """CenterPoint's single-group head: shared conv, then one separate head per output."""

    def __init__(self, cin: int, config: DetectorConfig) -> None:
        super().__init__()
        hc = config.head_channels
        self.shared = nn.Sequential(*_conv_bn_relu(cin, hc))
        outs = {"heatmap": config.num_classes, **HEAD_CHANNELS}
        if config.uncertainty:
            outs["logvar"] = len(VAR_NAMES)
        heads = {}
        for name, cout in outs.items():
            mods: list[nn.Module] = []
            for _ in range(config.head_conv_layers - 1):
                mods += _conv_bn_relu(hc, hc)
            mods.append(nn.Conv2d(hc, cout, 3, padding=1, bias=True))
            heads[name] = nn.Sequential(*mods)
        self.heads = nn.ModuleDict(heads)
        # CenterPoint's heatmap prior: sigmoid(-2.19) ≈ 0.1, so the focal loss starts sane.
        nn.init.constant_(self.heads["heatmap"][-1].bias, -2.19)
        if config.uncertainty:
            # start at σ ≈ 0.5 (log σ² ≈ -1.4): the NLL's gradients are then moderate from the first step
            nn.init.constant_(self.heads["logvar"][-1].bias, math.log(0.25))
            nn.init.normal_(self.heads["logvar"][-1].weight, std=1e-3)

    def forward(self, x: Tensor) -> dict[str, Tensor]:
        x = self.shared(x)
        return {name: head(x) for name, head in self.heads.items()}


class CenterPointNet(nn.Module):
    """The whole network; ``forward`` takes a list of (P, ≥4) point tensors (sensor frame) and returns raw head maps."""

    def __init__(self, config: DetectorConfig) -> None:
        super().__init__()
        self.config = config
        self.pfn = PillarFeatureNet(config)
        self.backbone = SecondBackbone(config.pfn_channels, config.backbone_layers, config.backbone_strides,
                                       config.backbone_channels)
        self.neck = SecondFPN(config.backbone_channels, config.neck_upsample_strides, config.neck_channels)
        self.head = CenterHead(sum(config.neck_channels), config)

    def forward_pillars(self, pillars: Pillars) -> dict[str, Tensor]:
        bev = scatter_to_bev(self.pfn(pillars), pillars, self.config)
        return self.head(self.neck(self.backbone(bev)))

    def forward(self, points: list[Tensor]) -> dict[str, Tensor]:
        return self.forward_pillars(voxelize(points, self.config))


def with_time_lag(model: CenterPointNet) -> CenterPointNet:
    """A five-field copy of a four-field ``model`` (x, y, z, intensity → plus the time lag of stacked sweeps), for
    fine-tuning single-sweep weights on stacked sweeps (``jitterguard train --init W --sweeps N``): every weight
    carried over and the PFN's new input column zero, so the copy starts out reading the lag as nothing — it
    computes what ``model`` computes on the same points with their lags — and training teaches it the rest."""
    if model.config.num_point_features != 4:
        raise ValueError(f"expected a four-field model, got {model.config.num_point_features} fields")
    wide = CenterPointNet(model.config.model_copy(update={"num_point_features": 5}))
    state = dict(model.state_dict())
    w = state["pfn.linear.weight"]  # (C, 4 + 5): the point's own fields, then the offsets
    state["pfn.linear.weight"] = torch.cat([w[:, :4], w.new_zeros(w.shape[0], 1), w[:, 4:]], dim=1)
    wide.load_state_dict(state)
    return wide.train(model.training)
