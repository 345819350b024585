"""`calibrate_scan` end to end on traced scans: `cm2 psf simulate`'s path (the default Gaussian
pinhole) on a design with an undeclared as-built effect, a realistic sensor added (shot noise at
the scan's gain, 2-count read noise, 100-count dark level, 12-bit clipping), then the loop against
the nominal design. Slow: three small scans (3 × 3 × 2 at 8× binning) are traced."""

from __future__ import annotations

import numpy as np
import pytest

from cm2optics.calibrate.noise import add_scan_noise
from cm2optics.calibrate.scan import calibrate_scan
from cm2optics.emission.psf import PSFSettings
from cm2optics.emission.scan import ScanSettings, calibration_grid_mm, simulate_scan

pytestmark = pytest.mark.slow

INJECTED = {
    "rotation": {"as_built.mla_rotation_deg": 0.5},
    "transmission": {"as_built.lenslet_transmission": [1, 1, 1, 1, 1, 1, 1, 1, 0.6]},
    "clean": {},
}


@pytest.fixture(scope="module", params=list(INJECTED))
def calibration(request, v2, tmp_path_factory):
    folder = tmp_path_factory.mktemp(request.param)
    built = v2.with_changes(INJECTED[request.param]) if INJECTED[request.param] else v2
    positions = calibration_grid_mm(v2, (3, 3, 2))
    settings = ScanSettings(psf=PSFSettings(binning=8))
    simulate_scan(built, positions, folder / "clean", settings, workers=1, processes=False, progress=False)
    scan = add_scan_noise(folder / "clean", folder / "scan", read_noise_counts=2.0, dark_level=100.0, seed=3)
    return request.param, calibrate_scan(scan, v2).document


def test_the_undeclared_effect_is_named_measured_and_explains_the_residual(calibration):
    case, doc = calibration
    names = [(e["name"], e["parameters"].get("lenslet")) for e in doc["effects"]]
    expected = {"rotation": [("mla_rotation", None)], "transmission": [("lenslet_transmission", 8)], "clean": []}
    assert names == expected[case], doc["effects"]
    if case == "rotation":
        assert doc["effects"][0]["parameters"]["angle_deg"] == pytest.approx(0.5, abs=0.05)
    if case == "transmission":
        assert doc["effects"][0]["parameters"]["transmission"] == pytest.approx(0.6, abs=0.03)
    if case != "clean":
        assert doc["nmse_after"] * 5 <= doc["nmse_before"] or doc["chi2_after"] <= 1.2
    assert doc["chi2_after"] <= 1.2
    assert doc["unexplained"] == []
    assert np.isfinite(doc["nmse_after"]) and doc["warnings"] == []
