"""Beam-shaping TIR collimators: the cm2-v2 architecture, designed for a flat-top beam.

:mod:`cm2optics.optics.collimator` designs both optical surfaces to send every ray from the LED's
centre parallel to the axis. A collimated beam lights a spot the size of the exit face; the
field of view is twice as wide, so the array's irradiance peaks in the middle. Here the same
two surfaces — the lens on the cavity floor and the freeform TIR wall — are designed for a
prescribed ray mapping instead: the ray leaving the LED at θ must leave the exit face (in air)
at ψ(θ) from the axis, chosen so that each sub-beam lights a disc uniformly on a plane across
the beam:

* lens rays, 0 ≤ θ ≤ θ_L:   tan ψ = tan α_lens · F_lens^γ, F_lens = sin²θ / sin²θ_L;
* TIR rays, θ_L < θ ≤ θ_max: tan ψ = ± tan α_tir · F_tir^γ, F_tir = (sin²θ_max − sin²θ) / (sin²θ_max − sin²θ_L),

(F is the sub-beam's flux fraction for a Lambertian source; with γ = ½ each sub-beam lights a
disc uniformly, as a uniform disc's flux grows as tan²ψ), ``+`` spreading outwards, ``−``
crossing the axis. In the material the ray must then
travel at φ with sin ψ = n sin φ (the flat exit face refracts it to ψ).

Surfaces from the mapping (meridional plane, LED at the origin, (r, z)):

* lens: P = ρ(θ) (sin θ, cos θ); its normal is parallel to e − n w (vector Snell, e the ray,
  w = (sin φ, cos φ)), which gives ``ρ'/ρ = n sin(θ − φ) / (n cos(θ − φ) − 1)``
  (with φ ≡ 0 the hyperbola of :mod:`cm2optics.optics.collimator`); scaled so that its edge meets the
  cavity wall on the ray θ_L;
* TIR wall: P = W + s u (W on the cavity wall, u the ray refracted there); the mirror normal is
  parallel to w − u, which gives ``s' = −(ẑ·N + s u'·N) / (u·N)`` along the wall height, started
  where the surface's tangent meets the entry plane ``entry_wall_mm`` outside the cavity.

With α = 0 both reduce exactly to the collimating design. The mapping's parameters are fields
of :class:`cm2optics.design.Collimator` (``lens_spread_deg``, ``tir_spread_deg``,
``tir_crossing``, ``lens_exponent``, ``tir_exponent``), so a design YAML rebuilds the shaped
part; :func:`cm2optics.optics.collimator.profile_from_parameters` calls :func:`shaped_profile` for them.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.integrate import solve_ivp

from cm2optics.design import Collimator, DesignError
from cm2optics.design.materials import refractive_index
from cm2optics.optics.collimator import CollimatorProfile, cone_wall, enclosed_profile

__all__ = ["shaped_profile"]


def _inside_angle(psi: np.ndarray, n: float) -> np.ndarray:
    return np.arcsin(np.sin(psi) / n)


def shaped_profile(collimator: Collimator, wavelength_nm: float, samples: int = 241) -> CollimatorProfile:
    """The collimator's section designed for its ray mapping (module docstring).

    collimator: envelope, lens angle and beam shape (spreads, crossing, exponents).
    wavelength_nm: design wavelength, nm. samples: points on each freeform curve.
    Raises :class:`DesignError` when the optics cannot be built in the envelope.
    """
    n = float(refractive_index(collimator.material, wavelength_nm))
    a, g = collimator.cavity_radius_mm, collimator.led_gap_mm
    theta_l = math.radians(collimator.lens_half_angle_deg)
    theta_max = math.atan2(a, g)
    if theta_l >= theta_max:
        raise DesignError(
            "collimator.lens_half_angle_deg",
            collimator.lens_half_angle_deg,
            "must be below the cavity mouth's ray angle",
        )
    lens_r, lens_z = _lens_curve(collimator, n, theta_l, samples)
    if collimator.tir_cone_deg > 0.0:
        tir_r, tir_z, tir_theta, margin = cone_wall(collimator, n)
    else:
        tir_r, tir_z, tir_theta, margin = _tir_wall_curve(collimator, n, theta_l, theta_max, float(lens_z[-1]), samples)
    return enclosed_profile(
        collimator, n, wavelength_nm, (lens_r, lens_z), (tir_r, tir_z), tir_theta, theta_max, margin
    )


def _lens_curve(collimator: Collimator, n: float, theta_l: float, samples: int) -> tuple[np.ndarray, np.ndarray]:
    """The lens on the cavity floor, (r, z) in mm from the LED, for the lens rays 0 ≤ θ ≤ θ_L
    (rad; material index n); its edge meets the cavity wall on the ray θ_L."""
    a, g = collimator.cavity_radius_mm, collimator.led_gap_mm
    tan_lens = math.tan(math.radians(collimator.lens_spread_deg))

    # Lens: ρ'/ρ = n sin(θ − φ)/(n cos(θ − φ) − 1), integrated as log ρ.
    def phi_lens(theta):
        fraction = (np.sin(theta) / math.sin(theta_l)) ** 2
        return _inside_angle(np.arctan(tan_lens * fraction**collimator.lens_exponent), n)

    def lens_rhs(theta, log_rho):
        delta = theta - phi_lens(theta)
        denominator = n * np.cos(delta) - 1.0
        return [n * np.sin(delta) / denominator]

    theta = np.linspace(0.0, theta_l, samples)
    if np.any(n * np.cos(theta - phi_lens(theta)) - 1.0 <= 1e-6):
        raise DesignError(
            "collimator.lens_half_angle_deg",
            collimator.lens_half_angle_deg,
            "no refracting lens reaches this cone with this spread (the ray would graze the surface)",
        )
    lens = solve_ivp(lens_rhs, (0.0, theta_l), [0.0], t_eval=theta, rtol=1e-10, atol=1e-12)
    if not lens.success:
        raise RuntimeError(f"lens integration failed: {lens.message}")
    rho_rel = np.exp(lens.y[0])
    scale = (a / math.sin(theta_l)) / rho_rel[-1]
    rho = scale * rho_rel
    vertex = float(rho[0])
    lens_r, lens_z = rho * np.sin(theta), rho * np.cos(theta)
    lens_edge = a / math.tan(theta_l)
    lens_r[-1], lens_z[-1] = a, lens_edge
    if vertex <= g:
        raise DesignError(
            "collimator.lens_half_angle_deg",
            collimator.lens_half_angle_deg,
            f"the lens vertex (z = {vertex:.3f} mm) must lie above the entry plane (led_gap_mm = {g})",
        )
    if np.any(np.diff(lens_r) <= 0):
        raise DesignError("collimator", "lens", "the lens profile folds back on itself for this spread")
    return lens_r, lens_z


def _tir_wall_curve(
    collimator: Collimator, n: float, theta_l: float, theta_max: float, lens_edge: float, samples: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The freeform TIR wall, (r, z) in mm, for the TIR rays θ_L < θ ≤ θ_max (rad), up to the lens
    edge's height (mm); also the rays' angles (rad) and the TIR margin along it (degrees)."""
    a, g = collimator.cavity_radius_mm, collimator.led_gap_mm
    tan_tir = math.tan(math.radians(collimator.tir_spread_deg))
    sign = -1.0 if collimator.tir_crossing else 1.0

    # TIR wall along the cavity wall height z_w (mouth ray at z_w = g up to the lens-edge ray).
    sin2_max, sin2_l = math.sin(theta_max) ** 2, math.sin(theta_l) ** 2

    def rays(zw):
        rho_w = np.hypot(a, zw)
        uz = zw / (n * rho_w)
        ur = np.sqrt(1.0 - uz**2)
        duz = a**2 / (n * rho_w**3)
        dur = -uz * duz / ur
        th = np.arctan2(a, zw)
        fraction = np.clip((sin2_max - np.sin(th) ** 2) / (sin2_max - sin2_l), 0.0, 1.0)
        phi = sign * _inside_angle(np.arctan(tan_tir * fraction**collimator.tir_exponent), n)
        return ur, uz, dur, duz, np.sin(phi), np.cos(phi)

    def normal(ur, uz, wr, wz):
        nr, nz = wr - ur, wz - uz
        length = np.hypot(nr, nz)
        return nr / length, nz / length

    def tir_rhs(zw, s):
        ur, uz, dur, duz, wr, wz = rays(zw)
        nr, nz = normal(ur, uz, wr, wz)
        return [-(nz + s[0] * (dur * nr + duz * nz)) / (ur * nr + uz * nz)]

    ur0, uz0, _, _, wr0, wz0 = rays(g)
    nr0, nz0 = normal(ur0, uz0, wr0, wz0)
    tr, tz = nz0, -nr0  # tangent
    s0 = collimator.entry_wall_mm / (ur0 - uz0 * tr / tz)
    if not (math.isfinite(s0) and s0 > 0):
        raise DesignError("collimator.entry_wall_mm", collimator.entry_wall_mm, "the TIR wall cannot start there")
    tir_theta = np.linspace(theta_max, theta_l, samples)
    wall_z = a / np.tan(tir_theta)
    wall_z[0], wall_z[-1] = g, lens_edge
    tir = solve_ivp(tir_rhs, (g, lens_edge), [s0], t_eval=wall_z, method="DOP853", rtol=1e-10, atol=1e-12)
    if not tir.success or tir.y.shape[1] != len(wall_z):
        raise DesignError("collimator", "TIR wall", f"integration failed ({tir.message})")
    s = tir.y[0]
    ur, uz, _, _, wr, wz = rays(wall_z)
    tir_r, tir_z = a + s * ur, wall_z + s * uz
    nr, nz = normal(ur, uz, wr, wz)
    incidence = np.arccos(np.clip(np.abs(ur * nr + uz * nz), 0.0, 1.0))
    margin = np.degrees(incidence - math.asin(1.0 / n))
    if margin.min() <= 0:
        raise DesignError(
            "collimator", "TIR wall", f"rays would leak through the TIR wall (margin {margin.min():.1f}°)"
        )
    if np.any(s <= 0) or np.any(np.diff(tir_z) <= 0):
        raise DesignError("collimator", "TIR wall", "the TIR wall folds back on itself for this spread")
    return tir_r, tir_z, tir_theta, margin
