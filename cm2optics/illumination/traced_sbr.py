"""The signal-to-background ratio of a traced illumination.

The emission model (:func:`cm2optics.emission.sbr.signal_and_background`) takes its excitation
from model beams by default: each unit a uniform cone of the étendue-limited half-angle from its
exit face, losing nothing. Here the excitation is the traced rays that land on the sample plane,
each carrying its share of the photons the LEDs emitted (so the landed share is the trace's, and
light lost in the units or landing outside the field costs signal, not background alone):

* the signal: the fluorescence of the field where those rays land in it;
* the glow: where they land (:func:`~cm2optics.emission.filter_angles.glow_from_hits`);
* the specular reflection: each ray mirrored at its landing point with the Fresnel reflectance of
  the sample's surface at its own angle (:func:`~cm2optics.emission.filter_angles.mirror_on_sample`).

So the SBR sees the beam the collimator really makes — its irradiance over the field, its tails,
and the aim's steep side that a flat sample mirrors into the lenslets — and can rank designs in a
search.
"""

from __future__ import annotations

import numpy as np

from cm2optics.emission.filter_angles import Excitation
from cm2optics.emission.sbr import Sample, SBRResult, signal_and_background
from cm2optics.illumination.geometry import IlluminationScene
from cm2optics.illumination.tracer import RayRecord, Status

__all__ = ["COARSE_SAMPLING", "traced_excitation", "traced_sbr"]

#: Sampling of the emission model for a search (≈ 1 s per design; the report's default is finer).
COARSE_SAMPLING = {"field_step_mm": 0.5, "pupil_samples": 16}


def traced_excitation(record: RayRecord) -> Excitation:
    """The rays of ``record`` that landed on the sample plane, each carrying 1 / (rays traced) of the
    LEDs' photons. Raises ValueError when none landed."""
    landed = (record.status == int(Status.SAMPLE)) & np.all(np.isfinite(record.exit_direction), axis=1)
    count = int(landed.sum())
    if count == 0:
        raise ValueError("no traced ray landed on the sample plane: no excitation to compute an SBR from")
    return Excitation(record.hit_mm[landed], record.exit_direction[landed], np.full(count, 1.0 / record.rays))


def traced_sbr(
    record: RayRecord, scene: IlluminationScene, sample: Sample | None = None, seed: int = 0, **sampling: float
) -> SBRResult:
    """Signal and background of ``scene``'s design with its traced excitation (``sample``: default
    :class:`Sample`; ``seed``: draw of the mirrored rays; ``sampling``: the model's field and pupil
    sampling, e.g. :data:`COARSE_SAMPLING`)."""
    sample = Sample() if sample is None else sample
    return signal_and_background(scene.design, sample, traced_excitation(record), seed=seed, **sampling)
