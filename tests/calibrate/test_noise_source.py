"""The inputs the loop takes from a scan's scan.yaml: the calibration source's profile, the noise
model's floor (quantisation steps) and noise-free scans; the sensor model run forwards."""

from __future__ import annotations

import numpy as np
import pytest

from cm2optics.calibrate.noise import estimate_noise, quantisation_step, raw_frames
from cm2optics.calibrate.residual import CalibrationError
from cm2optics.calibrate.scan import scan_gain, scan_source
from cm2optics.emission.source import AngularProfile, PointSource, ProfileKind, calibration_pinhole


@pytest.mark.parametrize(
    "profile",
    [
        AngularProfile(),
        AngularProfile(ProfileKind.LAMBERTIAN),
        AngularProfile(ProfileKind.COSINE, 3.5),
        AngularProfile(ProfileKind.GAUSSIAN, 26.0),
    ],
)
def test_a_profile_reads_back_from_its_description(profile):
    assert AngularProfile.parse(profile.describe()) == profile


def test_the_scans_source_is_read_and_a_missing_or_bad_one_said():
    extra = {"source_diameter_um": 5.0, "source_profile": "gaussian, 1/e^2 half-angle 26 deg"}
    assert scan_source(extra) == (calibration_pinhole(), [])
    source, warnings = scan_source({})
    assert source == PointSource(0.0, AngularProfile()) and "assumed isotropic" in warnings[0]
    assert scan_source(extra, 2.0, "lambertian")[0] == PointSource(2.0, AngularProfile(ProfileKind.LAMBERTIAN))
    with pytest.raises(CalibrationError, match="table of 4 angles"):
        scan_source({"source_profile": "table of 4 angles"})
    with pytest.raises(CalibrationError, match="half-angle"):
        scan_source({"source_profile": "gaussian, 1/e^2 half-angle 0.2 deg"})  # outside 1–180°


def test_a_noise_free_scan_is_fitted_with_its_noise_scale_profiled_out():
    assert scan_gain({"counts_per_electron": 0.25}) == (0.25, [])
    gain, warnings = scan_gain({"counts_per_electron": 0.25, "noise": "none"})
    assert gain is None and "no noise" in warnings[0]


def test_the_quantisation_step_is_found_and_floors_the_noise():
    rng = np.random.default_rng(0)
    twelve_bit = rng.integers(0, 4096, (64, 64)) * 16  # a 12-bit sensor in a 16-bit file
    assert quantisation_step(twelve_bit) == 16.0
    assert quantisation_step(rng.integers(100, 4000, 1000)) == 1.0
    assert quantisation_step(rng.normal(0, 1, 100)) == 1.0
    # noise-free frames: the residual is rounding only; read noise 0, σ² never below Δ²/12
    residual = np.zeros(5000)
    noise = estimate_noise(residual, np.linspace(0, 1000, 5000), np.arange(5000) < 2500, None, 16.0)
    assert noise.read_noise_counts == 0.0
    assert noise.variance(np.zeros(3)) == pytest.approx(np.full(3, 16.0**2 / 12.0))


def test_raw_frames_have_the_sensors_statistics():
    rng = np.random.default_rng(1)
    expected = np.full(200_000, 1100.0)  # 1000 counts above a 100-count dark
    frames = raw_frames(expected, 100.0, 0.5, 3.0, 12, rng).astype(float)
    assert frames.mean() == pytest.approx(1100.0, abs=0.2)
    assert frames.var() == pytest.approx(0.5 * 1000.0 + 9.0 + 1 / 12, rel=0.02)
    assert raw_frames(np.array([5000.0, -20.0]), 0.0, 1.0, 0.0, 12, rng).tolist() == [4095, 0]
