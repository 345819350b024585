"""Absorbing films: Beer–Lambert attenuation along the refracted path, Fresnel loss at the faces.

A ray meeting a film of thickness d and index n at angle θ (in air) is refracted to
θ_t = asin(sin θ / n) and crosses a path d / cos θ_t, so the internal transmittance is

    T_int(λ, θ) = 10^(−A(λ) / cos θ_t),    A(λ) = α(λ) · d,

with α the decadic absorption coefficient (1/mm) and A the film's absorbance at normal
incidence. Each face passes 1 − R(θ) of the light, R the unpolarised Fresnel reflectance;
multiple reflections inside a lossy film are neglected (they add < 0.2 % for n ≈ 1.5).
Unlike an interference filter, the edge does not move with angle: it only deepens slightly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cm2optics.optics import interfaces
from cm2optics.spectra.spectrum import DEFAULT_WAVELENGTH_NM, Spectrum

__all__ = [
    "AbsorptionFilm",
    "beer_lambert_transmittance",
    "fresnel_transmittance",
    "refracted_angle_rad",
]


def refracted_angle_rad(aoi_rad: float | np.ndarray, refractive_index: float) -> float | np.ndarray:
    """Angle inside a medium of index ``refractive_index`` (≥ 1) for incidence ``aoi_rad`` (rad) from air."""
    if not (math.isfinite(refractive_index) and refractive_index >= 1.0):
        raise ValueError(f"refractive_index = {refractive_index!r}: must be a finite number ≥ 1")
    result = np.arcsin(np.sin(np.asarray(aoi_rad, dtype=float)) / refractive_index)
    return float(result) if result.ndim == 0 else result


def beer_lambert_transmittance(
    absorbance: float | np.ndarray, aoi_rad: float | np.ndarray, refractive_index: float
) -> float | np.ndarray:
    """10^(−A / cos θ_t): internal transmittance of a layer of normal-incidence ``absorbance`` A
    (decadic, ≥ 0) met at ``aoi_rad`` (rad, in air), θ_t refracted by ``refractive_index``."""
    absorbance = np.asarray(absorbance, dtype=float)
    if np.any(absorbance[np.isfinite(absorbance)] < 0):
        raise ValueError("absorbance must be ≥ 0")
    cos_t = np.cos(refracted_angle_rad(aoi_rad, refractive_index))
    result = 10.0 ** (-absorbance / cos_t)
    return float(result) if result.ndim == 0 else result


def fresnel_transmittance(aoi_rad: float | np.ndarray, refractive_index: float) -> float | np.ndarray:
    """Unpolarised power transmittance 1 − (R_s + R_p)/2 of one air → medium face at ``aoi_rad`` (rad)."""
    theta = np.asarray(aoi_rad, dtype=float)
    n = refractive_index
    cos_i = np.cos(theta)
    cos_t = np.cos(refracted_angle_rad(theta, n))
    result = np.asarray(interfaces.fresnel_transmittance(cos_i, cos_t, 1.0, n))
    return float(result) if result.ndim == 0 else result


@dataclass(frozen=True)
class AbsorptionFilm:
    """A film of absorbing dye in a transparent base.

    absorption_coefficient: decadic absorption coefficient α(λ) of the material, 1/mm (a Spectrum).
    thickness_mm: film thickness, mm (> 0).
    refractive_index: index of the base (gelatin ≈ 1.53), ≥ 1.
    """

    absorption_coefficient: Spectrum
    thickness_mm: float
    refractive_index: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.thickness_mm) and 0 < self.thickness_mm <= 10.0):
            raise ValueError(f"thickness_mm = {self.thickness_mm!r}: must lie within 0–10 mm (> 0)")
        if not (math.isfinite(self.refractive_index) and 1.0 <= self.refractive_index <= 3.0):
            raise ValueError(f"refractive_index = {self.refractive_index!r}: must lie within 1–3")

    def absorbance(self, wavelength_nm: float | np.ndarray) -> float | np.ndarray:
        """Decadic absorbance α·d at normal incidence at ``wavelength_nm`` (nm)."""
        return self.absorption_coefficient(wavelength_nm) * self.thickness_mm

    def internal_transmittance(
        self, wavelength_nm: float | np.ndarray, aoi_rad: float | np.ndarray = 0.0
    ) -> np.ndarray:
        """Beer–Lambert transmittance along the refracted path (faces excluded); broadcasts."""
        return beer_lambert_transmittance(self.absorbance(wavelength_nm), aoi_rad, self.refractive_index)

    def transmittance(self, wavelength_nm: float | np.ndarray, aoi_rad: float | np.ndarray = 0.0) -> np.ndarray:
        """Transmittance of the film in air, both faces included, at ``aoi_rad`` (rad); broadcasts."""
        faces = fresnel_transmittance(aoi_rad, self.refractive_index) ** 2
        return faces * self.internal_transmittance(wavelength_nm, aoi_rad)

    def spectrum(
        self, aoi_deg: float = 0.0, wavelength_nm: np.ndarray = DEFAULT_WAVELENGTH_NM, source: str = ""
    ) -> Spectrum:
        """The transmittance at ``aoi_deg`` (degrees) as a :class:`Spectrum` on ``wavelength_nm`` (nm)."""
        if not (math.isfinite(aoi_deg) and 0 <= aoi_deg < 90):
            raise ValueError(f"aoi_deg = {aoi_deg!r}: must lie within 0–90°")
        values = self.transmittance(wavelength_nm, math.radians(aoi_deg))
        text = source or (
            f"Beer-Lambert film (cm2optics.spectra.absorption): {self.thickness_mm:g} mm, n = {self.refractive_index:g}, "
            f"absorption coefficient from [{self.absorption_coefficient.source}]"
        )
        return Spectrum(wavelength_nm, values, quantity="transmittance", source=text)
