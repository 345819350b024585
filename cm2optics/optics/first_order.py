"""Derived first-order optics of a design: functions of a :class:`~cm2optics.design.SystemDesign`.

Paraxial quantities come from the lenslet's ABCD matrix (:func:`cm2optics.design.paraxial.lenslet_system`);
the nominal focal plane is the plane of best focus, found by the exact on-axis trace of
:mod:`cm2optics.optics.focus`. The lenslets carry several waves of spherical aberration, so it
lies :func:`focus_shift_mm` nearer the device than the paraxial conjugate of the sensor. It is
where the PSFs are sharpest, where a lab centres its calibration scan and puts its sample:
object-space ``z`` of scans and volumes (DESIGN.md) is measured from this plane, ``+z`` towards
the device. Heights are in the device frame (mm, z = 0 on the sensor). A design is frozen, so
every function is cached per design.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from cm2optics.design import SystemDesign, paraxial
from cm2optics.design.materials import refractive_index
from cm2optics.optics.focus import on_axis_wavefront_rms_waves

__all__ = [
    "best_focus_height_mm",
    "chief_ray_magnification",
    "focus_shift_mm",
    "lenslet_focal_length_mm",
    "lenslet_system",
    "magnification",
    "object_na",
    "object_pixel_um",
    "object_plane_z_mm",
    "object_z_to_height_mm",
    "paraxial_magnification",
    "paraxial_object_plane_z_mm",
    "voxel_um",
    "working_distance_mm",
]

_CACHE = 64


@lru_cache(maxsize=_CACHE)
def lenslet_system(design: SystemDesign) -> np.ndarray:
    """ABCD matrix of one lenslet from the emission filter's front face to the sensor surface."""
    system = paraxial.lenslet_system(design)
    system.flags.writeable = False
    return system


def lenslet_focal_length_mm(design: SystemDesign) -> float:
    """Effective focal length of one lenslet (thin plano-convex) at the design wavelength, mm."""
    n_lens = refractive_index(design.mla.material, design.imaging.design_wavelength_nm)
    return design.mla.radius_mm / (n_lens - 1.0)


def _object_distance_mm(design: SystemDesign) -> float:
    return paraxial.conjugate_object_distance_mm(lenslet_system(design))


def paraxial_object_plane_z_mm(design: SystemDesign) -> float:
    """Height of the paraxial conjugate of the sensor (first-order optics), mm."""
    return float(design.emission_filter_z_mm + design.emission_filter.thickness_mm + _object_distance_mm(design))


def paraxial_magnification(design: SystemDesign) -> float:
    """Lateral magnification |m| of each lenslet between the sensor and its paraxial conjugate."""
    return float(abs(paraxial.lateral_magnification(lenslet_system(design), _object_distance_mm(design))))


def chief_ray_magnification(design: SystemDesign, height_mm: float) -> float:
    """|m| of a lenslet for a source plane at ``height_mm`` (device frame, mm): where the chief ray
    (through the lenslet's vertex, its stop) lands on the sensor per mm of source height
    (paraxial). At the sensor's conjugate this is the conjugate pair's magnification; elsewhere
    it is the magnification of the blurred image's centre."""
    filt = design.emission_filter
    n_f = refractive_index(filt.material, design.imaging.design_wavelength_nm)
    s = height_mm - (design.emission_filter_z_mm + filt.thickness_mm)
    a, b = paraxial.chain(paraxial.propagate(s, 1.0), lenslet_system(design))[0]
    to_vertex = s + filt.thickness_mm / n_f + (design.emission_filter_z_mm - design.mla_vertex_z_mm)
    return float(abs(a - b / to_vertex))


def best_focus_height_mm(design: SystemDesign, tolerance_mm: float = 1e-4) -> float:
    """Height (device frame, mm) of the plane of best focus: the on-axis source height that
    minimises :func:`~cm2optics.optics.focus.on_axis_wavefront_rms_waves`, found by golden-section
    search from 2.5 mm nearer the device to 0.5 mm beyond the paraxial conjugate, to ``tolerance_mm``."""
    paraxial_height = paraxial_object_plane_z_mm(design)
    low = max(paraxial_height - 2.5, design.emission_filter_z_mm + design.emission_filter.thickness_mm + 0.1)
    high = paraxial_height + 0.5
    ratio = (math.sqrt(5.0) - 1.0) / 2.0
    a, b = high - ratio * (high - low), low + ratio * (high - low)
    fa, fb = on_axis_wavefront_rms_waves(design, a), on_axis_wavefront_rms_waves(design, b)
    while high - low > tolerance_mm:
        if fa <= fb:
            high, b, fb = b, a, fa
            a = high - ratio * (high - low)
            fa = on_axis_wavefront_rms_waves(design, a)
        else:
            low, a, fa = a, b, fb
            b = low + ratio * (high - low)
            fb = on_axis_wavefront_rms_waves(design, b)
    return float(0.5 * (low + high))


@lru_cache(maxsize=_CACHE)
def object_plane_z_mm(design: SystemDesign) -> float:
    """Height of the nominal focal plane, mm: the plane of best focus (:func:`best_focus_height_mm`)."""
    return best_focus_height_mm(design)


def focus_shift_mm(design: SystemDesign) -> float:
    """Paraxial conjugate minus the plane of best focus, mm (> 0: best focus nearer the device,
    as for under-corrected spherical aberration)."""
    return paraxial_object_plane_z_mm(design) - object_plane_z_mm(design)


def working_distance_mm(design: SystemDesign) -> float:
    """Nominal focal plane to the lenslet vertices, mm."""
    return object_plane_z_mm(design) - design.mla_vertex_z_mm


def object_z_to_height_mm(design: SystemDesign, z_mm: float) -> float:
    """Object-space z (mm from the focal plane, +z towards the device) → device-frame height, mm."""
    return object_plane_z_mm(design) - z_mm


@lru_cache(maxsize=_CACHE)
def magnification(design: SystemDesign) -> float:
    """Lateral magnification |m| of each lenslet at the nominal focal plane (best focus): where
    the chief ray from a source in that plane lands on the sensor, per mm of source height.
    What a calibration scan measures there."""
    return chief_ray_magnification(design, object_plane_z_mm(design))


def object_pixel_um(design: SystemDesign) -> float:
    """Sensor pixel projected into object space, µm."""
    return design.sensor.pixel_um / magnification(design)


def object_na(design: SystemDesign) -> float:
    """Object-side numerical aperture of one lenslet (square aperture, inscribed circle)."""
    return math.sin(math.atan(design.mla.aperture_mm / 2 / working_distance_mm(design)))


def voxel_um(design: SystemDesign) -> tuple[float, float, float]:
    """(z, y, x) voxel of the design's native reconstruction grid, µm: ``volume.axial_step_um``
    along z and one sensor pixel in object space (:func:`object_pixel_um`) laterally."""
    pixel = object_pixel_um(design)
    return (design.volume.axial_step_um, pixel, pixel)
