"""An effective-PSF basis estimated from whole-pixel frames (measured scans).

A measured scan has whole pixels only. The ePSF's fine structure (the band between ½ and 1
cycle/px that the pixels alias) can be told only from frames of one focus shape at several
sub-pixel phases, as Anderson & King's ePSF (PASP 2000; photutils' ``EPSFBuilder``) pools many
stars of one PSF. Neighbouring calibration nodes do not quite give that: the PSF changes shape
between them about as fast as their phases add information (0.2-mm nodes at binning 2: NMSE 0.1
between neighbours, against 3.6 % of the energy beyond ½ cycle/px), and a shape change linear in
position looks like a sub-pixel shift. Sub-pixel dithers of a node do (a few µm of stage travel:
the same shape at other phases). Two estimates, by what the scan holds:

* **a scan with dithers** (:func:`has_dithers`): each node's fine crop, per lenslet, from the
  frames of the node and its dithers (:func:`neighbourhoods`: the nodes at its depth whose foci
  lie within :data:`DITHER_PX`), :func:`local_epsf_crops`:
  ``argmin_P Σ_m ‖D_m P − y_m‖² + λ‖∇²P‖²`` and the partition of unity (a point images to the
  same total at any phase: the S² phase sums are equal); the crops then go through the same
  low-rank build as a synthetic scan's ``epsf.h5``;
* **a scan without** (:func:`estimate_epsf_basis`): the basis and the coefficients jointly,
  alternating — the coefficients given the basis (per node, a K-term least-squares fit of its J
  foci), the basis given the coefficients (per lenslet, ``Σ_n ‖D_n(Σ_k c_nk·B_k) − y_n‖² +
  λ‖∇²B‖²`` by conjugate gradients), from the whole-pixel SVD upsampled (Keys); the low rank ties
  the nodes' phases together, but K·S² fine unknowns per pixel against N nodes leave it to the
  prior where the nodes are few.

``y_m`` is the whole-pixel window of the prepared image around frame m's focus (not resampled);
``D_m`` samples a fine patch at those pixels: fine coordinate ``(r − f_m)·S + S·(h//2)`` for pixel
r and chief ray f_m, by the Keys kernel (the model's own sampling,
:func:`~cm2optics.lsv.epsf.place_epsf`); the Laplacian prior fills the fine samples the phases
leave uncovered. :func:`phase_coverage` says how many of the S × S fine phases the nodes visit,
per lenslet.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from cm2optics.lsv.decompose import Decomposition
from cm2optics.lsv.epsf import sampling_matrix
from cm2optics.lsv.kernels import TAPS, shift_weights, split_shift

if TYPE_CHECKING:  # pragma: no cover
    from cm2optics.formats.scan import ScanIndex
    from cm2optics.lsv.preprocess import Geometry

__all__ = [
    "estimate_epsf_basis",
    "has_dithers",
    "local_epsf_crops",
    "neighbourhoods",
    "phase_spread_px",
    "phase_coverage",
    "pixel_windows",
]

#: Positions whose foci's phases all lie within this (px) of each other share one phase.
SINGLE_PHASE_PX = 0.02
#: Nodes whose foci lie within this (px) of each other are one node dithered: one shape, pooled.
DITHER_PX = 1.0


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
    each focus's chief ray (no resampling), and the chief rays ``foci`` (N, J, 2; px): pixel r of
    a window is at patch coordinate ``r − eps``, ``eps = foci − ⌊foci⌋``."""
    from cm2optics.lsv.preprocess import prepared_image

    h, w = patch
    J = geometry.n_lenslets
    focus = geometry.focus(index.positions_mm[:, 0], index.positions_mm[:, 1], index.positions_mm[:, 2])
    base = np.floor(focus).astype(np.int64)
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
    return out, focus


class _Sampler:
    """D_n for a stack of nodes: the Keys kernel (the model's own sampling, :func:`place_epsf`) of
    (hS, wS) fine patches at the fine coordinates (r − eps)·S of the window pixels, as four
    gathers per axis."""

    def __init__(self, eps: np.ndarray, h: int, w: int, S: int):
        self.h, self.w, self.S = h, w, S
        self.hS, self.wS = h * S, w * S
        self.rows = self._axis(eps[:, 0], h, S, self.hS)
        self.cols = self._axis(eps[:, 1], w, S, self.wS)

    @staticmethod
    def _axis(eps: np.ndarray, n: int, S: int, nf: int) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Per tap: fine indices (N, n) and weights (N, n), zero where the tap falls off the patch."""
        base, frac = split_shift((np.arange(n)[None, :] - eps[:, None]) * S)  # (N, n)
        weights = shift_weights(frac)  # (N, n, 4)
        taps = []
        for t, tap in enumerate(TAPS):
            index = base + tap
            weight = np.where((index >= 0) & (index < nf), weights[..., t], 0.0)
            taps.append((torch.as_tensor(np.clip(index, 0, nf - 1)), torch.as_tensor(weight, dtype=torch.float32)))
        return taps

    def forward(self, fine: torch.Tensor, nodes: slice | torch.Tensor) -> torch.Tensor:
        """(n, hS, wS) → (n, h, w) for the nodes ``nodes`` (a slice or an index tensor)."""
        rows = 0
        for index, weight in self.rows:
            i, wt = index[nodes], weight[nodes]
            rows = rows + torch.gather(fine, 1, i[:, :, None].expand(-1, -1, self.wS)) * wt[:, :, None]
        out = 0
        for index, weight in self.cols:
            i, wt = index[nodes], weight[nodes]
            out = out + torch.gather(rows, 2, i[:, None, :].expand(-1, self.h, -1)) * wt[:, None, :]
        return out

    def adjoint(self, image: torch.Tensor, nodes: slice | torch.Tensor) -> torch.Tensor:
        """(n, h, w) → (n, hS, wS), the transpose of :meth:`forward`."""
        n = image.shape[0]
        rows = torch.zeros((n, self.h, self.wS), dtype=image.dtype)
        for index, weight in self.cols:
            i, wt = index[nodes], weight[nodes]
            rows.scatter_add_(2, i[:, None, :].expand(-1, self.h, -1), image * wt[:, None, :])
        out = torch.zeros((n, self.hS, self.wS), dtype=image.dtype)
        for index, weight in self.rows:
            i, wt = index[nodes], weight[nodes]
            out.scatter_add_(1, i[:, :, None].expand(-1, -1, self.wS), rows * wt[:, :, None])
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
    y_np, foci = windows if windows is not None else pixel_windows(index, geometry, (h, w), progress=progress)
    eps = foci - np.floor(foci)
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


def _cg(normal, rhs: torch.Tensor, X: torch.Tensor, steps: int, dims: tuple[int, ...]) -> torch.Tensor:
    """``steps`` conjugate-gradient iterations on normal(X) = rhs from X (updated in place and
    returned); ``dims``: the axes one system spans (the others stack independent systems)."""
    r = rhs - normal(X)
    p = r.clone()
    rr = (r * r).sum(dims, keepdim=True)
    for _ in range(steps):
        Ap = normal(p)
        alpha = rr / (p * Ap).sum(dims, keepdim=True).clamp_min(1e-30)
        X += alpha * p
        r -= alpha * Ap
        rr_new = (r * r).sum(dims, keepdim=True)
        p = r + (rr_new / rr.clamp_min(1e-30)) * p
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
        B[:, j] = _cg(normal, rhs, B[:, j].clone(), cg_steps, dims=(0, 1, 2))


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


def neighbourhoods(foci_px: np.ndarray, depth: np.ndarray, within_px: float = DITHER_PX) -> list[np.ndarray]:
    """Per node, the nodes (itself first) at its ``depth`` (N,) whose foci ``foci_px`` (N, J, 2)
    all lie within ``within_px`` of its own: the same focus shape, moved by a sub-pixel dither."""
    out = []
    for n in range(len(foci_px)):
        apart = np.linalg.norm(foci_px - foci_px[n], axis=-1).max(axis=1)  # (N,) px, the farthest lenslet
        near = np.flatnonzero((depth == depth[n]) & (apart <= within_px))
        out.append(np.concatenate([[n], near[near != n]]))
    return out


def has_dithers(foci_px: np.ndarray, depth: np.ndarray, within_px: float = DITHER_PX) -> bool:
    """Whether any node of the scan has a sub-pixel dither (:func:`neighbourhoods` of more than one)."""
    return any(len(group) > 1 for group in neighbourhoods(foci_px, depth, within_px))


def phase_spread_px(eps: np.ndarray) -> float:
    """How far (px, circular, the larger axis) the sub-pixel phases ``eps`` (M, J, 2) of a
    neighbourhood's frames (its node first) reach from the node's, on its least dithered lenslet:
    0 for a node alone or dithered by whole pixels (one phase: nothing finer to learn from it)."""
    offset = np.abs((eps - eps[:1] + 0.5) % 1.0 - 0.5)  # (M, J, 2)
    return float(offset.max(axis=(0, 2)).min())


def local_epsf_crops(
    windows: np.ndarray,
    foci_px: np.ndarray,
    depth: np.ndarray,
    oversample: int,
    *,
    within_px: float = DITHER_PX,
    smoothness: float = 1e-2,
    cg_steps: int = 40,
    chunk: int = 16,
    progress=None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Fine crops (N, J, h·S, w·S) estimated per node from the whole-pixel ``windows`` (N, J, h,
    w) of its :func:`neighbourhoods` (``depth`` (N,) the nodes' depth index, ``within_px`` the
    dither radius): one ePSF per neighbourhood and lenslet, as Anderson & King's local ePSF,
    ``argmin_P Σ_m ‖D_m P − y_m‖² + λ‖∇²P‖²`` (and the partition of unity,
    :func:`_solve_neighbourhoods`) over the nodes m of the neighbourhood, each sampled at its own
    phase (the fraction of its foci ``foci_px`` (N, J, 2), the windows' layout of
    :func:`pixel_windows`) by :class:`_Sampler`; conjugate gradients, each node's system
    separately. ``smoothness``: λ relative to the data term's curvature per fine sample
    (neighbourhood size / S²). Returns the crops, registered like
    :func:`~cm2optics.lsv.epsf.epsf_crops`, and a report (phases per neighbourhood; the nodes whose
    neighbourhood holds one phase, :func:`phase_spread_px`)."""
    start = time.perf_counter()
    S = int(oversample)
    N, J, h, w = windows.shape
    eps = foci_px - np.floor(foci_px)
    groups = neighbourhoods(foci_px, depth, within_px)
    out = np.zeros((N, J, h * S, w * S), np.float32)
    phases = []
    for n0 in range(0, N, chunk):
        members = groups[n0 : n0 + chunk]
        owner = torch.as_tensor(np.concatenate([np.full(len(g), i) for i, g in enumerate(members)]))
        node = np.concatenate(members)
        lam = torch.as_tensor([smoothness * len(g) / S**2 for g in members], dtype=torch.float32)[:, None, None]
        for j in range(J):
            sampler = _Sampler(eps[node, j], h, w, S)
            out[n0 : n0 + len(members), j] = _solve_neighbourhoods(sampler, owner, windows[node, j], lam, cg_steps)
        for g in members:
            bins = np.minimum((eps[g] * S).astype(np.int64), S - 1)  # (len(g), J, 2)
            phases.append(min(len(np.unique(bins[:, j, 0] * S + bins[:, j, 1])) for j in range(J)))
        if progress:
            progress("local ePSFs", min(n0 + chunk, N), N)
    report = {
        "method": "one ePSF per node and lenslet from the whole-pixel frames of the node and its sub-pixel dithers",
        "dither_px": within_px,
        "smoothness": smoothness,
        "cg_steps": cg_steps,
        "nodes_per_neighbourhood": {
            "min": int(min(map(len, groups))),
            "median": float(np.median(list(map(len, groups)))),
        },
        "phase_bins_per_neighbourhood": {"min": int(min(phases)), "median": float(np.median(phases)), "of": S * S},
        "nodes_of_one_phase": int(sum(phase_spread_px(eps[g]) < SINGLE_PHASE_PX for g in groups)),
        "seconds": round(time.perf_counter() - start, 2),
    }
    return out, report


def _solve_neighbourhoods(
    sampler: _Sampler, owner: torch.Tensor, y: np.ndarray, lam: torch.Tensor, steps: int
) -> np.ndarray:
    """Fine patches (G, hS, wS) of G neighbourhoods: windows ``y`` (M, h, w) of their members,
    sampled by ``sampler`` (M nodes), member m belonging to neighbourhood ``owner[m]``; ``lam``
    (G, 1, 1) the Laplacian prior's weight per neighbourhood. A third term holds the ePSF's
    partition of unity (the pixels tile the sensor: a point images to the same total at every
    sub-pixel phase, so the S² phase sums are equal), weighted by the neighbourhood's size per
    pixel of the window."""
    members = slice(0, len(owner))
    pixels = sampler.h * sampler.w  # the phase sums' operator norm: scaled to the data term's
    unity = torch.bincount(owner, minlength=len(lam)).float()[:, None, None] / pixels
    shape = (len(lam), sampler.hS, sampler.wS)

    def normal(P: torch.Tensor) -> torch.Tensor:
        back = sampler.adjoint(sampler.forward(P[owner], members), members)
        return (
            torch.zeros(shape).index_add_(0, owner, back)
            + lam * _laplacian(_laplacian(P))
            + unity * _phase_spread(P, sampler.S)
        )

    rhs = torch.zeros(shape).index_add_(0, owner, sampler.adjoint(torch.as_tensor(y), members))
    return _cg(normal, rhs, torch.zeros_like(rhs), steps, dims=(1, 2)).numpy()


def _phase_spread(P: torch.Tensor, S: int) -> torch.Tensor:
    """The spread of (G, h·S, w·S) fine patches' S² phase sums ``s_φ = Σ_m P[m·S + φ]`` about
    their mean, put back on every fine sample of phase φ: the gradient of ½ Σ_φ (s_φ − s̄)²."""
    G, hS, wS = P.shape
    sums = P.reshape(G, hS // S, S, wS // S, S).sum((1, 3))  # (G, S, S)
    spread = sums - sums.mean((1, 2), keepdim=True)
    return spread[:, None, :, None, :].expand(G, hS // S, S, wS // S, S).reshape(G, hS, wS)
