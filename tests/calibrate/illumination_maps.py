"""Synthetic measured illumination maps for the tests of ``cm2 calibrate illumination``: the
design as built (its ``illumination_as_built``) traced with many rays, each LED's irradiance on
a camera's pixel grid (rows +y, columns +x), then weighted, scaled to counts and Poisson noise."""

from __future__ import annotations

import numpy as np

from cm2optics.design import SystemDesign
from cm2optics.illumination.as_built import as_built_scene
from cm2optics.illumination.compare import setup_from_options
from cm2optics.illumination.geometry import build_scene, collimator_from_design
from cm2optics.illumination.tracer import Status, trace

#: Rays per trace of a truth map (memory), and the seed step between its chunks (far from the
#: model's seeds, 0 and 1 by default).
CHUNK_RAYS = 8_000_000  # the largest single trace of the earlier tests: their maps unchanged
CHUNK_SEED_STEP = 1000


def unit_pixel_maps(
    design: SystemDesign,
    *,
    pixel_um: float = 50.0,
    size_px: int = 200,
    rays: int = 2_000_000,
    offset_mm: tuple[float, float] = (0.0, 0.0),
    seed: int = 7,
    chunk: int = CHUNK_RAYS,
) -> np.ndarray:
    """(units, size_px, size_px) rays landing in each pixel from each LED; the optical axis at
    ``offset_mm`` (x, y) from the image's centre. Traced in chunks of at most ``chunk`` rays (the
    k-th with seed ``seed + CHUNK_SEED_STEP·k``: independent rays, bounded memory), so that a truth
    can hold many times the model's rays — its own Monte Carlo noise, which a real map does not
    have, is then negligible beside the model's (BENCHMARKS.md, session 13)."""
    collimator = collimator_from_design(design) if design.collimator is not None else None
    scene = as_built_scene(build_scene(design, collimator))
    setup = setup_from_options(design)
    half = size_px * pixel_um / 2000
    out = np.zeros((scene.units, size_px, size_px))
    for k, start in enumerate(range(0, rays, chunk)):
        count = min(chunk, rays - start)
        record = trace(scene, setup.source, count, transmission=setup.transmission, seed=seed + CHUNK_SEED_STEP * k)
        on = record.status == int(Status.SAMPLE)
        hits, unit = record.hit_mm[on] + np.asarray(offset_mm), record.unit[on]
        out += np.stack(
            [
                np.histogram2d(hits[unit == u, 1], hits[unit == u, 0], bins=size_px, range=[[-half, half]] * 2)[0]
                for u in range(scene.units)
            ]
        )
    return out


def measured_map(
    unit_maps: np.ndarray, *, flux: tuple[float, ...] | None = None, mean_counts: float = 50.0, seed: int = 7
) -> np.ndarray:
    """A map of counts: the units' maps weighted by ``flux`` (default all 1), scaled to a mean
    of ``mean_counts`` over the image's central disc (radius 80 % of its half-width), Poisson noise."""
    weights = np.ones(len(unit_maps)) if flux is None else np.asarray(flux, float)
    total = np.tensordot(weights, unit_maps, axes=1)
    n = total.shape[-1]
    centres = np.arange(n) - (n - 1) / 2
    disc = np.hypot(centres[None, :], centres[:, None]) <= 0.4 * n
    expected = total * (mean_counts / total[disc].mean())
    return np.random.default_rng(seed).poisson(expected).astype(np.float32)
