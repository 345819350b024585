"""The cells of a microlens array: full cells and the partial ones left by dicing.

Pure geometry (no CAD), shared by the CAD part (:mod:`cm2optics.cad.mla`) and the emission
tracer (:mod:`cm2optics.emission.optics`). Coordinates in mm, in the array's plane, centred on
the central lenslet (x along columns, y along rows).
"""

from __future__ import annotations

from dataclasses import dataclass

from cm2optics.design import MicrolensArray, Side


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
