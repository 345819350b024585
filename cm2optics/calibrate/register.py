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


def _correlation_offset(data: np.ndarray, spectra: np.ndarray) -> np.ndarray:
    """Whole-pixel offset from the summed cross-power spectrum, refined by a parabola per axis."""
    cross = np.einsum("nij,nij->ij", sfft.rfft2(data, workers=-1), np.conj(spectra))
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
    shape = data.shape[-2:]
    exposure = np.asarray(exposure_ms, np.float32)[:, None, None]
    spectra = sfft.rfft2(rate, workers=-1)
    lit = valid & (rate > 1e-3 * float(rate.max()))
    dark_guess = float(np.median(data[valid & ~lit])) if np.any(valid & ~lit) else 0.0
    offset = _correlation_offset(np.where(valid, data - dark_guess, 0.0).astype(np.float32) / exposure, spectra)
    for _ in range(OFFSET_STEPS):
        model = exposure * shift_spectra(spectra, shape, tuple(offset))
        scale, dark = _scale_and_dark(data, model, valid)
        gy, gx = np.gradient(model, axis=(-2, -1))
        residual = (data - dark - scale * model)[valid]
        jy, jx = -scale * gy[valid], -scale * gx[valid]
        normal = np.array([[jy @ jy, jy @ jx], [jx @ jy, jx @ jx]], float)
        step = np.linalg.solve(normal + 1e-9 * np.trace(normal) * np.eye(2), [jy @ residual, jx @ residual])
        offset = offset + np.clip(step, -0.5, 0.5)
        if np.max(np.abs(step)) < 1e-4:
            break
    model = exposure * shift_spectra(spectra, shape, tuple(offset))
    scale, dark = _scale_and_dark(data, model, valid)
    registration = Registration((float(offset[0]), float(offset[1])), scale, dark)
    return registration, (dark + scale * model).astype(np.float32)


def _scale_and_dark(data: np.ndarray, model_counts: np.ndarray, valid: np.ndarray) -> tuple[float, float]:
    """Least-squares ``data ≈ dark + scale·model`` over the valid pixels (normal equations)."""
    m = model_counts[valid].astype(np.float64)
    d = data[valid].astype(np.float64)
    n = float(m.size)
    sm, sd = m.sum(), d.sum()
    smm, smd = m @ m, m @ d
    scale = (n * smd - sm * sd) / max(n * smm - sm * sm, 1e-30)
    return float(scale), float((sd - scale * sm) / n)
