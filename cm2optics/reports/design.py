"""The derived first-order optics of a design as one table (``cm2 design show``, the demo)."""

from __future__ import annotations

from cm2optics.design import SystemDesign

__all__ = ["design_summary"]


def design_summary(design: SystemDesign) -> dict[str, float | str]:
    """Derived optics of a design (mm, µm as named): at the focal plane (best focus) and paraxial."""
    return {
        "name": design.name,
        "lenslet_focal_length_mm": round(design.lenslet_focal_length_mm, 4),
        "magnification": round(design.magnification, 4),
        "object_pixel_um": round(design.object_pixel_um, 4),
        "working_distance_mm": round(design.working_distance_mm, 4),
        "object_plane_z_mm": round(design.object_plane_z_mm, 4),
        "paraxial_magnification": round(design.paraxial_magnification, 4),
        "paraxial_object_plane_z_mm": round(design.paraxial_object_plane_z_mm, 4),
        "focus_shift_mm": round(design.focus_shift_mm, 4),
        "object_na": round(design.object_na, 4),
        "mla_flat_z_mm": design.imaging.mla_to_sensor_mm,
        "mla_vertex_z_mm": round(design.mla_vertex_z_mm, 4),
        "emission_filter_z_mm": round(design.emission_filter_z_mm, 4),
        "lens_corner_sag_mm": round(design.mla.corner_sag_mm, 5),
        "parameter_hash": design.parameter_hash(),
    }
