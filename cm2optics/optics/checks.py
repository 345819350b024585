"""Plausibility of a design where it needs derived optics: a real, focused image in front of the
device, and filters that pass the fluorophore's light.

The dataclasses of :mod:`cm2optics.design` reject what their own numbers show to be impossible
(a part that does not fit, a sensor inside the lenslets' back focus, an MLA larger than the
sensor, a film that cuts on above the emission filter's band). What needs the exact best-focus
trace, or a fluorophore's spectrum, is checked here: :func:`check_design` lists the problems,
each a :class:`~cm2optics.design.DesignError` naming the dotted field; :func:`require_plausible`
raises the first. The CLI calls them when it loads or validates a design.
"""

from __future__ import annotations

import math

from cm2optics.design import DesignError, SystemDesign
from cm2optics.optics import first_order

__all__ = ["MIN_FILTER_CLEARANCE_MM", "check_design", "require_plausible"]

#: The plane of best focus must lie at least this far beyond the emission filter's front face, mm
#: (the best-focus search starts 0.1 mm beyond it: a focus found there is no focus at all).
MIN_FILTER_CLEARANCE_MM = 0.1 + 1e-3


def _band(center_nm: float, bandwidth_nm: float) -> tuple[float, float]:
    return center_nm - bandwidth_nm / 2, center_nm + bandwidth_nm / 2


def check_design(design: SystemDesign, emission_band_nm: tuple[float, float] | None = None) -> list[DesignError]:
    """The problems of ``design`` that need derived optics, each naming its dotted field.

    emission_band_nm: (low, high) band of the fluorophore's emission, nm (e.g. where its spectrum
        exceeds 10 % of its peak); None skips the checks against the fluorophore.
    """
    problems: list[DesignError] = []
    filter_top = design.emission_filter_z_mm + design.emission_filter.thickness_mm
    plane = first_order.object_plane_z_mm(design)
    if not math.isfinite(plane) or plane - filter_top < MIN_FILTER_CLEARANCE_MM:
        problems.append(
            DesignError(
                "imaging.filter_gap_mm",
                design.imaging.filter_gap_mm,
                f"no real image in front of the device: the lenslets' plane of best focus (z = {plane:.3f} mm) "
                f"lies inside or behind the emission filter (front face at z = {filter_top:.3f} mm)",
            )
        )
    else:
        distance, na = first_order.working_distance_mm(design), first_order.object_na(design)
        if not (distance > 0 and na > 0):
            problems.append(
                DesignError(
                    "mla.pitch_mm",
                    design.mla.pitch_mm,
                    f"no real image: working distance {distance:.3f} mm and object-side NA {na:.4f} must be > 0",
                )
            )
    if emission_band_nm is not None:
        low, high = emission_band_nm
        filt = design.emission_filter
        f_low, f_high = _band(filt.center_nm, filt.bandwidth_nm)
        if f_high <= low or f_low >= high:
            problems.append(
                DesignError(
                    "emission_filter.center_nm",
                    filt.center_nm,
                    f"the emission filter's passband {f_low:g}–{f_high:g} nm misses the fluorophore's "
                    f"emission band {low:g}–{high:g} nm: the sensor would see no signal",
                )
            )
        film = design.absorption_filter
        if film is not None and film.cut_on_nm >= high:
            problems.append(
                DesignError(
                    "absorption_filter.cut_on_nm",
                    film.cut_on_nm,
                    f"the film cuts on above the fluorophore's emission band ({low:g}–{high:g} nm): "
                    "it would absorb the signal",
                )
            )
    return problems


def require_plausible(design: SystemDesign, emission_band_nm: tuple[float, float] | None = None) -> SystemDesign:
    """``design`` if :func:`check_design` finds nothing; else raise its first problem (the
    message counts the others)."""
    problems = check_design(design, emission_band_nm)
    if problems:
        first = problems[0]
        more = (
            f" (and {len(problems) - 1} more: {', '.join(p.field for p in problems[1:])})" if len(problems) > 1 else ""
        )
        raise DesignError(first.field, first.value, first.allowed + more)
    return design
