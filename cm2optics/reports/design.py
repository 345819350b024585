"""The derived first-order optics of a design as one table (``cm2 design show``, the demo)."""

from __future__ import annotations

from cm2optics.design import SystemDesign
from cm2optics.optics import first_order

__all__ = ["design_summary"]


def design_summary(design: SystemDesign) -> dict[str, float | str]:
    """Derived optics of a design (mm, µm as named): at the focal plane (best focus) and paraxial."""
    return {
        "name": design.name,
        "lenslet_focal_length_mm": round(first_order.lenslet_focal_length_mm(design), 4),
        "magnification": round(first_order.magnification(design), 4),
        "object_pixel_um": round(first_order.object_pixel_um(design), 4),
        "working_distance_mm": round(first_order.working_distance_mm(design), 4),
        "object_plane_z_mm": round(first_order.object_plane_z_mm(design), 4),
        "paraxial_magnification": round(first_order.paraxial_magnification(design), 4),
        "paraxial_object_plane_z_mm": round(first_order.paraxial_object_plane_z_mm(design), 4),
        "focus_shift_mm": round(first_order.focus_shift_mm(design), 4),
        "object_na": round(first_order.object_na(design), 4),
        "mla_flat_z_mm": design.imaging.mla_to_sensor_mm,
        "mla_vertex_z_mm": round(design.mla_vertex_z_mm, 4),
        "emission_filter_z_mm": round(design.emission_filter_z_mm, 4),
        "lens_corner_sag_mm": round(design.mla.corner_sag_mm, 5),
        "parameter_hash": design.parameter_hash(),
    }
