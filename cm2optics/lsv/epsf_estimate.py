"""An effective-PSF basis estimated from whole-pixel frames (measured scans).

A measured scan has whole pixels only, but every calibration node sees its foci at a different
sub-pixel phase: the nodes together sample the ePSF on a grid finer than the pixels (the idea of
Anderson & King's ePSF, PASP 2000, and of photutils' ``EPSFBuilder``, here with a low-rank basis
instead of one ePSF). The basis and the coefficients are estimated jointly, alternating:

* **coefficients given the basis**: per node, a K-term least-squares fit of its J foci;
* **basis given the coefficients** (per lenslet, since the lenslets share only the
  coefficients): least squares over the fine samples, ``Σ_n ‖D_n(Σ_k c_nk·B_k) − y_n‖² +
  λ·‖∇²B‖²``, by conjugate gradients; the Laplacian prior fills the fine samples that the nodes'
  phases leave uncovered and keeps the estimate smooth where they are sparse.

``D_n`` samples a fine patch at the pixels of node n (``y_n``, the whole-pixel window of the
prepared image around each focus, not resampled): fine coordinate ``(m − f)·S + S·(h//2)`` for
pixel m and chief ray f, by linear interpolation on the fine grid (the ePSF is well sampled
there). The start is the whole-pixel SVD, upsampled (Keys). :func:`phase_coverage` says how many
of the S × S fine phases the nodes visit, per lenslet (how well-conditioned the estimate is).
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from cm2optics.lsv.decompose import Decomposition
from cm2optics.lsv.epsf import sampling_matrix

if TYPE_CHECKING:  # pragma: no cover
    from cm2optics.formats.scan import ScanIndex
    from cm2optics.lsv.preprocess import Geometry

__all__ = ["estimate_epsf_basis", "phase_coverage", "pixel_windows"]

#: Positions whose foci's phases all lie within this (px) of each other share one phase.
SINGLE_PHASE_PX = 0.02


def phase_coverage(geometry: Geometry, positions_mm: np.ndarray, oversample: int) -> dict[str, Any]:
    """Share of the S × S sub-pixel phase bins that the scan's foci visit, per lenslet, and
    whether all foci of every lenslet share one phase (then nothing finer can be estimated)."""
    S = int(oversample)
    focus = geometry.focus(positions_mm[:, 0], positions_mm[:, 1], positions_mm[:, 2])  # (N, J, 2)
    frac = focus - np.floor(focus)
    bins = np.minimum((frac * S).astype(np.int64), S - 1)
    flat = bins[..., 0] * S + bins[..., 1]  # (N, J)
    per_lenslet = [len(np.unique(flat[:, j])) / S**2 for j in range(flat.shape[1])]
    counts = [np.bincount(flat[:, j], minlength=S * S) for j in range(flat.shape[1])]
    # circular spread of the phases along each axis
    angle = 2 * np.pi * frac
    spread = 1.0 - np.abs(np.exp(1j * angle).mean(axis=0))  # (J, 2), 0 when all equal
    single = bool(np.all(spread < (2 * np.pi * SINGLE_PHASE_PX) ** 2 / 2))
    return {
        "oversample": S,
        "bins_visited_per_lenslet": [round(v, 3) for v in per_lenslet],
        "min_bins_visited": round(float(min(per_lenslet)), 3),
        "min_nodes_per_bin": int(min(c.min() for c in counts)),
        "single_phase": single,
    }


def pixel_windows(index: ScanIndex, geometry: Geometry, patch: tuple[int, int], progress=None):
    """Whole-pixel windows (N, J, h, w) of the prepared images whose pixel (h//2, w//2) holds
    each focus's chief ray (no resampling), and the chief rays' fractions ``eps`` (N, J, 2) past
    the window's pixel grid: pixel r of a window is at patch coordinate ``r − eps``."""
    from cm2optics.lsv.preprocess import prepared_image

    h, w = patch
    J = geometry.n_lenslets
    focus = geometry.focus(index.positions_mm[:, 0], index.positions_mm[:, 1], index.positions_mm[:, 2])
    base = np.floor(focus).astype(np.int64)
    eps = focus - base
    out = np.zeros((len(index), J, h, w), np.float32)
    for n in range(len(index)):
        image = prepared_image(index, n)
        H, W = image.shape
        for j in range(J):
            r0, c0 = base[n, j, 0] - h // 2, base[n, j, 1] - w // 2
            rs, re, cs, ce = max(r0, 0), min(r0 + h, H), max(c0, 0), min(c0 + w, W)
            if rs < re and cs < ce:
                out[n, j, rs - r0 : re - r0, cs - c0 : ce - c0] = image[rs:re, cs:ce]
        if progress:
            progress("pixel windows", n + 1, len(index))
    return out, eps


class _Sampler:
    """D_n for all nodes of one lenslet: linear interpolation of (hS, wS) fine patches at the
    fine coordinates (r − eps)·S of the window pixels, as two gathers per axis."""

    def __init__(self, eps: np.ndarray, h: int, w: int, S: int):
        self.h, self.w, self.S = h, w, S
        self.hS, self.wS = h * S, w * S
        self.rows = [self._axis(eps[:, 0], h, S, self.hS)]
        self.cols = [self._axis(eps[:, 1], w, S, self.wS)]

    @staticmethod
    def _axis(eps: np.ndarray, n: int, S: int, nf: int):
        u = (np.arange(n)[None, :] - eps[:, None]) * S  # (N, n)
        a0 = np.floor(u).astype(np.int64)
        t = u - a0
        w0 = np.where((a0 >= 0) & (a0 < nf), 1 - t, 0.0)
        w1 = np.where((a0 + 1 >= 0) & (a0 + 1 < nf), t, 0.0)
        return (
            torch.as_tensor(np.clip(a0, 0, nf - 1)),
            torch.as_tensor(np.clip(a0 + 1, 0, nf - 1)),
            torch.as_tensor(w0, dtype=torch.float32),
            torch.as_tensor(w1, dtype=torch.float32),
        )

    def forward(self, fine: torch.Tensor, nodes: slice) -> torch.Tensor:
        """(n, hS, wS) → (n, h, w) for the nodes ``nodes``."""
        i0, i1, w0, w1 = (t[nodes] for t in self.rows[0])
        rows = torch.gather(fine, 1, i0[:, :, None].expand(-1, -1, self.wS)) * w0[:, :, None]
        rows += torch.gather(fine, 1, i1[:, :, None].expand(-1, -1, self.wS)) * w1[:, :, None]
        i0, i1, w0, w1 = (t[nodes] for t in self.cols[0])
        out = torch.gather(rows, 2, i0[:, None, :].expand(-1, self.h, -1)) * w0[:, None, :]
        out += torch.gather(rows, 2, i1[:, None, :].expand(-1, self.h, -1)) * w1[:, None, :]
        return out

    def adjoint(self, image: torch.Tensor, nodes: slice) -> torch.Tensor:
        """(n, h, w) → (n, hS, wS), the transpose of :meth:`forward`."""
        n = image.shape[0]
        i0, i1, w0, w1 = (t[nodes] for t in self.cols[0])
        rows = torch.zeros((n, self.h, self.wS), dtype=image.dtype)
        rows.scatter_add_(2, i0[:, None, :].expand(-1, self.h, -1), image * w0[:, None, :])
        rows.scatter_add_(2, i1[:, None, :].expand(-1, self.h, -1), image * w1[:, None, :])
        i0, i1, w0, w1 = (t[nodes] for t in self.rows[0])
        out = torch.zeros((n, self.hS, self.wS), dtype=image.dtype)
        out.scatter_add_(1, i0[:, :, None].expand(-1, -1, self.wS), rows * w0[:, :, None])
        out.scatter_add_(1, i1[:, :, None].expand(-1, -1, self.wS), rows * w1[:, :, None])
        return out


def _laplacian(x: torch.Tensor) -> torch.Tensor:
    """5-point Laplacian of (…, a, b) with zero outside (self-adjoint)."""
    p = torch.nn.functional.pad(x, (1, 1, 1, 1))
    return p[..., :-2, 1:-1] + p[..., 2:, 1:-1] + p[..., 1:-1, :-2] + p[..., 1:-1, 2:] - 4 * x


def _upsample(basis: np.ndarray, S: int) -> np.ndarray:
    """Keys upsampling of (…, h, w) whole-pixel patches to (…, h·S, w·S), fine sample a at a/S."""
    h, w = basis.shape[-2:]
    rows = sampling_matrix(np.arange(h * S) / S, h)
    cols = sampling_matrix(np.arange(w * S) / S, w)
    return np.einsum("ar,...rc,bc->...ab", rows, basis.astype(np.float64), cols).astype(np.float32)


def estimate_epsf_basis(
    index: ScanIndex,
    geometry: Geometry,
    decomposition: Decomposition,
    crops: np.ndarray,
    oversample: int,
    *,
    iterations: int = 3,
    cg_steps: int = 15,
    smoothness: float = 1e-3,
    keep: np.ndarray | None = None,
    windows: tuple[np.ndarray, np.ndarray] | None = None,
    progress=None,
) -> tuple[Decomposition, dict[str, Any]]:
    """Estimate an ePSF basis (K, J, h·S, w·S) and coefficients from the scan's whole-pixel
    frames, starting from the whole-pixel ``decomposition`` of the registered ``crops`` (N, J,
    h, w). ``smoothness``: λ of the Laplacian prior, relative to the data term's mean curvature
    (‖C‖²/(K·S²)). ``keep``: the nodes (boolean, N) to estimate from (held-out checks; the others'
    coefficients are returned as zeros); ``windows``: :func:`pixel_windows` already read.
    Returns the new decomposition (orthonormal basis, singular values) and a report."""
    start = time.perf_counter()
    S = int(oversample)
    K, J, h, w = decomposition.basis.shape
    N_all = crops.shape[0]
    y_np, eps = windows if windows is not None else pixel_windows(index, geometry, (h, w), progress=progress)
    keep = np.ones(N_all, bool) if keep is None else np.asarray(keep, bool)
    y_np, eps = y_np[keep], eps[keep]
    y = torch.as_tensor(y_np)
    B = torch.as_tensor(_upsample(decomposition.basis, S))  # (K, J, hS, wS)
    C = torch.as_tensor(decomposition.coefficients[keep], dtype=torch.float32)  # (N, K)
    samplers = [_Sampler(eps[:, j], h, w, S) for j in range(J)]
    data_energy = float((y.double() ** 2).sum())
    # relative to the data term's scale: CᵀC (mean eigenvalue ‖C‖²/K) times DᵀD (≈ 1/S² per fine sample)
    lam = smoothness * float((C.double() ** 2).sum()) / (K * S * S)
    history = [_misfit(C, B, y, samplers) / data_energy]
    for _ in range(iterations):
        _basis_step(B, C, y, samplers, lam, cg_steps)
        C = _coefficient_step(B, y, samplers)
        history.append(_misfit(C, B, y, samplers) / data_energy)
    new = _orthonormal(C, B, keep, N_all, decomposition)
    report = {
        "method": "alternating least squares over whole-pixel frames (ePSF basis | coefficients)",
        "iterations": iterations,
        "cg_steps": cg_steps,
        "smoothness": smoothness,
        "pixel_misfit_nmse_per_iteration": [round(v, 5) for v in history],
        "seconds": round(time.perf_counter() - start, 2),
        "phase_coverage": phase_coverage(geometry, index.positions_mm, S),
    }
    return new, report


def _predict(C: torch.Tensor, B: torch.Tensor, sampler: _Sampler, j: int) -> torch.Tensor:
    """Lenslet j's whole-pixel windows (N, h, w) of the fine patches C·B[:, j] (N, h·S, w·S)."""
    K = B.shape[0]
    N = C.shape[0]
    fine = (C @ B[:, j].reshape(K, -1)).reshape(N, sampler.hS, sampler.wS)
    return sampler.forward(fine, slice(0, N))


def _misfit(C: torch.Tensor, B: torch.Tensor, y: torch.Tensor, samplers: list[_Sampler]) -> float:
    """The summed squared misfit (frames' units²) of every lenslet's predicted windows to the frames ``y``."""
    return sum(float(((_predict(C, B, samplers[j], j) - y[:, j]).double() ** 2).sum()) for j in range(len(samplers)))


def _cg(normal, rhs: torch.Tensor, X: torch.Tensor, steps: int) -> torch.Tensor:
    """``steps`` conjugate-gradient iterations on normal(X) = rhs from X (updated in place and returned)."""
    r = rhs - normal(X)
    p = r.clone()
    rr = float((r * r).sum())
    for _ in range(steps):
        Ap = normal(p)
        alpha = rr / max(float((p * Ap).sum()), 1e-300)
        X += alpha * p
        r -= alpha * Ap
        rr_new = float((r * r).sum())
        p = r + (rr_new / max(rr, 1e-300)) * p
        rr = rr_new
    return X


def _basis_step(
    B: torch.Tensor, C: torch.Tensor, y: torch.Tensor, samplers: list[_Sampler], lam: float, cg_steps: int
) -> None:
    """The basis B (K, J, h·S, w·S) given the coefficients C (N, K), in place: CG per lenslet."""
    K, _, hS, wS = B.shape
    N = C.shape[0]
    everything = slice(0, N)
    # CG per lenslet on (Cᵀ D ᵀD C + λ L²) B = Cᵀ Dᵀ y
    for j, sampler in enumerate(samplers):

        def normal(X: torch.Tensor, sampler: _Sampler = sampler) -> torch.Tensor:
            fine = (C @ X.reshape(K, -1)).reshape(N, hS, wS)
            back = sampler.adjoint(sampler.forward(fine, everything), everything)
            out = (C.T @ back.reshape(N, -1)).reshape(X.shape)
            return out + lam * _laplacian(_laplacian(X))

        rhs = (C.T @ sampler.adjoint(y[:, j], everything).reshape(N, -1)).reshape(K, hS, wS)
        B[:, j] = _cg(normal, rhs, B[:, j].clone(), cg_steps)


def _coefficient_step(B: torch.Tensor, y: torch.Tensor, samplers: list[_Sampler]) -> torch.Tensor:
    """The coefficients (N, K) given the basis: per node, K-term least squares over its J foci."""
    K = B.shape[0]
    N = y.shape[0]
    everything = slice(0, N)
    gram = torch.zeros((N, K, K), dtype=torch.float64)
    rhs = torch.zeros((N, K), dtype=torch.float64)
    for j, sampler in enumerate(samplers):
        sampled = torch.stack([sampler.forward(B[k, j].expand(N, -1, -1), everything) for k in range(K)], 1)
        sampled = sampled.reshape(N, K, -1)  # (N, K, h·w)
        rhs += torch.einsum("nkp,np->nk", sampled, y[:, j].reshape(N, -1)).double()
        gram += torch.bmm(sampled, sampled.transpose(1, 2)).double()
        del sampled
    ridge = 1e-9 * torch.diagonal(gram, dim1=1, dim2=2).mean(-1).clamp_min(1e-300)
    gram += ridge[:, None, None] * torch.eye(K, dtype=torch.float64)
    return torch.linalg.solve(gram, rhs[..., None])[..., 0].float()


def _orthonormal(
    C: torch.Tensor, B: torch.Tensor, keep: np.ndarray, N_all: int, decomposition: Decomposition
) -> Decomposition:
    """C·B rewritten as an orthonormal basis and its (N_all, K) coefficients (zeros for nodes not in ``keep``)."""
    K, J, hS, wS = B.shape
    # back to an orthonormal basis: C·B = Q·R·B, SVD of R·B
    Q, R = torch.linalg.qr(C.double())
    U, s, Vt = torch.linalg.svd(R @ B.reshape(K, -1).double(), full_matrices=False)
    basis = Vt.reshape(K, J, hS, wS).float().numpy()
    coefficients = np.zeros((N_all, K), np.float32)
    coefficients[keep] = (Q @ (U * s)).float().numpy()
    singular = s.numpy()
    return Decomposition(
        basis=basis,
        coefficients=coefficients,
        singular_values=singular,
        nmse=decomposition.nmse,
        nmse_per_psf=decomposition.nmse_per_psf,
    )
