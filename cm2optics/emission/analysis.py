"""Measurements on simulated PSFs: the numbers a design is judged by.

* :func:`measured_magnification`: focus displacement per source displacement (central lenslet);
* :func:`measured_shear` and :func:`paraxial_shear`: lateral shift of a focus per mm of source
  depth (the axial shear of the light field), simulated and from first-order optics;
* :func:`on_axis_focus`: FWHM and Strehl ratio of the central lenslet's PSF against the same
  aperture without aberrations (the diffraction limit for its NA);
* :func:`best_focus_z_mm`: the source depth where the central lenslet's wavefront error is least
  (≈ 0: the design's focal plane is its plane of best focus);
* :func:`foci_on_sensor` and :func:`vignetting_radius_mm`: which foci reach the sensor, and how far
  off axis a source can go before side foci fall off the sensor or are vignetted (by the array's
  diced sides; the housing shades a few per cent at most);
* :func:`relative_energy`: energy of one focus relative to the on-axis source.

Lengths in mm unless named (``_um``); positions in object space (see :mod:`.psf`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

from cm2optics.design import paraxial
from cm2optics.design.materials import refractive_index
from cm2optics.emission.psf import EmissionModel, Focus
from cm2optics.optics import first_order

__all__ = [
    "FocusQuality",
    "best_focus_z_mm",
    "central_lenslet",
    "fwhm",
    "foci_on_sensor",
    "focus_position_mm",
    "measured_magnification",
    "measured_shear",
    "on_axis_focus",
    "paraxial_shear",
    "relative_energy",
    "vignetting_radius_mm",
]


def central_lenslet(model: EmissionModel) -> int:
    """Index of the lenslet whose vertex is nearest the optical axis."""
    cells = model.optics.lenslets
    return min(cells, key=lambda c: math.hypot(c.vertex_x_mm, c.vertex_y_mm)).index


def _focus(model: EmissionModel, position_mm, lenslet: int) -> Focus | None:
    for focus in model.foci(position_mm, lenslets=[lenslet]):
        if focus.lenslet == lenslet:
            return focus
    return None


def focus_position_mm(model: EmissionModel, position_mm, lenslet: int) -> np.ndarray:
    """Intensity centroid (x, y) of one lenslet's focus on the sensor plane, mm (NaN if none)."""
    focus = _focus(model, position_mm, lenslet)
    if focus is None:
        return np.array([np.nan, np.nan])
    row, col = focus.centroid_px()
    return np.array([float(model.grid.x_mm(col)), float(model.grid.y_mm(row))])


def measured_magnification(model: EmissionModel, step_mm: float = 0.1, z_mm: float = 0.0) -> float:
    """|m| from the central focus's shift when the source moves ±``step_mm`` along x at depth
    ``z_mm`` (the image is inverted: the focus moves −m·Δx)."""
    k = central_lenslet(model)
    a = focus_position_mm(model, (-step_mm, 0.0, z_mm), k)
    b = focus_position_mm(model, (step_mm, 0.0, z_mm), k)
    return float(-(b[0] - a[0]) / (2 * step_mm))


def measured_shear(model: EmissionModel, lenslet: int, z_mm: np.ndarray, source_xy_mm=(0.0, 0.0)) -> np.ndarray:
    """Slope (dx/dz, dy/dz) of the focus centroid of ``lenslet`` over source depths ``z_mm``
    (least squares; mm on the sensor per mm of depth)."""
    z = np.asarray(z_mm, dtype=float)
    centres = np.array([focus_position_mm(model, (source_xy_mm[0], source_xy_mm[1], zi), lenslet) for zi in z])
    return np.array([np.polyfit(z, centres[:, 0], 1)[0], np.polyfit(z, centres[:, 1], 1)[0]])


def paraxial_shear(
    model: EmissionModel, lenslet: int, source_xy_mm=(0.0, 0.0), wavelength_nm: float | None = None
) -> np.ndarray:
    """First-order (dx/dz, dy/dz) of the chief ray's landing point through ``lenslet``, per mm
    of source depth: the ray from the source through the lenslet's vertex (the stop's centre),
    traced with ray-transfer matrices through the filter plate, the lens and the film."""
    design = model.design
    lam = wavelength_nm or design.imaging.design_wavelength_nm
    n_f = refractive_index(design.emission_filter.material, lam)
    n_l = refractive_index(design.mla.material, lam)
    cell = model.optics.lenslets[lenslet]
    after = [
        paraxial.refract(design.mla.radius_mm, 1.0, n_l),
        paraxial.propagate(design.mla.thickness_mm, n_l),
        paraxial.refract(math.inf, n_l, 1.0),
    ]
    below = design.imaging.mla_to_sensor_mm
    if design.absorption_filter is not None:
        n_m = refractive_index(design.absorption_filter.material, lam)
        film_top = design.imaging.film_to_sensor_mm + design.absorption_filter.thickness_mm
        after += [
            paraxial.propagate(below - film_top, 1.0),
            paraxial.propagate(design.absorption_filter.thickness_mm, n_m),
        ]
        below = design.imaging.film_to_sensor_mm
    after.append(paraxial.propagate(below, 1.0))
    lens_to_sensor = paraxial.chain(*after)
    top = design.emission_filter_z_mm + design.emission_filter.thickness_mm

    def landing(z: float, height: float) -> float:
        before = paraxial.chain(
            paraxial.propagate(first_order.object_plane_z_mm(design) - z - top, 1.0),
            paraxial.propagate(design.emission_filter.thickness_mm, n_f),
            paraxial.propagate(design.emission_filter_z_mm - design.mla_vertex_z_mm, 1.0),
        )
        a, b = before[0]
        angle = -a * height / b  # the chief ray crosses the vertex
        return float((lens_to_sensor @ before @ np.array([height, angle]))[0])

    dz = 0.01
    out = []
    for axis, centre in ((0, cell.vertex_x_mm), (1, cell.vertex_y_mm)):
        h = source_xy_mm[axis] - centre
        out.append((landing(dz, h) - landing(-dz, h)) / (2 * dz))
    return np.array(out)


def fwhm(profile: np.ndarray, step: float) -> float:
    """Full width at half maximum of a 1-D peak sampled at ``step`` (linear interpolation)."""
    p = np.asarray(profile, dtype=float)
    p = p / p.max()
    i = int(np.argmax(p))
    r = i
    while r < len(p) - 1 and p[r] > 0.5:
        r += 1
    left = i
    while left > 0 and p[left] > 0.5:
        left -= 1
    if p[r] > 0.5 or p[left] > 0.5:
        return float("nan")
    xr = r - 1 + (p[r - 1] - 0.5) / (p[r - 1] - p[r])
    xl = left + (0.5 - p[left]) / (p[left + 1] - p[left])
    return float((xr - xl) * step)


@dataclass(frozen=True)
class FocusQuality:
    """The central lenslet's focus in one band against the same aperture without aberrations.

    fwhm_um, ideal_fwhm_um: FWHM along x through the peak, µm (sensor side).
    strehl: peak over the aberration-free peak. rms_waves: RMS wavefront error (piston, tilt out).
    na: image-side numerical aperture along x of the rays that pass (half the L span).
    wavelength_nm: the band's wavelength.
    """

    fwhm_um: float
    ideal_fwhm_um: float
    strehl: float
    rms_waves: float
    na: float
    wavelength_nm: float


def on_axis_focus(
    model: EmissionModel, z_mm: float = 0.0, band: int | None = None, step_um: float = 0.1
) -> FocusQuality:
    """Quality of the central lenslet's focus of an on-axis source at depth ``z_mm``, in ``band``
    (default: the band nearest the middle of the detected spectrum), sampled at ``step_um``."""
    k = central_lenslet(model)
    band = model._mid_band if band is None else band
    pupil = model.pupils((0.0, 0.0, z_mm), lenslets=[k], bands=[band])[0]
    h = step_um / 1000.0
    n = 241
    axis = (np.arange(n) - n // 2) * h
    image = pupil.intensity(pupil.x_ref_mm + axis, pupil.y_ref_mm + axis)
    ideal = pupil.intensity(pupil.x_ref_mm + axis, pupil.y_ref_mm + axis, aberration_free=True)
    row = int(np.unravel_index(np.argmax(image), image.shape)[0])
    lit = pupil.amplitude > 0
    l_grid = np.broadcast_to(pupil.l_axis[None, :], lit.shape)[lit]
    return FocusQuality(
        fwhm_um=fwhm(image[row], step_um),
        ideal_fwhm_um=fwhm(ideal[n // 2], step_um),
        strehl=float(image.max() / ideal.max()),
        rms_waves=pupil.rms_wavefront_waves(),
        na=float((l_grid.max() - l_grid.min() + pupil.spacing) / 2),
        wavelength_nm=pupil.wavelength_mm * 1e6,
    )


def best_focus_z_mm(
    model: EmissionModel, bounds_mm: tuple[float, float] = (-1.5, 1.5), band: int | None = None
) -> float:
    """Source depth (mm, object space) that minimises the RMS wavefront error of the central
    lenslet's on-axis focus (defocus included), in ``band`` (default: mid band)."""
    k = central_lenslet(model)
    band = model._mid_band if band is None else band

    def rms(z: float) -> float:
        return model.pupils((0.0, 0.0, z), lenslets=[k], bands=[band])[0].rms_wavefront_waves()

    result = minimize_scalar(rms, bounds=bounds_mm, method="bounded", options={"xatol": 0.01})
    return float(result.x)


def foci_on_sensor(
    model: EmissionModel, position_mm, fraction: float = 0.1, reference: dict[int, float] | None = None
) -> list[int]:
    """Lenslets whose focus of a source at ``position_mm`` reaches the sensor with at least
    ``fraction`` of the energy that the same lenslet collects from an on-axis source at the same
    depth (``reference``: those energies by lenslet, if already known)."""
    if reference is None:
        reference = {f.lenslet: f.energy for f in model.foci((0.0, 0.0, float(position_mm[2])))}
    return sorted(f.lenslet for f in model.foci(position_mm) if f.energy >= fraction * reference.get(f.lenslet, np.inf))


def vignetting_radius_mm(
    model: EmissionModel,
    direction_deg: float = 90.0,
    z_mm: float = 0.0,
    step_mm: float = 0.1,
    max_mm: float = 4.0,
    fraction: float = 0.1,
    start_mm: float = 0.0,
) -> float:
    """Largest off-axis distance (mm, along ``direction_deg`` from +x; searched from ``start_mm`` in
    ``step_mm`` steps up to ``max_mm``) up to which all visible lenslets still put a focus on the
    sensor (each with ≥ ``fraction`` of its on-axis energy): beyond it, side foci fall off the
    sensor or are vignetted (for cm2-v2 by the array's diced sides: rays of the outer lenslets that
    would leave through them are lost)."""
    full = len(model._visible)
    reference = {f.lenslet: f.energy for f in model.foci((0.0, 0.0, z_mm))}
    c, s = math.cos(math.radians(direction_deg)), math.sin(math.radians(direction_deg))
    last = float(start_mm)
    for r in np.arange(start_mm + step_mm, max_mm + 1e-9, step_mm):
        if len(foci_on_sensor(model, (r * c, r * s, z_mm), fraction, reference)) < full:
            return last
        last = float(r)
    return last


def relative_energy(model: EmissionModel, position_mm, lenslet: int | None = None) -> float:
    """Energy of ``lenslet``'s focus (default: central) relative to an on-axis source at the same depth."""
    k = central_lenslet(model) if lenslet is None else lenslet
    here = _focus(model, position_mm, k)
    ref = _focus(model, (0.0, 0.0, float(position_mm[2])), k)
    return 0.0 if here is None else here.energy / ref.energy
