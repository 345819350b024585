"""The 3D-LSV model built from an emission-module scan against brute-force traced emitters, beside
the depth-wise LSI baseline (issue 6; the full-size version is benchmarks/bench_lsv_vs_traced.py).

A tiny end-to-end run: a 3 × 3 × 3 scan of the cm2-v2 emission path (binned 8×, ±2 mm, ±0.1 mm,
isotropic 2-µm beads as the calibration source), the model built from the scan folder exactly as
``cm2 lsv build`` does, and single emitters traced by the emission module: on the axis the two
models share the on-axis PSF and agree; 2 mm off axis, between calibration depths, the LSV model
must be much closer to the traced image than the LSI baseline (which keeps the on-axis PSF, its
nine foci and the in-focus magnification everywhere).
"""

from __future__ import annotations

import numpy as np
import pytest

from cm2optics.emission.image import render_emitters
from cm2optics.emission.psf import PSFSettings
from cm2optics.emission.scan import ScanSettings, calibration_grid_mm, simulate_scan
from cm2optics.emission.source import fluorescent_bead
from cm2optics.formats.emitters import Emitters
from cm2optics.lsv.build import build_model
from cm2optics.lsv.lsi import lsi_model
from cm2optics.lsv.validate import image_errors
from cm2optics.optics import first_order

BINNING = 8
DIAMETER_UM = 2.0


@pytest.fixture(scope="module")
def built(v2, tmp_path_factory):
    folder = tmp_path_factory.mktemp("traced") / "scan"
    points = calibration_grid_mm(v2, (3, 3, 3), field_mm=4.0, depth_mm=0.2)
    settings = ScanSettings(psf=PSFSettings(binning=BINNING), source=fluorescent_bead(DIAMETER_UM))
    simulate_scan(v2, points, folder, settings, workers=1, processes=False, progress=False)
    return build_model(folder, rank=16, design=v2)


def _traced(design, x_mm: float, y_mm: float, z_mm: float) -> np.ndarray:
    emitters = Emitters.from_positions_um(
        np.array([[x_mm, y_mm, z_mm]]) * 1000.0, np.array([DIAMETER_UM]), np.array([1.0])
    )
    return render_emitters(design, emitters, PSFSettings(binning=BINNING))


def _model(model, x_mm: float, y_mm: float, z_mm: float) -> np.ndarray:
    emitters = Emitters(*(np.array([v]) for v in (x_mm * 1000, y_mm * 1000, z_mm * 1000, DIAMETER_UM, 1.0)))
    return model.forward_sparse(emitters, subpixel_steps=None).astype(np.float64)


def test_lsv_beats_the_lsi_baseline_off_axis_against_traced_emitters(built, v2):
    model = built.model
    lsi = lsi_model(model)
    assert model.provenance["geometry"]["magnification_at_focus"] == pytest.approx(
        abs(first_order.magnification(v2)), rel=0.03
    )
    # the model's unit: the total of the in-focus on-axis source's image
    reference = _traced(v2, 0.0, 0.0, 0.0)
    unit = reference.sum()
    on_axis = {
        name: image_errors(_model(m, 0.0, 0.0, 0.0), reference / unit) for name, m in (("lsv", model), ("lsi", lsi))
    }
    assert on_axis["lsv"]["error"] == pytest.approx(on_axis["lsi"]["error"], rel=0.05)
    assert on_axis["lsv"]["flux_ratio"] == pytest.approx(1.0, abs=0.02)
    assert on_axis["lsv"]["error"] < 0.5  # the floor: undersampled foci interpolated to sub-pixel positions

    traced = _traced(v2, 2.0, 0.3, 0.05) / unit  # off the axis, between calibration depths and rows
    lsv = image_errors(_model(model, 2.0, 0.3, 0.05), traced)
    baseline = image_errors(_model(lsi, 2.0, 0.3, 0.05), traced)
    assert lsv["error"] < 0.7
    assert baseline["error"] > 1.5 * lsv["error"]
    assert abs(lsv["flux_ratio"] - 1.0) < 0.1 < abs(baseline["flux_ratio"] - 1.0)  # vignetting: LSV only
