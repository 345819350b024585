"""The device's filter chains, built from a :class:`~cm2optics.design.SystemDesign`.

Emission: the interference filter in front of the MLA, then (hybrid design) the absorption
film behind it; each sees its own angle of incidence. Excitation: the LED through the
excitation filter, which the collimated (or bare) LED light meets over a cone of angles.

The design fixes what it knows (band centres and widths, film cut-on, thickness and
material, LED peak); the rest comes from the library's models of the parts' classes
(:func:`~cm2optics.spectra.library.et_bandpass`, :func:`~cm2optics.spectra.library.wratten12_film`,
:func:`~cm2optics.spectra.library.led_spectrum`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cm2optics.design import AbsorptionFilter, InterferenceFilter, SystemDesign
from cm2optics.design.materials import refractive_index
from cm2optics.spectra.absorption import AbsorptionFilm
from cm2optics.spectra.interference import InterferenceBandpass
from cm2optics.spectra.library import et_bandpass, led_spectrum, wratten12_film
from cm2optics.spectra.spectrum import DEFAULT_WAVELENGTH_NM, Spectrum

__all__ = [
    "excitation_half_angle_rad",
    "DEFAULT_FILM",
    "EmissionChain",
    "absorption_film_from_design",
    "emission_chain",
    "excitation_spectrum",
    "interference_filter_from_design",
]

#: The film a design without one is compared against: Wratten no. 12 class, 0.1 mm, 515 nm.
DEFAULT_FILM = wratten12_film(515.0, 0.1)


def excitation_half_angle_rad(design: SystemDesign) -> float:
    """Half-angle of the cone of excitation light leaving an LED unit, rad.

    With a collimator: the étendue limit of a Lambertian emitter of side e through a square exit
    face of side b, sin δ = e / b (a perfect collimator can do no better). A bare LED: the widest
    ray from the emitter's edge through the excitation filter's far edge.
    """
    led = design.led
    if design.collimator is not None:
        return math.asin(min(1.0, led.emitter_mm / design.collimator.footprint_mm))
    half = max(design.excitation_filter.width_mm, design.excitation_filter.length_mm) / 2
    return math.atan((half + led.emitter_mm / 2) / design.led_array.excitation_gap_mm)


def interference_filter_from_design(part: InterferenceFilter) -> InterferenceBandpass:
    """The band-pass model of a design's interference filter (its centre and width; ET-class rest)."""
    return et_bandpass(part.center_nm, part.bandwidth_nm)


def absorption_film_from_design(part: AbsorptionFilter) -> AbsorptionFilm:
    """The Beer–Lambert model of a design's film: its cut-on, thickness and base material."""
    return wratten12_film(part.cut_on_nm, part.thickness_mm, refractive_index(part.material, part.cut_on_nm))


@dataclass(frozen=True)
class EmissionChain:
    """Interference filter, then an optional absorption film (the hybrid design).

    interference: the band-pass in front of the MLA.
    film: the absorbing film behind the MLA, or None (interference-only).
    """

    interference: InterferenceBandpass
    film: AbsorptionFilm | None = None

    def without_film(self) -> EmissionChain:
        """The interference-only chain."""
        return EmissionChain(self.interference, None)

    def transmittance(
        self,
        wavelength_nm: float | np.ndarray,
        aoi_filter_rad: float | np.ndarray = 0.0,
        aoi_film_rad: float | np.ndarray = 0.0,
    ) -> np.ndarray:
        """Unpolarised transmittance at ``wavelength_nm`` (nm) for angles of incidence (rad, in
        air) ``aoi_filter_rad`` at the interference filter and ``aoi_film_rad`` at the film; broadcasts."""
        t = self.interference.transmittance(wavelength_nm, aoi_filter_rad)
        if self.film is not None:
            t = t * self.film.transmittance(wavelength_nm, aoi_film_rad)
        return t

    def spectrum(self, aoi_filter_deg: float = 0.0, aoi_film_deg: float = 0.0) -> Spectrum:
        """The chain's transmittance as a :class:`Spectrum` (380–780 nm) at the given angles (degrees)."""
        for name, value in (("aoi_filter_deg", aoi_filter_deg), ("aoi_film_deg", aoi_film_deg)):
            if not (math.isfinite(value) and 0 <= value < 90):
                raise ValueError(f"{name} = {value!r}: must lie within 0–90°")
        values = self.transmittance(DEFAULT_WAVELENGTH_NM, math.radians(aoi_filter_deg), math.radians(aoi_film_deg))
        kind = "hybrid (interference + film)" if self.film is not None else "interference only"
        return Spectrum(
            DEFAULT_WAVELENGTH_NM,
            values,
            quantity="transmittance",
            source=f"emission chain, {kind}, at {aoi_filter_deg:g} deg / {aoi_film_deg:g} deg",
        )


def emission_chain(design: SystemDesign) -> EmissionChain:
    """The design's hybrid chain: its interference filter and its film, or :data:`DEFAULT_FILM`
    where the design has none (so that a V1 device can be compared with its hybrid upgrade)."""
    film = DEFAULT_FILM if design.absorption_filter is None else absorption_film_from_design(design.absorption_filter)
    return EmissionChain(interference_filter_from_design(design.emission_filter), film)


def excitation_spectrum(design: SystemDesign, angle_samples: int = 16) -> Spectrum:
    """Relative spectral power of the excitation light leaving an LED unit (LED × excitation filter).

    The filter's transmittance is averaged over the unit's cone of half-angle
    :func:`excitation_half_angle_rad`, weighted by the projected
    solid angle sin θ cos θ dθ (uniform radiance within the cone); ``angle_samples`` midpoints.
    """
    if not (isinstance(angle_samples, int) and 1 <= angle_samples <= 1000):
        raise ValueError(f"angle_samples = {angle_samples!r}: must be an integer within 1–1000")
    half = excitation_half_angle_rad(design)
    theta = (np.arange(angle_samples) + 0.5) * half / angle_samples
    weight = np.sin(theta) * np.cos(theta)
    weight /= weight.sum()
    band = interference_filter_from_design(design.excitation_filter)
    led = led_spectrum(design.led.peak_nm)
    mean_t = weight @ band.transmittance(led.wavelength_nm, theta[:, None])
    return Spectrum(
        led.wavelength_nm,
        led.values * mean_t,
        quantity="relative_power",
        source=(
            f"LED ({led.source}) x excitation filter {design.excitation_filter.center_nm:g}/"
            f"{design.excitation_filter.bandwidth_nm:g} averaged over a {math.degrees(half):.1f} deg cone"
        ),
    )
