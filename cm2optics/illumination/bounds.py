"""Upper bounds on what any collimator can deliver into the field circle of a design.

* :func:`etendue_bound` — étendue conservation: no passive optic puts more of a Lambertian
  emitter's power through a unit's clear aperture onto the circle than G_target / G_source
  allows; and the excitation filter passes at most its :func:`spectral_ceiling`.
* :func:`uniform_beam_bound` — the uniformity constraint: the largest fraction of a unit's
  output that *any rotationally symmetric beam* (the class of every revolved collimator, the
  authors' part included) aimed along the unit's axis can put inside the circle while the
  array's irradiance there keeps a coefficient of variation ≤ ``max_cv``. The beam is
  written as a non-negative sum of thin rings of direction (radial intensity profile), each
  ring's irradiance footprint on the sample plane is computed for the four units, and the
  best profile is a linear programme (``scipy.optimize.linprog``). An ideal point-like beam is
  assumed (no source blur), so real collimators fall below it.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy.optimize import linprog

from cm2optics.design import SystemDesign
from cm2optics.optics import first_order

__all__ = ["etendue_bound", "spectral_ceiling", "uniform_beam_bound"]


def _clear_aperture(design: SystemDesign) -> tuple[np.ndarray, tuple[float, float], float]:
    """(pose matrix of unit 0 (4×4), half-sides of its clear aperture (mm), the aperture's
    height above the LED in the unit's frame (mm)): the opening of the housing lip over the filter."""
    from cm2optics.optics.layout import led_poses

    pose = led_poses(design)[0].matrix
    f, c = design.excitation_filter, design.mechanics.clearance_mm
    half_sides = (f.width_mm / 2 - design.led_housing.lip_mm, f.length_mm / 2 - design.led_housing.lip_mm)
    aperture_z = design.led_array.excitation_gap_mm + f.thickness_mm + c + design.mechanics.min_wall_mm
    return pose, half_sides, aperture_z


def spectral_ceiling(design: SystemDesign, transmission: Any = None, spectrum: Any = None) -> float:
    """∫ S(λ) T(λ, 0) dλ / ∫ S dλ: the most of the LED's spectrum S the excitation filter passes
    (every ray at normal incidence), from the run's inputs. transmission: T(λ nm, θ rad) (a
    coating table's fit), default the model of the design's filter; spectrum: the LED's
    :class:`~cm2optics.illumination.source.SourceSpectrum`, default the design's LED model."""
    from cm2optics.illumination.excitation import design_filter_transmission
    from cm2optics.illumination.source import led_source

    spectrum = spectrum if spectrum is not None else led_source(design).spectrum
    transmission = transmission or design_filter_transmission(design)
    wl = spectrum.wavelength_nm
    power = spectrum.relative_power
    return float(np.trapezoid(power * transmission(wl, np.zeros_like(wl)), wl) / np.trapezoid(power, wl))


def etendue_bound(
    design: SystemDesign, transmission: Any = None, samples: int = 400_000, seed: int = 0, spectrum: Any = None
) -> dict[str, float]:
    """Upper bounds on the delivered fraction set by étendue and by the filter.

    G_source = π A_emitter (a Lambertian emitter into air, mm² sr). G_target = ∬ cosθ₁ cosθ₂ /
    r² dA₁ dA₂ between one unit's clear aperture (the housing lip's opening) and the field
    circle on the sample plane (Monte Carlo, ``samples`` pairs), mm² sr. No passive optic
    puts more than G_target / G_source of a Lambertian emitter's power through the aperture
    onto the circle. The filter passes at most ``spectral_ceiling`` = ∫ S(λ) T(λ, 0) dλ / ∫ S
    of the LED's spectrum (every ray at normal incidence, S the LED spectrum), so
    ``delivered_bound`` = min(1, G_target / G_source) × spectral_ceiling. transmission, spectrum:
    the run's filter and LED spectrum (:func:`spectral_ceiling`).
    """
    rng = np.random.default_rng(seed)
    pose, (ax, ay), aperture_z = _clear_aperture(design)
    local = np.column_stack(
        [rng.uniform(-ax, ax, samples), rng.uniform(-ay, ay, samples), np.full(samples, aperture_z)]
    )
    p1 = local @ pose[:3, :3].T + pose[:3, 3]
    n1 = pose[:3, 2]
    radius = design.volume.field_mm / 2
    rho, phi = radius * np.sqrt(rng.random(samples)), 2 * np.pi * rng.random(samples)
    p2 = np.column_stack(
        [rho * np.cos(phi), rho * np.sin(phi), np.full(samples, first_order.object_plane_z_mm(design))]
    )
    n2 = np.array([0.0, 0.0, -1.0])
    v = p2 - p1
    r2 = np.einsum("ij,ij->i", v, v)
    cos1 = np.clip(v @ n1, 0, None) / np.sqrt(r2)
    cos2 = np.clip(-(v @ n2), 0, None) / np.sqrt(r2)
    area1, area2 = 4 * ax * ay, math.pi * radius**2
    kernel = cos1 * cos2 / r2
    g_target = float(area1 * area2 * kernel.mean())
    g_target_se = float(area1 * area2 * kernel.std() / math.sqrt(samples))
    g_source = math.pi * design.led.emitter_mm**2
    spectral = spectral_ceiling(design, transmission, spectrum)
    geometric = min(1.0, g_target / g_source)
    return {
        "g_source_mm2sr": round(g_source, 4),
        "g_target_mm2sr": round(g_target, 4),
        "g_target_stderr_mm2sr": round(g_target_se, 4),
        "geometric_bound": round(geometric, 4),
        "spectral_ceiling": round(spectral, 4),
        "delivered_bound": round(geometric * spectral, 4),
    }


def _ring_footprints(
    design: SystemDesign, rings: int, max_angle_deg: float, bin_mm: float, rays_per_ring: int, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """Irradiance footprints of unit-power direction rings, summed over the array's units.

    Returns (fractions (bins inside the circle × rings): the share of one unit's ring power
    landing in each bin, averaged over the units; ring edges in tan(angle) from the axis).
    Rays leave the centre of each unit's clear aperture, uniform in the tangent plane of
    directions within each ring (a ring of the radial intensity profile).
    """
    from cm2optics.optics.layout import led_poses

    rng = np.random.default_rng(seed)
    _, _, aperture_z = _clear_aperture(design)
    radius = design.volume.field_mm / 2
    edges_xy = np.arange(-radius, radius + bin_mm / 2, bin_mm)
    centres = (edges_xy[:-1] + edges_xy[1:]) / 2
    cx, cy = np.meshgrid(centres, centres, indexing="ij")
    inside = cx**2 + cy**2 <= radius**2
    tan_edges = np.linspace(0.0, math.tan(math.radians(max_angle_deg)), rings + 1)
    rho = np.sqrt(rng.uniform(tan_edges[:-1, None] ** 2, tan_edges[1:, None] ** 2, (rings, rays_per_ring)))
    phi = rng.uniform(0.0, 2.0 * math.pi, (rings, rays_per_ring))
    local = np.stack([rho * np.cos(phi), rho * np.sin(phi), np.ones_like(rho)], axis=-1)
    poses = led_poses(design)
    counts = np.zeros((rings, inside.size))
    for pose in poses:  # a handful of units; the rays are vectorised
        matrix = pose.matrix
        start = matrix[:3, :3] @ np.array([0.0, 0.0, aperture_z]) + matrix[:3, 3]
        direction = local @ matrix[:3, :3].T
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (first_order.object_plane_z_mm(design) - start[2]) / direction[..., 2]
        hit = start[:2] + s[..., None] * direction[..., :2]
        ix = np.floor((hit[..., 0] + radius) / bin_mm).astype(int)
        iy = np.floor((hit[..., 1] + radius) / bin_mm).astype(int)
        ok = (s > 0) & (ix >= 0) & (ix < centres.size) & (iy >= 0) & (iy < centres.size)
        flat = np.arange(rings)[:, None] * inside.size + ix * centres.size + iy
        counts += np.bincount(flat[ok], minlength=counts.size).reshape(counts.shape)
    fractions = counts / (len(poses) * rays_per_ring)
    return fractions[:, inside.ravel()].T, tan_edges


def uniform_beam_bound(
    design: SystemDesign,
    max_cv: float = 0.10,
    transmission: Any = None,
    rings: int = 60,
    max_angle_deg: float = 50.0,
    bin_mm: float = 0.5,
    rays_per_ring: int = 20_000,
    seed: int = 0,
    spectrum: Any = None,
) -> dict[str, Any]:
    """The most a rotationally symmetric beam can deliver uniformly (module docstring).

    max_cv: the array's coefficient of variation allowed inside the circle (0–1), over bins of
    ``bin_mm`` (mm) as in the figures of merit. rings: rings of the radial profile, equal steps
    in tan(angle) up to ``max_angle_deg`` (deg). rays_per_ring, seed: Monte Carlo footprints.
    Returns ``output_bound`` (fraction of the light leaving a unit that lands in the circle),
    ``delivered_bound`` (× the filter's spectral ceiling: a fraction of the LED's power), the
    CV reached, and the best profile (relative power per ring, ring edges in degrees).
    The CV of the LP's optimum rises with the allowed band δ (irradiance within (1 ± δ) × mean);
    δ is bisected to the largest with CV ≤ ``max_cv``.
    """
    if not 0.0 < max_cv < 1.0:
        raise ValueError(f"max_cv must lie in (0, 1), got {max_cv}")
    footprints, tan_edges = _ring_footprints(design, rings, max_angle_deg, bin_mm, rays_per_ring, seed)
    delivered = footprints.sum(axis=0)
    bins = footprints.shape[0]

    def solve(band: float) -> tuple[float, float, np.ndarray]:
        # variables: ring powers x (sum 1) and the mean irradiance m; (1 − δ) m ≤ A x ≤ (1 + δ) m.
        upper = np.hstack([footprints, -(1 + band) * np.ones((bins, 1))])
        lower = np.hstack([-footprints, (1 - band) * np.ones((bins, 1))])
        result = linprog(
            np.append(-delivered, 0.0),
            A_ub=np.vstack([upper, lower]),
            b_ub=np.zeros(2 * bins),
            A_eq=np.append(np.ones(rings), 0.0)[None],
            b_eq=[1.0],
            bounds=[(0, None)] * (rings + 1),
            method="highs",
        )
        if not result.success:
            return 0.0, math.inf, np.zeros(rings)
        x = result.x[:rings]
        irradiance = footprints @ x
        if irradiance.mean() <= 0:  # every ring aimed off the circle: uniformly dark
            return 0.0, 0.0, x
        return float(delivered @ x), float(irradiance.std() / irradiance.mean()), x

    low, high = 0.0, 1.0
    best = solve(low)
    for _ in range(12):
        mid = (low + high) / 2
        trial = solve(mid)
        if trial[1] <= max_cv:
            low, best = mid, trial
        else:
            high = mid
    output, cv, profile = best
    ceiling = spectral_ceiling(design, transmission, spectrum)
    return {
        "max_cv": max_cv,
        "output_bound": round(output, 4),
        "cv": round(cv, 4),
        "spectral_ceiling": round(ceiling, 4),
        "delivered_bound": round(output * ceiling, 4),
        "profile": [round(float(v), 5) for v in profile],
        "ring_edges_deg": [round(math.degrees(math.atan(t)), 3) for t in tan_edges],
    }
