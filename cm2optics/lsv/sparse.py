"""Images of sparse emitters straight from the model, without a volume.

An emitter is a uniform ball (centre, diameter, total intensity) at a continuous position.
For every emitter and lenslet the model's focus patch is formed at the emitter's exact position
(coefficients interpolated along the chief ray, :mod:`cm2optics.lsv.interpolate`), shifted to
its sub-pixel focus position with the Keys cubic kernel, added to the sensor, and blurred by the
ball's projection (its column density ``∝ √(R² − r²)``, ``R`` = radius × the local
magnification). Two approximations keep 5,000 emitters at full size within seconds:

- sub-pixel positions are rounded to ``1/subpixel_steps`` of a pixel (default 4: ≤ 1/8 px; pass
  ``subpixel_steps=None`` for exact shifts), so that emitters share shifted basis PSFs and one
  matrix product forms all their patches;
- the ball's axial extent is not integrated: its whole image uses the PSF at its centre depth
  (a 20-µm ball spans two 10-µm planes; the PSF changes little over that), and ball diameters are
  rounded to 0.25 px on the sensor.

Each emitter's focus patch is blurred by its ball on the patch itself (a batched FFT of the
patch, a few tens of pixels wide, with its full linear support) before it is added to the
sensor: the same image as blurring whole sensor canvases, at the cost of the patches only.

:func:`point_image` is the exact image of one point source (validation, tests).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import torch

from cm2optics.formats.emitters import Emitters
from cm2optics.lsv.interpolate import chief_ray_nodes
from cm2optics.lsv.kernels import TAPS, shift_weights, split_shift
from cm2optics.lsv.operators import fast_length

if TYPE_CHECKING:  # pragma: no cover
    from cm2optics.lsv.model import LSVModel

__all__ = ["ball_kernel", "place_patches", "point_image", "render_emitters"]

SIZE_STEP_PX = 0.25
POINT_BELOW_PX = 0.5


def _shift_patch(patch: np.ndarray, eps: tuple[float, float]) -> np.ndarray:
    """Keys-shift (…, h, w) patches by fractions ``eps`` (row, col) ∈ [0, 1): (…, h+3, w+3),
    whose pixel (1, 1) corresponds to the input's (0, 0) shifted by eps."""
    wr = shift_weights(np.asarray(eps[0]))
    wc = shift_weights(np.asarray(eps[1]))
    h, w = patch.shape[-2:]
    dtype = np.float32 if patch.dtype == np.float32 else np.float64
    tmp = np.zeros(patch.shape[:-2] + (h + 3, w), dtype=dtype)
    for t, weight in zip(TAPS, wr, strict=True):
        tmp[..., 1 + t : 1 + t + h, :] += weight * patch
    out = np.zeros(patch.shape[:-2] + (h + 3, w + 3), dtype=dtype)
    for t, weight in zip(TAPS, wc, strict=True):
        out[..., 1 + t : 1 + t + w] += weight * tmp
    return out


def _placed(model: LSVModel, patch: np.ndarray, eps: tuple[float, float]) -> np.ndarray:
    """Patches placed at fraction ``eps``: the Keys shift of a whole-pixel basis, or the ePSF
    sampled at the pixel centres (:func:`cm2optics.lsv.epsf.place_epsf`)."""
    if model.oversample > 1:
        from cm2optics.lsv.epsf import place_epsf

        return place_epsf(patch, eps, model.oversample)
    return _shift_patch(patch, eps)


def _add(target: np.ndarray, block: np.ndarray, r: int, c: int) -> None:
    H, W = target.shape
    rs, re = max(r, 0), min(r + block.shape[0], H)
    cs, ce = max(c, 0), min(c + block.shape[1], W)
    if rs < re and cs < ce:
        target[rs:re, cs:ce] += block[rs - r : re - r, cs - c : ce - c]


def point_image(model: LSVModel, x_mm: float, y_mm: float, z_mm: float, per_lenslet: bool = False) -> np.ndarray:
    """Exact image (y, x) (or (J, y, x)) of a unit point source at (x, y, z) mm, float64."""
    patches = model.focus_patches(x_mm, y_mm, z_mm)
    return place_patches(model, patches, x_mm, y_mm, z_mm, per_lenslet=per_lenslet)


def place_patches(
    model: LSVModel, patches: np.ndarray, x_mm: float, y_mm: float, z_mm: float, per_lenslet: bool = False
) -> np.ndarray:
    """Image (y, x) (or (J, y, x)) float64 of focus patches (J, h·S, w·S), registered as the
    model's basis (e.g. a traced ePSF, or its fit by the basis, :meth:`LSVModel.project`), placed
    at the foci of a source at (x, y, z) mm exactly as :func:`point_image` places the model's own."""
    H, W = model.sensor_shape
    h, w = model.patch_shape
    out = np.zeros((model.n_lenslets if per_lenslet else 1, H, W))
    focus = model.geometry.focus(x_mm, y_mm, z_mm)
    patches = np.asarray(patches, np.float64)
    for j in range(model.n_lenslets):
        n, eps = split_shift(focus[j] - np.array([h // 2, w // 2]))
        placed = _placed(model, patches[j], (eps[0], eps[1]))
        _add(out[j if per_lenslet else 0], placed, int(n[0]) - 1, int(n[1]) - 1)
    return out if per_lenslet else out[0]


def ball_kernel(diameter_px: float, supersample: int = 8) -> np.ndarray:
    """Normalised projection of a uniform ball of ``diameter_px`` onto the pixel grid (odd size,
    centred), each pixel integrated over ``supersample²`` points."""
    radius = diameter_px / 2.0
    half = int(math.ceil(radius)) + 1
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    grid = np.arange(-half, half + 1)
    rr = grid[:, None, None, None] + offsets[None, None, :, None]
    cc = grid[None, :, None, None] + offsets[None, None, None, :]
    density = np.sqrt(np.clip(radius**2 - rr**2 - cc**2, 0, None)).mean(axis=(2, 3))
    total = density.sum()
    if total <= 0:
        density = np.zeros_like(density)
        density[half, half] = 1.0
        return density
    return density / total


def render_emitters(
    model: LSVModel,
    emitters: Emitters,
    *,
    per_lenslet: bool = False,
    subpixel_steps: int | None = 4,
    chunk: int = 2048,
) -> np.ndarray:
    """Sensor image (y, x) (or (J, y, x)) of ``emitters`` (see the module docstring), float32."""
    H, W = model.sensor_shape
    h, w = model.patch_shape
    J = model.n_lenslets
    keep = emitters.intensity > 0
    positions = emitters.positions_mm()[keep]
    intensity = emitters.intensity[keep]
    diameters_um = emitters.diameter_um[keep]
    n_out = J if per_lenslet else 1
    out = torch.zeros((n_out, H, W), dtype=torch.float32)
    if len(positions) == 0:
        return out.numpy() if per_lenslet else out[0].numpy()
    x, y, z = positions.T
    A = model.geometry.A(z)
    scale = np.sqrt(np.abs(np.linalg.det(A))) / 1000.0  # px per µm at each emitter's depth
    diameter_px = diameters_um * scale
    size_bin = np.where(diameter_px < POINT_BELOW_PX, 0, np.round(diameter_px / SIZE_STEP_PX).astype(np.int64))
    balls = _BallSpectra()
    focus = model.geometry.focus(x, y, z)  # (N, J, 2)
    for j in range(J):
        corner = focus[:, j, :] - np.array([h // 2, w // 2])
        visible = (corner[:, 0] > -h - 3) & (corner[:, 0] < H + 3) & (corner[:, 1] > -w - 3) & (corner[:, 1] < W + 3)
        index = np.nonzero(visible)[0]
        if len(index) == 0:
            continue
        nodes, weights = chief_ray_nodes(model.geometry, model.interpolation_axes, j, x[index], y[index], z[index])
        terms = model.lenslet_terms(j)  # the basis PSFs with light in lenslet j
        coefficients = model.lenslet_coefficients(j)[terms]
        c = np.einsum("kne,ne->nk", coefficients[:, nodes[..., 0], nodes[..., 1], nodes[..., 2]], weights)
        c = torch.as_tensor(c * intensity[index, None], dtype=torch.float32)
        n, phases, phase_values = _phases(corner[index], subpixel_steps)
        target = out[j if per_lenslet else 0]
        basis_j = np.ascontiguousarray(model.basis[terms, j], dtype=np.float32)
        bins, tops, lefts = size_bin[index], n[:, 0] - 1, n[:, 1] - 1
        for phase in np.unique(phases):
            members = np.nonzero(phases == phase)[0]
            shifted = torch.from_numpy(
                _placed(model, basis_j, phase_values[int(phase)]).astype(np.float32).reshape(len(terms), -1)
            )
            for start in range(0, len(members), chunk):
                part = members[start : start + chunk]
                patches = (c[part] @ shifted).reshape(len(part), h + 3, w + 3)
                for b in np.unique(bins[part]):
                    sel = np.nonzero(bins[part] == b)[0]
                    blurred, pad = balls.blur(patches[sel], int(b))
                    _scatter_add(target, blurred, tops[part[sel]] - pad, lefts[part[sel]] - pad)
    result = out.numpy()
    return result if per_lenslet else result[0]


def _phases(corner: np.ndarray, subpixel_steps: int | None) -> tuple[np.ndarray, np.ndarray, dict[int, tuple]]:
    """Whole-pixel corners (px), a phase id per emitter and each phase's sub-pixel shift (px).

    With ``subpixel_steps`` the shifts are rounded to 1/steps px (emitters share phases); without,
    every emitter is its own phase at its exact shift.
    """
    n, eps = split_shift(corner)
    if subpixel_steps:
        steps = np.round(eps * subpixel_steps).astype(np.int64)
        n = n + steps // subpixel_steps
        steps = steps % subpixel_steps
        phases = steps[:, 0] * subpixel_steps + steps[:, 1]
        phase_values = {
            int(p): (p // subpixel_steps / subpixel_steps, p % subpixel_steps / subpixel_steps)
            for p in np.unique(phases)
        }
    else:
        phases = np.arange(len(corner))
        phase_values = {int(p): (eps[p, 0], eps[p, 1]) for p in phases}
    return n, phases, phase_values


class _BallSpectra:
    """The rfft2 of ball kernels (size bin × FFT shape), made once per render."""

    def __init__(self) -> None:
        self._spectra: dict[tuple[int, tuple[int, int]], torch.Tensor] = {}
        self._kernels: dict[int, np.ndarray] = {}

    def blur(self, patches: torch.Tensor, size_bin: int) -> tuple[torch.Tensor, int]:
        """(n, P, Q) patches convolved (full linear support) with the ball of ``size_bin`` ×
        SIZE_STEP_PX px diameter: (n, P + 2R, Q + 2R) and R; bin 0 (a point) returns them as they are."""
        if size_bin == 0:
            return patches, 0
        if size_bin not in self._kernels:
            self._kernels[size_bin] = ball_kernel(size_bin * SIZE_STEP_PX)
        kernel = self._kernels[size_bin]
        k = kernel.shape[0]
        P, Q = patches.shape[-2:]
        shape = (fast_length(P + k - 1), fast_length(Q + k - 1))
        key = (size_bin, shape)
        if key not in self._spectra:
            self._spectra[key] = torch.fft.rfft2(torch.as_tensor(kernel, dtype=torch.float32), s=shape)
        full = torch.fft.irfft2(torch.fft.rfft2(patches, s=shape) * self._spectra[key], s=shape)
        return full[:, : P + k - 1, : Q + k - 1], k // 2


def _scatter_add(target: torch.Tensor, blocks: torch.Tensor, tops: np.ndarray, lefts: np.ndarray) -> None:
    """Add (n, P, Q) ``blocks`` into ``target`` (H, W) with their corners at (tops, lefts) px,
    clipped at the edges, in one indexed accumulation."""
    H, W = target.shape
    n, P, Q = blocks.shape
    rows = torch.as_tensor(tops, dtype=torch.int64)[:, None] + torch.arange(P)  # (n, P)
    cols = torch.as_tensor(lefts, dtype=torch.int64)[:, None] + torch.arange(Q)  # (n, Q)
    inside = ((rows >= 0) & (rows < H))[:, :, None] & ((cols >= 0) & (cols < W))[:, None, :]
    flat = rows[:, :, None] * W + cols[:, None, :]
    target.view(-1).index_put_((flat[inside],), blocks[inside], accumulate=True)
