"""Printing rules and the printed housings."""

from __future__ import annotations

from dataclasses import dataclass

from cm2optics.design.validation import check, in_range, non_negative, positive

__all__ = ["BasePlate", "LEDHousing", "MLAHousing", "Mechanics"]


@dataclass(frozen=True)
class Mechanics:
    """Printing and fit rules shared by every printed part.

    clearance_mm: radial gap between a seated part and its seat, mm (0.05–0.2 for a slip fit).
    wall_mm: nominal wall of printed parts, mm.
    min_wall_mm: thinnest wall the printer makes reliably, mm.
    """

    clearance_mm: float
    wall_mm: float
    min_wall_mm: float

    def __post_init__(self) -> None:
        in_range(self, "clearance_mm", 0.05, 0.2, " mm")
        in_range(self, "min_wall_mm", 0.2, 2.0, " mm")
        check("wall_mm", self.wall_mm, self.wall_mm >= self.min_wall_mm, f"must be ≥ min_wall_mm = {self.min_wall_mm}")


@dataclass(frozen=True)
class MLAHousing:
    """Printed housing of the imaging optics, screwed onto the sensor board.

    outer_mm: side of the square tower around the optics, mm.
    flange_mm: thickness of the base flange that carries the screw holes, mm.
    lip_mm: width of the ledges that hold each optic, mm.
    chamfer_mm: 45° chamfer on the tower's top outer edges (room for the tilted LED units), mm.
    """

    outer_mm: float
    flange_mm: float
    lip_mm: float
    chamfer_mm: float

    def __post_init__(self) -> None:
        positive(self, "outer_mm", "flange_mm", "lip_mm")
        non_negative(self, "chamfer_mm")


@dataclass(frozen=True)
class LEDHousing:
    """Printed housing of one LED unit: LED seat, collimator seat, excitation filter seat.

    outer_mm: side of the square housing, mm.
    back_mm: thickness of the back wall behind the LED package, mm.
    lip_mm: width of the front lip that retains the excitation filter, mm.
    """

    outer_mm: float
    back_mm: float
    lip_mm: float

    def __post_init__(self) -> None:
        positive(self, "outer_mm", "back_mm", "lip_mm")


@dataclass(frozen=True)
class BasePlate:
    """Printed dome-shaped plate that holds the LED units around the MLA housing.

    thickness_mm: shell thickness, mm.
    socket_depth_mm: how deep each LED housing sits in its socket, mm.
    """

    thickness_mm: float
    socket_depth_mm: float

    def __post_init__(self) -> None:
        positive(self, "thickness_mm", "socket_depth_mm")


# ----------------------------------------------------------------------------- the system
