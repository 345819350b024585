"""Sensor-side effects of a built device on its images: stray light, pixel crosstalk, leakage.

They act on the frames themselves, whatever model formed them, so they are applied here once:
by the emission scans (``cm2 psf simulate``, from a design's ``as_built`` section) and by the
calibration's effect library (:func:`cm2optics.calibrate.effects.apply_image_effects`), with the
same parameters (:class:`cm2optics.design.AsBuilt`):

- stray light: a ``fraction`` of each pixel's light spread into a Gaussian halo of σ
  ``width_um`` on the sensor (scatter in the housing and filters); light carried beyond the
  frame's edge is lost;
- pixel crosstalk: a ``fraction`` of each pixel's signal shared equally with its four neighbours;
- leakage: uniform counts per ms of exposure on every pixel (excitation leaking through the
  filters), added to the counts, not to the per-photon frame.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from cm2optics.design import AsBuilt

__all__ = ["apply_as_built", "crosstalk", "halo"]


def halo(images: np.ndarray, fraction: float, width_px: float) -> np.ndarray:
    """(1 − fraction) × images + fraction × images blurred by a Gaussian of σ ``width_px`` (px),
    over the last two axes."""
    if fraction <= 0:
        return images
    sigma = (0,) * (images.ndim - 2) + (width_px, width_px)
    blurred = ndimage.gaussian_filter(images, sigma=sigma, mode="constant")
    return (1.0 - fraction) * images + fraction * blurred


def crosstalk(images: np.ndarray, fraction: float) -> np.ndarray:
    """Each pixel keeps 1 − fraction of its signal and gives fraction/4 to each of its four
    neighbours (last two axes)."""
    if fraction <= 0:
        return images
    kernel = np.array([[0, 0.25, 0], [0.25, 0, 0.25], [0, 0.25, 0]]) * fraction
    kernel[1, 1] = 1.0 - fraction
    return ndimage.convolve(images, kernel.reshape((1,) * (images.ndim - 2) + (3, 3)), mode="constant")


def apply_as_built(images: np.ndarray, as_built: AsBuilt, pixel_um: float) -> np.ndarray:
    """Stray light then crosstalk of ``as_built`` on images (…, y, x) of pixel pitch ``pixel_um``
    (µm; the binned pitch); the images themselves when both are absent. Leakage is added to
    counts by the caller (``as_built.leakage_counts_per_ms`` × exposure)."""
    out = halo(images, as_built.stray_light_fraction, as_built.stray_light_width_um / pixel_um)
    return crosstalk(out, as_built.pixel_crosstalk_fraction)
