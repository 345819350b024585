"""Thin-film band-pass filters whose passband shifts with the angle of incidence.

A multi-cavity interference filter's features move to shorter wavelengths when light meets it
obliquely. For a Fabry–Perot cavity the resonance follows exactly

    λ(θ) = λ₀ · √(1 − (sin θ / n_eff)²)

with ``n_eff`` an effective index between the spacer's and the mirrors' (Macleod, *Thin-Film
Optical Filters*, ch. 8; Semrock/Chroma application notes use the same law for the edges of
band-pass filters, with n_eff ≈ 1.7–2.2 for hard-coated filters).

Two refinements of the single-index law are built in, because measured filters need them:

* each edge has its own index (``n_eff_short_*``, ``n_eff_long_*``): the short edge of a
  band-pass usually moves less than the long one, so the passband narrows with angle;
* s and p polarisation have their own indices: at oblique incidence the s passband narrows
  and the p passband widens (the mirrors' stop bands widen for s, shrink for p), so the
  unpolarised curve grows a ≈ 50 % shelf at each edge, where only p gets through.

The transmittance of one polarisation is a logistic step up at the short edge times a
logistic step down at the long edge, scaled to ``peak_transmittance``, above a floor
``10^−blocking_od`` that stands for the blocking coatings outside the band:

    T(λ) = T_b + (T_peak − T_b) · σ((λ − λ_short(θ)) / s) · σ((λ_long(θ) − λ) / s),
    s = edge_width_nm / ln 81,

so ``edge_width_nm`` is each edge's 10–90 % rise. Unpolarised light gets (T_s + T_p) / 2.
The model ignores the ripple and the loss of blocking that real coatings show beyond ≈ 45°.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from scipy.special import expit

from cm2optics.spectra.spectrum import DEFAULT_WAVELENGTH_NM, Spectrum

__all__ = [
    "InterferenceBandpass",
    "Polarisation",
    "angle_shifted_wavelength_nm",
]

_LN81 = math.log(81.0)  # a logistic rises from 10 % to 90 % over ln 81 scale lengths


class Polarisation(StrEnum):
    """Polarisation of the light meeting a filter, relative to its plane of incidence."""

    S = "s"
    P = "p"
    UNPOLARISED = "unpolarised"


def angle_shifted_wavelength_nm(
    wavelength_nm: float | np.ndarray, aoi_rad: float | np.ndarray, n_eff: float | np.ndarray
) -> float | np.ndarray:
    """λ(θ) = λ₀ √(1 − (sin θ / n_eff)²): where a filter feature at ``wavelength_nm`` (nm, normal
    incidence) lies at angle of incidence ``aoi_rad`` (rad, in air) for effective index ``n_eff`` (≥ 1).

    Broadcasts over its arguments; NaN in gives NaN out.
    """
    n = np.asarray(n_eff, dtype=float)
    if np.any(n[np.isfinite(n)] < 1.0):
        raise ValueError(f"n_eff = {n_eff}: must be ≥ 1 (no thin-film stack has an effective index below air's)")
    result = np.asarray(wavelength_nm, dtype=float) * np.sqrt(1.0 - (np.sin(aoi_rad) / n) ** 2)
    return float(result) if result.ndim == 0 else result


def _check_range(name: str, value: float, low: float, high: float, unit: str = "") -> None:
    if not (math.isfinite(value) and low <= value <= high):
        raise ValueError(f"{name} = {value!r}: must lie within {low:g}–{high:g}{unit}")


@dataclass(frozen=True)
class InterferenceBandpass:
    """A band-pass interference filter with angle-dependent edges.

    short_edge_nm, long_edge_nm: half-peak wavelengths of the two edges at normal incidence, nm.
    n_eff_short_s, n_eff_short_p: effective indices of the short edge for s and p light (1–4).
    n_eff_long_s, n_eff_long_p: effective indices of the long edge for s and p light (1–4).
    edge_width_nm: 10–90 % rise of each edge, nm (> 0).
    peak_transmittance: in-band transmittance (0–1].
    blocking_od: optical density of the out-of-band floor, T = 10^−OD (0–10).
    """

    short_edge_nm: float
    long_edge_nm: float
    n_eff_short_s: float
    n_eff_short_p: float
    n_eff_long_s: float
    n_eff_long_p: float
    edge_width_nm: float = 3.0
    peak_transmittance: float = 0.95
    blocking_od: float = 5.0

    def __post_init__(self) -> None:
        _check_range("short_edge_nm", self.short_edge_nm, 200.0, 2000.0, " nm")
        _check_range("long_edge_nm", self.long_edge_nm, self.short_edge_nm + 1e-6, 2000.0, " nm (above short_edge_nm)")
        for name in ("n_eff_short_s", "n_eff_short_p", "n_eff_long_s", "n_eff_long_p"):
            _check_range(name, getattr(self, name), 1.0, 4.0)
        _check_range("edge_width_nm", self.edge_width_nm, 1e-3, 100.0, " nm")
        _check_range("peak_transmittance", self.peak_transmittance, 1e-6, 1.0)
        _check_range("blocking_od", self.blocking_od, 0.0, 10.0)
        if 10.0**-self.blocking_od > self.peak_transmittance:
            raise ValueError(
                f"blocking_od = {self.blocking_od}: the out-of-band floor must lie below peak_transmittance"
            )

    @classmethod
    def single_index(
        cls, short_edge_nm: float, long_edge_nm: float, n_eff: float, **kwargs: float
    ) -> InterferenceBandpass:
        """The textbook filter: one effective index for both edges and both polarisations."""
        return cls(short_edge_nm, long_edge_nm, n_eff, n_eff, n_eff, n_eff, **kwargs)

    def edges_nm(
        self, aoi_rad: float | np.ndarray, polarisation: Polarisation | str
    ) -> tuple[float | np.ndarray, float | np.ndarray]:
        """Half-peak wavelengths (short, long) of one polarisation (s or p) at ``aoi_rad`` (rad), nm."""
        polarisation = Polarisation(polarisation)
        if polarisation is Polarisation.UNPOLARISED:
            raise ValueError("edges_nm needs polarisation 's' or 'p': unpolarised light has two edges per side")
        s = polarisation is Polarisation.S
        n_short = self.n_eff_short_s if s else self.n_eff_short_p
        n_long = self.n_eff_long_s if s else self.n_eff_long_p
        return (
            angle_shifted_wavelength_nm(self.short_edge_nm, aoi_rad, n_short),
            angle_shifted_wavelength_nm(self.long_edge_nm, aoi_rad, n_long),
        )

    def transmittance(
        self,
        wavelength_nm: float | np.ndarray,
        aoi_rad: float | np.ndarray = 0.0,
        polarisation: Polarisation | str = Polarisation.UNPOLARISED,
    ) -> np.ndarray:
        """Transmittance at ``wavelength_nm`` (nm) and angle of incidence ``aoi_rad`` (rad, in air).

        The two arguments broadcast against each other (e.g. wavelengths ``(n,)`` and angles
        ``(m, 1)`` give ``(m, n)``); NaN in gives NaN out.
        """
        polarisation = Polarisation(polarisation)
        if polarisation is Polarisation.UNPOLARISED:
            return 0.5 * (
                self.transmittance(wavelength_nm, aoi_rad, Polarisation.S)
                + self.transmittance(wavelength_nm, aoi_rad, Polarisation.P)
            )
        wavelength = np.asarray(wavelength_nm, dtype=float)
        short, long = self.edges_nm(np.asarray(aoi_rad, dtype=float), polarisation)
        scale = self.edge_width_nm / _LN81
        floor = 10.0**-self.blocking_od
        band = expit((wavelength - short) / scale) * expit((long - wavelength) / scale)
        return floor + (self.peak_transmittance - floor) * band

    def spectrum(
        self,
        aoi_deg: float = 0.0,
        polarisation: Polarisation | str = Polarisation.UNPOLARISED,
        wavelength_nm: np.ndarray = DEFAULT_WAVELENGTH_NM,
        source: str = "",
    ) -> Spectrum:
        """The transmittance at ``aoi_deg`` (degrees) as a :class:`Spectrum` on ``wavelength_nm`` (nm)."""
        _check_range("aoi_deg", aoi_deg, 0.0, 89.999, "°")
        values = self.transmittance(wavelength_nm, math.radians(aoi_deg), polarisation)
        return Spectrum(wavelength_nm, values, quantity="transmittance", source=source or self.describe())

    def describe(self) -> str:
        """One line with the model and its parameters (used as provenance)."""
        return (
            f"angle-shifted band-pass model (cm2optics.spectra.interference): edges {self.short_edge_nm:g}/"
            f"{self.long_edge_nm:g} nm, n_eff short s/p {self.n_eff_short_s:g}/{self.n_eff_short_p:g}, "
            f"long s/p {self.n_eff_long_s:g}/{self.n_eff_long_p:g}, 10-90% edge {self.edge_width_nm:g} nm, "
            f"peak T {self.peak_transmittance:g}, blocking OD {self.blocking_od:g}"
        )
