"""The sensor's noise model, estimated from the data themselves.

A raw pixel holds ``dark + g·(electrons) + read noise``: its variance about its expectation µ
(counts) is ``σ_read² + g·(µ − dark)`` with ``g`` the conversion gain (counts per electron), plus
the quantisation's ``Δ²/12`` (Δ the step between recorded values: 1 count, or 16 for a 12-bit
sensor saved in the top bits of a 16-bit file, found from the data by
:func:`quantisation_step`). That term is the floor: frames with no read or shot noise at all (an
unmodified synthetic scan) still get a finite σ. The read noise is measured where the model says no light falls
(the dark regions of every frame); the gain comes from the scan's metadata when the camera's is
known (``counts_per_electron`` in ``scan.yaml``), otherwise from the photon-transfer slope of the
residual variance against the signal level in the bright regions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class SensorNoise:
    """Shot + read noise of a raw frame.

    read_noise_counts: σ of the read noise, counts.
    counts_per_electron: conversion gain g, counts per photo-electron.
    gain_source: where g came from ("metadata" or "photon transfer").
    """

    read_noise_counts: float
    counts_per_electron: float
    gain_source: str
    step_counts: float = 1.0

    def variance(self, signal_counts: np.ndarray) -> np.ndarray:
        """Variance (counts²) of pixels whose expected signal above dark is ``signal_counts``."""
        shot = self.counts_per_electron * np.clip(signal_counts, 0.0, None)
        return self.read_noise_counts**2 + self.step_counts**2 / 12.0 + shot

    def to_dict(self) -> dict[str, float | str]:
        return {
            "read_noise_counts": round(self.read_noise_counts, 4),
            "counts_per_electron": round(self.counts_per_electron, 5),
            "gain_source": self.gain_source,
            "quantisation_step_counts": self.step_counts,
        }


def quantisation_step(counts: np.ndarray, samples: int = 1_000_000) -> float:
    """The step between the values a sensor records (counts): the greatest common divisor of the
    differences between the distinct values of (up to ``samples`` of) ``counts``; 1 for
    non-integer data or fewer than two distinct values. A 12-bit sensor saved as 16-bit by a
    left shift records multiples of 16: its rounding noise is 16²/12, not 1/12."""
    values = np.asarray(counts).ravel()
    values = values[:: max(1, values.size // samples)]
    if values.size == 0 or not np.all(np.isfinite(values)) or np.any(values != np.round(values)):
        return 1.0
    distinct = np.unique(values.astype(np.int64))
    if distinct.size < 2:
        return 1.0
    return float(max(int(np.gcd.reduce(np.diff(distinct))), 1))


def raw_frames(
    expected_counts: np.ndarray,
    dark_level: float,
    counts_per_electron: float,
    read_noise_counts: float,
    bit_depth: int,
    rng: np.random.Generator,
) -> np.ndarray:
    """Raw frames (uint16) a sensor records of ``expected_counts`` (…, counts, ``dark_level``
    included): Poisson shot noise of the electrons (signal above dark / ``counts_per_electron``),
    Gaussian read noise of ``read_noise_counts``, rounded to counts and clipped to
    0 … 2^``bit_depth`` − 1. The model this module estimates, run forwards (tests, benchmarks)."""
    electrons = np.clip(np.asarray(expected_counts, float) - dark_level, 0.0, None) / counts_per_electron
    counts = rng.poisson(electrons) * counts_per_electron + rng.normal(0.0, read_noise_counts, electrons.shape)
    return np.clip(np.round(counts + dark_level), 0, 2**bit_depth - 1).astype(np.uint16)


def robust_sigma(values: np.ndarray, clip: float = 4.0) -> float:
    """σ of the bulk of ``values``: the standard deviation after iterative clipping at ``clip``·σ
    (the MAD alone is too coarse for integer counts with σ of a few counts)."""
    values = np.asarray(values, float).ravel()
    if values.size == 0:
        return float("nan")
    values = values[:: max(1, values.size // 1_000_000)]  # a million samples fix σ to 0.1 %
    centre, sigma = float(np.median(values)), float(np.std(values))
    for _ in range(5):
        kept = values[np.abs(values - centre) <= clip * max(sigma, 1e-12)]
        if kept.size < 2:
            break
        centre, sigma = float(kept.mean()), float(kept.std())
    return sigma


def estimate_noise(
    residual_counts: np.ndarray,
    signal_counts: np.ndarray,
    dark_mask: np.ndarray,
    counts_per_electron: float | None = None,
    step_counts: float = 1.0,
) -> SensorNoise:
    """The noise model from the residual of registered data against its model.

    residual_counts: data − model (…), counts.
    signal_counts: the model's signal above dark at the same pixels (…), counts.
    dark_mask: pixels where the model has no light (…), bool.
    counts_per_electron: the camera's conversion gain when known (metadata); otherwise fitted.
    step_counts: the data's quantisation step, counts (:func:`quantisation_step`).
    """
    quantisation = step_counts**2 / 12.0
    read = robust_sigma(residual_counts[dark_mask])
    if not math.isfinite(read):
        raise ValueError("no dark pixels to measure the read noise: every pixel of the model receives light")
    read = math.sqrt(max(read**2 - quantisation, 0.0))  # the residual holds the rounding too
    if counts_per_electron is not None:
        return SensorNoise(read, float(counts_per_electron), "metadata", step_counts)
    bright = signal_counts > max(25.0 * read**2, 10.0) if read > 0 else signal_counts > 10.0
    if bright.sum() < 50:
        return SensorNoise(read, 1.0, "assumed 1 count per electron (too few bright pixels to fit)", step_counts)
    # Photon transfer: E[r²] = σ² + g·µ. Binned by level and robust per bin, so a few badly
    # modelled pixels do not inflate the slope.
    levels = signal_counts[bright]
    squares = residual_counts[bright] ** 2 - read**2 - quantisation
    edges = np.quantile(levels, np.linspace(0.0, 1.0, 11))
    which = np.clip(np.searchsorted(edges, levels, side="right") - 1, 0, 9)
    mean_level = np.array([levels[which == k].mean() for k in range(10) if np.any(which == k)])
    median_square = np.array([np.median(squares[which == k]) / 0.4549 for k in range(10) if np.any(which == k)])
    # the median of a χ²₁-distributed r²/σ² is 0.4549 of its mean
    slope = float(np.sum(mean_level * median_square) / np.sum(mean_level**2))
    return SensorNoise(read, max(slope, 1e-6), "photon transfer", step_counts)


def add_scan_noise(
    scan_dir: str | Path,
    out_dir: str | Path,
    *,
    read_noise_counts: float = 2.0,
    dark_level: float = 100.0,
    counts_per_electron: float | None = None,
    seed: int = 0,
) -> Path:
    """A noise-free (synthetic) scan ``scan_dir`` as a sensor would record it, written to
    ``out_dir``: its frames raised by ``dark_level`` counts and passed through :func:`raw_frames`
    (shot noise at the scan's ``counts_per_electron`` unless given, read noise, 12-bit or the
    scan's bit depth clipping), exposures and positions kept; ``scan.yaml`` records the new dark
    level, gain and the noise. Raises :class:`ValueError` for a scan that already holds noise."""
    from cm2optics.formats.scan import ScanMeta, read_scan, write_scan

    scan = read_scan(scan_dir)
    extra = dict(scan.meta.extra)
    if str(extra.get("noise", "")).strip().lower() != "none":
        raise ValueError(f"{scan_dir}: scan.yaml does not say noise: none; its frames may already hold noise")
    gain = float(counts_per_electron if counts_per_electron is not None else extra.get("counts_per_electron", 1.0))
    expected = scan.images.astype(np.float64) - scan.meta.dark_level + dark_level
    frames = raw_frames(expected, dark_level, gain, read_noise_counts, scan.meta.bit_depth, np.random.default_rng(seed))
    extra.update(
        counts_per_electron=gain,
        noise=f"shot (Poisson, {gain:g} counts per electron) + read ({read_noise_counts:g} counts), seed {seed}",
    )
    meta = ScanMeta(scan.meta.pixel_um, scan.meta.binning, scan.meta.bit_depth, float(dark_level), extra)
    return write_scan(out_dir, frames, scan.positions_mm, scan.exposure_ms, meta, names=list(scan.files))
