"""The excitation filter's transmittance T(λ, θ) as the tracer applies it, per ray.

The tracer takes the filter as any vectorised callable ``transmission(wavelength_nm, aoi_rad)
-> T`` (unpolarised, ``aoi_rad`` the angle of incidence in air on the coated face). By
default it is the spectra library's model of the design's filter
(:func:`cm2optics.spectra.library.et_bandpass`: an angle-shifted band-pass whose edges follow
λ(θ) = λ₀ √(1 − (sin θ / n_eff)²)).

``T`` is the whole filter's transmittance (as a vendor's curve is): the tracer applies it once,
where a ray meets the coated face, and lets the rest (1 − T) be reflected there; the plate's
other face then only refracts (and totally reflects beyond the critical angle), without a
second Fresnel loss. The filter's glass edges are ground and sit in the housing: absorbing.

Inside a compiled kernel a Python callable cannot run, so :func:`tabulate_transmission`
samples it once on a regular grid (0.25 nm × 0.25° by default: finer than the 3-nm edges of
hard-coated filters) and the tracer interpolates bilinearly.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from cm2optics.design import SystemDesign

__all__ = [
    "Transmission",
    "TransmissionTable",
    "design_filter_transmission",
    "filter_from_table",
    "tabulate_transmission",
]

#: ``transmission(wavelength_nm, aoi_rad) -> T`` (unpolarised, 0–1); arguments broadcast.
Transmission = Callable[[np.ndarray, np.ndarray], np.ndarray]


def design_filter_transmission(design: SystemDesign) -> Transmission:
    """The spectra library's model of ``design.excitation_filter`` (centre and bandwidth at
    normal incidence), unpolarised."""
    from cm2optics.spectra.library import et_bandpass

    model = et_bandpass(design.excitation_filter.center_nm, design.excitation_filter.bandwidth_nm)

    def transmission(wavelength_nm: np.ndarray, aoi_rad: np.ndarray) -> np.ndarray:
        return np.asarray(model.transmittance(wavelength_nm, aoi_rad), dtype=float)

    transmission.__doc__ = model.describe()
    return transmission


@dataclass(frozen=True, eq=False)
class TransmissionTable:
    """T sampled on a regular grid: ``values[i_aoi, i_wl]`` at ``aoi = i_aoi · aoi_step_rad``
    (0 to π/2) and ``wl = wavelength_start_nm + i_wl · wavelength_step_nm``.

    wavelength_start_nm, wavelength_step_nm: grid origin and pitch, nm.
    aoi_step_rad: angular pitch, rad.
    values: (n_aoi, n_wl) transmittances, 0–1.
    """

    wavelength_start_nm: float
    wavelength_step_nm: float
    aoi_step_rad: float
    values: np.ndarray

    def __call__(self, wavelength_nm: np.ndarray, aoi_rad: np.ndarray) -> np.ndarray:
        """Bilinear interpolation (clamped at the grid's ends), exactly as the kernel does it."""
        n_aoi, n_wl = self.values.shape
        fw = np.clip(
            (np.asarray(wavelength_nm, dtype=float) - self.wavelength_start_nm) / self.wavelength_step_nm, 0, n_wl - 1
        )
        fa = np.clip(np.asarray(aoi_rad, dtype=float) / self.aoi_step_rad, 0, n_aoi - 1)
        iw = np.minimum(np.floor(fw).astype(int), n_wl - 2)
        ia = np.minimum(np.floor(fa).astype(int), n_aoi - 2)
        tw, ta = fw - iw, fa - ia
        v = self.values
        return (1 - ta) * ((1 - tw) * v[ia, iw] + tw * v[ia, iw + 1]) + ta * (
            (1 - tw) * v[ia + 1, iw] + tw * v[ia + 1, iw + 1]
        )


def tabulate_transmission(
    transmission: Transmission,
    wavelength_range_nm: tuple[float, float],
    wavelength_step_nm: float = 0.25,
    aoi_step_deg: float = 0.25,
) -> TransmissionTable:
    """Sample ``transmission`` over ``wavelength_range_nm`` (nm) and 0–90° of incidence.

    wavelength_step_nm: grid pitch, nm. aoi_step_deg: grid pitch, degrees.
    Raises ValueError when the callable returns values outside 0–1 or not finite.
    """
    lo, hi = wavelength_range_nm
    if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
        raise ValueError(f"wavelength_range_nm = {wavelength_range_nm}: needs low < high")
    n_wl = int(math.ceil((hi - lo) / wavelength_step_nm)) + 1
    n_aoi = int(round(90.0 / aoi_step_deg)) + 1
    wl = lo + wavelength_step_nm * np.arange(n_wl)
    aoi = np.radians(aoi_step_deg) * np.arange(n_aoi)
    values = np.asarray(transmission(wl[None, :], aoi[:, None]), dtype=float)
    values = np.broadcast_to(values, (n_aoi, n_wl)).copy()
    if not np.all(np.isfinite(values)) or values.min() < -1e-9 or values.max() > 1 + 1e-9:
        raise ValueError("the excitation filter's transmission must be finite and within 0–1")
    return TransmissionTable(
        float(lo), float(wavelength_step_nm), math.radians(aoi_step_deg), np.clip(values, 0.0, 1.0)
    )


def filter_from_table(path: str) -> Transmission:
    """A vendor's angle table (CSV: ``wavelength_nm,aoi_deg`` and ``T`` or ``Ts,Tp``), fitted
    with the spectra module's angle-shifted band-pass models (:mod:`cm2optics.spectra.fit`;
    the model that best predicts the held-out angles is used): tables hold few angles, and
    interpolating between them would average two shifted edges into a false double step."""
    from cm2optics.spectra.fit import fit_filter_models, read_filter_table

    report = fit_filter_models(read_filter_table(path))
    model = report.best.filter

    def transmission(wavelength_nm: np.ndarray, aoi_rad: np.ndarray) -> np.ndarray:
        return np.asarray(model.transmittance(wavelength_nm, aoi_rad), dtype=float)

    transmission.__doc__ = f"fitted to {path} ({report.selected.value}): {model.describe()}"
    return transmission
