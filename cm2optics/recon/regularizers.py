"""Non-negativity, ℓ1 and 3-D total variation, and their proximal operators (torch).

TV is isotropic, ``TV(x) = Σ_voxels √(Σ_a (w_a·∂_a x)²)``, with forward differences (zero past
the last voxel) and per-axis weights ``w_a`` (by default the finest pitch over the axis pitch, so
that a step across a 10-µm axial voxel weighs what it does physically next to 4.15-µm lateral
ones). For a non-negative ``x``, ``‖x‖₁ = Σ x`` is linear, so

    prox_{t(λ₁‖·‖₁ + λ_tv TV + ι₊)}(v) = prox_{tλ_tv TV + ι₊}(v − tλ₁),

and the constrained TV prox is the fast gradient projection (FGP) of Beck & Teboulle (2009) on
the dual, warm-started from the previous call's dual variable.
"""

from __future__ import annotations

import torch

__all__ = ["TV", "axis_weights", "soft_nonneg"]


def axis_weights(voxel_um: tuple[float, float, float]) -> tuple[float, float, float]:
    """Default TV weights per axis (z, y, x): finest pitch / pitch."""
    finest = min(voxel_um)
    return tuple(finest / v for v in voxel_um)  # type: ignore[return-value]


def soft_nonneg(v: torch.Tensor, threshold: float) -> torch.Tensor:
    """prox of threshold·‖x‖₁ + ι₊ : max(v − threshold, 0)."""
    return torch.clamp(v - threshold, min=0.0)


class TV:
    """Weighted isotropic 3-D TV on (z, y, x) tensors; :meth:`prox` keeps its dual for warm starts."""

    def __init__(self, weights: tuple[float, float, float] = (1.0, 1.0, 1.0), iterations: int = 10):
        if any(w < 0 for w in weights):
            raise ValueError(f"TV weights = {weights}: must be ≥ 0")
        self.weights = tuple(float(w) for w in weights)
        self.iterations = int(iterations)
        self.lipschitz = 4.0 * sum(w * w for w in self.weights) or 1.0
        self._dual: torch.Tensor | None = None

    def grad(self, x: torch.Tensor) -> torch.Tensor:
        """Weighted forward differences (3, z, y, x), zero past the last voxel."""
        out = torch.zeros((3,) + tuple(x.shape), dtype=x.dtype, device=x.device)
        for a, w in enumerate(self.weights):
            if w == 0 or x.shape[a] < 2:
                continue
            n = x.shape[a]
            d = x.narrow(a, 1, n - 1) - x.narrow(a, 0, n - 1)
            out[a].narrow(a, 0, n - 1).copy_(d).mul_(w)
        return out

    def grad_adjoint(self, p: torch.Tensor) -> torch.Tensor:
        """Transpose of :meth:`grad` (= minus the divergence)."""
        out = torch.zeros(p.shape[1:], dtype=p.dtype, device=p.device)
        for a, w in enumerate(self.weights):
            if w == 0 or p.shape[1 + a] < 2:
                continue
            n = p.shape[1 + a]
            q = p[a].narrow(a, 0, n - 1) * w
            out.narrow(a, 0, n - 1).sub_(q)
            out.narrow(a, 1, n - 1).add_(q)
        return out

    def value(self, x: torch.Tensor) -> float:
        g = self.grad(x)
        return float(torch.sqrt((g * g).sum(0)).sum())

    def reset(self) -> None:
        self._dual = None

    @torch.no_grad()
    def prox(self, v: torch.Tensor, weight: float, nonneg: bool = True) -> torch.Tensor:
        """argmin_x ½‖x − v‖² + weight·TV(x) (+ x ≥ 0), by FGP on the dual."""
        if weight <= 0:
            return torch.clamp(v, min=0.0) if nonneg else v.clone()
        p = (
            self._dual
            if self._dual is not None and self._dual.shape[1:] == v.shape
            else torch.zeros((3,) + tuple(v.shape), dtype=v.dtype, device=v.device)
        )
        r = p.clone()
        t = 1.0
        step = 1.0 / (self.lipschitz * weight)
        for _ in range(self.iterations):
            x = v - weight * self.grad_adjoint(r)
            if nonneg:
                x.clamp_(min=0.0)
            p_new = r + step * self.grad(x)
            norm = torch.sqrt((p_new * p_new).sum(0)).clamp_(min=1.0)
            p_new /= norm
            t_new = (1.0 + (1.0 + 4.0 * t * t) ** 0.5) / 2.0
            r = p_new + ((t - 1.0) / t_new) * (p_new - p)
            p, t = p_new, t_new
            del x, norm
        self._dual = p
        x = v - weight * self.grad_adjoint(p)
        return torch.clamp(x, min=0.0) if nonneg else x
