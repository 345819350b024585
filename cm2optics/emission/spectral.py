"""Wavelength bands of the emission path and the weight each ray carries in each band.

A photon of wavelength λ emitted by the source is detected with probability

    w(λ) · T_filter(λ, θ_f) · T_film(λ, θ_m) · QE(λ),

w(λ) the source's photon spectrum (emission × λ, normalised to one photon), θ_f and θ_m the
ray's angles of incidence (in air) at the interference filter and at the absorption film. The
filter is the design's angle-shifted band-pass (:func:`~cm2optics.spectra.chain.interference_filter_from_design`),
the film the design's Beer–Lambert gel with its two Fresnel faces
(:func:`~cm2optics.spectra.chain.absorption_film_from_design`), QE the sensor's curve
(``imx178-qe`` from the spectral library).

The spectrum is cut into bands of at most ``band_nm`` over the wavelengths that can be
detected at any angle up to 60°; each band is traced at its own wavelength (refractive indices,
diffraction scale), and each ray's weight in band b is the band's sum of the product above on a
1-nm grid, read from a table over (θ_f, θ_m) (0–80° in 0.5° steps, bilinear). Summed over
bands, a ray's weight is the probability that a photon sent along it is detected.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cm2optics.design import SystemDesign
from cm2optics.spectra.chain import absorption_film_from_design, interference_filter_from_design
from cm2optics.spectra.library import load_spectrum
from cm2optics.spectra.spectrum import Spectrum

__all__ = ["SpectralBands", "spectral_bands"]

_ANGLE_STEP_DEG = 0.5
_ANGLE_MAX_DEG = 80.0
#: Angles of incidence at the filter over which a wavelength counts as detectable (deg).
_SUPPORT_MAX_AOI_DEG = 60.0
#: A wavelength is traced if its detection weight reaches this fraction of the peak.
_SUPPORT_FRACTION = 1e-3


@dataclass(frozen=True, eq=False)
class SpectralBands:
    """Bands traced for one design and source spectrum.

    wavelength_nm: (B,) wavelength each band is traced at (its weighted mean at normal incidence), nm.
    edges_nm: (B, 2) first and last 1-nm sample of each band, nm.
    table: (B, A, A) detection weight of a ray in each band vs (θ_f, θ_m) on :attr:`angles_rad`.
    angles_rad: (A,) the angle grid of the table, rad.
    filtered: whether the filter and film are applied (False: only spectrum × QE, for tests).
    description: one line on the spectra used (provenance).
    """

    wavelength_nm: np.ndarray
    edges_nm: np.ndarray
    table: np.ndarray
    angles_rad: np.ndarray
    filtered: bool
    description: str

    def __len__(self) -> int:
        return len(self.wavelength_nm)

    def _bilinear(self, flat: np.ndarray, base: np.ndarray | int, aoi_filter_rad, aoi_film_rad) -> np.ndarray:
        """Bilinear read of the tables flattened to ``flat`` at angle rows starting at ``base``."""
        step = self.angles_rad[1] - self.angles_rad[0]
        count = len(self.angles_rad)
        f = np.clip(np.asarray(aoi_filter_rad, dtype=float) / step, 0, count - 1 - 1e-9)
        m = np.clip(np.asarray(aoi_film_rad, dtype=float) / step, 0, count - 1 - 1e-9)
        i, j = f.astype(np.intp), m.astype(np.intp)
        a, b = f - i, m - j
        k = base + i * count + j
        return (1 - a) * ((1 - b) * flat[k] + b * flat[k + 1]) + a * (
            (1 - b) * flat[k + count] + b * flat[k + count + 1]
        )

    def weight(self, band: np.ndarray | int, aoi_filter_rad: np.ndarray, aoi_film_rad: np.ndarray) -> np.ndarray:
        """Detection weight (photons detected per photon emitted along the ray, this band only) of
        rays in ``band`` (index, scalar or per ray) at the given angles (rad); bilinear in angle."""
        count = len(self.angles_rad)
        base = np.asarray(band, dtype=np.intp) * (count * count)
        return self._bilinear(self.table.reshape(-1), base, aoi_filter_rad, aoi_film_rad)

    def total_weight(self, aoi_filter_rad: np.ndarray, aoi_film_rad: np.ndarray) -> np.ndarray:
        """Detection weight summed over all bands, per ray (bilinear in angle)."""
        total = self.__dict__.get("_total")
        if total is None:
            total = self.table.sum(axis=0).reshape(-1)
            object.__setattr__(self, "_total", total)
        return self._bilinear(total, 0, aoi_filter_rad, aoi_film_rad)

    def detected_fraction(self, aoi_filter_rad: float = 0.0, aoi_film_rad: float = 0.0) -> float:
        """Photons detected per photon emitted, summed over bands, at the given angles (rad)."""
        return float(sum(self.weight(b, aoi_filter_rad, aoi_film_rad) for b in range(len(self))))


def spectral_bands(
    design: SystemDesign,
    emission: Spectrum | None = None,
    quantum_efficiency: Spectrum | None = None,
    band_nm: float = 10.0,
    filtered: bool = True,
) -> SpectralBands:
    """The bands of ``design``'s emission path for a source spectrum.

    emission: the source's relative spectral power (default: the library's ``gfp-emission``).
    quantum_efficiency: the sensor's QE (default: the library's ``imx178-qe``).
    band_nm: widest band, nm (1–100): narrower bands follow the chromatic focal shift more finely.
    filtered: apply the interference filter and the absorption film (False: only emission × QE).
    """
    if not (math.isfinite(band_nm) and 1.0 <= band_nm <= 100.0):
        raise ValueError(f"band_nm = {band_nm!r}: must lie within 1–100 nm")
    emission = emission if emission is not None else load_spectrum("gfp-emission")
    qe = quantum_efficiency if quantum_efficiency is not None else load_spectrum("imx178-qe")
    low = max(emission.domain_nm[0], qe.domain_nm[0], 380.0)
    high = min(emission.domain_nm[1], qe.domain_nm[1], 780.0)
    if high - low < 2:
        raise ValueError(f"the emission spectrum and the QE overlap on {low:g}–{high:g} nm only: need ≥ 2 nm")
    lam = np.arange(math.ceil(low), math.floor(high) + 1, 1.0)
    photons = np.asarray(emission(lam), dtype=float) * lam
    if not photons.sum() > 0:
        raise ValueError("the emission spectrum is zero everywhere")
    photons /= photons.sum()
    base = photons * np.asarray(qe(lam), dtype=float)

    angles = np.radians(np.arange(0.0, _ANGLE_MAX_DEG + _ANGLE_STEP_DEG / 2, _ANGLE_STEP_DEG))
    if filtered:
        interference = interference_filter_from_design(design.emission_filter)
        t_filter = interference.transmittance(lam[None, :], angles[:, None])  # (A, L)
        if design.absorption_filter is not None:
            film = absorption_film_from_design(design.absorption_filter)
            t_film = film.transmittance(lam[None, :], angles[:, None])
        else:
            t_film = np.ones((len(angles), len(lam)))
    else:
        t_filter = np.ones((len(angles), len(lam)))
        t_film = np.ones((len(angles), len(lam)))

    reach = angles <= math.radians(_SUPPORT_MAX_AOI_DEG) + 1e-12
    detectable = (base[None, :] * t_filter[reach] * t_film[0][None, :]).max(axis=0)
    keep = np.flatnonzero(detectable >= _SUPPORT_FRACTION * detectable.max())
    first, last = int(keep[0]), int(keep[-1])
    count = max(1, math.ceil((last - first + 1) / band_nm))
    bounds = np.linspace(first, last + 1, count + 1).round().astype(int)

    centres, edges, tables = [], [], []
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        sl = slice(a, b)
        normal = base[sl] * t_filter[0, sl] * t_film[0, sl]
        weight = normal if normal.sum() > 0 else np.ones(b - a)
        centres.append(float(np.sum(weight * lam[sl]) / np.sum(weight)))
        edges.append((lam[a], lam[b - 1]))
        tables.append(np.einsum("l,fl,ml->fm", base[sl], t_filter[:, sl], t_film[:, sl]))
    text = (
        f"emission [{emission.source or emission.quantity}] x QE [{qe.source or qe.quantity}]"
        + (
            f" x filter {design.emission_filter.center_nm:g}/{design.emission_filter.bandwidth_nm:g}"
            if filtered
            else ""
        )
        + (" x film" if filtered and design.absorption_filter is not None else "")
    )
    return SpectralBands(
        wavelength_nm=np.asarray(centres),
        edges_nm=np.asarray(edges, dtype=float),
        table=np.stack(tables),
        angles_rad=angles,
        filtered=filtered,
        description=text,
    )
