"""Designs with no real image, an MLA larger than the sensor or filters that miss the fluorophore
are rejected (issue 12): by SystemDesign where its own numbers suffice, by check_design where the
best-focus trace or the fluorophore is needed; `cm2 design validate` exits 2 naming the field."""

from __future__ import annotations

import pytest
import yaml
from typer.testing import CliRunner

from cm2optics.cli import app
from cm2optics.design import DesignError, available_presets, load_preset, paraxial
from cm2optics.optics import first_order
from cm2optics.optics.checks import check_design, require_plausible
from cm2optics.spectra.library import egfp_emission_band_nm

runner = CliRunner()


def _validate(tmp_path, v2, changes: dict) -> str:
    data = v2.to_dict()
    for path, value in changes.items():
        node = data
        *parents, leaf = path.split(".")
        for part in parents:
            node = node[part]
        node[leaf] = value
    path = tmp_path / "design.yaml"
    path.write_text(yaml.safe_dump(data))
    result = runner.invoke(app, ["design", "validate", str(path)])
    assert result.exit_code == 2, result.output
    lines = [line for line in result.stderr.strip().splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and "Traceback" not in result.output
    return lines[0]


@pytest.mark.parametrize("name", available_presets())
def test_presets_are_plausible(name):
    design = load_preset(name)
    assert check_design(design, egfp_emission_band_nm()) == []
    assert require_plausible(design) is design


@pytest.mark.parametrize(
    ("changes", "field"),
    [
        ({"mla.pitch_mm": 2.0}, "mla.pitch_mm"),  # 6 mm array on a 4.98-mm-tall sensor
        ({"absorption_filter.cut_on_nm": 600.0}, "absorption_filter.cut_on_nm"),  # above 510–560 nm
        ({"emission_filter.center_nm": 470.0}, "emission_filter.center_nm"),  # on the excitation band
        ({"imaging.mla_to_sensor_mm": 0.5, "imaging.film_to_sensor_mm": 0.2}, "imaging.mla_to_sensor_mm"),  # no image
    ],
)
def test_system_design_rejects(v2, tmp_path, changes, field):
    with pytest.raises(DesignError) as error:
        v2.with_changes(changes)
    assert error.value.field == field
    assert isinstance(error.value, ValueError)
    assert field in _validate(tmp_path, v2, changes)


def test_emission_filter_outside_the_fluorophore_band(v2, tmp_path):
    design = v2.with_changes({"emission_filter.center_nm": 900.0})  # each part is fine on its own
    problems = check_design(design, egfp_emission_band_nm())
    assert [p.field for p in problems] == ["emission_filter.center_nm"]
    assert check_design(design) == []  # without a fluorophore there is nothing to compare with
    line = _validate(tmp_path, v2, {"emission_filter.center_nm": 900.0})
    assert "emission_filter.center_nm" in line and "fluorophore" in line


def test_no_real_image_in_front_of_the_filter(v2, tmp_path):
    # The filter 8 mm over the mask leaves the paraxial conjugate 0.4 mm beyond its front face and
    # the plane of best focus inside it: no sample can be put in focus.
    design = v2.with_changes({"imaging.filter_gap_mm": 8.0})
    assert paraxial.has_real_image(design)
    assert first_order.working_distance_mm(design) > 0
    (problem,) = check_design(design)
    assert problem.field == "imaging.filter_gap_mm" and "no real image" in str(problem)
    with pytest.raises(DesignError, match="imaging.filter_gap_mm"):
        require_plausible(design)
    assert "imaging.filter_gap_mm" in _validate(tmp_path, v2, {"imaging.filter_gap_mm": 8.0})


def test_spectra_report_warns_on_an_implausible_design(v2, tmp_path):
    path = tmp_path / "design.yaml"
    v2.with_changes({"emission_filter.center_nm": 900.0}).save(path)
    result = runner.invoke(app, ["spectra", "report", "--preset", str(path), "--out", str(tmp_path / "out"), "--json"])
    assert result.exit_code == 0, result.output
    assert "warning: the SBR is implausible" in result.stderr and "emission_filter.center_nm" in result.stderr
