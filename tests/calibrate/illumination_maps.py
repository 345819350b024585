"""Synthetic measured illumination maps for the tests of ``cm2 calibrate illumination``: the
design as built (its ``illumination_as_built``) traced with many rays, its irradiance on a
camera's pixel grid (rows +y, columns +x, centre on the axis), scaled to counts and Poisson noise."""

from __future__ import annotations

import numpy as np

from cm2optics.design import SystemDesign
from cm2optics.illumination.as_built import as_built_scene
from cm2optics.illumination.compare import setup_from_options
from cm2optics.illumination.geometry import build_scene, collimator_from_design
from cm2optics.illumination.tracer import Status, trace


def synthetic_map(
    design: SystemDesign,
    *,
    pixel_um: float = 50.0,
    size_px: int = 180,
    rays: int = 2_000_000,
    mean_counts: float = 50.0,
    offset_mm: tuple[float, float] = (0.0, 0.0),
    seed: int = 7,
) -> np.ndarray:
    """A (size_px, size_px) map of counts with a mean of ``mean_counts`` over its pixels that the
    field covers; the optical axis at the image centre plus ``offset_mm``."""
    collimator = collimator_from_design(design) if design.collimator is not None else None
    scene = as_built_scene(build_scene(design, collimator))
    setup = setup_from_options(design)
    record = trace(scene, setup.source, rays, transmission=setup.transmission, seed=seed)
    hits = record.hit_mm[record.status == int(Status.SAMPLE)] + np.asarray(offset_mm)
    pixel_mm = pixel_um / 1000
    half = size_px * pixel_mm / 2
    counts, _, _ = np.histogram2d(hits[:, 1], hits[:, 0], bins=size_px, range=[[-half, half], [-half, half]])
    centres = (np.arange(size_px) - (size_px - 1) / 2) * pixel_mm
    inside = np.hypot(centres[None, :], centres[:, None]) <= design.volume.field_mm / 2
    expected = counts * (mean_counts / counts[inside].mean())
    return np.random.default_rng(seed).poisson(expected).astype(np.float32)
