"""The emission path of a design, as the tracer sees it: surfaces, clear apertures, housing bore.

Everything is in the device frame (z = 0 on the sensor surface, +z towards the sample), mm.
Light from a source above the device crosses, top to bottom:

====================  ======================================================================
emission filter       N-BK7 plate (``emission_filter``), flush with the tower top; its
                      interference coating's T(λ, θ) is applied per ray (:mod:`.spectral`)
mask                  opaque plate with a square opening (``aperture_mask``)
MLA seat              the bore around the array, from its flat face up to the mask
lenslets              spheres of ``mla.radius_mm``, one per cell, clipped to the cell and to
                      the lenslet's square aperture (exact surfaces, not the CAD mesh)
MLA flat face         plane at ``imaging.mla_to_sensor_mm``; rays must leave through it
spacer                the bore between the MLA and the film (narrower than the film)
absorption film       gelatin plate (``absorption_filter``), optional; its seat is opaque
sensor                the active area at z = 0
====================  ======================================================================

The bore follows the printed MLA housing step by step (:func:`cm2optics.cad.mla_housing.bore_steps`,
rebuilt here without CadQuery and checked against it by the tests). Below the film the housing
opens as a cone onto the active area, which cannot clip a ray that lands on the sensor.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from cm2optics.design import Side, SystemDesign
from cm2optics.layout import mla_housing_envelope
from cm2optics.lenslets import lens_cells
from cm2optics.materials import Material

__all__ = ["Bore", "EmissionOptics", "Lenslet", "Plate", "emission_optics", "lenslets"]


@dataclass(frozen=True)
class Plate:
    """A plane-parallel plate: faces at ``z0_mm`` < ``z1_mm`` (mm), clear half-widths along x
    and y (mm), ``material``."""

    z0_mm: float
    z1_mm: float
    half_x_mm: float
    half_y_mm: float
    material: Material

    @property
    def thickness_mm(self) -> float:
        return self.z1_mm - self.z0_mm


@dataclass(frozen=True)
class Bore:
    """A centred rectangular opening a ray must stay inside from ``z0_mm`` to ``z1_mm`` (mm);
    half-widths along x and y (mm). Walls of the housing, or the opening of the mask."""

    name: str
    half_x_mm: float
    half_y_mm: float
    z0_mm: float
    z1_mm: float


@dataclass(frozen=True)
class Lenslet:
    """One lenslet: its vertex (device frame, mm) and the rectangle of its clear aperture (mm).

    index: position in :attr:`EmissionOptics.lenslets`. row, col: cell indices (row along +y,
    col along +x; −1 or rows/cols for partial cells). partial: a partial cell left by dicing.
    """

    index: int
    row: int
    col: int
    vertex_x_mm: float
    vertex_y_mm: float
    x0_mm: float
    x1_mm: float
    y0_mm: float
    y1_mm: float
    partial: bool


@dataclass(frozen=True)
class EmissionOptics:
    """The emission path of one design (see the module docstring); heights in the device frame, mm.

    filter: the interference filter's plate. mask_z0_mm, mask_z1_mm: mask faces; mask_half_mm:
    half the side of its square opening. vertex_z_mm: height of the lenslet vertices; land_z_mm: height of the lowest point of
    the lens surface (the corner creases);
    radius_mm: lenslet radius; lens_material: array material; flat_z_mm: the MLA's flat face;
    mla_x_mm, mla_y_mm: (low, high) extent of the diced array, partial cells included. film: the absorption film or None.
    bores: openings of the housing and mask. sensor_half_x_mm, sensor_half_y_mm: half the
    active area. object_plane_z_mm: the nominal focal plane.
    """

    filter: Plate
    mask_z0_mm: float
    mask_z1_mm: float
    mask_half_mm: float
    vertex_z_mm: float
    land_z_mm: float
    radius_mm: float
    lens_material: Material
    flat_z_mm: float
    mla_x_mm: tuple[float, float]
    mla_y_mm: tuple[float, float]
    film: Plate | None
    bores: tuple[Bore, ...]
    lenslets: tuple[Lenslet, ...]
    sensor_half_x_mm: float
    sensor_half_y_mm: float
    object_plane_z_mm: float

    def lenslet_visible(self, lenslet: Lenslet) -> bool:
        """Whether any of the lenslet's aperture lies inside the mask opening."""
        h = self.mask_half_mm
        return lenslet.x1_mm > -h and lenslet.x0_mm < h and lenslet.y1_mm > -h and lenslet.y0_mm < h


def lenslets(design: SystemDesign) -> tuple[Lenslet, ...]:
    """Every lenslet of the array (full cells row by row, then with the partial cells that
    :func:`cm2optics.lenslets.lens_cells` adds on ``partial_sides``), in the device frame.

    A lenslet's clear aperture is its cell intersected with the square of side
    ``mla.aperture_mm`` around its vertex.
    """
    half = design.mla.aperture_mm / 2
    rows, cols = design.mla.rows, design.mla.cols
    return tuple(
        Lenslet(
            index=index,
            row=round(cell.vertex_y / design.mla.pitch_mm + (rows - 1) / 2),
            col=round(cell.vertex_x / design.mla.pitch_mm + (cols - 1) / 2),
            vertex_x_mm=cell.vertex_x,
            vertex_y_mm=cell.vertex_y,
            x0_mm=max(cell.x_min, cell.vertex_x - half),
            x1_mm=min(cell.x_max, cell.vertex_x + half),
            y0_mm=max(cell.y_min, cell.vertex_y - half),
            y1_mm=min(cell.y_max, cell.vertex_y + half),
            partial=cell.partial,
        )
        for index, cell in enumerate(lens_cells(design.mla))
    )


def housing_bores(design: SystemDesign) -> tuple[Bore, ...]:
    """The bore of the printed MLA housing, bottom to top (as ``bore_steps`` of the CAD), plus the
    mask's opening. The film seat is left out: the film's own clear aperture stands for it."""
    c, lip = design.mechanics.clearance_mm, design.mla_housing.lip_mm
    mla, film, mask, filt = design.mla, design.absorption_filter, design.aperture_mask, design.emission_filter
    z_mla = design.imaging.mla_to_sensor_mm
    if film is not None:
        spacer = Bore(
            "spacer",
            film.width_mm / 2 - lip,
            film.length_mm / 2 - lip,
            design.imaging.film_to_sensor_mm + film.thickness_mm,
            z_mla,
        )
    else:
        spacer = Bore("spacer", mla.width_mm / 2 + c - lip, mla.length_mm / 2 + c - lip, z_mla - 2 * lip, z_mla)
    top = mla_housing_envelope(design).tower_top_z_mm
    return (
        spacer,
        Bore("MLA seat", mla.width_mm / 2 + c, mla.length_mm / 2 + c, z_mla, design.mask_z_mm),
        Bore(
            "mask opening",
            mask.opening_mm / 2,
            mask.opening_mm / 2,
            design.mask_z_mm,
            design.mask_z_mm + mask.thickness_mm,
        ),
        Bore("mask seat", mask.outer_mm / 2 + c, mask.outer_mm / 2 + c, design.mask_z_mm, design.emission_filter_z_mm),
        Bore("filter seat", filt.width_mm / 2 + c, filt.length_mm / 2 + c, design.emission_filter_z_mm, top),
    )


def _extent(design: SystemDesign, count: int, low_side: Side, high_side: Side) -> tuple[float, float]:
    mla = design.mla
    border = mla.partial_border_mm
    low = -count * mla.pitch_mm / 2 - (border if low_side in mla.partial_sides else 0.0)
    high = count * mla.pitch_mm / 2 + (border if high_side in mla.partial_sides else 0.0)
    return low, high


def emission_optics(design: SystemDesign) -> EmissionOptics:
    """The emission path of ``design`` (see the module docstring)."""
    filt, film = design.emission_filter, design.absorption_filter
    film_plate = None
    if film is not None:
        z0 = design.imaging.film_to_sensor_mm
        film_plate = Plate(z0, z0 + film.thickness_mm, film.width_mm / 2, film.length_mm / 2, film.material)
    z_filter = design.emission_filter_z_mm
    cells = lenslets(design)
    if not math.isfinite(design.object_plane_z_mm):
        raise ValueError(f"the design has no finite focal plane (object_plane_z_mm = {design.object_plane_z_mm})")
    return EmissionOptics(
        filter=Plate(z_filter, z_filter + filt.thickness_mm, filt.width_mm / 2, filt.length_mm / 2, filt.material),
        mask_z0_mm=design.mask_z_mm,
        mask_z1_mm=design.mask_z_mm + design.aperture_mask.thickness_mm,
        mask_half_mm=design.aperture_mask.opening_mm / 2,
        vertex_z_mm=design.mla_vertex_z_mm,
        land_z_mm=design.mla_vertex_z_mm - design.mla.corner_sag_mm,
        radius_mm=design.mla.radius_mm,
        lens_material=design.mla.material,
        flat_z_mm=design.imaging.mla_to_sensor_mm,
        mla_x_mm=_extent(design, design.mla.cols, Side.MINUS_X, Side.PLUS_X),
        mla_y_mm=_extent(design, design.mla.rows, Side.MINUS_Y, Side.PLUS_Y),
        film=film_plate,
        bores=housing_bores(design),
        lenslets=cells,
        sensor_half_x_mm=design.sensor.active_width_mm / 2,
        sensor_half_y_mm=design.sensor.active_length_mm / 2,
        object_plane_z_mm=design.object_plane_z_mm,
    )
