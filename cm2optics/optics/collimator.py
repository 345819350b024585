"""Freeform TIR collimator: its rotationally symmetric profile computed from the optics.

Pure NumPy/SciPy, shared by the CAD part, the illumination tracer and design optimisers.

Frame: the LED frame of :mod:`cm2optics.optics.layout` — origin at the centre of the LED's emitting
surface, ``+z`` along the unit's axis (the direction the light leaves in). A profile point is
``(r, z)``: distance from the axis and height, mm. The design point is the LED centre, the
shared focus of both optical surfaces.

The section, from the LED upwards:

* entry plane ``z = g`` (``led_gap_mm``), pierced by a cylindrical cavity of radius ``a``
  (``cavity_radius_mm``);
* the cavity's floor is the inner lens. A ray leaving the focus at ``θ`` from the axis must
  travel along ``+z`` inside the material; equal optical paths (Fermat) give
  ``ρ(θ) = d (n − 1) / (n cos θ − 1)`` — a hyperbola of eccentricity ``n`` with the LED at its
  far focus (conic constant ``−n²``, vertex radius ``d (n − 1)``). Its edge meets the cavity
  wall on the ray ``θ_L`` (``lens_half_angle_deg``), which fixes the vertex height
  ``d = (a / sin θ_L)(n cos θ_L − 1)/(n − 1)``. It exists only for ``θ_L < arccos(1/n)``
  (the hyperbola's asymptote, ≈ 48.7° in resin at 470 nm);
* rays with ``θ_L < θ < θ_max = atan(a / g)`` cross the cavity wall (``θ_max`` is the ray
  through the cavity mouth; steeper rays meet the flat entry ring and are not designed for).
  The wall refracts them to ``u = (√(1 − u_z²), cos θ / n)``. The outer surface point of that
  ray is ``P = W + s u`` with ``W = (a, z_w)`` on the wall; the reflection law (normal
  bisecting ``u`` and ``+z``) gives the linear ODE ``ds/dz_w = 1 + s u_z′/(1 − u_z)``,
  integrated with :func:`scipy.integrate.solve_ivp` from the mouth ray up to the lens-edge
  ray. The incidence there is ``90° − ψ/2`` (``ψ`` = angle of ``u`` from the axis), so TIR
  holds while ``ψ < 180° − 2 θ_c``; the margin is smallest for the mouth ray;
* below the mouth ray's point the outer surface continues along its tangent down to the entry
  plane, where it starts ``entry_wall_mm`` outside the cavity (the thinnest printed wall);
* with ``tir_max_radius_mm`` the wall stops at that radius (the rays meant for its upper part
  cross the side unreflected); with ``tir_cone_deg`` it is not designed but prescribed,
  ``r = a + w + tan β (z − g) + κ (z − g)²/2`` (:func:`cone_wall`): the designed wall collimates
  the LED's centre but outgrows a 4-mm footprint once the cavity encloses the 1-mm emitter;
* above the lens-edge ray's point it continues as a cylinder up to the square flange
  (``footprint_mm`` × ``footprint_mm`` × ``flange_mm``) whose top is the flat exit face at
  ``z = g + height_mm``. Collimated rays cross the exit face at normal incidence.

:func:`trace_meridional` traces rays in the meridional section through the faceted profile
(vertex normals from splines through the samples, not from the construction), so tests check
the construction rather than restate it.

Choice of the lens angle (the cm2-v2 preset). The paper's "∼52-degree conical angle" is the
full cone: no single air → resin surface collimates a half-angle beyond arccos(1/n) ≈ 48.7°,
and the authors' part has its lens edge ≈ 26.6° off the LED (radius 0.73 mm, 1.45 mm deep).
We collimate a 38° half-angle instead because every ray between the lens edge and the cavity
mouth must meet the TIR surface below the flange, inside a 4-mm square, ≤ 2 mm tall, with a
cavity wider than the 1-mm emitter and 0.4-mm walls: with a 26° lens the surface would have to
reach r ≈ 2.45 mm at z ≈ 2.6 mm. (The authors' wall stops at r ≈ 1.9 mm and, by our estimate,
lets the ≈ 26–35° band — ≈ 14 % of a Lambertian LED's flux — cross the exit plate unreflected.)
38° is about the smallest angle whose TIR surface fits. The price is a short lens focal
distance (0.37 mm), so the 1-mm emitter spreads the lens's beam by up to ≈ atan(0.5/0.37);
the TIR beam, with ≈ 2-mm paths, spreads far less, and the étendue of a 1-mm² Lambertian
emitter through a ≈ 3.8-mm exit allows no better than ≈ 17° overall.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
from scipy.integrate import solve_ivp
from scipy.interpolate import CubicSpline

from cm2optics.design import Collimator, DesignError, SystemDesign
from cm2optics.design.materials import refractive_index

__all__ = [
    "CollimatorProfile",
    "MeridionalTrace",
    "enclosed_profile",
    "Surface",
    "collimator_profile",
    "cone_wall",
    "profile_from_parameters",
    "tir_wall_reach_mm",
    "tir_wall_scale",
    "trace_meridional",
]

#: Azimuths at which the reach of a non-revolved TIR wall is checked against the footprint.
_REACH_AZIMUTHS = np.linspace(0.0, 2.0 * np.pi, 1440, endpoint=False)


def tir_wall_scale(cos2: float, cos4: float, phi_rad: np.ndarray | float) -> np.ndarray | float:
    """``1 + cos2 · cos 2φ + cos4 · cos 4φ``: the factor on the TIR wall's radial departure from
    its entry ring at azimuth ``phi_rad`` (rad, from the LED frame's x axis) of
    :attr:`cm2optics.design.Collimator.tir_cos2` and ``tir_cos4`` (dimensionless)."""
    return 1.0 + cos2 * np.cos(2.0 * np.asarray(phi_rad)) + cos4 * np.cos(4.0 * np.asarray(phi_rad))


def tir_wall_reach_mm(
    entry_radius_mm: float, end_radius_mm: float, cos2: float, cos4: float, phi_rad: np.ndarray | None = None
) -> float:
    """How far the TIR wall's top reaches towards the square footprint's sides, mm: the largest
    ``r(φ) · max(|cos φ|, |sin φ|)`` with ``r(φ) = r_e + (r_end − r_e) · scale(φ)`` (radii mm). The
    wall fits a footprint of side ``s`` when this is below ``s / 2``; for the revolved wall it is
    ``r_end``."""
    phi = _REACH_AZIMUTHS if phi_rad is None else np.asarray(phi_rad)
    radius = entry_radius_mm + (end_radius_mm - entry_radius_mm) * tir_wall_scale(cos2, cos4, phi)
    return float(np.max(radius * np.maximum(np.abs(np.cos(phi)), np.abs(np.sin(phi)))))


class Surface(IntEnum):
    """The faces of the collimator's section, as reported by :func:`trace_meridional`."""

    LENS = 0  # cavity floor: hyperbolic refracting lens
    CAVITY = 1  # cylindrical cavity wall
    ENTRY = 2  # flat entry ring between the cavity and the outer surface
    TIR = 3  # freeform outer surface (with its tangent continuation to the entry plane)
    SIDE = 4  # cylindrical continuation of the outer surface up to the flange
    FLANGE = 5  # underside and edge of the square flange
    EXIT = 6  # flat exit face


@dataclass(frozen=True, eq=False)
class CollimatorProfile:
    """The collimator's meridional profile in the LED frame (lengths mm, angles degrees).

    refractive_index: index of the material at ``wavelength_nm``.
    wavelength_nm: design wavelength (the LED's peak), nm.
    entry_z_mm: height of the entry plane (the cavity mouth), mm.
    exit_z_mm: height of the flat exit face, mm.
    flange_bottom_z_mm: height of the flange's underside, mm.
    footprint_mm: side of the square flange, mm.
    cavity_radius_mm: radius of the cylindrical cavity, mm.
    lens_r_mm, lens_z_mm: lens surface from its vertex (r = 0) to its edge on the cavity wall, mm.
    cavity_r_mm, cavity_z_mm: cavity wall from the lens edge down to the mouth, mm.
    tir_r_mm, tir_z_mm: freeform TIR surface from the mouth ray's point to the lens-edge ray's, mm.
    tir_angle_deg: emission angle from the axis of the ray reflected at each TIR sample, degrees.
    exit_r_mm: exit face (at ``exit_z_mm``) from the axis to the flange's edge along x, mm.
    lens_vertex_z_mm: height of the lens vertex (its focal distance from the LED), mm.
    lens_edge_z_mm: height where the lens meets the cavity wall, mm.
    outer_radius_entry_mm: radius of the outer surface at the entry plane, mm.
    outer_radius_exit_mm: radius of the outer surface where it meets the flange, mm.
    lens_half_angle_deg: half-angle of the cone collimated by the lens, degrees.
    max_angle_deg: steepest ray from the focus that still enters through the cavity, degrees.
    min_tir_margin_deg: smallest (incidence − critical angle) along the TIR surface, degrees.
    min_wall_mm: thinnest printed wall (entry ring, lens centre, flange), mm.
    """

    refractive_index: float
    wavelength_nm: float
    entry_z_mm: float
    exit_z_mm: float
    flange_bottom_z_mm: float
    footprint_mm: float
    cavity_radius_mm: float
    lens_r_mm: np.ndarray
    lens_z_mm: np.ndarray
    cavity_r_mm: np.ndarray
    cavity_z_mm: np.ndarray
    tir_r_mm: np.ndarray
    tir_z_mm: np.ndarray
    tir_angle_deg: np.ndarray
    exit_r_mm: np.ndarray
    lens_vertex_z_mm: float
    lens_edge_z_mm: float
    outer_radius_entry_mm: float
    outer_radius_exit_mm: float
    lens_half_angle_deg: float
    max_angle_deg: float
    min_tir_margin_deg: float
    min_wall_mm: float

    @property
    def lens_sag_mm(self) -> float:
        """Lens edge height above its vertex, mm."""
        return self.lens_edge_z_mm - self.lens_vertex_z_mm

    @property
    def lens_vertex_radius_mm(self) -> float:
        """Radius of curvature of the lens at its vertex, ``d (n − 1)``, mm."""
        return self.lens_vertex_z_mm * (self.refractive_index - 1.0)

    @property
    def lens_conic_constant(self) -> float:
        """Conic constant of the lens, ``−n²`` (a hyperbola of eccentricity n)."""
        return -(self.refractive_index**2)

    def lens_height_mm(self, r_mm: np.ndarray | float) -> np.ndarray | float:
        """Height of the lens surface at radius ``r_mm`` (mm), from the closed form
        ``(n²−1) z² − 2 n d (n−1) z + d²(n−1)² − r² = 0`` (far branch), mm."""
        n, d = self.refractive_index, self.lens_vertex_z_mm
        r = np.asarray(r_mm, dtype=float)
        z = (d * n * (n - 1.0) + np.sqrt(d**2 * (n - 1.0) ** 2 + (n**2 - 1.0) * r**2)) / (n**2 - 1.0)
        return float(z) if z.ndim == 0 else z

    def lens_slope(self, r_mm: np.ndarray | float) -> np.ndarray | float:
        """Slope dz/dr of the lens surface at radius ``r_mm`` (mm), dimensionless."""
        n, d = self.refractive_index, self.lens_vertex_z_mm
        r = np.asarray(r_mm, dtype=float)
        slope = r / ((n**2 - 1.0) * self.lens_height_mm(r) - n * d * (n - 1.0))
        return float(slope) if slope.ndim == 0 else slope

    @property
    def tir_end_z_mm(self) -> float:
        """Height where the lens-edge ray meets the TIR surface, mm."""
        return float(self.tir_z_mm[-1])

    @property
    def height_mm(self) -> float:
        """Entry plane to exit face, mm."""
        return self.exit_z_mm - self.entry_z_mm

    @property
    def critical_angle_deg(self) -> float:
        return math.degrees(math.asin(1.0 / self.refractive_index))

    def faces(self) -> list[tuple[Surface, np.ndarray, bool]]:
        """The right half (r ≥ 0) of the section as a chain of faces from the lens vertex to the
        exit face's centre, the material on the left when walking along it (counter-clockwise).

        Each entry: the face, its points (k, 2) as (r, z) in mm, and whether it is a smooth
        curve (lens, freeform TIR) rather than straight segments.
        """
        a, g = self.cavity_radius_mm, self.entry_z_mm
        half = self.footprint_mm / 2
        tir = np.column_stack([self.tir_r_mm, self.tir_z_mm])
        r_end, z_end = tir[-1]
        chain = [
            (Surface.LENS, np.column_stack([self.lens_r_mm, self.lens_z_mm]), True),
            (Surface.CAVITY, np.column_stack([self.cavity_r_mm, self.cavity_z_mm]), False),
            (Surface.ENTRY, np.array([[a, g], [self.outer_radius_entry_mm, g]]), False),
            (Surface.TIR, np.array([[self.outer_radius_entry_mm, g], tir[0]]), False),
            (Surface.TIR, tir, True),
            (Surface.SIDE, np.array([[r_end, z_end], [r_end, self.flange_bottom_z_mm]]), False),
            (
                Surface.FLANGE,
                np.array([[r_end, self.flange_bottom_z_mm], [half, self.flange_bottom_z_mm], [half, self.exit_z_mm]]),
                False,
            ),
            (Surface.EXIT, np.array([[half, self.exit_z_mm], [0.0, self.exit_z_mm]]), False),
        ]
        return [(face, pts, smooth) for face, pts, smooth in chain if np.linalg.norm(pts[-1] - pts[0]) > 1e-9]

    def lambertian_fractions(self) -> dict[str, float]:
        """Fractions of a Lambertian point source's flux at the focus collimated by the lens,
        by the TIR surface, and not designed for (beyond ``max_angle_deg``)."""
        lens = math.sin(math.radians(self.lens_half_angle_deg)) ** 2
        cavity = math.sin(math.radians(self.max_angle_deg)) ** 2
        return {"lens": lens, "tir": cavity - lens, "uncollimated": 1.0 - cavity}


def _tir_surface(a: float, g: float, z_lens_edge: float, n: float, entry_wall: float, z_samples: np.ndarray):
    """Integrate the outer surface for rays crossing the cavity wall at heights ``z_samples``.

    The surface starts on the mouth ray (``z_w = g``) where its tangent meets the entry plane
    ``entry_wall`` outside the cavity. Returns the surface points (k, 2) and the in-material
    ray directions (k, 2), as (r, z).
    """

    def direction(zw):
        rho = np.hypot(a, zw)
        uz = zw / (n * rho)
        return np.sqrt(1.0 - uz**2), uz, a**2 / (n * rho**3)  # u_r, u_z, du_z/dz_w

    def rhs(zw, s):
        _, uz, duz = direction(zw)
        return 1.0 + s * duz / (1.0 - uz)

    ur0, uz0, _ = direction(g)
    # The tangent (1 − u_z, u_r) ⊥ (+z − u) through P0 = (a, g) + s0 u meets z = g at
    # r = a + s0 (u_r − u_z (1 − u_z)/u_r) = a + entry_wall.
    s0 = entry_wall / (ur0 - uz0 * (1.0 - uz0) / ur0)
    solution = solve_ivp(rhs, (g, z_lens_edge), [s0], method="DOP853", rtol=1e-11, atol=1e-13, dense_output=True)
    if not solution.success:
        raise RuntimeError(f"TIR surface integration failed: {solution.message}")
    s = solution.sol(z_samples)[0]
    ur, uz, _ = direction(z_samples)
    points = np.column_stack([a + s * ur, z_samples + s * uz])
    return points, np.column_stack([ur, uz])


def cone_wall(collimator: Collimator, n: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The prescribed TIR wall ``r(z) = a + w + tan β (z − g) + κ (z − g)²/2`` (mm) of
    ``collimator`` (``tir_cone_deg`` β, ``tir_cone_curvature_per_mm`` κ) from the entry plane
    up to ``tir_max_radius_mm`` or the flange's underside, with — for each point — the LED
    angle of the ray from the LED's centre that meets it after crossing the cavity wall (rad,
    clipped to the rays that cross it) and that ray's margin beyond the critical angle (degrees)."""
    a, g = collimator.cavity_radius_mm, collimator.led_gap_mm
    top = collimator.height_mm - collimator.flange_mm
    slope0, kappa = math.tan(math.radians(collimator.tir_cone_deg)), collimator.tir_cone_curvature_per_mm
    rise = np.linspace(0.0, top, 801)
    r = a + collimator.entry_wall_mm + slope0 * rise + 0.5 * kappa * rise**2
    slope = slope0 + kappa * rise
    r, z, slope = _truncated_wall(np.column_stack([r, g + rise, slope]), collimator.tir_max_radius_mm).T
    if np.any(slope <= 0.0):
        raise DesignError("collimator.tir_cone_curvature_per_mm", kappa, "the cone wall turns inwards before its end")
    # The ray crossing the cavity wall at z_w travels along u = (u_r, u_z), u_z = z_w / (n ρ):
    # it meets the radius r at z_w + (r − a) u_z / u_r, increasing with z_w.
    theta_max = math.atan2(a, g)
    z_w = g + (a / math.tan(math.radians(collimator.lens_half_angle_deg)) - g) * np.linspace(0.0, 1.0, 2001)
    uz = z_w / (n * np.hypot(a, z_w))
    ur = np.sqrt(1.0 - uz**2)
    reach = z_w[None, :] + (r[:, None] - a) * (uz / ur)[None, :]
    k = np.clip(np.argmax(reach >= z[:, None], axis=1), 0, len(z_w) - 1)
    k[reach[:, -1] < z] = len(z_w) - 1
    theta = np.minimum(np.arctan2(a, z_w[k]), theta_max)
    normal = np.column_stack([np.ones_like(slope), -slope]) / np.hypot(1.0, slope)[:, None]
    incidence = np.arccos(np.clip(np.abs(ur[k] * normal[:, 0] + uz[k] * normal[:, 1]), 0.0, 1.0))
    return r, z, theta, np.degrees(incidence - math.asin(1.0 / n))


def profile_from_parameters(collimator: Collimator, wavelength_nm: float, samples: int = 401) -> CollimatorProfile:
    """Compute the profile of ``collimator`` for light of ``wavelength_nm``.

    wavelength_nm: design wavelength, nm (sets the index of ``collimator.material``).
    samples: points on each freeform curve (lens and TIR surface).
    Raises :class:`DesignError` when the optics cannot be built in the given envelope.
    A collimator with output spreads (``not collimator.collimates``) is designed by
    :func:`cm2optics.optics.collimator_shaping.shaped_profile` instead.
    """
    if not collimator.collimates:
        # Imported here: the shaping module builds on this module's CollimatorProfile.
        from cm2optics.optics.collimator_shaping import shaped_profile

        return shaped_profile(collimator, wavelength_nm, samples)
    n = float(refractive_index(collimator.material, wavelength_nm))
    a, g = collimator.cavity_radius_mm, collimator.led_gap_mm
    theta_lens = math.radians(collimator.lens_half_angle_deg)
    asymptote = math.degrees(math.acos(1.0 / n))
    if theta_lens >= math.acos(1.0 / n):
        raise DesignError(
            "collimator.lens_half_angle_deg",
            collimator.lens_half_angle_deg,
            f"a lens refracting air → n = {n:.4f} into a parallel beam collimates at most "
            f"arccos(1/n) = {asymptote:.1f}°",
        )
    rho_edge = a / math.sin(theta_lens)
    vertex = rho_edge * (n * math.cos(theta_lens) - 1.0) / (n - 1.0)
    lens_edge = a / math.tan(theta_lens)
    if vertex <= g:
        raise DesignError(
            "collimator.lens_half_angle_deg",
            collimator.lens_half_angle_deg,
            f"the lens vertex (z = {vertex:.3f} mm) must lie above the entry plane (led_gap_mm = {g}): lower the angle "
            "or widen the cavity",
        )
    theta = np.linspace(0.0, theta_lens, samples)
    rho = vertex * (n - 1.0) / (n * np.cos(theta) - 1.0)
    lens_r, lens_z = rho * np.sin(theta), rho * np.cos(theta)
    lens_r[-1], lens_z[-1] = a, lens_edge  # exact closure on the cavity wall

    theta_max = math.atan2(a, g)
    if collimator.tir_cone_deg > 0.0:
        tir_r, tir_z, tir_theta, margin = cone_wall(collimator, n)
    else:
        tir_theta = np.linspace(theta_max, theta_lens, samples)
        wall_z = a / np.tan(tir_theta)
        wall_z[0], wall_z[-1] = g, lens_edge
        tir, u = _tir_surface(a, g, lens_edge, n, collimator.entry_wall_mm, wall_z)
        tir_r, tir_z = tir[:, 0], tir[:, 1]
        # Incidence on the TIR surface: half the deflection from u to +z is 90° − ψ/2.
        incidence = math.pi / 2 - np.arccos(u[:, 1]) / 2
        margin = np.degrees(incidence - math.asin(1.0 / n))

    return enclosed_profile(
        collimator, n, wavelength_nm, (lens_r, lens_z), (tir_r, tir_z), tir_theta, theta_max, margin
    )


def enclosed_profile(
    collimator: Collimator,
    n: float,
    wavelength_nm: float,
    lens: tuple[np.ndarray, np.ndarray],
    tir: tuple[np.ndarray, np.ndarray],
    tir_theta: np.ndarray,
    theta_max: float,
    margin_deg: np.ndarray,
) -> CollimatorProfile:
    """Close the two designed surfaces into the collimator's section, checking the envelope.

    n: index at ``wavelength_nm`` (nm). lens: (r, z) of the lens, vertex first, edge on the
    cavity wall (mm). tir: (r, z) of the TIR wall from the entry plane upwards (mm).
    tir_theta: LED angle of each TIR point (rad). theta_max: steepest ray entering the cavity
    (rad). margin_deg: each TIR point's incidence beyond the critical angle (deg).
    Raises :class:`DesignError` when the TIR wall runs into the flange, past the footprint, or
    bulges (a revolved part could not be printed).
    """
    a, g = collimator.cavity_radius_mm, collimator.led_gap_mm
    lens_r, lens_z = lens
    wall = np.column_stack([*tir, tir_theta, margin_deg])
    tir_r, tir_z, tir_theta, margin_deg = _truncated_wall(wall, collimator.tir_max_radius_mm).T
    vertex, lens_edge = float(lens_z[0]), float(lens_z[-1])
    exit_z = g + collimator.height_mm
    flange_bottom = exit_z - collimator.flange_mm
    r_end, z_end = float(tir_r[-1]), float(tir_z[-1])
    if z_end > flange_bottom + 1e-9:
        raise DesignError(
            "collimator.height_mm",
            collimator.height_mm,
            f"the TIR surface ends at z = {z_end:.3f} mm, above the flange's underside: needs ≥ {z_end + collimator.flange_mm - g:.3f} mm",
        )
    if np.max(tir_r) > r_end + 1e-9:
        raise DesignError(
            "collimator", "TIR wall", "the TIR wall bulges beyond its end radius (not printable as revolved)"
        )
    entry_radius = a + collimator.entry_wall_mm
    if not collimator.tir_is_freeform and np.max(tir_r) >= collimator.footprint_mm / 2:
        raise DesignError(
            "collimator.footprint_mm",
            collimator.footprint_mm,
            f"the TIR surface reaches r = {np.max(tir_r):.3f} mm: the footprint must exceed {2 * np.max(tir_r):.3f} mm",
        )
    if collimator.tir_is_freeform:
        reach = tir_wall_reach_mm(entry_radius, r_end, collimator.tir_cos2, collimator.tir_cos4)
        if reach >= collimator.footprint_mm / 2:
            raise DesignError(
                "collimator.tir_cos2",
                collimator.tir_cos2,
                f"with tir_cos4 = {collimator.tir_cos4} the TIR wall (revolved end r = {r_end:.3f} mm) reaches "
                f"{reach:.3f} mm towards the flange's sides: the footprint must exceed {2 * reach:.3f} mm",
            )
        if abs(tir_r[0] - entry_radius) > 1e-6 or abs(tir_z[0] - g) > 1e-6:
            raise DesignError(
                "collimator.tir_cos2",
                collimator.tir_cos2,
                "a non-revolved TIR wall needs the wall to start on the entry ring (led_gap_mm = 0 or a cone wall)",
            )
    return CollimatorProfile(
        refractive_index=n,
        wavelength_nm=float(wavelength_nm),
        entry_z_mm=g,
        exit_z_mm=exit_z,
        flange_bottom_z_mm=flange_bottom,
        footprint_mm=collimator.footprint_mm,
        cavity_radius_mm=a,
        lens_r_mm=lens_r,
        lens_z_mm=lens_z,
        cavity_r_mm=np.array([a, a]),
        cavity_z_mm=np.array([lens_edge, g]),
        tir_r_mm=tir_r,
        tir_z_mm=tir_z,
        tir_angle_deg=np.degrees(tir_theta),
        exit_r_mm=np.array([0.0, collimator.footprint_mm / 2]),
        lens_vertex_z_mm=vertex,
        lens_edge_z_mm=lens_edge,
        outer_radius_entry_mm=a + collimator.entry_wall_mm,
        outer_radius_exit_mm=r_end,
        lens_half_angle_deg=collimator.lens_half_angle_deg,
        max_angle_deg=math.degrees(theta_max),
        min_tir_margin_deg=float(margin_deg.min()),
        min_wall_mm=min(collimator.entry_wall_mm, exit_z - vertex, collimator.flange_mm),
    )


def _truncated_wall(wall: np.ndarray, max_radius_mm: float) -> np.ndarray:
    """The TIR wall's samples (rows of r, z in mm, then any per-sample quantities) up to where
    it reaches ``max_radius_mm``, its last row interpolated linearly onto that radius; the whole
    wall when ``max_radius_mm`` is 0 or not reached."""
    beyond = np.flatnonzero(wall[:, 0] >= max_radius_mm) if max_radius_mm > 0.0 else []
    if len(beyond) == 0 or beyond[0] == 0:
        return wall
    k = int(beyond[0])
    t = (max_radius_mm - wall[k - 1, 0]) / (wall[k, 0] - wall[k - 1, 0])
    return np.vstack([wall[:k], wall[k - 1] + t * (wall[k] - wall[k - 1])])


def collimator_profile(design: SystemDesign, samples: int = 401) -> CollimatorProfile:
    """Profile of ``design.collimator`` at the LED's peak wavelength, checked against the
    printer's thinnest wall (``design.mechanics.min_wall_mm``).

    samples: points on each freeform curve (lens and TIR surface).
    """
    if design.collimator is None:
        raise DesignError("collimator", None, "this design has no collimator")
    profile = profile_from_parameters(design.collimator, design.led.peak_nm, samples)
    if profile.min_wall_mm < design.mechanics.min_wall_mm - 1e-9:
        raise DesignError(
            "collimator",
            f"thinnest wall {profile.min_wall_mm:.3f} mm",
            f"entry_wall_mm, flange_mm and the lens centre (exit face − lens vertex) must be ≥ "
            f"mechanics.min_wall_mm = {design.mechanics.min_wall_mm}",
        )
    return profile


# ----------------------------------------------------------------------------- tracing


@dataclass(frozen=True, eq=False)
class MeridionalTrace:
    """Rays traced in the meridional (x, z) section; one entry per ray.

    exit_angle_rad: angle from +z of the ray leaving the exit face (positive towards +x),
        radians; NaN if the ray left the part elsewhere or never entered it.
    exit_x_mm: where the ray crossed the exit face, mm; NaN likewise.
    first_surface: :class:`Surface` through which the ray entered the material; −1 if never.
    tir_reflections: reflections on the TIR surface.
    tir_margin_rad: smallest (incidence − critical angle) on the TIR surface, radians; NaN if
        the ray never reached it from inside (negative: it leaked out there).
    """

    exit_angle_rad: np.ndarray
    exit_x_mm: np.ndarray
    first_surface: np.ndarray
    tir_reflections: np.ndarray
    tir_margin_rad: np.ndarray

    @property
    def exited(self) -> np.ndarray:
        """Rays that left through the exit face."""
        return np.isfinite(self.exit_angle_rad)


def _vertex_normals(points: np.ndarray) -> np.ndarray:
    """Outward unit normals of a smooth counter-clockwise curve at its samples, from the
    derivative of a cubic spline through them (chord-length parameter)."""
    t = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    tangent = CubicSpline(t, points, axis=0)(t, 1)
    normal = np.column_stack([tangent[:, 1], -tangent[:, 0]])
    return normal / np.linalg.norm(normal, axis=1, keepdims=True)


def _section_segments(profile: CollimatorProfile):
    """The full section (both halves) as segments: start, end (M, 2) in (x, z) mm, outward
    unit normals at both ends (M, 2) and the face of each segment (M,)."""
    right = profile.faces()
    # The left half, walked on from the exit face's centre back to the lens vertex.
    left = [(face, pts[::-1] * [-1.0, 1.0], smooth) for face, pts, smooth in reversed(right)]
    starts, ends, n_start, n_end, ids = [], [], [], [], []
    for face, pts, smooth in right + left:
        a, b = pts[:-1], pts[1:]
        if smooth:
            normals = _vertex_normals(pts)
            na, nb = normals[:-1], normals[1:]
        else:
            chord = b - a
            na = np.column_stack([chord[:, 1], -chord[:, 0]]) / np.linalg.norm(chord, axis=1, keepdims=True)
            nb = na
        starts.append(a)
        ends.append(b)
        n_start.append(na)
        n_end.append(nb)
        ids.append(np.full(len(a), int(face)))
    return np.vstack(starts), np.vstack(ends), np.vstack(n_start), np.vstack(n_end), np.concatenate(ids)


def trace_meridional(
    profile: CollimatorProfile,
    source_x_mm: np.ndarray | float,
    angle_rad: np.ndarray | float,
    source_z_mm: np.ndarray | float = 0.0,
    max_events: int = 12,
) -> MeridionalTrace:
    """Trace rays in the meridional section from points ``(source_x_mm, source_z_mm)`` leaving
    at ``angle_rad`` from +z (positive towards +x). Arguments broadcast against each other.

    source_x_mm: lateral position of each source point (the emitter spans ±emitter_mm/2), mm.
    angle_rad: direction of each ray from the +z axis, radians.
    source_z_mm: height of each source point, mm (0: the LED's emitting surface).
    max_events: refractions and reflections followed per ray.

    Each face refracts (Snell) or, past the critical angle, reflects totally; Fresnel partial
    reflections are not followed. The faces are the profile's straight segments; on the
    curved faces the normal is interpolated between spline-derived vertex normals.
    """
    x0, z0, angle = np.broadcast_arrays(
        np.asarray(source_x_mm, dtype=float), np.asarray(source_z_mm, dtype=float), np.asarray(angle_rad, dtype=float)
    )
    count = x0.size
    origin = np.column_stack([x0.ravel(), z0.ravel()])
    direction = np.column_stack([np.sin(angle.ravel()), np.cos(angle.ravel())])
    seg_a, seg_b, seg_na, seg_nb, seg_id = _section_segments(profile)
    edge = seg_b - seg_a
    n = profile.refractive_index
    critical = math.asin(1.0 / n)

    inside = np.zeros(count, dtype=bool)
    alive = np.ones(count, dtype=bool)
    exit_angle = np.full(count, np.nan)
    exit_x = np.full(count, np.nan)
    first = np.full(count, -1, dtype=int)
    reflections = np.zeros(count, dtype=int)
    margin = np.full(count, np.nan)
    for _ in range(max_events):
        idx = np.flatnonzero(alive)
        if idx.size == 0:
            break
        o, d = origin[idx], direction[idx]
        # Solve o + t d = a + s (b − a) for every ray × segment pair.
        rel = seg_a[None, :, :] - o[:, None, :]
        denom = d[:, None, 0] * edge[None, :, 1] - d[:, None, 1] * edge[None, :, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (rel[..., 0] * edge[None, :, 1] - rel[..., 1] * edge[None, :, 0]) / denom
            s = (rel[..., 0] * d[:, None, 1] - rel[..., 1] * d[:, None, 0]) / denom
        valid = (t > 1e-9) & (s >= 0.0) & (s <= 1.0) & np.isfinite(t)
        t = np.where(valid, t, np.inf)
        hit = np.argmin(t, axis=1)
        t_hit = t[np.arange(idx.size), hit]
        escaped = ~np.isfinite(t_hit)
        alive[idx[escaped]] = False
        idx, hit, t_hit, o, d = idx[~escaped], hit[~escaped], t_hit[~escaped], o[~escaped], d[~escaped]
        s_hit = s[~escaped][np.arange(idx.size), hit]
        point = o + t_hit[:, None] * d
        normal = (1.0 - s_hit)[:, None] * seg_na[hit] + s_hit[:, None] * seg_nb[hit]
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        face = seg_id[hit]
        was_inside = inside[idx]
        # Refraction with the normal facing the incoming ray.
        cos_out = np.einsum("ij,ij->i", d, normal)
        facing = np.where((cos_out > 0)[:, None], -normal, normal)
        cos_i = np.abs(cos_out)
        eta = np.where(was_inside, n, 1.0 / n)
        k = 1.0 - eta**2 * (1.0 - cos_i**2)
        total = k < 0.0
        refracted = eta[:, None] * d + (eta * cos_i - np.sqrt(np.clip(k, 0.0, None)))[:, None] * facing
        reflected = d + 2.0 * cos_i[:, None] * facing
        new_d = np.where(total[:, None], reflected, refracted)
        new_d /= np.linalg.norm(new_d, axis=1, keepdims=True)

        on_tir = was_inside & (face == Surface.TIR)
        incidence = np.arccos(np.clip(cos_i, 0.0, 1.0))
        margin[idx[on_tir]] = np.fmin(margin[idx[on_tir]], incidence[on_tir] - critical)
        reflections[idx[on_tir & total]] += 1
        entering = ~was_inside & ~total
        first[idx[entering & (first[idx] < 0)]] = face[entering & (first[idx] < 0)]
        leaving_exit = was_inside & ~total & (face == Surface.EXIT)
        exit_angle[idx[leaving_exit]] = np.arctan2(new_d[leaving_exit, 0], new_d[leaving_exit, 1])
        exit_x[idx[leaving_exit]] = point[leaving_exit, 0]
        alive[idx[leaving_exit]] = False

        inside[idx] = np.where(total, was_inside, ~was_inside)
        origin[idx] = point
        direction[idx] = new_d
    shape = x0.shape
    return MeridionalTrace(
        exit_angle_rad=exit_angle.reshape(shape),
        exit_x_mm=exit_x.reshape(shape),
        first_surface=first.reshape(shape),
        tir_reflections=reflections.reshape(shape),
        tir_margin_rad=margin.reshape(shape),
    )
