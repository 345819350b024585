"""The cells of a microlens array: full cells and the partial ones left by dicing.

Pure geometry (no CAD), shared by the CAD part (:mod:`cm2optics.cad.mla`) and the emission
tracer (:mod:`cm2optics.emission.optics`). Coordinates in mm, in the array's plane, centred on
the central lenslet (x along columns, y along rows).

The one place where the as-built array geometry (:class:`cm2optics.design.AsBuilt`) is applied:
``lens_cells(mla, as_built)`` scales the lattice by (pitch + ``lenslet_pitch_delta_mm``)/pitch
about the central lenslet, displaces single lenslets by ``lenslet_decenter_mm[j]`` within their
cells, rotates the whole array by ``mla_rotation_deg`` about the nominal axis, then shifts it by
``mla_decenter_*_mm`` (the order of :class:`cm2optics.calibrate.simulate.AnalyticSimulator`).
Each cell's footprint moves with its centre (a displaced lenslet's vertex moves within its
footprint); footprints stay axis-aligned rectangles under a rotation, so the vertices (and the
foci) are exact while the cells' edges are off by ≤ half a pitch × the angle (≤ 26 µm at 3° for
a 1-mm pitch). The CAD part is the array as designed (``as_built`` omitted): the as-built
departures are properties of the assembly, traced, not manufactured.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cm2optics.design import AsBuilt, MicrolensArray, Side, SystemDesign


@dataclass(frozen=True)
class LensCell:
    """One (possibly partial) cell: its footprint and its lenslet's vertex, mm (local frame).

    row, col: cell indices (row along +y, col along +x; −1 or rows/cols for partial cells).
    """

    x_min: float
    x_max: float
    y_min: float
    y_max: float
    vertex_x: float
    vertex_y: float
    partial: bool
    row: int = 0
    col: int = 0


def lens_cells(mla: MicrolensArray, as_built: AsBuilt | None = None) -> list[LensCell]:
    """Full cells of the array plus the partial cells left by dicing on ``partial_sides``, row by
    row; with ``as_built``, placed as built (see the module docstring)."""
    p, b = mla.pitch_mm, mla.partial_border_mm
    x_idx = list(range(mla.cols))
    y_idx = list(range(mla.rows))
    if b > 0 and Side.MINUS_X in mla.partial_sides:
        x_idx.insert(0, -1)
    if b > 0 and Side.PLUS_X in mla.partial_sides:
        x_idx.append(mla.cols)
    if b > 0 and Side.MINUS_Y in mla.partial_sides:
        y_idx.insert(0, -1)
    if b > 0 and Side.PLUS_Y in mla.partial_sides:
        y_idx.append(mla.rows)

    def span(i: int, n: int) -> tuple[float, float, float]:
        centre = (i - (n - 1) / 2) * p
        low, high = centre - p / 2, centre + p / 2
        if i < 0:
            low = high - b
        elif i >= n:
            high = low + b
        return low, high, centre

    cells = []
    for j in y_idx:
        y0, y1, yc = span(j, mla.rows)
        for i in x_idx:
            x0, x1, xc = span(i, mla.cols)
            partial = not (0 <= i < mla.cols and 0 <= j < mla.rows)
            cells.append(LensCell(x0, x1, y0, y1, xc, yc, partial, j, i))
    if as_built is None or as_built.is_nominal:
        return cells
    return [_as_built(mla, as_built, cell) for cell in cells]


def _as_built(mla: MicrolensArray, as_built: AsBuilt, cell: LensCell) -> LensCell:
    """``cell`` placed as built: pitch scale, lenslet displacement, rotation, array decentre (mm)."""
    scale = (mla.pitch_mm + as_built.lenslet_pitch_delta_mm) / mla.pitch_mm
    centre_x, centre_y = cell.vertex_x * scale, cell.vertex_y * scale  # cell centre = nominal vertex
    dx, dy = (0.0, 0.0) if cell.partial else as_built.lenslet_offset_mm(cell.row * mla.cols + cell.col)
    a = math.radians(as_built.mla_rotation_deg)
    cos, sin = math.cos(a), math.sin(a)

    def place(x: float, y: float) -> tuple[float, float]:
        return (
            cos * x - sin * y + as_built.mla_decenter_x_mm,
            sin * x + cos * y + as_built.mla_decenter_y_mm,
        )

    cx, cy = place(centre_x, centre_y)
    vx, vy = place(centre_x + dx, centre_y + dy)
    half_low_x, half_high_x = (cell.vertex_x - cell.x_min) * scale, (cell.x_max - cell.vertex_x) * scale
    half_low_y, half_high_y = (cell.vertex_y - cell.y_min) * scale, (cell.y_max - cell.vertex_y) * scale
    return LensCell(
        cx - half_low_x, cx + half_high_x, cy - half_low_y, cy + half_high_y, vx, vy, cell.partial, cell.row, cell.col
    )


def lens_top_under_tabs_mm(design: SystemDesign, lip_mm: float, samples: int = 101) -> float:
    """Highest point (device frame, mm) of the array's lens surface under the corner tabs: the
    triangles of legs ``lip_mm`` (mm) in the corners of the array's footprint, sampled on a
    ``samples``-point grid per leg, plus 1 µm (the sampling's bound), so that the tabs touch the
    lenses without cutting into them."""
    mla = design.mla
    cells = lens_cells(mla)
    half_w, half_l, half = mla.width_mm / 2, mla.length_mm / 2, mla.aperture_mm / 2
    t = np.linspace(0.0, 1.0, samples)
    a, b = (g.ravel() for g in np.meshgrid(t, t))
    a, b = a[a + b <= 1.0], b[a + b <= 1.0]
    land = mla.thickness_mm - mla.corner_sag_mm
    top = land
    for sx in (-1, 1):
        for sy in (-1, 1):
            x, y = sx * (half_w - lip_mm * a), sy * (half_l - lip_mm * b)
            for cell in cells:
                inside = (x >= cell.x_min) & (x <= cell.x_max) & (y >= cell.y_min) & (y <= cell.y_max)
                lens = inside & (np.abs(x - cell.vertex_x) <= half) & (np.abs(y - cell.vertex_y) <= half)
                if lens.any():
                    rho2 = (x[lens] - cell.vertex_x) ** 2 + (y[lens] - cell.vertex_y) ** 2
                    top = max(top, float(np.max(mla.thickness_mm - mla.sag_mm(np.sqrt(rho2)))))
    return design.imaging.mla_to_sensor_mm + top + 1e-3
