"""The paper's own measurements as residuals of the model (issue 14, item 7): part (c), the
de-magnification and the calibration source's intensity drop at the edge of the field.

The paper calibrated a de-magnification of ≈ 1.7× (a 4.15-µm object pixel on the IMX178's
2.4-µm pixels), and saw the point source's intensity under the central lenslet fall by ≈ 85 %
towards the edge of the 7-mm field. :func:`field_residuals` traces the design's emission path
(:class:`~cm2optics.emission.psf.EmissionModel`, binned pixels) for a source stepped across
the field at the focal plane and compares:

* magnification: first-order (paraxial, and the chief ray at best focus,
  :mod:`cm2optics.optics.first_order`) and traced (the central focus's centroid against the
  source's position, least squares through the origin over the field, as a calibration scan
  measures it), then the MLA–sensor spacing that would make the traced value the paper's
  (one secant step of the traced magnification against the spacing);
* the edge drop: the central focus's energy against the field radius for an isotropic source
  (what the optics alone lose: the lenslet's solid angle, the filter's blue shift, vignetting)
  and for the source library's calibration pinhole, then the Gaussian 1/e² half-angle that
  reproduces the paper's drop, found with the calibration library's ``source_profile`` effect
  (:func:`cm2optics.calibrate.tracer.source_for`: a falloff on top of an isotropic source).

The paper's numbers are inputs (:data:`cm2optics.calibrate.paper.PAPER`), never results.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy.optimize import brentq

from cm2optics.calibrate.paper import PAPER
from cm2optics.design import SystemDesign

__all__ = ["edge_energy", "field_residuals", "traced_magnification"]

#: Source radii of the field profile, mm (along +x at the focal plane).
FIELD_RADII_MM = (0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0)
#: Step of the MLA–sensor spacing for the magnification's secant, mm.
SPACING_STEP_MM = 0.02


def _model(design: SystemDesign, half_angle_deg: float | None, binning: int) -> Any:
    """The emission model of ``design`` with a 5-µm calibration source: isotropic
    (``half_angle_deg`` None) or with the ``source_profile`` effect's Gaussian falloff."""
    from cm2optics.calibrate.tracer import source_for
    from cm2optics.emission.psf import EmissionModel, PSFSettings
    from cm2optics.emission.source import fluorescent_bead

    base = fluorescent_bead(PAPER["source_diameter_um"]["value"])
    values = (
        {} if half_angle_deg is None else {"source_profile": {"falloff_per_rad2": math.radians(half_angle_deg) ** -2}}
    )
    return EmissionModel(design, source_for(values, base), settings=PSFSettings(binning=binning))


def edge_energy(model: Any, radii_mm: tuple[float, ...] | np.ndarray) -> np.ndarray:
    """Energy of the central lenslet's focus for a source at each radius (along +x, focal plane),
    relative to the on-axis source (0 where the lenslet forms no focus)."""
    from cm2optics.emission.analysis import central_lenslet, relative_energy

    k = central_lenslet(model)
    return np.array([relative_energy(model, (float(r), 0.0, 0.0), k) for r in radii_mm])


def traced_magnification(model: Any, radii_mm: tuple[float, ...] | np.ndarray) -> tuple[float, np.ndarray]:
    """|m| from the central focus's centroid against the source's radius: the least-squares slope
    through the on-axis focus over ``radii_mm`` (> 0), and the local |m| at each radius."""
    from cm2optics.emission.analysis import central_lenslet, focus_position_mm

    k = central_lenslet(model)
    origin = focus_position_mm(model, (0.0, 0.0, 0.0), k)[0]
    r = np.asarray([x for x in radii_mm if x > 0], dtype=float)
    shift = np.array([origin - focus_position_mm(model, (float(x), 0.0, 0.0), k)[0] for x in r])  # inverted image
    return float(r @ shift / (r @ r)), shift / r


def _solve_half_angle(design: SystemDesign, radius_mm: float, target: float, binning: int) -> float:
    """Gaussian 1/e² half-angle (deg) whose source keeps ``target`` of the on-axis energy at ``radius_mm``."""

    def excess(log_deg: float) -> float:
        return float(edge_energy(_model(design, math.exp(log_deg), binning), [radius_mm])[0]) - target

    return math.exp(brentq(excess, math.log(5.0), math.log(120.0), xtol=2e-3))


def field_residuals(design: SystemDesign, *, binning: int = 4) -> dict[str, Any]:
    """Part (c): magnification and edge drop of the traced design against the paper (module
    docstring). ``binning``: sensor pixels per traced pixel (the centroids and energies are
    integrals, so 4 suffices)."""
    from cm2optics.emission.source import PINHOLE_HALF_ANGLE_DEG
    from cm2optics.optics import first_order

    pixel_um = design.sensor.pixel_um
    paper_pixel = PAPER["object_pixel_um"]["value"]
    paper_m = pixel_um / paper_pixel
    isotropic = _model(design, None, binning)
    traced_m, local_m = traced_magnification(isotropic, FIELD_RADII_MM)
    spacing = design.imaging.mla_to_sensor_mm
    moved = design.with_changes({"imaging.mla_to_sensor_mm": spacing + SPACING_STEP_MM})
    moved_m, _ = traced_magnification(_model(moved, None, binning), FIELD_RADII_MM)
    slope = (moved_m - traced_m) / SPACING_STEP_MM
    spacing_needed = spacing + (paper_m - traced_m) / slope
    magnification = {
        "paper_object_pixel_um": paper_pixel,
        "paper_object_pixel_source": PAPER["object_pixel_um"]["source"],
        "paper_demagnification": PAPER["demagnification"]["value"],
        "paper_demagnification_source": PAPER["demagnification"]["source"],
        "paper_magnification": round(paper_m, 4),
        "sensor_pixel_um": pixel_um,
        "paraxial_magnification": round(first_order.paraxial_magnification(design), 4),
        "chief_ray_magnification": round(first_order.magnification(design), 4),
        "chief_ray_object_pixel_um": round(first_order.object_pixel_um(design), 4),
        "traced_magnification": round(traced_m, 4),
        "traced_object_pixel_um": round(pixel_um / traced_m, 4),
        "traced_demagnification": round(1 / traced_m, 4),
        "traced_local_magnification": [round(float(m), 4) for m in local_m],
        "traced_radii_mm": [r for r in FIELD_RADII_MM if r > 0],
        "traced_over_paper": round(traced_m / paper_m, 4),
        "magnification_per_mm_spacing": round(slope, 4),
        "mla_to_sensor_mm": spacing,
        "mla_to_sensor_for_paper_mm": round(spacing_needed, 4),
        "description": (
            f"traced |m| = {traced_m:.4f} ({pixel_um / traced_m:.3f}-µm object pixel, least squares over the field) "
            f"against the paper's {paper_m:.4f} ({paper_pixel:g} µm): {100 * (traced_m / paper_m - 1):+.1f} %; "
            f"first order gives {first_order.magnification(design):.4f} at best focus. An MLA–sensor spacing of "
            f"{spacing_needed:.3f} mm instead of {spacing:g} mm ({1000 * (spacing_needed - spacing):+.0f} µm, "
            "the mla_spacing effect) would reproduce the paper's pixel"
        ),
    }
    drop = PAPER["edge_drop"]["value"]
    edge_r = PAPER["edge_radius_mm"]["value"]
    target = 1.0 - drop
    iso_profile = edge_energy(isotropic, FIELD_RADII_MM)
    pinhole_profile = edge_energy(_model(design, PINHOLE_HALF_ANGLE_DEG, binning), FIELD_RADII_MM)
    half_angle = _solve_half_angle(design, edge_r, target, binning)
    fitted_profile = edge_energy(_model(design, half_angle, binning), FIELD_RADII_MM)
    spread = PAPER["edge_drop"]["uncertainty"]
    bounds = [_solve_half_angle(design, edge_r, target + s, binning) for s in (-spread, spread)]
    iso_edge = float(np.interp(edge_r, FIELD_RADII_MM, iso_profile))
    edge = {
        "paper_drop": drop,
        "paper_drop_uncertainty": spread,
        "paper_drop_source": PAPER["edge_drop"]["source"],
        "paper_edge_radius_mm": edge_r,
        "radii_mm": list(FIELD_RADII_MM),
        "relative_energy_isotropic": [round(float(e), 4) for e in iso_profile],
        "relative_energy_library_pinhole": [round(float(e), 4) for e in pinhole_profile],
        "library_pinhole_half_angle_deg": PINHOLE_HALF_ANGLE_DEG,
        "relative_energy_fitted": [round(float(e), 4) for e in fitted_profile],
        "optics_drop_at_edge": round(1.0 - iso_edge, 4),
        "source_profile_half_angle_deg": round(half_angle, 2),
        "source_profile_half_angle_range_deg": [round(min(bounds), 2), round(max(bounds), 2)],
        "source_profile_falloff_per_rad2": round(math.radians(half_angle) ** -2, 4),
        "description": (
            f"the optics alone (isotropic source) lose {100 * (1 - iso_edge):.0f} % at r = {edge_r:g} mm (lenslet "
            f"solid angle, filter blue shift, vignetting); the paper's {100 * drop:.0f} % needs the source itself "
            f"to fall off: a Gaussian of 1/e² half-angle {half_angle:.1f}° ({min(bounds):.1f}–{max(bounds):.1f}° for "
            f"a {100 * (drop - spread):.0f}–{100 * (drop + spread):.0f} % drop), i.e. the source_profile effect; the "
            f"source library's pinhole ({PINHOLE_HALF_ANGLE_DEG:g}°) loses "
            f"{100 * (1 - float(np.interp(edge_r, FIELD_RADII_MM, pinhole_profile))):.0f} % there"
        ),
    }
    setup = {"design": design.name, "binning": binning}
    return {"magnification": magnification | {"setup": setup}, "edge_drop": edge | {"setup": setup}}
