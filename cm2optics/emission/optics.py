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
MLA tabs              small corner tabs over the array's corners that hold it from above
MLA flat face         plane at ``imaging.mla_to_sensor_mm``; rays must leave through it (a ray
                      that meets the diced side of the array is lost: in the device it is
                      reflected or scattered there, away from its focus)
spacer                the bore between the MLA and the film (the film's ledge: ``lip_mm``
                      narrower than the film)
absorption film       gelatin plate (``absorption_filter``), optional; its seat is opaque
sensor                the active area at z = 0
====================  ======================================================================

As built, the array and the sensor may be tilted (``as_built.mla_tilt_*_deg`` about the centre
of the array's vertex plane, ``as_built.sensor_tilt_*_deg`` about the sensor's centre; the
convention of :mod:`cm2optics.optics.tilt`): the tracer follows the rays into the array's own
frame for the lenslet and its flat face, and lands them on the tilted sensor plane, in its own
axes. The housing, the mask and the film stay put.

The bore is the printed MLA housing's, step by step with its corner tabs: one description,
:mod:`cm2optics.optics.housing`, for the CAD part and this tracer. Below
the film the housing opens as a cone onto the active area, which cannot clip a ray that lands
on the sensor.

Nothing of the housing lies under the array's flat face, where each lenslet's converging beam
is narrow and a small support would shade much of it (corner pads there would cost the corner
lenslets 30 % on axis and whole foci off axis); the tabs above shade ≤ 5 % of a corner lenslet,
where its beam fills its aperture. The spacer is as wide as the rays need (the preset's film is
sized for it: rays reach ≤ 1.92 mm from the axis at the film for any source of the 8-mm field),
so the side foci fade out because of the array itself and the sensor: rays of the outer lenslets
that would leave through the array's diced sides, and foci that land beyond the sensor's edge.
For cm2-v2 every focus keeps ≥ 10 % of its on-axis energy up to ≈ 1.5 mm off axis along y (the
sensor's short side) and ≈ 1.9 mm along x: the "> 1.7 mm" of the paper. The price of the tabs is
the mask's height: it sits ``imaging.mask_gap_mm`` = 0.35 mm over the lenses (a printable tab is
0.4 mm thick), where its edge shades the outer lenslets of off-axis sources a little more than a
mask right on the lenses would: ≈ 5 % less light at the edge of the 8-mm field, 10 % at its corner.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from cm2optics.design import SystemDesign
from cm2optics.design.materials import Material
from cm2optics.errors import UserError
from cm2optics.optics import first_order
from cm2optics.optics.housing import Bore, housing_bores, mla_tabs
from cm2optics.optics.lenslets import lens_cells
from cm2optics.optics.tilt import tilt_matrix

__all__ = ["Bore", "EmissionOptics", "Lenslet", "Plate", "emission_optics", "housing_bores", "lenslets", "mla_tabs"]


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
class Lenslet:
    """One lenslet: its vertex (device frame, mm) and the rectangle of its clear aperture (mm).

    index: position in :attr:`EmissionOptics.lenslets`. row, col: cell indices (row along +y,
    col along +x; −1 or rows/cols for partial cells). partial: a partial cell left by dicing.
    transmission: the fraction of its nominal light the lenslet passes (``as_built.lenslet_transmission``;
    1 for partial cells), applied to its focus.
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
    transmission: float = 1.0


@dataclass(frozen=True)
class EmissionOptics:
    """The emission path of one design (see the module docstring); heights in the device frame, mm.

    filter: the interference filter's plate. mask_z0_mm, mask_z1_mm: mask faces; mask_half_mm:
    half the side of its square opening (as built: + ``as_built.vignetting_radius_delta_mm``). vertex_z_mm: height of the lenslet vertices; land_z_mm: height of the lowest point of
    the lens surface (the corner creases);
    radius_mm: lenslet radius; lens_material: array material; flat_z_mm: the MLA's flat face;
    mla_x_mm, mla_y_mm: (low, high) extent of the diced array, partial cells included. film: the absorption film or None.
    bores: openings of the housing and mask. sensor_half_x_mm, sensor_half_y_mm: half the
    active area. object_plane_z_mm: the nominal focal plane (the plane of best focus,
    :func:`~cm2optics.optics.first_order.object_plane_z_mm`), where object-space z = 0.
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
    mla_tilt: tuple[tuple[float, float, float], ...] = ()
    mla_pivot_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    sensor_tilt: tuple[tuple[float, float, float], ...] = ()

    def lenslet_visible(self, lenslet: Lenslet) -> bool:
        """Whether any of the lenslet's aperture lies inside the mask opening."""
        h = self.mask_half_mm
        return lenslet.x1_mm > -h and lenslet.x0_mm < h and lenslet.y1_mm > -h and lenslet.y0_mm < h


def lenslets(design: SystemDesign) -> tuple[Lenslet, ...]:
    """Every lenslet of the array (full cells row by row, then with the partial cells that
    :func:`cm2optics.optics.lenslets.lens_cells` adds on ``partial_sides``), in the device frame.

    A lenslet's clear aperture is its cell intersected with the square of side
    ``mla.aperture_mm`` around its vertex. The array is placed as built (``design.as_built``:
    decentre, rotation, pitch, single lenslets displaced; see :mod:`cm2optics.optics.lenslets`).
    """
    half = design.mla.aperture_mm / 2
    as_built, cols = design.as_built, design.mla.cols
    return tuple(
        Lenslet(
            index=index,
            row=cell.row,
            col=cell.col,
            vertex_x_mm=cell.vertex_x,
            vertex_y_mm=cell.vertex_y,
            x0_mm=max(cell.x_min, cell.vertex_x - half),
            x1_mm=min(cell.x_max, cell.vertex_x + half),
            y0_mm=max(cell.y_min, cell.vertex_y - half),
            y1_mm=min(cell.y_max, cell.vertex_y + half),
            partial=cell.partial,
            transmission=1.0 if cell.partial else as_built.transmission(cell.row * cols + cell.col),
        )
        for index, cell in enumerate(lens_cells(design.mla, as_built))
    )


def _extent(design: SystemDesign, axis: str) -> tuple[float, float]:
    """(low, high) extent of the diced array along ``axis`` ("x" or "y"), partial cells included,
    as placed (mm): the cells' footprints, not the lenslets' apertures."""
    footprints = lens_cells(design.mla, design.as_built)
    if axis == "x":
        return min(c.x_min for c in footprints), max(c.x_max for c in footprints)
    return min(c.y_min for c in footprints), max(c.y_max for c in footprints)


def _bores(design: SystemDesign, mask_half_mm: float) -> tuple[Bore, ...]:
    """The housing's openings, the mask's with the as-built half-width ``mask_half_mm`` (mm):
    ``as_built.vignetting_radius_delta_mm`` widens or narrows the aperture that vignettes the
    foci of sources far off a lenslet's axis."""
    bores = housing_bores(design)
    if design.as_built.vignetting_radius_delta_mm == 0:
        return bores
    return tuple(
        replace(b, half_x_mm=mask_half_mm, half_y_mm=mask_half_mm) if b.name == "mask opening" else b for b in bores
    )


def emission_optics(design: SystemDesign) -> EmissionOptics:
    """The emission path of ``design`` (see the module docstring)."""
    filt, film, built = design.emission_filter, design.absorption_filter, design.as_built
    film_plate = None
    if film is not None:
        z0 = design.imaging.film_to_sensor_mm
        film_plate = Plate(z0, z0 + film.thickness_mm, film.width_mm / 2, film.length_mm / 2, film.material)
    z_filter = design.emission_filter_z_mm
    cells = lenslets(design)
    mask_half = design.aperture_mask.opening_mm / 2 + design.as_built.vignetting_radius_delta_mm
    if mask_half <= 0:
        raise UserError(
            f"as_built.vignetting_radius_delta_mm = {design.as_built.vignetting_radius_delta_mm:g}: closes the mask's "
            f"opening (half-width {design.aperture_mask.opening_mm / 2:g} mm)"
        )
    if not math.isfinite(first_order.object_plane_z_mm(design)):
        raise ValueError(
            f"the design has no finite focal plane (object_plane_z_mm = {first_order.object_plane_z_mm(design)})"
        )
    return EmissionOptics(
        filter=Plate(z_filter, z_filter + filt.thickness_mm, filt.width_mm / 2, filt.length_mm / 2, filt.material),
        mask_z0_mm=design.mask_z_mm,
        mask_z1_mm=design.mask_z_mm + design.aperture_mask.thickness_mm,
        mask_half_mm=mask_half,
        vertex_z_mm=design.mla_vertex_z_mm,
        land_z_mm=design.mla_vertex_z_mm - design.mla.corner_sag_mm,
        radius_mm=design.mla.radius_mm,
        lens_material=design.mla.material,
        flat_z_mm=design.imaging.mla_to_sensor_mm,
        mla_x_mm=_extent(design, "x"),
        mla_y_mm=_extent(design, "y"),
        film=film_plate,
        bores=_bores(design, mask_half),
        lenslets=cells,
        sensor_half_x_mm=design.sensor.active_width_mm / 2,
        sensor_half_y_mm=design.sensor.active_length_mm / 2,
        object_plane_z_mm=first_order.object_plane_z_mm(design),
        mla_tilt=_rotation(built.mla_tilt_x_deg, built.mla_tilt_y_deg),
        mla_pivot_mm=(built.mla_decenter_x_mm, built.mla_decenter_y_mm, design.mla_vertex_z_mm),
        sensor_tilt=_rotation(built.sensor_tilt_x_deg, built.sensor_tilt_y_deg),
    )


def _rotation(tilt_x_deg: float, tilt_y_deg: float) -> tuple[tuple[float, float, float], ...]:
    """The tilt's rotation as nested tuples (empty when untilted)."""
    if tilt_x_deg == 0 and tilt_y_deg == 0:
        return ()
    return tuple(tuple(float(v) for v in row) for row in tilt_matrix(tilt_x_deg, tilt_y_deg))
