"""The attribution's guard (:func:`cm2optics.calibrate.attribute.guard`) on a hand-made feature
space whose χ² changes are known: three groups of features (two foci and a frame's background)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from cm2optics.calibrate.attribute import MAX_WORSENED_SHARE, MIN_EXCESS_SHARE, State, guard


def _problem(data: np.ndarray, groups: np.ndarray) -> SimpleNamespace:
    """Features are the state's values (``values["f"]``), σ = 1, every feature used."""
    space = SimpleNamespace(data=data, sigma=np.ones_like(data))
    return SimpleNamespace(
        use=np.ones(len(data), bool),
        space=space,
        feature_groups=groups,
        n_features=len(data),
        noise_known=True,
        features=lambda state: np.asarray(state.values["f"]["model"]),
    )


def _state(model) -> State:
    return State(np.zeros(4), {"f": {"model": np.asarray(model, float)}})


GROUPS = np.array([0, 0, 1, 1, 2, 2])


def test_an_effect_that_fits_where_it_acts_passes():
    data = np.array([5.0, 3.0, 0.0, 0.0, 0.0, 0.0])
    check = guard(_problem(data, GROUPS), _state(np.zeros(6)), _state([5.0, 3.0, 0, 0, 0, 0]))
    # χ² 34 → 0 with 6 features: the whole excess (34 − 6 = 28) and more is removed; nothing worse
    assert check.excess_share == pytest.approx(34.0 / 28.0)
    assert check.worsened_share == 0.0
    assert check.passed


def test_an_effect_that_trades_a_few_gains_for_losses_elsewhere_fails():
    """A localised residual (group 0) absorbed by a parameter that also moves groups 1 and 2."""
    data = np.array([6.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    after = _state([4.0, 0.0, 2.0, 0.0, 2.0, 0.0])  # group 0: 36 → 4; groups 1, 2: 0 → 4 each
    check = guard(_problem(data, GROUPS), _state(np.zeros(6)), after)
    assert check.excess_share == pytest.approx((36.0 - 12.0) / 30.0)
    assert check.worsened_share == pytest.approx(8.0 / 32.0)  # at the limit: still kept
    assert MAX_WORSENED_SHARE == 0.25 and check.passed
    worse = _state([4.0, 0.0, 2.5, 0.0, 2.5, 0.0])  # losses 12.5 of a 32 gain
    check = guard(_problem(data, GROUPS), _state(np.zeros(6)), worse)
    assert check.worsened_share == pytest.approx(12.5 / 32.0) and not check.passed


def test_an_effect_that_removes_little_of_the_excess_fails():
    data = np.array([6.0, 6.0, 6.0, 6.0, 6.0, 6.0])  # χ² 216, excess 210
    check = guard(_problem(data, GROUPS), _state(np.zeros(6)), _state([1.0, 0, 0, 0, 0, 0]))
    assert check.excess_share == pytest.approx(11.0 / 210.0)
    assert check.excess_share < MIN_EXCESS_SHARE and not check.passed
