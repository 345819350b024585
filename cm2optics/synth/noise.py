"""Sensor noise on measurements normalised to a peak of 1.

- ``poisson-gaussian`` (the paper's): photon noise for ``peak_photons`` photons at the peak with a
  unit effective gain, ``Poisson(I·N)/N``, plus an additive Gaussian of mean ``offset_mean`` and
  sd ``offset_sd`` (0.048 and 0.017: dark frames at 30 ms, 40 dB gain). Mean ``I + offset_mean``,
  variance ``I/N + offset_sd²``.
- ``variance`` (the reference README's model for this sensor): ``I + √(a·I + b)·n``, ``n ~ N(0, 1)``,
  with a ≈ 1.5e-4 and b ≈ 5.4e-6: mean ``I``, variance ``a·I + b``.
- ``none``: the clean image.

Values are not clipped (a real ADC would clip at 0 and full scale; the Gaussian offset keeps
almost every pixel positive: 0.048 is 2.8 sd).
"""

from __future__ import annotations

import numpy as np

from cm2optics.synth.config import SynthConfig

__all__ = ["add_noise", "noise_variance", "poisson_gaussian"]


def poisson_gaussian(
    clean: np.ndarray, peak_photons: float, offset_mean: float, offset_sd: float, rng: np.random.Generator
) -> np.ndarray:
    """The paper's mixed noise on a normalised image (≥ 0): ``Poisson(I·N)/N + Normal(offset_mean,
    offset_sd)`` with ``N = peak_photons`` (float64)."""
    photons = rng.poisson(clean * peak_photons)
    return photons / peak_photons + rng.normal(offset_mean, offset_sd, clean.shape)


def add_noise(clean: np.ndarray, config: SynthConfig, rng: np.random.Generator) -> np.ndarray:
    """Noisy float32 copy of ``clean`` (normalised image; negatives count as 0) under ``config.noise``."""
    clean = np.asarray(clean, dtype=np.float64)
    if not np.all(np.isfinite(clean)):
        raise ValueError("a clean measurement must be finite")
    clean = np.maximum(clean, 0.0)  # a model's small negative ringing is no light
    if config.noise == "none":
        return clean.astype(np.float32)
    if config.noise == "poisson-gaussian":
        noisy = poisson_gaussian(clean, config.peak_photons, config.offset_mean, config.offset_sd, rng)
        return noisy.astype(np.float32)
    sd = np.sqrt(config.variance_a * clean + config.variance_b)
    return (clean + sd * rng.standard_normal(clean.shape)).astype(np.float32)


def noise_variance(intensity: np.ndarray, config: SynthConfig) -> np.ndarray:
    """Expected variance of a noisy pixel of clean value ``intensity`` (for checks)."""
    intensity = np.asarray(intensity, dtype=np.float64)
    if config.noise == "poisson-gaussian":
        return intensity / config.peak_photons + config.offset_sd**2
    if config.noise == "variance":
        return config.variance_a * intensity + config.variance_b
    return np.zeros_like(intensity)
