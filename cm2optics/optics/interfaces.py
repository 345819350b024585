"""One optical interface between media of indices n₁ (incident side) and n₂: Snell's law,
reflection, the Fresnel coefficients and total internal reflection.

Pure functions over an array-backend ``ops`` (:mod:`cm2optics.optics.arrays`: NumPy or Dr.Jit)
that need only ``sqrt`` and ``maximum``; the rest is arithmetic both backends share. Angles are
given by their cosines: ``cos_i`` of the incident ray with the normal that faces it (≥ 0),
``cos_t`` of the transmitted ray. Vectors (``d``, ``normal``) may be NumPy ``(n, 3)`` arrays with
``(n, 1)`` cosines, Dr.Jit ``Array3f``/``Array3f64``, or one component at a time.
"""

from __future__ import annotations

import math
from typing import Any

__all__ = [
    "brewster_angle_rad",
    "critical_angle_rad",
    "fresnel_amplitudes",
    "fresnel_reflectance",
    "fresnel_transmittance",
    "reflect",
    "refract",
    "snell_cos_t",
]


def snell_cos_t(ops: Any, cos_i: Any, eta: Any) -> tuple[Any, Any]:
    """Snell's law n₁ sin θᵢ = n₂ sin θₜ with ``eta`` = n₁/n₂: returns (cos θₜ, tir), where
    ``tir`` marks total internal reflection (sin θₜ ≥ 1; cos θₜ is 0 there)."""
    sin2_t = eta * eta * (1.0 - cos_i * cos_i)
    return ops.sqrt(ops.maximum(1.0 - sin2_t, 0.0)), sin2_t >= 1.0


def refract(d: Any, normal: Any, eta: Any, cos_i: Any, cos_t: Any) -> Any:
    """Refracted unit direction η d + (η cos θᵢ − cos θₜ) n of the unit direction ``d`` through
    the unit ``normal`` that faces it (n·d = −cos θᵢ)."""
    return eta * d + (eta * cos_i - cos_t) * normal


def reflect(d: Any, normal: Any, cos_i: Any) -> Any:
    """Mirror direction d + 2 cos θᵢ n of ``d`` about the unit ``normal`` that faces it."""
    return d + 2.0 * cos_i * normal


def fresnel_amplitudes(cos_i: Any, cos_t: Any, n1: Any, n2: Any) -> tuple[Any, Any]:
    """Fresnel amplitude reflection coefficients (r_s, r_p) of the interface n1 → n2."""
    r_s = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)
    r_p = (n2 * cos_i - n1 * cos_t) / (n2 * cos_i + n1 * cos_t)
    return r_s, r_p


def fresnel_reflectance(cos_i: Any, cos_t: Any, n1: Any, n2: Any) -> Any:
    """Unpolarised power reflectance (R_s + R_p)/2 of the interface n1 → n2 (without TIR: pair it
    with the ``tir`` flag of :func:`snell_cos_t`)."""
    r_s, r_p = fresnel_amplitudes(cos_i, cos_t, n1, n2)
    return 0.5 * (r_s * r_s + r_p * r_p)


def fresnel_transmittance(cos_i: Any, cos_t: Any, n1: Any, n2: Any) -> Any:
    """Unpolarised power transmittance 1 − (R_s + R_p)/2 of the interface n1 → n2."""
    return 1.0 - fresnel_reflectance(cos_i, cos_t, n1, n2)


def critical_angle_rad(n1: float, n2: float) -> float:
    """Angle of incidence (rad) beyond which light in n1 is totally reflected at n2 < n1."""
    if not n2 < n1:
        raise ValueError(f"n2 = {n2}: total internal reflection needs n2 < n1 = {n1}")
    return math.asin(n2 / n1)


def brewster_angle_rad(n1: float, n2: float) -> float:
    """Angle of incidence (rad) at which the p-polarised reflectance of n1 → n2 vanishes."""
    return math.atan2(n2, n1)
