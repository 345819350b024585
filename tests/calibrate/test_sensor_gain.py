"""A sensor gain that varies over the sensor (`calibrate.sensor_gain`): one smooth pattern that the
foci of every lenslet see where they land is named with its size; a loss that follows the source's
offset from each lenslet (as the source's profile or vignetting do), a dim lenslet and clean
frames are not."""

from __future__ import annotations

import numpy as np
import pytest
from lattice_scans import FIELD, VERTICES, lattice_analysis

from cm2optics.calibrate.sensor_gain import describe_sensor_gain, sensor_gain

TRAVEL = 30.0  # px per mm: the foci of neighbouring lenslets cover each other's ground (pitch 36 px)


def _bowl(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """1 − 0.2 r² about an off-centre point, r = 1 at 90 px: −20 % at 90 px from it."""
    return 1.0 - 0.2 * (((rows - 80.0) / 90.0) ** 2 + ((cols - 100.0) / 90.0) ** 2)


def _tilt(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """A gain falling 8 % per 90 px across the columns: a second shape and size."""
    return 1.0 - 0.08 * (cols - 90.0) / 90.0


@pytest.mark.parametrize(("gain", "lowest"), [(_bowl, None), (_tilt, "right")])
def test_a_smooth_gain_over_the_sensor_is_named_with_its_range(gain, lowest):
    analysis = lattice_analysis(1500.0, 0.0, 1, positions=FIELD, travel_px=TRAVEL, gain=gain)
    found = sensor_gain(analysis, VERTICES)
    assert found is not None
    centres = analysis.model.centroid_px[analysis.used].reshape(-1, 2)
    truth = gain(centres[:, 0], centres[:, 1])
    expected = np.array([truth.min(), truth.max()]) / np.median(truth)
    assert found["range"] == pytest.approx(expected, abs=0.02)
    if lowest == "right":
        assert found["lowest_px"][1] > 120.0
    assert "flat field" in describe_sensor_gain(found, 8)


def test_a_loss_that_follows_the_source_a_dim_lenslet_and_clean_frames_are_no_sensor_gain():
    seed = 2
    offset = np.hypot(FIELD[:, 0], FIELD[:, 1])[:, None] * np.ones((1, 9))  # the focus's offset from its vertex
    profile = lattice_analysis(1500.0, 0.0, seed, positions=FIELD, travel_px=TRAVEL, energy=1.0 - 0.12 * offset**2)
    assert sensor_gain(profile, VERTICES) is None
    dim = np.ones((len(FIELD), 9))
    dim[:, 4] = 0.8
    assert (
        sensor_gain(lattice_analysis(1500.0, 0.0, seed, positions=FIELD, travel_px=TRAVEL, energy=dim), VERTICES)
        is None
    )
    assert sensor_gain(lattice_analysis(1500.0, 0.0, seed, positions=FIELD, travel_px=TRAVEL), VERTICES) is None
