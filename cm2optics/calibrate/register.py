"""Register a model scan to measured frames: one sub-pixel frame offset, one flux scale, one dark level.

The data of image ``i`` (raw counts) are modelled as ``dark + s·e_i·M_i(r − δ)``: ``M_i`` the model's
image in counts per ms for a unit source (dark removed, exposure divided out), ``e_i`` the
exposure of the measured frame, ``s`` one flux scale for the whole scan, ``dark`` one dark level and
``δ`` one sub-pixel offset (row, col) of the whole frame (the sensor's placement, common to every
image). Nothing else is fitted: what the registration cannot absorb is the residual the
attribution explains with physical effects.

``δ`` comes from the peak of the summed cross-power spectrum (whole pixels, refined by a parabola),
then Gauss–Newton steps on the least-squares misfit; ``s`` and ``dark`` are linear given ``δ``.
Saturated pixels and frames the caller excludes take no part.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft

#: Gauss–Newton steps refining the offset after the correlation peak.
OFFSET_STEPS = 4


@dataclass(frozen=True)
class Registration:
    """The fitted registration.

    offset_px: (row, col) shift δ of the data relative to the model, px.
    flux_scale: s, data counts per model count (per ms of exposure).
    dark_level: counts.
    """

    offset_px: tuple[float, float]
    flux_scale: float
    dark_level: float

    def to_dict(self) -> dict[str, object]:
        return {
            "offset_px": [round(v, 4) for v in self.offset_px],
            "flux_scale": float(f"{self.flux_scale:.6g}"),
            "dark_level": round(self.dark_level, 3),
        }


def _ramp(shape: tuple[int, int], offset_px: tuple[float, float]) -> np.ndarray:
    """The Fourier-shift phase ramp (y, x//2+1) that moves an image by ``offset_px`` (row, col)."""
    ky = np.fft.fftfreq(shape[0])[:, None]
    kx = np.fft.rfftfreq(shape[1])[None, :]
    return np.exp(-2j * np.pi * (ky * offset_px[0] + kx * offset_px[1])).astype(np.complex64)


def shift_images(images: np.ndarray, offset_px: tuple[float, float]) -> np.ndarray:
    """Images (N, y, x) moved by ``offset_px`` (row, col) px, by the Fourier shift theorem."""
    shape = images.shape[-2:]
    return shift_spectra(sfft.rfft2(images.astype(np.float32), workers=-1), shape, offset_px)


def shift_spectra(spectra: np.ndarray, shape: tuple[int, int], offset_px: tuple[float, float]) -> np.ndarray:
    """Images (N, y, x) from their real FFTs, moved by ``offset_px`` (row, col) px."""
    return sfft.irfft2(spectra * _ramp(shape, offset_px), s=shape, workers=-1)


#: Images per block of the full-stack passes (the memory of a few blocks, not of the stack).
BLOCK = 16


def _blocks(count: int) -> list[slice]:
    return [slice(i, min(i + BLOCK, count)) for i in range(0, count, BLOCK)]


def _correlation_offset(
    data: np.ndarray, exposure: np.ndarray, valid: np.ndarray, dark: float, spectra: np.ndarray
) -> np.ndarray:
    """Whole-pixel offset from the summed cross-power spectrum of the dark-subtracted data per ms
    against the model's spectra, refined by a parabola per axis."""
    cross = np.zeros(spectra.shape[-2:], np.complex64)
    for b in _blocks(len(data)):
        block = np.where(valid[b], data[b] - dark, 0.0).astype(np.float32) / exposure[b]
        cross += np.einsum("nij,nij->ij", sfft.rfft2(block, workers=-1), np.conj(spectra[b]))
    corr = sfft.irfft2(cross, s=data.shape[-2:], workers=-1)
    peak = np.array(np.unravel_index(np.argmax(corr), corr.shape))
    offset = peak.astype(float)
    for axis in range(2):
        step = np.zeros(2, int)
        step[axis] = 1
        c0 = corr[tuple(peak)]
        cm = corr[tuple((peak - step) % corr.shape)]
        cp = corr[tuple((peak + step) % corr.shape)]
        denominator = cm - 2 * c0 + cp
        if denominator < 0:
            offset[axis] += 0.5 * (cm - cp) / denominator
    size = np.array(corr.shape, float)
    return (offset + size / 2) % size - size / 2


class _Sums:
    """Sums over the valid pixels of products of the shifted model m (counts per unit flux), its
    gradients g_y, g_x, the data d and 1: their Gram matrix, accumulated block by block in
    float64 — what the linear fit of scale and dark and the Gauss–Newton step of the offset need."""

    M, GY, GX, D, ONE = range(5)

    def __init__(self) -> None:
        self.gram = np.zeros((5, 5))

    def add(self, data: np.ndarray, model: np.ndarray, valid: np.ndarray, gradients: bool) -> None:
        rows = np.empty((5, int(np.count_nonzero(valid))))
        rows[self.M] = model[valid]
        if gradients:
            gy, gx = np.gradient(model, axis=(-2, -1))
            rows[self.GY], rows[self.GX] = gy[valid], gx[valid]
        else:
            rows[self.GY] = rows[self.GX] = 0.0
        rows[self.D] = data[valid]
        rows[self.ONE] = 1.0
        self.gram += rows @ rows.T

    def scale_and_dark(self) -> tuple[float, float]:
        """Least-squares ``data ≈ dark + scale·model`` (normal equations)."""
        g, m, d, one = self.gram, self.M, self.D, self.ONE
        n, sm, sd = g[one, one], g[m, one], g[d, one]
        scale = (n * g[m, d] - sm * sd) / max(n * g[m, m] - sm * sm, 1e-30)
        return float(scale), float((sd - scale * sm) / max(n, 1.0))

    def offset_step(self, scale: float, dark: float) -> np.ndarray:
        """The Gauss–Newton step of the offset (row, col) px given ``scale`` and ``dark``: the
        Jacobian of the model counts is −scale·g, the residual d − dark − scale·m."""
        g, grad = self.gram, [self.GY, self.GX]
        normal = scale**2 * g[np.ix_(grad, grad)]
        rhs = -scale * (g[grad, self.D] - dark * g[grad, self.ONE] - scale * g[grad, self.M])
        return np.linalg.solve(normal + 1e-9 * np.trace(normal) * np.eye(2), rhs)


def _shifted_sums(
    data: np.ndarray,
    exposure: np.ndarray,
    spectra: np.ndarray,
    valid: np.ndarray,
    offset: tuple[float, float],
    gradients: bool,
    out: np.ndarray | None = None,
) -> _Sums:
    """:class:`_Sums` of the model moved by ``offset`` (row, col) px, block by block; ``out``
    (N, y, x) float32, when given, receives the moved model in counts per unit flux."""
    sums = _Sums()
    shape = data.shape[-2:]
    for b in _blocks(len(data)):
        model = exposure[b] * shift_spectra(spectra[b], shape, offset)
        sums.add(data[b], model, valid[b], gradients)
        if out is not None:
            out[b] = model
    return sums


def register(
    data_counts: np.ndarray,
    exposure_ms: np.ndarray,
    model_rate: np.ndarray,
    valid: np.ndarray,
) -> tuple[Registration, np.ndarray]:
    """Fit the registration and return it with the registered model in counts (N, y, x), float32.

    data_counts: raw frames (N, y, x), counts.
    exposure_ms: exposures of the frames (N,), ms.
    model_rate: the model's images (N, y, x) for a unit source, counts per ms above dark.
    valid: pixels that take part (N, y, x), bool (not saturated, finite, frame not excluded).
    """
    data = np.asarray(data_counts, np.float32)
    rate = np.asarray(model_rate, np.float32)
    exposure = np.asarray(exposure_ms, np.float32)[:, None, None]
    spectra = np.empty(rate.shape[:-1] + (rate.shape[-1] // 2 + 1,), np.complex64)
    threshold = 1e-3 * float(rate.max())
    dark_pixels = []
    for b in _blocks(len(rate)):
        spectra[b] = sfft.rfft2(rate[b], workers=-1)
        dark_pixels.append(data[b][valid[b] & ~(rate[b] > threshold)])
    dark_pixels = np.concatenate(dark_pixels)
    dark_guess = float(np.median(dark_pixels)) if dark_pixels.size else 0.0
    del dark_pixels
    offset = _correlation_offset(data, exposure, valid, dark_guess, spectra)
    for _ in range(OFFSET_STEPS):
        sums = _shifted_sums(data, exposure, spectra, valid, tuple(offset), gradients=True)
        scale, dark = sums.scale_and_dark()
        step = sums.offset_step(scale, dark)
        offset = offset + np.clip(step, -0.5, 0.5)
        if np.max(np.abs(step)) < 1e-4:
            break
    model = np.empty(data.shape, np.float32)
    scale, dark = _shifted_sums(data, exposure, spectra, valid, tuple(offset), False, out=model).scale_and_dark()
    registration = Registration((float(offset[0]), float(offset[1])), scale, dark)
    for b in _blocks(len(model)):
        model[b] = dark + scale * model[b]
    return registration, model
