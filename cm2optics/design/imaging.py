"""Heights of the imaging elements and the imaged volume."""

from __future__ import annotations

from dataclasses import dataclass

from cm2optics.design.validation import in_range, non_negative, positive

__all__ = ["ImagedVolume", "ImagingLayout"]


@dataclass(frozen=True)
class ImagingLayout:
    """Heights of the imaging elements in the device frame.

    film_to_sensor_mm: sensor surface to the absorption film's lower face, mm.
    mla_to_sensor_mm: sensor surface to the MLA's flat face, mm.
    mask_gap_mm: lenslet vertices to the aperture mask's lower face, mm.
    filter_gap_mm: aperture mask's upper face to the emission filter's lower face, mm.
    design_wavelength_nm: wavelength of the paraxial design (focus, magnification), nm.
    """

    film_to_sensor_mm: float
    mla_to_sensor_mm: float
    mask_gap_mm: float
    filter_gap_mm: float
    design_wavelength_nm: float

    def __post_init__(self) -> None:
        positive(self, "film_to_sensor_mm", "mla_to_sensor_mm")
        non_negative(self, "mask_gap_mm", "filter_gap_mm")
        in_range(self, "design_wavelength_nm", 380.0, 1000.0, " nm")


@dataclass(frozen=True)
class ImagedVolume:
    """The object volume the device is designed to image, centred on the nominal focal plane.

    field_mm: lateral field of view (diameter of the illuminated circle), mm.
    depth_mm: axial extent, mm (± depth_mm/2 around the focal plane).
    axial_step_um: axial sampling of reconstructions, µm.
    """

    field_mm: float
    depth_mm: float
    axial_step_um: float

    def __post_init__(self) -> None:
        positive(self, "field_mm", "depth_mm", "axial_step_um")


# ----------------------------------------------------------------------------- illumination
