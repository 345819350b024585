"""TracerSimulator: the emission tracer driven by effect values written into the design's as-built
section; foci where focus_centres_px says, moved by a rotation and by the frame offset."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cm2optics.calibrate.effects import library
from cm2optics.calibrate.tracer import TracerSimulator, design_with, source_for
from cm2optics.design import SystemDesign
from cm2optics.emission.source import AngularProfile, PointSource, ProfileKind, calibration_pinhole

POSITIONS = np.array([[0.0, 0.0, 0.0], [0.5, -0.3, 0.2]])


@pytest.fixture(scope="module")
def simulator(v2: SystemDesign) -> TracerSimulator:
    return TracerSimulator(v2, binning=8)


@pytest.fixture(scope="module")
def nominal(simulator: TracerSimulator) -> np.ndarray:
    return simulator.rates(POSITIONS, {})


def _centroids(images: np.ndarray, centres: np.ndarray, half: int = 3) -> np.ndarray:
    """(N, J, 2) intensity centroids in (2·half + 1)² windows around ``centres`` (row, col px)."""
    out = np.full(centres.shape, np.nan)
    rows, cols = np.mgrid[-half : half + 1, -half : half + 1]
    for n, image in enumerate(images):
        for j, (r, c) in enumerate(centres[n]):
            r0, c0 = round(r), round(c)
            window = image[r0 - half : r0 + half + 1, c0 - half : c0 + half + 1]
            if window.shape == rows.shape and window.sum() > 0:
                out[n, j] = r0 + (window * rows).sum() / window.sum(), c0 + (window * cols).sum() / window.sum()
    return out


def test_protocol_and_mapping(simulator: TracerSimulator, v2: SystemDesign):
    assert simulator.lenslets == 9 and simulator.pixel_um == pytest.approx(19.2)
    assert simulator.shape == (v2.sensor.height_px // 8, v2.sensor.width_px // 8)
    assert all(simulator.supports(e) for e in library(9))
    built = design_with(
        v2,
        {
            "mla_spacing": {"delta_mm": 0.02},
            "mla_rotation": {"angle_deg": 0.4},
            "lenslet_transmission[3]": {"transmission": 0.5},
            "lenslet_decenter[8]": {"dx_mm": 0.01, "dy_mm": 0.0},
            "mla_tilt": {"tilt_x_deg": 0.5, "tilt_y_deg": -0.2},
            "sensor_tilt": {"tilt_x_deg": 0.0, "tilt_y_deg": 1.0},
            "partial_lenslets[+x]": {"border_mm": 0.3},
            "partial_lenslets[-y]": {"border_mm": 0.0},  # absent: no partial cells on −y
        },
        offset_px=(1.0, -2.0),
        pitch_um=19.2,
    )
    assert (built.as_built.mla_tilt_x_deg, built.as_built.mla_tilt_y_deg) == (0.5, -0.2)
    assert (built.as_built.sensor_tilt_x_deg, built.as_built.sensor_tilt_y_deg) == (0.0, 1.0)
    assert [str(side) for side in built.mla.partial_sides] == ["+x"] and built.mla.partial_border_mm == 0.3
    assert built.imaging.mla_to_sensor_mm == pytest.approx(v2.imaging.mla_to_sensor_mm + 0.02)
    assert built.as_built.mla_rotation_deg == 0.4 and built.as_built.transmission(3) == 0.5
    assert built.as_built.lenslet_offset_mm(8) == (0.01, 0.0)
    assert (built.as_built.sensor_offset_x_um, built.as_built.sensor_offset_y_um) == (38.4, -19.2)
    point = PointSource(5.0, AngularProfile(ProfileKind.ISOTROPIC))
    assert source_for({}, point) == point
    profile = source_for({"source_profile": {"falloff_per_rad2": 4.0}}, point).profile
    assert profile.kind is ProfileKind.GAUSSIAN and math.isclose(profile.parameter, math.degrees(0.5))


def test_foci_sit_where_focus_centres_px_says(simulator: TracerSimulator, nominal: np.ndarray):
    assert nominal.shape == (2, *simulator.shape) and nominal.dtype == np.float32
    centres = simulator.focus_centres_px(POSITIONS)
    found = _centroids(nominal, centres)
    lit = np.isfinite(found[..., 0])
    assert lit.sum() >= 14
    assert np.nanmax(np.hypot(*(found - centres)[lit].T)) < 1.0


def test_rotation_and_frame_offset_move_the_foci(simulator: TracerSimulator, nominal: np.ndarray):
    centres = simulator.focus_centres_px(POSITIONS)
    before = _centroids(nominal, centres)
    rotated = _centroids(simulator.rates(POSITIONS, {"mla_rotation": {"angle_deg": 1.0}}), centres)
    # on-axis source: a corner focus moves (1 + m)·√2 mm·sin 1° ≈ 1.4 px along the tangent
    step = rotated[0] - before[0]
    corner = 0  # lenslet (row 0, col 0), at (−1, −1) mm: ccw rotation moves it to +x, −y
    assert step[corner, 1] > 1.0 and step[corner, 0] < -1.0
    assert np.hypot(*step[4]) < 0.2  # the central focus stays
    shifted = simulator.rates(POSITIONS[:1], {}, offset_px=(2.0, -1.0))
    np.testing.assert_allclose(shifted[0, 2:, :-1], nominal[0, :-2, 1:], atol=1e-3 * float(nominal.max()))


def _nmse(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sum((a - b) ** 2) / np.sum(b**2))


def test_moved_foci_equal_a_trace_of_the_moved_design(v2: SystemDesign):
    """Effects that move or dim a lenslet are applied to traced foci (their ePSFs sampled at the
    moved pixel centres): the images equal a fresh trace of the design with the effect, to well
    under 1 % of the effect's own change of the image."""
    from cm2optics.emission.psf import EmissionModel, PSFSettings, add_focus
    from cm2optics.optics import first_order

    source = calibration_pinhole()
    simulator = TracerSimulator(v2, binning=8, source=source)
    positions = np.array([[0.0, 0.0, 0.0], [1.5, -1.0, 0.3], [-2.5, 2.0, -0.4]])
    nominal = simulator.rates(positions, {})
    cases = [
        ({"mla_rotation": {"angle_deg": 0.5}}, (0.0, 0.0)),
        ({"mla_decenter": {"dx_mm": 0.01, "dy_mm": -0.007}}, (0.3, -0.45)),
        (
            {
                "lenslet_pitch": {"delta_mm": 0.004},
                "lenslet_decenter[2]": {"dx_mm": 0.005, "dy_mm": 0.0},
                "lenslet_transmission[4]": {"transmission": 0.6},
            },
            (0.0, 0.0),
        ),
    ]
    for values, offset in cases:
        design = design_with(v2, values, offset, simulator.pixel_um)
        model = EmissionModel(design, source, settings=PSFSettings(binning=8))
        dz = first_order.object_plane_z_mm(design) - first_order.object_plane_z_mm(v2)
        traced = np.zeros_like(nominal)
        for i, (x, y, z) in enumerate(positions):
            for focus in model.foci(np.array([x, y, z + dz])):
                add_focus(traced[i], focus, 1e6)
        fast = simulator.rates(positions, values, offset)
        effect = _nmse(nominal, traced)
        assert effect > 0.1
        assert _nmse(fast, traced) < 2e-3 * effect, values


def test_the_traced_model_images_the_scans_own_source(v2: SystemDesign, tmp_path):
    """A scan made by `cm2 psf simulate` with its default Gaussian pinhole: the simulator built
    from the scan's scan.yaml reproduces its frames (counts per ms) to the rounding of the counts,
    where an isotropic point (the old assumption) differs by far more."""
    from cm2optics.calibrate.scan import scan_source
    from cm2optics.emission.psf import PSFSettings
    from cm2optics.emission.scan import ScanSettings, simulate_scan
    from cm2optics.formats.scan import read_scan

    positions = np.array([[x, 0.0, z] for z in (-0.2, 0.2) for x in (0.0, 2.0)])
    settings = ScanSettings(psf=PSFSettings(binning=8), dark_level=0.0)
    simulate_scan(v2, positions, tmp_path / "scan", settings, workers=1, processes=False, progress=False)
    scan = read_scan(tmp_path / "scan", sensor_pixel_um=v2.sensor.pixel_um)
    source, warnings = scan_source(scan.meta.extra)
    assert warnings == [] and source == calibration_pinhole()
    data = scan.normalised() / (settings.source_photons_per_ms * settings.counts_per_electron / 1e6)
    model = TracerSimulator(v2, binning=8, source=source).rates(scan.positions_mm, {})
    point = TracerSimulator(v2, binning=8).rates(scan.positions_mm, {})
    rounding = _nmse(data, model)
    assert rounding < 1e-4
    assert _nmse(data, point) > 100 * rounding


def test_the_source_profile_effect_multiplies_the_scans_profile():
    pinhole = calibration_pinhole()  # Gaussian, 1/e² half-angle 26°
    narrower = source_for({"source_profile": {"falloff_per_rad2": 2.0}}, pinhole).profile
    expected = math.degrees((math.radians(26.0) ** -2 + 2.0) ** -0.5)
    assert narrower.kind is ProfileKind.GAUSSIAN and math.isclose(narrower.parameter, expected)
    wider = source_for({"source_profile": {"falloff_per_rad2": -2.0}}, pinhole).profile
    assert wider.parameter > 26.0
    lambertian = PointSource(5.0, AngularProfile(ProfileKind.LAMBERTIAN))
    table = source_for({"source_profile": {"falloff_per_rad2": 3.0}}, lambertian).profile
    theta = np.radians([0.0, 20.0, 45.0])
    np.testing.assert_allclose(
        table.relative_intensity(theta), np.cos(theta) * np.exp(-6.0 * theta**2), rtol=2e-3, atol=1e-4
    )


@pytest.mark.slow
def test_a_larger_source_equals_a_trace_of_that_source(v2: SystemDesign):
    """``source_size`` blurs the foci traced with the scan's declared 5-µm pinhole by the extra
    disc's image (no new trace): the images equal a fresh trace with a 60-µm pinhole (what `cm2 psf
    simulate --pinhole-um 60` writes), to well under 1 % of the effect's own change of the image,
    at two depths (the disc's image grows with the magnification there)."""
    from cm2optics.emission.psf import EmissionModel, PSFSettings, add_focus

    declared, found = calibration_pinhole(5.0), calibration_pinhole(60.0)
    simulator = TracerSimulator(v2, binning=8, source=declared)
    positions = np.array([[0.0, 0.0, -0.4], [1.5, -1.0, 0.4]])
    nominal = simulator.rates(positions, {})
    fast = simulator.rates(positions, {"source_size": {"diameter_um": 60.0}})
    model = EmissionModel(v2, found, settings=PSFSettings(binning=8))
    traced = np.zeros_like(nominal)
    for i, position in enumerate(positions):
        for focus in model.foci(position):
            add_focus(traced[i], focus, 1e6)
    effect = _nmse(nominal, traced)
    assert effect > 0.01
    assert _nmse(fast, traced) < 1e-2 * effect


@pytest.mark.slow
def test_traced_rates_over_processes_equal_this_process(v2: SystemDesign):
    """Positions traced by two worker processes (the anchor travelling with them) give the same
    images and focus centres as the same simulator in this process."""
    from cm2optics.calibrate.tracer import submit_rates, traced_rates, tracing_pool

    positions = np.array([[0.0, 0.0, 0.0], [0.5, -0.3, 0.2], [-1.0, 0.8, -0.2]])
    values = {"mla_rotation": {"angle_deg": 0.3}, "lenslet_transmission[4]": {"transmission": 0.7}}
    simulator = TracerSimulator(v2, binning=8, anchor={"mla_rotation": {"angle_deg": 0.2}})
    here, centres_here = traced_rates(simulator, positions, values, with_centres=True)
    there, centres_there = traced_rates(simulator, positions, values, workers=2, chunk=1, with_centres=True)
    assert here.max() > 0
    np.testing.assert_array_equal(there, here)
    np.testing.assert_array_equal(centres_there, centres_here)
    with tracing_pool(2) as pool:  # one position here, the others in the workers, started before the wait
        wait = submit_rates(pool, simulator, positions, values, with_centres=True, here=np.array([1]), chunk=1)
        mixed, centres_mixed = wait()
    np.testing.assert_array_equal(mixed, here)
    np.testing.assert_array_equal(centres_mixed, centres_here)
