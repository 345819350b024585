"""Model-based reconstruction: FISTA, ADMM (general and the exact depth-wise LSI form) and
Richardson–Lucy, with non-negativity, ℓ1 and 3-D TV (torch, float32).

All solve, for a measurement ``b`` (background removed, or given to RL as ``background``),

    min_x ½‖A x − b‖² + λ₁‖x‖₁ + λ_tv TV(x)   subject to x ≥ 0

(RL: the Poisson likelihood instead of the squared error). ``λ₁`` and ``λ_tv`` are given
*relative* to ``‖Aᵀb‖_∞`` (RL: to the mean of ``Aᵀ1``), so the same values suit any brightness.

- :func:`fista`: accelerated proximal gradient (Beck & Teboulle 2009) with adaptive restart;
  step ``1/L``, ``L = ‖A‖²`` by :func:`power_iteration`; prox = FGP TV with ``x ≥ 0`` after the
  ℓ1 shift (:mod:`cm2optics.recon.regularizers`).
- :func:`admm`: splits ``u = Dx`` (TV) and ``w = x`` (ℓ1, ``x ≥ 0``); the x-update
  ``(AᵀA + μ DᵀD + μ I)x = …`` by a few warm-started conjugate-gradient steps: works with any
  operator (the LSV one).
- :func:`admm_lsi`: the V1 paper's ADMM for a depth-wise LSI operator (Antipa et al. 2018
  splitting ``v = Hx``, ``u = Dx``, ``w = x`` on the FFT canvas): every update is closed form —
  the x-update is diagonal in the 3-D Fourier domain up to one rank-one term per lateral
  frequency (Sherman–Morrison), with circular TV on a z-padded canvas.
- :func:`richardson_lucy`: multiplicative EM updates, non-negative by construction; ℓ1 and TV
  (Dey et al. 2006) enter the denominator.

**Stopping rule** (:class:`Stopping`): stop when the relative change ``‖x_k − x_{k−1}‖/‖x_k‖``
stays below ``tol`` for ``patience`` consecutive iterations, or after ``max_iter``.
"""

from __future__ import annotations

import math
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from cm2optics.formats.operator import VolumeOperator
from cm2optics.lsv.lsi import DepthwiseConvOperator
from cm2optics.recon.regularizers import TV, axis_weights, soft_nonneg

__all__ = ["SolverResult", "Stopping", "admm", "admm_lsi", "fista", "lipschitz", "power_iteration", "richardson_lucy"]

Progress = Callable[[int, int, dict[str, float]], None]


@dataclass(frozen=True)
class Stopping:
    """max_iter: iteration cap. tol: relative-change threshold. patience: consecutive iterations
    below ``tol`` needed to stop."""

    max_iter: int = 100
    tol: float = 1e-3
    patience: int = 3

    def __post_init__(self) -> None:
        if self.max_iter < 1:
            raise ValueError(f"max_iter = {self.max_iter}: must be ≥ 1")
        if not (self.tol >= 0 and math.isfinite(self.tol)):
            raise ValueError(f"tol = {self.tol}: must be a finite number ≥ 0")
        if self.patience < 1:
            raise ValueError(f"patience = {self.patience}: must be ≥ 1")


@dataclass
class SolverResult:
    """volume: (z, y, x) float32 tensor; iterations run; converged (the rule fired before
    max_iter); history: per iteration ``rel_change`` and ``residual`` (‖Ax − b‖/‖b‖ where known);
    lipschitz: ‖A‖² used (FISTA); seconds."""

    volume: torch.Tensor
    iterations: int
    converged: bool
    history: dict[str, list[float]] = field(default_factory=dict)
    lipschitz: float | None = None
    seconds: float = 0.0
    info: dict[str, Any] = field(default_factory=dict)


class _Monitor:
    def __init__(self, stopping: Stopping, progress: Progress | None):
        self.stopping = stopping
        self.progress = progress
        self.calm = 0
        self.history: dict[str, list[float]] = {"rel_change": [], "residual": []}

    def step(self, k: int, previous: torch.Tensor, current: torch.Tensor, residual: float | None = None) -> bool:
        norm = float(torch.linalg.vector_norm(current))
        change = float(torch.linalg.vector_norm(current - previous)) / max(norm, 1e-30)
        self.history["rel_change"].append(change)
        self.history["residual"].append(float("nan") if residual is None else residual)
        self.calm = self.calm + 1 if change < self.stopping.tol and norm > 0 else 0
        if self.progress:
            self.progress(
                k + 1,
                self.stopping.max_iter,
                {"rel_change": change, "residual": residual if residual is not None else float("nan")},
            )
        return self.calm >= self.stopping.patience


def _tensor(data: Any, device: torch.device | None = None) -> torch.Tensor:
    return torch.as_tensor(
        np.asarray(data) if not isinstance(data, torch.Tensor) else data, dtype=torch.float32, device=device
    )


def _device(operator: VolumeOperator) -> torch.device:
    """Where the operator computes (its ``device``; the CPU for operators that state none): the
    solvers keep their volume-sized arrays there."""
    return torch.device(getattr(operator, "device", "cpu"))


#: ‖A‖² per operator object (it depends on nothing else): computed once per operator.
_LIPSCHITZ: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def lipschitz(operator: VolumeOperator) -> float:
    """‖A‖² of ``operator`` (power iteration), cached on the operator object."""
    try:
        return _LIPSCHITZ[operator]
    except (KeyError, TypeError):
        pass
    value = power_iteration(operator)
    try:
        _LIPSCHITZ[operator] = value
    except TypeError:  # not weak-referenceable: no cache
        pass
    return value


@torch.no_grad()
def power_iteration(operator: VolumeOperator, iterations: int = 20, seed: int = 0) -> float:
    """Estimate ‖A‖² (the largest eigenvalue of AᵀA) by power iteration; returns it × 1.02."""
    generator = torch.Generator().manual_seed(seed)
    x = torch.rand(operator.grid.shape, generator=generator, dtype=torch.float32).to(_device(operator))
    x /= torch.linalg.vector_norm(x)
    value = 0.0
    for _ in range(max(int(iterations), 1)):
        y = _tensor(operator.adjoint(operator.forward(x)))
        value = float(torch.linalg.vector_norm(y))
        if value == 0:
            raise ValueError("the operator maps every volume to zero (an empty model?)")
        x = y / value
    return 1.02 * value


def _tv(tv_weights: tuple[float, float, float] | None, operator: VolumeOperator, iterations: int) -> TV:
    return TV(tv_weights if tv_weights is not None else axis_weights(operator.grid.voxel_um), iterations)


@torch.no_grad()
def fista(
    operator: VolumeOperator,
    b: Any,
    *,
    l1: float = 0.0,
    tv: float = 0.0,
    stopping: Stopping = Stopping(),
    lipschitz_value: float | None = None,
    tv_weights: tuple[float, float, float] | None = None,
    tv_iterations: int = 10,
    x0: torch.Tensor | None = None,
    progress: Progress | None = None,
) -> SolverResult:
    """FISTA with restart (see the module docstring). l1, tv: relative weights."""
    start = time.perf_counter()
    device = _device(operator)
    b = _tensor(b, device)
    L = lipschitz_value if lipschitz_value is not None else lipschitz(operator)
    scale = float(_tensor(operator.adjoint(b)).max()) or 1.0
    lam1, lamtv = l1 * scale, tv * scale
    reg = _tv(tv_weights, operator, tv_iterations)
    x = (
        torch.zeros(operator.grid.shape, dtype=torch.float32, device=device)
        if x0 is None
        else _tensor(x0, device).clone()
    )
    y = x.clone()
    t = 1.0
    monitor = _Monitor(stopping, progress)
    b_norm = float(torch.linalg.vector_norm(b)) or 1.0
    converged = False
    k = 0
    for k in range(stopping.max_iter):
        r = _tensor(operator.forward(y)) - b
        residual = float(torch.linalg.vector_norm(r)) / b_norm
        v = y - _tensor(operator.adjoint(r)) / L
        del r
        x_new = reg.prox(v - lam1 / L, lamtv / L) if lamtv > 0 else soft_nonneg(v, lam1 / L)
        del v
        t_new = (1.0 + math.sqrt(1.0 + 4.0 * t * t)) / 2.0
        # adaptive restart (O'Donoghue & Candès): momentum against the step direction
        if float(((y - x_new) * (x_new - x)).sum()) > 0:
            t_new, t = 1.0, 1.0
        y = x_new + ((t - 1.0) / t_new) * (x_new - x)
        done = monitor.step(k, x, x_new, residual)
        x, t = x_new, t_new
        if done:
            converged = True
            break
    return SolverResult(
        x, k + 1, converged, monitor.history, L, time.perf_counter() - start, {"l1_abs": lam1, "tv_abs": lamtv}
    )


def _cg(
    apply: Callable[[torch.Tensor], torch.Tensor], rhs: torch.Tensor, x: torch.Tensor, iterations: int
) -> torch.Tensor:
    r = rhs - apply(x)
    p = r.clone()
    rr = float((r * r).sum())
    for _ in range(iterations):
        if rr <= 1e-30:
            break
        Ap = apply(p)
        alpha = rr / max(float((p * Ap).sum()), 1e-30)
        x = x + alpha * p
        r = r - alpha * Ap
        rr_new = float((r * r).sum())
        p = r + (rr_new / rr) * p
        rr = rr_new
    return x


def _shrink_iso(g: torch.Tensor, threshold: float) -> torch.Tensor:
    """Isotropic vector shrinkage of (3, …) fields."""
    norm = torch.sqrt((g * g).sum(0, keepdim=True))
    return g * torch.clamp(1.0 - threshold / torch.clamp(norm, min=1e-30), min=0.0)


@torch.no_grad()
def admm(
    operator: VolumeOperator,
    b: Any,
    *,
    l1: float = 0.0,
    tv: float = 0.0,
    mu: float = 0.05,
    cg_iterations: int = 3,
    stopping: Stopping = Stopping(),
    lipschitz_value: float | None = None,
    tv_weights: tuple[float, float, float] | None = None,
    progress: Progress | None = None,
) -> SolverResult:
    """ADMM for any operator (see the module docstring). mu: penalty relative to ‖A‖²."""
    start = time.perf_counter()
    device = _device(operator)
    b = _tensor(b, device)
    L = lipschitz_value if lipschitz_value is not None else lipschitz(operator)
    Atb = _tensor(operator.adjoint(b))
    scale = float(Atb.max()) or 1.0
    lam1, lamtv = l1 * scale, tv * scale
    m = mu * L
    reg = _tv(tv_weights, operator, 0)
    x = torch.zeros(operator.grid.shape, dtype=torch.float32, device=device)
    w = x.clone()
    rho = x.clone()
    use_tv = lamtv > 0
    u = reg.grad(x) if use_tv else None
    eta = torch.zeros_like(u) if use_tv else None

    def normal(v: torch.Tensor) -> torch.Tensor:
        out = _tensor(operator.adjoint(_tensor(operator.forward(v)))) + m * v
        if use_tv:
            out += m * reg.grad_adjoint(reg.grad(v))
        return out

    monitor = _Monitor(stopping, progress)
    b_norm = float(torch.linalg.vector_norm(b)) or 1.0
    converged = False
    k = 0
    for k in range(stopping.max_iter):
        rhs = Atb + (m * w - rho)
        if use_tv:
            rhs += reg.grad_adjoint(m * u - eta)
        x = _cg(normal, rhs, x, cg_iterations)
        del rhs
        if use_tv:
            dx = reg.grad(x)
            u = _shrink_iso(dx + eta / m, lamtv / m)
            eta += m * (dx - u)
            del dx
        w_new = soft_nonneg(x + rho / m, lam1 / m)
        rho += m * (x - w_new)
        residual = float(torch.linalg.vector_norm(_tensor(operator.forward(w_new)) - b)) / b_norm if progress else None
        done = monitor.step(k, w, w_new, residual)
        w = w_new
        if done:
            converged = True
            break
    return SolverResult(
        w,
        k + 1,
        converged,
        monitor.history,
        L,
        time.perf_counter() - start,
        {"l1_abs": lam1, "tv_abs": lamtv, "mu_abs": m},
    )


#: The Fourier pieces of the closed-form LSI ADMM, per operator (the latest parameters only).
_LSI_SETUP: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _lsi_setup(
    operator: DepthwiseConvOperator, nzp: int, mu: tuple[float, float, float], weights: tuple, use_tv: bool
) -> tuple:
    """K̂ (z-padded), a = F_z conj(K̂), Λ = μ_tv·|D̂|² + μ_w, a/Λ, 1 + μ_v·aᴴΛ⁻¹a and max Σ|K̂|²."""
    key = (nzp, mu, weights, use_tv)
    cached = _LSI_SETUP.get(operator)
    if cached is not None and cached[0] == key:
        return cached[1]
    nz = operator.grid.shape[0]
    Hc, Wc = operator.canvas_shape
    Wf = Wc // 2 + 1
    K = torch.zeros((nzp, Hc, Wf), dtype=torch.complex64)
    K[:nz] = operator.kernel_spectra()
    norm_sq = float((K.abs() ** 2).sum(0).max()) or 1.0
    mu_v, mu_u, mu_w = mu[0], mu[1] * norm_sq, mu[2] * norm_sq
    a = torch.fft.fft(torch.conj(K), dim=0, norm="ortho")
    freq = [torch.fft.fftfreq(nzp), torch.fft.fftfreq(Hc), torch.fft.rfftfreq(Wc)]
    lam = torch.full((nzp, Hc, Wf), mu_w, dtype=torch.float32)
    if use_tv:
        for axis, (f, wgt) in enumerate(zip(freq, weights, strict=True)):
            shape = [1, 1, 1]
            shape[axis] = -1
            lam += mu_u * (wgt**2) * (2.0 - 2.0 * torch.cos(2.0 * math.pi * f)).reshape(shape).float()
    a_over = a / lam
    denom = 1.0 + mu_v * (torch.conj(a) * a_over).real.sum(0)  # (Hc, Wf)
    value = (K, a, lam, a_over, denom, norm_sq)
    try:
        _LSI_SETUP[operator] = (key, value)
    except TypeError:
        pass
    return value


def _lsi_canvas(
    operator: DepthwiseConvOperator, b: torch.Tensor, K: torch.Tensor, nzp: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, float]:
    """The closed-form ADMM's canvas pieces: the sensor mask, Cᵀb, the volume's support on the
    z-padded canvas, and the scale of Aᵀb (its maximum, 1 when none) that the weights refer to."""
    nz = operator.grid.shape[0]
    Hc, Wc = operator.canvas_shape
    mask = operator.sensor_mask_canvas()
    Ctb = operator.sensor_to_canvas(b)
    support = torch.zeros((nzp, Hc, Wc), dtype=torch.float32)
    ny, nx = operator.grid.shape[1:]
    support[:nz, :ny, :nx] = 1.0
    Atb_scale = (
        float(torch.fft.irfft2(torch.fft.rfft2(Ctb)[None] * torch.conj(K[:nz]), s=(Hc, Wc))[:, :ny, :nx].max()) or 1.0
    )
    return mask, Ctb, support, Atb_scale


def _periodic_gradient(weights: tuple) -> tuple[Callable, Callable]:
    """D (weighted forward differences along z, y, x with periodic wrap, stacked) and its adjoint Dᵀ."""

    def D(x: torch.Tensor) -> torch.Tensor:
        return torch.stack([wgt * (torch.roll(x, -1, dims=axis) - x) for axis, wgt in enumerate(weights)])

    def Dt(p: torch.Tensor) -> torch.Tensor:
        return sum(wgt * (torch.roll(p[axis], 1, dims=axis) - p[axis]) for axis, wgt in enumerate(weights))

    return D, Dt


def _lsi_residual(
    operator: DepthwiseConvOperator, w: torch.Tensor, K: torch.Tensor, b: torch.Tensor, b_norm: float
) -> float:
    """‖A w − b‖ / ‖b‖ for a z-padded canvas volume ``w`` (K̂ its kernel spectra)."""
    Hc, Wc = operator.canvas_shape
    model_image = torch.fft.irfft2((torch.fft.rfft2(w) * K).sum(0), s=(Hc, Wc))
    return float(torch.linalg.vector_norm(operator.canvas_to_sensor(model_image) - b)) / b_norm


@torch.no_grad()
def admm_lsi(
    operator: DepthwiseConvOperator,
    b: Any,
    *,
    l1: float = 0.0,
    tv: float = 0.0,
    mu: tuple[float, float, float] = (1.0, 0.05, 0.05),
    z_pad: int = 2,
    stopping: Stopping = Stopping(),
    tv_weights: tuple[float, float, float] | None = None,
    progress: Progress | None = None,
) -> SolverResult:
    """The V1 paper's ADMM for a :class:`~cm2optics.lsv.lsi.DepthwiseConvOperator` (see
    the module docstring). mu: (μ_v, μ_tv, μ_w), the last two relative to max |K̂|² (the
    operator's ‖A‖² on the canvas)."""
    start = time.perf_counter()
    b = _tensor(b)
    nz = operator.grid.shape[0]
    Hc, Wc = operator.canvas_shape
    nzp = nz + max(int(z_pad), 1)
    weights = tuple(tv_weights if tv_weights is not None else axis_weights(operator.grid.voxel_um))
    use_tv = tv > 0
    K, a, lam, a_over, denom, norm_sq = _lsi_setup(operator, nzp, tuple(float(m) for m in mu), weights, use_tv)
    mu_v, mu_u, mu_w = float(mu[0]), float(mu[1]) * norm_sq, float(mu[2]) * norm_sq
    mask, Ctb, support, Atb_scale = _lsi_canvas(operator, b, K, nzp)
    lam1, lamtv = l1 * Atb_scale, tv * Atb_scale
    D, Dt = _periodic_gradient(weights)
    x = torch.zeros((nzp, Hc, Wc), dtype=torch.float32)
    w, rho = x.clone(), x.clone()
    Hx = torch.zeros((Hc, Wc), dtype=torch.float32)
    xi = torch.zeros_like(Hx)
    Dx = torch.zeros((3, nzp, Hc, Wc), dtype=torch.float32) if use_tv else None
    eta = torch.zeros_like(Dx) if use_tv else None
    monitor = _Monitor(stopping, progress)
    b_norm = float(torch.linalg.vector_norm(b)) or 1.0
    converged = False
    k = 0
    for k in range(stopping.max_iter):
        v = (Ctb + mu_v * Hx + xi) / (mask + mu_v)
        w_new = soft_nonneg(x + rho / mu_w, lam1 / mu_w) * support
        rhs = mu_w * w_new - rho
        if use_tv:
            u = _shrink_iso(Dx + eta / mu_u, lamtv / mu_u)
            rhs += Dt(mu_u * u - eta)
        # Hᵀ(μ_v v − ξ) in the (kz, ky, kx) domain is a · rfft2(μ_v v − ξ)
        R = torch.fft.fft(torch.fft.rfft2(rhs), dim=0, norm="ortho")
        R += a * torch.fft.rfft2(mu_v * v - xi)[None]
        del rhs
        R /= lam
        coef = mu_v * (torch.conj(a) * R).sum(0) / denom
        R -= a_over * coef[None]
        Xz = torch.fft.ifft(R, dim=0, norm="ortho")  # per-plane spectra of the new x
        del R
        x = torch.fft.irfft2(Xz, s=(Hc, Wc))
        Hx = torch.fft.irfft2((Xz * K).sum(0), s=(Hc, Wc))
        del Xz
        xi += mu_v * (Hx - v)
        rho += mu_w * (x - w_new)
        if use_tv:
            Dx = D(x)
            eta += mu_u * (Dx - u)
        last = k == stopping.max_iter - 1
        residual = _lsi_residual(operator, w_new, K, b, b_norm) if k % 10 == 9 or last else None
        done = monitor.step(k, w, w_new, residual)
        w = w_new
        if done:
            converged = True
            break
    volume = operator.canvas_to_volume(w[:nz])
    return SolverResult(
        volume.contiguous(),
        k + 1,
        converged,
        monitor.history,
        norm_sq,
        time.perf_counter() - start,
        {"l1_abs": lam1, "tv_abs": lamtv, "canvas": [nzp, Hc, Wc]},
    )


@torch.no_grad()
def richardson_lucy(
    operator: VolumeOperator,
    b: Any,
    *,
    background: float = 0.0,
    l1: float = 0.0,
    tv: float = 0.0,
    stopping: Stopping = Stopping(),
    tv_weights: tuple[float, float, float] | None = None,
    progress: Progress | None = None,
) -> SolverResult:
    """Richardson–Lucy (see the module docstring); ``background``: constant added to the model
    image (the sensor offset), in b's units."""
    start = time.perf_counter()
    device = _device(operator)
    b = torch.clamp(_tensor(b, device), min=0.0)
    ones = _tensor(operator.adjoint(torch.ones_like(b)))
    sens = float(ones.mean()) or 1.0
    floor = 1e-6 * float(ones.max())
    lam1, lamtv = l1 * sens, tv * sens
    reg = _tv(tv_weights, operator, 0)
    total = float(torch.clamp(b - background, min=0.0).sum())
    x = torch.full(operator.grid.shape, total / max(float(ones.sum()), 1e-30), dtype=torch.float32, device=device)
    monitor = _Monitor(stopping, progress)
    b_norm = float(torch.linalg.vector_norm(b)) or 1.0
    eps = 1e-6 * (float(b.max()) or 1.0)
    converged = False
    k = 0
    for k in range(stopping.max_iter):
        estimate = _tensor(operator.forward(x)) + background
        residual = float(torch.linalg.vector_norm(estimate - b)) / b_norm
        correction = _tensor(operator.adjoint(b / torch.clamp(estimate, min=eps)))
        del estimate
        denominator = ones + lam1
        if lamtv > 0:
            g = reg.grad(x)
            g /= torch.sqrt((g * g).sum(0, keepdim=True)) + 1e-6 * (float(x.max()) or 1.0)
            denominator = denominator + lamtv * reg.grad_adjoint(g)
            del g
        x_new = x * correction / torch.clamp(denominator, min=floor)
        del correction, denominator
        done = monitor.step(k, x, x_new, residual)
        x = x_new
        if done:
            converged = True
            break
    return SolverResult(
        x, k + 1, converged, monitor.history, None, time.perf_counter() - start, {"l1_abs": lam1, "tv_abs": lamtv}
    )
