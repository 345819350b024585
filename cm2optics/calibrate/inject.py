"""A measured-like scan holding effects nobody declares: the loop's test bench.

:func:`injected_scan` traces a PSF scan (``cm2 psf simulate``'s path,
:func:`cm2optics.emission.scan.simulate_scan`) of a design with extra ``as_built`` values, then
records it through a realistic sensor (:func:`cm2optics.calibrate.noise.add_scan_noise`). The
scan's ``scan.yaml`` says nothing of the injected values: ``cm2 calibrate scan`` against the
nominal design has to find them.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from cm2optics.calibrate.noise import add_scan_noise
from cm2optics.design import SystemDesign
from cm2optics.emission.psf import PSFSettings
from cm2optics.emission.scan import ScanSettings, simulate_scan

__all__ = ["injected_scan"]


def injected_scan(
    design: SystemDesign,
    as_built: dict[str, object],
    positions_mm: np.ndarray,
    out_dir: str | Path,
    *,
    binning: int = 8,
    read_noise_counts: float = 2.0,
    dark_level: float = 100.0,
    seed: int = 0,
) -> Path:
    """Trace ``design`` with ``as_built`` (field → value, e.g. ``{"mla_rotation_deg": 0.5}``) at
    ``positions_mm`` (N, 3; object space, mm) with the default calibration pinhole, binned
    ``binning``×, and write it to ``out_dir`` as a sensor records it: shot noise at the scan's
    gain, ``read_noise_counts`` counts of read noise, a ``dark_level``-count offset, clipping at
    the sensor's bit depth, noise drawn with ``seed``. Returns ``out_dir``."""
    built = design.with_changes({f"as_built.{name}": value for name, value in as_built.items()})
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    settings = ScanSettings(psf=PSFSettings(binning=binning))
    with tempfile.TemporaryDirectory(prefix=".clean-", dir=out_dir.parent) as work:
        clean = Path(work) / "scan"
        simulate_scan(built, positions_mm, clean, settings, workers=1, processes=False, progress=False)
        add_scan_noise(clean, out_dir, read_noise_counts=read_noise_counts, dark_level=dark_level, seed=seed)
    return out_dir
