"""The microlens array and the aperture mask over it."""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum
from typing import Any

from cm2optics.design.materials import Material
from cm2optics.design.validation import check, positive

__all__ = ["ApertureMask", "MicrolensArray", "Side"]


class Side(StrEnum):
    """A side of the lenslet array, named by the device-frame axis it faces."""

    PLUS_X = "+x"
    MINUS_X = "-x"
    PLUS_Y = "+y"
    MINUS_Y = "-y"


@dataclass(frozen=True)
class MicrolensArray:
    """Square-cell array of plano-convex spherical lenslets, curved side towards the sample.

    rows, cols: lenslets along y and x.
    pitch_mm: cell pitch, mm.
    radius_mm: radius of curvature of every lenslet, mm.
    aperture_mm: side of each lenslet's square aperture inside its cell, mm (= pitch_mm for
        a 100 % fill factor; smaller leaves a flat land between lenslets).
    thickness_mm: substrate plus lens: flat face to lens vertex, mm.
    material: lens material.
    partial_border_mm: width of partial lenslets left around the array by dicing, mm (0: none).
    partial_sides: the sides that carry partial lenslets.
    """

    rows: int
    cols: int
    pitch_mm: float
    radius_mm: float
    aperture_mm: float
    thickness_mm: float
    material: Material
    partial_border_mm: float
    partial_sides: tuple[Side, ...]

    def __post_init__(self) -> None:
        for name in ("rows", "cols"):
            check(name, getattr(self, name), 1 <= getattr(self, name) <= 15, "must lie within 1–15")
        positive(self, "pitch_mm", "radius_mm", "aperture_mm", "thickness_mm")
        check(
            "aperture_mm",
            self.aperture_mm,
            self.aperture_mm <= self.pitch_mm,
            f"a lenslet cannot be larger than its cell (≤ pitch_mm = {self.pitch_mm})",
        )
        half_diagonal = self.aperture_mm / math.sqrt(2.0)
        check(
            "radius_mm",
            self.radius_mm,
            self.radius_mm > half_diagonal,
            f"the sphere must cover the aperture corners (> {half_diagonal:.4f} mm)",
        )
        check(
            "thickness_mm",
            self.thickness_mm,
            self.thickness_mm > self.corner_sag_mm + 0.2,
            f"must exceed the corner sag {self.corner_sag_mm:.4f} mm by ≥ 0.2 mm of substrate",
        )
        check("material", self.material, self.material.is_transparent, "a lens must be transparent")
        check(
            "partial_border_mm",
            self.partial_border_mm,
            0.0 <= self.partial_border_mm < self.pitch_mm,
            f"must lie within 0 ≤ width < pitch_mm = {self.pitch_mm}",
        )

    def sag_mm(self, r_mm: float | Any) -> float | Any:
        """Sag (mm) of a lenslet at radial distance ``r_mm`` (mm) from its vertex."""
        return self.radius_mm - (self.radius_mm**2 - r_mm**2) ** 0.5

    @property
    def corner_sag_mm(self) -> float:
        return float(self.sag_mm(self.aperture_mm / math.sqrt(2.0)))

    @property
    def width_mm(self) -> float:
        """Diced size along x, partial lenslets included, mm."""
        return self.cols * self.pitch_mm + self.partial_border_mm * self._n_partial(Side.PLUS_X, Side.MINUS_X)

    @property
    def length_mm(self) -> float:
        """Diced size along y, partial lenslets included, mm."""
        return self.rows * self.pitch_mm + self.partial_border_mm * self._n_partial(Side.PLUS_Y, Side.MINUS_Y)

    def _n_partial(self, *sides: Side) -> int:
        return sum(side in self.partial_sides for side in sides) if self.partial_border_mm > 0 else 0

    def lenslet_centres_mm(self) -> list[tuple[float, float]]:
        """(x, y) of the full lenslets' vertices in the device frame, mm, row by row."""
        return [
            ((c - (self.cols - 1) / 2) * self.pitch_mm, (r - (self.rows - 1) / 2) * self.pitch_mm)
            for r in range(self.rows)
            for c in range(self.cols)
        ]


@dataclass(frozen=True)
class ApertureMask:
    """Opaque plate over the lenslets that leaves the central array open.

    opening_mm: side of the square opening, mm.
    outer_mm: side of the square plate, mm.
    thickness_mm: plate thickness, mm.
    """

    opening_mm: float
    outer_mm: float
    thickness_mm: float

    def __post_init__(self) -> None:
        positive(self, "opening_mm", "outer_mm", "thickness_mm")
        check(
            "outer_mm",
            self.outer_mm,
            self.outer_mm > self.opening_mm + 0.8,
            "must exceed opening_mm by ≥ 0.8 mm (two 0.4-mm rims)",
        )
