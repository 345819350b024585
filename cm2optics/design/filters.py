"""The emission and excitation interference filters and the absorption film."""

from __future__ import annotations

from dataclasses import dataclass

from cm2optics.design.materials import Material
from cm2optics.design.validation import check, in_range, positive

__all__ = ["AbsorptionFilter", "InterferenceFilter"]


@dataclass(frozen=True)
class InterferenceFilter:
    """Thin-film band-pass filter on a glass plate.

    width_mm, length_mm, thickness_mm: plate size, mm.
    material: substrate.
    center_nm, bandwidth_nm: nominal passband centre and full width at normal incidence, nm.
    """

    width_mm: float
    length_mm: float
    thickness_mm: float
    material: Material
    center_nm: float
    bandwidth_nm: float

    def __post_init__(self) -> None:
        positive(self, "width_mm", "length_mm", "thickness_mm")
        in_range(self, "center_nm", 350.0, 1000.0, " nm")
        in_range(self, "bandwidth_nm", 1.0, 300.0, " nm")
        check("material", self.material, self.material.is_transparent, "a filter substrate must be transparent")


@dataclass(frozen=True)
class AbsorptionFilter:
    """Absorbing long-pass film (Wratten gel class).

    width_mm, length_mm, thickness_mm: film size, mm.
    material: film base.
    cut_on_nm: wavelength of 50 % transmission at normal incidence, nm.
    """

    width_mm: float
    length_mm: float
    thickness_mm: float
    material: Material
    cut_on_nm: float

    def __post_init__(self) -> None:
        positive(self, "width_mm", "length_mm", "thickness_mm")
        in_range(self, "cut_on_nm", 350.0, 1000.0, " nm")
