"""A scene as built: the design's ``illumination_as_built`` values applied to a traced scene.

Tilts and collimator decentres go through the robustness study's own perturbation
(:func:`cm2optics.illumination.robustness.perturbed_scene`: the unit turned about its LED's
centre, the LED moved in its plane — here by minus the collimator's decentre); relative LED
fluxes become the scene's ``led_flux`` (the unit emits proportionally more or fewer rays).
See :mod:`cm2optics.design.as_built_illumination` for the fields and their units.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from cm2optics.illumination.geometry import IlluminationScene
from cm2optics.illumination.robustness import UnitError, perturbed_scene

__all__ = ["as_built_scene"]


def as_built_scene(scene: IlluminationScene) -> IlluminationScene:
    """``scene`` with its design's ``illumination_as_built`` values (unchanged when nominal).
    A bare LED (no collimator) takes the tilts and fluxes but no decentre."""
    built = scene.design.illumination_as_built
    if built.is_nominal:
        return scene
    errors = [
        UnitError(
            -np.asarray(built.decenter_mm(unit)) if scene.collimator is not None else np.zeros(2),
            np.asarray(built.tilt_deg(unit)),
            None,
        )
        for unit in range(scene.units)
    ]
    moved = any(np.any(e.led_offset_mm != 0) or np.any(e.tilt_deg != 0) for e in errors)
    out = perturbed_scene(scene, errors) if moved else scene
    flux = tuple(built.flux(unit) for unit in range(scene.units))
    return dataclasses.replace(out, led_flux=flux if any(f != 1 for f in flux) else ())
