"""The cells of a microlens array: full cells and the partial ones left by dicing.

Pure geometry (no CAD), shared by the CAD part (:mod:`cm2optics.cad.mla`) and the emission
tracer (:mod:`cm2optics.emission.optics`). Coordinates in mm, in the array's plane, centred on
the central lenslet (x along columns, y along rows).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cm2optics.design import MicrolensArray, Side, SystemDesign


@dataclass(frozen=True)
class LensCell:
    """One (possibly partial) cell: its footprint and its lenslet's vertex, mm (local frame)."""

    x_min: float
    x_max: float
    y_min: float
    y_max: float
    vertex_x: float
    vertex_y: float
    partial: bool


def lens_cells(mla: MicrolensArray) -> list[LensCell]:
    """Full cells of the array plus the partial cells left by dicing on ``partial_sides``."""
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
            cells.append(LensCell(x0, x1, y0, y1, xc, yc, partial))
    return cells


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
