"""The depth-wise shift-invariant (LSI) baseline of the V1 paper (Xue et al., Sci. Adv. 2020).

Every depth plane is imaged by one PSF — the on-axis
PSF at that depth — shifted, not changed, as the source moves: ``g = Σ_z PSF_z ⊛ (F O_z)``, with
``F`` the in-focus mapping of voxels onto pixels (one voxel per sensor pixel, the image
inverted: ``row = r_ref + s_y·iy``, ``col = c_ref + s_x·ix`` with ``s = ±1``). The magnification's
change with depth, the field-dependent aberrations and vignetting are what it leaves out; that is
the point of comparing it with the LSV model. PSFs are kept per lenslet as compact patches
(J, nz, h, w) with their integer placement, so that the nine crosstalk-free views come for free.

Convolutions are FFTs on a canvas that holds the plane plus the kernel's whole extent (no
wrap-around reaches the sensor); the combined kernel spectra of all depths are precomputed
(``nz × canvas`` complex64: check :meth:`DepthwiseConvOperator.memory_bytes`).

The operator is saved and loaded as a PSF stack (:mod:`cm2optics.formats.psf_stack`).

:func:`lsi_model` gives the same baseline as an :class:`~cm2optics.lsv.model.LSVModel` (a single
lateral node, the in-focus magnification at every depth), for point images and sparse emitters.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from cm2optics.formats.psf_stack import read_psf_stack, write_psf_stack
from cm2optics.formats.volume import VolumeGrid
from cm2optics.lsv.model import LSVModel
from cm2optics.lsv.operators import fast_length
from cm2optics.lsv.preprocess import Geometry, _polyfit

__all__ = ["DepthwiseConvOperator", "lsi_from_model", "lsi_model"]


@dataclass(frozen=True)
class _Layout:
    canvas: tuple[int, int]  # canvas (rows, cols)
    plane_origin: tuple[int, int]  # sensor (row, col) of canvas pixel (0, 0)


class DepthwiseConvOperator:
    """Depth-wise shift-invariant operator (see the module docstring).

    patches: (J, nz, h, w) PSF patch of each lenslet at each depth (a unit source: the image it
        makes, in the model's units).
    origins: (J, nz, 2) integer sensor (row, col) of each patch's pixel (0, 0) for a source on the
        voxel (iy, ix) = (0, 0) of the plane after the flips (the plane's top-left once flipped).
    grid: the volume grid. sensor_shape: (rows, cols). flip: (flip rows, flip cols) of the plane
        before it is placed (True for an inverting system).
    centre_rays: (J, 2) optional focus (row, col) of each lenslet for a source at the centre of
        the focal plane (crops of the views); default: the brightest pixel of each in-focus patch.
    """

    def __init__(
        self,
        patches: np.ndarray,
        origins: np.ndarray,
        grid: VolumeGrid,
        sensor_shape: tuple[int, int],
        flip: tuple[bool, bool] = (True, True),
        centre_rays: np.ndarray | None = None,
        device: str = "cpu",
        meta: dict[str, Any] | None = None,
    ):
        patches = np.ascontiguousarray(patches, dtype=np.float32)
        origins = np.asarray(origins, dtype=np.int64)
        if patches.ndim != 4:
            raise ValueError(f"patches must be (J, nz, h, w), got shape {patches.shape}")
        if patches.shape[1] != grid.shape[0]:
            raise ValueError(f"patches have {patches.shape[1]} depths, the grid {grid.shape[0]}")
        if origins.shape != patches.shape[:2] + (2,):
            raise ValueError(f"origins must be (J, nz, 2) = {patches.shape[:2] + (2,)}, got {origins.shape}")
        if not np.all(np.isfinite(patches)):
            raise ValueError("patches contain NaN or infinite values")
        self.grid = grid
        self.sensor_shape = (int(sensor_shape[0]), int(sensor_shape[1]))
        self.flip = (bool(flip[0]), bool(flip[1]))
        self.n_lenslets = patches.shape[0]
        self.device = torch.device(device)
        self.patches = patches
        self.origins = origins
        self.meta = dict(meta or {})
        J, nz, h, w = patches.shape
        ny, nx = grid.shape[1:]
        lo = origins.reshape(-1, 2).min(axis=0)
        hi = origins.reshape(-1, 2).max(axis=0) + np.array([h, w])
        extent = hi - lo
        canvas = (fast_length(int(ny + extent[0])), fast_length(int(nx + extent[1])))
        self._layout = _Layout(canvas, (int(lo[0]), int(lo[1])))
        if centre_rays is None:
            focus = np.argmax(patches[:, nz // 2].reshape(J, -1), axis=1)
            centre = np.stack(np.unravel_index(focus, (h, w)), -1) + origins[:, nz // 2]
            centre_rays = centre + np.array([(ny - 1) / 2.0, (nx - 1) / 2.0])
        self._centre_rays = np.asarray(centre_rays, dtype=float).reshape(J, 2)
        self._spectra: torch.Tensor | None = None

    # -- geometry -----------------------------------------------------------------------------
    @property
    def canvas_shape(self) -> tuple[int, int]:
        return self._layout.canvas

    def chief_rays_px(self) -> np.ndarray:
        """(J, 2) sensor (row, col) where each lenslet images the centre of the focal plane."""
        return self._centre_rays.copy()

    def memory_bytes(self) -> int:
        """Bytes of the precomputed kernel spectra (the operator's own memory)."""
        Hc, Wc = self.canvas_shape
        return int(self.grid.shape[0] * Hc * (Wc // 2 + 1) * 8)

    def _kernel_canvas(self, z: int, lenslets: list[int] | None = None) -> torch.Tensor:
        Hc, Wc = self.canvas_shape
        h, w = self.patches.shape[2:]
        canvas = torch.zeros((Hc, Wc), dtype=torch.float32, device=self.device)
        r0, c0 = self._layout.plane_origin
        for j in range(self.n_lenslets) if lenslets is None else lenslets:
            r, c = self.origins[j, z] - (r0, c0)
            canvas[r : r + h, c : c + w] += torch.as_tensor(self.patches[j, z], device=self.device)
        return canvas

    def kernel_spectra(self) -> torch.Tensor:
        """(nz, Hc, Wc//2+1) rfft2 of the combined kernels on the canvas (cached)."""
        if self._spectra is None:
            self._spectra = torch.stack([torch.fft.rfft2(self._kernel_canvas(z)) for z in range(self.grid.shape[0])])
        return self._spectra

    #: Per-lenslet kernel spectra are cached when all of them fit in this many bytes.
    LENSLET_CACHE_BYTES = 256 * 2**20

    def _lenslet_spectra(self, j: int) -> torch.Tensor:
        """(nz, Hc, Wf) spectra of lenslet j's kernels (cached when small)."""
        cache = self.__dict__.setdefault("_lenslet_cache", {})
        if j in cache:
            return cache[j]
        spectra = torch.stack([torch.fft.rfft2(self._kernel_canvas(z, [j])) for z in range(self.grid.shape[0])])
        if self.n_lenslets * self.memory_bytes() <= self.LENSLET_CACHE_BYTES:
            cache[j] = spectra
        return spectra

    def _flip(self, data: torch.Tensor) -> torch.Tensor:
        dims = [d for d, f in zip((-2, -1), self.flip, strict=True) if f]
        return torch.flip(data, dims) if dims else data

    # -- canvas ↔ sensor ----------------------------------------------------------------------
    def _overlap(self) -> tuple[tuple[slice, slice], tuple[slice, slice]] | None:
        """(sensor slices, canvas slices) of the pixels both hold, or None when they do not meet."""
        H, W = self.sensor_shape
        Hc, Wc = self.canvas_shape
        r0, c0 = self._layout.plane_origin
        rs, re = max(r0, 0), min(r0 + Hc, H)
        cs, ce = max(c0, 0), min(c0 + Wc, W)
        if rs >= re or cs >= ce:
            return None
        return (slice(rs, re), slice(cs, ce)), (slice(rs - r0, re - r0), slice(cs - c0, ce - c0))

    def canvas_to_sensor(self, canvas: torch.Tensor) -> torch.Tensor:
        """The sensor's view of a canvas image (…, Hc, Wc) → (…, H, W), zero where unseen."""
        out = torch.zeros(canvas.shape[:-2] + self.sensor_shape, dtype=canvas.dtype, device=canvas.device)
        overlap = self._overlap()
        if overlap is not None:
            out[(..., *overlap[0])] = canvas[(..., *overlap[1])]
        return out

    def sensor_to_canvas(self, image: torch.Tensor) -> torch.Tensor:
        """Transpose of :meth:`canvas_to_sensor`."""
        out = torch.zeros(image.shape[:-2] + self.canvas_shape, dtype=image.dtype, device=image.device)
        overlap = self._overlap()
        if overlap is not None:
            out[(..., *overlap[1])] = image[(..., *overlap[0])]
        return out

    def sensor_mask_canvas(self) -> torch.Tensor:
        """(Hc, Wc) 1 where a canvas pixel is on the sensor."""
        return self.sensor_to_canvas(torch.ones(self.sensor_shape, device=self.device))

    def volume_to_canvas(self, volume: torch.Tensor) -> torch.Tensor:
        """(…, nz, ny, nx) → (…, nz, Hc, Wc): flipped planes in the canvas's top-left corner."""
        Hc, Wc = self.canvas_shape
        ny, nx = self.grid.shape[1:]
        out = torch.zeros(volume.shape[:-2] + (Hc, Wc), dtype=volume.dtype, device=volume.device)
        out[..., :ny, :nx] = self._flip(volume)
        return out

    def canvas_to_volume(self, canvas: torch.Tensor) -> torch.Tensor:
        ny, nx = self.grid.shape[1:]
        return self._flip(canvas[..., :ny, :nx])

    # -- operators ----------------------------------------------------------------------------
    @staticmethod
    def _as_tensor(data: Any, device: torch.device) -> tuple[torch.Tensor, bool]:
        is_numpy = not isinstance(data, torch.Tensor)
        return torch.as_tensor(np.asarray(data) if is_numpy else data, dtype=torch.float32, device=device), is_numpy

    #: Bytes of transient canvas arrays per chunk of depth planes (forward/adjoint stream over z).
    CHUNK_BYTES = 256 * 2**20

    def _chunk(self) -> int:
        Hc, Wc = self.canvas_shape
        per_plane = Hc * Wc * 4 + 2 * Hc * (Wc // 2 + 1) * 8  # canvas + spectrum + product
        return max(1, min(self.grid.shape[0], self.CHUNK_BYTES // per_plane))

    def transient_bytes(self) -> int:
        """Bytes of the canvas-sized temporaries of one forward or adjoint."""
        Hc, Wc = self.canvas_shape
        return int(self._chunk() * (Hc * Wc * 4 + 2 * Hc * (Wc // 2 + 1) * 8) + 3 * Hc * Wc * 4)

    @torch.no_grad()
    def forward(self, volume: Any, *, per_lenslet: bool = False, progress: Any = None) -> Any:
        """Image (y, x) of a volume (z, y, x) (or (B, …)); ``per_lenslet``: (…, J, y, x)."""
        tensor, is_numpy = self._as_tensor(volume, self.device)
        if tuple(tensor.shape[-3:]) != self.grid.shape:
            raise ValueError(f"volume shape {tuple(tensor.shape[-3:])} does not match the grid {self.grid.shape}")
        Hc, Wc = self.canvas_shape
        nz, step = self.grid.shape[0], self._chunk()
        kernels = [self._lenslet_spectra(j) for j in range(self.n_lenslets)] if per_lenslet else [self.kernel_spectra()]
        totals = [
            torch.zeros(tensor.shape[:-3] + (Hc, Wc // 2 + 1), dtype=torch.complex64, device=self.device)
            for _ in kernels
        ]
        for z0 in range(0, nz, step):
            planes = torch.fft.rfft2(self.volume_to_canvas(tensor[..., z0 : z0 + step, :, :]))  # (…, k, Hc, Wf)
            for total, spectra in zip(totals, kernels, strict=True):
                total += (planes * spectra[z0 : z0 + step]).sum(dim=-3)
            del planes
        images = [self.canvas_to_sensor(torch.fft.irfft2(total, s=(Hc, Wc))) for total in totals]
        out = torch.stack(images, dim=-3) if per_lenslet else images[0]
        return out.cpu().numpy() if is_numpy else out

    @torch.no_grad()
    def adjoint(self, image: Any, *, progress: Any = None) -> Any:
        """Adjoint of :meth:`forward`: volume (z, y, x) from an image (y, x) (or batched)."""
        tensor, is_numpy = self._as_tensor(image, self.device)
        if tuple(tensor.shape[-2:]) != self.sensor_shape:
            raise ValueError(f"image shape {tuple(tensor.shape[-2:])} does not match the sensor {self.sensor_shape}")
        Hc, Wc = self.canvas_shape
        nz, ny, nx = self.grid.shape
        step = self._chunk()
        spectrum = torch.fft.rfft2(self.sensor_to_canvas(tensor))[..., None, :, :]
        kernels = self.kernel_spectra()
        out = torch.empty(tensor.shape[:-2] + (nz, ny, nx), dtype=torch.float32, device=self.device)
        for z0 in range(0, nz, step):
            planes = torch.fft.irfft2(spectrum * torch.conj(kernels[z0 : z0 + step]), s=(Hc, Wc))
            out[..., z0 : z0 + step, :, :] = self.canvas_to_volume(planes)
            del planes
        return out.cpu().numpy() if is_numpy else out

    # -- files --------------------------------------------------------------------------------
    def save(self, path: str | Path) -> Path:
        """Write the PSF stack as one HDF5 file (:mod:`cm2optics.formats.psf_stack`), atomically."""
        return write_psf_stack(
            path, self.patches, self.origins, self.grid, self.sensor_shape, self.flip, self._centre_rays, self.meta
        )

    @classmethod
    def load(cls, path: str | Path, device: str = "cpu") -> DepthwiseConvOperator:
        """The operator of a PSF stack file written by :meth:`save`."""
        fields = read_psf_stack(path)
        return cls(**fields, device=device)


def lsi_from_model(model: Any, grid: VolumeGrid | None = None, *, device: str = "cpu") -> DepthwiseConvOperator:
    """The V1 paper's depth-wise LSI model of an LSV model: at each depth of ``grid`` the exact
    image (per lenslet) of a point source on the voxel nearest the optical axis, shifted one
    sensor pixel per voxel with the in-focus inversion — exact for that voxel column, shift
    invariant elsewhere. Needs a grid with one voxel per sensor pixel at the focal plane (the
    model's default grid is one)."""
    grid = grid or model.default_grid
    geometry = model.geometry
    A0 = np.asarray(geometry.A(0.0), float)  # rows (row, col), columns (x, y), px/mm
    dy, dx = grid.voxel_um[1] / 1000.0, grid.voxel_um[2] / 1000.0
    row_per_iy, col_per_ix = A0[0, 1] * dy, A0[1, 0] * dx
    cross = abs(A0[0, 0] * dx) + abs(A0[1, 1] * dy)
    if cross > 0.02 or abs(abs(row_per_iy) - 1) > 0.02 or abs(abs(col_per_ix) - 1) > 0.02:
        raise ValueError(
            f"the depth-wise LSI model needs one voxel per sensor pixel at the focal plane, without rotation: this grid "
            f"maps a voxel to ({row_per_iy:.3f}, {col_per_ix:.3f}) px (cross terms {cross:.3f}); use the model's default grid"
        )
    flip = (row_per_iy < 0, col_per_ix < 0)
    nz, ny, nx = grid.shape
    z_mm = grid.axis_mm(0)
    J = model.n_lenslets
    iy0, ix0 = ny // 2, nx // 2  # the voxel nearest the axis (exactly on it for odd sizes)
    x0_mm, y0_mm = float(grid.axis_mm(2)[ix0]), float(grid.axis_mm(1)[iy0])
    a0 = (ny - 1 - iy0) if flip[0] else iy0  # its index in the flipped plane
    b0 = (nx - 1 - ix0) if flip[1] else ix0
    # one pass over depths, keeping only each focus's bounding box (full frames would not fit at full size)
    crops: dict[tuple[int, int], tuple[np.ndarray, int, int, int, int]] = {}  # (j, z) → crop, top, left, peak row, col
    half_h = half_w = 0
    for z, depth in enumerate(z_mm):
        image = model.point_image(x0_mm, y0_mm, float(depth), per_lenslet=True)  # (J, H, W)
        for j in range(J):
            rows, cols = np.nonzero(image[j] > 1e-6 * max(float(image[j].max()), 1e-30))
            if not len(rows):
                continue
            peak = np.unravel_index(np.argmax(image[j]), image[j].shape)
            r_lo, r_hi, c_lo, c_hi = rows.min(), rows.max(), cols.min(), cols.max()
            crops[j, z] = (
                image[j, r_lo : r_hi + 1, c_lo : c_hi + 1].astype(np.float32),
                r_lo,
                c_lo,
                int(peak[0]),
                int(peak[1]),
            )
            half_h = max(half_h, peak[0] - r_lo, r_hi - peak[0])
            half_w = max(half_w, peak[1] - c_lo, c_hi - peak[1])
        del image
    if not crops:
        raise ValueError("the model's on-axis PSF is empty")
    h, w = 2 * int(half_h) + 1, 2 * int(half_w) + 1
    patches = np.zeros((J, nz, h, w), np.float32)
    origins = np.zeros((J, nz, 2), np.int64)
    H, W = model.sensor_shape
    centre_focus = np.asarray(geometry.focus(0.0, 0.0, 0.0), float).reshape(J, 2)
    for (j, z), (crop, top, left, peak_r, peak_c) in crops.items():
        r0, c0 = peak_r - h // 2, peak_c - w // 2  # the patch, centred on the peak, holds the whole box
        patches[j, z, top - r0 : top - r0 + crop.shape[0], left - c0 : left - c0 + crop.shape[1]] = crop
        # the source sits on flipped voxel (a0, b0): voxel (0, 0) of the flipped plane lands a0, b0 pixels before
        origins[j, z] = (r0 - a0, c0 - b0)
    meta = {
        "kind": "lsi-from-lsv",
        "model_provenance": getattr(model, "provenance", {}).get("scan", {}).get("fingerprint"),
    }
    return DepthwiseConvOperator(patches, origins, grid, (H, W), flip, centre_focus, device=device, meta=meta)


def lsi_model(model: LSVModel) -> LSVModel:
    """The depth-wise LSI baseline made from ``model``'s on-axis PSF stack."""
    x0, y0 = model.provenance.get("geometry", {}).get("axis_position_mm", (0.0, 0.0))
    zs = model.grid_z_mm
    on_axis = model.coefficients_at(np.full(len(zs), x0), np.full(len(zs), y0), zs)  # (nz, K)
    coefficients = np.ascontiguousarray(on_axis.T[:, :, None, None], dtype=np.float32)
    geometry = model.geometry
    A0 = geometry.A(0.0)
    # the on-axis source lands where the LSV model puts it: r0_LSI(z) + A0·(x0, y0) = r0(z) + A(z)·(x0, y0)
    r_axis = geometry.r0(zs) + np.einsum("zab,b->za", geometry.A(zs) - A0[None], np.array([x0, y0]))
    degree = len(geometry.r0_poly) - 1
    lsi_geometry = Geometry(
        r0_poly=_polyfit(zs, r_axis, degree) if len(zs) > 1 else geometry.r0_poly,
        A_poly=A0[None].copy(),
        o_poly=geometry.o_poly,
        rows=geometry.rows,
        cols=geometry.cols,
    )
    provenance = dict(model.provenance)
    provenance["baseline"] = "depth-wise LSI (V1): the on-axis PSF stack, in-focus magnification at every depth"
    return replace(
        model,
        coefficients=coefficients,
        grid_x_mm=np.array([float(x0)]),
        grid_y_mm=np.array([float(y0)]),
        geometry=lsi_geometry,
        provenance=provenance,
        focal_surface=None,
        refine=1,
        rotate_aberrations=False,
        warp_shapes=False,
        turned_coefficients=None,
    )
