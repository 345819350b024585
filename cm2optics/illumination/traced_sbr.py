"""The signal-to-background ratio of a traced illumination.

The emission model (:func:`cm2optics.emission.sbr.signal_and_background`) takes the excitation's
background from model beams: each unit a uniform cone of the étendue-limited half-angle from its
exit face. Here both background paths come from the traced rays that land on the sample plane
(equal power each, shares of the landed power, as the model's are of its beams'):

* the glow: where they land (:func:`~cm2optics.emission.filter_angles.footprint_from_hits`);
* the specular reflection: each ray mirrored at its landing point with the Fresnel reflectance of
  the sample's surface at its own angle (:func:`~cm2optics.emission.filter_angles.mirror_on_sample`).

So the SBR sees the beam the collimator really makes — its tails, and the aim's steep side that
a flat sample mirrors into the lenslets — and can rank designs in a search.
"""

from __future__ import annotations

import numpy as np

from cm2optics.emission.filter_angles import Sources, footprint_from_hits, mirror_on_sample
from cm2optics.emission.sbr import Sample, SBRResult, signal_and_background
from cm2optics.illumination.geometry import IlluminationScene
from cm2optics.illumination.tracer import RayRecord, Status

__all__ = ["COARSE_SAMPLING", "traced_background", "traced_sbr"]

#: Sampling of the emission model for a search (≈ 1 s per design; the report's default is finer).
COARSE_SAMPLING = {"field_step_mm": 0.5, "pupil_samples": 16}


def traced_background(
    record: RayRecord,
    scene: IlluminationScene,
    surface_index: float = Sample.surface_index,
    max_specular_rays: int = 200_000,
    glow_step_mm: float = 0.5,
    seed: int = 0,
) -> tuple[Sources, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(glow, specular rays) of the traced excitation: the glow counted on a ``glow_step_mm`` grid
    (mm) from every landed ray; the specular rays (origins_mm, directions, power) from at most
    ``max_specular_rays`` of them, drawn with ``seed``. Raises ValueError when no ray landed."""
    landed = (record.status == int(Status.SAMPLE)) & np.all(np.isfinite(record.exit_direction), axis=1)
    count = int(landed.sum())
    if count == 0:
        raise ValueError("no traced ray landed on the sample plane: no excitation background to compute")
    hits = record.hit_mm[landed]
    glow = footprint_from_hits(scene.design, hits, np.full(count, 1.0 / count), glow_step_mm)
    pick = np.random.default_rng(seed).permutation(count)[: min(count, max_specular_rays)]
    origins = np.column_stack([hits[pick], np.full(pick.size, scene.sample_z_mm)])
    directions = record.exit_direction[landed][pick]
    specular = mirror_on_sample(origins, directions, np.full(pick.size, 1.0 / pick.size), surface_index)
    return glow, specular


def traced_sbr(
    record: RayRecord, scene: IlluminationScene, sample: Sample | None = None, seed: int = 0, **sampling: float
) -> SBRResult:
    """Signal and background of ``scene``'s design with the background of its traced excitation
    (``sample``: default :class:`Sample`; ``sampling``: the model's field and pupil sampling,
    e.g. :data:`COARSE_SAMPLING`)."""
    sample = Sample() if sample is None else sample
    glow, specular = traced_background(record, scene, sample.surface_index, seed=seed)
    return signal_and_background(scene.design, sample, glow=glow, specular=specular, **sampling)
