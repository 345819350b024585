"""CM²Net's loss: α₁·BCE(demixed views) + α₂·L(volume), the paper's (1, 1) by default.

The volume term is the paper's BCE, or for very sparse volumes a weighted BCE (each voxel's
weight ``1 + (pos_weight − 1)·target``: emitters count ``pos_weight``× as much as background) or
the focal loss (Lin et al. 2017: BCE × (1 − p_t)^γ). Means over voxels (the paper sums; Adam is
indifferent to the scale). The volume term leaves out a ``border`` margin of the patch, where
the refocusing lacks the light shifted in from outside it (see :mod:`~.refocus`).
"""

from __future__ import annotations

import torch
from torch.nn import functional as F

from cm2optics.recon.net.config import NetConfig

__all__ = ["cm2net_loss", "volume_loss"]


def _crop(x: torch.Tensor, border: int) -> torch.Tensor:
    return x[..., border:-border, border:-border] if border > 0 else x


def volume_loss(
    logits: torch.Tensor, target: torch.Tensor, kind: str = "bce", *, pos_weight: float = 10.0, gamma: float = 2.0
) -> torch.Tensor:
    """The volume term on logits and targets in [0, 1] (same shape), a scalar mean."""
    if kind == "bce":
        return F.binary_cross_entropy_with_logits(logits, target)
    if kind == "weighted-bce":
        weight = 1.0 + (pos_weight - 1.0) * target
        return F.binary_cross_entropy_with_logits(logits, target, weight=weight)
    if kind == "focal":
        bce = F.binary_cross_entropy_with_logits(logits, target, reduction="none")
        p = torch.sigmoid(logits)
        p_t = p * target + (1 - p) * (1 - target)
        return ((1 - p_t).pow(gamma) * bce).mean()
    raise ValueError(f"volume loss {kind!r}: must be bce, weighted-bce or focal")


def cm2net_loss(
    demix_logits: torch.Tensor | None,
    volume_logits: torch.Tensor,
    demixed: torch.Tensor,
    volume: torch.Tensor,
    config: NetConfig,
    border: int,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Total loss and its parts (``demix``, ``volume``), detached parts for logging; without a
    demixing net (``demix_logits`` None, the ``no-demix`` ablation) the demixing term is 0."""
    if demix_logits is None:
        l_demix = volume_logits.new_zeros(())
    else:
        l_demix = F.binary_cross_entropy_with_logits(demix_logits, demixed.clamp(0.0, 1.0))
    l_volume = volume_loss(
        _crop(volume_logits, border),
        _crop(volume, border).clamp(0.0, 1.0),
        config.volume_loss,
        pos_weight=config.pos_weight,
        gamma=config.focal_gamma,
    )
    total = config.alpha_demix * l_demix + config.alpha_volume * l_volume
    return total, {"demix": l_demix.detach(), "volume": l_volume.detach()}
