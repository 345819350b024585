"""Orientation and units: which way the foci move, where they sit, and what the files say."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from cm2optics.emission.psf import EmissionModel, PSFSettings, SensorGrid
from cm2optics.emission.scan import ScanSettings, simulate_scan
from cm2optics.emission.source import fluorescent_bead
from cm2optics.formats.scan import read_scan
from cm2optics.optics import first_order


@pytest.fixture(scope="module")
def model(v2):
    return EmissionModel(v2, fluorescent_bead(0.0), settings=PSFSettings(binning=2))


def _centres(model, position):
    return {f.lenslet: np.array(f.centroid_px()) for f in model.foci(position)}


@pytest.mark.parametrize("axis", [0, 1])
def test_a_source_moved_plus_x_or_y_moves_every_focus_the_inverted_way(model, v2, axis):
    step = 0.2
    a = np.zeros(3)
    b = np.zeros(3)
    b[axis] = step
    before, after = _centres(model, a), _centres(model, b)
    assert set(before) == set(after) and len(before) == 9
    expected_px = (
        -first_order.magnification(v2) * step * 1000 / (v2.sensor.pixel_um * model.grid.binning)
    )  # inverted image
    for k in before:
        shift = after[k] - before[k]  # (row, col)
        along, across = (shift[1], shift[0]) if axis == 0 else (shift[0], shift[1])
        assert along == pytest.approx(expected_px, rel=0.1), (k, shift)
        assert abs(across) < 0.05 * abs(expected_px)


def test_foci_sit_where_the_lenslets_are(model, v2):
    centres = _centres(model, (0.0, 0.0, 0.0))
    grid = model.grid
    for cell in model.optics.lenslets:
        row, col = centres[cell.index]
        # An on-axis source images through a lenslet at (1 + m) × its offset from the axis.
        assert float(grid.x_mm(col)) == pytest.approx((1 + first_order.magnification(v2)) * cell.vertex_x_mm, abs=0.03)
        assert float(grid.y_mm(row)) == pytest.approx((1 + first_order.magnification(v2)) * cell.vertex_y_mm, abs=0.03)
    # View disparity ≈ 640–660 sensor pixels (the authors' crops are ≈ 645 px apart).
    disparity_px = (centres[5][1] - centres[4][1]) * grid.binning
    assert 630 < disparity_px < 670


def test_sensor_grid_maps_pixels_to_millimetres(v2):
    grid = SensorGrid.of(v2, 2)
    assert grid.shape == (v2.sensor.height_px // 2, v2.sensor.width_px // 2)
    assert grid.pitch_mm == pytest.approx(2 * v2.sensor.pixel_um / 1000)
    cols = np.array([0.0, 10.5, 1543.0])
    assert np.allclose(grid.col(grid.x_mm(cols)), cols)
    assert float(grid.x_mm((grid.shape[1] - 1) / 2)) == pytest.approx(0.0, abs=1e-12)  # the axis at the centre
    assert float(grid.x_mm(1)) > float(grid.x_mm(0))  # columns run along +x
    assert float(grid.y_mm(1)) > float(grid.y_mm(0))  # rows run along +y
    with pytest.raises(ValueError, match="binning"):
        SensorGrid.of(v2, 0)


def test_scan_files_carry_documented_units(v2, tmp_path):
    positions = np.array([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    settings = ScanSettings(psf=PSFSettings(binning=8), source=fluorescent_bead(5.0))
    simulate_scan(v2, positions, tmp_path / "scan", settings, workers=1, processes=False, progress=False)
    scan = read_scan(tmp_path / "scan")
    assert scan.meta.pixel_um == pytest.approx(8 * v2.sensor.pixel_um)
    assert scan.meta.binning == 8
    assert scan.meta.bit_depth == v2.sensor.bit_depth
    assert np.allclose(scan.positions_mm, positions)
    assert scan.images.dtype == np.uint16 and scan.images.shape[1:] == SensorGrid.of(v2, 8).shape
    meta = yaml.safe_load((tmp_path / "scan" / "scan.yaml").read_text())
    assert "mm" in meta["position_units"] and "+x" in meta["image_orientation"]
    # The source at x = +1 mm images its central focus left of the one at x = −1 mm.
    grid = SensorGrid.of(v2, 8)
    norm = scan.normalised()
    band = slice(int(grid.row(-0.3)), int(grid.row(0.3)) + 1), slice(int(grid.col(-0.8)), int(grid.col(0.8)) + 1)
    cols = [np.argmax(img[band].sum(axis=0)) for img in norm]
    assert cols[1] < cols[0]
    assert (tmp_path / "scan" / "montage.png").is_file() and (tmp_path / "scan" / "manifest.json").is_file()
