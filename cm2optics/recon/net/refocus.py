"""Shift-and-add light-field refocusing of the nine demixed views, its shifts from the model.

The views are cropped at each lenslet's chief ray for the centre of the focal plane. A source at
(x, y, z) lands in view j at ``q(x, y, z) + s_j(z)``: a position ``q`` common to all views (the
reference point ``r0(z) + A(z)·(x, y)`` and the mean lenslet offset) plus the lenslet's own
axial shear ``s_j(z) = Δo_j(z) − mean_k Δo_k(z)``, ``Δo_j(z) = o_j(z) − o_j(0)``
(:class:`~cm2optics.lsv.preprocess.Geometry`: magnification, lenslet centres and shear per
depth, as the 3D-LSV model fitted them). Refocusing at depth z averages ``view_j(p + s_j(z))``
over the views: a source at that depth adds up at ``q``, sources elsewhere spread.

Planes: the disparity ``d(z)`` is the least-squares fit ``s_j(z) ≈ d(z)·u_j`` with ``u_j`` the
lenslet's in-focus offset from the array centre in units of the lenslet pitch (px of shift
between neighbouring views). Plane k sits where ``d = d_k``, ``d_k = k − ⌊N/2⌋`` (the paper:
N = 36, shifts −18…+17 px), or, with N = 0 (auto), at every whole pixel of disparity the volume's
depth range spans. Each view's shift at plane k is ``round(s_j(z_k))`` px.

Borders: shifting brings in zeros (no wrap-around), exactly as the views are zero-padded where
they leave the sensor. On a training patch the outer ``max |shift|`` pixels lack the light shifted
in from outside it, so the volume loss leaves that margin out (``border_px``); at full field the
same margin is the views' outer edge, beyond the illuminated field, so the whole field is
reconstructed in one pass and nothing is cropped (the result names the margin).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

__all__ = ["RefocusPlanes", "ShiftAndAdd", "lenslet_offsets_px", "refocus_planes"]


@dataclass(frozen=True)
class RefocusPlanes:
    """z_mm: (N,) plane depths (mm, +z towards the device), increasing; disparity_px: (N,) the
    neighbour disparity at each plane; shifts_px: (N, J, 2) integer (row, col) shift of view j."""

    z_mm: np.ndarray
    disparity_px: np.ndarray
    shifts_px: np.ndarray

    @property
    def n_planes(self) -> int:
        return int(len(self.z_mm))

    @property
    def max_shift_px(self) -> int:
        return int(np.abs(self.shifts_px).max()) if self.shifts_px.size else 0

    def resampling(self, z_out_mm: np.ndarray) -> np.ndarray:
        """(P, N) linear interpolation weights from these planes to depths ``z_out_mm`` (clamped
        at the ends): the enhancement net's first layer starts from it."""
        z_out = np.asarray(z_out_mm, float)
        N = self.n_planes
        W = np.zeros((len(z_out), N), np.float32)
        if N == 1:
            W[:, 0] = 1.0
            return W
        for p, z in enumerate(z_out):
            k = int(np.clip(np.searchsorted(self.z_mm, z) - 1, 0, N - 2))
            t = float(np.clip((z - self.z_mm[k]) / (self.z_mm[k + 1] - self.z_mm[k]), 0.0, 1.0))
            W[p, k] += 1.0 - t
            W[p, k + 1] += t
        return W


def lenslet_offsets_px(source: Any, z_mm: np.ndarray) -> np.ndarray:
    """(n, J, 2) (row, col) focus offset of each lenslet, px, at depths ``z_mm``, up to a common
    part (any term the same for all lenslets cancels in the refocusing).

    source: an :class:`~cm2optics.lsv.model.LSVModel` (its fitted geometry), a depth-wise
    operator from :func:`~cm2optics.lsv.toy.gaussian_lsi_operator` (its shear), or anything with a
    ``geometry`` holding ``offsets(z_mm)``."""
    z = np.asarray(z_mm, float)
    geometry = getattr(source, "geometry", None)
    if geometry is not None and hasattr(geometry, "offsets"):
        return np.asarray(geometry.offsets(z), float)
    meta = getattr(source, "meta", {}) or {}
    if meta.get("kind") == "gaussian-cm2" and hasattr(source, "chief_rays_px"):
        rays = np.asarray(source.chief_rays_px(), float)
        rel = rays - rays.mean(axis=0)
        return rel[None] * (1.0 + float(meta["shear_per_um"]) * z[:, None, None] * 1000.0)
    raise ValueError(
        f"{type(source).__name__}: cannot tell the lenslets' axial shear (need a 3D-LSV model's geometry "
        "or the Gaussian toy operator)"
    )


def _disparity(source: Any, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shifts s_j(z) (n, J, 2) and the disparity d(z) (n,) per lenslet pitch."""
    off0 = lenslet_offsets_px(source, np.zeros(1))[0]
    off = lenslet_offsets_px(source, z)
    s = off - off0[None]
    s = s - s.mean(axis=1, keepdims=True)
    rel = off0 - off0.mean(axis=0)
    dist = np.linalg.norm(rel[:, None] - rel[None], axis=-1)
    pitch = float(dist[dist > 1e-6].min()) if np.any(dist > 1e-6) else 1.0
    u = rel / pitch
    denom = float((u**2).sum()) or 1.0
    d = np.einsum("njc,jc->n", s, u) / denom
    return s, d


def refocus_planes(source: Any, z_range_mm: tuple[float, float], n_planes: int = 0) -> RefocusPlanes:
    """The refocusing planes and integer shifts of ``source`` (see the module docstring).

    z_range_mm: the volume's depth range (low, high), mm; n_planes: N (0: auto)."""
    lo, hi = float(min(z_range_mm)), float(max(z_range_mm))
    span = max(hi - lo, 1e-3)
    _, d_ends = _disparity(source, np.array([lo, hi]))
    if n_planes == 0:
        targets = np.arange(np.ceil(d_ends.min() - 1e-9), np.floor(d_ends.max() + 1e-9) + 1)
        if len(targets) == 0:
            targets = np.array([0.0])
    else:
        targets = np.arange(n_planes, dtype=float) - n_planes // 2
    # a fine table of d(z) over the volume, widened (up to ±4 depth ranges) only as far as the
    # planes need: a geometry fitted to a scan is a polynomial valid near the scan, and far
    # outside it may turn back (d(z) not monotonic) where no plane lies
    for extra in (0.0, 0.25, 0.5, 1.0, 2.0, 4.0):
        z_table = np.linspace(lo - extra * span, hi + extra * span, 4001)
        _, d_table = _disparity(source, z_table)
        if not np.all(np.diff(d_table) > 0) and not np.all(np.diff(d_table) < 0):
            if extra == 0.0:
                raise ValueError(
                    "the lenslets' disparity is not monotonic in depth over the volume: cannot place refocus planes"
                )
            raise ValueError(
                f"{len(targets)} refocus planes need disparities {targets.min():g}…{targets.max():g} px; the geometry "
                f"gives {d_ends.min():.3g}…{d_ends.max():.3g} px over the volume and is not monotonic beyond "
                f"{extra * span * 1000:.0f} µm outside it: use fewer planes (or 0: auto)"
            )
        if d_table[-1] < d_table[0]:
            z_table, d_table = z_table[::-1], d_table[::-1]
        if targets.min() >= d_table[0] and targets.max() <= d_table[-1]:
            break
    else:
        raise ValueError(
            f"{len(targets)} refocus planes need disparities {targets.min():g}…{targets.max():g} px; the geometry gives "
            f"{d_table[0]:.3g}…{d_table[-1]:.3g} px within ±4 depth ranges: use fewer planes (or 0: auto)"
        )
    z = np.interp(targets, d_table, z_table)
    order = np.argsort(z)
    z, targets = z[order], targets[order]
    s, _ = _disparity(source, z)
    return RefocusPlanes(z, targets, np.rint(s).astype(np.int64))


class ShiftAndAdd(nn.Module):
    """(B, J, H, W) views → (B, N, H, W) refocused planes: the mean over views of
    ``view_j(p + shift_kj)`` with zeros shifted in. Not learned; differentiable."""

    def __init__(self, shifts_px: np.ndarray | torch.Tensor):
        super().__init__()
        shifts = torch.as_tensor(np.asarray(shifts_px), dtype=torch.int64)
        if shifts.ndim != 3 or shifts.shape[-1] != 2:
            raise ValueError(f"shifts must be (N, J, 2), got shape {tuple(shifts.shape)}")
        self.register_buffer("shifts", shifts)

    def forward(self, views: torch.Tensor) -> torch.Tensor:
        B, J, H, W = views.shape
        N, Js, _ = self.shifts.shape
        if J != Js:
            raise ValueError(f"{J} views, the refocusing expects {Js}")
        m = int(self.shifts.abs().max()) if self.shifts.numel() else 0
        padded = nn.functional.pad(views, (m, m, m, m))
        shifts = self.shifts.tolist()
        planes = []
        for k in range(N):
            acc = None
            for j in range(J):
                dr, dc = shifts[k][j]
                piece = padded[:, j, m + dr : m + dr + H, m + dc : m + dc + W]
                acc = piece if acc is None else acc + piece
            planes.append(acc)
        return torch.stack(planes, dim=1) / J
