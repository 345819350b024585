"""Angles of incidence at the emission filters, from the design's geometry.

Light reaches the emission path from the object plane (the nominal focal plane, where the
sample's surface is taken to lie) along three kinds of rays:

* fluorescence, isotropic, from points spread evenly over the imaged field (:func:`field_sources`);
* excitation light scattered back diffusely by the sample (Lambertian) wherever the LED beams
  land (:func:`excitation_footprint`): four tilted beams of finite width and étendue-limited
  spread reach beyond the imaged field, and glow far off-axis meets the filter obliquely;
* excitation light reflected specularly by the sample's flat surface (:func:`specular_rays`):
  the shallow edge of each tilted beam bounces back across the axis towards the mask.

Rays are traced (:func:`trace_rays`) through the emission filter (a parallel plate), the
aperture mask (both faces), one lenslet (exact refraction at its sphere and its flat face),
the absorption film's footprint (stopped by its seat outside it) and the film, to the sensor,
and kept if they land on the active area. Heights are those of the device frame (z = 0 on the
sensor, +z towards the sample); refractive indices at ``imaging.design_wavelength_nm``.

For point sources, directions are sampled on a square grid over the mask opening (plus a
margin), each standing for the solid angle dΩ = cos³θ dA / h² of its cell; an isotropic
source sends dΩ / 4π of its power along it, a Lambertian one cos θ dΩ / π.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from cm2optics.design import SystemDesign
from cm2optics.design.materials import refractive_index
from cm2optics.emission.optics import EmissionOptics, emission_optics
from cm2optics.emission.trace import RayBatch
from cm2optics.emission.trace import trace_rays as trace_emission_rays
from cm2optics.optics import first_order
from cm2optics.optics.layout import led_poses
from cm2optics.spectra.absorption import fresnel_transmittance
from cm2optics.spectra.chain import excitation_half_angle_rad

__all__ = [
    "EmissionRays",
    "Emitter",
    "Excitation",
    "Sources",
    "binned_sources",
    "excitation_beams",
    "excitation_footprint",
    "excitation_half_angle_rad",
    "field_sources",
    "glow_from_hits",
    "mirror_on_sample",
    "model_excitation",
    "specular_rays",
    "trace_from_sources",
    "trace_rays",
]


class Emitter(StrEnum):
    """Angular distribution of a source in the object plane."""

    ISOTROPIC = "isotropic"
    LAMBERTIAN = "lambertian"


@dataclass(frozen=True, eq=False)
class EmissionRays:
    """Rays that reach the sensor's active area.

    aoi_filter_rad: angle of incidence at the interference filter (in air), rad.
    aoi_film_rad: angle of incidence at the absorption film (in air), rad (0 with no film).
    power: fraction of the sources' total emitted (or incident) power each ray carries.
    """

    aoi_filter_rad: np.ndarray
    aoi_film_rad: np.ndarray
    power: np.ndarray

    @property
    def collection(self) -> float:
        """Fraction of the power that reaches the sensor (no filter losses)."""
        return float(self.power.sum())


@dataclass(frozen=True, eq=False)
class Sources:
    """Points of the object plane that emit, and the share of the power each emits.

    points_mm: (N, 2) lateral positions (x, y) in the device frame, mm.
    weights: (N,) shares of the emitted power, summing to 1.
    """

    points_mm: np.ndarray
    weights: np.ndarray

    def __post_init__(self) -> None:
        points = np.asarray(self.points_mm, dtype=float)
        weights = np.asarray(self.weights, dtype=float)
        if points.ndim != 2 or points.shape[1] != 2 or points.shape[0] == 0:
            raise ValueError(f"points_mm has shape {points.shape}: must be (N, 2) with N ≥ 1")
        if not np.all(np.isfinite(points)):
            raise ValueError("points_mm must be finite")
        if weights.shape != (points.shape[0],) or not np.all(np.isfinite(weights)) or np.any(weights < 0):
            raise ValueError("weights must be one finite value ≥ 0 per point")
        if not math.isclose(float(weights.sum()), 1.0, rel_tol=1e-9):
            raise ValueError(f"weights sum to {weights.sum():g}: must sum to 1")

    def radius_mm(self, fraction: float = 0.95) -> float:
        """Radius of the centred disc that holds ``fraction`` (0–1] of the power, mm."""
        r = np.hypot(self.points_mm[:, 0], self.points_mm[:, 1])
        order = np.argsort(r)
        cumulative = np.cumsum(self.weights[order])
        return float(r[order][min(int(np.searchsorted(cumulative, fraction - 1e-12)), r.size - 1)])


@dataclass(frozen=True, eq=False)
class Excitation:
    """Excitation light landing on the object plane, ray by ray.

    hits_mm: (N, 2) x, y where each ray lands (device frame), mm.
    directions: (N, 3) unit directions of travel, towards the sample (+z) where known (a traced ray
        that left its unit heading down and landed after a later bounce has z ≤ 0: such rays
        excite and glow but are not mirrored).
    power: (N,) each ray's share of the photons the LEDs emit; their sum is the share that lands
        (1 for the model beams, which lose nothing in the units; a trace's landed fraction).
    """

    hits_mm: np.ndarray
    directions: np.ndarray
    power: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.power)
        if self.hits_mm.shape != (n, 2) or self.directions.shape != (n, 3) or n == 0:
            raise ValueError("an excitation needs (N, 2) hits, (N, 3) directions and (N,) powers, N ≥ 1")
        finite = (
            np.isfinite(self.hits_mm).all() and np.isfinite(self.directions).all() and np.isfinite(self.power).all()
        )
        if not finite or np.any(self.power < 0):
            raise ValueError("excitation rays must be finite and carry power ≥ 0")


# ----------------------------------------------------------------------------- sources


def field_sources(design: SystemDesign, step_mm: float = 0.4) -> Sources:
    """Fluorescent points spread evenly over the imaged field (``volume.field_mm``): a square grid
    of spacing ``step_mm`` (mm, 0.01–2) inside the field's disc, equal shares."""
    if not (math.isfinite(step_mm) and 0.01 <= step_mm <= 2.0):
        raise ValueError(f"step_mm = {step_mm!r}: must lie within 0.01–2 mm")
    radius = design.volume.field_mm / 2
    n = int(math.ceil(radius / step_mm))
    axis = np.arange(-n, n + 1) * step_mm
    x, y = np.meshgrid(axis, axis)
    keep = x**2 + y**2 <= radius**2 + 1e-12
    points = np.column_stack([x[keep], y[keep]])
    return Sources(points, np.full(len(points), 1.0 / len(points)))


def excitation_beams(design: SystemDesign, samples: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays leaving the LED units and the power share of each: (origins_mm, directions, power).

    Each unit (at its :func:`cm2optics.optics.layout.led_poses` pose: ``offset_mm`` off the axis,
    tilted ``tilt_deg``, aimed at its aim point) emits from its exit face — the collimator's square exit
    (``collimator.footprint_mm``) or, bare, the excitation filter — into a cone of half-angle
    :func:`excitation_half_angle_rad` with uniform radiance: ``samples``² points on the face times
    ``samples`` × 2·``samples`` directions of equal projected solid angle. Origins are in the
    device frame, mm; only rays heading towards the sample (+z) are returned.
    """
    if not (isinstance(samples, int) and 2 <= samples <= 64):
        raise ValueError(f"samples = {samples!r}: must be an integer within 2–64")
    half_angle = excitation_half_angle_rad(design)
    width = design.collimator.footprint_mm if design.collimator is not None else design.excitation_filter.width_mm

    u = (np.arange(samples) + 0.5) / samples - 0.5
    face_a, face_b = (g.ravel() * width for g in np.meshgrid(u, u))
    ring = np.arcsin(np.sqrt((np.arange(samples) + 0.5) / samples) * math.sin(half_angle))
    spin = 2 * math.pi * (np.arange(2 * samples) + 0.5) / (2 * samples)
    polar, azimuth = (g.ravel() for g in np.meshgrid(ring, spin))

    origins, directions = [], []
    for pose in led_poses(design):
        axis, across, other = pose.matrix[:3, 2], pose.matrix[:3, 0], pose.matrix[:3, 1]
        aperture = pose.apply(np.array([0.0, 0.0, design.led_array.excitation_gap_mm]))
        start = aperture + face_a[:, None] * across + face_b[:, None] * other
        direction = (
            np.cos(polar)[:, None] * axis
            + (np.sin(polar) * np.cos(azimuth))[:, None] * across
            + (np.sin(polar) * np.sin(azimuth))[:, None] * other
        )
        origins.append(np.repeat(start, len(direction), axis=0))
        directions.append(np.tile(direction, (len(start), 1)))
    origins, directions = np.concatenate(origins), np.concatenate(directions)
    power = np.full(len(origins), 1.0 / len(origins))
    up = directions[:, 2] > 1e-6
    return origins[up], directions[up], power[up]


def model_excitation(design: SystemDesign, samples: int = 8) -> Excitation:
    """The model beams (:func:`excitation_beams`, ``samples``) where they land on the object plane;
    every photon leaving the units lands, so the powers sum to 1."""
    origins, directions, power = excitation_beams(design, samples)
    t = (first_order.object_plane_z_mm(design) - origins[:, 2]) / directions[:, 2]
    hits = origins + directions * t[:, None]
    return Excitation(hits[:, :2], directions, power / power.sum())


def binned_sources(points_mm: np.ndarray, power: np.ndarray, step_mm: float) -> Sources:
    """Points ((N, 2), mm) carrying ``power`` counted on a square grid of ``step_mm`` (mm): one
    source per occupied cell at its centre, with its share of the power."""
    if not (math.isfinite(step_mm) and 0.01 <= step_mm <= 5.0):
        raise ValueError(f"step_mm = {step_mm!r}: must lie within 0.01–5 mm")
    cells = np.rint(np.asarray(points_mm, dtype=float) / step_mm).astype(int)
    unique, inverse = np.unique(cells, axis=0, return_inverse=True)
    weights = np.bincount(inverse.ravel(), weights=power)
    return Sources(unique * step_mm, weights / weights.sum())


def excitation_footprint(design: SystemDesign, step_mm: float = 0.5, samples: int = 8) -> Sources:
    """Where the model beams (:func:`model_excitation`) land, counted on a grid of ``step_mm`` (mm):
    the glow of diffusely scattered excitation light (:func:`glow_from_hits`)."""
    excitation = model_excitation(design, samples)
    return glow_from_hits(design, excitation.hits_mm, excitation.power, step_mm)[0]


def glow_from_hits(
    design: SystemDesign, hits_mm: np.ndarray, power: np.ndarray, step_mm: float = 0.5
) -> tuple[Sources, float]:
    """The glow of excitation hits on the object plane ((N, 2) x, y, mm; powers): the hits within
    the sensor's reach (at most 75° off the axis, seen from the mask) counted on a grid of
    ``step_mm`` (mm), and the power they carry (what lands farther out can reach no pixel)."""
    if not (math.isfinite(step_mm) and 0.05 <= step_mm <= 5.0):
        raise ValueError(f"step_mm = {step_mm!r}: must lie within 0.05–5 mm")
    hits = np.asarray(hits_mm, dtype=float)
    reach = (first_order.object_plane_z_mm(design) - design.mask_z_mm) * math.tan(math.radians(75.0))
    keep = np.hypot(hits[:, 0], hits[:, 1]) <= reach + design.aperture_mask.opening_mm
    return binned_sources(hits[keep], power[keep], step_mm), float(power[keep].sum())


def specular_rays(design: SystemDesign, surface_index: float, samples: int = 24) -> tuple[np.ndarray, ...]:
    """The model beams (:func:`model_excitation`) mirrored by a flat sample surface of index
    ``surface_index`` (≥ 1) in the object plane: (origins_mm, directions, power), power = share of
    the beam × unpolarised Fresnel reflectance at the beam ray's angle. Trace them with
    :func:`trace_rays`."""
    excitation = model_excitation(design, samples)
    origins = np.column_stack(
        [excitation.hits_mm, np.full(len(excitation.power), first_order.object_plane_z_mm(design))]
    )
    return mirror_on_sample(origins, excitation.directions, excitation.power, surface_index)


def mirror_on_sample(
    hits_mm: np.ndarray, directions: np.ndarray, power: np.ndarray, surface_index: float
) -> tuple[np.ndarray, ...]:
    """Excitation rays (landing points on the object plane, mm; unit directions, +z; power shares)
    mirrored by a flat sample surface of index ``surface_index``: (origins_mm, directions,
    power × unpolarised Fresnel reflectance at each ray's angle)."""
    cos_i = directions[:, 2]
    reflectance = 1.0 - fresnel_transmittance(np.arccos(np.clip(cos_i, -1, 1)), surface_index)
    return hits_mm, directions * np.array([1.0, 1.0, -1.0]), power * reflectance


# ----------------------------------------------------------------------------- tracing


def _cells(optics: EmissionOptics, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Index of the lenslet (full or partial cell) whose clear aperture holds each (x, y), mm;
    the nearest vertex where none does."""
    cells = optics.lenslets
    index = np.argmin([(x - c.vertex_x_mm) ** 2 + (y - c.vertex_y_mm) ** 2 for c in cells], axis=0)
    for k, c in enumerate(cells):
        index[(x >= c.x0_mm) & (x <= c.x1_mm) & (y >= c.y0_mm) & (y <= c.y1_mm)] = k
    return index


def trace_rays(design: SystemDesign, origins_mm: np.ndarray, directions: np.ndarray, power: np.ndarray) -> EmissionRays:
    """Trace rays (device-frame origins, mm; unit directions; power shares) from above the emission
    filter to the sensor with the emission tracer (:func:`cm2optics.emission.trace.trace_rays`:
    filter, mask, housing bore and tabs, every lenslet cell of :func:`cm2optics.optics.lenslets.lens_cells`
    — partial cells included —, film); keep those that land on the active area.

    Each ray goes to the lenslet whose cell holds its crossing of the vertices' plane, or else of
    the lens surface's lowest plane (the sphere hit lies between the two)."""
    d = np.asarray(directions, dtype=float)
    p = np.asarray(origins_mm, dtype=float)
    power = np.asarray(power, dtype=float)
    down = d[:, 2] < -1e-9
    d, p, power = d[down], p[down], power[down]
    optics = emission_optics(design)
    lam = design.imaging.design_wavelength_nm
    n = len(d)
    indices = [
        np.full(n, refractive_index(part.material, lam) if part is not None else 1.0)
        for part in (design.emission_filter, design.mla, design.absorption_filter)
    ]
    u, v = d[:, 0] / -d[:, 2], d[:, 1] / -d[:, 2]
    # Filter plate: the ray leaves it parallel to itself, shifted by t·(1 − cos θ / (n cos θₜ)) tan θ.
    n_f = indices[0]
    tan2 = u * u + v * v
    shift = optics.filter.thickness_mm * (1.0 - 1.0 / np.sqrt(n_f * n_f * (1.0 + tan2) - tan2))
    passed = np.zeros(n, bool)
    result = None
    tried = np.full(n, -1)
    for z in (optics.vertex_z_mm, optics.land_z_mm):
        reach = p[:, 2] - z - shift
        lenslet = _cells(optics, p[:, 0] + u * reach, p[:, 1] + v * reach)
        todo = ~passed & (lenslet != tried)
        if not todo.any():
            continue
        batch = RayBatch(p[todo], u[todo], v[todo], lenslet[todo], *(a[todo] for a in indices))
        traced = trace_emission_rays(optics, batch)
        if result is None:
            result = (np.zeros(n), np.zeros(n))
        rows = np.flatnonzero(todo)[traced.passed]
        result[0][rows] = traced.aoi_filter_rad[traced.passed]
        result[1][rows] = traced.aoi_film_rad[traced.passed]
        passed[rows] = True
        tried = np.where(todo, lenslet, tried)
    aoi_filter, aoi_film = result if result is not None else (np.zeros(n), np.zeros(n))
    if design.absorption_filter is None:
        aoi_film = np.zeros(n)
    return EmissionRays(aoi_filter[passed], aoi_film[passed], power[passed])


def trace_from_sources(
    design: SystemDesign, sources: Sources, emitter: Emitter | str, pupil_samples: int = 24
) -> EmissionRays:
    """Trace ``sources`` in the object plane, each emitting as ``emitter``, to the sensor.

    pupil_samples: directions per source along each side of the mask opening (4–200).
    """
    emitter = Emitter(emitter)
    if not (isinstance(pupil_samples, int) and 4 <= pupil_samples <= 200):
        raise ValueError(f"pupil_samples = {pupil_samples!r}: must be an integer within 4–200")
    z_object = first_order.object_plane_z_mm(design)
    z_target = design.mask_z_mm + design.aperture_mask.thickness_mm
    half = design.aperture_mask.opening_mm / 2 + 0.3  # margin: the filter plate shifts rays sideways
    cell = 2 * half / pupil_samples
    axis = -half + cell * (np.arange(pupil_samples) + 0.5)
    tx, ty = (a.ravel() for a in np.meshgrid(axis, axis))
    points = sources.points_mm
    origins = np.repeat(np.column_stack([points, np.full(len(points), z_object)]), tx.size, axis=0)
    targets = np.column_stack([np.tile(tx, len(points)), np.tile(ty, len(points)), np.full(len(origins), z_target)])
    d = targets - origins
    d /= np.linalg.norm(d, axis=1)[:, None]
    cos_theta = -d[:, 2]
    solid_angle = cos_theta**3 * cell**2 / (z_object - z_target) ** 2
    intensity = 1 / (4 * math.pi) if emitter is Emitter.ISOTROPIC else cos_theta / math.pi
    power = np.repeat(sources.weights, tx.size) * intensity * solid_angle
    return trace_rays(design, origins, d, power)
