"""Fixed-pattern column and row offsets of the readout (`calibrate.fixed_pattern`): named with
their size when the same in every frame; white noise, a smooth background and column offsets
that change from frame to frame are not."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from cm2optics.calibrate.fixed_pattern import describe_fixed_pattern, fixed_pattern

SHAPE = (8, 120, 160)


def _analysis(residual: np.ndarray) -> SimpleNamespace:
    rows, cols = np.mgrid[0 : SHAPE[1], 0 : SHAPE[2]]
    model = 100.0 + np.stack([3000.0 * np.exp(-((rows - 60) ** 2 + (cols - 20 * i - 10) ** 2) / 4.0) for i in range(8)])
    return SimpleNamespace(used=np.ones(SHAPE[0], bool), model_counts=model, residual_counts=residual)


def test_column_offsets_the_same_in_every_frame_are_named_with_their_size():
    rng = np.random.default_rng(0)
    columns = rng.normal(0.0, 1.0, SHAPE[2])
    found = fixed_pattern(_analysis(rng.normal(0.0, 2.0, SHAPE) + columns[None, None, :]))
    assert found is not None and "rows" not in found
    truth = columns - np.median(columns)
    assert found["columns"]["rms_counts"] == pytest.approx(float(np.std(truth)), rel=0.2)
    assert found["noise_counts"] == pytest.approx(2.0, rel=0.15)
    assert "columns offset by" in describe_fixed_pattern(found)


def test_white_noise_a_smooth_background_and_offsets_of_each_frame_are_not():
    rng = np.random.default_rng(1)
    assert fixed_pattern(_analysis(rng.normal(0.0, 2.0, SHAPE))) is None
    ramp = np.linspace(0.0, 30.0, SHAPE[2])[None, None, :] + np.linspace(0.0, 10.0, SHAPE[1])[None, :, None]
    assert fixed_pattern(_analysis(rng.normal(0.0, 2.0, SHAPE) + ramp)) is None
    own = rng.normal(0.0, 1.0, (SHAPE[0], 1, SHAPE[2]))  # each frame its own columns: not fixed
    assert fixed_pattern(_analysis(rng.normal(0.0, 2.0, SHAPE) + own)) is None
