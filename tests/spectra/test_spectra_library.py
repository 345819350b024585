"""The shipped curves: present, provenanced, equal to their models, and close to the original
device's data where that is at hand (reference tables, never shipped)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cm2optics.spectra.fit import band_edges_nm
from cm2optics.spectra.library import (
    available_spectra,
    egfp_emission,
    et_bandpass,
    led_spectrum,
    library_spectra,
    load_spectrum,
    wratten12_film,
)

REPO = Path(__file__).resolve().parents[2]


def half_maximum_nm(wavelength: np.ndarray, values: np.ndarray) -> tuple[float, float]:
    low, high = band_edges_nm(wavelength, values / values.max())
    return float(low), float(high)


@pytest.mark.parametrize("name", available_spectra())
def test_every_shipped_curve_loads_with_provenance_and_equals_its_model(name):
    shipped = load_spectrum(name)
    assert shipped.source and not shipped.source.startswith("unspecified")
    assert shipped.domain_nm == (380.0, 780.0)
    assert np.all(shipped.values >= 0)
    model = library_spectra()[name]
    np.testing.assert_allclose(shipped.values, model.values, rtol=1e-5, atol=1e-12)


def test_top_level_spectra_folder_mirrors_the_package_data():
    package = sorted((REPO / "cm2optics" / "spectra" / "data").glob("*.csv"))
    top = sorted((REPO / "spectra").glob("*.csv"))
    assert [p.name for p in package] == [p.name for p in top] and len(package) == len(available_spectra())
    for a, b in zip(package, top, strict=True):
        assert a.read_text() == b.read_text(), a.name
    assert (REPO / "spectra" / "README.md").is_file()


def test_unknown_spectrum_name_lists_the_known_ones():
    with pytest.raises(ValueError, match="led-lxml-pb01-0040"):
        load_spectrum("nope")


def test_led_model_has_the_datasheet_peak_and_width():
    led = led_spectrum(470.0, 25.0)
    low, high = half_maximum_nm(led.wavelength_nm, led.values)
    assert led.peak_wavelength_nm == 470.0
    assert high - low == pytest.approx(25.0, abs=1.0)


def test_vendor_class_filters_have_their_nominal_edges():
    for centre, width in ((470.0, 40.0), (535.0, 50.0)):
        band = et_bandpass(centre, width)
        t = band.transmittance(np.array([centre - width / 2, centre, centre + width / 2]))
        np.testing.assert_allclose(t, [0.475, 0.95, 0.475], rtol=0.01)


def test_sensor_qe_peaks_in_the_blue_green_and_falls_in_the_red():
    qe = load_spectrum("imx178-qe")
    assert 0.7 < qe.values.max() < 0.85
    assert 430 <= qe.peak_wavelength_nm <= 520
    assert qe(700.0) < 0.6 * qe.values.max()


# ----------------------------------------------------------------------------- against the original device


def read_reference(reference_dir: Path, name: str) -> tuple[np.ndarray, np.ndarray]:
    data = np.genfromtxt(reference_dir / name, delimiter=",", names=True)
    return data[data.dtype.names[0]], data[data.dtype.names[1]]


def test_led_model_matches_the_devices_led(reference_dir):
    wavelength, power = read_reference(reference_dir, "led_spectrum.csv")
    model = led_spectrum(470.0, 25.0)
    assert abs(wavelength[np.argmax(power)] - model.peak_wavelength_nm) <= 6
    low, high = half_maximum_nm(wavelength, power)
    assert (high - low) == pytest.approx(25.0, abs=4)


def test_fluorophore_model_matches_the_devices_emission(reference_dir):
    wavelength, emission = read_reference(reference_dir, "gfp_emission.csv")
    model = egfp_emission()
    assert abs(wavelength[np.argmax(emission)] - model.peak_wavelength_nm) <= 5
    # the fraction of the fluorescence the 535/50 band passes: what the SBR depends on
    band = et_bandpass(535.0, 50.0)

    def passed(w, e):
        return np.trapezoid(e * band.transmittance(w), w) / np.trapezoid(e, w)

    assert passed(model.wavelength_nm, model.values) == pytest.approx(passed(wavelength, emission), rel=0.15)


def test_wratten_model_has_the_edge_shape_of_the_kodak_table(reference_dir):
    data = np.genfromtxt(reference_dir / "coating_kodak_em.csv", delimiter=",", names=True)
    normal = data["aoi_deg"] == 0
    wavelength, t = data["wavelength_nm"][normal], 0.5 * (data["Ts"][normal] + data["Tp"][normal])

    def crossing(w, values, level):
        return float(w[np.argmax(values >= level)])

    cut_on = crossing(wavelength, t, 0.5)
    film = wratten12_film(cut_on, 0.1)
    fine = np.arange(450.0, 700.0, 0.1)
    model = film.transmittance(fine)
    for level in (0.1, 0.8):
        assert crossing(fine, model, level) == pytest.approx(crossing(wavelength, t, level), abs=4), level
    assert model[-1] == pytest.approx(t[-1], abs=0.02)
