"""The attribution's guard (:func:`cm2optics.calibrate.attribute.guard`) on a hand-made feature
space whose χ² changes are known: three groups of features (two foci and a frame's background)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from cm2optics.calibrate.attribute import (
    ACTS_CHI2,
    CONFIRM_CHI2,
    CONFIRMED,
    MAX_CONTRADICTED_SHARE,
    MAX_WORSENED_SHARE,
    MIN_EXCESS_SHARE,
    State,
    _sectors,
    confirmation,
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
        pixel_change=lambda before, after: (np.zeros(0), np.zeros(0), np.ones(0), np.zeros(0, int)),  # no pixels
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


def test_the_confirmation_is_the_share_of_the_change_the_residual_holds():
    """r = 0.3·Δ + a part orthogonal to Δ: a = 0.3, and the χ² falls by S·(2a − 1) (here rises)."""
    change = np.array([2.0, -1.0, 0.0, 0.0])
    residual = 0.3 * change + np.array([0.0, 0.0, 4.0, -3.0])
    sigma = np.array([0.5, 0.5, 1.0, 1.0])
    a, size = confirmation(residual, change, sigma)
    assert a == pytest.approx(0.3) and size == pytest.approx(20.0)
    fall = np.sum((residual / sigma) ** 2) - np.sum(((residual - change) / sigma) ** 2)
    assert fall == pytest.approx(size * (2 * a - 1))
    assert confirmation(np.ones(3), np.zeros(3), np.ones(3)) == (1.0, 0.0)  # no change: nothing to bear out


def test_pixels_are_sorted_by_their_direction_from_the_nearest_focus():
    sector = _sectors((7, 20), np.array([[[3.0, 3.0], [3.0, 15.0], [np.nan, np.nan]]]))[0]
    assert [sector[3, 5], sector[5, 3], sector[3, 1], sector[1, 3]] == [0, 1, 2, 3]  # right, below, left, above
    assert [sector[3, 13], sector[3, 17]] == [2, 0]  # about the second focus, nearer


def _with_pixels(problem: SimpleNamespace, residual: np.ndarray, change: np.ndarray) -> SimpleNamespace:
    """100 pixels, 25 in each quarter about the foci (right, below, left, above)."""
    sector = np.repeat(np.arange(4), 25)
    problem.pixel_change = lambda before, after: (residual, change, np.ones_like(change), sector)
    return problem


def test_a_halo_fitted_to_a_ghost_is_not_borne_out_all_round_the_foci():
    """The features say yes (their χ² falls to the noise), and so do the pixels as a whole, but
    the fit adds light all round each focus (a halo: the change, 2 σ in 10 pixels of each quarter,
    χ² 40 per quarter) while the residual sits on one side (a ghost below, 6 σ in the halo's
    pixels there): amplitude 3 below, 0 elsewhere, 0.75 over all the pixels."""
    data = np.array([5.0, 3.0, 0.0, 0.0, 0.0, 0.0])
    halo = np.tile(np.r_[np.full(10, 2.0), np.zeros(15)], 4)
    ghost = np.zeros(100)
    ghost[25:35] = 6.0
    assert confirmation(ghost, halo, np.ones(100))[0] == pytest.approx(0.75)
    after = _state([5.0, 3.0, 0, 0, 0, 0])
    check = guard(_with_pixels(_problem(data, GROUPS), ghost, halo), _state(np.zeros(6)), after)
    assert CONFIRM_CHI2 == 36.0 and check.amplitudes["pixels below the foci"] == pytest.approx(3.0)
    assert check.unconfirmed == ["pixels right of the foci", "pixels left of the foci", "pixels above the foci"]
    assert not check.passed
    # the same fit where the light is all round the foci, as the halo puts it
    check = guard(_with_pixels(_problem(data, GROUPS), halo + 0.1, halo), _state(np.zeros(6)), after)
    assert check.amplitudes["pixels above the foci"] == pytest.approx(1.05) and check.passed


def test_a_change_of_widths_the_data_do_not_show_fails():
    """A tilt fitted as a proxy: it explains six foci's energies (kind 0) but also widens each
    focus (kind 2) by 2.5 σ, which the data's widths do not show. Every focus gains on the whole
    (16 in energy, 6.25 lost in width): the χ²-weighted checks pass; the widths' amplitude is 0."""
    foci = np.tile(np.arange(6), 2)
    data = np.concatenate([np.full(6, 4.0), np.zeros(6)])
    problem = _problem(data, foci)
    problem.feature_kinds = np.repeat([0, 2], 6)
    after = _state(np.concatenate([np.full(6, 4.0), np.full(6, 2.5)]))
    check = guard(problem, _state(np.zeros(12)), after)
    assert check.excess_share >= MIN_EXCESS_SHARE and check.worsened_share == 0.0 and check.contradicted_share == 0.0
    assert check.amplitudes == pytest.approx({"energy": 1.0, "width": 0.0})
    assert check.unconfirmed == ["width"] and not check.passed
    widened = _problem(np.concatenate([np.full(6, 4.0), np.full(6, 2.5)]), foci)
    widened.feature_kinds = problem.feature_kinds
    assert guard(widened, _state(np.zeros(12)), after).passed  # the data's foci widened too


def test_a_right_effect_beside_one_not_yet_fitted_passes():
    """A narrow source beside partial lenslets not yet fitted (the matrix's pair): its energies
    are borne out (a = 1, S = 400) and its small change of widths only in part (a = 0.3, S = 40,
    the other effect's residual there): above CONFIRMED, a quarter."""
    foci = np.tile(np.arange(4), 2)
    problem = _problem(np.concatenate([np.full(4, 10.0), np.full(4, 0.3 * 10**0.5)]), foci)
    problem.feature_kinds = np.repeat([0, 2], 4)
    after = _state(np.concatenate([np.full(4, 10.0), np.full(4, 10**0.5)]))
    check = guard(problem, _state(np.zeros(8)), after)
    assert check.amplitudes == pytest.approx({"energy": 1.0, "width": 0.3})
    assert check.sizes == pytest.approx({"energy": 400.0, "width": 40.0})
    assert CONFIRMED == 0.25 and check.unconfirmed == [] and check.passed
