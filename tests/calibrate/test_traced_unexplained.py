"""`calibrate_scan` on traced scans holding an effect outside the library (tests/calibrate/
foreign_effects.py): a ghost of every focus, a scratch on the emission filter. A realistic
sensor is added (shot noise at the scan's gain, 2-count read noise, 100-count dark, 12-bit
clipping). The loop must report an unexplained residual at the right place (the ghost's offset;
the lenslet the scratch dims) without forcing a library effect onto it (the attribution's guard),
and the low-rank correction must lower the error on positions held out of its fit.
Slow: a 3 × 3 × 2 scan at 8× binning is traced, then calibrated."""

from __future__ import annotations

import numpy as np
import pytest
from foreign_effects import filter_scratch, ghost

from cm2optics.calibrate.noise import add_scan_noise
from cm2optics.calibrate.scan import calibrate_scan
from cm2optics.emission.psf import PSFSettings
from cm2optics.emission.scan import ScanSettings, calibration_grid_mm, simulate_scan

pytestmark = pytest.mark.slow

GHOST = {"share": 0.04, "offset_px": (5.0, -3.0), "sigma_px": 1.5}


@pytest.fixture(scope="module")
def clean_scan(v2, tmp_path_factory):
    folder = tmp_path_factory.mktemp("foreign")
    positions = calibration_grid_mm(v2, (3, 3, 2))
    settings = ScanSettings(psf=PSFSettings(binning=8))
    simulate_scan(v2, positions, folder / "clean", settings, workers=1, processes=False, progress=False)
    return folder / "clean"


def _calibrate(v2, injected, folder):
    return calibrate_scan(add_scan_noise(injected, folder / "noisy", read_noise_counts=2.0, seed=5), v2)


def test_a_ghost_is_reported_where_it_is_and_corrected_on_held_out_positions(v2, clean_scan, tmp_path):
    result = _calibrate(v2, ghost(clean_scan, tmp_path / "ghost", **GHOST), tmp_path)
    doc = result.document
    copies = [u for u in doc["unexplained"] if "displaced copy" in u["description"]]
    assert len(copies) == 1, doc["unexplained"]
    assert len(copies[0]["lenslets"]) >= 7 and len(copies[0]["depths_mm"]) == 2
    text = copies[0]["description"].split("at (")[1]
    dr, dc = (float(v) for v in text.split(") px")[0].split(","))
    assert (dr, dc) == pytest.approx(GHOST["offset_px"], abs=1.0)
    _check_correction(doc)


def test_a_filter_scratch_is_left_unexplained_on_the_lenslet_it_dims(v2, clean_scan, tmp_path):
    """The scratch dims lenslet 2 (row 0, column 2) by ≈ 40 % at two source positions and ≈ 5 %
    at two more: no per-lenslet transmission, source profile or vignetting may be fitted to it
    (a transmission would dim the lenslet at all eight positions that see it), and the low-rank
    correction, which learns the loss from the positions beside the held-out ones, lowers the error."""
    injected, loss = filter_scratch(
        clean_scan, tmp_path / "scratch", v2, x0_mm=1.625, width_mm=0.35, y_range_mm=(-1.9, -1.15)
    )
    assert list(np.flatnonzero(loss.max(axis=0) > 0)) == [2]
    doc = _calibrate(v2, injected, tmp_path).document
    assert doc["effects"] == [], doc["effects"]
    assert [u["lenslets"] for u in doc["unexplained"]] == [[2]], doc["unexplained"]
    assert "energy" in doc["unexplained"][0]["description"]
    _check_correction(doc)


def _check_correction(doc):
    correction = doc["correction"]
    assert correction["physical"] is False and "non-physical" in correction["label"]
    held = correction["held_out"]
    floor = held["nmse_noise_floor"]
    assert held["nmse_after"] - floor < 0.85 * (held["nmse_before"] - floor), held
