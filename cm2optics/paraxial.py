"""Paraxial (first-order) optics with ray-transfer (ABCD) matrices.

A ray is the column (y, n·u): height y in mm and reduced angle n·u. Elements are
propagation through a medium and refraction at a spherical surface; matrices multiply
right to left in the order light meets them.
"""

from __future__ import annotations

import numpy as np


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
