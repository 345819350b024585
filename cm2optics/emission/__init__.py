"""The emission path: point sources → emission filter → MLA → film → sensor, with diffraction.

* :mod:`~cm2optics.emission.optics` — the path's surfaces, apertures and housing bore, from a design;
* :mod:`~cm2optics.emission.spectral` — wavelength bands and each ray's spectral weight
  (fluorophore × interference filter at its angle × film × sensor QE);
* :mod:`~cm2optics.emission.source` — point sources: pinhole diameter and angular profile;
* :mod:`~cm2optics.emission.trace` — the exact, vectorised ray trace (Dr.Jit float64 kernels;
  the housing as a Mitsuba scene, :mod:`~cm2optics.emission.housing`);
* :mod:`~cm2optics.emission.wavefront` — traced wavefront → PSF (Debye integral by FFT; a
  geometric branch for many-wave aberrations);
* :mod:`~cm2optics.emission.psf` — one source position → its foci on the (binned) sensor;
* :mod:`~cm2optics.emission.analysis` — magnification, shear, focus quality, vignetting;
* :mod:`~cm2optics.emission.scan` — synthetic PSF calibration scans (Dask, resumable);
* :mod:`~cm2optics.emission.image` — brute-force measurements of a few emitters;
* :mod:`~cm2optics.reports.emission` and :mod:`~cm2optics.cli.psf` — ``cm2 demo`` section, ``cm2 psf``.

Mitsuba and Dr.Jit are imported only inside this subpackage, :mod:`cm2optics.illumination` and
the variant choice both share, :mod:`~cm2optics.optics.backend`.
"""

from cm2optics.emission.optics import EmissionOptics, emission_optics
from cm2optics.emission.psf import EmissionModel, Focus, PSFSettings, Pupil, SensorGrid
from cm2optics.emission.scan import ScanSettings, calibration_grid_mm, simulate_scan
from cm2optics.emission.source import AngularProfile, PointSource, ProfileKind, calibration_pinhole, fluorescent_bead
from cm2optics.emission.spectral import SpectralBands, spectral_bands
from cm2optics.optics import backend as backend  # noqa: F401  (sets DRJIT_LIBLLVM_PATH first)

__all__ = [
    "AngularProfile",
    "EmissionModel",
    "EmissionOptics",
    "Focus",
    "PSFSettings",
    "PointSource",
    "ProfileKind",
    "Pupil",
    "ScanSettings",
    "SensorGrid",
    "SpectralBands",
    "calibration_grid_mm",
    "calibration_pinhole",
    "emission_optics",
    "fluorescent_bead",
    "simulate_scan",
    "spectral_bands",
]
