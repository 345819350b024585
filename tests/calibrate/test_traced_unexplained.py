"""`calibrate_scan` on traced scans holding an effect outside the library (tests/calibrate/
foreign_effects.py): a ghost of every focus. A realistic sensor is added (shot noise at the
scan's gain, 2-count read noise, 100-count dark, 12-bit clipping). The loop must report an
unexplained residual at the right place with the ghost's offset, and its low-rank correction
must lower the error on positions held out of its fit. (The filter scratch of foreign_effects.py
is not here: on a traced scan the attribution forces lenslet transmissions and other effects onto
it and the signature then names the wrong lenslets; BENCHMARKS.md, issue 14.) Slow: a 3 × 3 × 2
scan at 8× binning is traced, then calibrated."""

from __future__ import annotations

import pytest
from foreign_effects import ghost

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


def _check_correction(doc):
    correction = doc["correction"]
    assert correction["physical"] is False and "non-physical" in correction["label"]
    held = correction["held_out"]
    floor = held["nmse_noise_floor"]
    assert held["nmse_after"] - floor < 0.85 * (held["nmse_before"] - floor), held
