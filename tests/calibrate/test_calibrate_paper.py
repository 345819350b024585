"""`cm2 calibrate paper`: the paper's excitation power against the traced design, through a chain
of physical factors."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from cm2optics.calibrate.paper import PAPER, PRESET_V, _photometric_factor, _window_transmittance
from cm2optics.cli import app


def test_the_photometric_factor_weights_v_by_the_led_spectrum(v2):
    """V rises steeply through 470 nm (0.060 at 460, 0.139 at 480), so the spectrum-weighted V of
    a 25-nm-wide LED lies above V(470) = 0.091 and the same 40 lm are fewer milliwatts."""
    factor = _photometric_factor(v2)
    v_eff = PRESET_V / factor.value
    assert 0.091 < v_eff < 0.139 and factor.computed


def test_the_meter_window_passes_the_fresnel_share():
    """Normal incidence: 1 − ((n − 1)/(n + 1))² = 0.96 for n = 1.5; grazing: nothing."""
    t = _window_transmittance(np.array([1.0, np.cos(np.radians(45.0)), 1e-9]))
    assert t[0] == pytest.approx(0.96, abs=1e-12)
    assert 0.94 < t[1] < t[0] and t[2] < 1e-6


@pytest.mark.slow
def test_the_chain_multiplies_out_and_names_what_remains(tmp_path):
    result = CliRunner().invoke(app, ["calibrate", "paper", "--rays", "40000", "--out", str(tmp_path / "p"), "--json"])
    assert result.exit_code == 0, result.output
    power = json.loads(result.stdout)["excitation_power"]
    assert power["measured_mw"] == PAPER["measured_power_mw"]["value"]
    product = np.prod([f["value"] for f in power["factors"]])
    assert power["explained_mw"] == pytest.approx(power["predicted_mw"] * product, rel=1e-3)
    assert power["remaining_ratio"] == pytest.approx(
        power["measured_mw"] / power["explained_mw"], abs=1e-3
    )  # 3 decimals
    assert 500 < power["predicted_mw"] < 900  # ≈ 680 mW at 4 × 640 mW
    assert (tmp_path / "p" / "excitation_power.png").is_file() and (tmp_path / "p" / "report.html").is_file()
    document = json.loads(result.stdout)
    sbr = document["sbr_gain"]
    assert sbr["gain_by_terms"]["leakage"] > 100  # the film's rejection of the leakage alone
    assert 1 <= sbr["gain"] <= sbr["gain_by_terms"]["leakage+beads"] <= sbr["gain_by_terms"]["leakage"]
    assert 0 < sbr["bead_peak_fraction"] < 1 / 9  # nine foci share the bead's light
    assert 0.55 < document["magnification"]["traced_magnification"] < 0.6
    edge = document["edge_drop"]
    at_edge = edge["radii_mm"].index(edge["paper_edge_radius_mm"])
    assert edge["relative_energy_fitted"][at_edge] == pytest.approx(1 - edge["paper_drop"], abs=0.01)
    assert (tmp_path / "p" / "sbr_phantom.png").is_file() and (tmp_path / "p" / "edge_drop.png").is_file()


# (b) the hybrid filter's SBR gain on the bead phantom: the per-pixel terms and the gain's algebra,
# on made-up traced numbers (no trace: the formulas alone).


def _traced(leakage: float = 1e-7, peak: float = 0.005) -> dict:
    """Traced numbers of a made-up design: film passing 60 % in band, rejecting leakage 1000×."""
    return {
        "field_mm": 8.0,
        "pixels": 1_000_000,
        "signal_per_absorbed": {"interference_only": 1e-3, "hybrid": 6e-4},
        "yield_times_overlap": 0.6,
        "leakage_per_reflectance": {"interference_only": leakage, "hybrid": leakage / 1000},
        "leakage_specular": {"interference_only": 0.0, "hybrid": 0.0},
        "bead": {"peak": peak, "wings": {0.05: 0.3, 0.1: 0.4, 0.2: 0.5}},
    }


def test_leakage_alone_gains_the_films_rejection_times_its_transmission():
    from cm2optics.calibrate.paper_sbr import sbr_summary

    summary = sbr_summary(_traced())
    assert summary["gain_by_terms"]["leakage"] == pytest.approx(0.6 * 1000, rel=1e-3)
    assert summary["film_leakage_rejection"] == pytest.approx(1000, rel=1e-3)


def test_in_band_light_passes_both_chains_alike_so_it_caps_the_gain():
    """Without (almost any) leakage the hybrid film cuts signal and in-band background alike: gain 1."""
    from cm2optics.calibrate.paper_sbr import sbr_summary

    summary = sbr_summary(_traced(leakage=1e-20))
    assert summary["gain"] == pytest.approx(1.0, abs=1e-2)
    assert summary["sbr"]["hybrid"]["all"] == pytest.approx(summary["sbr"]["interference_only"]["all"], rel=1e-2)


def test_the_terms_follow_the_phantoms_numbers():
    """A bead's peak: collected × cross-section × absorption / field area × peak share; the beads'
    level: density × phantom area × per-bead × wing share / pixels."""
    from cm2optics.calibrate.paper_sbr import sbr_terms

    terms = sbr_terms(
        _traced(), bead_absorption=0.5, resin_autofluorescence_per_mm=1e-3, diffuse_reflectance=0.05, wing_level=0.1
    )["interference_only"]
    per_bead = 1e-3 * np.pi * 0.005**2 * 0.5 / (np.pi * 16)
    assert terms["signal"] == pytest.approx(per_bead * 0.005, rel=1e-9)
    beads = PAPER["bead_density_per_mm2"]["value"] * np.pi * (PAPER["phantom_diameter_mm"]["value"] / 2) ** 2
    assert terms["beads"] == pytest.approx(beads * per_bead * 0.4 / 1e6, rel=1e-9)
    assert terms["leakage"] == pytest.approx(1e-7 * 0.05 / 1e6, rel=1e-9)
    resin = 1e-3 * PAPER["phantom_thickness_mm"]["value"] * (PAPER["phantom_diameter_mm"]["value"] / 8) ** 2
    assert terms["autofluorescence"] == pytest.approx(1e-3 / 0.6 * resin / 1e6, rel=1e-9)


def test_the_leakage_it_asks_for_gives_the_measured_gain():
    """Scale the leakage by the factor the summary reports: the nominal gain becomes the paper's."""
    from cm2optics.calibrate.paper_sbr import ASSUMPTIONS, _gain, sbr_summary, sbr_terms

    traced = _traced()
    summary = sbr_summary(traced)
    factor = summary["leakage_factor_for_measured_gain"]
    assert factor > 1  # the made-up design falls short of 5×
    scaled = _traced(leakage=1e-7 * factor)
    nominal = {k: a["value"] for k, a in ASSUMPTIONS.items()}
    gain = _gain(sbr_terms(scaled, **nominal), ("leakage", "beads", "autofluorescence"))
    assert gain == pytest.approx(PAPER["sbr_gain"]["value"], rel=1e-2)
    low, high = summary["gain_range"]
    assert low <= summary["gain"] <= high


# (c) de-magnification and the edge drop (coarse pixels: the energies and centroids are integrals)


def test_the_source_profile_effect_multiplies_the_edge_energy_by_its_gaussian(v2):
    """The central focus of a source 3.5 mm off axis seen at θ ≈ atan(3.5 / working distance):
    a Gaussian source of 1/e² half-angle θe keeps ≈ exp(−2 θ²/θe²) of the isotropic energy."""
    from cm2optics.calibrate.paper_field import _model, edge_energy, traced_magnification
    from cm2optics.optics import first_order

    isotropic = edge_energy(_model(v2, None, 8), (3.5,))[0]
    gaussian = edge_energy(_model(v2, 23.0, 8), (3.5,))[0]
    theta = np.arctan(3.5 / first_order.working_distance_mm(v2))
    assert gaussian / isotropic == pytest.approx(np.exp(-2 * theta**2 / np.radians(23.0) ** 2), rel=0.1)
    assert 0.5 < isotropic < 0.95  # the optics alone lose a fraction, not all
    slope, local = traced_magnification(_model(v2, None, 8), (0.0, 1.0, 3.0))
    assert slope == pytest.approx((1 * local[0] + 9 * local[1]) / 10, rel=1e-9)  # least squares through 0
    assert slope == pytest.approx(first_order.magnification(v2), rel=0.05)


@pytest.mark.slow
def test_the_solved_half_angle_and_spacing_reproduce_the_paper(v2):
    from cm2optics.calibrate.paper_field import _model, edge_energy, field_residuals, traced_magnification

    result = field_residuals(v2, binning=8)
    edge, mag = result["edge_drop"], result["magnification"]
    kept = edge_energy(_model(v2, edge["source_profile_half_angle_deg"], 8), (edge["paper_edge_radius_mm"],))[0]
    assert kept == pytest.approx(1 - PAPER["edge_drop"]["value"], abs=0.01)
    low, high = edge["source_profile_half_angle_range_deg"]
    assert low < edge["source_profile_half_angle_deg"] < high
    moved = v2.with_changes({"imaging.mla_to_sensor_mm": mag["mla_to_sensor_for_paper_mm"]})
    m, _ = traced_magnification(_model(moved, None, 8), (0.0, 1.0, 2.0, 3.0, 4.0))
    assert m == pytest.approx(mag["paper_magnification"], rel=3e-3)
