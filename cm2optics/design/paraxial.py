"""Paraxial (first-order) optics with ray-transfer (ABCD) matrices.

A ray is the column (y, n·u): height y in mm and reduced angle n·u. Elements are
propagation through a medium and refraction at a spherical surface; matrices multiply
right to left in the order light meets them.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from cm2optics.design.materials import refractive_index

if TYPE_CHECKING:
    from cm2optics.design.system import SystemDesign


def propagate(distance_mm: float, index: float) -> np.ndarray:
    """Transfer through ``distance_mm`` (mm) of a medium of refractive index ``index``."""
    return np.array([[1.0, distance_mm / index], [0.0, 1.0]])


def refract(radius_mm: float, n_before: float, n_after: float) -> np.ndarray:
    """Refraction at a spherical surface of radius ``radius_mm`` (mm; +: centre after the
    vertex, ``inf`` for a plane) from index ``n_before`` into ``n_after``."""
    power = 0.0 if np.isinf(radius_mm) else (n_after - n_before) / radius_mm
    return np.array([[1.0, 0.0], [-power, 1.0]])


def chain(*elements: np.ndarray) -> np.ndarray:
    """System matrix of ``elements`` given in the order light meets them."""
    system = np.eye(2)
    for element in elements:
        system = element @ system
    return system


def focal_length_mm(system: np.ndarray) -> float:
    """Effective focal length (mm) of a system matrix (object and image in air)."""
    return -1.0 / system[1, 0]


def conjugate_object_distance_mm(system: np.ndarray) -> float:
    """Object distance (mm, in air, before the system) imaged onto the system's output plane.

    Imaging requires the B element of propagate(d) followed by ``system`` to vanish.
    """
    a, b = system[0]
    if a == 0:
        raise ValueError("the output plane is the system's back focal plane: the object is at infinity")
    return -b / a


def lateral_magnification(system: np.ndarray, object_distance_mm: float) -> float:
    """Lateral magnification (signed; negative for an inverted image) of the conjugate pair."""
    full = chain(propagate(object_distance_mm, 1.0), system)
    return float(full[0, 0])


def lenslet_system(design: SystemDesign) -> np.ndarray:
    """ABCD matrix of one lenslet of ``design`` from the emission filter's front face to the
    sensor surface, at the design wavelength: filter plate, air, the lenslet's sphere, the
    substrate, air, the absorption film (if any) and air."""
    lam = design.imaging.design_wavelength_nm
    n_filter = refractive_index(design.emission_filter.material, lam)
    n_lens = refractive_index(design.mla.material, lam)
    air = 1.0
    elements = [
        propagate(design.emission_filter.thickness_mm, n_filter),
        propagate(design.emission_filter_z_mm - design.mla_vertex_z_mm, air),
        refract(design.mla.radius_mm, air, n_lens),
        propagate(design.mla.thickness_mm, n_lens),
        refract(math.inf, n_lens, air),
    ]
    gap_below = design.imaging.mla_to_sensor_mm
    if design.absorption_filter is not None:
        n_film = refractive_index(design.absorption_filter.material, lam)
        film_top = design.imaging.film_to_sensor_mm + design.absorption_filter.thickness_mm
        elements += [propagate(gap_below - film_top, air), propagate(design.absorption_filter.thickness_mm, n_film)]
        gap_below = design.imaging.film_to_sensor_mm
    elements.append(propagate(gap_below, air))
    return chain(*elements)


def has_real_image(design: SystemDesign, min_magnification: float = 0.05) -> bool:
    """Whether the sensor of ``design`` lies beyond the lenslets' back focus: a real object plane
    in front of the filter is imaged onto it with |m| > ``min_magnification``."""
    system = lenslet_system(design)
    a, b = system[0]
    if a == 0:
        return False
    distance = -b / a
    return bool(distance > 0 and abs(lateral_magnification(system, distance)) > min_magnification)
