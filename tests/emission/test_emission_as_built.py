"""The emission tracer honours the design's as-built section: foci of a decentred, rotated or
rescaled array move by the first-order amounts, a lenslet's transmission scales its focus, the
sensor offset shifts the pixel grid, the vignetting delta cuts off-axis light; tilts are refused."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cm2optics.design import SystemDesign
from cm2optics.emission.psf import EmissionModel, PSFSettings
from cm2optics.emission.source import fluorescent_bead
from cm2optics.errors import UserError
from cm2optics.optics import first_order

SETTINGS = PSFSettings(binning=8, band_nm=50.0)


def _foci(design: SystemDesign, position=(0.0, 0.0, 0.0)) -> dict[tuple[int, int], object]:
    """Full lenslets' foci by (row, col)."""
    model = EmissionModel(design, fluorescent_bead(0.0), settings=SETTINGS)
    out = {}
    for focus in model.foci(position):
        lenslet = model.optics.lenslets[focus.lenslet]
        if not lenslet.partial:
            out[(lenslet.row, lenslet.col)] = focus
    return out


@pytest.fixture(scope="module")
def nominal(v2: SystemDesign):
    return _foci(v2)


def test_decentred_array_moves_the_foci_by_one_plus_m(v2: SystemDesign, nominal):
    d = (0.05, -0.03)
    moved = _foci(v2.with_changes({"as_built.mla_decenter_x_mm": d[0], "as_built.mla_decenter_y_mm": d[1]}))
    m = first_order.magnification(v2)
    for key in ((1, 1), (0, 1), (1, 2)):
        shift = np.subtract(moved[key].ray_centroid_mm, nominal[key].ray_centroid_mm)
        np.testing.assert_allclose(shift, (1 + m) * np.array(d), rtol=0.03)


def test_rotation_and_pitch_move_the_lattice(v2: SystemDesign, nominal):
    rotated = _foci(v2.with_changes({"as_built.mla_rotation_deg": 1.0}))
    for key in ((1, 0), (1, 2), (0, 1)):
        a0 = math.atan2(*nominal[key].ray_centroid_mm[::-1])
        a1 = math.atan2(*rotated[key].ray_centroid_mm[::-1])
        assert math.isclose(math.degrees(a1 - a0), 1.0, abs_tol=0.02)
    delta = 0.02
    scaled = _foci(v2.with_changes({"as_built.lenslet_pitch_delta_mm": delta}))
    scale = (v2.mla.pitch_mm + delta) / v2.mla.pitch_mm
    for key in ((1, 0), (0, 0), (2, 2)):
        np.testing.assert_allclose(
            scaled[key].ray_centroid_mm, scale * np.array(nominal[key].ray_centroid_mm), atol=1e-3
        )


def test_transmission_scales_one_focus_and_sensor_offset_shifts_the_grid(v2: SystemDesign, nominal):
    dimmed = _foci(v2.with_changes({"as_built.lenslet_transmission": [1, 1, 1, 1, 1, 0.4, 1, 1, 1]}))
    for key, focus in nominal.items():
        expected = 0.4 if key == (1, 2) else 1.0
        assert math.isclose(dimmed[key].energy / focus.energy, expected, rel_tol=1e-6)
    offset_um = (38.4, -19.2)  # the sensor moves +x, −y: the image moves −2, +1 binned pixels (19.2 µm)
    shifted = _foci(
        v2.with_changes({"as_built.sensor_offset_x_um": offset_um[0], "as_built.sensor_offset_y_um": offset_um[1]})
    )
    pitch_um = v2.sensor.pixel_um * SETTINGS.binning
    for key in ((1, 1), (0, 2)):
        (r0, c0), (r1, c1) = nominal[key].centroid_px(), shifted[key].centroid_px()
        assert math.isclose(c1 - c0, -offset_um[0] / pitch_um, abs_tol=0.05)
        assert math.isclose(r1 - r0, -offset_um[1] / pitch_um, abs_tol=0.05)
        assert shifted[key].ray_centroid_mm == pytest.approx(nominal[key].ray_centroid_mm)


def test_narrower_vignetting_aperture_cuts_off_axis_light(v2: SystemDesign):
    position = (2.5, 0.0, 0.0)
    nominal = sum(f.energy for f in _foci(v2, position).values())
    narrower = sum(
        f.energy for f in _foci(v2.with_changes({"as_built.vignetting_radius_delta_mm": -0.4}), position).values()
    )
    assert narrower < 0.95 * nominal


def test_tilts_are_recorded_but_not_traced(v2: SystemDesign):
    tilted = v2.with_changes({"as_built.sensor_tilt_x_deg": 0.5})
    assert tilted.as_built.sensor_tilt_x_deg == 0.5
    with pytest.raises(UserError, match="as_built.sensor_tilt_x_deg = 0.5: .*not yet traced"):
        EmissionModel(tilted, fluorescent_bead(0.0), settings=SETTINGS)


def test_scan_applies_the_sensor_side_effects(v2: SystemDesign, tmp_path):
    from cm2optics.emission.scan import ScanSettings, simulate_scan
    from cm2optics.formats.scan import read_scan

    settings = ScanSettings(psf=SETTINGS, source=fluorescent_bead(5.0))
    built = v2.with_changes(
        {
            "as_built.leakage_counts_per_ms": 3.0,
            "as_built.pixel_crosstalk_fraction": 0.3,
            "as_built.stray_light_fraction": 0.2,
        }
    )
    images = {}
    for name, design in (("nominal", v2), ("built", built)):
        simulate_scan(design, np.zeros((1, 3)), tmp_path / name, settings, workers=1, processes=False, progress=False)
        images[name] = read_scan(tmp_path / name).normalised()[0]
    nominal, measured = images["nominal"], images["built"]
    assert np.median(nominal) == 0.0
    assert math.isclose(float(np.median(measured)), 3.0, abs_tol=0.1)  # leakage: counts per ms on every pixel
    peak = np.unravel_index(np.argmax(nominal), nominal.shape)
    # crosstalk and the halo take light from the brightest pixel of each focus into its neighbours
    assert _peak_share(measured, peak, 3.0) < 0.9 * _peak_share(nominal, peak, 0.0)


def _peak_share(image: np.ndarray, peak: tuple[int, int], background: float) -> float:
    """The brightest pixel's share of its 3 × 3 neighbourhood, background removed."""
    r, c = peak
    window = image[r - 1 : r + 2, c - 1 : c + 2] - background
    return float(window[1, 1] / window.sum())
