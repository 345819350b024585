"""The printed MLA housing's bore and corner tabs as geometry: one description for the CAD part
(:mod:`cm2optics.cad.mla_housing` builds its solid from it) and for the emission tracer
(:mod:`cm2optics.emission.optics` keeps rays inside it). Device frame, mm.

The bore, bottom to top: film seat, spacer (``lip_mm`` narrower than the film: its ledge), MLA
seat, mask seat, filter seat; every seat is its part plus ``mechanics.clearance_mm`` per side.
Four corner tabs reach ``lip_mm`` over the array's corners and hold it from above.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cm2optics.design import SystemDesign
from cm2optics.optics.layout import mla_housing_envelope
from cm2optics.optics.lenslets import lens_top_under_tabs_mm

__all__ = ["Bore", "BoreStep", "TabGeometry", "bore_steps", "housing_bores", "mla_tab_geometry", "mla_tabs"]


@dataclass(frozen=True)
class BoreStep:
    """One step of the housing's bore: a centred rectangle from ``z0_mm`` to ``z1_mm``."""

    name: str
    width_mm: float
    length_mm: float
    z0_mm: float
    z1_mm: float


def bore_steps(design: SystemDesign) -> list[BoreStep]:
    """The seats and clear openings of the bore, bottom to top (sensor cone excluded)."""
    c, lip = design.mechanics.clearance_mm, design.mla_housing.lip_mm
    mla, film, mask, filt = design.mla, design.absorption_filter, design.aperture_mask, design.emission_filter
    z_mla = design.imaging.mla_to_sensor_mm
    steps = []
    if film is not None:
        z_film = design.imaging.film_to_sensor_mm
        steps.append(
            BoreStep("film seat", film.width_mm + 2 * c, film.length_mm + 2 * c, z_film, z_film + film.thickness_mm)
        )
        spacer_w, spacer_l = film.width_mm - 2 * lip, film.length_mm - 2 * lip
        spacer_z0 = z_film + film.thickness_mm
    else:  # no film: a short spacer, wider than the MLA, then the sensor cone
        spacer_w, spacer_l = mla.width_mm + 2 * c + 4 * lip, mla.length_mm + 2 * c + 4 * lip
        spacer_z0 = z_mla - 2 * lip
    steps += [
        BoreStep("spacer", spacer_w, spacer_l, spacer_z0, z_mla),
        BoreStep("MLA seat", mla.width_mm + 2 * c, mla.length_mm + 2 * c, z_mla, design.mask_z_mm),
        BoreStep(
            "mask seat", mask.outer_mm + 2 * c, mask.outer_mm + 2 * c, design.mask_z_mm, design.emission_filter_z_mm
        ),
        BoreStep(
            "filter seat",
            filt.width_mm + 2 * c,
            filt.length_mm + 2 * c,
            design.emission_filter_z_mm,
            mla_housing_envelope(design).tower_top_z_mm,
        ),
    ]
    return steps


@dataclass(frozen=True)
class TabGeometry:
    """The corner tabs that hold the MLA from above: triangles in the MLA seat's corners, from the
    highest point of the lens surface under them (where the array touches them) at ``z0_mm`` up
    to the mask at ``z1_mm``, bounded by the 45° line |x| + |y| = ``diagonal_mm`` (mm)."""

    z0_mm: float
    z1_mm: float
    diagonal_mm: float


def mla_tab_geometry(design: SystemDesign) -> TabGeometry:
    """The MLA's corner tabs: each reaches ``lip_mm`` over the array's corner along both edges
    (the array may sit ``clearance_mm`` off centre and still meet all four)."""
    mla, lip = design.mla, design.mla_housing.lip_mm
    return TabGeometry(lens_top_under_tabs_mm(design, lip), design.mask_z_mm, (mla.width_mm + mla.length_mm) / 2 - lip)


@dataclass(frozen=True)
class Bore:
    """A centred opening a ray must stay inside from ``z0_mm`` to ``z1_mm`` (mm): the rectangle
    |x| ≤ ``half_x_mm``, |y| ≤ ``half_y_mm`` (mm), its corners cut by 45° faces at
    |x| + |y| = ``diagonal_mm`` (mm; ``inf``: none) — a convex octagon. Walls of the housing,
    the opening of the mask, the MLA seat with its corner tabs."""

    name: str
    half_x_mm: float
    half_y_mm: float
    z0_mm: float
    z1_mm: float
    diagonal_mm: float = math.inf

    def __post_init__(self) -> None:
        if not (self.half_x_mm > 0 and self.half_y_mm > 0 and self.z1_mm > self.z0_mm):
            raise ValueError(f"bore {self.name!r}: needs half-widths > 0 and z1_mm > z0_mm (got {self})")
        if not self.diagonal_mm > max(self.half_x_mm, self.half_y_mm):
            raise ValueError(
                f"bore {self.name!r}: diagonal_mm = {self.diagonal_mm} must exceed both half-widths "
                f"({self.half_x_mm}, {self.half_y_mm}) mm, or the corner faces would close the opening"
            )

    def polygon_mm(self) -> np.ndarray:
        """Vertices (k, 2) of the opening, counter-clockwise, mm (4 for a rectangle, 8 for an octagon)."""
        hx, hy, d = self.half_x_mm, self.half_y_mm, self.diagonal_mm
        if d >= hx + hy:
            return np.array([[hx, -hy], [hx, hy], [-hx, hy], [-hx, -hy]])
        a, b = d - hx, d - hy  # where the corner faces meet the sides
        return np.array([[hx, -a], [hx, a], [b, hy], [-b, hy], [-hx, a], [-hx, -a], [-b, -hy], [b, -hy]])


def mla_tabs(design: SystemDesign) -> Bore:
    """The corner tabs (:func:`mla_tab_geometry`) as an opening: the MLA seat with its corners cut
    at |x| + |y| = ``diagonal_mm``, from the lens surface under them up to the mask."""
    seat = next(step for step in bore_steps(design) if step.name == "MLA seat")
    tabs = mla_tab_geometry(design)
    return Bore("MLA tabs", seat.width_mm / 2, seat.length_mm / 2, tabs.z0_mm, tabs.z1_mm, tabs.diagonal_mm)


def housing_bores(design: SystemDesign) -> tuple[Bore, ...]:
    """The openings a ray must stay inside, bottom to top: the steps of :func:`bore_steps` with the
    corner tabs over the MLA seat and the mask's opening under its seat. The film seat is left
    out: the film's own clear aperture stands for it."""
    mask = design.aperture_mask
    opening = Bore(
        "mask opening", mask.opening_mm / 2, mask.opening_mm / 2, design.mask_z_mm, design.mask_z_mm + mask.thickness_mm
    )
    bores: list[Bore] = []
    for step in bore_steps(design):
        if step.name == "film seat":
            continue
        if step.name == "mask seat":
            bores.append(opening)
        bores.append(Bore(step.name, step.width_mm / 2, step.length_mm / 2, step.z0_mm, step.z1_mm))
        if step.name == "MLA seat":
            bores.append(mla_tabs(design))
    return tuple(bores)
