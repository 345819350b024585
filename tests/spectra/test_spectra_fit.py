"""The filter fitter: parameters recovered from synthetic tables, the original device's coating
tables predicted at held-out angles, and malformed tables refused with one clear message."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from cm2optics.spectra.fit import (
    FilterModelKind,
    band_edges_nm,
    fit_filter_models,
    predict_edges_nm,
    read_filter_table,
)
from cm2optics.spectra.interference import InterferenceBandpass

TRUE = InterferenceBandpass(
    500.0, 550.0, 2.05, 1.80, 1.75, 1.95, edge_width_nm=1.5, peak_transmittance=0.97, blocking_od=4
)


def write_table(path: Path, model: InterferenceBandpass, angles=(0, 20, 40), polarised=True) -> Path:
    wavelength = np.arange(400.0, 650.0, 0.5)
    lines = ["wavelength_nm,aoi_deg," + ("Ts,Tp" if polarised else "T")]
    for aoi in angles:
        theta = math.radians(aoi)
        ts, tp = model.transmittance(wavelength, theta, "s"), model.transmittance(wavelength, theta, "p")
        for w, s, p in zip(wavelength, ts, tp, strict=True):
            lines.append(f"{w},{aoi}," + (f"{s:.6f},{p:.6f}" if polarised else f"{0.5 * (s + p):.6f}"))
    path.write_text("\n".join(lines) + "\n")
    return path


def test_band_edges_of_a_sampled_curve():
    wavelength = np.array([400.0, 410.0, 420.0, 430.0, 440.0])
    np.testing.assert_allclose(band_edges_nm(wavelength, np.array([0.0, 1.0, 1.0, 0.0, 0.0])), [405.0, 425.0])
    assert np.all(np.isnan(band_edges_nm(wavelength, np.zeros(5))))
    edges = band_edges_nm(wavelength, np.array([1.0, 1.0, 0.0, 0.0, 0.0]))  # runs off the short end
    assert np.isnan(edges[0]) and edges[1] == pytest.approx(415.0)


def test_polarised_table_gives_back_its_indices(tmp_path):
    table = read_filter_table(write_table(tmp_path / "t.csv", TRUE))
    assert table.polarised
    result = fit_filter_models(table)
    assert result.fit_aoi_deg == (0.0, 20.0) and result.held_out_aoi_deg == (40.0,)
    fit = result.best
    assert fit.kind is FilterModelKind.PER_EDGE_POLARISATION
    for name in ("n_eff_short_s", "n_eff_short_p", "n_eff_long_s", "n_eff_long_p"):
        assert getattr(fit.filter, name) == pytest.approx(getattr(TRUE, name), abs=0.01), name
    assert max(abs(e) for e in fit.held_out[0].error_nm) < 0.2
    np.testing.assert_allclose(result.to_dict(40.0)["edges_nm"], predict_edges_nm(TRUE, 40.0), atol=0.2)


def test_unpolarised_table_needs_the_refinements(tmp_path):
    table = read_filter_table(write_table(tmp_path / "t.csv", TRUE, polarised=False))
    assert not table.polarised
    result = fit_filter_models(table)
    errors = {f.kind: f.held_out_rms_nm for f in result.fits}
    assert errors[FilterModelKind.SINGLE] > 1.0  # the textbook law misses
    assert errors[FilterModelKind.PER_EDGE_POLARISATION] < 0.5 * errors[FilterModelKind.SINGLE]
    assert result.selected is FilterModelKind.PER_EDGE_POLARISATION
    best = result.best.filter  # s/p labels follow the convention: the s passband narrows
    assert best.n_eff_short_s > best.n_eff_short_p and best.n_eff_long_s < best.n_eff_long_p


def test_identical_s_and_p_columns_are_read_as_unpolarised(tmp_path):
    path = write_table(tmp_path / "t.csv", InterferenceBandpass.single_index(500, 550, 1.9), polarised=True)
    assert not read_filter_table(path).polarised
    assert "identical" in read_filter_table(path).note


def test_fit_angles_can_be_chosen_and_one_angle_is_refused(tmp_path):
    table = read_filter_table(write_table(tmp_path / "t.csv", TRUE, angles=(0, 10, 30)))
    assert fit_filter_models(table).fit_aoi_deg == (0.0, 10.0, 30.0)  # no 20°: fit on every angle
    assert fit_filter_models(table, (0, 30)).held_out_aoi_deg == (10.0,)
    with pytest.raises(ValueError, match="two different angles"):
        fit_filter_models(table, (0,))
    with pytest.raises(ValueError, match="not in the table"):
        fit_filter_models(table, (0, 45))


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ("wavelength_nm,T\n500,0.5\n", "aoi_deg"),
        ("wavelength_nm,aoi_deg,R\n500,0,0.5\n", "T"),
        ("wavelength_nm,aoi_deg,T\n500,0,nan\n", "NaN"),
        ("wavelength_nm,aoi_deg,T\n500,0,0.5\n490,0,0.5\n", "sort"),
        ("wavelength_nm,aoi_deg,T\n500,0,50\n", "percent"),
        ("wavelength_nm,aoi_deg,T\n500,0,-0.1\n", "negative"),
        ("wavelength_nm,aoi_deg,T\n500,95,0.5\n", "aoi_deg"),
        ("wavelength_nm,aoi_deg,T\n500,0,x\n", "not a number"),
        ("wavelength_nm,aoi_deg,T\n500,0,0.5\n510,0,0.5\n", "fewer than 10"),
    ],
)
def test_bad_tables_raise_one_clear_error(tmp_path, body, message):
    path = tmp_path / "bad.csv"
    path.write_text(body)
    with pytest.raises(ValueError, match=message):
        read_filter_table(path)


# ----------------------------------------------------------------------------- the original device


@pytest.fixture(scope="module", params=["coating_real_em.csv", "coating_real_ex.csv"])
def coating(request, reference_dir):
    return request.param, fit_filter_models(read_filter_table(reference_dir / request.param))


def test_held_out_40_degree_edges_within_3_nm(coating):
    name, result = coating
    assert result.fit_aoi_deg == (0.0, 20.0)
    best = result.best
    at_40 = next(h for h in best.held_out if h.aoi_deg == 40.0)
    assert max(abs(e) for e in at_40.error_nm) <= 3.0, (name, best.kind, at_40)


def test_fitted_effective_indices_are_physical(coating):
    _, result = coating
    for fit in result.fits:
        f = fit.filter
        for n in (f.n_eff_short_s, f.n_eff_short_p, f.n_eff_long_s, f.n_eff_long_p):
            assert 1.4 <= n <= 2.4, (fit.kind, n)


def test_each_refinement_lowers_the_held_out_error(coating):
    name, result = coating
    errors = [f.held_out_rms_nm for f in result.fits]
    assert errors[0] > errors[1] > errors[2], (name, errors)
    single = next(h for h in result.fits[0].held_out if h.aoi_deg == 40.0)
    assert max(abs(e) for e in single.error_nm) > 3.0  # one index for the whole filter is not enough
