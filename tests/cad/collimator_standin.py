"""A light stand-in for the collimator in the housing and base-plate tests: its outer surface and
flange (what the seats and sockets fit), without the lens and cavity inside."""

from __future__ import annotations

import cadquery as cq
import numpy as np

from cm2optics.cad.led_housing import Box
from cm2optics.optics.collimator import collimator_profile


def _outer_section(design) -> tuple[list[tuple[float, float]], float, float, float]:
    """(r, z) of the outer surface from the cavity mouth to the flange's underside (20 chords of
    the computed TIR surface: < 1 µm sagitta, then the side), the flange's underside and top
    and half its side, mm."""
    profile = collimator_profile(design)
    bottom = profile.flange_bottom_z_mm
    pick = np.unique(np.linspace(0, len(profile.tir_r_mm) - 1, 21).round().astype(int))
    outer = [(float(r), float(z)) for r, z in zip(profile.tir_r_mm[pick], profile.tir_z_mm[pick], strict=True)]
    outer.append((float(profile.tir_r_mm[-1]), bottom))
    return outer, bottom, profile.exit_z_mm, design.collimator.footprint_mm / 2


def collimator_envelope(design) -> cq.Solid:
    """The collimator's square flange and its revolved outer surface, filled to the axis (a
    freeform lens lies inside it). LED frame, mm."""
    outer, bottom, top, r = _outer_section(design)
    outline = [(0.0, outer[0][1]), *outer, (0.0, bottom)]
    body = cq.Workplane("XZ").polyline(outline).close().revolve(360, (0, 0), (0, 1))
    return Box(-r, r, -r, r, bottom, top).solid().union(body).val()


def collimator_swept_along_x(design, x_end_mm: float) -> cq.Solid:
    """The space the collimator (:func:`collimator_envelope`) sweeps when pushed along +x up to
    ``x_end_mm``: the part, its flange's box and its body's y–z silhouette carried to the end."""
    outer, bottom, top, r = _outer_section(design)
    silhouette = [(-y, z) for y, z in reversed(outer)] + outer
    body = cq.Workplane("YZ").polyline(silhouette).close().extrude(x_end_mm)
    flange = Box(-r, x_end_mm, -r, r, bottom, top).solid()
    return flange.union(body).union(cq.Workplane().add(collimator_envelope(design))).val()
