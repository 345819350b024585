"""The calibration loop on the analytic CM²-like model: residual analysis, bad data, attribution.

Data are simulated with a realistic sensor (Poisson shot noise at 1 e⁻/count, 2-count read noise,
a 100-count dark offset, 12-bit clipping, per-image exposures that fill the brightest pixel),
with effects injected that the tool is not told about.
"""

from __future__ import annotations

import numpy as np
import pytest

from cm2optics.calibrate.attribute import Problem, attribute
from cm2optics.calibrate.effects import apply_image_effects, leakage_counts, library
from cm2optics.calibrate.noise import raw_frames
from cm2optics.calibrate.residual import CalibrationError, ScanData, analyse_scan
from cm2optics.calibrate.simulate import AnalyticSimulator

DARK = 100.0
READ_NOISE = 2.0


@pytest.fixture(scope="module")
def positions() -> np.ndarray:
    grid = np.linspace(-1.5, 1.5, 3)
    return np.array([[x, y, z] for z in (-0.3, 0.3) for y in grid for x in grid])


def measured(simulator, positions, values=None, seed=0, peak=3000.0):
    """Raw 12-bit frames of the simulator with ``values`` (effects), and their exposures."""
    values = values or {}
    rng = np.random.default_rng(seed)
    rate = apply_image_effects(simulator.rates(positions, values), values, simulator.pixel_um)
    exposure = np.round(peak / rate.reshape(len(rate), -1).max(axis=1), 2)
    signal = rate * exposure[:, None, None] + leakage_counts(values, exposure)[:, None, None]
    return raw_frames(signal + DARK, DARK, 1.0, READ_NOISE, 12, rng), exposure


def _data(counts, exposure, positions):
    return ScanData(counts, exposure, positions, tuple(f"psf_{i:03d}.tif" for i in range(len(positions))), 12)


def _analyse(simulator, positions, counts, exposure, **options):
    rate = simulator.rates(positions, {})
    return analyse_scan(
        _data(counts, exposure, positions),
        rate,
        positions,
        simulator.focus_centres_px(positions),
        simulator.pitch_px(),
        **options,
    )


def test_clean_data_sit_at_the_noise_floor(simulator, positions):
    counts, exposure = measured(simulator, positions)
    analysis = _analyse(simulator, positions, counts, exposure)
    doc = analysis.to_dict()
    assert 0.85 < doc["chi2"] < 1.2
    assert analysis.noise.read_noise_counts == pytest.approx(READ_NOISE, rel=0.1)
    assert analysis.noise.counts_per_electron == pytest.approx(1.0, rel=0.2)
    assert analysis.registration.offset_px == pytest.approx((0.0, 0.0), abs=0.03)
    assert analysis.registration.dark_level == pytest.approx(DARK, abs=0.5)
    assert np.nanmean(np.abs(np.array(doc["per_lenslet"]["energy_ratio"]) - 1)) < 0.02
    assert doc["flags"] == {}


def test_registration_recovers_a_frame_offset_flux_and_dark():
    """Smooth (band-limited) blobs moved by a sub-pixel offset, scaled and offset."""
    from cm2optics.calibrate.register import register, shift_images

    rows, cols = np.mgrid[0:96, 0:128]
    centres = [(30.3, 40.7), (60.1, 90.2), (48.0, 20.5)]
    rate = np.stack([np.exp(-((rows - r) ** 2 + (cols - c) ** 2) / (2 * 3.0**2)) for r, c in centres]).astype(
        np.float32
    )
    exposure = np.array([2.0, 3.0, 4.0])
    truth = shift_images(rate, (0.37, -0.61)) * 1.7 * exposure[:, None, None] + 55.0
    registration, model = register(truth, exposure, rate, np.ones(truth.shape, bool))
    assert registration.offset_px == pytest.approx((0.37, -0.61), abs=1e-3)
    assert registration.flux_scale == pytest.approx(1.7, rel=1e-3)
    assert registration.dark_level == pytest.approx(55.0, abs=1e-2)
    np.testing.assert_allclose(model, truth, atol=1e-2)


def test_a_transmission_loss_shows_in_its_lenslets_energy(simulator, positions):
    counts, exposure = measured(simulator, positions, {"lenslet_transmission[4]": {"transmission": 0.6}})
    doc = _analyse(simulator, positions, counts, exposure).to_dict()
    ratio = np.array(doc["per_lenslet"]["energy_ratio"])
    others = np.delete(ratio, 4)
    assert ratio[4] / np.mean(others) == pytest.approx(0.6, abs=0.05)


def test_bad_data_get_a_clear_error_or_a_flag(simulator, positions):
    counts, exposure = measured(simulator, positions)
    rate = simulator.rates(positions, {})
    centres, pitch = simulator.focus_centres_px(positions), simulator.pitch_px()
    with pytest.raises(CalibrationError, match="wrong sensor size"):
        analyse_scan(_data(counts[:, :-8], exposure, positions), rate, positions, centres, pitch)
    with pytest.raises(CalibrationError, match="other positions"):
        analyse_scan(_data(counts, exposure, positions), rate, positions + 0.1, centres, pitch)
    broken = counts.copy()
    broken[2] = 4095  # saturated
    broken[5] = np.round(DARK).astype(np.uint16)  # no light at all
    doc = analyse_scan(_data(broken, exposure, positions), rate, positions, centres, pitch).to_dict()
    assert doc["flags"]["saturated"] == ["psf_002.tif"]
    assert doc["flags"]["empty"] == ["psf_005.tif"]
    assert doc["images_used"] == len(positions) - 2
    assert doc["chi2"] < 1.3  # the bad frames take no part in the fit


def _attribute(simulator, positions, values, seed=0, gain=None):
    counts, exposure = measured(simulator, positions, values, seed=seed)
    problem = Problem(simulator, counts, exposure, positions, np.ones(counts.shape, bool), library(9), gain)
    return attribute(problem)


@pytest.mark.parametrize(
    ("seed", "gain"),
    [(1, None), pytest.param(2, None, marks=pytest.mark.slow), (3, 1.0), (4, 1.0)],  # seed 2: 19 s, for the 20 min
)
def test_clean_data_yield_no_effect(simulator, positions, seed, gain):
    """With the camera's gain given (known noise) or estimated (noise scale profiled out)."""
    result = _attribute(simulator, positions, {}, seed, gain)
    assert result.effects == {}
    assert result.chi2_after < 1.2


@pytest.mark.parametrize("gain", [None, 1.0])
def test_an_undeclared_rotation_is_named_and_measured(simulator, positions, gain):
    result = _attribute(simulator, positions, {"mla_rotation": {"angle_deg": 0.4}}, gain=gain)
    assert list(result.effects) == ["mla_rotation"]
    assert result.effects["mla_rotation"]["angle_deg"] == pytest.approx(0.4, abs=0.05)
    assert result.uncertainties["mla_rotation"]["angle_deg"] < 0.05
    assert result.chi2_before > 2 and result.chi2_after < 1.2


def test_a_derivative_at_the_edge_of_a_range_steps_inward(simulator, positions):
    """A parameter at its upper bound is differentiated backwards, never outside its range."""
    from cm2optics.calibrate.attribute import _columns

    counts, exposure = measured(simulator, positions)
    problem = Problem(simulator, counts, exposure, positions, np.ones(counts.shape, bool), library(9), 1.0)
    state = problem.start()
    state.values["lenslet_transmission[3]"] = {"transmission": 1.5}
    column = _columns(problem, state, [("lenslet_transmission[3]", "transmission")], problem.features(state))
    assert np.isfinite(column).any() and np.nanmax(np.abs(column)) > 0


def test_a_scan_taken_on_another_design_is_refused(simulator, positions):
    """Foci spread 15 % farther than the design's (another magnification): a clear error."""
    from dataclasses import replace

    from cm2optics.calibrate.scan import _check_magnification

    other = AnalyticSimulator(replace(simulator.model, magnification=simulator.model.magnification * 1.4), 0.5)
    counts, exposure = measured(other, positions)
    analysis = _analyse(simulator, positions, counts, exposure)
    with pytest.raises(CalibrationError, match="another design"):
        _check_magnification(analysis)
    same, exposure = measured(simulator, positions)
    _check_magnification(_analyse(simulator, positions, same, exposure))


def test_calibrate_scan_end_to_end(simulator, positions, tmp_path, monkeypatch, v2):
    """The whole `cm2 calibrate scan` loop on a scan file with an undeclared rotation, the
    analytic model standing in for the tracer: effect named, error cut, corrected design saved."""
    import cm2optics.calibrate.scan as calibration
    from cm2optics.design import load_design
    from cm2optics.formats.scan import ScanMeta, write_scan
    from cm2optics.reports.calibrate import write_calibration_report

    counts, exposure = measured(simulator, positions, {"mla_rotation": {"angle_deg": 0.4}})
    extra = {"lenslets": [3, 3], "counts_per_electron": 1.0}
    meta = ScanMeta(pixel_um=simulator.pixel_um, binning=8, bit_depth=12, dark_level=DARK, extra=extra)
    scan = write_scan(tmp_path / "scan", counts, positions, exposure, meta)
    monkeypatch.setattr(calibration, "TracerSimulator", lambda design, **options: simulator)
    result = calibration.calibrate_scan(scan, v2)
    doc = result.document
    assert [e["name"] for e in doc["effects"]] == ["mla_rotation"]
    assert doc["effects"][0]["parameters"]["angle_deg"] == pytest.approx(0.4, abs=0.05)
    assert doc["nmse_after"] < doc["nmse_before"] / 5 and doc["chi2_after"] < 1.3
    assert doc["unexplained"] == []
    report = write_calibration_report(result, tmp_path / "report")
    assert report.is_file() and (tmp_path / "report" / "residual_montage.png").is_file()
    corrected = load_design(tmp_path / "report" / "corrected-design.yaml")
    assert corrected.as_built.mla_rotation_deg == pytest.approx(0.4, abs=0.05)


# ----------------------------------------------------------------------------- the injection matrix
# Every library effect alone at two magnitudes, pairs of effects, clean data: the tool is not told
# what was injected. Tolerances (the documented recovery accuracy on this 18-position scan):
# rotation ± 0.05°, spacing ± 5 µm, decentres ± 5 µm, source half-angle ± 2°, MLA and sensor tilts
# ± 0.05°, partial lenslets' border ± 20 µm, the calibration source's diameter ± 10 µm; the others as given.
# Crosstalk below ≈ 0.1 leaves χ² under the 1.2 floor on this scan (0.05: χ² 1.08) and is not sought.


def _half_angle_deg(falloff_per_rad2: float) -> float:
    return float(np.degrees(1.0 / np.sqrt(falloff_per_rad2)))


#: effect key → (two magnitudes, tolerance per parameter, in the parameter's unit)
SINGLE = {
    "mla_decenter": (
        ({"dx_mm": 0.012, "dy_mm": -0.006}, {"dx_mm": 0.03, "dy_mm": 0.02}),
        {"dx_mm": 0.005, "dy_mm": 0.005},
    ),
    "mla_rotation": (({"angle_deg": 0.15}, {"angle_deg": -0.6}), {"angle_deg": 0.05}),
    "mla_spacing": (({"delta_mm": 0.01}, {"delta_mm": -0.04}), {"delta_mm": 0.005}),
    "lenslet_pitch": (({"delta_mm": 0.002}, {"delta_mm": -0.006}), {"delta_mm": 0.0005}),
    "source_profile": (({"falloff_per_rad2": 5.0}, {"falloff_per_rad2": 20.0}), {"half_angle_deg": 2.0}),
    "stray_light": (
        ({"fraction": 0.05, "width_um": 200.0}, {"fraction": 0.15, "width_um": 500.0}),
        {"fraction": 0.02, "width_um": 100.0},
    ),
    "leakage_background": (({"counts_per_ms": 0.05}, {"counts_per_ms": 0.2}), {"counts_per_ms": 0.01}),
    "pixel_crosstalk": (({"fraction": 0.1}, {"fraction": 0.2}), {"fraction": 0.02}),
    "vignetting": (({"radius_delta_mm": -0.3}, {"radius_delta_mm": -0.6}), {"radius_delta_mm": 0.05}),
    "lenslet_transmission[4]": (({"transmission": 0.85}, {"transmission": 0.6}), {"transmission": 0.03}),
    "lenslet_decenter[2]": (
        ({"dx_mm": 0.01, "dy_mm": 0.0}, {"dx_mm": -0.02, "dy_mm": 0.015}),
        {"dx_mm": 0.005, "dy_mm": 0.005},
    ),
    "mla_tilt": (
        ({"tilt_x_deg": 0.3, "tilt_y_deg": 0.0}, {"tilt_x_deg": -1.0, "tilt_y_deg": 1.5}),
        {"tilt_x_deg": 0.05, "tilt_y_deg": 0.05},
    ),
    "sensor_tilt": (
        ({"tilt_x_deg": 0.0, "tilt_y_deg": 0.3}, {"tilt_x_deg": 0.8, "tilt_y_deg": -1.0}),
        {"tilt_x_deg": 0.05, "tilt_y_deg": 0.05},
    ),
    "partial_lenslets[+x]": (({"border_mm": 0.1}, {"border_mm": 0.4}), {"border_mm": 0.02}),
    "partial_lenslets[-y]": (({"border_mm": 0.2}, {"border_mm": 0.6}), {"border_mm": 0.02}),
    "source_size": (({"diameter_um": 50.0}, {"diameter_um": 150.0}), {"diameter_um": 10.0}),
}
PAIRS = [
    ({"mla_rotation": {"angle_deg": 0.3}, "lenslet_transmission[4]": {"transmission": 0.7}}),
    ({"mla_spacing": {"delta_mm": 0.02}, "stray_light": {"fraction": 0.1, "width_um": 300.0}}),
    ({"source_profile": {"falloff_per_rad2": 10.0}, "leakage_background": {"counts_per_ms": 0.1}}),
    ({"lenslet_decenter[6]": {"dx_mm": 0.015, "dy_mm": -0.01}, "pixel_crosstalk": {"fraction": 0.1}}),
    # the paper's two effects: a narrow source and a column of partial lenslets
    ({"source_profile": {"falloff_per_rad2": 10.0}, "partial_lenslets[+x]": {"border_mm": 0.3}}),
    ({"sensor_tilt": {"tilt_x_deg": 0.5, "tilt_y_deg": 0.0}, "mla_rotation": {"angle_deg": -0.3}}),
    # the calibration pinhole as it may be: narrower in angle and larger than declared (measured in
    # session 14: nothing named — an expected failure until the attribution takes the two together)
    pytest.param(
        {"source_profile": {"falloff_per_rad2": 10.0}, "source_size": {"diameter_um": 80.0}},
        marks=pytest.mark.xfail(strict=True, reason="session 14: neither effect kept (issue 14, round 5)"),
    ),
]


def _check_recovered(result, injected: dict, tolerances: dict) -> None:
    assert sorted(result.effects) == sorted(injected), (result.effects, injected)
    for key, truth in injected.items():
        found = result.effects[key]
        tolerance = tolerances.get(key, SINGLE.get(key, (None, {}))[1])
        for name, value in truth.items():
            if name == "falloff_per_rad2":
                assert _half_angle_deg(found[name]) == pytest.approx(_half_angle_deg(value), abs=2.0), found
            else:
                assert found[name] == pytest.approx(value, abs=tolerance[name]), (key, found)
    assert result.chi2_after <= 1.2 or result.chi2_after * 5 <= result.chi2_before


@pytest.mark.slow
@pytest.mark.parametrize("magnitude", [0, 1])
@pytest.mark.parametrize("key", list(SINGLE))
def test_each_library_effect_alone_is_named_and_measured(simulator, positions, key, magnitude):
    values, tolerance = SINGLE[key]
    injected = {key: values[magnitude]}
    _check_recovered(
        _attribute(simulator, positions, injected, seed=10 + magnitude, gain=1.0), injected, {key: tolerance}
    )


@pytest.mark.slow
@pytest.mark.parametrize("injected", PAIRS, ids=lambda v: "+".join(v))
def test_pairs_of_effects_are_named_and_measured(simulator, positions, injected):
    tolerances = {k: SINGLE[k][1] if k in SINGLE else SINGLE["lenslet_decenter[2]"][1] for k in injected}
    _check_recovered(_attribute(simulator, positions, injected, seed=20, gain=1.0), injected, tolerances)


@pytest.mark.slow
@pytest.mark.parametrize(("seed", "gain"), [(s, None if s % 2 else 1.0) for s in range(30, 36)])
def test_more_clean_seeds_yield_no_effect(simulator, positions, seed, gain):
    """With the four seeds of the fast suite, ten clean seeds in all."""
    result = _attribute(simulator, positions, {}, seed, gain)
    assert result.effects == {}


# ----------------------------------------------------------------------------- a sensor's flat field
# A real sensor's gain varies a little over its area (an uncorrected flat field): not an effect of the
# optics, but it moves every focus's energy and hid an MLA decentre beside it (issue 14, round 3).


def _bowl_gain(shape: tuple[int, int]) -> np.ndarray:
    """1 − 0.125 r² about a point off the sensor's centre (r = 1 at the half-height / half-width):
    in the flat field's coordinates u, v (from the centre, in half-sizes), 1 − 0.125 ((u + 0.16)² +
    (v − 0.16)²)."""
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]]
    u = (rows - (shape[0] - 1) / 2) / (shape[0] / 2)
    v = (cols - (shape[1] - 1) / 2) / (shape[1] / 2)
    return 1.0 - 0.125 * ((u + 0.16) ** 2 + (v - 0.16) ** 2)


def test_the_flat_field_nuisance_is_its_closed_form():
    from cm2optics.calibrate.attribute import FLAT_FIELD, flat_field_gain

    assert FLAT_FIELD.name not in {e.name for e in library(9)}  # a nuisance of the sensor, not in the vocabulary
    values = {"gain_row": 0.04, "gain_col": -0.02, "gain_row2": -0.1, "gain_row_col": 0.03, "gain_col2": 0.05}
    gain = flat_field_gain((101, 201), values)
    assert gain[50, 100] == pytest.approx(1.0)  # the centre: u = v = 0
    u, v = 100 / 101 * 2 - 1.0 + 1 / 101, 1.0 - 1 / 201  # the bottom-right pixel, (n − 1)/2 / (n/2) from the centre
    expected = 1 + 0.04 * u - 0.02 * v - 0.1 * u * u + 0.03 * u * v + 0.05 * v * v
    assert gain[100, 200] == pytest.approx(expected, rel=1e-5)
    assert flat_field_gain((11, 11), {}) == pytest.approx(np.ones((11, 11)))


def _attribute_with_gain(simulator, positions, values, seed, gain_scale=1.0):
    counts, exposure = measured(simulator, positions, values, seed=seed)
    gain = 1.0 + gain_scale * (_bowl_gain(simulator.shape) - 1.0)
    signal = (counts.astype(np.float64) - DARK) * gain[None] + DARK  # the sensor's gain on the noisy signal
    counts = np.clip(np.round(signal), 0, 4095).astype(np.uint16)
    problem = Problem(simulator, counts, exposure, positions, np.ones(counts.shape, bool), library(9), 1.0)
    return attribute(problem)


@pytest.mark.slow
def test_a_decentre_beside_a_sensor_gain_map_is_named_and_the_gain_is_no_effect(simulator, positions):
    """The MLA decentred 40 µm in x beside a flat-field error of −25 % at the corners: the decentre
    is named and measured; the gain is fitted as the sensor's nuisance, not reported as an effect."""
    result = _attribute_with_gain(simulator, positions, {"mla_decenter": {"dx_mm": 0.04, "dy_mm": 0.0}}, seed=40)
    assert list(result.effects) == ["mla_decenter"]
    assert result.effects["mla_decenter"]["dx_mm"] == pytest.approx(0.04, abs=0.005)
    assert result.effects["mla_decenter"]["dy_mm"] == pytest.approx(0.0, abs=0.005)
    assert result.flat_field is not None
    assert result.flat_field["gain_row2"] == pytest.approx(-0.125, abs=0.03)
    assert result.flat_field["gain_col2"] == pytest.approx(-0.125, abs=0.03)
    assert result.chi2_after < 1.2


@pytest.mark.slow
def test_a_sensor_gain_map_alone_is_no_effect(simulator, positions):
    """A weaker, second magnitude of the gain map (−12 % at the corners), never tuned on."""
    result = _attribute_with_gain(simulator, positions, {}, seed=41, gain_scale=0.5)
    assert result.effects == {}
    assert result.chi2_after < 1.2


def test_effects_that_only_widen_the_foci_carry_the_larger_source_caveat():
    """pixel_crosstalk, and a halo barely wider than the foci, widen every focus as a larger source
    does; a wide halo does not (foci of RMS radius 2.2 px at 19.2 µm: σ ≈ 30 µm)."""
    from types import SimpleNamespace

    from cm2optics.calibrate.scan import _widening_caveats
    from cm2optics.emission.source import AngularProfile, PointSource

    after = SimpleNamespace(model=SimpleNamespace(width_px=np.full((4, 9), 2.2)), used=np.ones(4, bool))
    source = PointSource(2.0, AngularProfile.parse("isotropic"))

    def caveats(effects):
        return _widening_caveats(SimpleNamespace(effects=effects), source, 8, after, 19.2)

    assert caveats({"mla_rotation": {"angle_deg": 0.3}}) == []
    assert caveats({"stray_light": {"fraction": 0.05, "width_um": 200.0}}) == []
    narrow = caveats({"stray_light": {"fraction": 0.13, "width_um": 44.0}})
    assert len(narrow) == 1 and "larger than declared (2 µm)" in narrow[0]
    crosstalk = caveats({"pixel_crosstalk": {"fraction": 0.2}})
    assert len(crosstalk) == 1 and crosstalk[0].startswith("pixel_crosstalk (0.200 between the 8×-binned")


# ----------------------------------------------------------------------------- a source larger than declared
# A pinhole or bead larger than the design declares blurs every focus by its disc image (d × the
# magnification at the source's depth): named `source_size`, not `pixel_crosstalk` or a narrow
# `stray_light` (issue 14, round 5).


def _second_moments(image: np.ndarray, centre: tuple[float, float], half: int = 9) -> np.ndarray:
    """(row, col) variance (px²) of ``image`` in a (2·half + 1)² window about ``centre``."""
    r0, c0 = round(centre[0]), round(centre[1])
    window = image[r0 - half : r0 + half + 1, c0 - half : c0 + half + 1].astype(np.float64)
    rows, cols = np.mgrid[-half : half + 1, -half : half + 1]
    total = window.sum()
    mr, mc = (window * rows).sum() / total, (window * cols).sum() / total
    return np.array([(window * (rows - mr) ** 2).sum() / total, (window * (cols - mc) ** 2).sum() / total])


def test_a_larger_source_adds_its_disc_images_second_moment(simulator):
    """The closed form: a disc of diameter D has a second moment D²/16 per axis, which adds to the
    focus's; the image of the source's disc is d·m(z) across, so the widening grows with the
    magnification over depth; at the declared size (here a point) the effect is absent."""
    from cm2optics.calibrate.effects import source_size_effect

    effect = source_size_effect(0.0)
    assert effect.defaults() == {"diameter_um": 0.0} and effect.parameters[0].low == 0.0
    assert source_size_effect(25.0).defaults() == {"diameter_um": 25.0} and source_size_effect(200.0) is None
    assert "source_size" in {e.name for e in library(9)}
    positions = np.array([[0.0, 0.0, -0.3], [0.0, 0.0, 0.3]])
    point = simulator.rates(positions, {})
    np.testing.assert_array_equal(simulator.rates(positions, {"source_size": {"diameter_um": 0.0}}), point)
    disc = simulator.rates(positions, {"source_size": {"diameter_um": 100.0}})
    centres = simulator.focus_centres_px(positions)[:, 4]
    for i, z in enumerate(positions[:, 2]):
        image_px = 100.0 * float(simulator.model.magnification_at(z)) / simulator.pixel_um
        added = _second_moments(disc[i], centres[i]) - _second_moments(point[i], centres[i])
        np.testing.assert_allclose(added, image_px**2 / 16, rtol=0.02)
        assert disc[i].sum() == pytest.approx(point[i].sum(), rel=1e-4)  # a blur: the energy stays


def test_the_tracers_source_disc_adds_its_second_moment_and_keeps_the_centroid():
    """A traced focus (ePSF samples 1/8 px apart) convolved with the extra disc: its centroid stays,
    its second moment grows by D²/16 per axis; the extra disc is √(d² − d₀²), none at the declared d₀."""
    from cm2optics.calibrate.tracer import _blurred, _Traced, source_disc_um
    from cm2optics.emission.source import AngularProfile, PointSource, ProfileKind

    declared = PointSource(5.0, AngularProfile(ProfileKind.ISOTROPIC))
    assert source_disc_um({}, declared) == 0.0
    assert source_disc_um({"source_size": {"diameter_um": 5.0}}, declared) == 0.0
    assert source_disc_um({"source_size": {"diameter_um": 13.0}}, declared) == pytest.approx(12.0)
    s = 8
    u = (np.arange(97) - 48.3) / s  # px from the focus's centre, the centre between samples
    epsf = np.exp(-0.5 * (u[:, None] ** 2 + u[None, :] ** 2) / 1.5**2).astype(np.float32)
    focus = _Traced(4, epsf, (800, 1200), (0.0, 0.0), 1.0)
    blurred = _blurred(focus, 3.0, s)

    def moments(t):
        rows = (np.arange(t.epsf.shape[0]) + t.origin[0]) / s
        cols = (np.arange(t.epsf.shape[1]) + t.origin[1]) / s
        w = t.epsf.astype(np.float64)
        total = w.sum()
        mr, mc = w.sum(axis=1) @ rows / total, w.sum(axis=0) @ cols / total
        var = (w.sum(axis=1) @ (rows - mr) ** 2 / total, w.sum(axis=0) @ (cols - mc) ** 2 / total)
        return total, np.array([mr, mc]), np.array(var)

    total, centre, var = moments(focus)
    total_b, centre_b, var_b = moments(blurred)
    assert total_b == pytest.approx(total, rel=1e-5)
    np.testing.assert_allclose(centre_b, centre, atol=1e-4)
    np.testing.assert_allclose(var_b - var, 3.0**2 / 16, rtol=0.01)


def _disc_offsets_mm(diameter_um: float, points: int = 64) -> np.ndarray:
    """(points, 2) offsets (x, y) mm spread uniformly over a disc of ``diameter_um`` (a Vogel
    spiral: equal areas, second moment d²/16 per axis)."""
    k = np.arange(points)
    r = diameter_um / 2000.0 * np.sqrt((k + 0.5) / points)
    t = k * np.pi * (3.0 - np.sqrt(5.0))
    return np.column_stack([r * np.cos(t), r * np.sin(t)])


class _Bead:
    """A calibration source that is a uniform disc: the simulator's images of 64 point sources
    spread over it, averaged — the disc as it is, not the model's equal-moment Gaussian."""

    def __init__(self, simulator, diameter_um: float):
        self.simulator, self.offsets = simulator, _disc_offsets_mm(diameter_um)
        self.pixel_um = simulator.pixel_um

    def rates(self, positions, values):
        total = sum(self.simulator.rates(positions + np.array([dx, dy, 0.0]), values) for dx, dy in self.offsets)
        return (total / len(self.offsets)).astype(np.float32)


@pytest.mark.slow
@pytest.mark.parametrize(("diameter_um", "seed"), [(60.0, 50), (100.0, 51)])
def test_a_bead_larger_than_declared_is_named_source_size(simulator, positions, diameter_um, seed):
    """Round 4's case: a uniform 60- or 100-µm disc imaged, a point declared (once named
    `pixel_crosstalk` 0.47 and a 44-µm `stray_light` halo): `source_size` alone, its diameter ± 10 µm."""
    counts, exposure = measured(_Bead(simulator, diameter_um), positions, seed=seed)
    problem = Problem(simulator, counts, exposure, positions, np.ones(counts.shape, bool), library(9), 1.0)
    result = attribute(problem)
    assert list(result.effects) == ["source_size"], result.effects
    assert result.effects["source_size"]["diameter_um"] == pytest.approx(diameter_um, abs=10.0)
    assert result.chi2_after < 1.2
