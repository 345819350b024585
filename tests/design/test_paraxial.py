"""Paraxial optics against closed forms: thin-lens imaging, thick plano-convex lens, plates."""

import math

import numpy as np
import pytest

from cm2optics.design import paraxial


def test_thin_lens_imaging_matches_gaussian_formula():
    f, s_o = 3.0, 10.0
    s_i = 1 / (1 / f - 1 / s_o)
    system = paraxial.chain(
        paraxial.refract(2 * f * 0.5, 1.0, 1.5), paraxial.refract(-2 * f * 0.5, 1.5, 1.0), paraxial.propagate(s_i, 1.0)
    )
    # A symmetric biconvex thin lens with R = f has power 2·0.5/f = 1/f.
    assert paraxial.conjugate_object_distance_mm(system) == pytest.approx(s_o, rel=1e-12)
    assert paraxial.lateral_magnification(system, s_o) == pytest.approx(-s_i / s_o, rel=1e-12)


def test_thick_plano_convex_lens_focal_length_and_back_focus():
    r, t, n = 1.65, 3.3, 1.49
    lens = paraxial.chain(paraxial.refract(r, 1.0, n), paraxial.propagate(t, n), paraxial.refract(math.inf, n, 1.0))
    f = r / (n - 1)
    assert paraxial.focal_length_mm(lens) == pytest.approx(f, rel=1e-12)
    # Back focal distance from the flat face: f − t/n.
    with_bfd = paraxial.chain(lens, paraxial.propagate(f - t / n, 1.0))
    assert with_bfd[0, 0] == pytest.approx(0.0, abs=1e-12)


def test_plate_shifts_focus_by_t_times_one_minus_inverse_n():
    t, n = 1.0, 1.5
    assert paraxial.propagate(t, n)[0, 1] == pytest.approx(t - t * (1 - 1 / n))


def test_object_at_front_focus_is_rejected():
    system = paraxial.chain(paraxial.refract(1.0, 1.0, 2.0), paraxial.propagate(2.0, 2.0))
    with pytest.raises(ValueError, match="infinity"):
        paraxial.conjugate_object_distance_mm(system)


def test_chain_order_is_light_order():
    a, b = paraxial.propagate(1.0, 1.0), paraxial.refract(2.0, 1.0, 1.5)
    np.testing.assert_allclose(paraxial.chain(a, b), b @ a)
