"""Trace several illumination designs in the same setup and collect their figures.

The configurations of ``cm2 illum run``: the V1 baseline (a bare LED behind the excitation
filter), the design's own collimator (the CAD part), and any STL a user brings — all with the
same LED, filter, housing, placement and sample plane, so their figures compare directly.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cm2optics.design import SystemDesign
from cm2optics.design.materials import Material
from cm2optics.illumination.as_built import as_built_scene
from cm2optics.illumination.excitation import Transmission, design_filter_transmission, filter_from_table
from cm2optics.illumination.geometry import CollimatorMesh, build_scene, collimator_from_design, collimator_from_stl
from cm2optics.illumination.metrics import IlluminationFigures, figures_of_merit
from cm2optics.illumination.source import LEDSource, led_source, read_angular_profile, read_source_spectrum
from cm2optics.illumination.tracer import DEFAULT_MAX_BOUNCES, trace

__all__ = ["Setup", "compare_designs", "setup_from_options"]

V1_LABEL = "V1: bare LED + filter"


@dataclass(frozen=True, eq=False)
class Setup:
    """What every configuration shares.

    source: the LED. transmission: the excitation filter's T(λ, θ) (None: no filter).
    housing: absorbing housings and imaging tower. smooth_normals: shade collimators smoothly.
    rays: rays per configuration (all LEDs). seed: random seed. bin_mm: uniformity bins, mm.
    max_bounces: surfaces per ray. notes: where the inputs came from.
    """

    source: LEDSource
    transmission: Transmission | None
    housing: bool = True
    smooth_normals: bool = True
    rays: int = 1_000_000
    seed: int = 0
    bin_mm: float = 0.5
    max_bounces: int = DEFAULT_MAX_BOUNCES
    notes: dict[str, str] = field(default_factory=dict)


def setup_from_options(
    design: SystemDesign,
    *,
    led_profile: str | Path | None = None,
    led_spectrum: str | Path | None = None,
    filter_table: str | Path | None = None,
    excitation_filter: bool = True,
    led_flux_mw: float | None = None,
    **kwargs: Any,
) -> Setup:
    """A :class:`Setup` from the CLI's options (file paths or defaults); ``kwargs`` go to Setup."""
    profile = read_angular_profile(led_profile) if led_profile else None
    spectrum = read_source_spectrum(led_spectrum) if led_spectrum else None
    source = led_source(design, profile, spectrum, led_flux_mw)
    if not excitation_filter:
        transmission = None
        filter_note = "none (bare trace)"
    elif filter_table:
        transmission = filter_from_table(str(filter_table))
        filter_note = transmission.__doc__ or str(filter_table)
    else:
        transmission = design_filter_transmission(design)
        filter_note = transmission.__doc__ or "spectra library model"
    notes = {
        "led_profile": source.profile.source,
        "led_spectrum": source.spectrum.source,
        "excitation_filter": filter_note,
    }
    return Setup(source=source, transmission=transmission, notes=notes, **kwargs)


def stl_collimator(
    design: SystemDesign,
    path: str | Path,
    led_position_mm: np.ndarray,
    led_axis: np.ndarray,
    material: Material | None = None,
) -> CollimatorMesh:
    """A user's STL as a collimator, in the design's collimator material unless ``material`` is given."""
    if material is None:
        material = design.collimator.material if design.collimator is not None else Material.CLEAR_RESIN
    return collimator_from_stl(path, led_position_mm, led_axis, material, label=Path(path).name)


def configurations(
    design: SystemDesign, stl: CollimatorMesh | None, include_v1: bool = True
) -> list[tuple[str, CollimatorMesh | None]]:
    """(label, collimator) of every design to compare: V1, the design's CAD collimator, the STL."""
    configs: list[tuple[str, CollimatorMesh | None]] = []
    if include_v1:
        configs.append((V1_LABEL, None))
    if design.collimator is not None:
        cad = collimator_from_design(design)
        configs.append((cad.label, cad))
    if stl is not None:
        configs.append((stl.label, stl))
    return configs


def compare_designs(
    design: SystemDesign,
    setup: Setup,
    configs: list[tuple[str, CollimatorMesh | None]],
    progress: Any = None,
) -> list[IlluminationFigures]:
    """Trace every configuration in ``setup`` (as built: the design's ``illumination_as_built``)
    and return their figures, in order.

    progress: optional callable ``progress(label)`` called before each trace.
    """
    results = []
    for label, collimator in configs:
        if progress is not None:
            progress(label)
        scene = as_built_scene(
            build_scene(
                design,
                collimator,
                excitation_filter=setup.transmission is not None,
                housing=setup.housing,
                smooth_normals=setup.smooth_normals,
                label=label,
            )
        )
        record = trace(
            scene,
            setup.source,
            setup.rays,
            transmission=setup.transmission,
            seed=setup.seed,
            max_bounces=setup.max_bounces,
        )
        results.append(figures_of_merit(record, scene, bin_mm=setup.bin_mm))
    return results
