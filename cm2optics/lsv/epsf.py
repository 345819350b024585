"""Effective-PSF (ePSF) basis: the 3D-LSV model's basis PSFs on a grid S times finer than the
saved pixels, each the optical PSF already integrated over one pixel's area (Anderson & King,
PASP 2000). The image of a point at any sub-pixel position is the ePSF *sampled* at the pixel
centres; nothing undersampled is ever interpolated.

Conventions (``S`` = ``model.oversample``): a basis patch is (h·S, w·S); its fine sample ``a``
is the patch-pixel coordinate ``a/S``, so fine sample ``S·(h//2)`` (= ``(h·S)//2`` for even h)
is the chief ray, like pixel ``h//2`` of a whole-pixel basis. A focus whose chief ray lands on
the sensor at ``f`` (row, col px) puts on sensor pixel ``m`` the ePSF at fine coordinate
``(m − f)·S + S·(h//2)``, sampled by the Keys kernel on the fine grid (where the ePSF is well
sampled: at S = 4 the pixel box alone low-passes it below the fine grid's Nyquist frequency).

* :func:`place_epsf`: (…, h·S, w·S) fine patches → (…, h+3, w+3) pixel patches for a focus at
  fraction ``eps`` past an integer pixel (the layout of :func:`cm2optics.lsv.sparse._shift_patch`).
* :func:`fine_model` and :class:`EPSFOperator`: the dense forward/adjoint of an ePSF model is
  the whole-pixel operator of the same model on the fine grid (geometry × S, sensor × S), whose
  output is sampled at the pixel centres (every S-th fine sample); the adjoint puts the image
  back on those samples (zeros between) and runs the fine adjoint. Exact sub-pixel placement of
  every voxel (the splat and the shear at 1/S px, then Keys on the well-sampled fine grid).
* :func:`epsf_crops`: registered fine crops from a synthetic scan's ``epsf.h5``.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from cm2optics.lsv.crop_store import DEFAULT_MEMORY_BYTES, CropStore, crop_array
from cm2optics.lsv.kernels import TAPS, sample_window, shift_weights, split_shift

if TYPE_CHECKING:  # pragma: no cover
    from cm2optics.formats.scan import ScanIndex
    from cm2optics.lsv.model import LSVModel
    from cm2optics.lsv.preprocess import Geometry

__all__ = [
    "EPSF_FILE",
    "EPSFOperator",
    "epsf_crops",
    "fine_model",
    "place_epsf",
    "read_epsf_position",
    "sampling_matrix",
]


def sampling_matrix(u: np.ndarray, n_fine: int) -> np.ndarray:
    """(len(u), n_fine) Keys weights that sample a fine signal at continuous fine coordinates
    ``u`` (zero outside ``[0, n_fine)``)."""
    n, eps = split_shift(np.asarray(u, np.float64))
    weights = shift_weights(eps)  # (n_out, 4)
    out = np.zeros((len(n), n_fine))
    for t, column in zip(TAPS, weights.T, strict=True):
        idx = n + t
        ok = (idx >= 0) & (idx < n_fine)
        out[np.nonzero(ok)[0], idx[ok]] += column[ok]
    return out


def place_epsf(fine: np.ndarray, eps: tuple[float, float], oversample: int) -> np.ndarray:
    """Pixel patches (…, h+3, w+3) of fine ePSF patches (…, h·S, w·S) for a focus at the fraction
    ``eps`` (row, col) ∈ [0, 1) past an integer pixel: pixel (r, c) of the output is the ePSF at
    fine coordinates ``((r − 1 − eps_r)·S, (c − 1 − eps_c)·S)`` (the layout of the whole-pixel
    Keys shift: pixel (1, 1) is the patch's pixel (0, 0) moved by eps)."""
    S = int(oversample)
    hS, wS = fine.shape[-2:]
    h, w = hS // S, wS // S
    rows = sampling_matrix((np.arange(h + 3) - 1 - eps[0]) * S, hS)
    cols = sampling_matrix((np.arange(w + 3) - 1 - eps[1]) * S, wS)
    dtype = np.float32 if fine.dtype == np.float32 else np.float64
    return rows.astype(dtype) @ fine.astype(dtype, copy=False) @ cols.T.astype(dtype)


def epsf_crops(
    index: ScanIndex,
    geometry: Geometry,
    patch: tuple[int, int],
    oversample: int,
    progress=None,
    memory_bytes: int = DEFAULT_MEMORY_BYTES,
) -> np.ndarray | CropStore:
    """(N, J, h·S, w·S) float32 fine crops of a synthetic scan's ePSFs (``epsf.h5``) registered on
    every focus's chief ray (fine sample ``S·(h//2)`` on it), in the scan's normalised units less
    each image's background (as :func:`~cm2optics.lsv.preprocess.prepared_image`); on disk
    (:func:`~cm2optics.lsv.crop_store.crop_array`) if they take more than ``memory_bytes``."""
    import h5py

    from cm2optics.formats.scan import ScanError
    from cm2optics.lsv.preprocess import image_background

    path = Path(index.folder) / EPSF_FILE
    if not path.is_file():
        raise ScanError(f"{index.folder}: no {EPSF_FILE} (simulate the scan with --oversample S)")
    S = int(oversample)
    h, w = patch
    J = geometry.n_lenslets
    out = crop_array((len(index), J, h * S, w * S), memory_bytes)
    crop = np.zeros((J, h * S, w * S), np.float32)
    centres = geometry.focus(index.positions_mm[:, 0], index.positions_mm[:, 1], index.positions_mm[:, 2])
    with h5py.File(path, "r") as f:
        have = int(f.attrs["oversample"])
        if have != S:
            raise ScanError(f"{path}: ePSFs oversampled {have}×, asked for {S}×")
        for n in range(len(index)):
            background = image_background(index.normalised(n))
            entries = read_epsf_position(f, n)
            if not entries:
                continue
            r0 = min(e[1] for e in entries)
            c0 = min(e[2] for e in entries)
            r1 = max(e[1] + e[3].shape[0] for e in entries)
            c1 = max(e[2] + e[3].shape[1] for e in entries)
            canvas = np.zeros((r1 - r0, c1 - c0), np.float64)
            for _, r, c, data in entries:
                canvas[r - r0 : r - r0 + data.shape[0], c - c0 : c - c0 + data.shape[1]] += data
            canvas -= background  # the frames' median background (0 for a noiseless synthetic scan)
            for j in range(J):
                centre = (centres[n, j, 0] * S - r0, centres[n, j, 1] * S - c0)
                crop[j] = sample_window(canvas, centre, (h * S, w * S))
            out[n] = crop
            if progress:
                progress("cropping ePSFs", n + 1, len(index))
    return out


#: The synthetic scan's ePSF file (written by :mod:`cm2optics.emission.epsf`; read here without
#: importing the emission package, which the LSV stage must not: DESIGN.md).
EPSF_FILE = "epsf.h5"


def read_epsf_position(f, index: int) -> list[tuple[int, int, int, np.ndarray]]:
    """The ePSF patches of scan row ``index`` of an open ``epsf.h5``: (lenslet, fine row0, fine
    col0, patch) each (layout: :mod:`cm2optics.emission.epsf`)."""
    g = f[f"p{index:05d}"]
    data = g["data"][()]
    out, offset = [], 0
    for lenslet, (r0, c0), (h, w) in zip(g["lenslet"][()], g["origin"][()], g["shape"][()], strict=True):
        out.append((int(lenslet), int(r0), int(c0), data[offset : offset + h * w].reshape(h, w)))
        offset += h * w
    return out


def fine_model(model: LSVModel, sampling: int | None = None) -> LSVModel:
    """The ePSF model as a whole-pixel model on the fine grid: geometry × S, sensor × S, pixel / S.
    Its operator's output sampled at every S-th fine sample is the ePSF model's image.
    ``sampling``: a divisor S' of S to run on a coarser grid (the ePSF taken every S/S' fine
    samples: S'² instead of S² times the pixels). Only for dense content: on the traced models of
    BENCHMARKS.md, S' = 2 is 0.2–0.3 % from S' = 4 on a dense random volume but 7.5–15 % on single
    voxels (S' = 1, whole pixels: 20–37 %)."""
    from cm2optics.lsv.preprocess import Geometry

    S = sampling or model.oversample
    if model.oversample % S:
        raise ValueError(f"sampling = {sampling}: must divide the model's oversample ({model.oversample})")
    step = model.oversample // S
    g = model.geometry
    geometry = Geometry(g.r0_poly * S, g.A_poly * S, g.o_poly * S, g.rows, g.cols)
    H, W = model.sensor_shape
    fine = replace(
        model,
        geometry=geometry,
        sensor_shape=((H - 1) * S + 1, (W - 1) * S + 1),
        pixel_um=model.pixel_um / S,
        basis=np.ascontiguousarray(model.basis[:, :, ::step, ::step]),
        oversample=1,
        provenance={},
        focal_surface=None,
        refine=1,
        rotate_aberrations=False,
        warp_shapes=False,
    )
    # the interpolated coefficients live in the basis's coefficient space, whatever its sampling:
    # the model's own (along its focal surface, turned with the azimuth), not computed again
    object.__setattr__(fine, "_interpolation", model._interpolation)  # type: ignore[attr-defined]
    return fine


class EPSFOperator:
    """Forward/adjoint of an ePSF model on a volume grid (see the module docstring)."""

    def __init__(self, model: LSVModel, grid, device: str | torch.device = "cpu", sampling: int | None = None):
        from cm2optics.lsv.operators import LSVOperator

        self.model = model
        self.grid = grid
        self.device = torch.device(device)
        self.oversample = sampling or model.oversample
        self.sensor_shape = model.sensor_shape
        self.n_lenslets = model.n_lenslets
        self.fine = LSVOperator(fine_model(model, sampling), grid, device=device)

    def memory_bytes(self) -> int:
        return self.fine.memory_bytes()

    def transient_bytes(self) -> int:
        return self.fine.transient_bytes()

    def forward(self, volume, *, per_lenslet: bool = False, progress=None):
        S = self.oversample
        is_numpy = not isinstance(volume, torch.Tensor)
        out = self.fine.forward(
            torch.as_tensor(np.asarray(volume) if is_numpy else volume, dtype=torch.float32, device=self.device),
            per_lenslet=per_lenslet,
            progress=progress,
        )
        out = out[..., ::S, ::S].contiguous()
        return out.cpu().numpy() if is_numpy else out

    def adjoint(self, image, *, progress=None):
        S = self.oversample
        is_numpy = not isinstance(image, torch.Tensor)
        image = torch.as_tensor(np.asarray(image) if is_numpy else image, dtype=torch.float32, device=self.device)
        H, W = self.fine.sensor_shape
        fine = torch.zeros(image.shape[:-2] + (H, W), dtype=torch.float32, device=self.device)
        fine[..., ::S, ::S] = image
        out = self.fine.adjoint(fine, progress=progress)
        return out.cpu().numpy() if is_numpy else out
