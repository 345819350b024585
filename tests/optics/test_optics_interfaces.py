"""The optics core's interface physics against closed forms, on NumPy and on Dr.Jit."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cm2optics.optics.arrays import numpy_ops
from cm2optics.optics.interfaces import (
    brewster_angle_rad,
    critical_angle_rad,
    fresnel_amplitudes,
    fresnel_reflectance,
    fresnel_transmittance,
    reflect,
    refract,
    snell_cos_t,
)

ANGLES = np.linspace(0.0, 1.5, 31)


def _drjit():
    from cm2optics.optics.arrays import drjit_ops
    from cm2optics.optics.backend import is_jit

    if not is_jit():
        pytest.skip("no JIT variant of Mitsuba (LLVM ≥ 17 or CUDA) here")
    ops = drjit_ops()
    return ops, lambda values: ops.Float64(np.asarray(values, dtype=float)), lambda value: np.asarray(value, float)


def _numpy():
    return numpy_ops(), lambda values: np.asarray(values, dtype=float), lambda value: np.asarray(value, float)


@pytest.fixture(params=["numpy", "drjit"])
def backend(request):
    return _numpy() if request.param == "numpy" else _drjit()


def _interface(backend, theta, n1, n2):
    ops, array, back = backend
    cos_i = array(np.cos(theta))
    cos_t, tir = snell_cos_t(ops, cos_i, n1 / n2)
    return ops, array, back, cos_i, cos_t, tir


def test_normal_incidence_reflects_four_percent_at_n_1_5(backend):
    _, _, back, cos_i, cos_t, tir = _interface(backend, [0.0], 1.0, 1.5)
    assert back(fresnel_reflectance(cos_i, cos_t, 1.0, 1.5))[0] == pytest.approx(0.04, abs=1e-12)
    assert not back(tir)[0]


def test_p_reflectance_vanishes_at_brewster(backend):
    theta = brewster_angle_rad(1.0, 1.5)
    assert math.tan(theta) == pytest.approx(1.5)
    _, _, back, cos_i, cos_t, _ = _interface(backend, [theta], 1.0, 1.5)
    r_s, r_p = fresnel_amplitudes(cos_i, cos_t, 1.0, 1.5)
    assert back(r_p)[0] == pytest.approx(0.0, abs=1e-12)
    assert abs(back(r_s)[0]) > 0.1


def test_total_internal_reflection_beyond_the_critical_angle(backend):
    critical = critical_angle_rad(1.5, 1.0)
    assert math.sin(critical) == pytest.approx(1.0 / 1.5)
    theta = np.array([critical - 0.01, critical + 0.01, 1.4])
    _, _, back, _, cos_t, tir = _interface(backend, theta, 1.5, 1.0)
    assert back(tir).tolist() == [False, True, True]
    assert back(cos_t)[1:] == pytest.approx([0.0, 0.0])
    with pytest.raises(ValueError, match="n2"):
        critical_angle_rad(1.0, 1.5)


@pytest.mark.parametrize(("n1", "n2"), [(1.0, 1.5), (1.5, 1.0), (1.0, 1.33)])
def test_energy_is_conserved(backend, n1, n2):
    theta = ANGLES[np.sin(ANGLES) * n1 / n2 < 1.0]
    _, _, back, cos_i, cos_t, _ = _interface(backend, theta, n1, n2)
    r = back(fresnel_reflectance(cos_i, cos_t, n1, n2))
    t = back(fresnel_transmittance(cos_i, cos_t, n1, n2))
    assert np.all((r >= 0) & (r <= 1))
    np.testing.assert_allclose(r + t, 1.0, atol=1e-12)
    # Transmitted power by the s and p amplitude transmittances: T = (n2 cos θt / n1 cos θi)·|t|².
    c_i, c_t = np.cos(theta), back(cos_t)
    t_s = 2 * n1 * c_i / (n1 * c_i + n2 * c_t)
    t_p = 2 * n1 * c_i / (n2 * c_i + n1 * c_t)
    np.testing.assert_allclose(t, 0.5 * (t_s**2 + t_p**2) * n2 * c_t / (n1 * c_i), atol=1e-12)


def test_refraction_keeps_the_snell_invariant_and_unit_length():
    rng = np.random.default_rng(3)
    normal = np.array([[0.0, 0.0, 1.0]])
    d = rng.normal(size=(200, 3))
    d[:, 2] = -np.abs(d[:, 2]) - 0.2
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    cos_i = -(d @ normal.T)
    for n1, n2 in ((1.0, 1.5), (1.5, 1.0)):
        cos_t, tir = snell_cos_t(numpy_ops(), cos_i, n1 / n2)
        t = refract(d, normal, n1 / n2, cos_i, cos_t)
        ok = ~tir[:, 0]
        np.testing.assert_allclose(np.linalg.norm(t[ok], axis=1), 1.0, atol=1e-12)
        sin_i = np.linalg.norm(d[ok, :2], axis=1)
        sin_t = np.linalg.norm(t[ok, :2], axis=1)
        np.testing.assert_allclose(n1 * sin_i, n2 * sin_t, atol=1e-12)
        # The plane of incidence holds: tangential components stay parallel.
        np.testing.assert_allclose(d[ok, 0] * t[ok, 1] - d[ok, 1] * t[ok, 0], 0.0, atol=1e-12)
    mirrored = reflect(d, normal, cos_i)
    np.testing.assert_allclose(mirrored[:, :2], d[:, :2])
    np.testing.assert_allclose(mirrored[:, 2], -d[:, 2])


def test_refraction_matches_between_backends():
    ops, array, back = _drjit()
    theta = ANGLES
    d = (np.sin(theta), np.zeros_like(theta), -np.cos(theta))
    cos_np, tir_np = snell_cos_t(numpy_ops(), np.cos(theta), 1.0 / 1.5)
    cos_dr, tir_dr = snell_cos_t(ops, array(np.cos(theta)), 1.0 / 1.5)
    np.testing.assert_allclose(back(cos_dr), cos_np, atol=1e-14)
    assert back(tir_dr).tolist() == tir_np.tolist()
    for component, normal in zip(d, (0.0, 0.0, 1.0), strict=True):
        got = refract(array(component), normal, 1.0 / 1.5, array(np.cos(theta)), cos_dr)
        np.testing.assert_allclose(back(got), refract(component, normal, 1.0 / 1.5, np.cos(theta), cos_np), atol=1e-14)
