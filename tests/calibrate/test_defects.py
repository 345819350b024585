"""Sensor defects found in a scan's own frames (`calibrate.defects`): hot pixels, a saturated
cluster and a dead column are found exactly, clean frames yield none, and a defect is filled
from its neighbours; `analyse_scan` then keeps every frame (a hot pixel saturated in every frame
used to leave every frame out as "saturated")."""

from __future__ import annotations

import numpy as np
import pytest

from cm2optics.calibrate.defects import defective_pixels, describe_defects, fill_defects
from cm2optics.calibrate.noise import raw_frames
from cm2optics.calibrate.residual import CalibrationError, ScanData, analyse_scan

SHAPE = (60, 80)


def _scan(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Raw frames of a Gaussian focus (σ 1.2 px) moving over a 4 × 4 grid, its rate and centres."""
    rows, cols = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]]
    centres = np.array([[r, c] for r in (12.0, 24.5, 36.0, 47.3) for c in (15.2, 32.0, 48.6, 64.1)])
    rate = np.exp(-((rows - centres[:, None, None, 0]) ** 2 + (cols - centres[:, None, None, 1]) ** 2) / 2.88)
    rate = rate.astype(np.float32)
    counts = raw_frames(100.0 + 2500.0 * rate, 100.0, 1.0, 2.0, 12, np.random.default_rng(seed))
    return counts, rate, centres, centres[:, None, :]


def _with_defects(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    out = counts.copy()
    truth = np.zeros(SHAPE, bool)
    out[:, 5:8, 70:73] = 4095  # a saturated cluster, in every frame
    truth[5:8, 70:73] = True
    out[:, 30, 5] = 600  # a hot pixel
    truth[30, 5] = True
    out[:, :, 40] = 0  # a dead column, through the foci of the third column
    truth[:, 40] = True
    return out, truth


def test_hot_pixels_a_cluster_and_a_dead_column_are_found_exactly_and_clean_frames_give_none():
    for seed in range(3):
        counts, rate, _, _ = _scan(seed)
        assert not defective_pixels(counts, rate, np.ones(len(counts))).any()
        damaged, truth = _with_defects(counts)
        found = defective_pixels(damaged, rate, np.ones(len(counts)))
        assert np.array_equal(found, truth)
        described = describe_defects(found)
        assert described["pixels"] == 60 + 9 + 1 and described["columns"] == [40] and described["rows"] == []


def test_defects_are_filled_from_their_neighbours_and_every_frame_stays_in_the_fit():
    counts, rate, centres, centres_j = _scan(1)
    damaged, truth = _with_defects(counts)
    filled = fill_defects(damaged, truth)
    assert np.array_equal(filled[:, ~truth], damaged[:, ~truth])
    assert np.abs(filled[:, 5:8, 70:73] - 100.0).max() < 8  # dark around the cluster
    peak = filled[:, 24, 40]  # the dead column crosses a focus centred at column 40.5 in row 24.5
    assert np.all(np.abs(peak[4:8] - counts[4:8, 24, 40]) < np.abs(peak[4:8] - 0))
    exposure = np.ones(len(counts))
    positions = np.column_stack([centres[:, 1], centres[:, 0], np.zeros(len(centres))]) * 0.01
    files = tuple(f"{i}.tif" for i in range(len(counts)))
    with pytest.raises(CalibrationError, match="saturated"):  # defects not known: every frame saturated
        analyse_scan(ScanData(damaged, exposure, positions, files, 12), rate, positions, centres_j, 16.0)
    data = ScanData(filled, exposure, positions, files, 12, truth)
    analysis = analyse_scan(data, rate, positions, centres_j, 16.0, counts_per_electron=1.0)
    assert analysis.used.all() and "saturated" not in analysis.flags
    assert np.all(analysis.residual_counts[:, truth] == 0)  # no information there: no misfit
    clean = analyse_scan(
        ScanData(counts, exposure, positions, files, 12), rate, positions, centres_j, 16.0, counts_per_electron=1.0
    )
    assert analysis.chi2_total < 1.2
    assert abs(analysis.nmse_total - clean.nmse_total) < 0.3 * clean.nmse_total
    assert np.nanmax(np.abs(analysis.energy_ratio - 1.0)) < 0.05  # the foci the column crosses included


def test_a_background_that_scales_with_the_exposure_is_no_defect():
    """Room light, a ramp across x, on frames exposed 1 or 20 ms in turn: the pixels' level over
    the frames is bimodal, and foci that light a pixel in a few frames used to tip its median."""
    _, rate, _, _ = _scan()
    exposure = np.where(np.arange(len(rate)) % 2 == 0, 20.0, 1.0)
    ramp = np.linspace(0.0, 30.0, SHAPE[1])[None, None, :] * exposure[:, None, None]
    counts = raw_frames(100.0 + 2500.0 * rate + ramp, 100.0, 1.0, 2.0, 12, np.random.default_rng(2))
    assert not defective_pixels(counts, rate / exposure[:, None, None], exposure).any()
