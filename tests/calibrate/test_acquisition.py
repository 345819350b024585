"""A source that drifts over the scan (`calibrate.acquisition.flux_drift`): a flux falling 30 %
along the acquisition order is reported with its size, clean frames and a flux that changes with
the field (as an optical effect does) are not."""

from __future__ import annotations

import numpy as np
import pytest

from cm2optics.calibrate.acquisition import flux_drift, frame_flux, stage_errors
from cm2optics.calibrate.features import focus_features, focus_windows
from cm2optics.calibrate.noise import raw_frames
from cm2optics.calibrate.residual import ScanData, analyse_scan
from cm2optics.calibrate.unexplained import describe_unexplained

SHAPE = (100, 120)
GAIN = 0.25  # counts per electron
CENTRES = np.array([[r, c] for r in (32.0, 44.5, 56.0, 67.3) for c in (35.2, 52.0, 68.6, 84.1)])


def _focus(centres: np.ndarray) -> np.ndarray:
    rows, cols = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]]
    return np.exp(-((rows - centres[:, None, None, 0]) ** 2 + (cols - centres[:, None, None, 1]) ** 2) / 2.88)


def _analysis(flux: np.ndarray, seed: int = 0, shift_px: np.ndarray | None = None):
    """The analysis of a Gaussian focus moving over a 4 × 4 raster, frame i at ``flux[i]`` × the
    model's, its focus displaced by ``shift_px[i]`` columns."""
    rate = _focus(CENTRES).astype(np.float32)
    moved = CENTRES + np.column_stack(
        [np.zeros(len(CENTRES)), np.zeros(len(CENTRES)) if shift_px is None else shift_px]
    )
    expected = 100.0 + 2500.0 * flux[:, None, None] * _focus(moved)
    counts = raw_frames(expected, 100.0, GAIN, 2.0, 12, np.random.default_rng(seed))
    positions = np.column_stack([CENTRES[:, 1], CENTRES[:, 0], np.zeros(len(CENTRES))]) * 0.01
    data = ScanData(counts, np.ones(len(counts)), positions, tuple(f"{i}.tif" for i in range(len(counts))), 12)
    return analyse_scan(data, rate, positions, CENTRES[:, None, :], 16.0, counts_per_electron=GAIN)


def test_a_flux_falling_along_the_acquisition_order_is_reported_with_its_size():
    drift = 1.0 - 0.3 * np.arange(16) / 15
    analysis = _analysis(drift)
    flux = frame_flux(analysis)
    assert flux / flux[0] == pytest.approx(drift, abs=0.02)
    warning = flux_drift(analysis)
    assert warning is not None and "drifted" in warning
    assert "-30%" in warning or "-29%" in warning or "-31%" in warning


@pytest.mark.parametrize("seed", [0, 1])
def test_clean_frames_and_a_flux_that_changes_with_the_field_are_no_drift(seed):
    assert flux_drift(_analysis(np.ones(16), seed)) is None
    radius = np.hypot(CENTRES[:, 0] - 50.0, CENTRES[:, 1] - 60.0)
    assert flux_drift(_analysis(1.0 - 0.3 * (radius / radius.max()) ** 2, seed)) is None


def test_with_the_drift_named_the_frames_own_flux_leaves_nothing_unexplained():
    analysis = _analysis(1.0 - 0.3 * np.arange(16) / 15)
    assert describe_unexplained(analysis, 19.2)  # against one flux for the scan: a position-dependent "loss"
    assert describe_unexplained(analysis, 19.2, per_frame=True) == []


def test_frames_displaced_as_a_whole_are_named_as_a_stage_error():
    backlash = np.where((np.arange(16) // 4) % 2 == 1, 0.8, 0.0)  # alternate rows of the raster
    warning = stage_errors(_analysis(np.ones(16), shift_px=backlash), 19.2)
    assert warning is not None and "stage" in warning
    assert 0.7 < float(warning.split("up to ")[1].split(" px")[0]) < 0.9
    assert stage_errors(_analysis(np.ones(16)), 19.2) is None
    assert stage_errors(_analysis(np.ones(16), shift_px=np.full(16, 0.8)), 19.2) is None  # common: the sensor's offset


def test_a_background_gradient_does_not_pull_the_centroids():
    """A ramp of 0–150 counts across the frame: the foci's centroids are measured above each
    window's own background plane (the plain centroids move ≈ 0.1 px towards the bright side)."""
    ramp = np.linspace(0.0, 150.0, SHAPE[1])[None, None, :]
    rate = _focus(CENTRES).astype(np.float32)
    counts = raw_frames(100.0 + 2500.0 * _focus(CENTRES) + ramp, 100.0, GAIN, 2.0, 12, np.random.default_rng(4))
    positions = np.column_stack([CENTRES[:, 1], CENTRES[:, 0], np.zeros(len(CENTRES))]) * 0.01
    data = ScanData(counts, np.ones(len(counts)), positions, tuple(f"{i}.tif" for i in range(len(counts))), 12)
    analysis = analyse_scan(data, rate, positions, CENTRES[:, None, :], 40.0, counts_per_electron=GAIN)
    local = np.nanmax(np.abs(analysis.centroid_error_px))
    signal = counts.astype(float) - analysis.registration.dark_level
    centres, radii = focus_windows(rate, CENTRES[:, None, :], 40.0)
    plain = focus_features(signal, centres, radii).centroid_px
    assert local < 0.25 * np.nanmax(np.abs(plain - CENTRES[:, None, :]))
