"""Cross-check against an independent code: one lenslet in Optiland (open-source optical design).

:func:`optiland_lenslet` builds the central lenslet's prescription in Optiland from the same
design — source plane, emission-filter plate, air gap, spherical lenslet (the stop, with the
lenslet's square aperture as a rectangular physical aperture), PMMA substrate, air, film, air,
sensor — with constant refractive indices at one wavelength. :func:`compare_with_optiland`
computes Optiland's FFT PSF and ours for the same field and wavelength, on Optiland's grid, and
returns their Strehl ratios and normalised cross-correlation (centroids aligned). Ours is either

* ``"debye"``: the production model (:mod:`.wavefront`): pupil uniform in direction cosines,
  amplitude from the ray density there (energy-conserving), exact direction of every sample; or
* ``"classical"``: the FFT-PSF model that Optiland (and Zemax) use, on our ray trace: a uniform
  grid over the entrance pupil (the circle around the lenslet, clipped by its square), uniform
  amplitude, and directions taken as an affine function of the pupil coordinates.

The two differ by the pupil aberration: this lenslet has ≈ 5 waves of spherical aberration at
its corners, so its rays' directions are not a linear function of where they cross the lens and
the energy per solid angle is not uniform. ``"classical"`` reproduces Optiland's Strehl ratio to
≈ 0.1 %, which checks the trace and the wavefront themselves against the independent code.

The scale of Optiland's image grid: its FFT maps the pupil linearly onto directions, so its
samples are λ / (grid · ΔL) apart with ΔL the direction step between pupil samples of that linear
map. Optiland *reports* the pitch from a working F-number of four marginal rays at the edge of
the circumscribed entrance pupil (outside the square lenslet), whose spherical aberration bends
them ≈ 10 % more than the linear map does; at the broad paraxial focus that hardly shows, at the
compact best focus it costs ≈ 0.1 in cross-correlation. The comparison therefore puts Optiland's
image on the pitch of the linear map (the affine fit of the rays' directions over the pupil that
``"classical"`` also uses), per axis; :attr:`Comparison.pitch_um` is that pitch and
:attr:`Comparison.optiland_pitch_um` Optiland's own figure.

Optiland is a test dependency (``pip install optiland``): it is imported only when these
functions run. Our side uses an isotropic source and no filters, as the Optiland model has
none; everything else (Fresnel losses, the direction-space Jacobian) stays on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from cm2optics.design import SystemDesign
from cm2optics.design.materials import refractive_index
from cm2optics.emission.analysis import central_lenslet
from cm2optics.emission.psf import EmissionModel, PSFSettings, Pupil
from cm2optics.emission.source import PointSource
from cm2optics.emission.trace import paraxial_reach_mm, trace_rays
from cm2optics.emission.wavefront import solve_least_squares
from cm2optics.optics import first_order

__all__ = ["METHODS", "Comparison", "classical_pupil", "compare_with_optiland", "optiland_lenslet", "optiland_psf"]

METHODS = ("debye", "classical")


def optiland_lenslet(design: SystemDesign, wavelength_nm: float, field_mm: float, z_mm: float = 0.0) -> Any:
    """The central lenslet of ``design`` as an ``optiland.optic.Optic``: object height ``field_mm``
    (mm, along y) at depth ``z_mm`` (mm from the nominal focal plane, +z towards the device), one
    wavelength (nm)."""
    from optiland.materials import IdealMaterial
    from optiland.optic import Optic
    from optiland.physical_apertures import RectangularAperture

    lam = wavelength_nm
    n_f = float(refractive_index(design.emission_filter.material, lam))
    n_l = float(refractive_index(design.mla.material, lam))
    top = design.emission_filter_z_mm + design.emission_filter.thickness_mm
    half = design.mla.aperture_mm / 2
    optic = Optic()
    s = optic.surfaces
    s.add(index=0, radius=math.inf, thickness=first_order.object_plane_z_mm(design) - z_mm - top)
    s.add(index=1, radius=math.inf, thickness=design.emission_filter.thickness_mm, material=IdealMaterial(n=n_f))
    s.add(index=2, radius=math.inf, thickness=design.emission_filter_z_mm - design.mla_vertex_z_mm)
    s.add(
        index=3,
        radius=design.mla.radius_mm,
        thickness=design.mla.thickness_mm,
        material=IdealMaterial(n=n_l),
        is_stop=True,
        aperture=RectangularAperture(-half, half, -half, half),
    )
    if design.absorption_filter is not None:
        n_m = float(refractive_index(design.absorption_filter.material, lam))
        film_top = design.imaging.film_to_sensor_mm + design.absorption_filter.thickness_mm
        s.add(index=4, radius=math.inf, thickness=design.imaging.mla_to_sensor_mm - film_top)
        s.add(index=5, radius=math.inf, thickness=design.absorption_filter.thickness_mm, material=IdealMaterial(n=n_m))
        s.add(index=6, radius=math.inf, thickness=design.imaging.film_to_sensor_mm)
        s.add(index=7)
    else:
        s.add(index=4, radius=math.inf, thickness=design.imaging.mla_to_sensor_mm)
        s.add(index=5)
    # The entrance pupil circumscribes the square lenslet; the rectangular aperture clips it.
    optic.set_aperture(aperture_type="EPD", value=design.mla.aperture_mm * math.sqrt(2.0))
    optic.fields.set_type("object_height")
    optic.fields.add(y=0.0)
    if field_mm > 0:
        optic.fields.add(y=field_mm)
    optic.wavelengths.add(value=lam / 1000.0, is_primary=True)
    return optic


def optiland_psf(
    optic: Any, field_mm: float, wavelength_nm: float, num_rays: int = 128, grid_size: int = 256
) -> tuple[np.ndarray, float]:
    """Optiland's FFT PSF (peak 100 × Strehl) and its sample pitch on the sensor, mm."""
    from optiland.psf import FFTPSF

    psf = FFTPSF(
        optic, (0.0, 1.0 if field_mm > 0 else 0.0), wavelength_nm / 1000.0, num_rays=num_rays, grid_size=grid_size
    )
    image = np.asarray(psf.psf, dtype=float)
    width_um, _ = psf._get_psf_units(image)
    return image, float(width_um) / image.shape[1] / 1000.0


@dataclass(frozen=True)
class Comparison:
    """Ours against Optiland for one lenslet, field and wavelength.

    strehl_ours, strehl_optiland: peak over the aberration-free peak (same aperture).
    ncc: normalised cross-correlation of the two PSFs on Optiland's grid (centroids aligned).
    pitch_um: the grid's pitch on the sensor along x, µm (the linear pupil map's; see the module
    docstring). field_mm, wavelength_nm: the case. optiland_pitch_um: the pitch Optiland reports, µm.
    """

    strehl_ours: float
    strehl_optiland: float
    ncc: float
    pitch_um: float
    field_mm: float
    wavelength_nm: float
    optiland_pitch_um: float = float("nan")

    @property
    def strehl_ratio(self) -> float:
        return self.strehl_ours / self.strehl_optiland


def _centroid(image: np.ndarray) -> tuple[float, float]:
    total = image.sum()
    rows, cols = np.indices(image.shape)
    return float((rows * image).sum() / total), float((cols * image).sum() / total)


def compare_with_optiland(
    design: SystemDesign,
    field_mm: float = 0.0,
    z_mm: float = 0.0,
    band: int | None = None,
    num_rays: int = 128,
    grid_size: int = 512,
    method: str = "debye",
) -> Comparison:
    """Compare the central lenslet's PSF of a source ``field_mm`` (mm) off axis along y at depth
    ``z_mm`` (mm from the nominal focal plane), at the wavelength of ``band`` (default: mid band),
    computed by ``method`` (see the module docstring)."""
    if method not in METHODS:
        raise ValueError(f"method = {method!r}: must be one of {', '.join(METHODS)}")
    model = EmissionModel(design, PointSource(0.0), settings=PSFSettings(binning=1), filtered=False)
    band = model._mid_band if band is None else band
    k = central_lenslet(model)
    if method == "debye":
        pupil = model.pupils((0.0, field_mm, z_mm), lenslets=[k], bands=[band])[0]
    else:
        pupil = classical_pupil(model, (0.0, field_mm, z_mm), k, band)
    lam = pupil.wavelength_mm * 1e6
    reference, reported = optiland_psf(
        optiland_lenslet(design, lam, field_mm, z_mm), field_mm, lam, num_rays, grid_size
    )
    # Optiland's grid on the scale of its linear pupil map: the direction step between its
    # num_rays samples across the circumscribed pupil, from the affine fit over our rays.
    linear = pupil if method == "classical" else classical_pupil(model, (0.0, field_mm, z_mm), k, band)
    step_l = abs(linear.l_axis[-1] - linear.l_axis[0]) / (num_rays - 1)  # the lenslet inverts: L falls along x
    step_m = abs(linear.m_axis[-1] - linear.m_axis[0]) / (num_rays - 1)
    pitch_x, pitch_y = linear.wavelength_mm / (grid_size * step_l), linear.wavelength_mm / (grid_size * step_m)
    # Our PSF on Optiland's grid, its origin moved until the intensity centroids coincide.
    n = reference.shape[0]
    index = np.arange(n) - n // 2
    ox, oy = pupil.x_ref_mm, pupil.y_ref_mm
    target = _centroid(reference)
    for _ in range(3):
        ours = pupil.intensity(ox + index * pitch_x, oy + index * pitch_y)
        here = _centroid(ours)
        ox += (here[1] - target[1]) * pitch_x
        oy += (here[0] - target[0]) * pitch_y
    ours = pupil.intensity(ox + index * pitch_x, oy + index * pitch_y)
    a = ours - ours.mean()
    b = reference - reference.mean()
    ncc = float((a * b).sum() / math.sqrt((a * a).sum() * (b * b).sum()))
    peak_r, peak_c = np.unravel_index(np.argmax(ours), ours.shape)
    fine = (np.arange(81) - 40) * (min(pitch_x, pitch_y) / 8)
    px, py = ox + index[peak_c] * pitch_x, oy + index[peak_r] * pitch_y
    peak = pupil.intensity(px + fine, py + fine).max()
    ideal = pupil.intensity(pupil.x_ref_mm + fine, pupil.y_ref_mm + fine, aberration_free=True).max()
    return Comparison(
        float(peak / ideal), float(reference.max() / 100.0), ncc, pitch_x * 1000.0, field_mm, lam, reported * 1000.0
    )


def classical_pupil(
    model: EmissionModel, position_mm: tuple[float, float, float], lenslet: int, band: int, samples: int = 128
) -> Pupil:
    """The classical FFT-PSF pupil of one lenslet on our trace (see the module docstring):
    ``samples``² rays aimed (paraxially through the filter plate) at a uniform grid over the circle
    around the lenslet's aperture on its vertex plane; amplitude 1 where a ray passes; W the
    wavefront of each ray (piston removed); directions an affine fit of the grid coordinates."""
    optics = model.optics
    source = model.device_point_mm(position_mm)
    cell = optics.lenslets[lenslet]
    reach = paraxial_reach_mm(optics, source[2], model._indices[band, 0], optics.vertex_z_mm)
    half = math.hypot(cell.x1_mm - cell.x0_mm, cell.y1_mm - cell.y0_mm) / 2
    g = np.linspace(-half, half, samples)
    gx, gy = np.meshgrid(cell.vertex_x_mm + g, cell.vertex_y_mm + g)
    u, v = ((gx - source[0]) / reach).ravel(), ((gy - source[1]) / reach).ravel()
    traced = trace_rays(
        optics, model._batch(source, u, v, np.full(u.size, lenslet), np.full(u.size, band)), model.engine
    )
    inside = ((gx - cell.vertex_x_mm) ** 2 + (gy - cell.vertex_y_mm) ** 2 <= half**2).ravel()
    ok = traced.passed & inside
    L, M = traced.direction[:, 0], traced.direction[:, 1]
    basis = np.column_stack(
        [np.ones(ok.sum()), (gx.ravel() - cell.vertex_x_mm)[ok], (gy.ravel() - cell.vertex_y_mm)[ok]]
    )
    cl = solve_least_squares(basis, L[ok])
    cm = solve_least_squares(basis, M[ok])
    # Reference sphere: centred on the chief ray's hit (the ray nearest the pupil's centre),
    # through the paraxial exit pupil (the stop, the lens, seen through the PMMA and the film).
    chief = int(
        np.argmin(np.where(ok, (gx - cell.vertex_x_mm).ravel() ** 2 + (gy - cell.vertex_y_mm).ravel() ** 2, np.inf))
    )
    x_ref, y_ref = float(traced.x_mm[chief]), float(traced.y_mm[chief])
    design = model.design
    n_l = model._indices[band, 1]
    depth = optics.flat_z_mm + design.mla.thickness_mm / n_l
    if optics.film is not None:
        depth -= optics.film.thickness_mm * (1.0 - 1.0 / model._indices[band, 2])
    centre = np.array([x_ref, y_ref, 0.0])
    radius = float(np.linalg.norm(np.array([cell.vertex_x_mm, cell.vertex_y_mm, depth]) - centre))
    # Back along each ray's last segment from its hit p to the sphere: |p − t s − c| = R, t > 0.
    p = np.column_stack([traced.x_mm, traced.y_mm, np.zeros(u.size)]) - centre
    s_dir = traced.direction
    b = np.sum(p * s_dir, axis=1)
    t = b + np.sqrt(np.maximum(b * b - (np.sum(p * p, axis=1) - radius**2), 0.0))
    wave = traced.opl_mm - t
    wave = np.where(ok, wave - wave[ok].mean(), 0.0).reshape(samples, samples)
    spacing = float(cl[1] * (g[1] - g[0]))
    amplitude = ok.reshape(samples, samples).astype(float)
    lam = model.bands.wavelength_nm[band] * 1e-6
    return Pupil(
        lenslet,
        band,
        lam,
        cl[0] + cl[1] * g,
        cm[0] + cm[2] * g,
        spacing,
        amplitude,
        wave,
        x_ref,
        y_ref,
        float(amplitude.sum() * spacing * spacing),
    )
