"""Random emitter sets drawn the paper's way (Section 2.4).

Per sample: a field of view ``F ~ U[fov]`` (mm), a density ``ρ ~ U[density]`` (per mm²), and
``N = round(ρ · area(F))`` emitters (area of the disc of diameter F, or of the square of side F),
uniformly inside the field laterally and within ±depth/2 axially (centres), each with diameter
``d ~ U[diameter]`` and intensity ``(d / 10 µm)² · U[jitter]`` (∝ surface area, so the 8–20 µm
range spans 6.25×; 1 for a 10-µm emitter before jitter).

Random numbers come from ``numpy.random.default_rng(SeedSequence([seed, index]))``: sample
``index`` of data set ``seed`` is the same whatever the order, the worker or the number of
samples made.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cm2optics.formats.emitters import Emitters
from cm2optics.synth.config import SynthConfig

__all__ = ["EmitterDraw", "sample_emitters", "sample_rng"]

REFERENCE_DIAMETER_UM = 10.0


@dataclass(frozen=True)
class EmitterDraw:
    """A sample's draw: its emitters and the field, density and count behind them."""

    emitters: Emitters
    fov_mm: float
    density_per_mm2: float
    area_mm2: float


def sample_rng(seed: int, index: int, stream: int = 0) -> np.random.Generator:
    """The generator of sample ``index`` of data set ``seed`` (``stream`` separates uses)."""
    if seed < 0 or index < 0:
        raise ValueError(f"seed = {seed}, index = {index}: must be ≥ 0")
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(index), int(stream)]))


def sample_emitters(config: SynthConfig, rng: np.random.Generator) -> EmitterDraw:
    """Draw one sample's emitters (see the module docstring)."""
    fov = float(rng.uniform(*config.fov_mm))
    density = float(rng.uniform(*config.density_per_mm2))
    if config.field_shape == "disk":
        area = math.pi * fov**2 / 4.0
    else:
        area = fov**2
    n = int(round(density * area))
    half_um = fov * 1000.0 / 2.0
    if config.field_shape == "disk":
        radius = half_um * np.sqrt(rng.uniform(0.0, 1.0, n))
        angle = rng.uniform(0.0, 2.0 * math.pi, n)
        x, y = radius * np.cos(angle), radius * np.sin(angle)
    else:
        x, y = rng.uniform(-half_um, half_um, n), rng.uniform(-half_um, half_um, n)
    z = rng.uniform(-config.depth_um / 2.0, config.depth_um / 2.0, n)
    diameter = rng.uniform(*config.diameter_um, n)
    intensity = (diameter / REFERENCE_DIAMETER_UM) ** 2 * rng.uniform(*config.intensity_jitter, n)
    return EmitterDraw(Emitters(x, y, z, diameter, intensity), fov, density, area)
