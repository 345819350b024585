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
