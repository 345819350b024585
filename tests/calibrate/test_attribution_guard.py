"""The attribution's guard (:func:`cm2optics.calibrate.attribute.guard`) on a hand-made feature
space whose χ² changes are known: three groups of features (two foci and a frame's background)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from cm2optics.calibrate.attribute import (
    ACTS_CHI2,
    MAX_CONTRADICTED_SHARE,
    MAX_WORSENED_SHARE,
    MIN_EXCESS_SHARE,
    State,
    guard,
)


def _problem(data: np.ndarray, groups: np.ndarray) -> SimpleNamespace:
    """Features are the state's values (``values["f"]``), σ = 1, every feature used."""
    space = SimpleNamespace(data=data, sigma=np.ones_like(data))
    return SimpleNamespace(
        use=np.ones(len(data), bool),
        space=space,
        feature_groups=groups,
        feature_kinds=np.zeros(len(data), int),  # every feature an energy
        pixel_change=lambda before, after: (np.zeros(0), np.zeros(0), np.ones(0)),  # no pixels
        n_features=len(data),
        noise_known=True,
        features=lambda state: sum(np.asarray(v["model"], float) for v in state.values.values()),
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


def test_an_effect_that_explains_the_sum_but_not_each_focus_fails():
    """A new effect "t" that dims one lenslet's focus by the same share at four positions: by
    20 σ-units where the focus is bright (group 0), 3.5 where it is dim (groups 1–3), fitted to
    data dimmed at the bright position only (a scratch): χ² 900 → 100 + 3 × 12.25 passes the
    χ²-weighted shares (removes 85 % of the excess, gives back 4.6 %), but three of the four
    foci it acts on get worse."""
    groups = np.arange(4)
    before = State(np.zeros(4), {"f": {"model": np.zeros(4)}})
    after = before.copy()
    after.values["t"] = {"model": np.array([-20.0, -3.5, -3.5, -3.5])}
    check = guard(_problem(np.array([-30.0, 0.0, 0.0, 0.0]), groups), before, after)
    assert check.excess_share == pytest.approx((900.0 - 100.0 - 36.75) / 896.0)
    assert check.worsened_share == pytest.approx(36.75 / 800.0) and check.worsened_share < MAX_WORSENED_SHARE
    assert check.contradicted_share == pytest.approx(0.75) and MAX_CONTRADICTED_SHARE == 0.5
    assert not check.passed
    # the same effect where the data show it at every position: each focus better
    check = guard(_problem(np.array([-22.0, -4.0, -3.0, -3.5]), groups), before, after)
    assert check.contradicted_share == 0.0 and check.passed
    # foci it moves by less than 3 σ do not count: it acts on group 0 alone
    weak = before.copy()
    weak.values["t"] = {"model": np.array([-20.0, -1.0, -1.0, -1.0])}
    check = guard(_problem(np.array([-30.0, 0.0, 0.0, 0.0]), groups), before, weak)
    assert ACTS_CHI2 == 9.0 and check.contradicted_share == 0.0 and check.passed
