"""The image sensor and the camera board it sits on."""

from __future__ import annotations

from dataclasses import dataclass

from cm2optics.design.validation import check, in_range, positive

__all__ = ["Sensor", "SensorBoard"]


@dataclass(frozen=True)
class Sensor:
    """Image sensor: pixel grid and package.

    name: model name (informational).
    width_px, height_px: active pixels along x (rows) and y.
    pixel_um: pixel pitch, µm.
    bit_depth: ADC bits of a raw frame.
    package_width_mm, package_length_mm: package footprint along x and y, mm.
    package_height_mm: PCB top to the photosensitive surface, mm.
    """

    name: str
    width_px: int
    height_px: int
    pixel_um: float
    bit_depth: int
    package_width_mm: float
    package_length_mm: float
    package_height_mm: float

    def __post_init__(self) -> None:
        for name in ("width_px", "height_px"):
            check(name, getattr(self, name), 16 <= getattr(self, name) <= 100_000, "must lie within 16–100000 px")
        in_range(self, "pixel_um", 0.5, 20.0, " µm")
        check("bit_depth", self.bit_depth, self.bit_depth in (8, 10, 12, 14, 16), "must be one of 8, 10, 12, 14, 16")
        positive(self, "package_width_mm", "package_length_mm", "package_height_mm")
        check(
            "package_width_mm",
            self.package_width_mm,
            self.package_width_mm >= self.active_width_mm and self.package_length_mm >= self.active_length_mm,
            f"the package must enclose the active area {self.active_width_mm:.2f} × {self.active_length_mm:.2f} mm",
        )

    @property
    def active_width_mm(self) -> float:
        return self.width_px * self.pixel_um / 1000.0

    @property
    def active_length_mm(self) -> float:
        return self.height_px * self.pixel_um / 1000.0


@dataclass(frozen=True)
class SensorBoard:
    """The camera PCB the MLA housing screws onto.

    size_mm: side of the square board, mm.
    thickness_mm: PCB thickness, mm.
    hole_spacing_mm: centre-to-centre spacing of the four mounting holes (square pattern), mm.
    hole_diameter_mm: clearance hole diameter for the mounting screws, mm.
    """

    size_mm: float
    thickness_mm: float
    hole_spacing_mm: float
    hole_diameter_mm: float

    def __post_init__(self) -> None:
        positive(self, "size_mm", "thickness_mm", "hole_spacing_mm", "hole_diameter_mm")
        check(
            "hole_spacing_mm",
            self.hole_spacing_mm,
            self.hole_spacing_mm + self.hole_diameter_mm < self.size_mm,
            f"the holes must lie on the board (spacing + diameter < size_mm = {self.size_mm})",
        )


# ----------------------------------------------------------------------------- imaging optics
