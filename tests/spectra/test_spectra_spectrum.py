"""The Spectrum type: closed forms, n-dimensional input, edges and NaN, CSV I/O and its errors."""

from __future__ import annotations

import colour
import numpy as np
import pytest

from cm2optics.spectra.interference import InterferenceBandpass
from cm2optics.spectra.spectrum import (
    DEFAULT_WAVELENGTH_NM,
    Normalisation,
    Spectrum,
    read_spectrum_csv,
    write_spectrum_csv,
)


def flat(value: float = 1.0, start: float = 380, end: float = 780, step: float = 0.1) -> Spectrum:
    wavelength = np.arange(start, end + step / 2, step)
    return Spectrum(wavelength, np.full(wavelength.size, value), quantity="relative_power", source="flat")


def test_flat_top_filter_times_flat_spectrum_integrates_to_its_width():
    band = InterferenceBandpass.single_index(
        500.0, 560.0, 2.0, edge_width_nm=0.5, peak_transmittance=1.0, blocking_od=10
    )
    product = band.spectrum(wavelength_nm=np.arange(380, 780.05, 0.05)) * flat()
    assert product.integrate() == pytest.approx(60.0, abs=0.01)


def test_evaluation_interpolates_linearly_and_keeps_shape():
    s = Spectrum([500.0, 510.0, 520.0], [0.0, 1.0, 0.5], quantity="transmittance")
    assert s(505.0) == pytest.approx(0.5)
    grid = np.array([[500.0, 515.0], [510.0, 520.0]])
    np.testing.assert_allclose(s(grid), [[0.0, 0.75], [1.0, 0.5]])
    assert s(grid).shape == (2, 2)


def test_nan_in_gives_nan_out_and_outside_range_raises():
    s = Spectrum([500.0, 510.0], [1.0, 2.0])
    out = s(np.array([505.0, np.nan]))
    assert out[0] == pytest.approx(1.5) and np.isnan(out[1])
    with pytest.raises(ValueError, match="outside"):
        s(520.0)


def test_product_lives_on_the_overlap_of_both_grids():
    a = Spectrum([400.0, 500.0, 600.0], [1.0, 1.0, 1.0])
    b = Spectrum([450.0, 550.0, 700.0], [2.0, 2.0, 2.0])
    product = a * b
    assert product.domain_nm == (450.0, 600.0)
    np.testing.assert_allclose(product.wavelength_nm, [450.0, 500.0, 550.0, 600.0])
    np.testing.assert_allclose(product.values, 2.0)
    with pytest.raises(ValueError, match="do not overlap"):
        a * Spectrum([700.0, 800.0], [1.0, 1.0])


def test_normalise_to_peak_and_area():
    s = Spectrum([500.0, 510.0, 520.0], [0.0, 4.0, 0.0])
    assert s.normalise(Normalisation.PEAK).values.max() == pytest.approx(1.0)
    assert s.normalise("area").integrate() == pytest.approx(1.0)
    with pytest.raises(ValueError, match="zero everywhere"):
        Spectrum([500.0, 510.0], [0.0, 0.0]).normalise()


def test_colour_round_trip_and_resample():
    sd = colour.SpectralDistribution({500: 0.1, 510: 0.3, 520: 0.2})
    s = Spectrum.from_sd(sd, quantity="transmittance", source="test")
    assert isinstance(s.sd, colour.SpectralDistribution)
    np.testing.assert_allclose(s.sd.values, sd.values)
    fine = s.resample(colour.SpectralShape(500, 520, 5))
    np.testing.assert_allclose(fine.values, [0.1, 0.2, 0.3, 0.25, 0.2])


def test_arrays_are_read_only_copies():
    values = np.array([1.0, 2.0])
    s = Spectrum([500.0, 510.0], values)
    values[0] = 99
    assert s.values[0] == 1.0
    with pytest.raises(ValueError):
        s.values[0] = 5


@pytest.mark.parametrize(
    ("wavelength", "values", "message"),
    [
        ([500.0, 490.0], [1.0, 1.0], "increase strictly"),
        ([500.0, 510.0], [1.0, -0.1], "≥ 0"),
        ([500.0, 510.0], [1.0, np.nan], "finite"),
        ([-5.0, 510.0], [1.0, 1.0], "> 0"),
        ([500.0], [1.0], "≥ 2 samples"),
        ([500.0, 510.0], [1.0], "must match"),
    ],
)
def test_bad_arrays_raise_clear_errors(wavelength, values, message):
    with pytest.raises(ValueError, match=message):
        Spectrum(wavelength, values)


def test_csv_round_trip_keeps_provenance(tmp_path):
    s = Spectrum(DEFAULT_WAVELENGTH_NM, np.linspace(0, 1, DEFAULT_WAVELENGTH_NM.size), "transmittance", "a model, v1")
    path = write_spectrum_csv(s, tmp_path / "t.csv")
    text = path.read_text()
    assert text.startswith("# source: a model, v1\nwavelength_nm,transmittance\n")
    back = read_spectrum_csv(path)
    assert back.source == "a model, v1" and back.quantity == "transmittance"
    np.testing.assert_allclose(back.values, s.values, rtol=1e-5)
    assert not list(tmp_path.glob(".*tmp*"))  # atomic write leaves no temporary file


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ("wavelength_nm,T\n510,0.5\n500,0.4\n", "increase strictly"),
        ("wavelength_nm,T\n500,0.5\n510,-0.2\n", "negative"),
        ("wavelength_nm,T\n500,0.5\n510,nan\n", "NaN"),
        ("wl,T\n500,0.5\n510,0.4\n", "header"),
        ("wavelength_nm,T,R\n500,0.5,0.5\n510,0.4,0.6\n", "header"),
        ("wavelength_nm,T\n500,0.5\n510,abc\n", "not a number"),
        ("wavelength_nm,T\n500,0.5\n", "at least 2"),
        ("wavelength_nm,T\n0,0.5\n510,0.4\n", "> 0"),
    ],
)
def test_bad_csv_files_raise_one_clear_error(tmp_path, body, message):
    path = tmp_path / "bad.csv"
    path.write_text("# source: test\n" + body)
    with pytest.raises(ValueError, match=message) as error:
        read_spectrum_csv(path)
    assert "bad.csv" in str(error.value)


def test_missing_file_and_missing_provenance(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_spectrum_csv(tmp_path / "none.csv")
    path = tmp_path / "plain.csv"
    path.write_text("wavelength_nm,relative_power\n500,1\n510,2\n")
    assert read_spectrum_csv(path).source == "unspecified (plain.csv)"
