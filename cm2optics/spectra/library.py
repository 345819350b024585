"""The spectral library: the curves of a CM² device, by name, and the models that made them.

No measured curve of the device's parts can be shipped here, so every curve is a documented
parametric model evaluated at the nominal parts of the ``cm2-v2`` preset (380–780 nm, 1 nm):

=========================  =====================================================================
name                       model
=========================  =====================================================================
led-lxml-pb01-0040         Lumileds LUXEON Rebel blue: Ohno (2005) LED model, peak 470 nm,
                           FWHM 25 nm (datasheet typical spectral half-width)
excitation-filter-470-40   Chroma 470/40 (ET class): angle-shifted band-pass at 0°
emission-filter-535-50     Chroma 535/50 (ET class): angle-shifted band-pass at 0°
wratten-12                 Kodak Wratten no. 12 class yellow gel, 0.1 mm, 50 % at 515 nm:
                           Beer–Lambert film at 0°
gfp-excitation             EGFP/fluorescein class excitation (peak 488 nm), log-normal bands
gfp-emission               EGFP/fluorescein class emission (peak ≈ 510 nm), log-normal bands
imx178-qe                  back-side illuminated silicon pixel (Sony IMX178 class)
=========================  =====================================================================

The CSVs live in the package (``cm2optics/spectra/data/``, found after any install) and, as
the documented copy, in the repository's top-level ``spectra/`` folder; both are written by
:func:`write_library` (``python -m cm2optics.spectra.library spectra cm2optics/spectra/data``)
and a test checks that they still equal the models.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable
from importlib import resources
from pathlib import Path

import colour
import numpy as np
from scipy.optimize import brentq
from scipy.special import expit, logit

from cm2optics.spectra.absorption import AbsorptionFilm, fresnel_transmittance
from cm2optics.spectra.interference import InterferenceBandpass
from cm2optics.spectra.spectrum import DEFAULT_WAVELENGTH_NM, Spectrum, read_spectrum_csv, write_spectrum_csv

__all__ = [
    "GELATIN_INDEX",
    "available_spectra",
    "bsi_silicon_quantum_efficiency",
    "egfp_emission",
    "egfp_emission_band_nm",
    "egfp_excitation",
    "et_bandpass",
    "led_spectrum",
    "library_spectra",
    "load_spectrum",
    "wratten12_film",
    "write_library",
]

#: Refractive index of a gelatin film base (n_D ≈ 1.53; cm2optics.design.materials uses the same value).
GELATIN_INDEX = 1.53

# ----------------------------------------------------------------------------- LED


def _ohno_half_width_factor() -> float:
    """FWHM / Δλ₀.₅ of the Ohno (2005) shape (g + 2g⁵)/3, g = exp(−(Δλ/Δλ₀.₅)²)."""
    g_half = brentq(lambda g: (g + 2 * g**5) / 3 - 0.5, 1e-6, 1.0)
    return 2.0 * math.sqrt(-math.log(g_half))


def led_spectrum(peak_nm: float = 470.0, fwhm_nm: float = 25.0) -> Spectrum:
    """Relative spectral power of a single-colour LED (peak 1) on 380–780 nm.

    peak_nm: peak wavelength, nm. fwhm_nm: full width at half maximum, nm.
    Model: Ohno, "Spectral design considerations for white LED color rendering", Opt. Eng. 44,
    111302 (2005), as implemented by :func:`colour.sd_single_led` (colour-science).
    """
    if not (math.isfinite(peak_nm) and 350 <= peak_nm <= 800):
        raise ValueError(f"peak_nm = {peak_nm!r}: must lie within 350–800 nm")
    if not (math.isfinite(fwhm_nm) and 1 <= fwhm_nm <= 150):
        raise ValueError(f"fwhm_nm = {fwhm_nm!r}: must lie within 1–150 nm")
    sd = colour.sd_single_led(
        peak_nm, shape=colour.SpectralShape(380, 780, 1), half_spectral_width=fwhm_nm / _ohno_half_width_factor()
    )
    return Spectrum.from_sd(
        sd,
        quantity="relative_power",
        source=f"Ohno (2005) single-LED model (colour.sd_single_led), peak {peak_nm:g} nm, FWHM {fwhm_nm:g} nm",
    )


# ----------------------------------------------------------------------------- interference filters


def et_bandpass(center_nm: float, bandwidth_nm: float) -> InterferenceBandpass:
    """A hard-coated (sputtered, Chroma ET / Semrock BrightLine class) band-pass filter.

    center_nm, bandwidth_nm: nominal centre and 50 % full width at normal incidence, nm.
    Assumed, typical of such filters (vendors' application notes): mean effective index 1.9 for
    both edges; s and p split by ±0.1 so that the s passband narrows and the p passband widens
    with angle (Macleod, Thin-Film Optical Filters); 3-nm 10–90 % edges; 95 % in band;
    blocking OD 5 outside the band.
    """
    return InterferenceBandpass(
        short_edge_nm=center_nm - bandwidth_nm / 2,
        long_edge_nm=center_nm + bandwidth_nm / 2,
        n_eff_short_s=2.0,
        n_eff_short_p=1.8,
        n_eff_long_s=1.8,
        n_eff_long_p=2.0,
        edge_width_nm=3.0,
        peak_transmittance=0.95,
        blocking_od=5.0,
    )


# ----------------------------------------------------------------------------- absorption film

_WRATTEN_MAX_ABSORBANCE = 6.0  # decadic, in the blue, for the 0.1-mm gel
_WRATTEN_REFERENCE_MM = 0.1
_WRATTEN_TAIL_NM = 10.0  # decay length of the absorption tail towards the red


def wratten12_film(
    cut_on_nm: float = 515.0, thickness_mm: float = 0.1, refractive_index: float = GELATIN_INDEX
) -> AbsorptionFilm:
    """A yellow (minus-blue) gel film of the Kodak Wratten no. 12 class.

    cut_on_nm: wavelength of 50 % transmittance (faces included) at normal incidence, nm.
    thickness_mm: film thickness, mm. refractive_index: gelatin base index.

    The dye's decadic absorption coefficient is α(λ) = (A_max / 0.1 mm) · σ((λ_e − λ) / τ): it
    saturates at optical density A_max = 6 per 0.1 mm in the blue (the gel is opaque below
    ≈ 490 nm) and falls off exponentially towards the red with decay length τ = 10 nm (an
    Urbach-like dye tail). With a 515–520-nm cut-on this reproduces the published Wratten 12
    edge: ≈ 1 % at 22 nm, ≈ 10 % at 13 nm below the 50 % point, ≈ 80 % 15 nm above it, and a
    ≈ 91 % plateau set by the two gelatin faces. λ_e is placed so that this film,
    at this thickness, transmits 50 % at ``cut_on_nm``: a thicker film with the same cut-on
    therefore blocks deeper and has a steeper edge.
    """
    if not (math.isfinite(cut_on_nm) and 400 <= cut_on_nm <= 700):
        raise ValueError(f"cut_on_nm = {cut_on_nm!r}: must lie within 400–700 nm")
    if not (math.isfinite(thickness_mm) and 0 < thickness_mm <= 10):
        raise ValueError(f"thickness_mm = {thickness_mm!r}: must lie within 0–10 mm (> 0)")
    internal = 0.5 / fresnel_transmittance(0.0, refractive_index) ** 2
    alpha_max = _WRATTEN_MAX_ABSORBANCE / _WRATTEN_REFERENCE_MM  # 1/mm
    fraction = -math.log10(internal) / (alpha_max * thickness_mm)
    if fraction >= 1.0:
        raise ValueError(
            f"thickness_mm = {thickness_mm}: too thin for this dye to reach 50 % transmittance "
            f"(needs > {thickness_mm * fraction:.4f} mm)"
        )
    edge_nm = cut_on_nm + _WRATTEN_TAIL_NM * float(logit(fraction))
    wavelength = DEFAULT_WAVELENGTH_NM
    alpha = alpha_max * expit((edge_nm - wavelength) / _WRATTEN_TAIL_NM)
    coefficient = Spectrum(
        wavelength,
        alpha,
        quantity="absorption_coefficient_per_mm",
        source=(
            f"Wratten no. 12 class dye model: decadic alpha = {alpha_max:g}/mm * logistic((lambda_e - lambda)/"
            f"{_WRATTEN_TAIL_NM:g} nm), lambda_e = {edge_nm:.2f} nm"
        ),
    )
    return AbsorptionFilm(coefficient, thickness_mm, refractive_index)


# ----------------------------------------------------------------------------- fluorophore


def _log_normal_band(wavenumber: np.ndarray, peak: float, fwhm: float, asymmetry: float) -> np.ndarray:
    """Siano & Metzler (1969) log-normal band in wavenumber (cm⁻¹), peak 1; asymmetry ≠ 0."""
    x = 1.0 + 2.0 * asymmetry * (wavenumber - peak) / fwhm
    out = np.zeros_like(wavenumber)
    ok = x > 0
    out[ok] = np.exp(-math.log(2.0) * (np.log(x[ok]) / asymmetry) ** 2)
    return out


_VIBRONIC_CM = 1300.0  # spacing of the 0-0 and 0-1 vibronic bands of the GFP chromophore, cm⁻¹


def egfp_emission() -> Spectrum:
    """Relative emission (power per nm, peak 1) of a green fluorophore of the EGFP/fluorescein class.

    Two log-normal bands (Siano & Metzler, J. Chem. Phys. 51, 1856 (1969)) in wavenumber: the
    0-0 band at 508 nm (FWHM 1250 cm⁻¹) and a vibronic shoulder 1300 cm⁻¹ lower (≈ 544 nm, FWHM
    1800 cm⁻¹, 33 % high), both with a red tail (asymmetry −0.15); converted to power per nm
    (× 1/λ²). Peak ≈ 510 nm, half maximum ≈ 495–530 nm, as EGFP (FPbase) and fluorescein.
    """
    wavelength = DEFAULT_WAVELENGTH_NM
    nu = 1e7 / wavelength
    nu0 = 1e7 / 508.0
    bands = _log_normal_band(nu, nu0, 1250.0, -0.15) + 0.33 * _log_normal_band(nu, nu0 - _VIBRONIC_CM, 1800.0, -0.15)
    values = bands / wavelength**2
    return Spectrum(
        wavelength,
        values / values.max(),
        quantity="relative_emission",
        source="EGFP/fluorescein class emission: log-normal 0-0 band at 508 nm + vibronic shoulder at -1300 cm-1 (Siano & Metzler 1969)",
    )


def egfp_emission_band_nm(level: float = 0.1) -> tuple[float, float]:
    """(low, high) wavelengths, nm, between which :func:`egfp_emission` exceeds ``level`` (0–1) of
    its peak: the band an emission filter must pass (≈ 484–578 nm at 10 %)."""
    spectrum = egfp_emission()
    above = spectrum.wavelength_nm[spectrum.values >= level]
    return float(above.min()), float(above.max())


def egfp_excitation() -> Spectrum:
    """Relative excitation (absorption) spectrum, peak 1, of the EGFP/fluorescein class.

    The mirror image of :func:`egfp_emission` about the 0-0 transition: a log-normal band at
    488 nm (FWHM 1250 cm⁻¹, blue tail) with its vibronic shoulder 1300 cm⁻¹ higher (≈ 458 nm,
    33 %), plus the neutral-chromophore band near 400 nm (12 %, FWHM 3000 cm⁻¹) that EGFP keeps.
    """
    wavelength = DEFAULT_WAVELENGTH_NM
    nu = 1e7 / wavelength
    nu0 = 1e7 / 488.0
    values = (
        _log_normal_band(nu, nu0, 1250.0, 0.15)
        + 0.33 * _log_normal_band(nu, nu0 + _VIBRONIC_CM, 1800.0, 0.15)
        + 0.12 * _log_normal_band(nu, 1e7 / 400.0, 3000.0, 0.1)
    )
    return Spectrum(
        wavelength,
        values / values.max(),
        quantity="relative_excitation",
        source="EGFP/fluorescein class excitation: log-normal band at 488 nm + vibronic shoulder at +1300 cm-1 + 400-nm band (mirror of the emission model)",
    )


# ----------------------------------------------------------------------------- sensor

# Absorption coefficient of crystalline silicon at 300 K, 1/cm: Green & Keevers, Prog.
# Photovolt. 3, 189 (1995) (the PV Education table), interpolated log-linearly.
_SILICON_ALPHA_PER_CM = (
    (380.0, 2.93e5),
    (390.0, 1.50e5),
    (400.0, 9.52e4),
    (450.0, 2.55e4),
    (500.0, 1.11e4),
    (550.0, 6.39e3),
    (600.0, 4.14e3),
    (650.0, 2.81e3),
    (700.0, 1.90e3),
    (750.0, 1.30e3),
    (800.0, 8.50e2),
)


def bsi_silicon_quantum_efficiency(
    epi_thickness_um: float = 3.0, dead_layer_um: float = 0.02, optical_efficiency: float = 0.8
) -> Spectrum:
    """Quantum efficiency of a back-side illuminated silicon pixel (Sony IMX178 class) on 380–780 nm.

    QE(λ) = η · exp(−α d_dead) · (1 − exp(−α d_epi)): light enters through a thin dead layer
    (``dead_layer_um``, µm) whose carriers recombine, and only the epitaxial layer
    (``epi_thickness_um``, µm) collects; ``optical_efficiency`` η lumps the anti-reflection
    coating and the micro-lens fill. α(λ): silicon at 300 K (Green & Keevers 1995). The
    defaults give a peak QE ≈ 0.76 near 450–500 nm, as published for STARVIS-class sensors.
    """
    for name, value, low, high in (
        ("epi_thickness_um", epi_thickness_um, 0.1, 50.0),
        ("dead_layer_um", dead_layer_um, 0.0, 1.0),
        ("optical_efficiency", optical_efficiency, 0.01, 1.0),
    ):
        if not (math.isfinite(value) and low <= value <= high):
            raise ValueError(f"{name} = {value!r}: must lie within {low:g}–{high:g}")
    table = np.array(_SILICON_ALPHA_PER_CM)
    wavelength = DEFAULT_WAVELENGTH_NM
    alpha_per_um = 10 ** np.interp(wavelength, table[:, 0], np.log10(table[:, 1])) * 1e-4
    qe = optical_efficiency * np.exp(-alpha_per_um * dead_layer_um) * (1 - np.exp(-alpha_per_um * epi_thickness_um))
    return Spectrum(
        wavelength,
        qe,
        quantity="quantum_efficiency",
        source=(
            f"BSI silicon pixel model: QE = {optical_efficiency:g} * exp(-alpha*{dead_layer_um:g} um) * "
            f"(1 - exp(-alpha*{epi_thickness_um:g} um)), alpha of Si from Green & Keevers (1995)"
        ),
    )


# ----------------------------------------------------------------------------- the library

_MODELS: dict[str, tuple[str, Callable[[], Spectrum]]] = {
    "led-lxml-pb01-0040": ("led_lxml_pb01_0040.csv", lambda: led_spectrum(470.0, 25.0)),
    "excitation-filter-470-40": (
        "excitation_filter_470_40.csv",
        lambda: et_bandpass(470.0, 40.0).spectrum(
            source="Chroma 470/40 (ET class), 0 deg: " + et_bandpass(470.0, 40.0).describe()
        ),
    ),
    "emission-filter-535-50": (
        "emission_filter_535_50.csv",
        lambda: et_bandpass(535.0, 50.0).spectrum(
            source="Chroma 535/50 (ET class), 0 deg: " + et_bandpass(535.0, 50.0).describe()
        ),
    ),
    "wratten-12": ("wratten_12.csv", lambda: wratten12_film(515.0, 0.1).spectrum()),
    "gfp-excitation": ("gfp_excitation.csv", egfp_excitation),
    "gfp-emission": ("gfp_emission.csv", egfp_emission),
    "imx178-qe": ("imx178_qe.csv", bsi_silicon_quantum_efficiency),
}


def available_spectra() -> list[str]:
    """Names of the shipped curves."""
    return list(_MODELS)


def load_spectrum(name: str) -> Spectrum:
    """A shipped curve by name (see :func:`available_spectra`), read from the package data."""
    if name not in _MODELS:
        raise ValueError(f"spectrum = {name!r}: unknown; available: {', '.join(_MODELS)}")
    resource = resources.files("cm2optics.spectra") / "data" / _MODELS[name][0]
    with resources.as_file(resource) as path:
        return read_spectrum_csv(path)


def library_spectra() -> dict[str, Spectrum]:
    """Every shipped curve computed afresh from its model (what :func:`write_library` writes)."""
    return {name: make() for name, (_, make) in _MODELS.items()}


def write_library(folder: str | Path) -> list[Path]:
    """Write every curve of the library as CSV into ``folder`` (atomically); return the paths."""
    folder = Path(folder)
    return [write_spectrum_csv(spectrum, folder / _MODELS[name][0]) for name, spectrum in library_spectra().items()]


if __name__ == "__main__":  # pragma: no cover - maintenance entry point
    for target in sys.argv[1:] or ["cm2optics/spectra/data"]:
        for path in write_library(target):
            print(path)
