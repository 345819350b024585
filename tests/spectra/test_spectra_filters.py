"""Filter physics against closed forms: the angle shift, s/p splitting, Beer–Lambert, Fresnel."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cm2optics.spectra.absorption import (
    AbsorptionFilm,
    beer_lambert_transmittance,
    fresnel_transmittance,
    refracted_angle_rad,
)
from cm2optics.spectra.fit import predict_edges_nm
from cm2optics.spectra.interference import InterferenceBandpass, Polarisation, angle_shifted_wavelength_nm
from cm2optics.spectra.library import wratten12_film
from cm2optics.spectra.spectrum import Spectrum


def test_angle_shift_is_zero_at_normal_incidence():
    assert angle_shifted_wavelength_nm(535.0, 0.0, 1.9) == 535.0


def test_angle_shift_closed_form_and_broadcasting():
    # n = 2 at 30°: sin θ / n = 1/4, so λ = λ₀ √(15/16)
    assert angle_shifted_wavelength_nm(500.0, math.radians(30), 2.0) == pytest.approx(500 * math.sqrt(15 / 16))
    grid = angle_shifted_wavelength_nm(np.array([500.0, 600.0]), np.radians([[0.0], [30.0]]), 2.0)
    assert grid.shape == (2, 2)
    np.testing.assert_allclose(grid[1], np.array([500.0, 600.0]) * math.sqrt(15 / 16))
    assert np.isnan(angle_shifted_wavelength_nm(np.nan, 0.3, 2.0))
    with pytest.raises(ValueError, match="n_eff"):
        angle_shifted_wavelength_nm(500.0, 0.3, 0.9)


def test_a_higher_index_shifts_less():
    theta = math.radians(40)
    assert angle_shifted_wavelength_nm(500, theta, 2.2) > angle_shifted_wavelength_nm(500, theta, 1.5)


def test_bandpass_edges_peak_and_blocking():
    band = InterferenceBandpass.single_index(
        510.0, 560.0, 1.9, edge_width_nm=2.0, peak_transmittance=0.95, blocking_od=5
    )
    t = band.transmittance(np.array([400.0, 510.0, 535.0, 560.0, 700.0]))
    np.testing.assert_allclose(t[[0, 4]], 1e-5, rtol=1e-3)
    np.testing.assert_allclose(t[[1, 3]], 0.95 / 2, rtol=1e-3)
    assert t[2] == pytest.approx(0.95, rel=1e-6)
    # 10–90 % rise over edge_width_nm
    short = band.transmittance(np.array([509.0, 511.0])) / 0.95
    np.testing.assert_allclose(short, [0.1, 0.9], atol=2e-3)


def test_s_and_p_split_only_off_normal():
    band = InterferenceBandpass(510.0, 560.0, 2.0, 1.8, 1.8, 2.0, edge_width_nm=1.0)
    wavelength = np.linspace(450, 600, 301)
    np.testing.assert_allclose(band.transmittance(wavelength, 0.0, "s"), band.transmittance(wavelength, 0.0, "p"))
    theta = math.radians(40)
    s_short, s_long = band.edges_nm(theta, Polarisation.S)
    p_short, p_long = band.edges_nm(theta, Polarisation.P)
    assert s_long - s_short < p_long - p_short  # the s passband narrows, p widens
    unpolarised = band.transmittance(wavelength, theta)
    mean = 0.5 * (band.transmittance(wavelength, theta, "s") + band.transmittance(wavelength, theta, "p"))
    np.testing.assert_allclose(unpolarised, mean)
    # between the s and p short edges only p passes: a shelf at half the peak
    shelf = band.transmittance(0.5 * (s_short + p_short), theta)
    assert shelf == pytest.approx(band.peak_transmittance / 2, rel=0.05)
    with pytest.raises(ValueError, match="unpolarised"):
        band.edges_nm(theta, Polarisation.UNPOLARISED)


def test_predicted_edges_follow_the_shift_law():
    band = InterferenceBandpass.single_index(
        500.0, 550.0, 1.9, edge_width_nm=1.0, peak_transmittance=1.0, blocking_od=8
    )
    edges = predict_edges_nm(band, 30.0)
    factor = math.sqrt(1 - (0.5 / 1.9) ** 2)
    np.testing.assert_allclose(edges, [500 * factor, 550 * factor], atol=0.02)


@pytest.mark.parametrize(
    ("field", "kwargs"),
    [
        ("long_edge_nm", {"short_edge_nm": 560.0, "long_edge_nm": 510.0}),
        ("n_eff_short_s", {"n_eff_short_s": 0.8}),
        ("peak_transmittance", {"peak_transmittance": 1.2}),
        ("edge_width_nm", {"edge_width_nm": 0.0}),
        ("blocking_od", {"blocking_od": -1.0}),
    ],
)
def test_bad_filter_parameters_name_the_field(field, kwargs):
    base = dict(
        short_edge_nm=510.0, long_edge_nm=560.0, n_eff_short_s=2, n_eff_short_p=2, n_eff_long_s=2, n_eff_long_p=2
    )
    with pytest.raises(ValueError, match=field):
        InterferenceBandpass(**{**base, **kwargs})


def test_beer_lambert_path_grows_as_one_over_cos_refracted():
    n, theta, absorbance = 1.53, math.radians(40), 0.7
    theta_t = math.asin(math.sin(theta) / n)
    assert refracted_angle_rad(theta, n) == pytest.approx(theta_t)
    assert beer_lambert_transmittance(absorbance, theta, n) == pytest.approx(10 ** (-absorbance / math.cos(theta_t)))
    assert beer_lambert_transmittance(absorbance, 0.0, n) == pytest.approx(10**-absorbance)
    out = beer_lambert_transmittance(np.array([[0.0], [1.0]]), np.array([0.0, theta]), n)
    assert out.shape == (2, 2) and np.all(out[0] == 1.0)


def test_fresnel_normal_incidence_and_grazing():
    assert fresnel_transmittance(0.0, 1.5) == pytest.approx(1 - 0.04)
    assert fresnel_transmittance(math.radians(89.99), 1.5) < 0.01
    assert fresnel_transmittance(0.3, 1.0) == pytest.approx(1.0)


def test_film_doubles_its_absorbance_with_thickness():
    alpha = Spectrum([400.0, 700.0], [3.0, 3.0], quantity="absorption_coefficient_per_mm")
    thin, thick = AbsorptionFilm(alpha, 0.1, 1.5), AbsorptionFilm(alpha, 0.2, 1.5)
    assert thick.internal_transmittance(500.0) == pytest.approx(thin.internal_transmittance(500.0) ** 2)
    assert thin.transmittance(500.0) == pytest.approx(0.96**2 * 10**-0.3)
    with pytest.raises(ValueError, match="thickness_mm"):
        AbsorptionFilm(alpha, 0.0, 1.5)


def test_wratten_film_meets_its_cut_on_and_barely_moves_with_angle():
    film = wratten12_film(515.0, 0.1)
    assert film.transmittance(515.0) == pytest.approx(0.5, abs=1e-6)
    assert film.transmittance(470.0) < 1e-4 and film.transmittance(600.0) > 0.9
    edges_0 = predict_edges_nm_of(film, 0.0)
    edges_40 = predict_edges_nm_of(film, 40.0)
    assert 0 < edges_40 - edges_0 < 3  # a longer path deepens the edge a little; no blue shift
    thick = wratten12_film(515.0, 0.2)
    assert thick.transmittance(480.0) < 0.1 * film.transmittance(480.0)  # deeper blocking, same cut-on
    assert thick.transmittance(515.0) == pytest.approx(0.5, abs=1e-6)
    with pytest.raises(ValueError, match="too thin"):
        wratten12_film(515.0, 0.001)


def predict_edges_nm_of(film: AbsorptionFilm, aoi_deg: float) -> float:
    wavelength = np.arange(450.0, 600.0, 0.01)
    t = film.transmittance(wavelength, math.radians(aoi_deg))
    return float(wavelength[np.argmax(t >= 0.5)])
