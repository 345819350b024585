"""The CM²Net network (Xue et al., Optica 2022, Section 2.3 and Supplement 1), in torch.

::

    views (B, 9, H, W) ──demix──► demixed logits (B, 9, H, W) ──σ──► demixed views
        demixed ──shift-and-add (N planes, not learned)──► refocused (B, N, H, W)
                ──resample N → P (1×1, initialised as linear interpolation in z)──► enhancement ─┐
        demixed ──view synthesis (9 → P)─────────────────────────────────────────────────────────┤ +
                                                                         fusion ◄────────────────┘
                                                              volume logits (B, P, H, W)

Every sub-network is a 3×3 convolution to ``channels`` maps, a PReLU, ``blocks`` residual blocks
(conv–BN–PReLU–conv–BN plus the identity) and a 3×3 convolution to its outputs. Everything is a
convolution with 'same' padding, so the network takes any H × W: patches in training, the full
field in one pass at inference. The outputs are logits (σ gives the demixed views and the volume
in [0, 1], the BCE targets); the last biases start at a sparse prior (σ(−4) ≈ 2 %).

Normalisation ``batch`` is :class:`SyncBatchNorm2d`: batch statistics pooled over the
distributed ranks (gloo or NCCL, differentiable), so a DDP run computes what one process does
with the same global batch; ``group`` (GroupNorm, per sample) and ``none`` are options.

Ablations (``config.ablation``, the paper's Fig. 4): ``no-demix`` feeds the raw views to both
branches (no demixing net; the demixed-logits output is None), ``enhancement-only`` and
``synthesis-only`` keep one branch before the fusion.
"""

from __future__ import annotations

import copy
import math

import numpy as np
import torch
import torch.distributed as dist
from torch import nn

from cm2optics.recon.net.config import NetConfig
from cm2optics.recon.net.refocus import RefocusPlanes, ShiftAndAdd

__all__ = ["CM2Net", "ResBlock", "SyncBatchNorm2d", "build_net", "fused_for_inference"]

#: Initial bias of the output layers: sparse outputs from the start.
PRIOR_LOGIT = -4.0


class SyncBatchNorm2d(nn.BatchNorm2d):
    """BatchNorm2d whose training statistics are pooled over all ranks of an initialised
    process group (any backend, CPU included); alone it is :class:`torch.nn.BatchNorm2d`."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not (self.training and dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1):
            return super().forward(x)
        from torch.distributed.nn.functional import all_reduce

        C = x.shape[1]
        count = torch.full((1,), float(x.numel() // C), dtype=x.dtype, device=x.device)
        packed = torch.cat([x.sum(dim=(0, 2, 3)), (x * x).sum(dim=(0, 2, 3)), count])
        packed = all_reduce(packed)  # sums over ranks, gradients flow back to every rank
        total = packed[-1]
        mean = packed[:C] / total
        var = (packed[C : 2 * C] / total - mean * mean).clamp_min(0.0)
        if self.track_running_stats and self.running_mean is not None:
            with torch.no_grad():
                n = float(total)
                momentum = self.momentum if self.momentum is not None else 1.0 / float(self.num_batches_tracked + 1)
                self.running_mean.mul_(1 - momentum).add_(momentum * mean.detach())
                self.running_var.mul_(1 - momentum).add_(momentum * var.detach() * n / max(n - 1.0, 1.0))
                self.num_batches_tracked.add_(1)
        y = (x - mean[None, :, None, None]) * torch.rsqrt(var + self.eps)[None, :, None, None]
        if self.affine:
            y = y * self.weight[None, :, None, None] + self.bias[None, :, None, None]
        return y


def _norm(kind: str, channels: int) -> nn.Module:
    if kind == "batch":
        return SyncBatchNorm2d(channels)
    if kind == "group":
        groups = math.gcd(8, channels)
        return nn.GroupNorm(groups, channels)
    return nn.Identity()


def _conv(cin: int, cout: int, k: int = 3, bias: bool = True) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, k, padding=k // 2, bias=bias)


class ResBlock(nn.Module):
    """x + BN(conv(PReLU(BN(conv(x)))))."""

    def __init__(self, channels: int, norm: str = "batch"):
        super().__init__()
        bias = norm == "none"
        self.body = nn.Sequential(
            _conv(channels, channels, bias=bias),
            _norm(norm, channels),
            nn.PReLU(channels),
            _conv(channels, channels, bias=bias),
            _norm(norm, channels),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.body(x)


def _branch(cin: int, cout: int, channels: int, blocks: int, norm: str) -> nn.Sequential:
    layers: list[nn.Module] = [_conv(cin, channels), nn.PReLU(channels)]
    layers += [ResBlock(channels, norm) for _ in range(blocks)]
    layers.append(_conv(channels, cout))
    return nn.Sequential(*layers)


class CM2Net(nn.Module):
    """The network (see the module docstring). ``planes``: the refocusing planes and shifts
    (from the forward model's geometry); ``z_out_mm``: the P output planes' depths, mm."""

    def __init__(self, config: NetConfig, planes: RefocusPlanes, z_out_mm: np.ndarray):
        super().__init__()
        J = int(planes.shifts_px.shape[1])
        C, B, P, N = config.channels, config.blocks, config.n_planes, planes.n_planes
        if len(z_out_mm) != P:
            raise ValueError(f"{len(z_out_mm)} output depths for n_planes = {P}")
        self.n_views, self.n_planes, self.n_refocus = J, P, N
        self.ablation = config.ablation
        self.demix = _branch(J, J, C, B, config.norm) if config.ablation != "no-demix" else None
        self.refocus = ShiftAndAdd(planes.shifts_px)
        self.register_buffer("refocus_z_mm", torch.as_tensor(planes.z_mm, dtype=torch.float64))
        self.register_buffer("refocus_disparity_px", torch.as_tensor(planes.disparity_px, dtype=torch.float64))
        self.register_buffer("volume_z_mm", torch.as_tensor(np.asarray(z_out_mm, float), dtype=torch.float64))
        self.resample = self.enhance = self.synthesis = None
        if config.ablation != "synthesis-only":
            self.resample = nn.Conv2d(N, P, 1, bias=False)
            with torch.no_grad():
                self.resample.weight.copy_(torch.from_numpy(planes.resampling(z_out_mm))[:, :, None, None])
            self.enhance = _branch(P, P, C, B, config.norm)
        if config.ablation != "enhancement-only":
            self.synthesis = _branch(J, P, C, B, config.norm)
        self.fusion = _branch(P, P, C, config.fusion_blocks, config.norm)
        with torch.no_grad():
            for head in (self.demix, self.fusion):
                if head is not None:
                    head[-1].bias.fill_(PRIOR_LOGIT)

    @property
    def planes(self) -> RefocusPlanes:
        return RefocusPlanes(
            self.refocus_z_mm.cpu().numpy(), self.refocus_disparity_px.cpu().numpy(), self.refocus.shifts.cpu().numpy()
        )

    def forward(self, views: torch.Tensor) -> tuple[torch.Tensor | None, torch.Tensor]:
        """views (B, J, H, W) → (demixed logits (B, J, H, W), or None without demixing; volume
        logits (B, P, H, W))."""
        if views.ndim != 4 or views.shape[1] != self.n_views:
            raise ValueError(f"views must be (B, {self.n_views}, H, W), got shape {tuple(views.shape)}")
        demix_logits = self.demix(views) if self.demix is not None else None
        demixed = torch.sigmoid(demix_logits) if demix_logits is not None else views
        fused = 0.0
        if self.enhance is not None:
            fused = fused + self.enhance(self.resample(self.refocus(demixed)))
        if self.synthesis is not None:
            fused = fused + self.synthesis(demixed)
        return demix_logits, self.fusion(fused)

    def parameter_count(self) -> int:
        return sum(p.numel() for p in self.parameters())


def build_net(config: NetConfig, planes: RefocusPlanes, z_out_mm: np.ndarray, *, seed: int | None = None) -> CM2Net:
    """A freshly initialised network (weights from ``seed``, default ``config.seed``)."""
    state = torch.random.get_rng_state()
    torch.manual_seed(config.seed if seed is None else seed)
    try:
        return CM2Net(config, planes, z_out_mm)
    finally:
        torch.random.set_rng_state(state)


def fused_for_inference(net: CM2Net) -> CM2Net:
    """A copy of ``net`` in eval mode with every convolution–batch-norm pair folded into one
    convolution (the running statistics: the same outputs up to float rounding, one pass over the
    feature maps fewer per pair)."""
    from torch.nn.utils.fusion import fuse_conv_bn_eval

    fused = copy.deepcopy(net).eval()
    for module in fused.modules():
        if isinstance(module, nn.Sequential):
            for i in range(len(module) - 1):
                if isinstance(module[i], nn.Conv2d) and isinstance(module[i + 1], nn.BatchNorm2d):
                    module[i] = fuse_conv_bn_eval(module[i], module[i + 1])
                    module[i + 1] = nn.Identity()
    return fused
