"""Upper bounds on what any collimator can deliver into the field circle of a design.

* :func:`etendue_bound` — étendue conservation: no passive optic puts more of a Lambertian
  emitter's power through a unit's clear aperture onto the circle than G_target / G_source
  allows; and the excitation filter passes at most its :func:`spectral_ceiling`
  (:func:`filter_throughput` at normal incidence; off it the filter's edges shift blue).
* :func:`uniform_beam_bound` — the uniformity constraint: the largest fraction of a unit's
  output that *any rotationally symmetric beam* (the class of every revolved collimator, the
  authors' part included) aimed along the unit's axis can put inside the circle while the
  array's irradiance there keeps a coefficient of variation ≤ ``max_cv``. The beam is
  written as a non-negative sum of thin rings of direction (radial intensity profile), each
  ring's irradiance footprint on the sample plane is computed for the four units, and the
  best profile is a linear programme (``scipy.optimize.linprog``). An ideal point-like beam is
  assumed (no source blur), so real collimators fall below it; with ``finite_source`` the beam
  leaves the whole clear aperture and every ring is blurred by the étendue-limited cone of the
  finite LED (:func:`etendue_blur_rad`: sin α = √(A_emitter / A_aperture), 17.1° for cm2-v2), an
  estimate of what a revolved collimator fed by the real 1 × 1-mm die can reach.
* :func:`free_aim_bound` — the same for re-aimed units: the best over a grid of placements
  (tilt, aim point on the focal plane, aperture offset) whose housings clear the imaging tower,
  point-like or finite source. With the finite source it is an estimate, not a strict bound:
  the blur is the étendue minimum spread evenly over the aperture, and a freeform optic may
  distribute it differently.
* with ``freeform`` both take a beam of any shape (cells of direction rather than rings): the
  bound of a freeform optic (of a post-filter spreader, for instance).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy.optimize import linprog

from cm2optics.design import SystemDesign
from cm2optics.optics import first_order

__all__ = [
    "THROUGHPUT_STEP_NM",
    "FREE_AIM_GRID",
    "blur_directions",
    "etendue_blur_rad",
    "etendue_bound",
    "filter_share_by_angle",
    "filter_throughput",
    "free_aim_bound",
    "spectral_ceiling",
    "uniform_beam_bound",
]


def _clear_aperture(design: SystemDesign) -> tuple[np.ndarray, tuple[float, float], float]:
    """(pose matrix of unit 0 (4×4), half-sides of its clear aperture (mm), the aperture's
    height above the LED in the unit's frame (mm)): the opening of the housing lip over the filter."""
    from cm2optics.optics.layout import led_poses

    pose = led_poses(design)[0].matrix
    f, c = design.excitation_filter, design.mechanics.clearance_mm
    half_sides = (f.width_mm / 2 - design.led_housing.lip_mm, f.length_mm / 2 - design.led_housing.lip_mm)
    aperture_z = design.led_array.excitation_gap_mm + f.thickness_mm + c + design.mechanics.min_wall_mm
    return pose, half_sides, aperture_z


#: Wavelength step of :func:`filter_throughput`'s integral, nm.
THROUGHPUT_STEP_NM = 0.02


def filter_throughput(design: SystemDesign, aoi_rad: Any, transmission: Any = None, spectrum: Any = None) -> np.ndarray:
    """∫ S(λ) T(λ, θ) dλ / ∫ S dλ at each angle of incidence θ (rad, in air; any shape): the share
    of the LED's power the excitation filter passes for a ray at θ. S is linear between its
    samples (as the tracer draws wavelengths from it) and the integral is taken on steps of
    :data:`THROUGHPUT_STEP_NM`, finer than a hard-coated filter's edge. transmission: T(λ nm, θ rad)
    (a coating table's fit), default the model of the design's filter; spectrum: the LED's
    :class:`~cm2optics.illumination.source.SourceSpectrum`, default the design's LED model."""
    from cm2optics.illumination.excitation import design_filter_transmission
    from cm2optics.illumination.source import led_source

    spectrum = spectrum if spectrum is not None else led_source(design).spectrum
    transmission = transmission or design_filter_transmission(design)
    aoi = np.asarray(aoi_rad, dtype=float)
    lo, hi = spectrum.wavelength_nm[0], spectrum.wavelength_nm[-1]
    grid = np.linspace(lo, hi, int(math.ceil((hi - lo) / THROUGHPUT_STEP_NM)) + 1)
    wl = np.union1d(spectrum.wavelength_nm, grid)
    power = np.interp(wl, spectrum.wavelength_nm, spectrum.relative_power)
    passed = np.broadcast_to(transmission(wl, aoi.reshape(-1, 1)), (aoi.size, wl.size))
    return (np.trapezoid(power * passed, wl, axis=-1) / np.trapezoid(power, wl)).reshape(aoi.shape)


def filter_share_by_angle(design: SystemDesign, transmission: Any = None, spectrum: Any = None) -> Any:
    """``share(angle_rad)``: :func:`filter_throughput` tabulated every 0.25° from 0 to 90° and
    interpolated linearly (angles beyond 90° pass nothing)."""
    grid = np.radians(np.arange(0.0, 90.001, 0.25))
    table = filter_throughput(design, grid, transmission, spectrum)
    return lambda angle_rad: np.interp(angle_rad, grid, table, right=0.0)


def spectral_ceiling(design: SystemDesign, transmission: Any = None, spectrum: Any = None) -> float:
    """:func:`filter_throughput` at normal incidence: the most of the LED's spectrum the
    excitation filter passes (every ray at normal incidence), from the run's inputs."""
    return float(filter_throughput(design, 0.0, transmission, spectrum))


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


def etendue_blur_rad(design: SystemDesign) -> float:
    """The smallest angular blur of a unit's beam, rad: the half-angle α of a cone of uniform
    radiance that carries the LED's étendue through the unit's clear aperture. A Lambertian
    emitter of area A_e has G = π A_e; a uniform cone of half-angle α over the aperture's area
    A_a has G = π A_a sin²α, so sin α = √(A_e / A_a) (in air)."""
    _, (ax, ay), _ = _clear_aperture(design)
    return math.asin(min(1.0, math.sqrt(design.led.emitter_mm**2 / (4 * ax * ay))))


def blur_directions(directions: np.ndarray, half_angle_rad: float, rng: np.random.Generator) -> np.ndarray:
    """Each unit vector of ``directions`` (…, 3) turned to a random direction within the cone of
    ``half_angle_rad`` (rad) around it, uniform in projected solid angle (uniform radiance)."""
    if half_angle_rad <= 0.0:
        return directions
    sin_t = math.sin(half_angle_rad) * np.sqrt(rng.random(directions.shape[:-1]))
    cos_t, psi = np.sqrt(1.0 - sin_t**2), rng.uniform(0.0, 2.0 * math.pi, directions.shape[:-1])
    helper = np.where(np.abs(directions[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    u = np.cross(directions, helper)
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    v = np.cross(directions, u)
    return cos_t[..., None] * directions + (sin_t * np.cos(psi))[..., None] * u + (sin_t * np.sin(psi))[..., None] * v


def _ring_directions(
    rings: int, max_angle_deg: float, rays: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """(directions (rings, rays, 3), not normalised, in a unit's frame; ring edges in tan(angle)):
    rays uniform in the tangent plane of directions within each ring of the radial profile."""
    tan_edges = np.linspace(0.0, math.tan(math.radians(max_angle_deg)), rings + 1)
    rho = np.sqrt(rng.uniform(tan_edges[:-1, None] ** 2, tan_edges[1:, None] ** 2, (rings, rays)))
    phi = rng.uniform(0.0, 2.0 * math.pi, (rings, rays))
    return np.stack([rho * np.cos(phi), rho * np.sin(phi), np.ones_like(rho)], axis=-1), tan_edges


def _cell_directions(
    cells: int, max_angle_deg: float, rays: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """(directions (n, rays, 3), not normalised, in a unit's frame; cell centres (n, 2) in the
    tangent plane): ``cells`` × ``cells`` square cells of the tangent plane of directions over
    ±tan(``max_angle_deg``), those whose centre lies within that angle, rays uniform in each —
    the pixels of a beam of any shape (a freeform optic's), not only of rings."""
    reach = math.tan(math.radians(max_angle_deg))
    side = 2 * reach / cells
    centres_1d = -reach + side * (np.arange(cells) + 0.5)
    tx, ty = np.meshgrid(centres_1d, centres_1d, indexing="ij")
    keep = tx**2 + ty**2 <= reach**2
    centres = np.column_stack([tx[keep], ty[keep]])
    jitter = rng.uniform(-side / 2, side / 2, (len(centres), rays, 2))
    plane = centres[:, None, :] + jitter
    return np.concatenate([plane, np.ones((len(centres), rays, 1))], axis=-1), centres


def _footprints(
    design: SystemDesign,
    local: np.ndarray,
    bin_mm: float,
    rng: np.random.Generator,
    finite_source: bool,
    filter_share: Any = None,
) -> np.ndarray:
    """Irradiance footprints of unit-power beam components, summed over the array's units.

    local: (components, rays, 3) directions in a unit's frame (a ring or a cell of directions).
    Returns fractions (bins inside the circle × components): the share of one unit's component
    power landing in each bin, averaged over the units. Rays leave the centre of each unit's
    clear aperture (an ideal point-like beam) or, with ``finite_source``, points spread
    uniformly over the aperture, each direction blurred by the étendue-limited cone of
    :func:`etendue_blur_rad` (the finite LED). filter_share: ``share(angle_rad)``, the part of
    a ray's power the excitation filter passes at its angle to the unit's axis (the beam shaped
    before the filter); None: every ray counts whole (the beam shaped after it).
    """
    from cm2optics.optics.layout import led_poses

    _, (ax, ay), aperture_z = _clear_aperture(design)
    radius = design.volume.field_mm / 2
    edges_xy = np.arange(-radius, radius + bin_mm / 2, bin_mm)
    centres = (edges_xy[:-1] + edges_xy[1:]) / 2
    cx, cy = np.meshgrid(centres, centres, indexing="ij")
    inside = cx**2 + cy**2 <= radius**2
    components, rays = local.shape[:2]
    local_start = np.zeros((components, rays, 3))
    local_start[..., 2] = aperture_z
    if finite_source:
        local = blur_directions(local / np.linalg.norm(local, axis=-1, keepdims=True), etendue_blur_rad(design), rng)
        local_start[..., 0] = rng.uniform(-ax, ax, (components, rays))
        local_start[..., 1] = rng.uniform(-ay, ay, (components, rays))
    power = np.ones((components, rays))
    if filter_share is not None:
        power = filter_share(np.arccos(np.clip(local[..., 2] / np.linalg.norm(local, axis=-1), -1.0, 1.0)))
    poses = led_poses(design)
    counts = np.zeros((components, inside.size))
    for pose in poses:  # a handful of units; the rays are vectorised
        matrix = pose.matrix
        start = local_start @ matrix[:3, :3].T + matrix[:3, 3]
        direction = local @ matrix[:3, :3].T
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (first_order.object_plane_z_mm(design) - start[..., 2]) / direction[..., 2]
        hit = start[..., :2] + s[..., None] * direction[..., :2]
        ix = np.floor((hit[..., 0] + radius) / bin_mm).astype(int)
        iy = np.floor((hit[..., 1] + radius) / bin_mm).astype(int)
        ok = (s > 0) & (ix >= 0) & (ix < centres.size) & (iy >= 0) & (iy < centres.size)
        flat = np.arange(components)[:, None] * inside.size + ix * centres.size + iy
        counts += np.bincount(flat[ok], power[ok], minlength=counts.size).reshape(counts.shape)
    fractions = counts / (len(poses) * rays)
    return fractions[:, inside.ravel()].T


def _ring_footprints(
    design: SystemDesign,
    rings: int,
    max_angle_deg: float,
    bin_mm: float,
    rays_per_ring: int,
    seed: int,
    finite_source: bool = False,
    filter_share: Any = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(:func:`_footprints` of the rings of a radial intensity profile, ring edges in tan(angle))."""
    rng = np.random.default_rng(seed)
    local, tan_edges = _ring_directions(rings, max_angle_deg, rays_per_ring, rng)
    return _footprints(design, local, bin_mm, rng, finite_source, filter_share), tan_edges


def _beam_footprints(
    design: SystemDesign,
    freeform: bool,
    components: int,
    max_angle_deg: float,
    bin_mm: float,
    rays: int,
    seed: int,
    finite_source: bool,
    filter_share: Any = None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Footprints of a beam's components — ``components`` rings of a rotationally symmetric
    beam, or with ``freeform`` a ``components`` × ``components`` grid of direction cells (a beam
    of any shape, the same for every unit) — and how to read the best weights: ring edges in
    degrees, or the cells' centres as (x, y) angles in degrees. filter_share: see :func:`_footprints`."""
    if not freeform:
        footprints, tan_edges = _ring_footprints(
            design, components, max_angle_deg, bin_mm, rays, seed, finite_source, filter_share
        )
        return footprints, {"ring_edges_deg": [round(math.degrees(math.atan(t)), 3) for t in tan_edges]}
    rng = np.random.default_rng(seed)
    local, centres = _cell_directions(components, max_angle_deg, rays, rng)
    cell_deg = np.degrees(np.arctan(centres)).round(3)
    return _footprints(design, local, bin_mm, rng, finite_source, filter_share), {"cell_centres_deg": cell_deg.tolist()}


def _best_profile(footprints: np.ndarray, max_cv: float) -> tuple[float, float, np.ndarray]:
    """(output delivered into the circle, its CV, ring powers) of the best radial profile: the
    linear programme over the ring powers x (sum 1) and the mean irradiance m with
    (1 − δ) m ≤ A x ≤ (1 + δ) m, δ bisected to the largest whose optimum keeps CV ≤ ``max_cv``."""
    delivered = footprints.sum(axis=0)
    bins, rings = footprints.shape

    def solve(band: float) -> tuple[float, float, np.ndarray]:
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
    return best


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
    finite_source: bool = False,
    freeform: bool = False,
    cells: int = 24,
    before_filter: bool = False,
) -> dict[str, Any]:
    """The most a rotationally symmetric beam can deliver uniformly (module docstring); with
    ``freeform`` the most a beam of any shape can (the same beam from every unit: for an array
    symmetric under its units' rotation the best beam can be taken symmetric, so no loss).

    max_cv: the array's coefficient of variation allowed inside the circle (0–1), over bins of
    ``bin_mm`` (mm) as in the figures of merit. rings: rings of the radial profile, equal steps
    in tan(angle) up to ``max_angle_deg`` (deg). rays_per_ring, seed: Monte Carlo footprints.
    finite_source: the beam leaves the whole clear aperture with the étendue-limited blur of
    the finite LED (:func:`etendue_blur_rad`) rather than as an ideal point-like beam.
    freeform, cells: the beam as ``cells`` × ``cells`` cells of direction (tangent plane within
    ``max_angle_deg``; ``rays_per_ring`` rays per cell) instead of rings.
    before_filter: the beam is shaped before the excitation filter, which passes each ray's
    :func:`filter_throughput` at its angle to the unit's axis (so a wide beam pays at the
    filter); ``output_bound`` is then the fraction of the light reaching the filter that lands,
    filtered, in the circle, and ``delivered_bound`` is it (the filter is counted). Default:
    shaped after the filter (a spreader beyond it), every ray passing the normal-incidence share.
    Returns ``output_bound`` (fraction of the light leaving a unit that lands in the circle),
    ``delivered_bound`` (× the filter's spectral ceiling: a fraction of the LED's power), the
    CV reached, and the best profile (relative power per ring, ring edges in degrees; or per
    cell, the cells' centres as x, y angles in degrees).
    The CV of the LP's optimum rises with the allowed band δ (irradiance within (1 ± δ) × mean);
    δ is bisected to the largest with CV ≤ ``max_cv``. transmission, spectrum: the run's filter
    and LED spectrum (:func:`spectral_ceiling`).
    """
    if not 0.0 < max_cv < 1.0:
        raise ValueError(f"max_cv must lie in (0, 1), got {max_cv}")
    share = filter_share_by_angle(design, transmission, spectrum) if before_filter else None
    footprints, layout = _beam_footprints(
        design, freeform, cells if freeform else rings, max_angle_deg, bin_mm, rays_per_ring, seed, finite_source, share
    )
    output, cv, profile = _best_profile(footprints, max_cv)
    ceiling = spectral_ceiling(design, transmission, spectrum)
    return {
        "max_cv": max_cv,
        "finite_source": finite_source,
        "freeform": freeform,
        "before_filter": before_filter,
        "output_bound": round(output, 4),
        "cv": round(cv, 4),
        "spectral_ceiling": round(ceiling, 4),
        "delivered_bound": round(output if before_filter else output * ceiling, 4),
        "profile": [round(float(v), 5) for v in profile],
        **layout,
    }


#: The placements :func:`free_aim_bound` tries by default: tilt (deg) × aim point (mm) × offset (mm).
FREE_AIM_GRID: dict[str, tuple[float, ...]] = {
    "led_array.tilt_deg": (40.0, 45.0, 50.0, 55.0),
    "led_array.aim_mm": (-2.0, -1.0, 0.0, 1.0, 2.0),
    "led_array.offset_mm": (6.7, 8.0),
}


def free_aim_bound(
    design: SystemDesign,
    max_cv: float = 0.10,
    transmission: Any = None,
    grid: dict[str, tuple[float, ...]] | None = None,
    finite_source: bool = True,
    rings: int = 40,
    max_angle_deg: float = 50.0,
    bin_mm: float = 0.5,
    rays_per_ring: int = 5_000,
    seed: int = 0,
    spectrum: Any = None,
    freeform: bool = False,
    cells: int = 24,
    before_filter: bool = False,
) -> dict[str, Any]:
    """The most a rotationally symmetric beam (with ``freeform``: a beam of any shape, as
    :func:`uniform_beam_bound`'s ``cells``; ``before_filter``: shaped before the filter, as
    there) can deliver uniformly when the units may be re-aimed: :func:`uniform_beam_bound`'s linear programme for every placement of the grid
    (dotted ``led_array`` fields → values, every combination; default :data:`FREE_AIM_GRID`)
    whose units clear the imaging tower and each other (:func:`cm2optics.optics.layout.unit_clashes`),
    and the best of them. finite_source: the étendue-limited beam of the finite LED (default)
    or an ideal point-like beam. Returns the best placement, its ``output_bound``,
    ``delivered_bound`` and CV, the spectral ceiling, and every placement tried (``placements``:
    the values, and the output bound or the reason it was skipped).
    """
    import itertools

    from cm2optics.design import DesignError
    from cm2optics.optics.layout import unit_clashes

    if not 0.0 < max_cv < 1.0:
        raise ValueError(f"max_cv must lie in (0, 1), got {max_cv}")
    grid = FREE_AIM_GRID if grid is None else grid
    share = filter_share_by_angle(design, transmission, spectrum) if before_filter else None
    names = list(grid)
    tried: list[dict[str, Any]] = []
    best: tuple[float, float, dict[str, float]] | None = None
    for values in itertools.product(*(grid[n] for n in names)):
        changes = dict(zip(names, values, strict=True))
        entry: dict[str, Any] = {"placement": changes}
        try:
            placed = design.with_changes(changes)
        except DesignError as error:
            tried.append({**entry, "skipped": str(error).splitlines()[0]})
            continue
        clashes = unit_clashes(placed)
        if clashes:
            tried.append({**entry, "skipped": clashes[0]})
            continue
        footprints, _ = _beam_footprints(
            placed,
            freeform,
            cells if freeform else rings,
            max_angle_deg,
            bin_mm,
            rays_per_ring,
            seed,
            finite_source,
            share,
        )
        output, cv, _ = _best_profile(footprints, max_cv)
        if not math.isfinite(cv):  # no profile of this placement lights the circle within max_cv
            tried.append({**entry, "skipped": f"no beam profile reaches CV ≤ {max_cv}"})
            continue
        tried.append({**entry, "output_bound": round(output, 4), "cv": round(cv, 4)})
        if best is None or output > best[0]:
            best = (output, cv, changes)
    if best is None:
        raise ValueError("free_aim_bound: no placement of the grid clears the imaging tower")
    ceiling = spectral_ceiling(design, transmission, spectrum)
    output, cv, placement = best
    return {
        "max_cv": max_cv,
        "finite_source": finite_source,
        "freeform": freeform,
        "before_filter": before_filter,
        "placement": placement,
        "output_bound": round(output, 4),
        "cv": round(cv, 4),
        "spectral_ceiling": round(ceiling, 4),
        "delivered_bound": round(output if before_filter else output * ceiling, 4),
        "placements": tried,
    }
