"""`cm2 spectra report` and `cm2 spectra fit-filter`: JSON output, plots, one-line errors."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from cm2optics.cli.spectra import spectra_app
from cm2optics.reports.spectra import FIGURES
from cm2optics.spectra.fit import band_edges_nm, predict_edges_nm
from cm2optics.spectra.interference import InterferenceBandpass

app = typer.Typer()
app.add_typer(spectra_app, name="spectra")
runner = CliRunner()


@app.callback()
def _root() -> None:
    """Test root: a group, so that `spectra` is a subcommand as under `cm2`."""


def test_report_json_and_plots(tmp_path):
    result = runner.invoke(app, ["spectra", "report", "--preset", "cm2-v2", "--out", str(tmp_path), "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    for key in ("sbr_interference_only", "sbr_hybrid", "sbr_gain"):
        assert isinstance(data[key], float) and data[key] > 0
    assert data["sbr_gain"] >= 5
    assert data["sbr_gain"] == pytest.approx(data["sbr_hybrid"] / data["sbr_interference_only"], rel=1e-2)
    gains = {row["case"]: row["sbr_gain"] for row in data["sensitivity"]}
    assert gains["film twice as thick"] > gains["as designed"] > gains["film half as thick"]
    assert gains["cut-on 10 nm redder"] > gains["as designed"] > gains["cut-on 10 nm bluer"]
    assert data["emission_filter_edges_nm_vs_aoi_deg"]["0"] == pytest.approx([510.0, 560.0], abs=0.2)
    for name in FIGURES:
        assert (tmp_path / name).stat().st_size > 10_000
    assert not [p for p in tmp_path.iterdir() if ".tmp" in p.name]


def test_report_human_output_and_bad_preset(tmp_path):
    result = runner.invoke(app, ["spectra", "report", "--preset", "nope.yaml", "--out", str(tmp_path)])
    assert result.exit_code == 2
    assert "error" in result.output and "Traceback" not in result.output


def synthetic_table(path, model: InterferenceBandpass) -> None:
    wavelength = np.arange(420.0, 620.0, 1.0)
    rows = ["# a vendor's table", "wavelength_nm,aoi_deg,T"]
    for aoi in (0, 20, 40):
        t = model.transmittance(wavelength, math.radians(aoi))
        rows += [f"{w},{aoi},{v:.5f}" for w, v in zip(wavelength, t, strict=True)]
    path.write_text("\n".join(rows) + "\n")


def test_fit_filter_json_with_prediction(tmp_path):
    model = InterferenceBandpass(500.0, 550.0, 2.0, 1.8, 1.75, 1.95, edge_width_nm=2.0)
    path = tmp_path / "curves.csv"
    synthetic_table(path, model)
    result = runner.invoke(app, ["spectra", "fit-filter", str(path), "--predict-aoi", "30", "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert [m["model"] for m in data["models"]] == ["single-n_eff", "n_eff-per-edge", "n_eff-per-edge-and-polarisation"]
    assert data["fit_aoi_deg"] == [0.0, 20.0] and data["held_out_aoi_deg"] == [40.0]
    assert set(data["parameters"]) >= {"short_edge_nm", "long_edge_nm", "n_eff_short_s", "n_eff_long_p"}
    np.testing.assert_allclose(data["edges_nm"], predict_edges_nm(model, 30.0), atol=0.3)


def test_fit_filter_angles_option_and_human_output(tmp_path):
    path = tmp_path / "curves.csv"
    synthetic_table(path, InterferenceBandpass.single_index(500.0, 550.0, 1.9))
    result = runner.invoke(app, ["spectra", "fit-filter", str(path), "--fit-aoi", "0,40"])
    assert result.exit_code == 0, result.output
    assert "selected" in result.output and "single" in result.output
    bad = runner.invoke(app, ["spectra", "fit-filter", str(path), "--fit-aoi", "zero"])
    assert bad.exit_code == 2 and "--fit-aoi" in bad.output


@pytest.mark.parametrize(
    "body",
    [
        "wavelength_nm,aoi_deg,T\n500,0,0.5\n490,0,0.5\n",
        "wavelength,T\n500,0.5\n",
        "wavelength_nm,aoi_deg,T\n500,0,nan\n",
    ],
)
def test_fit_filter_bad_csv_is_one_line_and_exit_2(tmp_path, body):
    path = tmp_path / "bad.csv"
    path.write_text(body)
    result = runner.invoke(app, ["spectra", "fit-filter", str(path), "--json"])
    assert result.exit_code == 2
    assert "Traceback" not in result.output and result.output.count("error:") == 1


def test_fit_filter_predicts_the_original_emission_filter_at_40_degrees(reference_dir):
    path = reference_dir / "coating_real_em.csv"
    result = runner.invoke(app, ["spectra", "fit-filter", str(path), "--predict-aoi", "40", "--json"])
    assert result.exit_code == 0, result.output
    data = np.genfromtxt(path, delimiter=",", names=True)
    at_40 = data["aoi_deg"] == 40
    measured = band_edges_nm(data["wavelength_nm"][at_40], 0.5 * (data["Ts"][at_40] + data["Tp"][at_40]))
    np.testing.assert_allclose(json.loads(result.stdout)["edges_nm"], measured, atol=3.0)
