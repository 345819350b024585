"""The wavefront of a design's lenslets for an on-axis point: the exact trace that finds the plane
of best focus (:func:`cm2optics.optics.first_order.object_plane_z_mm`).

The lenslets carry several waves of spherical aberration, so the sharpest image of a point
lies nearer the device than the paraxial conjugate of the sensor. Heights are in the device
frame (mm, z = 0 on the sensor).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from cm2optics.design.materials import refractive_index
from cm2optics.optics.arrays import NumpyOps
from cm2optics.optics.interfaces import refract, snell_cos_t

if TYPE_CHECKING:
    from cm2optics.design import SystemDesign

__all__ = ["FOCUS_RAYS", "on_axis_wavefront_rms_waves"]

#: Rays along each side of the launch grid that finds the plane of best focus.
FOCUS_RAYS = 48


def _refract(d: np.ndarray, normal: np.ndarray, eta: np.ndarray | float) -> np.ndarray:
    """Snell's law for unit directions ``d`` (n, 3) through unit normals facing the rays, index
    ratio ``eta`` = n₁/n₂; NaN where totally reflected."""
    cos_i = -np.sum(d * normal, axis=-1, keepdims=True)
    cos_t, tir = snell_cos_t(NumpyOps, cos_i, eta)
    return np.where(tir, np.nan, refract(d, normal, eta, cos_i, cos_t))


def on_axis_wavefront_rms_waves(design: SystemDesign, height_mm: float, rays: int = FOCUS_RAYS) -> float:
    """RMS wavefront error (waves, piston and tilt removed) on the sensor of a point source at
    ``height_mm`` (device frame, mm) on a lenslet's axis, imaged by that lenslet.

    Exact trace at the design wavelength through the emission filter, the lenslet's sphere
    (clipped to its square aperture), the substrate, the film and the air gaps; the wavefront
    is the optical path to the reference sphere centred on the axial point of the sensor through
    the exit pupil's centre, weighted uniformly over a ``rays`` × ``rays`` grid of launch tangents.
    """
    lam = design.imaging.design_wavelength_nm
    filt, mla, film = design.emission_filter, design.mla, design.absorption_filter
    n_f, n_l = refractive_index(filt.material, lam), refractive_index(mla.material, lam)
    z_filter, z_vertex, z_flat = design.emission_filter_z_mm, design.mla_vertex_z_mm, design.imaging.mla_to_sensor_mm
    half = mla.aperture_mm / 2
    reach = height_mm - z_vertex - filt.thickness_mm * (1.0 - 1.0 / n_f)
    if not reach > 0:
        return float("inf")
    t = ((np.arange(rays) + 0.5) / rays * 2.0 - 1.0) * 1.02 * half / reach
    u, v = (g.ravel() for g in np.meshgrid(t, t))
    d = np.column_stack([u, v, -np.ones_like(u)]) / np.sqrt(1.0 + u * u + v * v)[:, None]
    up = np.array([0.0, 0.0, 1.0])
    # Emission filter: a plane-parallel plate (the ray leaves it with its own direction).
    p = np.column_stack([np.zeros_like(u), np.zeros_like(u), np.full_like(u, height_mm)])
    step = (z_filter + filt.thickness_mm - height_mm) / d[:, 2]
    p, opl = p + step[:, None] * d, step
    g = _refract(d, up, 1.0 / n_f)
    step = -filt.thickness_mm / g[:, 2]
    p, opl = p + step[:, None] * g, opl + n_f * step
    # The lenslet's sphere, its aperture and the substrate.
    centre = np.array([0.0, 0.0, z_vertex - mla.radius_mm])
    o = p - centre
    b = np.sum(d * o, axis=1)
    with np.errstate(invalid="ignore"):
        step = -b - np.sqrt(b * b - (np.sum(o * o, axis=1) - mla.radius_mm**2))
    p, opl = p + step[:, None] * d, opl + step
    keep = (np.abs(p[:, 0]) <= half) & (np.abs(p[:, 1]) <= half)
    d = _refract(d, (p - centre) / mla.radius_mm, 1.0 / n_l)
    step = (z_flat - p[:, 2]) / d[:, 2]
    p, opl = p + step[:, None] * d, opl + n_l * step
    d = _refract(d, up, n_l)
    pupil_depth = z_flat + mla.thickness_mm / n_l
    if film is not None:
        n_m = refractive_index(film.material, lam)
        z_film = design.imaging.film_to_sensor_mm
        step = (z_film + film.thickness_mm - p[:, 2]) / d[:, 2]
        p, opl = p + step[:, None] * d, opl + step
        g = _refract(d, up, 1.0 / n_m)
        step = -film.thickness_mm / g[:, 2]
        p, opl = p + step[:, None] * g, opl + n_m * step
        pupil_depth -= film.thickness_mm * (1.0 - 1.0 / n_m)
    step = -p[:, 2] / d[:, 2]
    p, opl = p + step[:, None] * d, opl + step
    # Back along the last segment to the reference sphere (centre: the axial point of the sensor).
    along = p[:, 0] * d[:, 0] + p[:, 1] * d[:, 1]
    with np.errstate(invalid="ignore"):
        back = along + np.sqrt(along * along - (p[:, 0] ** 2 + p[:, 1] ** 2 - pupil_depth**2))
    wave = opl - back
    keep &= np.isfinite(wave)
    if keep.sum() < 16:
        return float("inf")
    q = p[keep, :2] - back[keep, None] * d[keep, :2]
    basis = np.column_stack([np.ones(keep.sum()), q])
    coef, *_ = np.linalg.lstsq(basis, wave[keep], rcond=None)
    residual = wave[keep] - basis @ coef
    return float(np.sqrt(np.mean(residual**2)) / (lam * 1e-6))
