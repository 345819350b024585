"""Freeform departures of the collimator from revolution: a Zernike sag added to its lens.

Pure NumPy, shared by the CAD part (:mod:`cm2optics.cad.collimator`) and the sweep's meshes
(:mod:`cm2optics.illumination.optimize`), so the tracer reads the same surface the printer gets.

The lens (the cavity's floor) becomes ``z(x, y) = z_lens(r) + S(x, y)`` with
``S = Σ_j c_j Z_j(ρ, φ)``, ``ρ = r / a`` (``a`` the cavity radius), ``Z_j`` the Zernike
polynomials in Noll's order and normalisation (unit RMS over the disc: ``Z_2 = 2ρ cos φ`` is a
tilt about y of slope ``2 c_2 / a``, ``Z_4 = √3 (2ρ² − 1)`` defocus …), ``c_j`` in µm. The cavity
wall below the lens edge follows with a linear blend, ``δz = S(a, φ) (z − g)/(z_edge − g)``
(``g`` the entry plane), so the solid stays closed; every other face is untouched.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from cm2optics.optics.collimator import CollimatorProfile

__all__ = [
    "MAX_TERMS",
    "displace_lens",
    "lens_sag_mm",
    "noll_indices",
    "rim_piston_um",
    "zernike",
    "zernike_with_gradient",
]

#: Most Zernike terms a design may give (Noll j = 1 … 28: up to the 6th radial order).
MAX_TERMS = 28
#: Distance within which a vertex counts as lying on the cavity wall, mm.
_ON_WALL_MM = 1e-5


def noll_indices(j: int) -> tuple[int, int]:
    """Radial order n and signed azimuthal frequency m of Noll's term ``j`` (≥ 1); m > 0 is a
    cosine term, m < 0 a sine term."""
    if j < 1:
        raise ValueError(f"Noll index {j}: must be ≥ 1")
    n = int((math.isqrt(8 * (j - 1) + 1) - 1) // 2)
    p = j - n * (n + 1) // 2
    k = n % 2
    m = ((p + k) // 2) * 2 - k
    return n, (m if j % 2 == 0 else -m) if m else 0


def _radial_terms(n: int, am: int) -> list[tuple[float, int]]:
    """(weight, power of ρ) of the radial polynomial ``R_n^|m|(ρ)``."""
    terms = []
    for s in range((n - am) // 2 + 1):
        weight = (-1) ** s * math.factorial(n - s)
        weight /= math.factorial(s) * math.factorial((n + am) // 2 - s) * math.factorial((n - am) // 2 - s)
        terms.append((weight, n - 2 * s))
    return terms


def zernike(j: int, rho: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Noll's ``Z_j(ρ, φ)``, unit RMS over the unit disc (dimensionless)."""
    n, m = noll_indices(j)
    am = abs(m)
    radial = np.zeros_like(rho, dtype=float)
    for weight, power in _radial_terms(n, am):
        radial = radial + weight * rho**power
    if m == 0:
        return math.sqrt(n + 1) * radial
    angular = np.cos(am * phi) if m > 0 else np.sin(am * phi)
    return math.sqrt(2 * (n + 1)) * radial * angular


def zernike_with_gradient(j: int, x_mm: Any, y_mm: Any, radius_mm: float, ops: Any) -> tuple[Any, Any, Any]:
    """``Z_j`` at (x, y) (mm) over a disc of ``radius_mm`` and its slopes ``∂Z_j/∂x``,
    ``∂Z_j/∂y`` (1/mm), for points inside the disc. ``ops``: the array module (``numpy`` or
    ``drjit``: ``sqrt``, ``atan2``, ``cos``, ``sin``), so the Dr.Jit gradient trace evaluates the
    same polynomials as the CAD part."""
    n, m = noll_indices(j)
    am = abs(m)
    r = ops.sqrt(x_mm * x_mm + y_mm * y_mm) + 1e-12  # finite slopes at the vertex (they are: R ∝ ρ^|m|)
    rho = r / radius_mm
    radial = 0.0 * rho
    slope = 0.0 * rho  # dR/dρ
    for weight, power in _radial_terms(n, am):
        radial = radial + weight * rho**power
        if power:
            slope = slope + weight * power * rho ** (power - 1)
    norm = math.sqrt(n + 1) if m == 0 else math.sqrt(2 * (n + 1))
    if m == 0:
        angular, d_angular = 1.0, 0.0
    else:
        phi = ops.atan2(y_mm, x_mm)
        cos_m, sin_m = ops.cos(am * phi), ops.sin(am * phi)
        angular, d_angular = (cos_m, -am * sin_m) if m > 0 else (sin_m, am * cos_m)
    # ∂ρ/∂x = x / (r a), ∂φ/∂x = −y / r², ∂ρ/∂y = y / (r a), ∂φ/∂y = x / r².
    along_r = norm * slope * angular / (r * radius_mm)
    along_phi = norm * radial * d_angular / (r * r)
    return norm * radial * angular, along_r * x_mm - along_phi * y_mm, along_r * y_mm + along_phi * x_mm


def rim_piston_um(terms: tuple[int, ...], coefficients_um: Any) -> Any:
    """The piston ``c_1`` (µm) that holds the lens's rim where it is for the rotationally
    symmetric terms among ``terms`` (``Z_j(1) = √(n + 1)`` for m = 0): ``−Σ √(n + 1) c_j``, so
    that these terms reshape the lens without moving its junction with the cavity wall.
    ``coefficients_um``: floats or Dr.Jit arrays, one per term."""
    piston = 0.0
    for j, c in zip(terms, coefficients_um, strict=True):
        n, m = noll_indices(j)
        if m == 0 and j > 1:
            piston = piston - math.sqrt(n + 1) * c
    return piston


def lens_sag_mm(
    coefficients_um: tuple[float, ...], x_mm: np.ndarray, y_mm: np.ndarray, radius_mm: float, clip: bool = True
) -> np.ndarray:
    """The sag ``S(x, y)`` (mm) of Zernike coefficients ``c_1 … c_J`` (µm) over a disc of
    ``radius_mm``; ``clip``: ρ is clipped at 1 (points past the rim get the rim's sag), else the
    polynomials continue past it."""
    rho = np.hypot(x_mm, y_mm) / radius_mm
    rho = np.minimum(rho, 1.0) if clip else rho
    phi = np.arctan2(y_mm, x_mm)
    sag = np.zeros_like(rho, dtype=float)
    for j, c in enumerate(coefficients_um, start=1):
        if c != 0.0:
            sag = sag + 1e-3 * c * zernike(j, rho, phi)
    return sag


def displace_lens(
    vertices_mm: np.ndarray, profile: CollimatorProfile, coefficients_um: tuple[float, ...]
) -> np.ndarray:
    """Vertices (LED frame, mm) of a collimator mesh of ``profile`` with the lens sag of
    ``coefficients_um`` (µm) applied to the lens and blended down the cavity wall."""
    v = np.array(vertices_mm, dtype=float)
    a, g = profile.cavity_radius_mm, profile.entry_z_mm
    r = np.hypot(v[:, 0], v[:, 1])
    z = v[:, 2]
    inside = (z > g + _ON_WALL_MM) & (z < profile.exit_z_mm - _ON_WALL_MM)
    lens = inside & (r < a - _ON_WALL_MM)
    wall = (np.abs(r - a) <= _ON_WALL_MM) & (z >= g - _ON_WALL_MM) & (z <= profile.lens_edge_z_mm + _ON_WALL_MM)
    sag = lens_sag_mm(coefficients_um, v[:, 0], v[:, 1], a)
    blend = np.clip((z - g) / (profile.lens_edge_z_mm - g), 0.0, 1.0)
    v[:, 2] += np.where(lens, sag, 0.0) + np.where(wall & ~lens, sag * blend, 0.0)
    return v
