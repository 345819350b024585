"""Spectra and filter models: the spectral physics every stage shares (no ray tracing here; the
emission path's angles of incidence and its signal-to-background ratio are computed by
:mod:`cm2optics.emission.filter_angles` and :mod:`cm2optics.emission.sbr`, which trace rays).

* :mod:`~cm2optics.spectra.spectrum` — the :class:`Spectrum` type (colour-science based), CSV I/O;
* :mod:`~cm2optics.spectra.library` — the shipped curves by name and the models that made them;
* :mod:`~cm2optics.spectra.interference` — band-pass filters whose edges shift with angle;
* :mod:`~cm2optics.spectra.absorption` — Beer–Lambert films;
* :mod:`~cm2optics.spectra.fit` — fit the band-pass model to a vendor's angle-resolved curves;
* :mod:`~cm2optics.spectra.chain` — the design's excitation and emission filter chains;
* :mod:`~cm2optics.reports.spectra` — plots and figures for ``cm2 spectra report`` and ``cm2 demo``.

Wavelengths in nm, angles in degrees in files and radians (``_rad``) in code.
"""

from cm2optics.spectra.absorption import AbsorptionFilm, beer_lambert_transmittance, fresnel_transmittance
from cm2optics.spectra.chain import EmissionChain, emission_chain, excitation_spectrum
from cm2optics.spectra.fit import band_edges_nm, fit_filter_models, predict_edges_nm, read_filter_table
from cm2optics.spectra.interference import InterferenceBandpass, Polarisation, angle_shifted_wavelength_nm
from cm2optics.spectra.library import available_spectra, load_spectrum
from cm2optics.spectra.spectrum import Normalisation, Spectrum, read_spectrum_csv, write_spectrum_csv

__all__ = [
    "AbsorptionFilm",
    "EmissionChain",
    "InterferenceBandpass",
    "Normalisation",
    "Polarisation",
    "Spectrum",
    "angle_shifted_wavelength_nm",
    "available_spectra",
    "band_edges_nm",
    "beer_lambert_transmittance",
    "emission_chain",
    "excitation_spectrum",
    "fit_filter_models",
    "fresnel_transmittance",
    "load_spectrum",
    "predict_edges_nm",
    "read_filter_table",
    "read_spectrum_csv",
    "write_spectrum_csv",
]
